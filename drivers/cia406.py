"""CiA 406 (CANopen encoder) wheel positions: the `canopen` package for NMT, SDO configuration
and PDO mapping; our own codec for heartbeats and the position TPDO; our own heartbeat watchdog
(the package has none).

Per node: NMT pre-operational, SDO writes of the heartbeat time (0x1017), optionally the
resolution (0x6001), TPDO1 = position value 0x6004 sent every ``tpdo_period_ms`` (event timer
and 0x6200 cyclic timer), SDO reads of the resolution and total measuring range (0x6002, the
counter's wrap), then NMT start. A node that goes silent is reset (NMT reset communication,
rate-limited); its boot-up heartbeat triggers the configuration again.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import INTEGER8, INTEGER16, INTEGER32, INTEGER64
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from trundle.drivers.can_bus import CanBus
from trundle.drivers.encoder_protocol import EncoderProtocol, HeartbeatWatchdog, WheelReading
from trundle.logs.errors import DeviceError, ProtocolError

DEFAULT_EDS = Path(__file__).with_name("data") / "cia406_encoder.eds"

NMT, EMCY, TPDO1, SDO_TX, SDO_RX, HEARTBEAT = 0x000, 0x080, 0x180, 0x580, 0x600, 0x700
NMT_START, NMT_STOP, NMT_PRE_OPERATIONAL, NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x01, 0x02, 0x80, 0x81, 0x82
BOOT_UP, STOPPED, OPERATIONAL, PRE_OPERATIONAL = 0x00, 0x04, 0x05, 0x7F
POSITION_VALUE, UNITS_PER_REV, TOTAL_RANGE, CYCLIC_TIMER, HEARTBEAT_TIME = 0x6004, 0x6001, 0x6002, 0x6200, 0x1017
PROFILE_406 = 0x0196
_SIGNED = {INTEGER8, INTEGER16, INTEGER32, INTEGER64}

log = logging.getLogger(__name__)


def decode_heartbeat(data: bytes | bytearray) -> int:
    """NMT state of a heartbeat (0 boot-up, 4 stopped, 5 operational, 127 pre-operational);
    the toggle bit (node guarding) is masked off."""
    if len(data) < 1:
        raise ValueError("empty CANopen heartbeat")
    state = data[0] & 0x7F
    if state not in (BOOT_UP, STOPPED, OPERATIONAL, PRE_OPERATIONAL):
        raise ValueError(f"unknown NMT state 0x{state:02X}")
    return state


def decode_emcy(data: bytes | bytearray) -> tuple[int, int]:
    """``(error code, error register)`` of an emergency frame."""
    if len(data) < 3:
        raise ValueError(f"CANopen EMCY needs 3 bytes, got {len(data)}")
    return struct.unpack_from("<HB", data)


@dataclass(frozen=True)
class PositionLayout:
    """Where the position value sits in the TPDO: byte offset, size in bytes, signedness."""

    offset: int = 0
    size: int = 4
    signed: bool = False

    def decode(self, data: bytes | bytearray) -> int:
        end = self.offset + self.size
        if len(data) < end:
            raise ValueError(f"TPDO of {len(data)} bytes too short for the position at bytes {self.offset}..{end - 1}")
        return int.from_bytes(data[self.offset:end], "little", signed=self.signed)


class _Node:
    """Host-side state of one encoder node."""

    def __init__(self, node_id: int, wheel: int) -> None:
        self.id, self.wheel = node_id, wheel
        self.remote: canopen.RemoteNode | None = None
        self.configured = False
        self.queued = False
        self.state: int | None = None
        self.layout = PositionLayout()
        self.modulus = 2**32
        self.next_reset_ns = 0


class Cia406Encoders(EncoderProtocol):
    """CiA 406 encoders ``node_ids`` (one per wheel, in the order of ``wheels``).

    Parameters
    ----------
    eds : object dictionary of the devices (vendor EDS); default a generic CiA 406 encoder.
    counts_per_rev : write this resolution to 0x6001 (default: read the device's).
    tpdo_period_ms : TPDO1 event timer / cyclic timer in ms.
    heartbeat_ms : producer heartbeat time written to 0x1017; stale after
        ``heartbeat_timeout_factor`` heartbeat periods of silence.
    data_timeout_s : a wheel is stale after this long without a position TPDO.
    sdo_timeout_s, sdo_retries : SDO client response timeout and retries (slow devices exist).
    reset_period_s : how often a silent node is sent NMT reset communication.
    """

    name = "cia406"

    def __init__(self, node_ids: tuple[int, ...], wheels: tuple[int, ...], *, eds: str | Path | None = None,
                 counts_per_rev: int | None = None, tpdo_period_ms: int = 10, heartbeat_ms: int = 100,
                 heartbeat_timeout_factor: float = 3.0, data_timeout_s: float = 0.25, sdo_timeout_s: float = 0.3,
                 sdo_retries: int = 2, reset_period_s: float = 1.0) -> None:
        super().__init__(wheels)
        if len(node_ids) != len(wheels):
            raise ValueError("one CANopen node id per wheel")
        if any(not 1 <= n <= 127 for n in node_ids):
            raise ValueError(f"CANopen node ids are 1..127, got {node_ids}")
        self.eds = Path(eds) if eds else DEFAULT_EDS
        if not self.eds.is_file():
            raise ValueError(f"EDS file not found: {self.eds}")
        self.od_counts_per_rev = counts_per_rev
        self.tpdo_period_ms, self.heartbeat_ms = int(tpdo_period_ms), int(heartbeat_ms)
        self.sdo_timeout_s, self.sdo_retries = float(sdo_timeout_s), int(sdo_retries)
        self.reset_period_ns = int(reset_period_s * 1e9)
        self.nodes = {n: _Node(n, w) for n, w in zip(node_ids, wheels, strict=True)}
        self._by_cob: dict[int, _Node] = {}  # heartbeat, EMCY and SDO response COB-IDs
        self._tpdo: dict[int, _Node] = {}  # position TPDO COB-IDs, known once configured
        self.heartbeats = HeartbeatWatchdog(heartbeat_timeout_factor * heartbeat_ms / 1000.0)
        self.data = HeartbeatWatchdog(data_timeout_s)
        self.network: canopen.Network | None = None
        self._bus: CanBus | None = None
        self._todo: queue.Queue[_Node | None] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()

    # -- life cycle ----------------------------------------------------------------------------
    def start(self, bus: CanBus, now_ns: int) -> None:
        """Build a fresh canopen network on ``bus`` and queue every node for configuration."""
        self._bus = bus
        self.network = canopen.Network(bus)  # type: ignore[arg-type]  # only .send() is used
        self.heartbeats.reset()
        self.data.reset()
        self._by_cob, self._tpdo = {}, {}
        for node in self.nodes.values():
            node.remote = canopen.RemoteNode(node.id, str(self.eds))
            node.remote.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
            node.remote.sdo.MAX_RETRIES = self.sdo_retries
            self.network.add_node(node.remote)
            node.configured = node.queued = False
            node.state = None
            node.next_reset_ns = now_ns
            self._by_cob[HEARTBEAT + node.id] = node
            self._by_cob[EMCY + node.id] = node
            self._by_cob[SDO_TX + node.id] = node
        self._stop.clear()
        self._todo = queue.Queue()
        for node in self.nodes.values():
            self._queue(node)
        self._worker = threading.Thread(target=self._configure_loop, name="cia406-config", daemon=True)
        self._worker.start()

    def stop(self) -> None:
        self._stop.set()
        self._todo.put(None)
        if self._worker is not None:
            self._worker.join(5.0)
            self._worker = None

    # -- receive -------------------------------------------------------------------------------
    def handle(self, msg: can.Message, now_ns: int) -> list[WheelReading]:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return []
        cob = msg.arbitration_id
        node = self._by_cob.get(cob)
        if node is not None:
            base = cob - node.id
            if base == SDO_TX and self.network is not None:
                self.network.notify(cob, msg.data, msg.timestamp)
            elif base == HEARTBEAT:
                self._on_heartbeat(node, decode_heartbeat(msg.data), now_ns)
            elif base == EMCY:
                code, _ = decode_emcy(msg.data)
                self.counters["emergencies"] += 1 if code else 0
            return []
        node = self._tpdo.get(cob)
        if node is None:
            return []
        position = node.layout.decode(msg.data)
        self.data.beat(node.id, now_ns)
        return [WheelReading(node.wheel, position, modulus=node.modulus)]

    def _on_heartbeat(self, node: _Node, state: int, now_ns: int) -> None:
        self.heartbeats.beat(node.id, now_ns)
        previous, node.state = node.state, state
        if state == BOOT_UP:
            # rebooted or reset: its communication settings are back to defaults
            if node.configured:
                self.counters["reboots"] += 1
            node.configured = False
            self._queue(node)
        elif state in (STOPPED, PRE_OPERATIONAL) and node.configured and previous != state:
            self._nmt(NMT_START, node.id)

    def healthy_wheels(self, now_ns: int) -> set[int]:
        return {n.wheel for n in self.nodes.values()
                if n.configured and n.state == OPERATIONAL and self.heartbeats.alive(n.id, now_ns)
                and self.data.alive(n.id, now_ns)}

    def poll(self, now_ns: int) -> None:
        self.counters["heartbeat_losses"] += len(self.heartbeats.check(now_ns))
        self.counters["data_losses"] += len(self.data.check(now_ns))
        for node in self.nodes.values():
            silent = node.id in self.heartbeats.last_ns and not self.heartbeats.alive(node.id, now_ns)
            if silent and now_ns >= node.next_reset_ns:
                node.next_reset_ns = now_ns + self.reset_period_ns
                self.counters["resets_sent"] += 1
                self._nmt(NMT_RESET_COMMUNICATION, node.id)

    def _nmt(self, command: int, node_id: int) -> None:
        if self._bus is not None:
            self._bus.send(can.Message(arbitration_id=NMT, data=bytes((command, node_id)), is_extended_id=False))

    # -- configuration (worker thread; SDO replies arrive through handle) ----------------------
    def _queue(self, node: _Node) -> None:
        if not node.queued:
            node.queued = True
            self._todo.put(node)

    def _configure_loop(self) -> None:
        while not self._stop.is_set():
            node = self._todo.get()
            if node is None:
                return
            try:
                self._configure(node)
                self.counters["configured"] += 1
            except (SdoCommunicationError, SdoAbortedError, DeviceError, can.CanError, OSError, ValueError) as error:
                self.counters["config_failures"] += 1
                log.info("CiA 406 node %d not configured: %s", node.id, error)
                node.queued = False
                # a silent node is reset by poll(); its boot-up requeues it. A node that answers
                # but refuses is retried after the reset period.
                if not self._stop.wait(self.reset_period_ns / 1e9):
                    self._queue(node)
                continue
            node.queued = False

    def _configure(self, node: _Node) -> None:
        remote = node.remote
        assert remote is not None
        self._nmt(NMT_PRE_OPERATIONAL, node.id)
        remote.sdo[HEARTBEAT_TIME].raw = self.heartbeat_ms
        device_type = remote.sdo[0x1000].raw
        if device_type & 0xFFFF != PROFILE_406:
            self.counters["not_cia406"] += 1
        if self.od_counts_per_rev:
            remote.sdo[UNITS_PER_REV].raw = int(self.od_counts_per_rev)
        counts = int(remote.sdo[UNITS_PER_REV].raw)
        total = int(remote.sdo[TOTAL_RANGE].raw)
        if counts <= 0:
            raise ProtocolError(f"node {node.id} reports {counts} units per revolution")
        pdo = remote.tpdo[1]
        pdo.read()
        pdo.clear()
        pdo.add_variable(POSITION_VALUE)
        pdo.trans_type = 254
        pdo.event_timer = self.tpdo_period_ms
        pdo.enabled = True
        pdo.save()
        with contextlib.suppress(SdoAbortedError, KeyError):  # an optional object
            remote.sdo[CYCLIC_TIMER].raw = self.tpdo_period_ms
        var = pdo.map[0]
        node.layout = PositionLayout(var.offset // 8, var.length // 8, var.od.data_type in _SIGNED)
        node.modulus = total if total > 1 else 2**32
        self.counts_per_rev[node.wheel] = float(counts)
        self._tpdo[pdo.cob_id] = node
        node.configured = True
        self._nmt(NMT_START, node.id)

    def diagnostics(self) -> list[tuple[str, str]]:
        names = {BOOT_UP: "boot-up", STOPPED: "stopped", OPERATIONAL: "operational", PRE_OPERATIONAL: "pre-operational"}
        values = super().diagnostics()
        for node in self.nodes.values():
            state = names.get(node.state, "silent") if node.state is not None else "silent"
            values.append((f"cia406.{node.id}", f"{state}{'' if node.configured else ', unconfigured'}"))
        return values
