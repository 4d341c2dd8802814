"""Bytes → MAVLink messages with every bad frame counted, for both ends of a link.

The agent's autopilot link (``swarm.mavlink_link``) and the emulated vehicle
(``sim_world.vehicle``) parse the same way: pymavlink with robust parsing turns junk, bad
CRCs and bad lengths into BAD_DATA and frames of messages outside the dialect into
UNKNOWN_<id>; those are counted by reason and dropped. Over UDP a frame never spans two
datagrams, so bytes left in the parser after a datagram are a truncated frame: counted and
dropped, or they would swallow the start of the next valid frame.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2


def reset_parser(parser: mavlink2.MAVLink) -> None:
    """Forget any partial frame held by ``parser``."""
    parser.buf = bytearray()
    parser.buf_index = 0
    parser.expected_length = mavlink2.HEADER_LEN_V1 + 2


def parse_bytes(parser: mavlink2.MAVLink, data: bytes, rejections: Counter[str], *,
                datagram: bool) -> list[Any]:
    """The complete, known messages in ``data``; everything else counted in ``rejections``
    (``bad_data``, ``unknown_message``, ``truncated``, ``parser_error:<type>``).
    ``datagram``: ``data`` is one whole UDP datagram (a leftover is a truncated frame)."""
    try:
        messages = parser.parse_buffer(bytes(data)) or []
    except Exception as exc:  # pymavlink should not raise with robust parsing; be safe
        rejections[f"parser_error:{type(exc).__name__}"] += 1
        reset_parser(parser)
        return []
    out: list[Any] = []
    for msg in messages:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            rejections["bad_data"] += 1
        elif kind.startswith("UNKNOWN"):
            rejections["unknown_message"] += 1
        else:
            out.append(msg)
    if datagram and parser.buf_len() > 0:
        rejections["truncated"] += 1
        reset_parser(parser)
    return out
