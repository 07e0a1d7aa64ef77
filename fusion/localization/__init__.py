"""Localization in a known map: grid (laser) and landmarks."""
