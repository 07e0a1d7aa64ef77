"""Laser range finder drivers by URL, for ``trundle record --lrf URL`` and robot configs.

- ``scip2:///dev/ttyACM0`` Hokuyo SCIP 2.0 on a USB/serial port (also ``scip2:/dev/...``)
- ``scip2+tcp://192.168.0.10:10940`` Hokuyo SCIP 2.0 over Ethernet (UST, UTM-EW)
- ``rplidar:///dev/ttyUSB0?model=s2&mode=DenseBoost`` Slamtec RPLIDAR (model a1, a2, a2m12, a3, c1, s1,
  s2, s3 sets the first baud rate tried; mode defaults to the device's typical scan mode)

Query parameters and the ``config`` table (the ``[lrf]`` section of a robot TOML) set driver
options; see ``ScipConfig`` and ``RplidarConfig`` for the keys (and ``name``, the driver's name
in diagnostics, default ``lrf``). Use a stable path such as
``/dev/serial/by-id/...`` so reconnects find the device again after an unplug.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar
from urllib.parse import parse_qsl, urlsplit

from trundle.drivers.lifecycle import Driver, Sink
from trundle.drivers.rplidar_driver import RplidarConfig, RplidarDriver
from trundle.drivers.scip2_driver import ScipConfig, ScipDriver
from trundle.logs.errors import ConfigError, UserError
from trundle.logs.schema import Schema, parse_text

SCHEMES = ("scip2", "scip2+tcp", "rplidar")
Config = TypeVar("Config", bound=Schema)


def laser_config(model: type[Config], port: str, options: Mapping[str, Any], query: Mapping[str, str]) -> Config:
    """The driver config ``model`` for ``port`` from a table of options (``url``, ``name`` and
    ``enabled`` are not the driver's) under the URL's query parameters; a ConfigError names the key."""
    if "port" in options or "port" in query:
        raise ConfigError("lrf.port: the port is the URL's path (scip2:///dev/ttyACM0) or host (scip2+tcp://host)")
    table = {k: v for k, v in options.items() if k not in ("url", "name", "enabled")}
    return parse_text(model, {**table, "port": port}, {k: v for k, v in query.items() if k != "name"}, "lrf")


def driver_from_url(url: str, sink: Sink, config: Mapping[str, Any] | None = None) -> Driver:
    """A laser driver for ``url`` sending messages to ``sink``; a bad URL or option is a UserError."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise UserError(f"unknown laser URL {url!r}: use scip2:///dev/ttyACM0, scip2+tcp://host:10940 "
                        "or rplidar:///dev/ttyUSB0?model=a2")
    options, query = dict(config or {}), dict(parse_qsl(parts.query))
    name = query.get("name", options.get("name", "lrf"))
    if not isinstance(name, str) or not name:
        raise ConfigError(f"lrf.name = {name!r}: expected a non-empty string")
    if scheme == "scip2+tcp":
        if not parts.hostname:
            raise UserError(f"laser URL {url!r} needs a host: scip2+tcp://192.168.0.10:10940")
        try:
            port_number = parts.port or 10940
        except ValueError:
            raise UserError(f"laser URL {url!r} has a bad port number") from None
        port = f"socket://{parts.hostname}:{port_number}"
    else:
        port = f"/{parts.netloc}{parts.path}" if parts.netloc else parts.path
        if not port:
            raise UserError(f"laser URL {url!r} needs a device path, e.g. {scheme}:///dev/ttyUSB0")
    if scheme == "rplidar":
        return RplidarDriver(laser_config(RplidarConfig, port, options, query), sink, name=name)
    return ScipDriver(laser_config(ScipConfig, port, options, query), sink, name=name)
