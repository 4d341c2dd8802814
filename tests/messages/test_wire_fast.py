"""The codec's short ways (what an agent process runs every step) against its long ways.

``encode_consensus`` / ``encode_beacon`` / ``encode_telemetry`` must give exactly the bytes of
``encode`` of the message built the usual way, and refuse exactly what it refuses, with the same
reason. Every decoder first tries a quick check and only then the full ``validate``: whatever it
accepts the full check must accept too, and what it returns must equal what the long way
(``_decode_checked``) returns.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarm.core.agent import ConsensusMessage
from swarm.messages.wire import (
    WIRE_VERSION,
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
    consensus_from_wire,
    consensus_to_wire,
    telemetry_from_diagnostics,
)
from tests.helpers.wire_samples import (
    CODEC,
    MESSAGES,
    NS,
    PAYLOADS,
    SPECIAL,
    M,
    N,
    consensus_message,
    mutate,
    raw,
    real_agent_outputs,
    same_bits,
)

HUGE = 1.7976931348623157e308  # finite, but two of them overflow a sum
FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def outcome(call: Callable[[], Any]) -> tuple[str, Any]:
    """("ok", value) or ("error", WireError reason); any other exception fails the test."""
    try:
        return "ok", call()
    except WireError as err:
        return "error", err.reason


def same_outcome(short: Callable[[], Any], long: Callable[[], Any]) -> tuple[str, Any]:
    got, expected = outcome(short), outcome(long)
    assert got == expected
    return got


# -- encoders ----------------------------------------------------------------------------


def test_encode_consensus_gives_the_bytes_of_encode() -> None:
    for rnd in (0, 1, 2):
        message = consensus_message(round_=rnd)
        payload = CODEC.encode_consensus(message)
        assert payload == CODEC.encode(consensus_to_wire(message))
        assert CODEC.encode(message) == payload  # encode(ConsensusMessage) takes the short way
        back = CODEC.decode_consensus(payload)
        for name in ("information", "information_vector", "projector_mean", "weight_mean",
                     "projector_integral", "weight_integral", "gramian"):
            a, b = getattr(message, name), getattr(back, name)
            assert (a is None and b is None) or same_bits(a, b), name


def replace(message: ConsensusMessage, **changes: Any) -> ConsensusMessage:
    return dataclasses.replace(message, **changes)


def bad_consensus_messages() -> list[ConsensusMessage]:
    good, later = consensus_message(), consensus_message(round_=2)
    nan_info = good.information.copy()
    nan_info[1, 2, 3] = np.nan
    inf_gramian = good.gramian.copy()
    inf_gramian[0, 0, 0] = -np.inf
    return [
        replace(good, information=nan_info), replace(good, gramian=inf_gramian),
        replace(later, information_vector=np.full((M, NS), np.inf)),
        replace(good, sender=N), replace(good, sender=-1), replace(good, step=-3),
        replace(good, round=3), replace(good, sender=np.int64(2)), replace(good, sender=True),
        replace(good, sender=2.0), replace(good, gramian=None),
        replace(good, projector_mean=None, projector_integral=None, weight_mean=None,
                weight_integral=None, gramian=None),
        replace(later, weight_mean=good.weight_mean),
        replace(later, projector_mean=good.projector_mean,
                projector_integral=good.projector_integral, weight_mean=good.weight_mean,
                weight_integral=good.weight_integral, gramian=good.gramian),
        replace(good, information=good.information[:, :5, :5]),
        replace(good, information=np.zeros((M, NS + 1, NS + 1))),
        replace(good, information_vector=np.ones((M, NS), dtype=np.float32)),
        replace(good, information_vector=np.ones((M, NS), dtype=np.int64)),
        replace(good, information_vector=good.information_vector.tolist()),
        replace(good, weight_mean=good.weight_mean.astype(">f8")),
        replace(good, gramian=np.asfortranarray(good.gramian)),
        replace(good, information=None), replace(good, information="x"),
        replace(good, weight_mean=np.array(["a", "b"])),
        replace(good, information=np.full((M, NS, NS), HUGE)),  # valid: the sum overflows
    ]


BAD_CONSENSUS = bad_consensus_messages()


@pytest.mark.parametrize("index", range(len(BAD_CONSENSUS)))
def test_encode_consensus_refuses_what_encode_refuses(index: int) -> None:
    message = BAD_CONSENSUS[index]

    def long() -> bytes:
        try:
            wire = consensus_to_wire(message)
        except WireError:
            raise
        except Exception as exc:
            raise WireError(f"cannot encode ConsensusMessage: {type(exc).__name__}: {exc}"
                            ) from None
        return CODEC.encode(wire)

    same_outcome(lambda: CODEC.encode_consensus(message), long)


def test_consensus_whose_sum_overflows_is_still_sent_and_received() -> None:
    message = replace(consensus_message(), information=np.full((M, NS, NS), HUGE))
    payload = CODEC.encode_consensus(message)
    back = CODEC.decode_consensus(payload)
    assert same_bits(back.information, message.information)


finite = st.floats(allow_nan=False, allow_infinity=False)
anything = st.one_of(st.floats(), st.sampled_from([float(v) for v in SPECIAL]))


@FUZZ
@given(sender=st.integers(-2, N + 1), step=st.integers(-2, 10**12), time_s=anything,
       position=st.lists(anything, min_size=3, max_size=3),
       velocity=st.lists(anything, min_size=3, max_size=3), age=anything,
       stamp=st.integers(-2, 2**33), as_array=st.booleans())
def test_encode_beacon_matches_encode_of_build(sender, step, time_s, position, velocity, age,
                                               stamp, as_array) -> None:
    if as_array:
        position, velocity = np.array(position), np.array(velocity)
    same_outcome(
        lambda: CODEC.encode_beacon(sender, step, time_s, position, velocity_m_s=velocity,
                                    sample_age_s=age, vehicle_time_ms=stamp),
        lambda: CODEC.encode(BeaconWire.build(sender, step, time_s, position,
                                              velocity_m_s=velocity, sample_age_s=age,
                                              vehicle_time_ms=stamp)))


def test_encode_beacon_takes_numpy_numbers_and_lists() -> None:
    args = (np.int64(2), np.int32(7), np.float64(0.14), [1, 2, 3])
    assert CODEC.encode_beacon(*args) == CODEC.encode(BeaconWire.build(*args))
    assert CODEC.decode_beacon(CODEC.encode_beacon(*args)).position_m == (1.0, 2.0, 3.0)


COUNTERS = dict(qp_fallbacks=1, rejected_messages=2, missing_neighbour_messages=3,
                stale_neighbour_messages=4, late_steps=5, steps=6, neighbour_age_ms=float("nan"),
                mavlink_state="armed OFFBOARD")


def check_telemetry(diag, position, counters=None, **fields) -> tuple[str, Any]:
    def long() -> bytes:
        return CODEC.encode(telemetry_from_diagnostics(diag, position, counters, **fields))

    return same_outcome(lambda: CODEC.encode_telemetry(diag, position, counters, **fields), long)


def test_encode_telemetry_gives_the_bytes_of_encode() -> None:
    _, diag = real_agent_outputs()
    position = np.array([0.5, -0.0, 3.0])
    for fields in (COUNTERS, {**COUNTERS, "neighbour_age_ms": 12.5}, {}, {"late_steps": 2},
                   {**COUNTERS, "neighbour_age_ms": None}):
        assert check_telemetry(diag, position, **fields)[0] == "ok"
    assert check_telemetry(diag, position, TelemetryCounters(steps=3, neighbour_age_ms=1.0))[0] \
        == "ok"
    assert check_telemetry(diag, [0, 0, 3])[0] == "ok"
    decoded = CODEC.decode_telemetry(CODEC.encode_telemetry(diag, position, **COUNTERS))
    assert decoded.counters.neighbour_age_ms is None and decoded.counters.steps == 6
    back = decoded.to_diagnostics()
    for field in ("velocity", "estimates", "psi0", "weight_slacks"):
        assert same_bits(getattr(diag, field), getattr(back, field))


def diagnostics_variants() -> list[tuple[str, Any, dict[str, Any]]]:
    """(label, diagnostics, counter fields) that the short way must hand to the long way."""
    _, diag = real_agent_outputs()
    nan_psi = diag.psi1.copy()
    nan_psi[-1] = np.nan
    r = dataclasses.replace
    return [
        ("nan array", r(diag, psi1=nan_psi), COUNTERS),
        ("inf velocity", r(diag, velocity=np.array([0.0, np.inf, 0.0])), COUNTERS),
        ("huge values", r(diag, lambda_bar=np.full(M, HUGE)), COUNTERS),
        ("short array", r(diag, slacks=np.zeros(M - 1)), COUNTERS),
        ("wrong shape", r(diag, estimates=np.zeros((M, NS + 1))), COUNTERS),
        ("float32", r(diag, weights=diag.weights.astype(np.float32)), COUNTERS),
        ("int array", r(diag, weights=np.ones(M, dtype=np.int64)), COUNTERS),
        ("list", r(diag, psi0=diag.psi0.tolist()), COUNTERS),
        ("detected list", r(diag, detected=[True, False]), COUNTERS),
        ("detected ints", r(diag, detected=np.array([1, 0])), COUNTERS),
        ("detected short", r(diag, detected=np.array([True])), COUNTERS),
        ("drone", r(diag, drone_id=N), COUNTERS),
        ("numpy drone", r(diag, drone_id=np.int64(1)), COUNTERS),
        ("negative step", r(diag, step=-1), COUNTERS),
        ("nan time", r(diag, time_s=np.nan), COUNTERS),
        ("negative solve", r(diag, qp_solve_us=-1.0), COUNTERS),
        ("nan bearing", r(diag, bearing_error=np.nan), COUNTERS),
        ("bearing", r(diag, bearing_error=0.25), COUNTERS),
        ("long status", r(diag, qp_status="s" * 65), COUNTERS),
        ("negative missing", r(diag, missing_neighbour_messages=-2), COUNTERS),
        ("negative counter", diag, {**COUNTERS, "late_steps": -1}),
        ("float counter", diag, {**COUNTERS, "late_steps": 1.0}),
        ("bool counter", diag, {**COUNTERS, "steps": True}),
        ("numpy counter", diag, {**COUNTERS, "steps": np.int64(4)}),
        ("inf age", diag, {**COUNTERS, "neighbour_age_ms": np.inf}),
        ("negative age", diag, {**COUNTERS, "neighbour_age_ms": -1.0}),
        ("int age", diag, {**COUNTERS, "neighbour_age_ms": 3}),
        ("long label", diag, {**COUNTERS, "mavlink_state": "m" * 65}),
        ("label type", diag, {**COUNTERS, "mavlink_state": 5}),
    ]


DIAGNOSTICS_VARIANTS = diagnostics_variants()


@pytest.mark.parametrize("index", range(len(DIAGNOSTICS_VARIANTS)))
def test_encode_telemetry_refuses_what_encode_refuses(index: int) -> None:
    _label, diag, fields = DIAGNOSTICS_VARIANTS[index]
    check_telemetry(diag, np.array([0.5, 0.0, 3.0]), **fields)


def test_encode_telemetry_counter_argument_errors_are_the_same() -> None:
    _, diag = real_agent_outputs()
    for counters, fields in ((TelemetryCounters(), {"late_steps": 1}),
                             (None, {**COUNTERS, "late_stepz": 1}),
                             (None, {"late_stepz": 1, **{k: v for k, v in COUNTERS.items()
                                                         if k != "late_steps"}})):
        with pytest.raises(TypeError):
            CODEC.encode_telemetry(diag, [0, 0, 3], counters, **fields)
        with pytest.raises(TypeError):
            telemetry_from_diagnostics(diag, [0, 0, 3], counters, **fields)
    nan_counters = TelemetryCounters(neighbour_age_ms=float("nan"))
    assert check_telemetry(diag, [0, 0, 3], nan_counters)[0] == "error"


def test_encode_telemetry_for_another_swarm_size_is_refused() -> None:
    _, diag = real_agent_outputs()
    other = WireCodec(N, M + 1, NS)
    with pytest.raises(WireError, match="shape"):
        other.encode_telemetry(diag, [0, 0, 3], **COUNTERS)


# -- decoders ----------------------------------------------------------------------------


DECODE = {
    "consensus": (CODEC.decode_consensus, ConsensusWire),
    "beacon": (CODEC.decode_beacon, BeaconWire),
    "camera": (CODEC.decode_camera, CameraFrameWire),
    "truth": (CODEC.decode_truth, TruthWire),
    "clock": (CODEC.decode_clock, ClockWire),
    "telemetry": (CODEC.decode_telemetry, TelemetryWire),
}


def long_way(kind: str, payload: Any) -> Any:
    """Decode, then the full field-by-field validate (never the quick check)."""
    decoded = CODEC._decode_checked(payload, DECODE[kind][1])
    CODEC.validate(decoded)
    return consensus_from_wire(decoded) if kind == "consensus" else decoded


def check_decoders(payload: Any) -> None:
    """Every decoder: the short way accepts exactly what the full check accepts, equal."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy RuntimeWarning on hostile floats either
        for kind, (decode, _) in DECODE.items():
            short, long = outcome(lambda d=decode: d(payload)), outcome(
                lambda k=kind: long_way(k, payload))
            assert short[0] == long[0], (kind, short, long)
            if short[0] == "error":
                assert not short[1].startswith("internal"), short[1]
            elif kind == "consensus":
                for name in ("sender", "step", "round"):
                    assert getattr(short[1], name) == getattr(long[1], name)
                for name, array in consensus_to_wire(long[1]).arrays().items():
                    assert same_bits(getattr(short[1], name), array), name
            else:
                assert short[1] == long[1]


@pytest.mark.parametrize("name", list(PAYLOADS))
def test_decoders_short_and_long_way_agree_on_valid_payloads(name: str) -> None:
    check_decoders(PAYLOADS[name])
    check_decoders(bytearray(PAYLOADS[name]))
    check_decoders(memoryview(PAYLOADS[name]))


def test_decoded_consensus_arrays_are_independent_writable_views() -> None:
    message = CODEC.decode_consensus(PAYLOADS["consensus"])
    arrays = [message.information, message.information_vector, message.projector_mean,
              message.weight_mean, message.projector_integral, message.weight_integral,
              message.gramian]
    assert all(a.flags.writeable and a.flags.c_contiguous and a.dtype == np.float64
               for a in arrays)
    before = [a.copy() for a in arrays]
    message.weight_mean[:] = 7.0  # touches nothing else
    for k, (a, b) in enumerate(zip(arrays, before, strict=True)):
        if k != 3:
            assert same_bits(a, b)
    later = CODEC.decode_consensus(PAYLOADS["consensus_round"])
    assert later.round == 2 and later.gramian is None and later.projector_mean is None
    expected = consensus_from_wire(MESSAGES["consensus_round"])
    for name in ("information", "information_vector"):
        assert same_bits(getattr(later, name), getattr(expected, name))


def floats_with_trouble() -> st.SearchStrategy[float]:
    return st.one_of(st.floats(), st.sampled_from([HUGE, -HUGE, math.inf, -math.inf, math.nan,
                                                   -0.0, 5e-324]))


@FUZZ
@given(sender=st.integers(0, N + 1), step=st.integers(0, 3), time_s=floats_with_trouble(),
       p=st.lists(floats_with_trouble(), min_size=3, max_size=3),
       v=st.lists(floats_with_trouble(), min_size=3, max_size=3), age=floats_with_trouble(),
       version=st.sampled_from([WIRE_VERSION, WIRE_VERSION + 1]))
def test_beacon_fields_short_and_long_way_agree(sender, step, time_s, p, v, age,
                                                version) -> None:
    check_decoders(raw(BeaconWire(version=version, sender=sender, step=step, time_s=time_s,
                                  position_m=tuple(p), velocity_m_s=tuple(v),
                                  sample_age_s=age)))


@FUZZ
@given(sender=st.integers(0, N), rnd=st.integers(0, 3), m=st.sampled_from([M, M + 1]),
       n=st.sampled_from([NS, 3]), with_states=st.booleans(), fill=floats_with_trouble(),
       at=st.integers(0, 1000), extra=st.sampled_from([b"", b"\x00", bytes(8)]))
def test_consensus_fields_short_and_long_way_agree(sender, rnd, m, n, with_states, fill, at,
                                                   extra) -> None:
    floats = m * (n * n + n) + (29 * m if with_states else 0)
    data = np.random.default_rng(at).normal(size=floats)
    data[at % floats] = fill
    check_decoders(raw(ConsensusWire(sender=sender, step=at, round=rnd, n_targets=m, n_state=n,
                                     data=data.astype("<f8").tobytes() + extra)))


@FUZZ
@given(base=st.sampled_from(list(PAYLOADS)), mutations=st.lists(
    st.tuples(st.sampled_from(["flip", "set", "truncate", "insert", "delete", "dup"]),
              st.integers(0, 1 << 16), st.integers(0, 255), st.binary(min_size=1, max_size=16)),
    min_size=1, max_size=4))
def test_mutated_payloads_short_and_long_way_agree(base: str, mutations) -> None:
    check_decoders(mutate(PAYLOADS[base], mutations))


def test_seeded_float_mutations_short_and_long_way_agree() -> None:
    """Byte flips that land in floats mostly keep a payload valid: the quick checks see them."""
    rng = np.random.default_rng(5)
    for name, payload in PAYLOADS.items():
        for _ in range(300):
            buf = bytearray(payload)
            for _ in range(rng.integers(1, 3)):
                at = int(rng.integers(len(buf)))
                buf[at] = int(rng.choice([0x7F, 0xFF, 0xF0, 0xF8, int(rng.integers(256))]))
            check_decoders(bytes(buf))
        assert name


def test_quick_checks_never_accept_what_validate_refuses() -> None:
    """Directly: hand-made invalid messages fail each quick check (or validate accepts)."""
    cases = [
        msgspec.structs.replace(MESSAGES["beacon"], time_s=-0.5),
        msgspec.structs.replace(MESSAGES["beacon"], sample_age_s=math.nan),
        msgspec.structs.replace(MESSAGES["beacon"], position_m=(HUGE, HUGE, 0.0)),  # valid
        msgspec.structs.replace(MESSAGES["clock"], time_s=math.inf),
        msgspec.structs.replace(MESSAGES["camera"], vehicle_time_ms=-1),
        msgspec.structs.replace(MESSAGES["camera"], detections=(
            DetectionWire(1, 0.0, 0.0), DetectionWire(1, 0.5, 0.0))),
        msgspec.structs.replace(MESSAGES["camera"], detections=(DetectionWire(M, 0.0, 0.0),)),
        msgspec.structs.replace(MESSAGES["camera"], detections=(
            DetectionWire(0, math.inf, 0.0),)),
        msgspec.structs.replace(MESSAGES["camera"], target_velocities=F64Array.from_array(
            np.full((M, 3), np.nan))),
        msgspec.structs.replace(MESSAGES["camera"], target_velocities=F64Array.from_array(
            np.zeros((M + 1, 3)))),
        msgspec.structs.replace(MESSAGES["telemetry"], qp_solve_us=-2.0),
        msgspec.structs.replace(MESSAGES["telemetry"], bearing_error=math.inf),
        msgspec.structs.replace(MESSAGES["telemetry"], counters=TelemetryCounters(
            neighbour_age_ms=-1.0)),
        msgspec.structs.replace(MESSAGES["truth"], time_s=math.nan),
        msgspec.structs.replace(MESSAGES["consensus"], n_state=3),
    ]
    for message in cases:
        quick = CODEC._quick[type(message)]
        try:
            CODEC.validate(message)
            valid = True
        except WireError:
            valid = False
        assert valid or not quick(message), message
        check_decoders(raw(message))


def test_valid_messages_take_the_short_way(monkeypatch) -> None:
    """The agent's every-step messages never reach the field-by-field validate (or the generic
    encode): what makes them cheap."""
    calls: list[str] = []
    monkeypatch.setattr(WireCodec, "validate", lambda self, m: calls.append(type(m).__name__))
    monkeypatch.setattr(WireCodec, "_decode_checked",
                        lambda self, p, cls: calls.append(f"long {cls.__name__}"))
    codec = WireCodec(N, M, NS, n_rounds=3)
    message, diag = real_agent_outputs()
    rng = np.random.default_rng(3)
    later = ConsensusMessage(2, 5, 1, rng.normal(size=(M, NS, NS)), rng.normal(size=(M, NS)))
    payloads = [codec.encode_consensus(message), codec.encode_consensus(later),
                codec.encode_beacon(1, 2, 0.04, np.array([1.0, 2.0, 3.0]),
                                    velocity_m_s=np.zeros(3), sample_age_s=0.001),
                codec.encode_telemetry(diag, np.array([0.5, 0.0, 3.0]), **COUNTERS)]
    codec.encode_telemetry(diag, np.array([0.5, 0.0, 3.0]))  # counters left at their defaults
    codec.encode_telemetry(diag, np.array([0.5, 0.0, 3.0]), late_steps=2, steps=3)
    codec.encode_telemetry(diag, np.array([0.5, 0.0, 3.0]), TelemetryCounters(steps=1))
    assert calls == []
    codec.decode_consensus(payloads[0])
    codec.decode_consensus(payloads[1])
    codec.decode_beacon(payloads[2])
    codec.decode_telemetry(payloads[3])
    for name in ("camera", "camera_plain", "truth", "clock"):
        DECODE[name.split("_")[0]][0].__func__(codec, PAYLOADS[name])
    assert calls == []
