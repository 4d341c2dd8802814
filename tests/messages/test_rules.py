"""The rules of the wire messages, declared on their fields (``swarm.messages.rules``): every
field declares one, the generated checks enforce exactly them, and a refusal names the field
and the kind of rule it broke."""

from __future__ import annotations

import math
from typing import Annotated, Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from swarm.messages import wire
from swarm.messages.rules import RULES, SwarmRules, WireError, declared_fields
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
)
from tests.helpers.wire_samples import CODEC, MESSAGES, NS, M, N, raw

FLOAT_MAX = 1.7976931348623157e308
FUZZ = settings(max_examples=400, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
KINDS = (ConsensusWire, BeaconWire, CameraFrameWire, TruthWire, ClockWire, TelemetryWire)
INSPECT = msgspec.inspect


def parts(cls: type) -> list[tuple[str, Any, dict[str, Any]]]:
    """(dotted name, type, markers) of every field of ``cls`` and of its nested parts."""
    out = []
    for name, t, extra, _ in declared_fields(cls):
        out.append((f"{cls.__name__}.{name}", t, extra))
        item = t.item_type if isinstance(t, INSPECT.VarTupleType) else t
        if isinstance(item, INSPECT.StructType) and item.cls is not F64Array:
            out += parts(item.cls)
    return out


@pytest.mark.parametrize("cls", KINDS, ids=lambda c: c.__name__)
def test_every_field_declares_its_rule(cls: type) -> None:
    """A field of a new message cannot go unchecked: each integer is >= 0 (the version is
    exactly this build's), each float finite, each string and list bounded, each array
    shaped, and raw bytes appear only as an array's data or a declared packing."""
    for name, t, extra in parts(cls):
        if isinstance(t, INSPECT.IntType):
            if name.endswith(".version"):
                assert t.ge == t.le == WIRE_VERSION, name
            else:
                assert t.ge == 0, name
        elif isinstance(t, INSPECT.FloatType):
            assert t.le == FLOAT_MAX and t.ge is not None and t.ge >= -FLOAT_MAX, name
        elif isinstance(t, INSPECT.StrType | INSPECT.VarTupleType):
            assert t.max_length is not None, name
        elif isinstance(t, INSPECT.TupleType):
            assert all(isinstance(f, INSPECT.FloatType) and f.le == FLOAT_MAX
                       for f in t.item_types), name
        elif isinstance(t, INSPECT.StructType):
            assert t.cls is not F64Array or "shape" in extra, name
        elif isinstance(t, INSPECT.BytesType):
            assert extra.get("packed") in ("consensus", "telemetry", "radio_links",
                                           "neighbours_heard"), name
        else:
            assert isinstance(t, INSPECT.BoolType | INSPECT.LiteralType), (name, t)


def test_markers_that_name_nothing_are_refused_when_compiled() -> None:
    class Odd(msgspec.Struct, array_like=True):
        sender: Annotated[int, msgspec.Meta(ge=0, extra={"bellow": "drones"})]

    class Unshaped(msgspec.Struct, array_like=True):
        values: F64Array

    class UnknownSize(msgspec.Struct, array_like=True):
        sender: Annotated[int, msgspec.Meta(ge=0, extra={"below": "planets"})]

    sizes = {"drones": N, "targets": M, "state": NS, "rounds": None}
    for cls, words in ((Odd, "unknown wire rule markers"), (Unshaped, "declare its shape"),
                       (UnknownSize, "unknown swarm size")):
        with pytest.raises(TypeError, match=words):
            SwarmRules(sizes, (cls,), array_type=F64Array, packings={})


def test_generated_checks_hold_only_the_swarms_rules() -> None:
    rules = SwarmRules({"drones": N, "targets": M, "state": NS, "rounds": 3},
                       (ConsensusWire, ClockWire, BeaconWire), array_type=F64Array,
                       packings={"consensus": wire._consensus_block})
    assert "pass" in rules.sources[ClockWire]  # msgspec checks every rule a clock has
    beacon = rules.sources[BeaconWire]
    assert f">= {N}" in beacon and "step" not in beacon and "time_s" not in beacon
    assert f">= {3}" in rules.sources[ConsensusWire]
    unbounded = SwarmRules({"drones": N, "targets": M, "state": NS, "rounds": None},
                           (ConsensusWire,), array_type=F64Array,
                           packings={"consensus": wire._consensus_block})
    assert "'round'" not in unbounded.sources[ConsensusWire]
    check = unbounded.checks[ConsensusWire]
    check(msgspec.structs.replace(MESSAGES["consensus_round"], round=10**9))


def rule_of(decode, payload: bytes) -> tuple[str, str]:
    with pytest.raises(WireError) as info:
        decode(payload)
    assert info.value.rule in RULES
    return info.value.rule, info.value.reason


def test_each_refusal_names_its_field_and_rule() -> None:
    beacon, camera, tel = MESSAGES["beacon"], MESSAGES["camera"], MESSAGES["telemetry"]
    r = msgspec.structs.replace
    cases = [
        (CODEC.decode_beacon, bytes(CODEC.max_payload_bytes + 1), "size", "exceeds"),
        (CODEC.decode_beacon, b"\xc1", "malformed", "malformed beacon message"),
        (CODEC.decode_beacon, raw(MESSAGES["clock"]), "kind", "expected a beacon message"),
        (CODEC.decode_beacon, raw(r(beacon, version=WIRE_VERSION + 1)), "version",
         f"wire version {WIRE_VERSION + 1}"),
        (CODEC.decode_beacon, raw(r(beacon, position_m=(0.0, "x", 0.0))), "type",
         "position_m[1]: Expected `float`, got `str`"),
        (CODEC.decode_beacon, raw(r(beacon, position_m=(0.0, math.nan, 0.0))), "finite",
         "position_m[1] is not finite (nan)"),
        (CODEC.decode_beacon, raw(r(beacon, sample_age_s=-1.0)), "range",
         "sample_age_s must be >= 0.0, got -1.0"),
        (CODEC.decode_beacon, raw(r(beacon, sender=N)), "range", "sender 6 out of range"),
        (CODEC.decode_camera, raw(r(camera, detections=(DetectionWire(0, 0.0, 0.0),
                                                        DetectionWire(0, 1.0, math.inf)))),
         "finite", "detections[1].y is not finite (inf)"),
        (CODEC.decode_camera, raw(r(camera, detections=(DetectionWire(0, 0.0, 0.0),
                                                        DetectionWire(M, 1.0, 0.0)))),
         "range", "detections[1].target 2 out of range"),
        (CODEC.decode_camera, raw(r(camera, detections=(DetectionWire(1, 0.0, 0.0),
                                                        DetectionWire(1, 1.0, 0.0)))),
         "duplicate", "target 1 appears twice in detections"),
        (CODEC.decode_camera, raw(r(camera, detections=(DetectionWire(0, 0.0, 0.0),) * 3)),
         "length", "detections holds 3 items, more than this swarm's 2 targets"),
        (CODEC.decode_telemetry, raw(r(tel, counters=TelemetryCounters(late_steps=-4))),
         "range", "counters.late_steps must be an integer >= 0, got -4"),
        (CODEC.decode_telemetry, raw(r(tel, detected=(True,))), "shape",
         "detected holds 1 items, this swarm has 2 targets"),
        (CODEC.decode_telemetry, raw(r(tel, qp_status="q" * 65)), "length",
         "qp_status has length 65"),
        (CODEC.decode_clock, raw(r(MESSAGES["clock"], state="flying")), "value",
         "state must be one of"),
        (CODEC.decode_truth, raw(r(MESSAGES["truth"], drone_positions=F64Array(
            (N, 3), bytes(8 * 3 * N - 8)))), "shape", "drone_positions carries"),
    ]
    for decode, payload, rule, words in cases:
        got = rule_of(decode, payload)
        assert got[0] == rule and words in got[1], (got, rule, words)


def floats_with_trouble() -> st.SearchStrategy[float]:
    return st.one_of(st.floats(), st.sampled_from([FLOAT_MAX, -FLOAT_MAX, math.inf, -math.inf,
                                                   math.nan, -0.0, 5e-324]))


@FUZZ
@given(sender=st.integers(0, N), rnd=st.integers(0, 3), m=st.sampled_from([M, M + 1]),
       n=st.sampled_from([NS, 3]), with_states=st.booleans(), fill=floats_with_trouble(),
       at=st.integers(0, 1000), extra=st.sampled_from([b"", b"\x00", bytes(8)]))
def test_consensus_decoder_accepts_exactly_the_valid_messages(sender, rnd, m, n, with_states,
                                                              fill, at, extra) -> None:
    floats = m * (n * n + n) + (29 * m if with_states else 0)
    data = np.random.default_rng(at).normal(size=floats)
    data[at % floats] = fill
    payload = raw(ConsensusWire(sender=sender, step=at, round=rnd, n_targets=m, n_state=n,
                                data=data.astype("<f8").tobytes() + extra))
    valid = (sender < N and rnd < 3 and (m, n) == (M, NS) and extra == b""
             and with_states == (rnd == 0) and math.isfinite(fill))
    try:
        message = CODEC.decode_consensus(payload)
    except WireError as err:
        assert not valid, err.reason
        return
    assert valid
    assert message.information.tobytes() == data[:M * NS * NS].tobytes()
    assert (message.gramian is None) == (rnd != 0)


@FUZZ
@given(targets=st.lists(st.integers(-1, M), max_size=M + 1), xs=st.lists(
    floats_with_trouble(), min_size=2 * (M + 1), max_size=2 * (M + 1)),
    time_s=floats_with_trouble())
def test_camera_decoder_accepts_exactly_the_valid_frames(targets, xs, time_s) -> None:
    detections = tuple(DetectionWire(k, xs[2 * j], xs[2 * j + 1])
                       for j, k in enumerate(targets))
    payload = raw(CameraFrameWire(drone=1, step=2, time_s=time_s, vehicle_time_ms=5,
                                  detections=detections))
    valid = (len(targets) <= M and all(0 <= k < M for k in targets)
             and len(set(targets)) == len(targets) and math.isfinite(time_s) and time_s >= 0
             and all(math.isfinite(xs[j]) for j in range(2 * len(targets))))
    try:
        frame = CODEC.decode_camera(payload)
    except WireError as err:
        assert not valid, err.reason
        return
    assert valid and [d.target for d in frame.detections] == targets


def test_an_unbounded_round_count_takes_any_round() -> None:
    codec = WireCodec(N, M, NS)
    later = msgspec.structs.replace(MESSAGES["consensus_round"], round=1000)
    assert codec.decode_consensus(raw(later)).round == 1000
    with pytest.raises(WireError, match="round 1000 out of range"):
        CODEC.decode_consensus(raw(later))
