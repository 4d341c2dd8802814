"""The agent's own encoders (``encode_consensus``, ``encode_beacon``, ``encode_telemetry``):
one conversion from the core's types, then ``encode``, which checks the bytes the way a peer
will. What each refuses, and why (the rule it names), is stated here case by case."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarm.core.consensus_message import (
    ARRAY_NAMES,
    STATE_NAMES,
    ConsensusMessage,
    ConsensusMessageError,
)
from swarm.messages.wire import (
    BeaconWire,
    TelemetryCounters,
    WireCodec,
    WireError,
    consensus_to_wire,
    telemetry_from_diagnostics,
)
from tests.helpers.wire_samples import (
    CODEC,
    NS,
    SPECIAL,
    M,
    N,
    consensus_message,
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
    """``message`` with other header fields (``dataclasses.replace``) or other arrays (packed
    again by ``ConsensusMessage.of_arrays``, which may refuse them)."""
    arrays = {name: changes.pop(name) for name in ARRAY_NAMES if name in changes}
    if arrays:
        given = {**dict.fromkeys(STATE_NAMES), **message.arrays(), **arrays}
        message = ConsensusMessage.of_arrays(
            message.sender, message.step, message.round, given.pop("information"),
            given.pop("information_vector"), **given)
    return dataclasses.replace(message, **changes)


def raw_message(rnd: int = 0, **changes: Any) -> ConsensusMessage:
    """A message made directly (not by ``of_arrays``), for what the encoder must refuse."""
    good = consensus_message(round_=rnd)
    return dataclasses.replace(good, **changes)


def bad_consensus_messages() -> list[Callable[[], ConsensusMessage]]:
    """Ways to make a consensus message, most of them wrong: each is built inside the test
    (``of_arrays`` refuses some of them before any encoder sees them)."""
    good, later = consensus_message(), consensus_message(round_=2)
    nan_info = good.information.copy()
    nan_info[1, 2, 3] = np.nan
    inf_gramian = good.gramian.copy()
    inf_gramian[0, 0, 0] = -np.inf
    full, pair = good.data.shape[0], later.data.shape[0]
    return [
        lambda: replace(good, information=nan_info), lambda: replace(good, gramian=inf_gramian),
        lambda: replace(later, information_vector=np.full((M, NS), np.inf)),
        lambda: replace(good, sender=N), lambda: replace(good, sender=-1),
        lambda: replace(good, step=-3), lambda: replace(good, round=3),
        lambda: replace(good, sender=np.int64(2)), lambda: replace(good, sender=True),
        lambda: replace(good, sender=2.0), lambda: replace(good, gramian=None),
        lambda: replace(good, projector_mean=None, projector_integral=None, weight_mean=None,
                        weight_integral=None, gramian=None),
        lambda: replace(later, weight_mean=good.weight_mean),
        lambda: replace(later, projector_mean=good.projector_mean,
                        projector_integral=good.projector_integral,
                        weight_mean=good.weight_mean, weight_integral=good.weight_integral,
                        gramian=good.gramian),
        lambda: replace(good, information=good.information[:, :5, :5]),
        lambda: replace(good, information=np.zeros((M, NS + 1, NS + 1))),
        lambda: replace(good, information_vector=np.ones((M, NS), dtype=np.float32)),
        lambda: replace(good, information_vector=np.ones((M, NS), dtype=np.int64)),
        lambda: replace(good, information_vector=good.information_vector.tolist()),
        lambda: replace(good, weight_mean=good.weight_mean.astype(">f8")),
        lambda: replace(good, gramian=np.asfortranarray(good.gramian)),
        lambda: replace(good, information=None), lambda: replace(good, information="x"),
        lambda: replace(good, weight_mean=np.array(["a", "b"])),
        lambda: replace(good, information=np.full((M, NS, NS), HUGE)),  # valid: sum overflows
        # made directly, not by of_arrays:
        lambda: raw_message(data=good.data[:-1]), lambda: raw_message(data=good.data.tolist()),
        lambda: raw_message(data=good.data.reshape(-1, 2)),
        lambda: raw_message(data=good.data.astype(np.float32)),
        lambda: raw_message(data=good.data.astype(">f8")),
        lambda: raw_message(data=np.zeros(full, dtype=np.int64)),
        lambda: raw_message(2, data=good.data), lambda: raw_message(0, data=later.data[:pair]),
        lambda: raw_message(n_targets=M + 1), lambda: raw_message(n_state=np.int64(NS)),
        lambda: raw_message(n_targets=M + 1, data=np.zeros(full + 29 + NS * (NS + 1))),
    ]


BAD_CONSENSUS = bad_consensus_messages()
# What each of BAD_CONSENSUS gives: "ok" (converted as the core's arrays would be), the rule of
# the encoder's refusal and a word of its reason, or "made": ``of_arrays`` refuses the arrays
# (a ``ConsensusMessageError``) and no message exists to send.
CONSENSUS_OUTCOMES = [
    ("finite", "information contains"), ("finite", "gramian contains"),
    ("finite", "information_vector contains"), ("range", "sender 6 out of range"),
    ("range", "sender must be an integer >= 0"), ("range", "step must be an integer >= 0"),
    ("range", "round 3 out of range"), ("ok", ""), ("type", "sender: Expected `int`"),
    ("type", "sender: Expected `int`, got `float`"), ("made", "gramian missing"),
    ("shape", "round 0 without the consensus states"), ("made", "incomplete"),
    ("shape", "must not carry"), ("made", "information_vector has shape"),
    ("made", "information_vector has shape"), ("ok", ""), ("ok", ""), ("ok", ""), ("ok", ""),
    ("ok", ""), ("made", "information has shape ()"), ("made", "information has shape ()"),
    ("made", "weight_mean is not numbers: ValueError"), ("ok", ""),
    ("shape", "does not fit M = 2"), ("shape", "consensus data list does not fit"),
    ("shape", "does not fit M = 2"), ("finite", "information contains"), ("ok", ""),
    ("type", "consensus data must be floats, got int64"), ("shape", "must not carry"),
    ("shape", "round 0 without the consensus states"), ("shape", "does not fit M = 3"),
    ("type", "consensus sizes must be integers"), ("shape", "n_targets 3 does not match"),
]


@pytest.mark.parametrize("index", range(len(BAD_CONSENSUS)))
def test_encode_consensus_refuses_with_the_rule_broken(index: int) -> None:
    build = BAD_CONSENSUS[index]
    rule, words = CONSENSUS_OUTCOMES[index]
    if rule == "made":
        with pytest.raises(ConsensusMessageError, match=words.replace("(", r"\(").replace(
                ")", r"\)")):
            build()
        return
    message = build()
    got = outcome(lambda: CODEC.encode_consensus(message))
    if rule == "ok":
        assert got[0] == "ok", got
        back = CODEC.decode_consensus(got[1])  # sent as float64, C order
        assert np.array_equal(back.information_vector, np.asarray(
            message.information_vector, dtype=np.float64))
        assert np.array_equal(back.data, np.asarray(message.data, dtype=np.float64))
    else:
        assert got[0] == "error" and words in got[1], got
        with pytest.raises(WireError) as info:
            CODEC.encode_consensus(message)
        assert info.value.rule == rule
    assert same_outcome(lambda: CODEC.encode_consensus(message),
                        lambda: CODEC.encode(message))


def test_consensus_whose_sum_overflows_is_still_sent_and_received() -> None:
    message = replace(consensus_message(), information=np.full((M, NS, NS), HUGE))
    payload = CODEC.encode_consensus(message)
    back = CODEC.decode_consensus(payload)
    assert same_bits(back.information, message.information)


finite = st.floats(allow_nan=False, allow_infinity=False)
anything = st.one_of(st.floats(), st.sampled_from([float(v) for v in SPECIAL]))


def beacon_is_valid(sender: int, step: int, time_s: float, position, velocity, age: float,
                    stamp: int) -> bool:
    """SPEC §12's beacon, said plainly: the test's own statement of the rules."""
    return (0 <= sender < N and step >= 0 and stamp >= 0 and math.isfinite(time_s)
            and time_s >= 0 and math.isfinite(age) and age >= 0
            and all(math.isfinite(v) for v in (*position, *velocity)))


@FUZZ
@given(sender=st.integers(-2, N + 1), step=st.integers(-2, 10**12), time_s=anything,
       position=st.lists(anything, min_size=3, max_size=3),
       velocity=st.lists(anything, min_size=3, max_size=3), age=anything,
       stamp=st.integers(-2, 2**33), as_array=st.booleans())
def test_encode_beacon_accepts_exactly_the_valid_beacons(sender, step, time_s, position,
                                                         velocity, age, stamp,
                                                         as_array) -> None:
    valid = beacon_is_valid(sender, step, time_s, position, velocity, age, stamp)
    if as_array:
        position, velocity = np.array(position), np.array(velocity)
    got = same_outcome(
        lambda: CODEC.encode_beacon(sender, step, time_s, position, velocity_m_s=velocity,
                                    sample_age_s=age, vehicle_time_ms=stamp),
        lambda: CODEC.encode(BeaconWire.build(sender, step, time_s, position,
                                              velocity_m_s=velocity, sample_age_s=age,
                                              vehicle_time_ms=stamp)))
    assert (got[0] == "ok") == valid, got
    if valid:
        back = CODEC.decode_beacon(got[1])
        assert (back.sender, back.step, back.vehicle_time_ms) == (sender, step, stamp)
        assert back.position_m == tuple(float(v) for v in position)


def test_encode_beacon_takes_numpy_numbers_and_lists() -> None:
    args = (np.int64(2), np.int32(7), np.float64(0.14), [1, 2, 3])
    assert CODEC.encode_beacon(*args) == CODEC.encode(BeaconWire.build(*args))
    assert CODEC.decode_beacon(CODEC.encode_beacon(*args)).position_m == (1.0, 2.0, 3.0)


COUNTERS = dict(qp_fallbacks=1, rejected_messages=2, missing_neighbour_messages=3,
                stale_neighbour_messages=4, late_steps=5, steps=6, neighbour_age_ms=float("nan"),
                mavlink_state="armed OFFBOARD")


def check_telemetry(diag, position, counters=None, **fields) -> tuple[str, Any]:
    def long() -> bytes:
        return CODEC.encode(telemetry_from_diagnostics(diag, position, counters,
                                                       n_drones=CODEC.n_drones, **fields))

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
# label: "ok" (converted: float32, ints, lists, numpy numbers become what the wire carries),
# or (rule, words of the reason).
TELEMETRY_OUTCOMES: dict[str, Any] = {
    "nan array": ("finite", "psi1 contains a non-finite value"),
    "inf velocity": ("finite", "velocity contains"), "huge values": "ok",
    "short array": ("shape", "slacks has shape (1,)"),
    "wrong shape": ("shape", "n_state 7 does not match"), "float32": "ok", "int array": "ok",
    "list": "ok", "detected list": "ok", "detected ints": "ok",
    "detected short": ("shape", "detected holds 1 items"),
    "drone": ("range", "drone 6 out of range"), "numpy drone": "ok",
    "negative step": ("range", "step must be an integer >= 0"),
    "nan time": ("finite", "time_s is not finite"),
    "negative solve": ("range", "qp_solve_us must be >= 0"),
    "nan bearing": ("finite", "bearing_error is not finite"), "bearing": "ok",
    "long status": ("length", "qp_status has length 65"),
    "negative missing": ("range", "missing_neighbour_messages must be an integer >= 0"),
    "negative counter": ("range", "counters.late_steps must be an integer >= 0"),
    "float counter": ("type", "counters.late_steps: Expected `int`, got `float`"),
    "bool counter": ("type", "counters.steps: Expected `int`, got `bool`"),
    "numpy counter": ("type", "numpy.int64"),
    "inf age": ("finite", "counters.neighbour_age_ms is not finite"),
    "negative age": ("range", "counters.neighbour_age_ms must be >= 0"), "int age": "ok",
    "long label": ("length", "counters.mavlink_state has length 65"),
    "label type": ("type", "counters.mavlink_state: Expected `str`, got `int`"),
}


@pytest.mark.parametrize("index", range(len(DIAGNOSTICS_VARIANTS)))
def test_encode_telemetry_refuses_with_the_rule_broken(index: int) -> None:
    label, diag, fields = DIAGNOSTICS_VARIANTS[index]
    expected = TELEMETRY_OUTCOMES[label]
    got = check_telemetry(diag, np.array([0.5, 0.0, 3.0]), **fields)
    if expected == "ok":
        assert got[0] == "ok", (label, got)
        assert CODEC.decode_telemetry(got[1]).drone == int(diag.drone_id)
        return
    rule, words = expected
    assert got[0] == "error" and words in got[1], (label, got)
    with pytest.raises(WireError) as info:
        CODEC.encode_telemetry(diag, np.array([0.5, 0.0, 3.0]), **fields)
    assert info.value.rule == rule, (label, info.value.rule)


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


