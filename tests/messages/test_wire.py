"""Wire messages: bit-exact round trips, strict validation, decoders that only raise WireError."""

from __future__ import annotations

import resource
import struct
import time
from collections.abc import Callable

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarm.core.drone_step import ConsensusMessage
from swarm.messages.wire import (
    MAX_TELEMETRY_BATCH,
    TELEMETRY_ARRAYS,
    WIRE_VERSION,
    BeaconRelayWire,
    BeaconWire,
    CameraFrameWire,
    ClockWire,
    ConsensusWire,
    DetectionWire,
    F64Array,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
    WireCodec,
    WireError,
    consensus_to_wire,
    telemetry_from_diagnostics,
)
from tests.helpers.wire_samples import (
    CODEC,
    KIND_OF,
    MESSAGES,
    MUTATIONS,
    NS,
    PAYLOADS,
    M,
    N,
    consensus_message,
    decode_only_wire_error,
    mutate,
    raw,
    real_agent_outputs,
    reason_of,
    same_bits,
)

# Values that a lossy path would change: signed zero, subnormals, extremes, an inexact sum.












DECODERS: dict[str, Callable[[bytes], object]] = {
    "consensus": CODEC.decode_consensus,
    "beacon": CODEC.decode_beacon,
    "beacons": CODEC.decode_beacon_relay,
    "camera": CODEC.decode_camera,
    "truth": CODEC.decode_truth,
    "clock": CODEC.decode_clock,
    "telemetry": CODEC.decode_telemetry,
}








# -- round trips ---------------------------------------------------------------------------------




@pytest.mark.parametrize("round_", [0, 2])
def test_consensus_round_trip_is_bit_exact(round_: int) -> None:
    original = consensus_message(round_=round_)
    decoded = CODEC.decode_consensus(CODEC.encode(original))
    assert (decoded.sender, decoded.step, decoded.round) == (3, 17, round_)
    for name in ("information", "information_vector", "projector_mean", "projector_integral",
                 "weight_mean", "weight_integral", "gramian"):
        a, b = getattr(original, name), getattr(decoded, name)
        if a is None:
            assert b is None
            continue
        assert np.array_equal(a, b) and same_bits(a, b), name
        assert b.flags.writeable and b.flags.c_contiguous
    # The special values really are in there, sign of zero included.
    bits = decoded.information.tobytes()
    for value in (-0.0, 5e-324, -2.5e-310):
        assert struct.pack("<d", value) in bits


def test_real_agent_message_and_diagnostics_round_trip() -> None:
    message, diag = real_agent_outputs()
    decoded = CODEC.decode_consensus(CODEC.encode(message))
    assert decoded.is_finite()
    for name in ("information", "information_vector", "gramian", "weight_mean"):
        assert same_bits(getattr(message, name), getattr(decoded, name))
    wire = telemetry_from_diagnostics(diag, [0.5, -0.25, 3.0])
    back = CODEC.decode_telemetry(CODEC.encode(wire)).to_diagnostics()
    for field in diag.__dataclass_fields__:
        a, b = getattr(diag, field), getattr(back, field)
        if isinstance(a, np.ndarray):
            assert a.shape == b.shape and a.tobytes() == np.asarray(b, a.dtype).tobytes(), field
        else:
            assert a == b and type(a) is type(b), field


@pytest.mark.parametrize("name", list(MESSAGES))
def test_every_message_round_trips_bit_exact(name: str) -> None:
    payload = PAYLOADS[name]
    decoded = DECODERS[KIND_OF[name]](payload)
    if isinstance(decoded, ConsensusMessage):
        decoded = consensus_to_wire(decoded)
    assert decoded == MESSAGES[name]
    assert CODEC.encode(decoded) == payload  # re-encoding gives the same bytes: every bit kept
    assert decoded.version == WIRE_VERSION
    for field, array in decoded.arrays().items():
        assert same_bits(array, MESSAGES[name].arrays()[field])


def test_helpers_give_numpy_back() -> None:
    cam = CODEC.decode_camera(PAYLOADS["camera"])
    dets = cam.detection_list()
    assert [d.target for d in dets] == [1, 0]
    assert same_bits(dets[0].image_point, np.array([-0.0, 0.1 + 0.2]))
    assert same_bits(cam.target_velocity_array(), MESSAGES["camera"].target_velocities.to_array())
    assert CODEC.decode_camera(PAYLOADS["camera_plain"]).target_velocity_array() is None
    beacon = CODEC.decode_beacon(PAYLOADS["beacon"])
    assert same_bits(beacon.position(), np.array([-0.0, 5e-324, 1.7976931348623157e308]))
    truth = CODEC.decode_truth(PAYLOADS["truth"]).arrays()
    assert set(truth) == {"drone_positions", "target_positions", "target_velocities"}
    tel = CODEC.decode_telemetry(PAYLOADS["telemetry"])
    assert tel.counters.mavlink_state == "offboard" and tel.counters.late_steps == 6
    assert same_bits(tel.position(), np.array([0.5, -0.0, 3.0]))


@settings(max_examples=200, deadline=None)
@given(shape=st.lists(st.integers(0, 4), min_size=1, max_size=3),
       seed=st.integers(0, 2**32 - 1))
def test_a_wire_array_as_lists_is_its_array_bit_for_bit(shape: list[int], seed: int) -> None:
    """``F64Array.to_list`` (what the lockstep exchange gives the core, and the recordings'
    JSON) holds the very floats of ``to_array``, -0.0, NaN payloads and subnormals included,
    nested as the shape says; so does ``CameraFrameWire.drone_position_rows``."""
    rng = np.random.default_rng(seed)
    values = rng.normal(size=shape) * 10.0 ** rng.integers(-320, 300, size=shape)
    values.flat[::3] = np.array([-0.0, np.nan, np.inf, 5e-324])[: len(values.flat[::3])]
    array = F64Array.from_array(values)
    listed = array.to_list()
    assert np.array(listed, dtype=np.float64).reshape(shape).tobytes() == values.tobytes()
    if all(shape):  # (lists cannot nest below an empty one)
        assert np.shape(listed) == tuple(shape)
    frame = MESSAGES["camera_lockstep"]
    rows = frame.drone_position_rows()
    assert np.array(rows).tobytes() == frame.drone_position_array().tobytes()
    assert all(type(v) is float for row in rows for v in row)


# -- validation ----------------------------------------------------------------------------------


def with_nan(array: F64Array, value: float = np.nan) -> F64Array:
    a = array.to_array()
    a.flat[-1] = value
    return F64Array.from_array(a)


def telemetry_fields(tel: TelemetryWire) -> dict:
    """Every field of ``tel`` as ``TelemetryWire.build`` takes them: the arrays by name."""
    fields = {name: getattr(tel, name) for name in tel.__struct_fields__
              if name not in ("version", "n_targets", "n_state", "data")}
    return {**fields, **{name: getattr(tel, name) for name in TELEMETRY_ARRAYS}}


def telemetry_with(tel: TelemetryWire, **arrays) -> TelemetryWire:
    """``tel`` with some of its arrays replaced (packed again)."""
    return TelemetryWire.build(**{**telemetry_fields(tel), **arrays})


def consensus_with_nan(wire: ConsensusWire, field: str, value: float = np.nan) -> ConsensusWire:
    """``wire`` with the last value of one of its packed arrays replaced."""
    message = CODEC.consensus_from_wire(wire)
    getattr(message, field).flat[-1] = value
    return consensus_to_wire(message)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_values_are_rejected(bad: float) -> None:
    cons = MESSAGES["consensus"]
    cases = [
        ("consensus", consensus_with_nan(cons, "gramian", bad)),
        ("consensus", consensus_with_nan(cons, "information", bad)),
        ("consensus", consensus_with_nan(MESSAGES["consensus_round"], "information_vector", bad)),
        ("beacon", msgspec.structs.replace(MESSAGES["beacon"], position_m=(0.0, bad, 1.0))),
        ("beacon", msgspec.structs.replace(MESSAGES["beacon"], time_s=bad)),
        ("beacons", relayed((2, bad))),
        ("beacons", BeaconRelayWire.build(3, ((msgspec.structs.replace(
            MESSAGES["beacon"], position_m=(bad, 0.0, 0.0)), 0.0),))),
        ("camera", msgspec.structs.replace(MESSAGES["camera"],
                                           detections=(DetectionWire(0, bad, 0.0),))),
        ("truth", msgspec.structs.replace(MESSAGES["truth"], target_velocities=with_nan(
            MESSAGES["truth"].target_velocities, bad))),
        ("clock", msgspec.structs.replace(MESSAGES["clock"], time_s=bad)),
        ("telemetry", telemetry_with(MESSAGES["telemetry"], psi1=with_nan(
            MESSAGES["telemetry"].psi1, bad))),
        ("telemetry", msgspec.structs.replace(MESSAGES["telemetry"], bearing_error=bad)),
        ("telemetry", msgspec.structs.replace(MESSAGES["telemetry"], counters=TelemetryCounters(
            neighbour_age_ms=bad))),
    ]
    for kind, message in cases:
        reason = reason_of(DECODERS[kind], raw(message))
        assert "finite" in reason, reason
        with pytest.raises(WireError, match="finite"):  # and nobody can send it either
            CODEC.encode(message)


@pytest.mark.parametrize("name", list(MESSAGES))
def test_wrong_version_is_rejected_naming_both_versions(name: str) -> None:
    kind = KIND_OF[name]
    message = msgspec.structs.replace(MESSAGES[name], version=WIRE_VERSION + 1)
    reason = reason_of(DECODERS[kind], raw(message))
    assert f"version {WIRE_VERSION + 1}" in reason and f"version {WIRE_VERSION}" in reason
    # A future version with a different layout is still explained by its version.
    future = raw([kind, WIRE_VERSION + 1, "a", "different", "layout"])
    reason = reason_of(DECODERS[kind], future)
    assert f"version {WIRE_VERSION + 1}" in reason and f"version {WIRE_VERSION}" in reason
    with pytest.raises(WireError, match="version"):
        CODEC.encode(message)


def test_wrong_message_kind_is_rejected() -> None:
    assert reason_of(CODEC.decode_consensus, PAYLOADS["beacon"]) == (
        "expected a consensus message, got beacon")
    assert "expected a clock message" in reason_of(CODEC.decode_clock, raw(["x" * 10_000, 1]))
    for kind, decode in DECODERS.items():
        for name, payload in PAYLOADS.items():
            if KIND_OF[name] != kind:
                assert "expected a" in reason_of(decode, payload)


def test_wrong_shapes_and_lengths_are_rejected() -> None:
    cons = MESSAGES["consensus"]
    # A consensus message packs its arrays in one block: its sizes and byte count are checked.
    bad_shape = msgspec.structs.replace(cons, n_state=NS + 1)
    assert "shape" in reason_of(CODEC.decode_consensus, raw(bad_shape))
    short = msgspec.structs.replace(cons, data=cons.data[:-1])
    assert "bytes" in reason_of(CODEC.decode_consensus, raw(short))
    longer = msgspec.structs.replace(cons, data=cons.data + bytes(8))
    assert "bytes" in reason_of(CODEC.decode_consensus, raw(longer))
    huge = msgspec.structs.replace(cons, n_targets=1 << 20, data=b"")
    assert "shape" in reason_of(CODEC.decode_consensus, raw(huge))
    # The same bytes are wrong for a swarm of another size.
    other = WireCodec(N, M + 1, NS)
    assert "shape" in reason_of(other.decode_consensus, PAYLOADS["consensus"])
    assert "shape" in reason_of(WireCodec(N + 1, M, NS).decode_truth, PAYLOADS["truth"])
    assert "n_targets 2 does not match" in reason_of(other.decode_telemetry,
                                                     PAYLOADS["telemetry"])
    # A telemetry block of the wrong length, or arrays that do not fit its layout.
    tel = MESSAGES["telemetry"]
    for data in (tel.data[:-8], tel.data + bytes(8), tel.data[:-1]):
        assert "telemetry data carries" in reason_of(
            CODEC.decode_telemetry, raw(msgspec.structs.replace(tel, data=data)))
    with pytest.raises(WireError, match=r"velocity has shape \(4,\), expected \(3,\)"):
        telemetry_with(tel, velocity=np.zeros(4))
    with pytest.raises(WireError, match="telemetry arrays missing: psi0"):
        TelemetryWire.build(**{k: v for k, v in telemetry_fields(tel).items() if k != "psi0"})


def relayed(*entries: tuple[int, float]) -> BeaconRelayWire:
    """A relay of these (sender, held_s): no codec involved, so it may break the rules."""
    return BeaconRelayWire.build(3, (
        (BeaconWire.build(sender, 2, 0.04, (0.0, 0.0, 3.0)), held) for sender, held in entries))


def test_ids_steps_and_rounds_are_range_checked() -> None:
    cons, cam = MESSAGES["consensus"], MESSAGES["camera"]
    cases = [
        (CODEC.decode_consensus, msgspec.structs.replace(cons, sender=N), "sender 6 out of range"),
        (CODEC.decode_consensus, msgspec.structs.replace(cons, step=-1), ">= 0"),
        (CODEC.decode_consensus, msgspec.structs.replace(MESSAGES["consensus_round"], round=3),
         "round 3 out of range"),
        (CODEC.decode_consensus, msgspec.structs.replace(
            cons, data=MESSAGES["consensus_round"].data), "gramian missing"),
        (CODEC.decode_consensus, msgspec.structs.replace(
            MESSAGES["consensus_round"], data=cons.data), "must not carry"),
        (CODEC.decode_beacon, msgspec.structs.replace(MESSAGES["beacon"], sender=99), "sender"),
        (CODEC.decode_beacon, msgspec.structs.replace(MESSAGES["beacon"], vehicle_time_ms=-1),
         ">= 0"),
        (CODEC.decode_camera, msgspec.structs.replace(cam, drone=N), "drone"),
        (CODEC.decode_camera, msgspec.structs.replace(
            cam, detections=(DetectionWire(M, 0.0, 0.0),)), "target 2 out of range"),
        (CODEC.decode_camera, msgspec.structs.replace(
            cam, detections=(DetectionWire(1, 0.0, 0.0), DetectionWire(1, 0.1, 0.0))), "twice"),
        (CODEC.decode_camera, msgspec.structs.replace(cam, vehicle_time_ms=-5), ">= 0"),
        (CODEC.decode_telemetry, msgspec.structs.replace(MESSAGES["telemetry"], drone=N), "drone"),
        (CODEC.decode_telemetry, msgspec.structs.replace(
            MESSAGES["telemetry"], counters=TelemetryCounters(late_steps=-1)), ">= 0"),
        (CODEC.decode_clock, msgspec.structs.replace(MESSAGES["clock"], state="flying"),
         "flying"),
        (CODEC.decode_clock, msgspec.structs.replace(MESSAGES["clock"], mode="fast"), "fast"),
        (CODEC.decode_beacon, msgspec.structs.replace(MESSAGES["beacon"], sender=True), "int"),
        # The world's relay: each drone once, at most N, ages ≥ 0, one row per sender.
        (CODEC.decode_beacon_relay, relayed((9, 0.0)), "sender 9 out of range"),
        (CODEC.decode_beacon_relay, relayed((1, 0.0), (1, 0.5)), "sender 1 appears twice"),
        (CODEC.decode_beacon_relay, relayed((2, -0.001)), "negative sample age or held time"),
        (CODEC.decode_beacon_relay, relayed(*((j % N, 0.0) for j in range(N + 1))),
         "more than this swarm's 6 drones"),
        (CODEC.decode_beacon_relay, msgspec.structs.replace(
            relayed((1, 0.0), (2, 0.0)), senders=b"\x01\x00\x02"), "not 2 per drone id"),
        (CODEC.decode_beacon_relay, msgspec.structs.replace(
            relayed((1, 0.0), (2, 0.0)), senders=b"\x01\x00"),
         "data carries 128 bytes, expected 64 for 1 senders"),
    ]
    for decode, message, needle in cases:
        assert needle in reason_of(decode, raw(message)), needle


def test_strings_and_lists_are_bounded() -> None:
    clock = msgspec.structs.replace(MESSAGES["clock"], detail="x" * 513)
    assert "length" in reason_of(CODEC.decode_clock, raw(clock))
    with pytest.raises(WireError, match="longer than 512"):
        CODEC.encode(clock)
    assert CODEC.decode_clock(raw(msgspec.structs.replace(clock, detail="y" * 512)))
    tel = msgspec.structs.replace(MESSAGES["telemetry"],
                                  counters=TelemetryCounters(mavlink_state="z" * 65))
    assert "length" in reason_of(CODEC.decode_telemetry, raw(tel))
    many = tuple(DetectionWire(0, 0.0, 0.0) for _ in range(2000))
    cam = msgspec.structs.replace(MESSAGES["camera"], detections=many)
    assert "length" in reason_of(CODEC.decode_camera, raw(cam))


def test_encode_refuses_what_peers_would_reject() -> None:
    with pytest.raises(WireError, match="sender"):
        CODEC.encode(consensus_message(sender=N))
    with pytest.raises(WireError, match="not a wire message"):
        CODEC.encode({"sender": 1})  # type: ignore[arg-type]
    with pytest.raises(WireError):
        CODEC.encode(BeaconWire(sender=1, step=0, time_s=0.0, position_m=("a", 0.0, 0.0)))
    with pytest.raises(WireError):
        CODEC.encode(msgspec.structs.replace(MESSAGES["beacon"], step=np.int64(3)))


def test_codec_sizes_are_validated() -> None:
    for args in [(0, 1, 6), (6, 0, 6), (6, 1, 0), (6, 1, 10_000), (True, 1, 6), (6.0, 1, 6)]:
        with pytest.raises(ValueError, match="WireCodec"):
            WireCodec(*args)
    with pytest.raises(ValueError, match="n_rounds"):
        WireCodec(6, 1, 6, n_rounds=0)


# -- hostile bytes -------------------------------------------------------------------------------


def test_huge_length_prefixes_and_deep_nesting_fail_fast_without_allocating() -> None:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    hostile = [
        b"\xc6\xff\xff\xff\xff",  # bin32, 4 GiB announced
        b"\xdd\xff\xff\xff\xff" + b"\xc0" * 10,  # array32 of 4G elements
        b"\xdf\xff\xff\xff\xff",  # map32
        b"\xdb\xff\xff\xff\xff" + b"a" * 100,  # str32
        b"\x96\xa9consensus\x01\x01\x01\x00\x92\x93\xce\x00\x10\x00\x00" * 3,
        raw(["consensus", 1, 1, 1, 0, [[1 << 20, 1 << 20, 1 << 20], b""], [[2, 6], b""]]),
        b"\x91" * 200_000,  # 200k nested arrays
        b"\xdd\x00\x00\x00\x02" * 100_000,  # nested array32s
        b"\x81\xa1k" * 100_000,  # nested maps
        bytes(CODEC.max_payload_bytes + 1),  # over the size limit
        b"",
    ]
    started = time.perf_counter()
    for payload in hostile:
        for decode in DECODERS.values():
            with pytest.raises(WireError):
                decode(payload)
    assert time.perf_counter() - started < 2.0
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown_kib < 64 * 1024, f"decoding hostile payloads grew RSS by {grown_kib} KiB"
    with pytest.raises(WireError, match="bytes"):
        CODEC.decode_beacon("not bytes")  # type: ignore[arg-type]


@pytest.mark.parametrize("name", list(PAYLOADS))
def test_every_truncation_and_every_bit_flip(name: str) -> None:
    payload = PAYLOADS[name]
    for decode in DECODERS.values():
        for cut in range(len(payload)):
            with pytest.raises(WireError):
                decode(payload[:cut])
    decode = DECODERS[KIND_OF[name]]
    buf = bytearray(payload)
    for i in range(len(buf)):
        for bit in range(8):
            buf[i] ^= 1 << bit
            decode_only_wire_error(decode, bytes(buf))
            buf[i] ^= 1 << bit


FUZZ = settings(max_examples=2000, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
KIND_PREFIXES = [raw([kind, WIRE_VERSION])[1:] for kind in DECODERS]  # tag and version bytes


@FUZZ
@given(data=st.one_of(
    st.binary(max_size=512),
    st.tuples(st.integers(0x90, 0x9F), st.sampled_from(KIND_PREFIXES), st.binary(max_size=256))
    .map(lambda t: bytes([t[0]]) + t[1] + t[2]),
))
def test_fuzz_random_bytes_only_raise_wire_error(data: bytes) -> None:
    """2000 examples, each fed to every decoder (so ≥ 2000 per decoder)."""
    for decode in DECODERS.values():
        decode_only_wire_error(decode, data)






ALL_PAYLOADS = list(PAYLOADS.values())


@FUZZ
@given(base=st.integers(0, len(ALL_PAYLOADS) - 1), mutations=MUTATIONS)
def test_fuzz_mutated_valid_payloads_only_raise_wire_error(base: int, mutations) -> None:
    """2000 mutated payloads of every kind, each fed to every decoder."""
    payload = mutate(ALL_PAYLOADS[base], mutations)
    for decode in DECODERS.values():
        decode_only_wire_error(decode, payload)


@pytest.mark.parametrize("kind", list(DECODERS))
def test_bulk_seeded_mutations_only_raise_wire_error(kind: str) -> None:
    """A cheaper, larger sweep: 10 000 seeded random mutations of this kind's payloads. What
    decodes is a valid message: encoded again it decodes to the same bytes' message."""
    rng = np.random.default_rng(list(DECODERS).index(kind))
    own = [p for name, p in PAYLOADS.items() if KIND_OF[name] == kind]
    ops = ["flip", "set", "truncate", "insert", "delete", "dup"]
    accepted = 0
    for _ in range(10_000):
        mutations = [(ops[rng.integers(6)], int(rng.integers(1 << 16)), int(rng.integers(256)),
                      rng.bytes(int(rng.integers(1, 17)))) for _ in range(rng.integers(1, 4))]
        payload = mutate(own[rng.integers(len(own))], mutations)
        try:
            message = DECODERS[kind](payload)
        except WireError as err:
            assert not err.reason.startswith("internal"), err.reason
            continue
        accepted += 1
        canonical = CODEC.encode(message)
        assert CODEC.encode(DECODERS[kind](canonical)) == canonical
    # Measured with these seeds: 290 (clock) to 1 493 (consensus) of 10 000 decode — the
    # mutations that only change a number's bits, or leave the bytes as they were. A decoder
    # that let malformed structure through would accept far more.
    assert accepted < 2_000, accepted


def test_clock_and_camera_types() -> None:
    assert isinstance(CODEC.decode_clock(PAYLOADS["clock"]), ClockWire)
    assert isinstance(CODEC.decode_camera(PAYLOADS["camera"]), CameraFrameWire)
    assert isinstance(CODEC.decode_truth(PAYLOADS["truth"]), TruthWire)
    assert isinstance(CODEC.decode_consensus_wire(PAYLOADS["consensus"]), ConsensusWire)


def test_clock_carries_the_worlds_rejection_count() -> None:
    """A trailing field with a default: a clock without it (an older world) still decodes,
    as 0; a negative or non-integer count is rejected."""
    clock = ClockWire(step=3, time_s=0.06, state="running", mode="lockstep",
                      rejected_inputs=70_123)
    assert CODEC.decode_clock(CODEC.encode(clock)).rejected_inputs == 70_123
    older = msgspec.msgpack.encode(["clock", WIRE_VERSION, 3, 0.06, "running", "lockstep", ""])
    assert CODEC.decode_clock(older).rejected_inputs == 0
    for bad in (-1, 1.5, True, "7"):
        payload = msgspec.msgpack.encode(["clock", WIRE_VERSION, 3, 0.06, "running",
                                          "lockstep", "", bad])
        with pytest.raises(WireError, match=r"rejected_inputs|Expected `int`"):
            CODEC.decode_clock(payload)
    with pytest.raises(WireError, match="rejected_inputs"):
        CODEC.encode(ClockWire(step=3, time_s=0.06, state="running", mode="lockstep",
                               rejected_inputs=-1))


def test_telemetry_counters_as_keywords() -> None:
    _, diag = real_agent_outputs()
    wire = TelemetryWire.from_diagnostics(diag, [0.0, 0.0, 3.0], qp_fallbacks=1, late_steps=2,
                                          neighbour_age_ms=float("nan"), mavlink_state="armed")
    decoded = CODEC.decode_telemetry(CODEC.encode(wire))
    assert decoded.counters == TelemetryCounters(qp_fallbacks=1, late_steps=2,
                                                 neighbour_age_ms=None, mavlink_state="armed")
    assert telemetry_from_diagnostics(diag, [0, 0, 3], neighbour_age_ms=4).counters == (
        TelemetryCounters(neighbour_age_ms=4.0))
    with pytest.raises(TypeError, match="not both"):
        telemetry_from_diagnostics(diag, [0, 0, 3], TelemetryCounters(), late_steps=1)
    with pytest.raises(TypeError, match="unknown"):
        telemetry_from_diagnostics(diag, [0, 0, 3], late_stepz=1)
    message = consensus_message()
    back = CODEC.consensus_from_wire(CODEC.consensus_to_wire(message))
    assert same_bits(back.gramian, message.gramian)


def test_one_codec_shared_by_threads() -> None:
    import threading

    errors: list[BaseException] = []

    def work(name: str) -> None:
        try:
            for _ in range(300):
                payload = CODEC.encode(MESSAGES[name])
                assert payload == PAYLOADS[name]
                DECODERS[KIND_OF[name]](payload)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(n,)) for n in MESSAGES]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


# -- telemetry batches (a lockstep agent's telemetry, several steps per message) -----------------


def telemetry_steps(steps: list[int], drone: int = 1) -> list[bytes]:
    """``encode_telemetry``-checked payloads of the sample telemetry at these steps."""
    base = MESSAGES["telemetry"]
    return [CODEC.encode(msgspec.structs.replace(base, drone=drone, step=k, time_s=0.02 * k))
            for k in steps]


@given(steps=st.lists(st.integers(0, 10**6), min_size=1, max_size=MAX_TELEMETRY_BATCH,
                      unique=True).map(sorted), drone=st.integers(0, N - 1))
def test_a_telemetry_batch_decodes_to_its_steps_messages_in_order(steps: list[int],
                                                                  drone: int) -> None:
    payloads = telemetry_steps(steps, drone)
    batch = CODEC.encode_telemetry_batch(payloads)
    items = CODEC.decode_telemetry_items(batch)
    assert items == tuple(CODEC.decode_telemetry(p) for p in payloads)
    assert [CODEC.encode(item) for item in items] == payloads  # every bit as sent
    # A telemetry key may carry one message of its own too: the same decoder takes it.
    assert CODEC.decode_telemetry_items(payloads[0]) == (CODEC.decode_telemetry(payloads[0]),)


def test_a_telemetry_batch_is_refused_whole_naming_the_item_and_the_rule() -> None:
    good = telemetry_steps([3, 4])
    bad_item = raw(msgspec.structs.replace(MESSAGES["telemetry"], step=5, qp_solve_us=-1.0))
    batch = ["telemetry_batch", WIRE_VERSION]
    cases = [
        (raw([*batch, []]), "type", "items: Expected `array` of length >= 1"),
        (raw([*batch, [msgspec.Raw(good[0])] * (MAX_TELEMETRY_BATCH + 1)]), "length",
         f"more than {MAX_TELEMETRY_BATCH} items"),
        (raw([*batch, [msgspec.Raw(p) for p in (*good, bad_item)]]), "range",
         "telemetry batch item 2: qp_solve_us must be >= 0.0"),
        (raw([*batch, [msgspec.Raw(p) for p in telemetry_steps([3, 3])]]), "value",
         "item 1 has step 3, not after 3"),
        (raw([*batch, [msgspec.Raw(p) for p in (*good, *telemetry_steps([5], drone=2))]]),
         "value", "item 2 is drone 2's, item 0 drone 1's"),
        (raw(["telemetry_batch", WIRE_VERSION + 1, [msgspec.Raw(good[0])]]), "version",
         f"wire version {WIRE_VERSION + 1}"),
        (raw(MESSAGES["clock"]), "kind", "expected a telemetry message"),
        (CODEC.encode_telemetry_batch(good)[:-1], "malformed", "malformed"),
        (bytes(CODEC.max_payload_bytes + 1), "size", "exceeds"),
    ]
    for payload, rule, words in cases:
        with pytest.raises(WireError) as info:
            CODEC.decode_telemetry_items(payload)
        assert info.value.rule == rule and words in info.value.reason, (info.value, words)
    # The sender cannot emit what the observers would refuse.
    with pytest.raises(WireError, match="not after 3"):
        CODEC.encode_telemetry_batch(telemetry_steps([3, 3]))
    with pytest.raises(WireError, match="a sequence of payloads, not one"):
        CODEC.encode_telemetry_batch(good[0])


BATCH_PREFIX = bytes([0x93]) + raw(["telemetry_batch", WIRE_VERSION])[1:]  # [tag, version, …


@FUZZ
@given(data=st.one_of(st.binary(max_size=512),
                      st.binary(max_size=256).map(lambda tail: BATCH_PREFIX + tail)),
       mutations=MUTATIONS)
def test_fuzz_telemetry_batches_only_raise_wire_error(data: bytes, mutations) -> None:
    """Random bytes (some shaped like a batch's start) and mutated valid batches."""
    decode_only_wire_error(CODEC.decode_telemetry_items, data)
    batch = CODEC.encode_telemetry_batch(telemetry_steps([7, 8, 9]))
    decode_only_wire_error(CODEC.decode_telemetry_items, mutate(batch, mutations))
