"""The per-drone step: estimation, consensus, Gramian, barrier rows and the local QP.

One ``DroneAgent`` per drone. A step is split where the drone talks to its neighbours, so the
same object runs unchanged in the in-process reference runner and in a ``swarm-agent``
process that talks over Zenoh::

    message = agent.begin_step(step, position, detections)        # round-0 data, to neighbours
    for _ in range(K):                                              # K consensus rounds
        message = agent.consensus_round(inbox)                      # inbox: neighbours' messages
    result = agent.finish_step(beacons)                             # velocity + diagnostics

``consensus_round`` returns the message for the next round, or None after the K-th. The
agent never learns whether its neighbours are in-process or remote; a neighbour missing from
an inbox (lost or stale) is left out of the consensus sums and counted.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swarm.core import icf
from swarm.core.barrier import collision_row, localization_barrier, weight_sum_row
from swarm.core.dynamic_consensus import pi_consensus_step
from swarm.core.formation import bearing_error, bearing_formation_velocity
from swarm.core.gramian import gramian_step, initial_gramian
from swarm.core.params import ControlParams, EstimationParams, GramianParams, PerceptionParams
from swarm.core.perception import perception_terms
from swarm.core.projector import bearing_from_image_point, projector
from swarm.core.qp import INACTIVE_ROW_LOWER, QpSolution, QpSolver, build_local_qp

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Detection:
    """One camera detection: target id and its noisy image-plane point [x̄, ȳ] (SPEC §2)."""

    target: int
    image_point: Array


@dataclass(frozen=True)
class ConsensusMessage:
    """What drone ``sender`` sends its neighbours in round ``round`` of step ``step``.

    Round 0 also carries the continuous-time consensus states at the start of the step
    (SPEC §6); later rounds carry only the ICF information pair (SPEC §5).
    """

    sender: int
    step: int
    round: int
    information: Array  # V^κ, (M, n, n)
    information_vector: Array  # v^κ, (M, n)
    projector_mean: Array | None = None  # s for wΠ̂, (M, 3, 3)
    projector_integral: Array | None = None  # η for wΠ̂, (M, 3, 3)
    weight_mean: Array | None = None  # s for w, (M,)
    weight_integral: Array | None = None  # η for w, (M,)
    gramian: Array | None = None  # G copies, (M, 3, 3)

    def is_finite(self) -> bool:
        parts = [self.information, self.information_vector]
        parts += [a for a in (self.projector_mean, self.projector_integral, self.weight_mean,
                              self.weight_integral, self.gramian) if a is not None]
        return all(bool(np.isfinite(a).all()) for a in parts)


@dataclass(frozen=True)
class AgentSetup:
    """Everything a drone knows about the swarm before it starts (no state)."""

    drone_id: int
    n_drones: int
    n_targets: int
    dt_s: float
    neighbour_weights: Mapping[int, float]  # ICF consensus weights a_ij
    perception: PerceptionParams
    estimation: EstimationParams
    gramian: GramianParams
    control: ControlParams
    desired_bearings: Mapping[int, Array] = field(default_factory=dict)  # g*_ij per neighbour

    @property
    def neighbours(self) -> tuple[int, ...]:
        return tuple(sorted(self.neighbour_weights))


@dataclass(frozen=True)
class StepDiagnostics:
    """What one drone did in one step, for telemetry, checks and figures."""

    drone_id: int
    step: int
    time_s: float
    velocity: Array  # commanded u_i [m/s]
    nominal_velocity: Array  # u_d [m/s]
    estimates: Array  # x̂⁺ per target, (M, n)
    lambda_bar: Array  # λ̄ of the G copies, (M,)
    psi0: Array
    psi1: Array
    weights: Array  # w_ir, (M,)
    weight_sum_estimate: Array  # S_w, (M,)
    slacks: Array  # δ_ir, (M,)
    weight_slacks: Array  # δw_ir, (M,)
    detected: Array  # μ_ir, (M,) bool
    control_active: bool
    qp_status: str
    qp_iterations: int
    qp_fallback: bool  # the QP failed (or hard was infeasible) and a fallback was used
    qp_solve_us: float
    step_us: float  # compute time of this drone's step, without waiting for neighbours
    bearing_error: float | None
    missing_neighbour_messages: int  # consensus sums that ran without a neighbour this step
    rejected_inputs: int  # non-finite detections or messages dropped this step


@dataclass(frozen=True)
class StepResult:
    velocity: Array
    diagnostics: StepDiagnostics


class AgentStateError(RuntimeError):
    """The step API was called out of order (a bug in the caller, not bad data)."""


class DroneAgent:
    """State and step of one drone (SPEC §3-§10)."""

    def __init__(self, setup: AgentSetup, initial_target_guesses: Array) -> None:
        self.setup = setup
        m = setup.n_targets
        est = setup.estimation
        self._n_state = icf.state_dimension(est.model)
        self._transition = icf.transition_matrix(est.model, setup.dt_s)
        guesses = np.asarray(initial_target_guesses, dtype=float).reshape(m, 3)
        self._prior_state = np.zeros((m, self._n_state))
        self._prior_state[:, :3] = guesses
        self._prior_information = np.broadcast_to(np.eye(self._n_state),
                                                  (m, self._n_state, self._n_state)).copy()
        self._posterior_state = self._prior_state.copy()
        self._gramian = np.broadcast_to(initial_gramian(setup.gramian.epsilon), (m, 3, 3)).copy()
        self._projector_mean: Array | None = None  # set on the first step from u_i(0)
        self._projector_integral = np.zeros((m, 3, 3))
        self._weight_mean: Array | None = None
        self._weight_integral = np.zeros(m)
        self._solver_relaxed = QpSolver()
        self._solver_hard = QpSolver()
        # Per-step working state.
        self._phase = "idle"
        self._step = -1
        self._round = 0
        self._position = np.zeros(3)
        self._information = np.zeros((m, self._n_state, self._n_state))
        self._information_vector = np.zeros((m, self._n_state))
        self._round0: dict[int, ConsensusMessage] = {}
        self._detected = np.zeros(m, dtype=bool)
        self._communicated_velocity: Array | None = None
        self._missing = 0
        self._rejected = 0
        self._busy_s = 0.0  # own compute time in this step, excluding waits for neighbours
        # Running totals.
        self.qp_fallbacks = 0
        self.missing_neighbour_messages = 0
        self.rejected_inputs = 0

    # -- step API -----------------------------------------------------------------------

    @property
    def n_rounds(self) -> int:
        return self.setup.estimation.consensus_rounds

    def begin_step(
        self,
        step: int,
        position: Array,
        detections: Sequence[Detection],
        communicated_velocities: Array | None = None,
    ) -> ConsensusMessage:
        """Start step k: fold the detections into V⁰, v⁰ (2.4-2.5) and return round 0."""
        if self._phase != "idle":
            raise AgentStateError(f"begin_step({step}) called while in phase {self._phase!r}")
        entered = time.perf_counter()
        self._busy_s = 0.0
        setup = self.setup
        position = np.asarray(position, dtype=float)
        if position.shape != (3,) or not np.isfinite(position).all():
            raise ValueError(f"drone {setup.drone_id}: own position must be 3 finite numbers, "
                             f"got {position!r}")
        self._step, self._round, self._position = step, 0, position
        self._missing = self._rejected = 0
        measured: list[Array | None] = [None] * setup.n_targets
        for det in detections:
            point = np.asarray(det.image_point, dtype=float)
            if (not 0 <= det.target < setup.n_targets or point.shape != (2,)
                    or not np.isfinite(point).all()):
                self._rejected += 1
                continue
            measured[det.target] = projector(bearing_from_image_point(point))
        self._detected = np.array([p is not None for p in measured])
        if communicated_velocities is not None:
            self._communicated_velocity = np.asarray(communicated_velocities, dtype=float)
        if self._projector_mean is None:
            self._initialise_consensus_states()
        for r in range(setup.n_targets):
            self._information[r], self._information_vector[r] = icf.initial_information(
                self._prior_state[r], self._prior_information[r], measured[r], position,
                setup.n_drones, setup.estimation.info_gain)
        self._phase = "consensus"
        assert self._projector_mean is not None and self._weight_mean is not None
        self._busy_s += time.perf_counter() - entered
        return ConsensusMessage(
            sender=setup.drone_id, step=step, round=0,
            information=self._information.copy(),
            information_vector=self._information_vector.copy(),
            projector_mean=self._projector_mean.copy(),
            projector_integral=self._projector_integral.copy(),
            weight_mean=self._weight_mean.copy(),
            weight_integral=self._weight_integral.copy(),
            gramian=self._gramian.copy(),
        )

    def consensus_round(self, inbox: Mapping[int, ConsensusMessage]) -> ConsensusMessage | None:
        """Apply one ICF consensus iteration (2.6-2.7) with the neighbours' current-round data."""
        if self._phase != "consensus":
            raise AgentStateError(f"consensus_round called in phase {self._phase!r}")
        entered = time.perf_counter()
        usable = self._usable(inbox)
        if self._round == 0:
            self._round0 = usable
        weights = self.setup.neighbour_weights
        for r in range(self.setup.n_targets):
            self._information[r] = icf.consensus_iteration(
                self._information[r], ((weights[j], m.information[r]) for j, m in usable.items()))
            self._information_vector[r] = icf.consensus_iteration(
                self._information_vector[r],
                ((weights[j], m.information_vector[r]) for j, m in usable.items()))
        self._round += 1
        self._busy_s += time.perf_counter() - entered
        if self._round >= self.n_rounds:
            self._phase = "finish"
            return None
        return ConsensusMessage(self.setup.drone_id, self._step, self._round,
                                self._information.copy(), self._information_vector.copy())

    def finish_step(self, beacons: Mapping[int, Array]) -> StepResult:
        """Posterior and prediction, barrier rows, QP, then advance consensus and Gramian.

        ``beacons`` maps other drones' ids to their positions at this step (collision rows for
        those within R_ca, formation bearings for graph neighbours).
        """
        if self._phase != "finish":
            raise AgentStateError(f"finish_step called in phase {self._phase!r}")
        entered = time.perf_counter()
        setup, ctrl, gram = self.setup, self.setup.control, self.setup.gramian
        m, n_drones, dt = setup.n_targets, setup.n_drones, setup.dt_s
        position = self._position
        time_s = self._step * dt

        clean_beacons: dict[int, Array] = {}
        for j, p_j in beacons.items():
            p_j = np.asarray(p_j, dtype=float)
            if j == setup.drone_id or p_j.shape != (3,) or not np.isfinite(p_j).all():
                self._rejected += j != setup.drone_id
                continue
            clean_beacons[j] = p_j

        # ICF posterior and prediction (2.8-2.11).
        for r in range(m):
            state, info = icf.posterior(self._information[r], self._information_vector[r],
                                        n_drones)
            self._posterior_state[r] = state
            velocity_in = (self._communicated_velocity[r]
                           if setup.estimation.model == "single_integrator"
                           and self._communicated_velocity is not None else None)
            self._prior_state[r], self._prior_information[r] = icf.predict(
                state, info, self._transition, setup.estimation.process_noise,
                communicated_velocity=velocity_in, dt_s=dt)
        target_positions = self._posterior_state[:, :3]
        target_velocities = self._target_velocity_estimates()

        # Perception weights and barrier terms from the estimates (SPEC §3, §8).
        assert self._projector_mean is not None and self._weight_mean is not None
        terms = [perception_terms(position, target_positions[r], setup.perception)
                 for r in range(m)]
        barriers = [
            localization_barrier(
                self._gramian[r], self._projector_mean[r], terms[r], target_velocities[r],
                n_agents=n_drones, forgetting=gram.forgetting, epsilon=gram.epsilon,
                exponent=gram.smooth_min_exponent, info_gain=setup.estimation.info_gain)
            for r in range(m)
        ]
        weight_sums = n_drones * self._weight_mean

        nominal, formation_error = self._nominal_velocity(position, clean_beacons)
        control_active = time_s >= ctrl.start_s
        slacks = np.zeros(m)
        weight_slacks = np.zeros(m)
        qp_status, qp_iterations, qp_us, fallback = "inactive", 0, 0.0, False
        if control_active:
            qp_rows = self._qp_rows(barriers, terms, target_velocities, weight_sums, position,
                                    clean_beacons)
            solution, fallback = self._solve(nominal, qp_rows, np.array([t.weight for t in terms]))
            velocity = solution.velocity.copy() if solution.found else np.zeros(3)
            if solution.found and solution.z.shape[0] > 3:
                slacks, weight_slacks = solution.z[3:3 + m].copy(), solution.z[3 + m:].copy()
            qp_status, qp_iterations = solution.status, solution.iterations
            qp_us = solution.solve_time_s * 1e6
        else:
            velocity = np.clip(nominal, -ctrl.u_max_m_s, ctrl.u_max_m_s)

        # Advance the dynamic consensus (3.30) and the Gramian copies (3.29) to step k + 1,
        # with the neighbours' states at step k from round 0.
        weighted_projectors = np.array([t.weight * t.projector for t in terms])
        weights = np.array([t.weight for t in terms])
        nbrs = list(self._round0.values())
        old_projector_mean = self._projector_mean
        self._projector_mean, self._projector_integral = pi_consensus_step(
            self._projector_mean, self._projector_integral, weighted_projectors,
            [msg.projector_mean for msg in nbrs], [msg.projector_integral for msg in nbrs],
            gram.projector_consensus, dt)
        self._weight_mean, self._weight_integral = pi_consensus_step(
            self._weight_mean, self._weight_integral, weights,
            [msg.weight_mean for msg in nbrs], [msg.weight_integral for msg in nbrs],
            gram.weight_consensus, dt)
        self._gramian = gramian_step(
            self._gramian, old_projector_mean, [msg.gramian for msg in nbrs],
            n_agents=n_drones, forgetting=gram.forgetting, info_gain=setup.estimation.info_gain,
            consensus_gain=gram.consensus_gain, dt_s=dt)

        self.qp_fallbacks += int(fallback)
        self.missing_neighbour_messages += self._missing
        self.rejected_inputs += self._rejected
        self._phase = "idle"
        diagnostics = StepDiagnostics(
            drone_id=setup.drone_id, step=self._step, time_s=time_s,
            velocity=velocity, nominal_velocity=nominal,
            estimates=self._posterior_state.copy(),
            lambda_bar=np.array([b.lambda_bar for b in barriers]),
            psi0=np.array([b.psi0 for b in barriers]),
            psi1=np.array([b.psi1 for b in barriers]),
            weights=weights, weight_sum_estimate=weight_sums.copy(),
            slacks=slacks, weight_slacks=weight_slacks, detected=self._detected.copy(),
            control_active=control_active, qp_status=qp_status, qp_iterations=qp_iterations,
            qp_fallback=fallback, qp_solve_us=qp_us,
            step_us=(self._busy_s + time.perf_counter() - entered) * 1e6,
            bearing_error=formation_error, missing_neighbour_messages=self._missing,
            rejected_inputs=self._rejected,
        )
        return StepResult(velocity, diagnostics)

    # -- helpers ------------------------------------------------------------------------

    @property
    def gramian_copies(self) -> Array:
        return self._gramian.copy()

    @property
    def target_estimates(self) -> Array:
        return self._posterior_state.copy()

    def _usable(self, inbox: Mapping[int, ConsensusMessage]) -> dict[int, ConsensusMessage]:
        usable: dict[int, ConsensusMessage] = {}
        for j in self.setup.neighbours:
            msg = inbox.get(j)
            if msg is None:
                self._missing += 1
                continue
            if msg.sender != j or not self._well_formed(msg):
                self._rejected += 1
                continue
            usable[j] = msg
        return usable

    def _well_formed(self, msg: ConsensusMessage) -> bool:
        m, n = self.setup.n_targets, self._n_state
        if msg.information.shape != (m, n, n) or msg.information_vector.shape != (m, n):
            return False
        if msg.round == 0:
            shapes = ((msg.projector_mean, (m, 3, 3)), (msg.projector_integral, (m, 3, 3)),
                      (msg.weight_mean, (m,)), (msg.weight_integral, (m,)),
                      (msg.gramian, (m, 3, 3)))
            if any(a is None or a.shape != s for a, s in shapes):
                return False
        return msg.round == self._round and msg.is_finite()

    def _initialise_consensus_states(self) -> None:
        """s_i(0) = u_i(0) from the initial estimate, η_i(0) = 0 (SPEC §6)."""
        m = self.setup.n_targets
        terms = [perception_terms(self._position, self._prior_state[r, :3],
                                  self.setup.perception) for r in range(m)]
        self._projector_mean = np.array([t.weight * t.projector for t in terms])
        self._weight_mean = np.array([t.weight for t in terms])

    def _target_velocity_estimates(self) -> Array:
        if self.setup.estimation.model == "double_integrator":
            return self._posterior_state[:, 3:6]
        if self._communicated_velocity is None:
            return np.zeros((self.setup.n_targets, 3))
        return self._communicated_velocity

    def _nominal_velocity(
        self, position: Array, beacons: Mapping[int, Array]
    ) -> tuple[Array, float | None]:
        ctrl = self.setup.control
        if ctrl.task == "zero":
            return np.zeros(3), None
        neighbours = {j: beacons[j] for j in self.setup.neighbours if j in beacons}
        desired = self.setup.desired_bearings
        return (bearing_formation_velocity(position, neighbours, desired, ctrl.formation_gain),
                bearing_error(position, neighbours, desired))

    def _qp_rows(self, barriers, terms, target_velocities, weight_sums, position, beacons):
        ctrl, n = self.setup.control, self.setup.n_drones
        m = self.setup.n_targets
        loc_rows = np.array([b.lie_g for b in barriers]).reshape(m, 3)
        loc_lower = np.array([b.lower_bound for b in barriers])
        w_rows = np.zeros((m, 3))
        w_lower = np.zeros(m)
        for r in range(m):
            w_rows[r], w_lower[r] = weight_sum_row(terms[r], target_velocities[r],
                                                   float(weight_sums[r]), ctrl.gamma, n)
        col_rows = np.zeros((n - 1, 3))
        col_lower = np.full(n - 1, INACTIVE_ROW_LOWER)
        slot = 0
        for _, p_j in sorted(beacons.items()):
            if slot >= n - 1:
                break
            if np.linalg.norm(p_j - position) <= ctrl.collision_radius_m:
                col_rows[slot], col_lower[slot] = collision_row(
                    position, p_j, ctrl.collision_distance_m, ctrl.collision_gain)
                slot += 1
        return loc_rows, loc_lower, w_rows, w_lower, col_rows, col_lower

    def _solve(self, nominal: Array, rows, weights: Array) -> tuple[QpSolution, bool]:
        """Hard QP (3.37) or relaxed QP (3.36); hard failures fall back to relaxed (SPEC §9)."""
        ctrl = self.setup.control
        common = dict(slack_weight=ctrl.slack_weight, weight_floor=ctrl.weight_floor,
                      u_max=ctrl.u_max_m_s)
        if ctrl.qp == "hard":
            hard = self._solver_hard.solve(build_local_qp(nominal, *rows, weights,
                                                          relaxed=False, **common))
            if hard.found:
                return hard, False
        relaxed = self._solver_relaxed.solve(build_local_qp(nominal, *rows, weights,
                                                            relaxed=True, **common))
        return relaxed, ctrl.qp == "hard" or not relaxed.found
