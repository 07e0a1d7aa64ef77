"""A python-can bus opened from a URL, with receive time stamps, bus health and safe sending.

URLs:

- ``socketcan://can0`` (the robot; ``vcan0`` where the kernel has it). Kernel receive stamps
  are used. Bus-off recovery is the kernel's: ``ip link set can0 type can restart-ms 100``;
  for ENOBUFS on send raise ``txqueuelen`` (``ip link set can0 txqueuelen 1000``).
- ``slcan:///dev/ttyACM0@1000000`` (Lawicel/CANable serial adapters; ``@`` gives the CAN bit
  rate, default 500000; ``?tty_baudrate=115200`` the serial rate). The adapter's stamps are
  dropped by python-can, so frames are stamped at receipt. Status flags are polled with ``F``;
  a bus-off (bus error flag) is left by ``C`` then ``O``, as Lawicel adapters require. The
  adapter is read by our own :class:`~trundle.drivers.slcan.SlcanBus` (every available byte per
  read); ``?reader=python-can`` selects python-can's own slcan interface instead (byte-at-a-time,
  without status polling or bus-off recovery: it has no public call for ``F``; and without the
  port's lock, since python-can 4.6.1 opens the port itself and takes no ``exclusive``).
- ``virtual://name`` (in-process python-can virtual bus, for tests and replay;
  ``?timestamps=device`` keeps the sender's stamps, e.g. a replayed log with
  ``preserve_timestamps``).

Every received frame gets a host stamp taken from the monotonic clock at receipt and mapped
to wall time through an offset measured when the bus opens, so stamps within one session never
step with the wall clock. Where the interface gives its own stamp (``timestamps=device``, the
default for socketcan) that stamp is the frame's ``stamp_ns``; the host stamp is kept as well.
"""

from __future__ import annotations

import contextlib
import errno
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import can

from trundle.drivers.lifecycle import wall_ns
from trundle.drivers.slcan import BITRATE_COMMANDS, SlcanBus
from trundle.logs.errors import DeviceError, ProtocolError, UserError

SCHEMES = ("socketcan", "slcan", "virtual")
SLCAN_BITRATES = tuple(BITRATE_COMMANDS)

# SocketCAN error frame classes (linux/can/error.h), in the arbitration id of an error frame.
CAN_ERR_TX_TIMEOUT, CAN_ERR_LOSTARB, CAN_ERR_CRTL, CAN_ERR_PROT = 0x001, 0x002, 0x004, 0x008
CAN_ERR_TRX, CAN_ERR_ACK, CAN_ERR_BUSOFF, CAN_ERR_BUSERROR, CAN_ERR_RESTARTED = 0x010, 0x020, 0x040, 0x080, 0x100
# Controller status in data[1] of a CAN_ERR_CRTL frame.
CAN_ERR_CRTL_RX_OVERFLOW, CAN_ERR_CRTL_TX_OVERFLOW = 0x01, 0x02
CAN_ERR_CRTL_WARNING = 0x04 | 0x08
CAN_ERR_CRTL_PASSIVE = 0x10 | 0x20

# SLCAN "F" status flags.
SLCAN_RX_FIFO_FULL, SLCAN_TX_FIFO_FULL, SLCAN_ERROR_WARNING, SLCAN_DATA_OVERRUN = 0x01, 0x02, 0x04, 0x08
SLCAN_ERROR_PASSIVE, SLCAN_ARBITRATION_LOST, SLCAN_BUS_ERROR = 0x20, 0x40, 0x80


@dataclass(frozen=True)
class BusSpec:
    """A parsed CAN URL: python-can ``interface`` and ``channel``, CAN ``bitrate``, options."""

    url: str
    interface: str
    channel: str
    bitrate: int | None = None
    device_stamps: bool = False
    options: dict[str, str] = field(default_factory=dict)


def parse_url(url: str) -> BusSpec:
    """Parse ``socketcan://can0``, ``slcan:///dev/ttyACM0@1000000`` or ``virtual://name``."""
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme not in SCHEMES or "://" not in url:
        raise UserError(f"unsupported CAN URL {url!r}: use socketcan://can0, slcan:///dev/ttyACM0@1000000 or virtual://name")
    options = dict(parse_qsl(parts.query))
    stamps = options.pop("timestamps", "device" if scheme == "socketcan" else "host")
    if stamps not in ("host", "device"):
        raise UserError(f"timestamps must be host or device in {url!r}")
    location = parts.netloc + parts.path
    bitrate = None
    if scheme == "slcan":
        location, _, rate = location.partition("@")
        try:
            bitrate = int(rate) if rate else 500000
        except ValueError:
            raise UserError(f"bad CAN bit rate {rate!r} in {url!r}") from None
        if bitrate not in SLCAN_BITRATES:
            raise UserError(f"SLCAN bit rate {bitrate} not one of {', '.join(map(str, sorted(SLCAN_BITRATES)))}")
        if options.get("reader", "lines") not in ("lines", "python-can"):
            raise UserError(f"SLCAN reader must be lines or python-can in {url!r}")
    elif "bitrate" in options:
        try:
            bitrate = int(options.pop("bitrate"))
        except ValueError:
            raise UserError(f"bad bitrate in {url!r}") from None
    if not location:
        raise UserError(f"no CAN channel in {url!r}")
    return BusSpec(url, scheme, location, bitrate, stamps == "device", options)


@dataclass(frozen=True)
class Received:
    """A received frame with its stamps: ``host_ns`` (receipt, monotonic mapped to wall time),
    ``device_ns`` (the interface's own stamp, if it gives a meaningful one) and ``stamp_ns``
    (the one to use: device where trusted, else host)."""

    msg: can.Message
    host_ns: int
    device_ns: int | None

    @property
    def stamp_ns(self) -> int:
        return self.device_ns if self.device_ns is not None else self.host_ns


class CanBus:
    """One CAN interface with counters (``frames``, ``corrupt_frames``, ``error_frames``, ``bus_off``,
    ``bus_errors``, ``error_passive``, ``error_warnings``, ``overruns``, ``restarts``, ``tx_frames``,
    ``tx_retries``, ``tx_dropped``) and a ``state`` (closed, active, warning, passive, bus-off).

    Faults that need the adapter reopened (unplugged, vanished port) raise ``DeviceError``.
    """

    def __init__(self, spec: BusSpec | str, *, status_poll_s: float = 0.5, tx_retries: int = 3,
                 tx_backoff_s: float = 0.002) -> None:
        self.spec = parse_url(spec) if isinstance(spec, str) else spec
        self.status_poll_s = status_poll_s
        self.tx_retries = tx_retries
        self.tx_backoff_s = tx_backoff_s
        self.counters: Counter[str] = Counter()
        self.state = "closed"
        self.bus: can.BusABC | None = None
        self._offset_ns = 0
        self._next_status = 0.0
        self._tx_lock = threading.Lock()

    # -- life cycle ----------------------------------------------------------------------------
    def open(self) -> None:
        spec = self.spec
        kwargs: dict[str, Any] = {}
        if spec.interface == "slcan":
            kwargs.update(bitrate=spec.bitrate, sleep_after_open=float(spec.options.get("sleep_after_open", 0)))
            if "tty_baudrate" in spec.options:
                kwargs["tty_baudrate"] = int(spec.options["tty_baudrate"])
        elif spec.interface == "virtual":
            kwargs.update(preserve_timestamps=spec.device_stamps, receive_own_messages=False)
        elif spec.bitrate is not None:
            kwargs["bitrate"] = spec.bitrate
        try:
            if spec.interface == "slcan" and spec.options.get("reader", "lines") == "lines":
                self.bus = SlcanBus(spec.channel, **kwargs)
            else:
                self.bus = can.Bus(interface=spec.interface, channel=spec.channel, **kwargs)
        except (can.CanError, OSError, ValueError) as error:
            raise DeviceError(f"cannot open {spec.url}: {error}") from error
        self._offset_ns = wall_ns() - time.monotonic_ns()
        self._next_status = time.monotonic() + self.status_poll_s
        self.state = "active"

    def close(self) -> None:
        bus, self.bus = self.bus, None
        self.state = "closed"
        if bus is not None:
            # an unplugged slcan adapter fails its closing "C"; the port is released anyway
            with contextlib.suppress(can.CanError, OSError, ValueError):
                bus.shutdown()

    def host_ns(self) -> int:
        """Now on the session's clock: monotonic time mapped to wall time at open."""
        return time.monotonic_ns() + self._offset_ns

    # -- receive -------------------------------------------------------------------------------
    def recv(self, timeout_s: float) -> Received | None:
        """The next frame (error frames included, counted), or None after ``timeout_s``."""
        bus = self._require()
        try:
            msg = bus.recv(timeout_s)
        except (can.CanError, OSError) as error:
            raise DeviceError(f"{self.spec.url}: {error}") from error
        except (ProtocolError, ValueError, IndexError):  # ValueError, IndexError: python-can's slcan parser
            self.counters["corrupt_frames"] += 1  # a garbled SLCAN line
            return None
        if msg is None:
            self.maybe_poll_status()
            return None
        host = self.host_ns()
        self.counters["frames"] += 1
        if msg.is_error_frame:
            self._count_error_frame(msg)
        device = int(round(msg.timestamp * 1e9)) if self.spec.device_stamps and msg.timestamp else None
        return Received(msg, host, device)

    def _count_error_frame(self, msg: can.Message) -> None:
        self.counters["error_frames"] += 1
        cls = msg.arbitration_id
        status = msg.data[1] if len(msg.data) > 1 else 0
        if cls & CAN_ERR_BUSOFF:
            self.counters["bus_off"] += 1
            self.state = "bus-off"
        elif cls & CAN_ERR_RESTARTED:
            self.counters["restarts"] += 1
            self.state = "active"
        if cls & (CAN_ERR_BUSERROR | CAN_ERR_PROT):
            self.counters["bus_errors"] += 1
        if cls & CAN_ERR_CRTL:
            if status & (CAN_ERR_CRTL_RX_OVERFLOW | CAN_ERR_CRTL_TX_OVERFLOW):
                self.counters["overruns"] += 1
            if status & CAN_ERR_CRTL_PASSIVE:
                self.counters["error_passive"] += 1
                self.state = "passive"
            elif status & CAN_ERR_CRTL_WARNING:
                self.counters["error_warnings"] += 1
                self.state = "warning"

    # -- status (SLCAN) ------------------------------------------------------------------------
    def maybe_poll_status(self) -> None:
        """Poll the adapter's status flags when due (SLCAN only) and leave bus-off."""
        if self.spec.interface != "slcan" or time.monotonic() < self._next_status:
            return
        self._next_status = time.monotonic() + self.status_poll_s
        flags = self.slcan_status()
        if flags is None:
            return
        if flags & (SLCAN_DATA_OVERRUN | SLCAN_RX_FIFO_FULL):
            self.counters["overruns"] += 1
        if flags & SLCAN_ERROR_WARNING:
            self.counters["error_warnings"] += 1
        if flags & SLCAN_ERROR_PASSIVE:
            self.counters["error_passive"] += 1
        if flags & SLCAN_BUS_ERROR:
            self.counters["bus_off"] += 1
            self.state = "bus-off"
            self._slcan_restart()
        else:
            self.state = ("passive" if flags & SLCAN_ERROR_PASSIVE else "warning" if flags & SLCAN_ERROR_WARNING
                          else "active")

    def slcan_status(self, timeout_s: float = 0.1) -> int | None:
        """The adapter's ``F`` status flags, or None if it does not answer (or is read by
        python-can's own slcan interface, which has no status call); frames that arrive
        meanwhile stay queued for ``recv``."""
        bus = self._require()
        if not isinstance(bus, SlcanBus):
            return None
        try:
            return bus.status_flags(timeout_s)
        except (can.CanError, OSError) as error:
            raise DeviceError(f"{self.spec.url}: {error}") from error

    def _slcan_restart(self) -> None:
        bus = self._require()
        assert isinstance(bus, SlcanBus)  # only our bus reports the flags that lead here
        try:
            with self._tx_lock:
                bus.restart()
        except (can.CanError, OSError) as error:
            raise DeviceError(f"{self.spec.url}: restart after bus-off failed: {error}") from error
        self.counters["restarts"] += 1
        self.state = "active"

    # -- send ----------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout_s: float | None = 0.01) -> bool:
        """Send ``msg``; retries a full transmit queue (ENOBUFS) with back-off and drops the
        frame (counted) if it stays full. A vanished adapter raises ``DeviceError``."""
        bus = self._require()
        for attempt in range(self.tx_retries + 1):
            try:
                with self._tx_lock:
                    bus.send(msg, timeout_s)
                self.counters["tx_frames"] += 1
                return True
            except can.CanOperationError as error:
                cause = error.__cause__
                full = errno.ENOBUFS in (error.error_code, getattr(cause, "errno", None)) \
                    or "timeout" in f"{error} {cause}".lower()
                if not full:
                    raise DeviceError(f"{self.spec.url}: {error}") from error
            except OSError as error:
                if error.errno != errno.ENOBUFS:
                    raise DeviceError(f"{self.spec.url}: {error}") from error
            if attempt < self.tx_retries:
                self.counters["tx_retries"] += 1
                time.sleep(self.tx_backoff_s * (2**attempt))
        self.counters["tx_dropped"] += 1
        return False

    def _require(self) -> can.BusABC:
        if self.bus is None:
            raise DeviceError(f"{self.spec.url} is not open")
        return self.bus
