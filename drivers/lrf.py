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

import dataclasses
from typing import Any, Mapping, TypeVar
from urllib.parse import parse_qsl, urlsplit

from trundle.drivers.lifecycle import Driver, Sink
from trundle.drivers.rplidar_driver import RplidarConfig, RplidarDriver
from trundle.drivers.scip2_driver import ScipConfig, ScipDriver
from trundle.logs.errors import UserError

SCHEMES = ("scip2", "scip2+tcp", "rplidar")
Config = TypeVar("Config")


def _value(text: str) -> Any:
    """A query value as bool, int or float when it reads as one."""
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def make_config(cls: type[Config], port: str, options: Mapping[str, Any], device: str) -> Config:
    """A driver config dataclass from a table of options (``url`` ignored); UserError on a bad one."""
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name != "port"}
    unknown = sorted(set(options) - set(fields) - {"url", "port", "name"})
    if unknown:
        raise UserError(f"lrf: unknown option(s) {', '.join(unknown)} for {device}; known: {', '.join(sorted(fields))}")
    values = {}
    for key, value in options.items():
        if key not in fields:
            continue
        default = fields[key].default
        kind = type(default) if default is not None else float
        if kind is bool and not isinstance(value, bool):
            raise UserError(f"lrf: {key} must be true or false, got {value!r}")
        try:
            values[key] = kind(value)
        except (TypeError, ValueError):
            raise UserError(f"lrf: {key} must be a {kind.__name__}, got {value!r}") from None
    return cls(port=port, **values)


def driver_from_url(url: str, sink: Sink, config: Mapping[str, Any] | None = None) -> Driver:
    """A laser driver for ``url`` sending messages to ``sink``; a bad URL or option is a UserError."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES:
        raise UserError(f"unknown laser URL {url!r}: use scip2:///dev/ttyACM0, scip2+tcp://host:10940 "
                        "or rplidar:///dev/ttyUSB0?model=a2")
    options = {**dict(config or {}), **{k: _value(v) for k, v in parse_qsl(parts.query)}}
    name = options.get("name", "lrf")
    if not isinstance(name, str) or not name:
        raise UserError(f"lrf: name must be a non-empty string, got {name!r}")
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
        return RplidarDriver(make_config(RplidarConfig, port, options, "an RPLIDAR"), sink, name=name)
    return ScipDriver(make_config(ScipConfig, port, options, "a SCIP 2.0 laser"), sink, name=name)
