"""The MJPEG stream codec: multipart/x-mixed-replace bodies cut into parts as mjpg-streamer and IP
cameras send them, whatever the split of the bytes; arbitrary bytes never crash it or make it hold
more than its limits."""

from __future__ import annotations

from unittest import mock

from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.drivers import mjpeg_parts
from trundle.drivers.mjpeg_parts import MultipartParser, Part, x_timestamp_ns

# as mjpg-streamer's output_http writes a stream (httpd.c send_stream): the first delimiter ends the
# response's own header block, each part is followed by CRLF and the next delimiter
MJPG_STREAMER = (b"--boundarydonotcross\r\n"
                 b"Content-Type: image/jpeg\r\nContent-Length: 6\r\nX-Timestamp: 1764675000.012345\r\n\r\n"
                 b"\xff\xd8ab\xff\xd9\r\n--boundarydonotcross\r\n"
                 b"Content-Type: image/jpeg\r\nContent-Length: 4\r\nX-Timestamp: 1764675000.045678\r\n\r\n"
                 b"\xff\xd8\xff\xd9\r\n--boundarydonotcross\r\n")


def parse(data: bytes, cuts: list[int], boundary: str = "B") -> tuple[list[Part], Part | None, int]:
    """Parts, the cut-off part and the skipped count of ``data`` fed in pieces split at ``cuts``."""
    parser = MultipartParser(boundary)
    parts: list[Part] = []
    points = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    for a, b in zip(points, points[1:], strict=False):
        parts += parser.feed(data[a:b])
    return parts, parser.finish(), parser.skipped_parts


def test_mjpg_streamer_parts_with_their_capture_times() -> None:
    parts, cut, skipped = parse(MJPG_STREAMER, [], "boundarydonotcross")
    assert [p.body for p in parts] == [b"\xff\xd8ab\xff\xd9", b"\xff\xd8\xff\xd9"]
    assert [x_timestamp_ns(p.headers["x-timestamp"]) for p in parts] == [1764675000_012345000, 1764675000_045678000]
    assert parts[0].headers["content-type"] == "image/jpeg" and cut is None and skipped == 0


def test_parts_without_a_length_run_to_the_next_delimiter() -> None:
    data = (b"preamble\r\n--B\r\nContent-Type: image/jpeg\r\n\r\nline\r\nmore\r\n--B  \n\nlast\n"
            b"--B--\r\nepilogue --B\r\n\r\nignored")
    parts, cut, _ = parse(data, [])
    assert [(p.headers, p.body) for p in parts] == [({"content-type": "image/jpeg"}, b"line\r\nmore"), ({}, b"last")]
    assert cut is None


def test_a_part_cut_off_by_the_end_of_the_stream_is_given_as_it_came() -> None:
    parts, cut, _ = parse(b"--B\r\nContent-Length: 10\r\n\r\n\xff\xd8abc", [7])
    assert parts == [] and cut == Part({"content-length": "10"}, b"\xff\xd8abc")


def test_the_boundary_inside_other_text_is_not_a_delimiter() -> None:
    parts, _, _ = parse(b"--B\r\n\r\nx--BB\r\ny\r\n--Bz\r\n--B\r\n", [3, 9])
    assert [p.body for p in parts] == [b"x--BB\r\ny\r\n--Bz"]


def test_x_timestamp_values() -> None:
    assert x_timestamp_ns("1764675000.012345") == 1764675000_012345000
    assert x_timestamp_ns(" 12 ") == 12_000_000_000 and x_timestamp_ns("3.5") == 3_500_000_000
    assert [x_timestamp_ns(v) for v in ("", "-1.0", "1e9", "abc", "1.", "1.0123456789")] == [None] * 6


def test_over_long_headers_and_bodies_are_skipped_whole() -> None:
    with mock.patch.multiple(mjpeg_parts, MAX_HEADER_BYTES=30, MAX_BODY_BYTES=8):
        data = (b"--B\r\nX-Long: " + b"a" * 40 + b"\r\n\r\nbody\r\n--B\r\nContent-Length: 9\r\n\r\n123456789\r\n"
                b"--B\r\n\r\n0123456789\r\n--B\r\nContent-Length: 3\r\n\r\nok!\r\n")
        parts, _, skipped = parse(data, [])
    assert [p.body for p in parts] == [b"ok!"] and skipped == 3


pieces = st.sampled_from([b"--B", b"--B--", b"\r\n", b"\n", b"\r", b" ", b"-", b":", b"Content-Length: 3",
                          b"Content-Length: 40", b"Content-Length: x", b"X-Timestamp: 1.5", b"abc", b"\xff\xd8"])
whole_parts = st.tuples(st.sampled_from([b"--B\r\n", b"--B \n"]), st.sampled_from([b"", b"X-Timestamp: 2.25\r\n"]),
                        st.binary(max_size=20), st.booleans()).map(
    lambda p: p[0] + p[1] + (b"Content-Length: %d\r\n" % len(p[2]) if p[3] else b"") + b"\r\n" + p[2] + b"\r\n")
streams = st.one_of(st.binary(max_size=400), st.lists(pieces, max_size=60).map(b"".join),
                    st.lists(st.one_of(whole_parts, pieces), max_size=20).map(b"".join))


@settings(max_examples=400, deadline=None)
@given(streams, st.lists(st.integers(min_value=0, max_value=10_000), max_size=12))
def test_any_bytes_at_any_split_give_the_same_parts(data: bytes, cuts: list[int]) -> None:
    with mock.patch.multiple(mjpeg_parts, MAX_HEADER_BYTES=24, MAX_BODY_BYTES=16, MAX_PADDING=3):
        whole = parse(data, [])
        split = parse(data, cuts)
        bytewise = parse(data, list(range(len(data))))
    assert split == whole and bytewise == whole
    assert all(len(p.body) <= 16 for p in whole[0])


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.binary(min_size=0, max_size=50), st.booleans()), max_size=8),
       st.lists(st.integers(min_value=0, max_value=10_000), max_size=12))
def test_well_formed_streams_give_their_bodies_byte_for_byte(bodies: list[tuple[bytes, bool]], cuts: list[int]) -> None:
    data = b""
    for body, with_length in bodies:
        length = f"Content-Length: {len(body)}\r\n".encode() if with_length else b""
        data += b"--trundleframe\r\nContent-Type: image/jpeg\r\n" + length + b"\r\n" + body + b"\r\n"
    data += b"--trundleframe--\r\n"
    parts, cut, skipped = parse(data, cuts, "trundleframe")
    expected = [body for body, _ in bodies]
    assert [p.body for p in parts] == expected or any(b"--trundleframe" in b for b in expected)
    assert cut is None and skipped == 0


def test_garbage_does_not_grow_the_buffer() -> None:
    parser = MultipartParser("B")
    for _ in range(1000):
        assert parser.feed(b"x" * 1000 + b"--") == []
    assert len(parser._buf) <= len(parser.delimiter) + mjpeg_parts.MAX_PADDING + 2
