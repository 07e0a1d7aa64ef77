"""The `trundle` command: the entry point (``main``) and one thin module per command."""
