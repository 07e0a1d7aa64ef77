"""Argument types for numbers and ports with their ranges, so a wrong value is refused by the
parser (one line naming the option) instead of running with it: argparse ``type=`` callables.

NaN and infinities are refused everywhere: no option of ours means anything with them.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def _number(text: str, kind: type) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if kind is int else 'a number'}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def number_in(low: float | None = None, high: float | None = None, *, low_open: bool = False,
              whole: bool = False) -> Callable[[str], float]:
    """A type accepting a finite number in [low, high] (``low_open``: (low, high]); None: no bound."""
    kind = int if whole else float

    def parse(text: str) -> float:
        value = _number(text, kind)
        if low is not None and (value < low or (low_open and value == low)):
            raise argparse.ArgumentTypeError(f"{text} must be {'above' if low_open else 'at least'} {low:g}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"{text} must be at most {high:g}")
        return value

    parse.__name__ = "whole number" if whole else "number"  # what argparse names in its message
    parse.bounds = (low, high, low_open, whole)  # type: ignore[attr-defined]  # for tests that probe the edges
    return parse


positive = number_in(0.0, low_open=True)
non_negative = number_in(0.0)
finite = number_in()
positive_int = number_in(1, whole=True)
non_negative_int = number_in(0, whole=True)
tcp_port = number_in(0, 65535, whole=True)
percent = number_in(1, 100, whole=True)


def host_port(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` as (host, port); HOST defaults to the loopback 127.0.0.1 (nothing is served to
    the network unless asked), PORT is a TCP port (0: any free one)."""
    host, sep, port = text.rpartition(":")
    if sep and not host:
        raise argparse.ArgumentTypeError(f"{text!r} has no host before ':' (give PORT or HOST:PORT)")
    return host or "127.0.0.1", int(tcp_port(port))


host_port.__name__ = "[HOST:]PORT"
