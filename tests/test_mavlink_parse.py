"""Both ends of the MAVLink link parse bytes the same way: good frames out, the rest counted."""

from __future__ import annotations

from collections import Counter

from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.mavlink_parse import parse_bytes


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
