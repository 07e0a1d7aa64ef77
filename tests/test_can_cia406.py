"""CiA 406 over CANopen: codec examples, the configuration on the wire checked against CiA 301
byte layouts, and fuzzing of the frame decoder."""

from __future__ import annotations

import time

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.can_rig import can_rig
from trundle.drivers import cia406
from trundle.drivers.cia406 import PositionLayout, decode_emcy, decode_heartbeat


def test_heartbeat_states():
    assert [decode_heartbeat(bytes((b,))) for b in (0x00, 0x04, 0x05, 0x7F, 0x85, 0xFF)] == [0, 4, 5, 127, 5, 127]
    for bad in (b"", b"\x01", b"\x42"):
        with pytest.raises(ValueError):
            decode_heartbeat(bad)


def test_position_and_emcy_layouts():
    assert PositionLayout().decode(bytes.fromhex("79000000")) == 0x79
    assert PositionLayout(offset=2, size=4, signed=True).decode(bytes.fromhex("AAAAFFFFFFFF")) == -1
    assert PositionLayout(offset=0, size=4, signed=False).decode(bytes.fromhex("FFFFFFFF")) == 2**32 - 1
    with pytest.raises(ValueError):
        PositionLayout().decode(b"\x01\x02\x03")
    assert decode_emcy(bytes.fromhex("1023010000000000")) == (0x2310, 1)


@pytest.fixture(scope="module")
def configured(tmp_path_factory):
    """A CiA 406 node configured by the wheels driver on a virtual bus, with a sniffer on the bus."""
    with can_rig(tmp_path_factory.mktemp("cia"), "cia406", "virtual", "0:0.25,0.25") as rig:
        protocol = rig.driver.protocols[0]
        assert rig.wait_for(lambda: len(rig.topic("/odom")) > 5)
        sniffer = can.Bus(interface="virtual", channel=rig.driver.bus.spec.channel)
        rig.driver.stop()
        configured = protocol.counters["configured"]
        rig.driver.start()  # configure again with the sniffer listening
        assert rig.wait_for(lambda: protocol.counters["configured"] == configured + 2)
        time.sleep(0.2)
        frames = []
        while (msg := sniffer.recv(0)) is not None:
            frames.append(msg)
        sniffer.shutdown()
        rig.driver.stop()
        rig.driver.bus.open()  # for the decoder's own NMT commands during fuzzing
        yield rig, frames
        rig.driver.bus.close()


def test_configuration_on_the_wire(configured):
    _, frames = configured
    wire = [(f.arbitration_id, bytes(f.data).hex()) for f in frames if f.arbitration_id in (0x000, 0x605, 0x585)]
    # CiA 301: NMT [cs, node]; expedited download 2B = 2 data bytes; upload request 40; response 43 = 4 bytes
    assert (0x000, "8005") in wire
    assert (0x605, "2b17100064000000") in wire and (0x585, "6017100000000000") in wire  # 0x1017 = 100 ms
    assert (0x605, "4001600000000000") in wire and (0x585, "4301600000100000") in wire  # 0x6001 = 4096
    assert (0x605, "4002600000000000") in wire and (0x585, "4302600000000001") in wire  # 0x6002 = 2**24
    assert (0x605, "2b0018050a000000") in wire  # TPDO1 event timer 10 ms
    assert (0x605, "23001a0120000460") in wire  # TPDO1 entry 1 = 0x6004 sub 0, 32 bits
    assert wire.index((0x000, "0105")) > wire.index((0x605, "23001a0120000460"))  # started last
    tpdos = [f for f in frames if f.arbitration_id == 0x185]
    assert len(tpdos) > 5 and all(len(f.data) == 4 for f in tpdos)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from([0x185, 0x186, 0x705, 0x706, 0x085, 0x585, 0x000, 0x123]), st.binary(max_size=8))
def test_decoder_refuses_corrupt_frames_with_valueerror_only(configured, cob_id, data):
    rig, _ = configured
    protocol = rig.driver.protocols[0]
    try:
        readings = protocol.handle(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False), 0)
    except ValueError:
        return
    for reading in readings:
        assert reading.modulus == 2**24 and isinstance(reading.position, int) and 0 <= reading.position < 2**32


def test_defaults_come_from_the_eds():
    protocol = cia406.Cia406Encoders((5,), (0,))
    assert protocol.eds == cia406.DEFAULT_EDS and protocol.eds.is_file()
    with pytest.raises(ValueError):
        cia406.Cia406Encoders((0,), (0,))
