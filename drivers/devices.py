"""Device families and the driver for a URL: the one place that maps ``lrf``/``can``/``camera`` to
the module whose ``driver_from_url(url, sink, config)`` builds the driver (as python-can's
``interface`` setting picks a bus class)."""

from __future__ import annotations

import importlib
from typing import Any

from trundle.drivers.lifecycle import Driver
from trundle.logs.errors import UserError

# device family -> module providing driver_from_url(url, sink, config) -> Driver
FAMILIES = {"lrf": "trundle.drivers.lrf", "can": "trundle.drivers.wheels", "camera": "trundle.drivers.camera"}


def make_driver(family: str, url: str, sink: Any, config: dict[str, Any]) -> Driver:
    """A driver of ``family`` for ``url``; a family whose support is missing is a user error."""
    if family not in FAMILIES:
        raise UserError(f"unknown device family {family!r} (known: {', '.join(FAMILIES)})")
    try:
        module = importlib.import_module(FAMILIES[family])
    except ModuleNotFoundError as error:
        raise UserError(f"{family} devices are not supported by this installation ({error.name})") from None
    return module.driver_from_url(url, sink, config)
