"""What every CAN wheel-encoder protocol gives the wheels driver, and the heartbeat watchdog they share.

A protocol turns received frames into :class:`WheelReading` values in its device's own counts
(turns for ODrive estimates, encoder counts for CiA 406, scaled signal units for a DBC) and says
which of its wheels are healthy. The wheels driver unwraps, scales to radians and publishes.
Times passed in as ``now_ns`` are host monotonic nanoseconds.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Hashable
from typing import Any, NamedTuple

import can

from trundle.drivers.can_bus import CanBus


class WheelReading(NamedTuple):
    """One wheel's position in device counts (int for a counter, float for turns), its velocity
    in counts per second (NaN if the frame has none) and the counter period for unwrapping
    (None for a position that does not wrap). A named tuple: one is made per frame."""

    wheel: int
    position: int | float
    velocity: float = math.nan
    modulus: int | None = None


def per_wheel(value: object, n: int, what: str) -> list[float]:
    """A per-wheel setting given as one number or one number per wheel; ``ValueError`` if not."""
    values: list[Any] = list(value) if isinstance(value, (list, tuple)) else [value] * n  # float() checks each
    if len(values) != n:
        raise ValueError(f"{what} has {len(values)} values for {n} wheels")
    try:
        return [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers, got {value!r}") from None


class HeartbeatWatchdog:
    """Last time each key (node, wheel) was heard; stale after ``timeout_s`` of silence.

    ``losses`` counts alive -> stale transitions per key. A key never heard is not alive.
    ``timeout_s <= 0`` disables the watch (every key heard once stays alive).
    """

    def __init__(self, timeout_s: float) -> None:
        self.timeout_ns = int(timeout_s * 1e9)
        self.last_ns: dict[Hashable, int] = {}
        self.losses: Counter[Hashable] = Counter()
        self._stale: set[Hashable] = set()

    def beat(self, key: Hashable, now_ns: int) -> bool:
        """Record a sign of life; True if the key was stale (or never heard) before."""
        revived = key in self._stale or key not in self.last_ns
        self.last_ns[key] = now_ns
        self._stale.discard(key)
        return revived

    def alive(self, key: Hashable, now_ns: int) -> bool:
        last = self.last_ns.get(key)
        if last is None:
            return False
        return self.timeout_ns <= 0 or now_ns - last <= self.timeout_ns

    def check(self, now_ns: int) -> set[Hashable]:
        """Keys that went stale since the last check (each loss is reported once)."""
        newly = {k for k in self.last_ns if k not in self._stale and not self.alive(k, now_ns)}
        for key in newly:
            self.losses[key] += 1
        self._stale |= newly
        return newly

    def reset(self) -> None:
        self.last_ns.clear()
        self._stale.clear()


class EncoderProtocol(ABC):
    """Base of a wheel-encoder protocol serving the wheels at global indices ``wheels``.

    ``counts_per_rev[wheel]`` (device counts per motor revolution) must be known once the
    protocol is configured; ``start`` must not block (slow configuration runs on a worker
    while the driver keeps receiving and passing frames to ``handle``).
    """

    name = "encoders"

    def __init__(self, wheels: tuple[int, ...]) -> None:
        self.wheels = tuple(wheels)
        self.counts_per_rev: dict[int, float] = {}
        self.counters: Counter[str] = Counter()

    @abstractmethod
    def start(self, bus: CanBus, now_ns: int) -> None:
        """Begin talking to the devices on a freshly opened ``bus``."""

    @abstractmethod
    def handle(self, msg: can.Message, now_ns: int) -> list[WheelReading]:
        """Decode one received frame (others' frames give []); ``ValueError`` if it is corrupt."""

    @abstractmethod
    def healthy_wheels(self, now_ns: int) -> set[int]:
        """Wheels whose node is alive and whose positions can be trusted now."""

    def poll(self, now_ns: int) -> None:  # noqa: B027  an optional hook: protocols without periodic work keep it
        """Periodic work (requests, watchdog recovery); called often by the driver."""

    def stop(self) -> None:  # noqa: B027  an optional hook: protocols without a worker keep it
        """Stop any worker; the bus is closed by the driver."""

    def silence_hint(self, seen_ids: set[int]) -> str:
        """Why these wheels give no readings though the bus carries frames (``seen_ids``: the
        arbitration ids heard), "" when the protocol has no guess."""
        return ""

    def diagnostics(self) -> list[tuple[str, str]]:
        return [(f"{self.name}.{k}", str(v)) for k, v in sorted(self.counters.items())]
