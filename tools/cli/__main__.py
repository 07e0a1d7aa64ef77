"""``python -m trundle.tools.cli``: the `trundle` command."""

from trundle.tools.cli.main import entry

entry()
