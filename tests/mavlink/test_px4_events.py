"""PX4 EVENT messages: ids, checksum, decoding and names (swarm.mavlink.px4_events), and the
generator of the name table (tools/px4_event_names.py).

The frames below were captured from PX4 v1.15.4 SITL (SIH) on its onboard link while a
pymavlink script asked it to arm once a second from boot until it armed (~37 s).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import all as mavlink_all
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.mavlink import px4_events as pe
from swarm.mavlink.px4_event_names import EVENT_NAMES, PX4_COMMIT, PX4_VERSION

# (frame, name, id, time since boot [ms], sequence, external level, internal level,
# arguments without their trailing zeros)
CAPTURED = [
    ("fd1200009f01019a010027371d0124080000feff00008800020802288e65", "commander_health_summary",
     0x011D3727, 2084, 65534, "protocol", "protocol", "0002080228"),
    ("fd1e0000e001019a0100e093a80120870000ffff000088000000120080000000802b0180803b0180539a",
     "commander_arming_check_summary", 0x01A893E0, 34592, 65535, "protocol", "protocol",
     "000000120080000000802b0180803b0180"),
    ("fd120000e101019a010040d687012087000000000000337ed07e0011ecbf",
     "check_estimator_hor_vel_not_stable", 0x0187D640, 34592, 0, "error", "error",
     "7ed07e0011"),
    ("fd120000e201019a0100b91bd3012087000001000000337c007e0014671b", "check_modes_local_pos",
     0x01D31BB9, 34592, 1, "error", "error", "7c007e0014"),
    ("fd0d0000d301019a01009d0802013c040000f6ff0000629de1",
     "commander_arm_denied_resolve_failures", 0x0102089D, 1084, 65526, "critical", "info", ""),
    ("fd1200009101019a01008f749f0114080000f8ff0000227ed07e0014f2f9", "check_modes_attitude",
     0x019F748F, 2068, 65528, "critical", "critical", "7ed07e0014"),
    ("fd1200009601019a010029ed060114080000fdff000044ffffffff077e81",
     "check_modes_manual_control", 0x0106ED29, 2068, 65533, "warning", "warning", "ffffffff07"),
    ("fd0e00003301019a0100f3ca9001c88c00003300000066045528", "commander_armed_by", 0x0190CAF3,
     36040, 51, "info", "info", "04"),
]
# Other PX4 frames pymavlink 2.4.50 does not decode: (frame, MAVLink name).
CAPTURED_OTHER = [
    ("fd030000d201019b0100f6ff018be5", "CURRENT_EVENT_SEQUENCE"),
    ("fd080000a40101b4010000000403000004037736", "CURRENT_MODE"),
    ("fd110000d00101080000c07a1000000000000000000000000000d0b135", "LINK_NODE_STATUS"),
    ("fd1400008c01017c010000000000ffffffffffffffffffffffffffffffff0cd3",
     "TIME_ESTIMATE_TO_TARGET"),
]

# Further ids seen from the same firmware (events with arguments whose frames are not kept).
SEEN_IDS = {
    "check_modes_global_pos": 0x0198C273,
    "check_modes_mission": 0x0105C2D9,
    "check_modes_offboard_signal": 0x012F1DC7,
    "check_rc_dl_no_dllink": 0x0167C97B,
}


def parse(frame: bytes) -> list:
    """What our link's pymavlink parser hands over for ``frame``."""
    parser = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    parser.robust_parsing = True
    return parser.parse_buffer(frame) or []


def only(frame: bytes):
    messages = parse(frame)
    assert len(messages) == 1
    return messages[0]


def _tool() -> ModuleType:
    path = Path(__file__).resolve().parents[2] / "tools" / "px4_event_names.py"
    spec = importlib.util.spec_from_file_location("px4_event_names_tool", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


tool = _tool()


# -- ids ------------------------------------------------------------------------------------------


def test_fnv1a_32_reference_vectors():
    # FNV-1a 32-bit test vectors (offset basis for the empty string).
    assert pe.fnv1a_32(b"") == 0x811C9DC5
    assert pe.fnv1a_32(b"a") == 0xE40C292C
    assert pe.fnv1a_32(b"foobar") == 0xBF9CF968


@pytest.mark.parametrize(("name", "event_id"),
                         [(c[1], c[2]) for c in CAPTURED] + list(SEEN_IDS.items()))
def test_event_id_reproduces_the_firmware(name, event_id):
    assert pe.px4_event_id(name) == event_id
    assert EVENT_NAMES[event_id] == name


def test_generated_table_is_consistent():
    assert PX4_VERSION == "v1.15.4"
    assert PX4_COMMIT.startswith("99c40407ff")
    assert len(EVENT_NAMES) > 300
    for event_id, name in EVENT_NAMES.items():
        assert pe.px4_event_id(name) == event_id


# -- checksum -------------------------------------------------------------------------------------


def test_event_crc_extra_is_the_published_one():
    assert pe.EVENT_CRC_EXTRA == 160  # MAVLINK_MSG_ID_EVENT_CRC of the generated C headers


@pytest.mark.parametrize("message_class", [mavlink2.MAVLink_heartbeat_message,
                                           mavlink2.MAVLink_local_position_ned_message,
                                           mavlink2.MAVLink_param_value_message,
                                           mavlink2.MAVLink_named_value_float_message])
def test_crc_extra_derivation_matches_pymavlink(message_class):
    """The derivation reproduces pymavlink's own CRC_EXTRA for messages without extension
    fields (pymavlink's classes do not say which fields are extensions), char arrays included
    (PARAM_VALUE, NAMED_VALUE_FLOAT)."""
    types = dict(zip(message_class.fieldnames, message_class.fieldtypes, strict=True))
    fields = [(types[name], name, length) for name, length
              in zip(message_class.ordered_fieldnames, message_class.array_lengths,
                     strict=True)]
    assert pe.mavlink_crc_extra(message_class.msgname, fields) == message_class.crc_extra


def test_pymavlink_does_not_decode_the_listed_ids():
    for msgid, name in pe.UNDECODED_MESSAGES.items():
        assert msgid not in mavlink2.mavlink_map, f"pymavlink now decodes {name}"
        if msgid in mavlink_all.mavlink_map:  # its development dialect names some of them
            assert mavlink_all.mavlink_map[msgid].msgname == name


# -- decoding -------------------------------------------------------------------------------------


@pytest.mark.parametrize("captured", CAPTURED, ids=[c[1] for c in CAPTURED])
def test_decodes_captured_frames(captured):
    frame_hex, name, event_id, time_ms, sequence, external, internal, arguments = captured
    msg = only(bytes.fromhex(frame_hex))
    assert msg.get_type() == "UNKNOWN_410"
    assert pe.undecoded_message_name(msg) == "EVENT"
    event = pe.event_from_message(msg)
    assert event == pe.Px4Event(
        event_id=event_id, name=name, time_boot_ms=time_ms, sequence=sequence,
        log_level_external=external, log_level_internal=internal,
        arguments=bytes.fromhex(arguments).ljust(40, b"\x00"), destination_system=0,
        destination_component=0)
    assert event.component_id == 1
    assert pe.describe(event) == f"PX4 {name} ({external})"


def test_source_of_undecoded_messages_comes_from_the_frame():
    msg = only(bytes.fromhex(CAPTURED[0][0]))
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (0, 0)  # pymavlink leaves them
    assert pe.message_source(msg) == (1, 1)
    sender = mavlink2.MAVLink(None, srcSystem=7, srcComponent=191)
    heartbeat = only(sender.heartbeat_encode(18, 8, 0, 0, 0).pack(sender))
    assert pe.message_source(heartbeat) == (7, 191)


def test_zero_stripped_payloads_decode():
    # Every captured frame's payload was stripped (13 to 30 of 53 bytes); the shortest:
    frame = bytes.fromhex(CAPTURED[4][0])
    assert frame[1] == 13
    event = pe.event_from_message(only(frame))
    assert event is not None and event.arguments == bytes(40)
    # A one-byte payload (id 0x00000001, everything else zero), straight to the decoder:
    assert pe.decode_event_payload(b"\x01") == pe.Px4Event(
        event_id=1, name=None, time_boot_ms=0, sequence=0, log_level_external="emergency",
        log_level_internal="emergency", arguments=bytes(40), destination_system=0,
        destination_component=0)


@pytest.mark.parametrize("index", [1, 4, 10, 20, -3, -2, -1])
def test_corrupted_frame_gives_none(index):
    """A flipped bit in the header, payload or checksum: the CRC no longer holds."""
    frame = bytearray.fromhex(CAPTURED[1][0])
    frame[index] ^= 0x10
    msg = mavlink2.MAVLink_unknown(410, frame)  # what the parser would hand over, unchecked
    assert pe.event_from_message(msg) is None


def test_wrong_length_gives_none():
    frame = bytes.fromhex(CAPTURED[0][0])
    assert pe.event_from_message(mavlink2.MAVLink_unknown(410, frame[:-1])) is None
    assert pe.event_from_message(mavlink2.MAVLink_unknown(410, frame + b"\x00")) is None


def test_signed_frame_decodes():
    event = pe.event_from_message(only(bytes.fromhex(CAPTURED[2][0])))
    assert event is not None
    frame = bytearray(pe.pack_event_frame(event, seq=7, system_id=1))
    frame[2] |= 0x01  # signed: the checksum covers the flag, a 13-byte signature follows
    frame[-2:] = b""
    frame += _checksum(frame)
    frame += bytes(range(13))
    assert pe.event_from_message(mavlink2.MAVLink_unknown(410, frame)) == event


def _checksum(frame_without_checksum: bytes | bytearray) -> bytes:
    crc = mavlink2.x25crc(bytes(frame_without_checksum[1:]))
    crc.accumulate(bytes((pe.EVENT_CRC_EXTRA,)))
    return crc.crc.to_bytes(2, "little")


@pytest.mark.parametrize(("frame_hex", "name"), CAPTURED_OTHER, ids=[c[1] for c in CAPTURED_OTHER])
def test_other_px4_messages_are_not_events(frame_hex, name):
    msg = only(bytes.fromhex(frame_hex))
    assert msg.get_type().startswith("UNKNOWN_")
    assert pe.event_from_message(msg) is None
    assert pe.undecoded_message_name(msg) == name


def test_decoded_messages_are_not_events():
    sender = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = sender.heartbeat_encode(2, 12, 0, 0, 3)
    msg = only(heartbeat.pack(sender))
    assert msg.get_type() == "HEARTBEAT"
    assert pe.event_from_message(msg) is None
    assert pe.undecoded_message_name(msg) is None
    assert pe.event_from_message(mavlink2.MAVLink_unknown(999, bytes(12))) is None


class _DecodedEvent:
    """An EVENT as a pymavlink whose dialect defines it would deliver it (checked, decoded)."""

    def __init__(self, event: pe.Px4Event) -> None:
        self.id = event.event_id
        self.event_time_boot_ms = event.time_boot_ms
        self.sequence = event.sequence
        self.destination_component = event.destination_component
        self.destination_system = event.destination_system
        self.log_levels = (pe.log_level_number(event.log_level_internal) << 4
                           | pe.log_level_number(event.log_level_external))
        self.arguments = list(event.arguments)

    def get_msgId(self) -> int:  # noqa: N802 (pymavlink's name)
        return pe.EVENT_MSG_ID

    def get_type(self) -> str:
        return "EVENT"


def test_event_decoded_by_pymavlink_is_taken_as_is():
    event = pe.event_from_message(only(bytes.fromhex(CAPTURED[3][0])))
    assert event is not None
    assert pe.event_from_message(_DecodedEvent(event)) == event


def test_describe_unknown_event():
    event = pe.decode_event_payload(bytes.fromhex("cdab3412") + bytes(8) + b"\x44")
    assert event.name is None
    assert pe.describe(event) == "PX4 event 0x1234abcd (warning; not a known v1.15 event)"


def test_log_levels():
    assert [pe.log_level_name(n) for n in (0, 2, 3, 4, 8, 9, 12)] == [
        "emergency", "critical", "error", "warning", "protocol", "disabled", "level12"]
    for level in range(16):
        assert pe.log_level_number(pe.log_level_name(level)) == level
    with pytest.raises(ValueError, match="unknown log level"):
        pe.log_level_number("fatal")
    with pytest.raises(ValueError, match="out of range"):
        pe.log_level_name(16)


def test_too_many_argument_bytes_refused():
    event = pe.decode_event_payload(b"\x01")
    with pytest.raises(ValueError, match="41 bytes"):
        pe.encode_event_payload(
            pe.Px4Event(**{**event.__dict__, "arguments": bytes(41)}))


# -- round trip -----------------------------------------------------------------------------------

_levels = st.integers(0, 15).map(pe.log_level_name)
_events = st.builds(
    lambda event_id, **fields: pe.Px4Event(event_id=event_id, name=EVENT_NAMES.get(event_id),
                                           **fields),
    event_id=st.one_of(st.sampled_from(sorted(EVENT_NAMES)), st.integers(0, 2**32 - 1)),
    time_boot_ms=st.integers(0, 2**32 - 1), sequence=st.integers(0, 2**16 - 1),
    log_level_external=_levels, log_level_internal=_levels,
    arguments=st.binary(min_size=40, max_size=40), destination_system=st.integers(0, 255),
    destination_component=st.integers(0, 255))


@given(event=_events, seq=st.integers(0, 255), system_id=st.integers(1, 255))
def test_encode_decode_round_trip(event, seq, system_id):
    """Payload and whole frame (through pymavlink's parser, zero-stripped) give it back."""
    payload = pe.encode_event_payload(event)
    assert pe.decode_event_payload(payload) == event
    assert pe.decode_event_payload(payload.rstrip(b"\x00")) == event
    msg = only(pe.pack_event_frame(event, seq=seq, system_id=system_id))
    assert msg.get_type() == "UNKNOWN_410"
    assert pe.event_from_message(msg) == event


# -- the table's generator ------------------------------------------------------------------------


def test_generator_finds_names_outside_comments():
    text = """
        events::send(events::ID("check_alpha"), {events::Log::Error}, "x");
        reporter.armingCheckFailure(NavModes::All, health_component_t::gps,
            events::ID( "check_beta" ), events::Log::Error, "y");
        // events::send(events::ID("commented_out"), ...);
        /* events::ID("block_comment")
         * events::ID("block_comment_too") */
        foo(); // events::ID("trailing_comment")
    """
    assert tool.names_in_text(text) == {"check_alpha", "check_beta"}


def test_generator_renders_an_importable_table(tmp_path):
    table = tool.id_table(["check_alpha", "commander_armed_by"])
    assert table[0x0190CAF3] == "commander_armed_by"
    text = tool.render(table, px4_version="v9.9.9", px4_commit="0" * 40)
    namespace: dict = {}
    exec(compile(text, "generated", "exec"), namespace)
    assert namespace["EVENT_NAMES"] == table
    assert namespace["PX4_VERSION"] == "v9.9.9"
    assert all(len(line) <= 100 for line in text.splitlines())


def test_generator_refuses_colliding_names(monkeypatch):
    monkeypatch.setattr(tool, "px4_event_id", lambda name: 0x01000001)
    with pytest.raises(tool.EventNamesError, match="share id 0x01000001"):
        tool.id_table(["a", "b"])


def test_generator_end_to_end(tmp_path, capsys):
    checkout = tmp_path / "PX4"
    checks = checkout / "src" / "modules" / "commander" / "HealthAndArmingChecks"
    checks.mkdir(parents=True)
    (checks / "gpsCheck.cpp").write_text('x(events::ID("check_modes_local_pos"));\n')
    (checkout / "src" / "README.md").write_text('events::ID("not_source")\n')
    output = tmp_path / "names.py"
    argv = [str(checkout), "--output", str(output), "--px4-commit", "abc", "--px4-version", "v1"]
    assert tool.main(argv) == 0
    assert '0x01d31bb9: "check_modes_local_pos",' in output.read_text()
    assert "not_source" not in output.read_text()
    assert tool.main([str(tmp_path), "--output", str(output)]) == 2
    assert "not a PX4-Autopilot checkout" in capsys.readouterr().err
