"""Host time of a device's wrapping tick counter: round-trip offset, unwrap, reset detection, drift.

A sensor stamps its data with a free-running counter (Hokuyo: 24-bit milliseconds, wrapping
every 4.66 h and set to 0 by a reboot). ``SensorClock`` turns each reading into host
nanoseconds: the offset comes from request/reply round trips (median of the midpoint
estimates, as urg_node does), wraps are unwrapped forwards, a reset is recognised when the
counter claims more time passed than the host saw (seqsense/urg_stamped PR #65), and drift is
the slope of receive latency against device time (urg_stamped models 50 ppm).

A device that is never asked (a camera stamping each frame it streams: mjpg-streamer's
``X-Timestamp``) gets ``envelope=True``: the offset is anchored on the first reading received
and kept at the smallest receive latency seen since, as a delivery delay only ever adds latency:
a reading received sooner after its device time than any before lowers the offset at once, so
no stamp lies after its own arrival and late readings change nothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClockReading:
    """One converted reading: ``raw`` counter, ``unwrapped`` ticks, host ``stamp_ns`` and the
    event it caused: "" normal, "wrap" the counter wrapped, "reset" the device clock restarted,
    "resync" the offset was re-anchored on receive times."""

    raw: int
    unwrapped: int
    stamp_ns: int
    offset_ns: int
    event: str = ""


class SensorClock:
    """Converts a ``bits``-wide device tick counter (``tick_ns`` per tick) to host nanoseconds.

    Parameters
    ----------
    bits, tick_ns : counter width and tick length (Hokuyo: 24 bits of 1 ms).
    reset_tolerance_ns : how much more time the device may claim to have passed than the host
        saw between two readings before it counts as a reset.
    resync_tolerance_ns : receive latency may leave its running median by this much (urg_node2
        uses 0.1 s). Latency below minus this even once means the offset is wrong (data received
        before it was measured): re-anchored at once. Above the median by this for
        ``resync_after_ticks`` of device time in a row too: a busy host only ever makes latency
        larger, so that case waits longer.
    bin_ticks : drift is fitted to the smallest receive latency in each bin of this many ticks
        (the lower envelope is what transmission jitter cannot blur).
    window : bins kept for the drift fit; ``min_drift_bins`` before drift is estimated.
    max_drift_ppm : drift estimates are clipped to this magnitude.
    envelope : no round trips (see the module's doc): the offset follows the lower envelope of
        receive latency instead of its running median.
    """

    RECENT = 64  # readings kept for the latency median
    REFINE = 16  # readings after a re-anchoring whose median latency corrects it

    def __init__(self, bits: int = 24, tick_ns: int = 1_000_000, reset_tolerance_ns: int = 500_000_000,
                 resync_tolerance_ns: int = 100_000_000, resync_after_ticks: int = 5000, bin_ticks: int = 1000,
                 window: int = 600, min_drift_bins: int = 30, max_drift_ppm: float = 1000.0,
                 envelope: bool = False) -> None:
        self.mask = (1 << bits) - 1
        self.tick_ns = tick_ns
        self.reset_tolerance_ns = reset_tolerance_ns
        self.resync_tolerance_ns = resync_tolerance_ns
        self.resync_after_ticks = resync_after_ticks
        self.bin_ticks = bin_ticks
        self.window = window
        self.min_drift_bins = min_drift_bins
        self.max_drift_ppm = max_drift_ppm
        self.envelope = envelope
        self.offset_ns = 0
        self.drift_ppm = 0.0
        self.wraps = 0
        self.resets = 0
        self.resyncs = 0
        self._ref = 0  # unwrapped tick at which offset_ns holds exactly
        self._last_raw: int | None = None
        self._last_host = 0
        self._unwrapped = 0
        self._recent = np.zeros(self.RECENT, np.float64)
        self._n_recent = 0
        self._outside: int | None = None  # unwrapped tick at which latency left its band
        self._bin_t = np.zeros(window, np.float64)
        self._bin_y = np.zeros(window, np.float64)
        self._bins = 0
        self._bin = -1
        self._bin_min = np.inf
        self._median_at = (0, 0, 0)  # (readings in the window, readings seen, median) when computed
        self._target: int | None = None  # median latency to restore after a re-anchoring
        self._refine: list[int] = []

    @property
    def synced(self) -> bool:
        return self._last_raw is not None

    def host_ns(self, unwrapped: int) -> int:
        """Host time of an unwrapped tick count under the current offset and drift."""
        elapsed = (unwrapped - self._ref) * self.tick_ns
        return self.offset_ns + unwrapped * self.tick_ns + round(elapsed * self.drift_ppm * 1e-6)  # exact ints

    def synchronise(self, samples: Sequence[tuple[int, int, int]]) -> int:
        """Set the offset from round trips ``(host_request_ns, raw_ticks, host_reply_ns)``.

        Each gives ``midpoint - device_time`` (plus half a tick: the counter truncates). A slow
        round trip is a lopsided one more often than not, so only the faster half is kept (as
        NTP prefers its shortest round trips) and their median taken. Unwrapping restarts at
        the last sample. Returns the offset in ns.
        """
        if not samples:
            raise ValueError("clock synchronisation needs at least one round trip")
        unwrapped = [samples[0][1] & self.mask]
        for _, raw, _ in samples[1:]:
            unwrapped.append(unwrapped[-1] + (((raw & self.mask) - unwrapped[-1]) & self.mask))
        mids = np.array([(req + rep) / 2.0 - u * self.tick_ns - self.tick_ns / 2.0
                         for (req, _, rep), u in zip(samples, unwrapped, strict=True)])
        rtt = np.array([rep - req for req, _, rep in samples])
        mids = mids[rtt <= np.median(rtt)]
        self._restart(samples[-1][1] & self.mask, samples[-1][2])
        self.offset_ns = int(np.median(mids)) + (unwrapped[-1] - self._unwrapped) * self.tick_ns
        self.drift_ppm = 0.0
        return self.offset_ns

    def anchor(self, raw: int, host_ns: int, latency_ns: int = 0) -> None:
        """Set the offset from one reading received at ``host_ns``, ``latency_ns`` after it was taken."""
        self._restart(raw & self.mask, host_ns)
        self.offset_ns = host_ns - latency_ns - self._unwrapped * self.tick_ns
        self.drift_ppm = 0.0

    def _restart(self, raw: int, host_ns: int) -> None:
        self._last_raw = raw
        self._last_host = host_ns
        self._unwrapped = self._ref = raw
        self._n_recent = self._bins = 0
        self._outside = None
        self._median_at = (0, 0, 0)
        self._bin, self._bin_min = -1, np.inf

    def update(self, raw: int, host_rx_ns: int) -> ClockReading:
        """Convert a reading received at ``host_rx_ns`` (after its measurement) to host time."""
        raw &= self.mask
        if self._last_raw is None:
            self.anchor(raw, host_rx_ns)
            return ClockReading(raw, self._unwrapped, self.host_ns(self._unwrapped), self.offset_ns, "resync")
        step = (raw - self._last_raw) & self.mask
        host_step = host_rx_ns - self._last_host
        event = ""
        if step * self.tick_ns > host_step + self.reset_tolerance_ns:
            event = "reset"
            self.resets += 1
            self._unwrapped += max(host_step, 0) // self.tick_ns
            self._reanchor(self._anchor_stamp(host_rx_ns))
        else:
            if raw < self._last_raw:
                event = "wrap"
                self.wraps += 1
            self._unwrapped += step
        self._last_raw = raw
        self._last_host = host_rx_ns
        if self._track(host_rx_ns, self.host_ns(self._unwrapped)) and not event:
            event = "resync"
            self.resyncs += 1
            self._reanchor(self._anchor_stamp(host_rx_ns))
        stamp = self.host_ns(self._unwrapped)  # under the offset as this reading left it
        return ClockReading(raw, self._unwrapped, stamp, self.offset_ns, event)

    def _anchor_stamp(self, host_rx_ns: int) -> int:
        """The stamp a re-anchoring gives the reading received at ``host_rx_ns``: the typical latency
        before it, or none with ``envelope`` (the envelope then lowers it as faster readings come)."""
        return host_rx_ns if self.envelope else host_rx_ns - self._median_latency()

    def _lower_offset(self, shift_ns: int) -> None:
        """Make every stamp ``shift_ns`` earlier; the latencies kept for the median and the drift
        fit grow by as much, so they stay comparable with those still to come."""
        self.offset_ns -= shift_ns
        n = min(self._n_recent, self.RECENT)
        self._recent[:n] += shift_ns
        self._median_at = (*self._median_at[:2], self._median_at[2] + shift_ns)
        self._bin_y[:min(self._bins, self.window)] += shift_ns
        self._bin_min += shift_ns

    def _reanchor(self, stamp_ns: int) -> None:
        """Make the current unwrapped tick map to ``stamp_ns``, keeping the drift estimate.

        One receive time is only as good as its latency; once ``REFINE`` more readings have
        come, the offset is shifted so their median latency matches the one before.
        """
        if self._n_recent and not self.envelope:
            self._target, self._refine = self._median_latency(), []
        self.offset_ns = stamp_ns - self._unwrapped * self.tick_ns
        self._ref = self._unwrapped
        self._bins = 0
        self._outside = None
        self._bin, self._bin_min = -1, np.inf

    def _median_latency(self) -> int:
        """Median of the recent latencies (recomputed every 8 readings: it moves slowly)."""
        n = min(self._n_recent, self.RECENT)
        if n != self._median_at[0] and (n < self.RECENT or self._n_recent - self._median_at[1] >= 8):
            self._median_at = (n, self._n_recent, int(np.median(self._recent[:n])) if n else 0)
        return self._median_at[2]

    def _track(self, host_rx_ns: int, stamp_ns: int) -> bool:
        """Record a receive latency, update the drift; True when the offset needs re-anchoring."""
        latency = host_rx_ns - stamp_ns
        if latency < -self.resync_tolerance_ns:
            return True
        if self.envelope and latency < 0:
            self._lower_offset(-latency)
            latency = 0
        if self._n_recent >= 8 and latency - self._median_latency() > self.resync_tolerance_ns:
            if self._outside is None:
                self._outside = self._unwrapped
            return self._unwrapped - self._outside >= self.resync_after_ticks
        self._outside = None
        if self._target is not None:
            self._refine.append(latency)
            if len(self._refine) < self.REFINE:
                return False
            shift = int(np.median(self._refine)) - self._target
            self.offset_ns += shift
            latency -= shift
            self._target = None
        self._recent[self._n_recent % self.RECENT] = latency
        self._n_recent += 1
        ticks = self._unwrapped - self._ref
        plain = host_rx_ns - (self.offset_ns + self._unwrapped * self.tick_ns)  # latency without drift
        current = ticks // self.bin_ticks
        if current != self._bin:
            if self._bin >= 0 and np.isfinite(self._bin_min):
                slot = self._bins % self.window
                self._bin_t[slot] = (self._bin + 0.5) * self.bin_ticks * self.tick_ns
                self._bin_y[slot] = self._bin_min
                self._bins += 1
                if self._bins >= self.min_drift_bins:
                    self._fit_drift()
            self._bin, self._bin_min = current, np.inf
        self._bin_min = min(self._bin_min, plain)
        return False

    def _fit_drift(self) -> None:
        """Drift = slope of the per-bin minimum latency over device time."""
        n = min(self._bins, self.window)
        t, y = self._bin_t[:n], self._bin_y[:n]
        if np.ptp(t) <= 0:
            return
        slope = np.polyfit(t, y, 1)[0]
        self.drift_ppm = float(np.clip(slope * 1e6, -self.max_drift_ppm, self.max_drift_ppm))
