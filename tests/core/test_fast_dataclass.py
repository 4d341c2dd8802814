"""The hot path's records (swarm.core.fast_dataclass): each one the agent, the QP and the wire
make without ``__init__`` has exactly its class's fields, and none of those classes validates
in a ``__post_init__`` that this would skip."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from swarm.core.drone_step import ConsensusMessage, Detection, StepDiagnostics, StepResult
from swarm.core.qp import LocalQpWorkspace, QpSolution
from swarm.messages.wire import CameraFrameWire
from swarm.scenario.config import load_config
from swarm.scenario.setup import build_agent, initial_drone_positions
from swarm.scenario.world_step import Scene

CASE2 = Path(__file__).resolve().parents[2] / "configs" / "case2.toml"
RECORDS = (Detection, ConsensusMessage, StepDiagnostics, StepResult, QpSolution)


def complete(obj: object) -> bool:
    return set(vars(obj)) == {f.name for f in dataclasses.fields(type(obj))}


def test_the_record_classes_are_frozen_and_validate_nothing() -> None:
    for cls in RECORDS:
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, cls
        assert not hasattr(cls, "__post_init__"), cls


def test_every_record_of_a_swarm_step_has_exactly_its_fields() -> None:
    """Case 2 in process for 30 steps (control on from t = 0: the QP runs), each message also
    through the wire's fast decoder."""
    config = load_config(CASE2)
    config = dataclasses.replace(config, control=dataclasses.replace(config.control,
                                                                     start_s=0.0))
    n = config.swarm.n_drones
    codec, scene = config.wire_codec(), Scene(config, 0)
    agents = [build_agent(config, 0, i) for i in range(n)]
    positions = initial_drone_positions(config, 0)
    made: list[object] = []
    for k in range(30):
        view = scene.at(k, positions)
        frames = [codec.decode_camera(codec.encode(CameraFrameWire.build(
            drone=i, step=k, time_s=view.time_s, vehicle_time_ms=20 * k,
            detections=view.detections[i])))
            for i in range(n)]
        detections = [frame.detection_list() for frame in frames]
        made += [d for ds in detections for d in ds]
        messages = [agents[i].begin_step(k, positions[i], detections[i]) for i in range(n)]
        for _ in range(agents[0].n_rounds):
            decoded = [codec.decode_consensus(codec.encode_consensus(m)) for m in messages]
            made += messages + decoded
            messages = [agents[i].consensus_round({j: decoded[j] for j in
                                                   config.swarm.graph.neighbours[i]})
                        for i in range(n)]
        results = [agents[i].finish_step(dict(enumerate(positions))) for i in range(n)]
        made += results + [r.diagnostics for r in results]
        positions = positions + config.scenario.dt_s * np.array([r.velocity for r in results])
    kinds = {type(obj) for obj in made}
    assert kinds == {Detection, ConsensusMessage, StepDiagnostics, StepResult}
    assert all(complete(obj) for obj in made)
    assert any(r.diagnostics.qp_status not in ("inactive",) for r in results)


def test_both_ways_out_of_the_workspace_give_complete_solutions() -> None:
    workspace = LocalQpWorkspace(1, 1, relaxed=True, slack_weight=1e6, weight_floor=1e-3,
                                 u_max=3.0)
    easy = workspace.solve((0.5, 0.0, 0.0), [0.0] * 9, [-1.0, -1.0, -1.0], [0.5])
    hard = workspace.solve((0.5, 0.0, 0.0), [1.0, 0.0, 0.0] + [0.0] * 6, [1.0, -1.0, -1.0],
                           [0.5])
    assert (easy.status, hard.status) == ("NOMINAL_FEASIBLE", "DAQP_OPTIMAL")
    assert complete(easy) and complete(hard)
