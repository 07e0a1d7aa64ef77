"""Times read from a dataset's text: decimal Unix seconds to the integer nanoseconds trundle stamps with.

A float would round a 10-digit second with 6 decimals by about 100 ns; ``Decimal`` reads the text exactly.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation


def seconds_ns(token: str) -> int:
    """Decimal Unix seconds (``"1248275403.011"``) to integer nanoseconds, exactly. Text that is no number, an
    infinity or NaN, or a time before 1970 or past 2262 (outside int64 nanoseconds, as MCAP and our stamps hold
    them) is a ValueError."""
    try:
        value = Decimal(token)
    except InvalidOperation:
        raise ValueError(f"not a time: {token!r}") from None
    if not value.is_finite():   # "inf" and "nan" are decimals, but no integer
        raise ValueError(f"not a time: {token!r}")
    ns = int((value * 1_000_000_000).to_integral_value())
    if not 0 <= ns < 1 << 63:
        raise ValueError(f"time out of range: {token!r}")
    return ns
