"""Generic DBC encoders (cantools): the VESC status example bytes, counter unwrapping at the
signal width, float signals, configuration errors and fuzzing."""

from __future__ import annotations

import math

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.can_rig import VESC_DBC
from trundle.drivers.dbc_wheels import DbcWheels

SIGNALS = ["VESC_Status5_id9.Tachometer", "VESC_Status5_id10.Tachometer"]
VELOCITIES = ["VESC_Status1_id9.ERPM", "VESC_Status1_id10.ERPM"]


def ext(can_id: int, hex_data: str) -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes.fromhex(hex_data), is_extended_id=True)


@pytest.fixture
def vesc():
    return DbcWheels(VESC_DBC, SIGNALS, (0, 1), units_per_rev=42, velocity_signals=VELOCITIES, velocity_scale=1 / 420)


def test_vesc_status_example_decodes_with_the_shipped_dbc():
    # comm_can.md: STATUS from VESC 9, ERPM 12000, 12.3 A, duty 0.456 -> id 0x909, 00 00 2E E0 00 7B 01 C8
    db = cantools.database.load_file(str(VESC_DBC))
    decoded = db.decode_message(0x909, bytes.fromhex("00002EE0007B01C8"))
    assert decoded == {"ERPM": 12000, "Current": pytest.approx(12.3), "Duty": pytest.approx(0.456)}


def test_positions_and_velocities(vesc):
    assert vesc.handle(ext(0x909, "00002EE0007B01C8"), 0) == []  # velocity only: cached
    (reading,) = vesc.handle(ext(0x1B09, "0000002A01F40000"), 0)  # tachometer 42, 50.0 V
    assert (reading.wheel, reading.position, reading.modulus) == (0, 42, 2**32)
    assert reading.velocity == pytest.approx(12000 / 420 * 42)  # counts/s
    assert vesc.counts_per_rev == {0: 42.0, 1: 42.0}
    (right,) = vesc.handle(ext(0x1B0A, "FFFFFFFE00000000"), 0)
    assert (right.wheel, right.position) == (1, -2) and math.isnan(right.velocity)
    assert vesc.handle(can.Message(arbitration_id=0x1B09, data=bytes(8), is_extended_id=False), 0) == []
    with pytest.raises(ValueError):
        vesc.handle(ext(0x1B09, "0000"), 0)


def test_float_position_signal(tmp_path):
    dbc = tmp_path / "motor.dbc"
    dbc.write_text('VERSION ""\nBS_:\nBU_: M\nBO_ 100 Motor: 8 M\n'
                   ' SG_ Turns : 0|32@1- (1,0) [0|0] "turns" Vector__XXX\n'
                   ' SG_ Speed : 32|32@1- (1,0) [0|0] "turns/s" Vector__XXX\n'
                   'SIG_VALTYPE_ 100 Turns : 1;\nSIG_VALTYPE_ 100 Speed : 1;\n')
    wheels = DbcWheels(dbc, ["Motor.Turns"], (0,), velocity_signals=["Motor.Speed"])
    (reading,) = wheels.handle(can.Message(arbitration_id=100, data=bytes.fromhex("0000C03F000080BE"),
                                           is_extended_id=False), 0)
    assert (reading.position, reading.velocity, reading.modulus) == (1.5, -0.25, None)
    with pytest.raises(ValueError):
        wheels.handle(can.Message(arbitration_id=100, data=bytes.fromhex("0000C07F00000000"), is_extended_id=False), 0)


def test_configuration_errors():
    with pytest.raises(ValueError, match="no signal"):
        DbcWheels(VESC_DBC, ["VESC_Status5_id9.Tacho"], (0,))
    with pytest.raises(ValueError, match="Message.Signal"):
        DbcWheels(VESC_DBC, ["Tachometer"], (0,))
    with pytest.raises(ValueError, match="cannot read"):
        DbcWheels("/nonexistent.dbc", ["A.b"], (0,))
    with pytest.raises(ValueError, match="units_per_rev"):
        DbcWheels(VESC_DBC, SIGNALS, (0, 1), units_per_rev=[42])
    with pytest.raises(ValueError, match="one velocity signal per wheel"):  # wheel 1 would have no speed
        DbcWheels(VESC_DBC, SIGNALS, (0, 1), velocity_signals=VELOCITIES[:1])


FUZZED = DbcWheels(VESC_DBC, SIGNALS, (0, 1), units_per_rev=42, velocity_signals=VELOCITIES)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([0x909, 0x90A, 0x1B09, 0x1B0A, 0x123]), st.binary(max_size=8))
def test_decoder_refuses_corrupt_frames_with_valueerror_only(can_id, data):
    wheels = FUZZED
    try:
        readings = wheels.handle(ext(can_id, data.hex()), 0)
    except ValueError:
        return
    assert all(-(2**31) <= r.position < 2**31 for r in readings)
