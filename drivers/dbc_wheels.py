"""Wheel positions from any motor controller described by a DBC file (VESC, Roboteq, custom),
decoded by cantools: the user names one ``Message.Signal`` per wheel and its units per turn.

Integer position signals are unwrapped on their raw value at the signal's bit width, then
scaled, so a wrapping tachometer stays exact; float signals are used as they are.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import cast

import can
import cantools
from cantools.database.can import Database as CanDatabase
from cantools.database.can import Message as DbcMessage
from cantools.database.can import Signal
from cantools.database.errors import Error as CantoolsError

from trundle.drivers.can_bus import CanBus
from trundle.drivers.encoder_protocol import EncoderProtocol, HeartbeatWatchdog, WheelReading, per_wheel

VESC_DBC = Path(__file__).with_name("data") / "vesc_status.dbc"  # VESC status frames: an example DBC


class DbcWheels(EncoderProtocol):
    """DBC-described encoders: ``signals[i]`` = ``"Message.Signal"`` of wheel ``wheels[i]``.

    Parameters
    ----------
    dbc : path of the DBC (or any format cantools loads: KCD, SYM, ARXML).
    units_per_rev : position signal units (after the DBC's scale) per motor turn; one number
        or one per wheel. E.g. a VESC tachometer counts 6 per electrical turn: 6 * pole pairs.
    velocity_signals : optional ``"Message.Signal"`` per wheel with its speed.
    velocity_scale : multiplies a velocity signal's value to motor turns per second (ERPM:
        1 / (60 * pole pairs)).
    data_timeout_s : a wheel is stale after this long without its position signal.
    """

    name = "dbc"

    def __init__(self, dbc: str | Path, signals: list[str], wheels: tuple[int, ...], *,
                 units_per_rev: float | list[float] = 1.0, velocity_signals: list[str] | None = None,
                 velocity_scale: float | list[float] = 1.0, data_timeout_s: float = 0.25) -> None:
        super().__init__(wheels)
        if len(signals) != len(wheels):
            raise ValueError("one position signal per wheel")
        if velocity_signals and len(velocity_signals) != len(wheels):
            raise ValueError("one velocity signal per wheel")
        try:
            db = cantools.database.load_file(str(dbc), strict=False)
        except (OSError, CantoolsError, ValueError) as error:
            raise ValueError(f"cannot read {dbc}: {error}") from None
        if not isinstance(db, CanDatabase):
            raise ValueError(f"cannot read {dbc}: a diagnostics database, not a CAN one")
        self.db = db
        n = len(wheels)
        units = per_wheel(units_per_rev, n, "units_per_rev")
        vscale = per_wheel(velocity_scale, n, "velocity_scale")
        if any(u <= 0 for u in units):
            raise ValueError("units_per_rev must be positive")
        # frame id -> (message, [(wheel, signal, is position)])
        self._routes: dict[tuple[int, bool], tuple[DbcMessage, list[tuple[int, Signal, bool]]]] = {}
        self._modulus: dict[int, int | None] = {}
        self._scale: dict[int, float] = {}
        for wheel, name, unit in zip(wheels, signals, units, strict=True):
            message, signal = self._add_route(name, wheel, True)
            if signal.is_float:
                self._modulus[wheel], self._scale[wheel] = None, 1.0
                self.counts_per_rev[wheel] = unit
            else:
                self._modulus[wheel], self._scale[wheel] = 2**signal.length, float(signal.scale)
                self.counts_per_rev[wheel] = unit / float(signal.scale)
        self._velocity_scale = dict(zip(wheels, vscale, strict=True))
        for wheel, name in zip(wheels, velocity_signals or [], strict=False):  # none: no speed routes
            self._add_route(name, wheel, False)
        self.data = HeartbeatWatchdog(data_timeout_s)
        self._velocity: dict[int, float] = {}

    def _add_route(self, qualified: str, wheel: int, is_position: bool) -> tuple[DbcMessage, Signal]:
        message_name, dot, signal_name = str(qualified).rpartition(".")
        if not dot:
            raise ValueError(f"signal {qualified!r} must be written Message.Signal")
        try:
            message = self.db.get_message_by_name(message_name)
            signal = message.get_signal_by_name(signal_name)
        except KeyError:
            raise ValueError(f"no signal {signal_name!r} in message {message_name!r} of the DBC") from None
        key = (message.frame_id, bool(message.is_extended_frame))
        targets = self._routes.setdefault(key, (message, []))[1]
        # velocities first, so a position in the same frame carries the fresh velocity
        targets.insert(len(targets) if is_position else 0, (wheel, signal, is_position))
        return message, signal

    def start(self, bus: CanBus, now_ns: int) -> None:
        self.data.reset()
        self._velocity.clear()

    def handle(self, msg: can.Message, now_ns: int) -> list[WheelReading]:
        if msg.is_error_frame or msg.is_remote_frame:
            return []
        route = self._routes.get((msg.arbitration_id, msg.is_extended_id))
        if route is None:
            return []
        message, targets = route
        try:
            # neither choices nor scaling: every value is the signal's raw number
            raw = cast(dict[str, int | float], message.decode(bytes(msg.data), decode_choices=False, scaling=False))
        except (CantoolsError, ValueError, KeyError, IndexError) as error:
            raise ValueError(f"{message.name}: {error}") from None
        readings = []
        for wheel, signal, is_position in targets:
            value = raw[signal.name]
            if not is_position:
                speed = (value * signal.scale + signal.offset) * self._velocity_scale[wheel]
                self._velocity[wheel] = speed * self.counts_per_rev[wheel]
                continue
            if self._modulus[wheel] is None:
                if not math.isfinite(value):
                    raise ValueError(f"{message.name}.{signal.name} is not finite")
                position: int | float = float(value) * signal.scale + signal.offset
            else:
                position = int(value)
            self.data.beat(wheel, now_ns)
            readings.append(WheelReading(wheel, position, self._velocity.get(wheel, math.nan), self._modulus[wheel]))
        return readings

    def healthy_wheels(self, now_ns: int) -> set[int]:
        return {w for w in self.wheels if self.data.alive(w, now_ns)}

    def poll(self, now_ns: int) -> None:
        self.counters["data_losses"] += len(self.data.check(now_ns))
