"""Valid wire messages of every kind, their payloads and ways to break them (tests/messages)."""

from __future__ import annotations

from collections.abc import Callable

import msgspec
import numpy as np
import pytest
from hypothesis import strategies as st

from swarm.core.drone_step import AgentSetup, ConsensusMessage, Detection, DroneAgent
from swarm.core.params import ControlParams, EstimationParams, GramianParams, PerceptionParams
from swarm.messages.wire import (
    BeaconRelayWire,
    BeaconWire,
    CameraFrameWire,
    ClockWire,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
    WireCodec,
    WireError,
    consensus_to_wire,
    telemetry_from_diagnostics,
)

N, M, NS = 6, 2, 6  # drones, targets, ICF state dimension


CODEC = WireCodec(N, M, NS, n_rounds=3)


SPECIAL = np.array([-0.0, 0.0, 5e-324, -2.5e-310, 2.2250738585072014e-308, 1.7976931348623157e308,
                    -1.7976931348623157e308, 0.1 + 0.2, 1.0 / 3.0, -1e-300, np.nextafter(1.0, 2)])


RNG = np.random.default_rng(1)


def tricky(*shape: int) -> np.ndarray:
    """Random normals with the SPECIAL values spread through them."""
    a = RNG.normal(size=shape).ravel()
    a[::2][: min(len(SPECIAL), len(a[::2]))] = SPECIAL[: len(a[::2])]
    return a.reshape(shape)


def consensus_message(round_: int = 0, sender: int = 3, step: int = 17) -> ConsensusMessage:
    extras = {}
    if round_ == 0:
        extras = dict(projector_mean=tricky(M, 3, 3), projector_integral=tricky(M, 3, 3),
                      weight_mean=tricky(M), weight_integral=tricky(M), gramian=tricky(M, 3, 3))
    return ConsensusMessage.of_arrays(sender, step, round_, tricky(M, NS, NS), tricky(M, NS),
                                      **extras)


def real_agent_outputs():
    """A real round-0 message and real diagnostics from the core's per-drone step."""
    setup = AgentSetup(
        drone_id=0, n_drones=N, n_targets=M, dt_s=0.02, neighbour_weights={1: 0.2, 5: 0.2},
        perception=PerceptionParams(), estimation=EstimationParams(), gramian=GramianParams(),
        control=ControlParams(start_s=0.0))
    agent = DroneAgent(setup, np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]]))
    message = agent.begin_step(0, np.array([0.5, -0.25, 3.0]),
                               [Detection(1, np.array([0.01, -0.02]))])
    agent.consensus_round({})
    result = agent.finish_step({1: np.array([2.0, 0.0, 3.0])})
    return message, result.diagnostics


def telemetry_message() -> TelemetryWire:
    _, diag = real_agent_outputs()
    counters = TelemetryCounters(qp_fallbacks=2, rejected_messages=3,
                                 missing_neighbour_messages=4, stale_neighbour_messages=5,
                                 late_steps=6, neighbour_age_ms=12.5, mavlink_state="offboard")
    return telemetry_from_diagnostics(diag, np.array([0.5, -0.0, 3.0]), counters)


def valid_messages() -> dict[str, object]:
    return {
        "consensus": consensus_to_wire(consensus_message()),
        "consensus_round": consensus_to_wire(consensus_message(round_=2)),
        "beacon": BeaconWire.build(5, 3, 0.06, [-0.0, 5e-324, 1.7976931348623157e308],
                                   vehicle_time_ms=0xFFFF_FFFF),
        "beacons": BeaconRelayWire.build(11, (
            (BeaconWire.build(1, 10, 0.2, [-0.0, 5e-324, 2.0], velocity_m_s=(0.5, -0.0, 0.0),
                              sample_age_s=0.003, vehicle_time_ms=77), 0.0125),
            (BeaconWire.build(4, 9, 0.18, [1.0, 2.0, 3.0]), 0.0))),
        "beacons_none": BeaconRelayWire(step=0),
        "camera": CameraFrameWire.build(2, 9, 0.18, 123456,
                              [Detection(1, np.array([-0.0, 0.1 + 0.2])),
                               Detection(0, np.array([5e-324, -1e-300]))],
                              target_velocities=tricky(M, 3)),
        "camera_lockstep": CameraFrameWire.build(3, 9, 0.18, 123456, [],
                                                 drone_positions=tricky(N, 3)),
        "camera_plain": CameraFrameWire.build(0, 0, 0.0, 0, []),
        "camera_radio": CameraFrameWire.build(1, 9, 0.18, 123456, [],
                                              radio_links=[True, False, True, True, False,
                                                           False]),
        "truth": TruthWire.build(4, 0.08, tricky(N, 3), tricky(M, 3), tricky(M, 3)),
        "truth_radio": TruthWire.build(4, 0.08, tricky(N, 3), tricky(M, 3), tricky(M, 3),
                                       radio_links=np.eye(N, k=1, dtype=bool)
                                       | np.eye(N, k=-1, dtype=bool)),
        "clock": ClockWire(step=7, time_s=0.14, state="running", mode="lockstep", detail="ok"),
        "telemetry": telemetry_message(),
        "telemetry_radio": telemetry_from_diagnostics(
            real_agent_outputs()[1], np.array([0.5, -0.0, 3.0]), n_drones=N),
    }


MESSAGES = valid_messages()


PAYLOADS = {name: CODEC.encode(msg) for name, msg in MESSAGES.items()}


KIND_OF = {name: name.split("_")[0] for name in MESSAGES}


def raw(message) -> bytes:
    """Encode without the codec's checks (what a buggy or hostile sender could put on the wire)."""
    return msgspec.msgpack.encode(message)


def decode_only_wire_error(decode: Callable[[bytes], object], payload: bytes) -> None:
    try:
        decode(payload)
    except WireError as err:
        assert "\n" not in str(err)
        assert not err.reason.startswith("internal"), err.reason


def reason_of(decode: Callable[[bytes], object], payload: bytes) -> str:
    with pytest.raises(WireError) as info:
        decode(payload)
    return info.value.reason


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype == np.float64 and a.shape == b.shape and a.tobytes() == b.tobytes()


MUTATIONS = st.lists(
    st.tuples(st.sampled_from(["flip", "set", "truncate", "insert", "delete", "dup"]),
              st.integers(0, 1 << 16), st.integers(0, 255), st.binary(min_size=1, max_size=16)),
    min_size=1, max_size=6)


def mutate(payload: bytes, mutations) -> bytes:
    buf = bytearray(payload)
    for op, position, byte, blob in mutations:
        at = position % max(len(buf), 1)
        if op == "flip" and buf:
            buf[at] ^= 1 << (byte % 8)
        elif op == "set" and buf:
            buf[at] = byte
        elif op == "truncate":
            del buf[at:]
        elif op == "insert":
            buf[at:at] = blob
        elif op == "delete":
            del buf[at:at + 1 + byte % 16]
        elif op == "dup":
            buf[at:at] = buf[at:at + 1 + byte % 64]
    return bytes(buf)
