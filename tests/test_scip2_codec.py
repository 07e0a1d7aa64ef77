"""SCIP 2.0 codec against the protocol's own byte examples, plus fuzzing of the decoder."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.lrf_harness import MUTATIONS, mutate
from trundle.drivers import scip2
from trundle.drivers.scip2 import Measure, Reply, ScipError, ScipFramer

# Byte-exact lines published for real sensors (lrf-protocols.md section 1.5, checksums included).
URG_PP = [b"MODL:URG-04LX(Hokuyo Automatic Co.,Ltd.);N", b"DMIN:20;4", b"DMAX:5600;_", b"ARES:1024;\\",
          b"AMIN:44;7", b"AMAX:725;o", b"AFRT:384;6", b"SCAN:600;e"]
URG_VV = [b"VEND:Hokuyo Automatic Co.,Ltd.;[", b"PROD:SOKUIKI Sensor URG-04LX;[", b"FIRM:3.1.00(18/Jan./2007);`",
          b"PROT:SCIP 2.0;N", b"SERI:H0614967;V"]
URG_II = [b"LASR:OFF;7", b"MESM:IDLE;:", b"TIME:081615;N", b"STAT:Sensor works well.;8"]
UTM_PP = [b"MODL:UTM-30LX-EW;I", b"DMIN:23;7", b"DMAX:60000;J", b"ARES:1440;^", b"AMIN:0;?", b"AMAX:1080;Z",
          b"AFRT:540;0", b"SCAN:2400;U"]


def reply_of(echo: bytes, status_line: bytes, lines: list[bytes]) -> Reply:
    framer = ScipFramer()
    framer.expect(echo)
    replies = framer.feed(echo + b"\n" + status_line + b"\n" + b"".join(line + b"\n" for line in lines) + b"\n")
    assert len(replies) == 1
    return replies[0]


def test_encodings_from_the_specification():
    assert scip2.encode_values([1234], 2) == b"CB"
    assert scip2.encode_values([5432], 3) == b"1Dh"
    assert scip2.encode_values([16_000_000], 4) == b"m2@0"
    assert scip2.decode_values(b"CB", 2).tolist() == [1234]
    assert scip2.decode_values(b"1Dh", 3).tolist() == [5432]
    assert scip2.decode_values(b"m2@0", 4).tolist() == [16_000_000]


@pytest.mark.parametrize("line,status", [(b"00P", "00"), (b"99b", "99"), (b"01Q", "01"), (b"02R", "02"),
                                         (b"10Q", "10"), (b"0Ee", "0E"), (b"0Ll", "0L"), (b"0Mm", "0M")])
def test_status_line_sums(line, status):
    assert scip2.with_checksum(status.encode()) == line
    assert reply_of(b"QT", line, []).status == status


def test_published_key_value_lines_sum_without_the_semicolon():
    for line in URG_PP + URG_VV + URG_II + UTM_PP:
        key_value, sum_char = line[:-2], line[-1]
        assert scip2.checksum(key_value) == sum_char
        assert scip2.checksum(line[:-1]) != sum_char  # the ";" is not covered


def test_pp_replies_parse_to_the_model_table():
    urg = scip2.SensorParams.from_info(scip2.parse_info(reply_of(b"PP", b"00P", URG_PP)))
    assert (urg.model, urg.dmin, urg.dmax, urg.ares, urg.amin, urg.amax, urg.afrt, urg.rpm) == (
        "URG-04LX(Hokuyo Automatic Co.,Ltd.)", 20, 5600, 1024, 44, 725, 384, 600)
    utm = scip2.SensorParams.from_info(scip2.parse_info(reply_of(b"PP", b"00P", UTM_PP)))
    assert (utm.dmin, utm.dmax, utm.ares, utm.amin, utm.amax, utm.afrt, utm.rpm) == (
        23,
        60000,
        1440,
        0,
        1080,
        540,
        2400,
    )
    assert utm.scan_period_s == pytest.approx(0.025)
    # URG-04LX step 44 = -119.53 deg, step 725 = +119.88 deg (spec geometry)
    assert np.degrees(urg.step_angle(44)) == pytest.approx(-119.53, abs=0.01)
    assert np.degrees(urg.step_angle(725)) == pytest.approx(119.88, abs=0.01)
    assert scip2.encode_info(utm.info()) == b"".join(line + b"\n" for line in UTM_PP)


def test_vv_and_ii_parse():
    vv = scip2.parse_info(reply_of(b"VV", b"00P", URG_VV))
    assert vv["SERI"] == "H0614967" and vv["PROT"] == "SCIP 2.0" and vv["FIRM"] == "3.1.00(18/Jan./2007)"
    ii = scip2.parse_info(reply_of(b"II", b"00P", URG_II))
    assert ii["STAT"] == "Sensor works well." and ii["TIME"] == "081615"


def test_firmware_that_sums_the_semicolon_is_tolerated_but_data_lines_are_strict():
    wrong = b"SERI:H0614967;" + bytes((scip2.checksum(b"SERI:H0614967;"),))
    assert scip2.parse_info(reply_of(b"VV", b"00P", [wrong]))["SERI"] == "H0614967"
    with pytest.raises(ScipError) as error:
        scip2.parse_info(reply_of(b"VV", b"00P", [b"SERI:H0614967;X"]))
    assert error.value.kind == "checksum"
    with pytest.raises(ScipError):
        scip2.verify_line(b"0?X0?Y0?Z" + bytes((scip2.checksum(b"0?X0?Y0?"),)))


def test_worked_md_example_from_the_notes():
    measure = Measure("MD", 44, 46, 1, 0, 2)
    assert measure.encode() == b"MD0044004601002\n"
    stream = b"MD0044004601002\n00P\n\n" + b"MD0044004601001\n99b\nm2@0?\n0?X0?Y0?ZH\n\n"
    assert scip2.encode_reply(measure.echo(), "00") == b"MD0044004601002\n00P\n\n"
    assert scip2.encode_scan(measure, 16_000_000, [1000, 1001, 1002], remaining=1) == stream[21:]
    framer = ScipFramer()
    framer.expect(measure.echo(), measure.echo(1))
    ack, scan_reply = framer.feed(stream)
    assert ack.status == "00" and ack.lines() == []
    scan = scip2.decode_scan(scan_reply, measure)
    assert scan.timestamp == 16_000_000 and scan.distances.tolist() == [1000, 1001, 1002] and scan.remaining == 1
    assert scan.intensities is None
    assert framer.resyncs == 0


@pytest.mark.parametrize("command,start,end,lines,last", [("MD", 44, 725, 32, 62), ("MD", 0, 1080, 51, 43),
                                                          ("ME", 0, 1080, 102, 22), ("MS", 0, 1080, 34, 50)])
def test_full_scans_straddle_lines(command, start, end, lines, last):
    measure = Measure(command, start, end)
    rng = np.random.default_rng(1)
    width_max = 4095 if command == "MS" else 60000
    distances = rng.integers(0, width_max, measure.beams)
    intensities = rng.integers(0, 10000, measure.beams) if measure.intensity else None
    raw = scip2.encode_scan(measure, 123, distances, intensities, remaining=0)
    data_lines = raw.split(b"\n")[3:-2]
    assert len(data_lines) == lines and len(data_lines[-1]) == last + 1
    assert all(len(line) == 65 for line in data_lines[:-1])
    framer = ScipFramer()
    framer.expect(measure.echo())
    scan = scip2.decode_scan(framer.feed(raw)[0], measure)
    np.testing.assert_array_equal(scan.distances, distances)
    if intensities is not None:
        np.testing.assert_array_equal(scan.intensities, intensities)


def test_cluster_and_beam_count():
    assert Measure("MD", 0, 1080, 3).beams == 361
    assert Measure("MD", 0, 1080, 0).beams == 1081 == Measure("MD", 0, 1080, 1).beams
    assert Measure.from_echo(b"MD0044072501003;abc") == Measure("MD", 44, 725, 1, 0, 3, "abc")
    assert Measure.from_echo(b"GE0000108001") == Measure("GE", 0, 1080, 1)
    with pytest.raises(ScipError):
        Measure.from_echo(b"MD00440725")
    with pytest.raises(ValueError):
        scip2.encode_command("MD", "0044072501000", "x" * 17)


def test_each_defect_has_its_kind():
    measure = Measure("MD", 0, 1080)
    raw = scip2.encode_scan(measure, 5, np.full(1081, 1234), remaining=0)
    framer = ScipFramer()
    framer.expect(measure.echo())

    def kind(stream: bytes) -> str:
        (reply,) = framer.feed(stream)
        with pytest.raises(ScipError) as error:
            scip2.decode_scan(reply, measure)
        return error.value.kind

    at = raw.index(b"\n", 30) + 10  # inside the first data line
    assert kind(raw[:at] + bytes((raw[at] + 1,)) + raw[at + 1:]) == "checksum"
    assert kind(raw[:at] + raw[at + 5:]) == "truncated"
    assert kind(raw[:at] + b"\x80" + raw[at + 1:]) in ("checksum", "format")
    assert kind(scip2.encode_reply(measure.echo(), "0M")) == "status"


def test_framer_resyncs_on_garbage_and_cut_replies():
    measure = Measure("MD", 0, 10, string="T1")
    one = scip2.encode_scan(measure, 1, np.arange(11), remaining=0)
    two = scip2.encode_scan(measure, 2, np.arange(11) + 5, remaining=0)
    framer = ScipFramer()
    framer.expect(measure.echo())
    replies = framer.feed(b"\x00garbage\nwith\n\nlines" + one + b"noise" + two)
    assert [scip2.decode_scan(r, measure).timestamp for r in replies] == [1, 2]
    assert framer.resyncs == 2 and framer.garbage_bytes == len(b"\x00garbage\nwith\n\nlines") + 5
    # A reply that lost its end is cut where the next one starts; the next one survives.
    replies = framer.feed(one[:-30] + b"\n" + two)
    assert len(replies) == 2
    with pytest.raises(ScipError):
        scip2.decode_scan(replies[0], measure)
    assert scip2.decode_scan(replies[1], measure).timestamp == 2
    # Replies of an earlier session (other string) are not taken for ours.
    stale = scip2.encode_scan(Measure("MD", 0, 10, string="T0"), 9, np.arange(11), remaining=0)
    assert [scip2.decode_scan(r, measure).timestamp for r in framer.feed(stale + one)] == [1]


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_framer_is_independent_of_chunking(data):
    measure = Measure("ME", 0, 200)
    rng = np.random.default_rng(data.draw(st.integers(0, 1000)))
    stream = b"".join(scip2.encode_scan(measure, t, rng.integers(0, 60000, 201), rng.integers(0, 9999, 201),
                                        remaining=0) for t in range(3))
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=20)))
    framer = ScipFramer()
    framer.expect(measure.echo())
    replies = []
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        replies += framer.feed(stream[a:b])
    assert [scip2.decode_scan(r, measure).timestamp for r in replies] == [0, 1, 2]
    assert framer.resyncs == 0


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000), st.lists(st.binary(min_size=1, max_size=20), max_size=3))
def test_random_bytes_never_raise_out_of_the_decoder(noise, echoes):
    framer = ScipFramer(max_reply=1024)
    framer.expect(b"MD0000001001000", *echoes)
    measure = Measure("MD", 0, 10)
    for reply in framer.feed(noise) + framer.feed(b"MD0000001001000\n" + noise):
        try:
            _ = reply.status
            scip2.decode_scan(reply, measure)
            scip2.parse_info(reply)
        except ScipError:
            pass


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 10_000), st.sampled_from(MUTATIONS), st.integers(0, 255),
       st.integers(0, 2**32))
def test_one_mutation_never_yields_a_wrong_scan(seed, how, value, where):
    measure = Measure("MD", 0, 300, string="S1")
    rng = np.random.default_rng(seed)
    sent = {t: rng.integers(0, 60000, measure.beams) for t in range(4)}
    stream = bytearray(b"".join(scip2.encode_scan(measure, t, d, remaining=0) for t, d in sent.items()))
    mutate(stream, how, where, value)
    framer = ScipFramer()
    framer.expect(measure.echo())
    good = 0
    for reply in framer.feed(bytes(stream)):
        try:
            scan = scip2.decode_scan(reply, measure)
        except ScipError:
            continue
        good += 1
        np.testing.assert_array_equal(scan.distances, sent[scan.timestamp])
    assert good >= 3
