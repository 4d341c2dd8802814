"""Both ends of the MAVLink link parse bytes the same way: good frames out, the rest counted."""

from __future__ import annotations

import struct
from collections import Counter

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.mavlink.parse import LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED, parse_bytes


class _Sink:
    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data += data


def frame(seq: int = 0) -> bytes:
    sink = _Sink()
    tx = mavlink2.MAVLink(sink, srcSystem=1, srcComponent=1)
    tx.seq = seq
    tx.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0, 0)
    return sink.data


def parser() -> mavlink2.MAVLink:
    rx = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    rx.robust_parsing = True
    return rx


def test_good_frames_come_out_and_nothing_is_counted() -> None:
    rejections: Counter[str] = Counter()
    msgs = parse_bytes(parser(), frame(0) + frame(1), rejections, datagram=True)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "HEARTBEAT"]
    assert rejections == Counter()


def test_a_bad_crc_is_counted_and_the_next_frame_survives() -> None:
    bad = bytearray(frame(0))
    bad[-1] ^= 0xFF
    rejections: Counter[str] = Counter()
    msgs = parse_bytes(parser(), bytes(bad) + frame(1), rejections, datagram=True)
    assert [m.get_seq() for m in msgs] == [1]
    assert rejections["bad_data"] >= 1


def test_a_truncated_datagram_is_dropped_not_carried_into_the_next() -> None:
    rx, rejections = parser(), Counter()
    assert parse_bytes(rx, frame(0)[:-4], rejections, datagram=True) == []
    assert rejections["truncated"] == 1
    msgs = parse_bytes(rx, frame(1), rejections, datagram=True)
    assert [m.get_seq() for m in msgs] == [1]


def test_a_stream_keeps_a_partial_frame_for_the_next_bytes() -> None:
    rx, rejections = parser(), Counter()
    whole = frame(3)
    assert parse_bytes(rx, whole[:5], rejections, datagram=False) == []
    msgs = parse_bytes(rx, whole[5:], rejections, datagram=False)
    assert [m.get_seq() for m in msgs] == [3] and rejections == Counter()


def test_an_unknown_message_id_is_counted() -> None:
    raw = bytearray(frame(0))
    raw[7:10] = (60000).to_bytes(3, "little")  # a message id outside the dialect
    rejections: Counter[str] = Counter()
    assert parse_bytes(parser(), bytes(raw), rejections, datagram=True) == []
    assert sum(rejections.values()) == 1


@given(st.binary(max_size=600))
def test_any_bytes_never_raise_and_a_following_frame_still_parses(junk: bytes) -> None:
    rx, rejections = parser(), Counter()
    parse_bytes(rx, junk, rejections, datagram=True)
    msgs = parse_bytes(rx, frame(7), rejections, datagram=True)
    assert [m.get_seq() for m in msgs] == [7]



# -- console text between frames (ArduPilot prints its console on its first MAVLink port) ----

# What ArduCopter SITL sent to the agent's port while booting, one datagram each (captured on
# the build of ../shared/autopilots/ardupilot): its gyro calibration, a "*" per round.
ARDUPILOT_BOOT_TEXT = [b"Init Gyro", b"*", b"*", b"\n"]


def test_console_text_goes_to_the_console_buffer_and_is_not_counted() -> None:
    rx, rejections, console = parser(), Counter(), bytearray()
    msgs = []
    for datagram in [frame(0), *ARDUPILOT_BOOT_TEXT, frame(1) + b"gyro[0] ok\r\n" + frame(2)]:
        msgs += parse_bytes(rx, datagram, rejections, datagram=True, console=console)
    assert [m.get_seq() for m in msgs] == [0, 1, 2]
    assert rejections == Counter()
    assert console == b"Init Gyro**\ngyro[0] ok\r\n"


def test_without_a_console_buffer_console_text_is_counted_as_bad_data() -> None:
    rx, rejections = parser(), Counter()
    for datagram in ARDUPILOT_BOOT_TEXT:
        assert parse_bytes(rx, datagram, rejections, datagram=True) == []
    assert rejections == Counter({"bad_data": len(ARDUPILOT_BOOT_TEXT)})


def _bad_crc() -> bytes:
    bad = bytearray(frame(0))
    bad[-1] ^= 0xFF
    return bytes(bad)


@pytest.mark.parametrize("junk", [
    pytest.param(_bad_crc(), id="bad CRC"),
    pytest.param(b"A" + frame(0)[1:], id="frame with its magic byte hit"),
    pytest.param(b"Init\xb0Gyro", id="text with a byte outside ASCII"),
    pytest.param(b"Init\x00Gyro", id="text with a control byte"),
    pytest.param(bytes(range(0xFD)), id="binary junk"),  # no magic byte to swallow the frame
])
def test_junk_and_broken_frames_are_still_counted_with_a_console_buffer(junk: bytes) -> None:
    rx, rejections, console = parser(), Counter(), bytearray()
    msgs = parse_bytes(rx, junk + frame(5), rejections, datagram=True, console=console)
    assert [m.get_seq() for m in msgs] == [5]
    assert rejections["bad_data"] >= 1
    assert b"Gyro" not in console  # no part of a rejected run passes as console text


@given(st.lists(st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E)
                        | st.sampled_from("\t\r\n"), min_size=1), max_size=5))
def test_any_console_text_between_frames_is_kept_whole(lines: list[str]) -> None:
    rx, rejections, console = parser(), Counter(), bytearray()
    data = b"".join(line.encode() + frame(i) for i, line in enumerate(lines))
    msgs = parse_bytes(rx, data, rejections, datagram=False, console=console)
    assert [m.get_seq() for m in msgs] == list(range(len(lines)))
    assert console == "".join(lines).encode() and rejections == Counter()

# -- the fast path of the per-step messages --------------------------------------------------

_FLOATS = st.one_of(st.floats(width=32), st.sampled_from([0.0, -0.0]))


def _pymavlink_frame(send: str, seq: int, system: int, component: int, *args: object) -> bytes:
    sink = _Sink()
    tx = mavlink2.MAVLink(sink, srcSystem=system, srcComponent=component)
    tx.seq = seq
    getattr(tx, send)(*args)
    return sink.data


@given(st.integers(0, 255), st.integers(1, 255), st.integers(0, 255),
       st.integers(0, 0xFFFFFFFF), st.lists(_FLOATS, min_size=6, max_size=6))
def test_fast_local_position_is_pymavlinks_frame_and_reads_back(
        seq: int, system: int, component: int, stamp: int, values: list[float]) -> None:
    expected = _pymavlink_frame("local_position_ned_send", seq, system, component, stamp,
                                *values)
    tx = mavlink2.MAVLink(None, srcSystem=system, srcComponent=component)
    tx.seq = seq
    assert LOCAL_POSITION_NED.pack(tx, stamp, *values) == expected
    assert (tx.seq, tx.total_packets_sent, tx.total_bytes_sent) == (
        (seq + 1) % 256, 1, len(expected))
    (reference,) = parse_bytes(parser(), expected, Counter(), datagram=True)
    unpacked = LOCAL_POSITION_NED.unpack(expected)
    assert unpacked is not None
    assert unpacked[:2] == (system, component)
    fields = [getattr(reference, name) for name in LOCAL_POSITION_NED.fields]
    assert struct.pack("<I6f", *unpacked[2]) == struct.pack("<I6f", *fields)  # NaN-safe


@given(st.integers(0, 255), st.integers(0, 0xFFFFFFFF), st.lists(_FLOATS, min_size=3,
                                                                  max_size=3),
       st.integers(0, 0xFFFF), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255))
def test_fast_setpoint_is_pymavlinks_frame_and_message(
        seq: int, stamp: int, velocity: list[float], mask: int, target: int, component: int,
        frame_id: int) -> None:
    expected = _pymavlink_frame("set_position_target_local_ned_send", seq, 7, 191, stamp,
                                target, component, frame_id, mask, 0.0, 0.0, 0.0, *velocity,
                                0.0, 0.0, 0.0, 0.0, 0.0)
    tx = mavlink2.MAVLink(None, srcSystem=7, srcComponent=191)
    tx.seq = seq
    packed = SET_POSITION_TARGET_LOCAL_NED.pack(tx, stamp, 0.0, 0.0, 0.0, *velocity, 0.0, 0.0,
                                                0.0, 0.0, 0.0, mask, target, component,
                                                frame_id)
    assert packed == expected
    (reference,) = parse_bytes(parser(), expected, Counter(), datagram=True)
    fast = SET_POSITION_TARGET_LOCAL_NED.message(expected)
    assert fast is not None and fast.get_type() == reference.get_type()
    assert (fast.get_srcSystem(), fast.get_srcComponent(), fast.get_seq()) == (7, 191, seq)
    wire = mavlink2.MAVLink_set_position_target_local_ned_message.unpacker  # NaN-safe compare
    fields = SET_POSITION_TARGET_LOCAL_NED.fields
    assert wire.pack(*(getattr(fast, name) for name in fields)) == wire.pack(
        *(getattr(reference, name) for name in fields))


def test_fast_unpack_leaves_everything_else_to_the_parser() -> None:
    good = _pymavlink_frame("local_position_ned_send", 3, 1, 1, 1000, 1.0, 2.0, 3.0, 0.0,
                            0.0, 0.0)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    signed = bytearray(good)
    signed[2] = mavlink2.MAVLINK_IFLAG_SIGNED
    for data in (bytes(bad_crc), good[:-1], good + good, bytes(signed), frame(0), b"",
                 b"\xfd" + bytes(20)):
        assert LOCAL_POSITION_NED.unpack(data) is None, data.hex()
    assert SET_POSITION_TARGET_LOCAL_NED.message(good) is None  # another message id


def test_fast_pack_gives_way_to_pymavlink_when_signing() -> None:
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    tx.signing.sign_outgoing = True
    assert LOCAL_POSITION_NED.pack(tx, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0) is None
    assert tx.seq == 0


@given(st.integers(0, 255), st.integers(0, 255), st.data())
def test_every_single_byte_corruption_of_a_fast_frame_is_refused(
        seq: int, byte: int, data: st.DataObject) -> None:
    """The compiled framing checks magic, flags, length, id and checksum: a frame with any one
    byte changed (CRC-16 catches every burst of up to 16 bits) is not taken."""
    good = _pymavlink_frame("local_position_ned_send", seq, 1, 1, 1000, 1.0, 2.0, 3.0, 0.5,
                            0.0, 0.0)
    at = data.draw(st.integers(0, len(good) - 1))
    corrupted = bytearray(good)
    corrupted[at] ^= byte or 1
    assert LOCAL_POSITION_NED.unpack(bytes(corrupted)) is None
    assert LOCAL_POSITION_NED.unpack(memoryview(good)) is not None  # any bytes-like


@given(st.binary(max_size=80))
def test_fast_unpack_of_any_bytes_is_a_frame_or_none(junk: bytes) -> None:
    got = SET_POSITION_TARGET_LOCAL_NED.unpack(junk)
    assert got is None or parse_bytes(parser(), junk, Counter(), datagram=True)


def test_the_compiled_framing_refuses_out_of_range_arguments() -> None:
    from swarm.mavlink import _frame

    with pytest.raises(ValueError, match="a payload holds 1 to 255 bytes, got 0"):
        _frame.frame_v2(b"", 0, 1, 1, 32, 185)
    with pytest.raises(ValueError, match="seq must be in \\[0, 255\\], got 256"):
        _frame.frame_v2(b"\x01", 256, 1, 1, 32, 185)
    with pytest.raises(ValueError, match="message_id must be in \\[0, 16777215\\], got -1"):
        _frame.payload_v2(b"", -1, 0, 28)
    with pytest.raises(TypeError, match="frame_v2 takes 6 arguments, got 1"):
        _frame.frame_v2(b"\x01")
    with pytest.raises(TypeError):
        _frame.frame_v2("text", 0, 1, 1, 32, 185)  # not bytes-like
