"""trundle: onboard software of a wheeled mobile robot.

The repository root is the package ``trundle``; its subpackages are the top-level folders
(``trundle.drivers``, ``trundle.perception``, ``trundle.fusion``, ``trundle.logs``,
``trundle.tools``), mapped by ``package-dir`` in pyproject.toml. This file is the one source of
the version.
"""

__version__ = "0.1.0"
