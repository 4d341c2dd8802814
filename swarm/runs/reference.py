"""In-process reference runner: N ``DroneAgent``s, exact synchronous exchange, seeded.

The world (the scene of ``swarm.scenario.world_step``, the very one the world process renders,
and the vehicles' kinematics) and the agents live in one process and step in lockstep; every
neighbour message of round κ is delivered before round κ + 1. Same config and seed →
bit-identical output, and the same output as a lockstep run of the process swarm: the
autopilot link is modelled exactly as MAVLink carries it (positions and velocity setpoints as
float32 in each vehicle's local NED frame, ``swarm.models.frames``). Besides what the agents
compute, the runner integrates the true and measured Gramians from ground truth
(``swarm.runs.ground_truth``) for checking.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from swarm.core.drone_step import Detection, DroneAgent, StepDiagnostics
from swarm.messages.wire import (
    BeaconWire,
    CameraFrameWire,
    CameraImageWire,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
    telemetry_from_diagnostics,
)
from swarm.models.frames import position_over_link, velocity_over_link
from swarm.models.kinematics import step_vehicle
from swarm.runs.ground_truth import ReferenceGramians
from swarm.runs.record import RunRecord
from swarm.scenario.config import ScenarioConfig
from swarm.scenario.setup import build_agent, initial_drone_positions
from swarm.scenario.world_step import Scene

Array = NDArray[np.float64]

StepCallback = Callable[[int, list[StepDiagnostics]], None]


class MessageSink(Protocol):
    """Where a run's messages go as the process swarm's recorder would hear them (a
    ``swarm.observe.recording.writer.Recorder``)."""

    def put(self, message: BeaconWire | CameraFrameWire | CameraImageWire | TelemetryWire
            | TruthWire) -> None:
        ...


def run_reference(config: ScenarioConfig, seed: int | None = None,
                  on_step: StepCallback | None = None,
                  sink: MessageSink | None = None) -> RunRecord:
    """Run the scenario in one process and return every time series.

    ``sink``: also hand it, every step, the messages a process swarm's recording holds
    (telemetry, beacons, camera frames, truth, and rendered cameras' images;
    ``swarm.observe.recording.writer.record_reference``).
    """
    seed = config.scenario.seed if seed is None else seed
    return _run(config, seed, on_step, sink)


def _record_step(recorder: MessageSink, agents: list[DroneAgent], step: int, time_s: float,
                 positions: Array, seen: list[Array], flying: Array,
                 detections: list[list[Detection]], targets: Array, target_vel: Array,
                 communicated: Array | None, diags: list[StepDiagnostics],
                 links: NDArray[np.bool_] | None, images: list[bytes] | None) -> None:
    """One step as the process swarm's recorder would hear it: each agent's beacon (what it
    read from its autopilot and the velocity it flies) and telemetry, each camera frame (and
    rendered image), and the ground truth."""
    stamp_ms = round(time_s * 1000)
    for i, agent in enumerate(agents):
        frame = CameraFrameWire.build(drone=i, step=step, time_s=time_s,
                                      vehicle_time_ms=stamp_ms, detections=detections[i],
                                      target_velocities=communicated,
                                      radio_links=None if links is None else links[i])
        if images is not None:
            recorder.put(CameraImageWire.of_frame(frame, images[i]))
        recorder.put(frame)
        recorder.put(BeaconWire.build(sender=i, step=step, time_s=time_s, position_m=seen[i],
                                      velocity_m_s=flying[i]))
        counters = TelemetryCounters(
            qp_fallbacks=agent.qp_fallbacks, rejected_messages=agent.rejected_inputs,
            missing_neighbour_messages=agent.missing_neighbour_messages, steps=step + 1,
            mavlink_state="in-process", rate_limit_releases=agent.rate_limit_releases,
            safety_conflicts=agent.safety_conflicts, link_conflicts=agent.link_conflicts,
            splits_said=agent.splits_said)
        recorder.put(telemetry_from_diagnostics(diags[i], seen[i], counters,
                                                n_drones=len(agents)))
    recorder.put(TruthWire.build(step=step, time_s=time_s, drone_positions=positions,
                                 target_positions=targets, target_velocities=target_vel,
                                 radio_links=links))


def _run(config: ScenarioConfig, seed: int, on_step: StepCallback | None,
         recorder: MessageSink | None) -> RunRecord:
    """The run itself; every step also goes to ``recorder`` when one is given."""
    started = time.perf_counter()
    n, m, dt = config.swarm.n_drones, len(config.targets), config.scenario.dt_s
    steps = config.n_steps
    graph = config.swarm.graph
    agents = [build_agent(config, seed, i) for i in range(n)]
    scene = Scene(config, seed)
    positions = initial_drone_positions(config, seed)
    n_state = agents[0].target_estimates.shape[1]
    origins = [config.vehicles.origin_w(i) for i in range(n)]
    truth = ReferenceGramians(m, config.gramian, config.perception, config.estimation.info_gain,
                              dt)
    flying = np.zeros((n, 3))  # the setpoint each drone flies (its beacon's velocity)
    response = config.vehicles.velocity_response
    vehicle_velocities = np.zeros((n, 3))  # every drone starts hovering
    # Who hears whom: the scene's radio (network.topology = "range"), else the configured
    # graph.
    ranged = config.network.ranged
    neighbours = graph.neighbours

    rec: dict[str, Any] = {
        "pos": np.zeros((steps, n, 3)), "vel": np.zeros((steps, n, 3)),
        "tpos": np.zeros((steps, m, 3)), "tvel": np.zeros((steps, m, 3)),
        "est": np.zeros((steps, n, m, n_state)), "lam": np.zeros((steps, n, m)),
        "psi0": np.zeros((steps, n, m)), "psi1": np.zeros((steps, n, m)),
        "w": np.zeros((steps, n, m)), "slack": np.zeros((steps, n, m)),
        "wslack": np.zeros((steps, n, m)), "det": np.zeros((steps, n, m), dtype=bool),
        "true": np.zeros((steps, m)), "meas": np.zeros((steps, m)),
        "berr": np.full((steps, n), np.nan), "fb": np.zeros((steps, n), dtype=bool),
        "us": np.zeros((steps, n)), "conflict": np.zeros((steps, n), dtype=bool),
        "links": np.zeros((steps, n, n), dtype=bool) if ranged else None,
        "reached": np.zeros((steps, n), dtype=np.int64),
        "link_conflict": np.zeros((steps, n), dtype=bool),
    }
    for k in range(steps):
        view = scene.at(k, positions)
        t, targets, target_vel = view.time_s, view.target_positions_m, view.target_velocities_m_s
        detections, communicated = view.detections, view.communicated_velocities_m_s
        # What each agent reads from its autopilot (LOCAL_POSITION_NED, float32 NED).
        seen = [position_over_link(positions[i], origins[i]) for i in range(n)]
        messages = [agents[i].begin_step(k, seen[i], detections[i], communicated)
                    for i in range(n)]
        if view.links is not None:
            rec["links"][k] = view.links
            neighbours = tuple(view.radio_neighbours(i) or () for i in range(n))
        for _ in range(agents[0].n_rounds):
            inboxes = [{j: messages[j] for j in neighbours[i]} for i in range(n)]
            replies = [agents[i].consensus_round(inboxes[i]) for i in range(n)]
            messages = [m for m in replies if m is not None]  # the last round answers none
        beacons = {i: p.tolist() for i, p in enumerate(seen)}  # as an agent's exchange has them
        results = [agents[i].finish_step(beacons) for i in range(n)]
        diags = [r.diagnostics for r in results]
        if recorder is not None:
            _record_step(recorder, agents, k, t, positions, seen, flying, detections, targets,
                         target_vel, communicated, diags, view.links, view.images)
            flying = np.array([r.velocity for r in results])

        rec["pos"][k], rec["tpos"][k], rec["tvel"][k] = positions, targets, target_vel
        for i, d in enumerate(diags):
            rec["vel"][k, i] = d.velocity
            rec["est"][k, i] = d.estimates
            rec["lam"][k, i], rec["psi0"][k, i], rec["psi1"][k, i] = d.lambda_bar, d.psi0, d.psi1
            rec["w"][k, i], rec["slack"][k, i], rec["wslack"][k, i] = (
                d.weights, d.slacks, d.weight_slacks)
            rec["det"][k, i], rec["fb"][k, i], rec["us"][k, i] = (
                d.detected, d.qp_fallback, d.step_us)
            rec["conflict"][k, i] = d.safety_conflict
            rec["reached"][k, i], rec["link_conflict"][k, i] = d.reached, d.link_conflict
            if d.bearing_error is not None:
                rec["berr"][k, i] = d.bearing_error
        rec["true"][k], rec["meas"][k] = truth.lambda_min()
        truth.advance(positions, targets, rec["det"][k])
        if on_step is not None:
            on_step(k, diags)
        # The vehicle applies the float32 setpoint it received, clamped to u_max, through its
        # velocity response (ideal by default: p + ΔT·u), exactly as the emulated vehicles.
        for i in range(n):
            positions[i], vehicle_velocities[i] = step_vehicle(
                positions[i], vehicle_velocities[i], velocity_over_link(results[i].velocity),
                config.control.u_max_m_s, dt, response)

    return RunRecord(
        config=config, seed=seed, times_s=np.arange(steps, dtype=np.float64) * dt,
        drone_positions_m=rec["pos"], velocities_m_s=rec["vel"],
        target_positions_m=rec["tpos"], target_velocities_m_s=rec["tvel"],
        estimates=rec["est"], lambda_bar=rec["lam"], psi0=rec["psi0"], psi1=rec["psi1"],
        weights=rec["w"], slacks=rec["slack"], weight_slacks=rec["wslack"],
        detected=rec["det"], true_lambda_min=rec["true"], measured_lambda_min=rec["meas"],
        bearing_errors=rec["berr"], qp_fallback=rec["fb"], step_us=rec["us"],
        wall_time_s=time.perf_counter() - started, safety_conflict=rec["conflict"],
        links=rec["links"], reached=rec["reached"] if ranged else None,
        link_conflict=rec["link_conflict"] if ranged else None,
    )
