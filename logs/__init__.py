"""The data model: message types, ROS 2 encoding, MCAP writer/reader/replay, importers."""
