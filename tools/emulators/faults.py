"""Fault plans for the device emulators: which faults to inject, how often and how long.

A plan is written as comma-separated ``kind=value`` items, e.g.
``checksum=0.05,garbage=0.02,stall=0.01,stall_s=0.2,streaming,seed=3``:

- per-scan kinds take a probability (0..1) that one scan (RPLIDAR: one revolution) carries
  that fault; at most one fault is drawn per scan;
- flags (``streaming``, ``health_error``) take no value;
- durations end in ``_s`` (seconds) and ``wrap`` is the time in seconds from power-on to the
  first wrap of the 24-bit clock; ``seed`` makes the draw repeatable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from trundle.logs.errors import UserError

DURATIONS = {"stall_s": 0.3, "unplug_s": 0.5, "reboot_s": 0.3}


@dataclass
class FaultPlan:
    """Per-scan fault probabilities, flags and durations (see the module docstring)."""

    rates: dict[str, float] = field(default_factory=dict)
    flags: frozenset[str] = frozenset()
    stall_s: float = DURATIONS["stall_s"]
    unplug_s: float = DURATIONS["unplug_s"]
    reboot_s: float = DURATIONS["reboot_s"]
    wrap_s: float | None = None
    seed: int = 0
    rng: np.random.Generator = field(init=False, repr=False)
    forced: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def force(self, kind: str) -> None:
        """Inject ``kind`` into the next scan (before any random draw), once."""
        self.forced.append(kind)

    def draw(self) -> str:
        """The fault kind for the next scan, or "" for none."""
        if self.forced:
            return self.forced.pop(0)
        if not self.rates:
            return ""
        x = self.rng.random()
        for kind, rate in self.rates.items():
            if x < rate:
                return kind
            x -= rate
        return ""

    def clear(self) -> None:
        """Stop injecting per-scan faults (flags and durations stay)."""
        self.rates = {}


def parse_faults(spec: str | None, kinds: tuple[str, ...], flags: tuple[str, ...]) -> FaultPlan:
    """Parse a fault spec for an emulator that knows per-scan ``kinds`` and ``flags``."""
    plan = FaultPlan()
    if not spec:
        return plan
    rates: dict[str, float] = {}
    seen: set[str] = set()
    for item in (part.strip() for part in spec.split(",")):
        if not item:
            continue
        name, sep, value = item.partition("=")
        name = name.strip()
        if name in flags and not sep:
            seen.add(name)
            continue
        if not sep:
            raise UserError(f"fault {name!r} needs a value (e.g. {name}=0.05); known: {', '.join(kinds + flags)}")
        try:
            number = float(value)
        except ValueError:
            raise UserError(f"fault {name!r}: {value!r} is not a number") from None
        if not math.isfinite(number) or number < 0:
            raise UserError(f"fault {name!r}: value must be a non-negative number")
        if name in kinds:
            if number > 1:
                raise UserError(f"fault {name!r}: a probability must be at most 1")
            rates[name] = number
        elif name in DURATIONS:
            setattr(plan, name, number)
        elif name == "wrap":
            plan.wrap_s = number
        elif name == "seed":
            plan.seed = int(number)
        else:
            raise UserError(f"unknown fault {name!r}; known: {', '.join(kinds + flags + tuple(DURATIONS))}, wrap, seed")
    if sum(rates.values()) > 1:
        raise UserError("fault probabilities add up to more than 1")
    plan.rates, plan.flags = rates, frozenset(seen)
    plan.rng = np.random.default_rng(plan.seed)
    return plan
