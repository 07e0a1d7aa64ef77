"""ODrive CAN Simple codec: protocol byte examples, a third-party decoder, fuzzing."""

from __future__ import annotations

import math
import struct

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers import odrive

# Get_Encoder_Estimates and the 0.5.x heartbeat as the CAN Simple protocol table defines them
# (little-endian floats / u32 + u8 flags), in DBC form for cantools to decode independently.
DBC = """VERSION ""
BS_:
BU_: ODrive
BO_ 9 Get_Encoder_Estimates: 8 ODrive
 SG_ Pos_Estimate : 0|32@1- (1,0) [0|0] "turns" Vector__XXX
 SG_ Vel_Estimate : 32|32@1- (1,0) [0|0] "turns/s" Vector__XXX
BO_ 1 Heartbeat: 8 ODrive
 SG_ Axis_Error : 0|32@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Axis_State : 32|8@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Motor_Error_Flag : 40|1@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Encoder_Error_Flag : 48|1@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Controller_Error_Flag : 56|1@1+ (1,0) [0|0] "" Vector__XXX
 SG_ Trajectory_Done_Flag : 63|1@1+ (1,0) [0|0] "" Vector__XXX
SIG_VALTYPE_ 9 Pos_Estimate : 1;
SIG_VALTYPE_ 9 Vel_Estimate : 1;
"""


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_string(DBC, "dbc")


def test_ids_follow_node_shl_5_or_cmd():
    assert odrive.arbitration_id(3, odrive.GET_ENCODER_ESTIMATES) == 0x069
    assert odrive.split_id(0x069) == (3, 9)
    assert odrive.arbitration_id(0x3F, 0x1F) == 0x7FF
    with pytest.raises(ValueError):
        odrive.arbitration_id(64, 1)


def test_encoder_estimates_byte_example():
    # ODrive node 3 replies t06980000C03F000080BE: pos 1.5 turns, vel -0.25 turns/s
    data = bytes.fromhex("0000C03F000080BE")
    assert odrive.decode_encoder_estimates(data) == (1.5, -0.25)
    assert odrive.encode_encoder_estimates(1.5, -0.25) == data


def test_heartbeat_byte_example():
    # Axis0_Heartbeat 01 00 00 00 0B 00 00 00: axis error 0x1 (INVALID_STATE), state 11 (HOMING)
    hb = odrive.decode_heartbeat(bytes.fromhex("010000000B000000"))
    assert (hb.axis_error, hb.axis_state, hb.flags, hb.healthy) == (1, 11, (0, 0, 0), False)
    hb6 = odrive.decode_heartbeat(bytes.fromhex("0000000008000100"), "0.6")
    assert (hb6.axis_state, hb6.flags) == (8, (0, 1, 0))
    with pytest.raises(ValueError):
        odrive.decode_heartbeat(b"\0" * 8, "0.4")


def test_encoder_count_is_signed():
    assert odrive.decode_encoder_count(struct.pack("<ii", -5, 8191)) == (-5, 8191)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(width=32, allow_nan=False, allow_infinity=False),
    st.floats(width=32, allow_nan=False, allow_infinity=False),
)
def test_estimates_agree_with_cantools(db, pos, vel):
    data = odrive.encode_encoder_estimates(pos, vel)
    ref = db.decode_message(9, data)
    assert odrive.decode_encoder_estimates(data) == (ref["Pos_Estimate"], ref["Vel_Estimate"])


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=8, max_size=8))
def test_heartbeat_agrees_with_cantools(db, data):
    ref = db.decode_message(1, data)
    hb = odrive.decode_heartbeat(data)
    assert (hb.axis_error, hb.axis_state) == (ref["Axis_Error"], ref["Axis_State"])
    assert (hb.flags[0] & 1, hb.flags[1] & 1, hb.flags[2] & 1, hb.flags[2] >> 7) == (
        ref["Motor_Error_Flag"], ref["Encoder_Error_Flag"], ref["Controller_Error_Flag"], ref["Trajectory_Done_Flag"])
    assert odrive.encode_heartbeat(hb) == data


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=8), st.sampled_from(odrive.FIRMWARES))
def test_decoders_fail_only_with_valueerror(data, firmware):
    for decode in (odrive.decode_encoder_estimates, odrive.decode_encoder_count, odrive.decode_axis_state,
                   odrive.decode_input_vel, lambda d: odrive.decode_heartbeat(d, firmware)):
        try:
            result = decode(data)
        except ValueError:
            continue
        if decode is odrive.decode_encoder_estimates:
            assert all(math.isfinite(v) for v in result)
