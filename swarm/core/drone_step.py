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

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swarm.core import icf, kernels
from swarm.core.consensus_layout import ConsensusLayout
from swarm.core.consensus_message import ConsensusMessage, message_layout, message_size
from swarm.core.fast_dataclass import record
from swarm.core.formation import bearing_formation_scalars
from swarm.core.gramian import initial_gramian
from swarm.core.kernels import ROW
from swarm.core.network import NetworkParams, ReachTracker, keep_row
from swarm.core.params import ControlParams, EstimationParams, GramianParams, PerceptionParams
from swarm.core.perception import perception_terms
from swarm.core.qp import (
    FailedQp,
    LocalQpWorkspace,
    QpSolution,
    estimate_free_rows,
    rate_limited_box,
)
from swarm.core.safety import SafetyParams, safety_conflict, safety_rows
from swarm.errors import VigilError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Detection:
    """One camera detection: target id and its noisy image-plane point [x̄, ȳ] (SPEC §2)."""

    target: int
    image_point: Array


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
    safety: SafetyParams = field(default_factory=SafetyParams)  # the envelope's hard rows
    # The radio (``swarm.core.network``): with topology "range" the neighbours of a step are
    # the drones heard in its round 0 (``neighbour_weights`` then names every other drone,
    # each with the weight 1/N), and the drone tracks how far its news reaches.
    network: NetworkParams = field(default_factory=NetworkParams)
    kept_links: tuple[int, ...] = ()  # drones kept within R_keep by barrier rows (keep rows)

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
    estimate_covariance: Array  # position block of P⁺ = pinv(W⁺) per target, (M, 3, 3) [m²]
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
    rate_limit_released: bool  # no solution within the rate box: solved without it
    safety_conflict: bool  # localization slack used while an envelope row held u back
    qp_solve_us: float
    step_us: float  # compute time of this drone's step, without waiting for neighbours
    bearing_error: float | None
    missing_neighbour_messages: int  # consensus sums that ran without a neighbour this step
    rejected_inputs: int  # non-finite detections or messages dropped this step
    # The radio (topology "range"; with "fixed": the configured neighbours and N): the
    # neighbours heard in round 0, the drones this one's news reaches (itself included:
    # fewer than N means the swarm has split), the smallest R_keep − ‖p_i − p_j‖ of its kept
    # links [m, +inf without keep rows] and whether a keep row held u back while
    # localization slack was used.
    neighbours_heard: tuple[int, ...] = ()
    reached: int = 0
    keep_margin_m: float = math.inf
    link_conflict: bool = False


@dataclass(frozen=True)
class StepResult:
    velocity: Array
    diagnostics: StepDiagnostics


@dataclass(frozen=True)
class TargetPrior:
    """The ICF prior of every target, what the next step starts from (SPEC §5): x̂⁻ and W⁻.

    Given to ``DroneAgent`` in place of the initial guesses, it is the prior of the first
    step (a drone that resumes with what it knew); ``DroneAgent.snapshot`` shows it."""

    state: Array  # x̂⁻ per target, (M, n): position [m], then velocity [m/s] if estimated
    information: Array  # W⁻ per target, (M, n, n)


@dataclass(frozen=True)
class AgentSnapshot:
    """A copy of a drone's filter and consensus state between two calls of the step API
    (``DroneAgent.snapshot``), for tests and tools: its arrays are copies, read-only."""

    phase: str  # "idle" (next: begin_step), "consensus" (consensus_round), "finish"
    step: int  # the step under way or last finished (-1 before the first)
    rounds_done: int  # consensus rounds done in this step
    position: Array  # the own position of the step [m]
    last_command: tuple[float, float, float]  # u of the last step [m/s] (the rate box's)
    prior: TargetPrior  # of the next begin_step (the prediction of the last finish_step)
    posterior_state: Array  # x̂⁺ per target of the last finish_step, (M, n)
    icf_pair: Array  # the ICF pair (V, v) after the latest round, packed (``message_layout``)
    consensus_states: Array  # s, η and G packed (SPEC §6, ``ConsensusLayout``)
    disagreement: Array  # Σ_j (x_i − x_j) of the round-0 consensus states of this step
    missing_this_step: int  # consensus sums without a neighbour so far in this step
    rejected_this_step: int  # inputs dropped so far in this step


class AgentStateError(VigilError, RuntimeError):
    """The step API was called out of order (a bug in the caller, not bad data)."""


# Sections of the step timed in ``DroneAgent.section_us`` (benchmarks/bench_step.py).
SECTIONS = ("estimation", "consensus", "barrier", "qp", "other")
ESTIMATION, CONSENSUS, BARRIER, QP, OTHER = range(len(SECTIONS))


class SectionClock:
    """Compute time of one step by section (``SECTIONS``), kept out of the math: each call of
    the step starts with ``begin()`` and ends each section with ``lap(section)``, which adds
    the time since the previous mark to it; ``busy_s`` is the step's own compute time so far
    (waits for neighbours between its calls excluded)."""

    __slots__ = ("busy_s", "mark", "seconds")

    def __init__(self) -> None:
        self.seconds = [0.0] * len(SECTIONS)
        self.busy_s = self.mark = 0.0

    def reset(self) -> None:
        """A new step."""
        self.seconds = [0.0] * len(SECTIONS)
        self.busy_s = 0.0

    def begin(self) -> None:
        self.mark = time.perf_counter()

    def lap(self, section: int) -> None:
        now = time.perf_counter()
        elapsed = now - self.mark
        self.seconds[section] += elapsed
        self.busy_s += elapsed
        self.mark = now

    def running_s(self) -> float:
        """``busy_s`` including the section under way."""
        return self.busy_s + time.perf_counter() - self.mark


class DroneAgent:
    """State and step of one drone (SPEC §3-§10).

    The step runs on stacks over the M targets and on plain floats for 3-vectors, because on
    arrays this small each numpy call costs far more than its arithmetic: the ICF local steps
    and the perception and barrier terms of all targets in one call each of the compiled
    kernels (``swarm.core.kernels``: ``icf.StackedFilter``, ``perception_barrier_rows``), the
    QP's rows from those in one more (``qp_rows``), the neighbours' data of a round gathered
    in one array with the own state as its first row, the consensus states (SPEC §6) packed
    in one vector and advanced by one precomputed linear operator, the QP in preallocated
    matrices (``LocalQpWorkspace``). The array functions of
    ``swarm.core`` compute the same quantities up to round-off (the ICF consensus sums are even
    bit-identical to ``consensus_iteration``: same terms, same order; the perception terms bit
    for bit too).
    """

    def __init__(self, setup: AgentSetup, initial_target_guesses: Array | TargetPrior, *,
                 last_command_m_s: Sequence[float] | None = None) -> None:
        """``initial_target_guesses``: each target's position (M, 3) [m], the prior of the
        first step with zero velocity and W⁻ = I; or the whole prior (``TargetPrior``).
        ``last_command_m_s``: the velocity the vehicle was last commanded (the first step's
        rate box is around it; default zero)."""
        self.setup = setup
        m = setup.n_targets
        est, gram, ctrl = setup.estimation, setup.gramian, setup.control
        n = self._n_state = icf.state_dimension(est.model)
        # N of the formulas: the drones taking part now (``set_swarm_size``); the
        # N-dependent constants below are rebuilt when it changes.
        self._swarm_size = setup.n_drones
        self._filter = icf.StackedFilter(icf.transition_matrix(est.model, setup.dt_s),
                                         est.process_noise, setup.n_drones, setup.dt_s)
        if isinstance(initial_target_guesses, TargetPrior):
            self._prior_state, self._prior_information = _checked_prior(
                initial_target_guesses, setup.drone_id, m, n)
        else:
            guesses = np.asarray(initial_target_guesses, dtype=float).reshape(m, 3)
            self._prior_state = np.zeros((m, n))
            self._prior_state[:, :3] = guesses
            self._prior_information = np.broadcast_to(np.eye(n), (m, n, n)).copy()
        self._posterior_state = self._prior_state.copy()
        self._position_covariance = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()  # pinv(I)
        # ICF pair (V, v) packed as one vector, as ``kernels.initial_information`` writes it
        # and a consensus message carries it (``message_layout``): (where, shape) of each.
        pair = {name: (slice(start, stop), shape)
                for name, shape, start, stop in message_layout(m, n, False)}
        self._information_at, self._vector_at = pair["information"], pair["information_vector"]
        self._icf = np.zeros(message_size(m, n, False))
        # Consensus states packed as one vector (SPEC §6, ``ConsensusLayout``).
        self._layout = layout = ConsensusLayout(m)
        self._cons_array = np.zeros(layout.size)
        self._cons_array[layout.gramian] = np.tile(initial_gramian(gram.epsilon).ravel(), m)
        self._consensus_started = False  # s_i(0) = u_i(0) is set on the first step
        self._disagreement = np.zeros(layout.size)  # Σ_j (x_i − x_j) of the round-0 states
        self._operator = _consensus_operator(layout, setup.dt_s, gram,
                                             est.info_gain * setup.n_drones)
        self._message_size = message_size(m, n, with_states=True)
        # The radio (``swarm.core.network``): with topology "range", round 0 also carries the
        # reach stamps (N floats after the consensus states) and N follows the component.
        net = setup.network
        self._reach = (ReachTracker(setup.drone_id, setup.n_drones, net.reach_slack_steps)
                       if net.ranged else None)
        self._message_size += setup.n_drones if net.ranged else 0
        self._reached = setup.n_drones
        self._kept = tuple(sorted(setup.kept_links))
        self._keep_range_m, self._keep_gain = net.kept_range_m, net.keep_gain
        self._n_keep_rows = 0
        self._keep_margin_m = math.inf
        # g*_ij of the formation task as float triples (SPEC §10), made once.
        self._desired_bearings = {j: tuple(np.asarray(g, dtype=float).reshape(3).tolist())
                                  for j, g in setup.desired_bearings.items()}
        self._neighbours = setup.neighbours
        self._barrier_constants = self._kernel_constants(setup.n_drones)
        self._row_constants = self._qp_row_constants(setup.n_drones)
        self._single_integrator = est.model == "single_integrator"
        # Rows for the drones within R_ca only: the QP's size depends on them, not on N.
        self._qp_relaxed = LocalQpWorkspace(
            m, relaxed=True, slack_weight=ctrl.slack_weight, weight_floor=ctrl.weight_floor,
            u_max=ctrl.u_max_m_s, solver=ctrl.qp_solver)
        self._qp_hard = (LocalQpWorkspace(
            m, relaxed=False, slack_weight=ctrl.slack_weight, weight_floor=ctrl.weight_floor,
            u_max=ctrl.u_max_m_s, solver=ctrl.qp_solver) if ctrl.qp == "hard" else None)
        # |u_k − u_(k−1)| ≤ a_max·ΔT per component (0: no limit), from the last command.
        self._max_change = ctrl.command_accel_limit_m_s2 * setup.dt_s
        self._n_safety_rows = setup.safety.n_rows  # the last rows of every QP
        self._last_command = _ZERO3
        if last_command_m_s is not None:
            command = np.asarray(last_command_m_s, dtype=float)
            if command.shape != (3,) or not _all_finite(command.tolist()):
                raise ValueError(f"drone {setup.drone_id}: last command must be 3 finite "
                                 f"numbers [m/s], got {last_command_m_s!r}")
            self._last_command = (float(command[0]), float(command[1]), float(command[2]))
        # Per-step working state.
        self._phase = "idle"
        self._step = -1
        self._round = 0
        self._heard: tuple[int, ...] = ()
        self._position = np.zeros(3)
        self._own = [0.0, 0.0, 0.0]
        self._detected = np.zeros(m, dtype=bool)
        self._communicated_velocity: Array | None = None
        self._missing = 0
        self._rejected = 0
        self._clock = SectionClock()
        # Running totals.
        self.qp_fallbacks = 0
        self.rate_limit_releases = 0
        self.safety_conflicts = 0
        self.link_conflicts = 0
        self.splits_said = 0  # times this drone found its part of the swarm smaller than N
        # The QPs of the last step that got no acceptable solution (``FailedQp``), in the
        # order they were tried; emptied when a step begins.
        self.qp_failures: list[FailedQp] = []
        self.missing_neighbour_messages = 0
        self.rejected_inputs = 0

    # -- step API -----------------------------------------------------------------------

    @property
    def n_rounds(self) -> int:
        return self.setup.estimation.consensus_rounds

    @property
    def swarm_size(self) -> int:
        """N used in the formulas (SPEC §5-§8): the live membership, ``setup.n_drones`` at
        start."""
        return self._swarm_size

    def set_swarm_size(self, n_live: int) -> None:
        """Take N = ``n_live`` drones in the formulas from the next step on: the 1/N and N of
        the information consensus (2.4-2.9), bN in the Gramian copies (3.29), S_w = N s_w and
        the 1/N shares of the barrier rows (3.32, 3.34-3.36).

        For a swarm whose membership changes (a drone lost or rejoined). Every member must
        use the same N: the consensus averages over the drones that exchange data. The PI
        consensus (3.30) then tracks the average of the members' own inputs whatever states
        a lost drone left behind: the integral states enter the estimates only through
        neighbour differences, so their leftover sum does not bias the equilibrium. The
        collision rows keep their ``setup.n_drones − 1`` slots.
        """
        n_live = int(n_live)
        if not 1 <= n_live <= self.setup.n_drones:
            raise ValueError(f"drone {self.setup.drone_id}: swarm size must be in "
                             f"1..{self.setup.n_drones}, got {n_live}")
        if self._phase != "idle":
            raise AgentStateError(f"set_swarm_size called in phase {self._phase!r}")
        if n_live == self._swarm_size:
            return
        setup, est, gram = self.setup, self.setup.estimation, self.setup.gramian
        self._swarm_size = n_live
        self._filter = icf.StackedFilter(self._filter.transition, est.process_noise, n_live,
                                         setup.dt_s)
        self._operator = _consensus_operator(self._layout, setup.dt_s, gram,
                                             est.info_gain * n_live)
        self._barrier_constants = self._kernel_constants(n_live)
        self._row_constants = self._qp_row_constants(n_live)

    def begin_step(
        self,
        step: int,
        position: Array,
        detections: Sequence[Detection],
        communicated_velocities: Array | None = None,
        camera_position: Array | None = None,
    ) -> ConsensusMessage:
        """Start step k: fold the detections into V⁰, v⁰ (2.4-2.5) and return round 0.

        ``camera_position``: where the detections were taken from, when that is not
        ``position`` (a realtime frame rendered from an older pose of the vehicle); the
        measurement (2.15) is made from it, everything else from ``position``.
        """
        if self._phase != "idle":
            raise AgentStateError(f"begin_step({step}) called while in phase {self._phase!r}")
        if self._reach is not None:
            self._follow_component(step)
        clock = self._clock
        clock.reset()
        clock.begin()
        setup = self.setup
        m = setup.n_targets
        position = np.ascontiguousarray(position, dtype=float)
        if position.shape != (3,) or not _all_finite(own := position.tolist()):
            raise ValueError(f"drone {setup.drone_id}: own position must be 3 finite numbers, "
                             f"got {position!r}")
        self._step, self._round, self._position, self._own = step, 0, position, own
        seen_from = own
        if camera_position is not None:
            camera = np.asarray(camera_position, dtype=float)
            if camera.shape != (3,) or not _all_finite(seen_from := camera.tolist()):
                raise ValueError(f"drone {setup.drone_id}: camera position must be 3 finite "
                                 f"numbers, got {camera_position!r}")
        self._missing = self._rejected = 0
        if self.qp_failures:
            self.qp_failures = []
        image_points = [0.0] * (2 * m)  # the measured [x̄, ȳ] of each target (SPEC §4)
        detected = [0.0] * m  # μ: 1.0 for a target seen this step
        for det in detections:
            point = np.asarray(det.image_point, dtype=float)
            if (not 0 <= det.target < m or point.shape != (2,)
                    or not _all_finite(xy := point.tolist())):
                self._rejected += 1
                continue
            image_points[2 * det.target:2 * det.target + 2] = xy
            detected[det.target] = 1.0
        self._detected = np.array(detected, dtype=bool)
        if communicated_velocities is not None:
            self._communicated_velocity = np.asarray(communicated_velocities, dtype=float)
        if not self._consensus_started:
            self._initialise_consensus_states()
        clock.lap(OTHER)
        # V⁰ = W⁻/N + bμ[[Π,0],[0,0]], v⁰ = W⁻x̂⁻/N + bμ[Πp_i; 0] (2.4-2.5, 2.15), Π of the
        # measured bearing, for every target in one compiled call (icf.initial_information).
        packed = np.empty_like(self._icf)
        kernels.initial_information(self._prior_information, self._prior_state,
                                    float(self._swarm_size), setup.estimation.info_gain,
                                    seen_from, image_points, detected, packed)
        self._icf = packed
        self._phase = "consensus"
        clock.lap(ESTIMATION)
        message = self._message(0, with_states=True)
        clock.lap(OTHER)
        return message

    def _follow_component(self, step: int) -> None:
        """Topology "range": stamp this step and take N = the drones the stamps still reach
        (``ReachTracker``): a component of the split swarm sums its own information only."""
        reach = self._reach
        assert reach is not None
        reach.stamp(step)
        reached = int(np.count_nonzero(reach.reached(step)))
        if reached < self.setup.n_drones <= self._reached:
            self.splits_said += 1
        self._reached = reached
        if reached != self._swarm_size:
            self.set_swarm_size(reached)

    def consensus_round(self, inbox: Mapping[int, ConsensusMessage]) -> ConsensusMessage | None:
        """Apply one ICF consensus iteration (2.6-2.7) with the neighbours' current-round data.

        In round 0 it also takes the neighbours' consensus states (SPEC §6) that
        ``finish_step`` advances.
        """
        if self._phase != "consensus":
            raise AgentStateError(f"consensus_round called in phase {self._phase!r}")
        self._clock.begin()
        first = self._round == 0
        blocks, weights = self._gather(inbox, first)
        # a + Σ_j a_ij (a_j − a) of the ICF pair in neighbour order, as ``consensus_iteration``
        # adds them (2.6-2.7), and in round 0 Σ_j (x_i − x_j) of the consensus states
        # (3.29-3.30); a block with a non-finite number is left out and counted.
        icf = np.empty_like(self._icf)
        if first:
            self._disagreement = np.empty_like(self._cons_array)
            self._rejected += kernels.consensus_sums(self._icf, self._cons_array, blocks,
                                                     weights, icf, self._disagreement)
        else:
            self._rejected += kernels.consensus_sums(self._icf, None, blocks, weights, icf,
                                                     None)
        self._icf = icf
        self._round += 1
        if self._round >= self.n_rounds:
            self._phase = "finish"
            message = None
        else:
            message = self._message(self._round, with_states=False)
        self._clock.lap(CONSENSUS)
        return message

    def finish_step(self, beacons: Mapping[int, Sequence[float]]) -> StepResult:
        """Posterior and prediction, barrier rows, QP, then advance consensus and Gramian.

        ``beacons`` maps other drones' ids to their positions at this step (collision rows for
        those within R_ca, formation bearings for graph neighbours).
        """
        if self._phase != "finish":
            raise AgentStateError(f"finish_step called in phase {self._phase!r}")
        clock = self._clock
        clock.begin()
        setup, ctrl = self.setup, self.setup.control
        m = setup.n_targets
        time_s = self._step * setup.dt_s
        own = self._own
        clean_beacons = self._clean_beacons(beacons)
        clock.lap(OTHER)

        estimates, target_velocities = self._estimate()
        clock.lap(ESTIMATION)

        terms, rows, weight_sums = self._barrier_terms(estimates, target_velocities)
        weights = [row[ROW.WEIGHT] for row in rows]
        nominal, formation_error = self._nominal_velocity(own, clean_beacons)
        # Localization and weight-sum rows from control.start_s on (filter warm-up before);
        # the safety rows (collision, envelope) from the first step (SPEC §9).
        control_active = time_s >= ctrl.start_s
        box = (rate_limited_box(self._last_command, self._max_change, ctrl.u_max_m_s)
               if self._max_change > 0.0 else None)
        u_rows, lower = self._qp_rows(terms, target_velocities, weight_sums, own, clean_beacons)
        if not control_active:
            estimate_free_rows(u_rows, lower, 2 * m)
        clock.lap(BARRIER)
        solution, fallback, released = self._solve(nominal, u_rows, lower, weights, box)
        clock.lap(QP)
        if solution.found:
            velocity = solution.z[:3].copy()
        else:  # SPEC §9: the safest input; within the rate box, braking as hard as it lets
            velocity = np.array(_clip3(_ZERO3, box) if box is not None else _ZERO3)
        found_slacks = solution.found and solution.z.shape[0] > 3
        slacks = solution.z[3:3 + m].copy() if found_slacks else np.zeros(m)
        weight_slacks = solution.z[3 + m:].copy() if found_slacks else np.zeros(m)
        n_keep = self._n_keep_rows
        conflict = found_slacks and self._n_safety_rows > 0 and safety_conflict(
            u_rows, lower, self._n_safety_rows, solution.z[:3].tolist(),
            solution.z[3:].tolist(), skip_last=n_keep)
        link_conflict = found_slacks and n_keep > 0 and safety_conflict(
            u_rows, lower, n_keep, solution.z[:3].tolist(), solution.z[3:].tolist())
        qp_status, qp_iterations = solution.status, solution.iterations
        qp_us = solution.solve_time_s * 1e6
        self._last_command = tuple(velocity.tolist())
        clock.lap(OTHER)

        # Advance the dynamic consensus (3.30) and the Gramian copies (3.29) to step k + 1,
        # with the neighbours' states at step k from round 0.
        self._advance_consensus(rows, weights)
        clock.lap(CONSENSUS)

        self.qp_fallbacks += int(fallback)
        self.rate_limit_releases += int(released)
        self.safety_conflicts += int(conflict)
        self.link_conflicts += int(link_conflict)
        self.missing_neighbour_messages += self._missing
        self.rejected_inputs += self._rejected
        self._phase = "idle"
        series = np.array([row[ROW.LAMBDA_BAR] for row in rows]
                          + [row[ROW.PSI0] for row in rows] + [row[ROW.PSI1] for row in rows]
                          + weights + weight_sums)
        diagnostics = record(StepDiagnostics, dict(
            drone_id=setup.drone_id, step=self._step, time_s=time_s,
            velocity=velocity,
            nominal_velocity=np.array(nominal) if nominal is not _ZERO3 else np.zeros(3),
            estimates=self._posterior_state.copy(),
            estimate_covariance=self._position_covariance,
            lambda_bar=series[0:m], psi0=series[m:2 * m], psi1=series[2 * m:3 * m],
            weights=series[3 * m:4 * m], weight_sum_estimate=series[4 * m:],
            slacks=slacks, weight_slacks=weight_slacks, detected=self._detected,
            control_active=control_active, qp_status=qp_status, qp_iterations=qp_iterations,
            qp_fallback=fallback, rate_limit_released=released, safety_conflict=conflict,
            qp_solve_us=qp_us,
            step_us=clock.running_s() * 1e6,
            bearing_error=formation_error, missing_neighbour_messages=self._missing,
            rejected_inputs=self._rejected,
            neighbours_heard=self._heard, reached=self._reached,
            keep_margin_m=self._keep_margin_m, link_conflict=link_conflict,
        ))
        clock.lap(OTHER)
        return record(StepResult, {"velocity": velocity, "diagnostics": diagnostics})

    def _estimate(self) -> tuple[Array, Array]:
        """ICF posterior and prediction (2.8-2.11), all targets at once, from the consensus
        result. Returns the posterior estimates (M, n) and the targets' velocities the barrier
        uses (M, 3: estimated, communicated or zero)."""
        m = self.setup.n_targets
        packed = self._icf
        (information, information_shape), (vector, vector_shape) = (self._information_at,
                                                                    self._vector_at)
        posterior_state, self._prior_state, self._prior_information, covariance = self._filter(
            packed[information].reshape(information_shape), packed[vector].reshape(vector_shape),
            self._communicated_velocity if self._single_integrator else None)
        self._posterior_state = posterior_state
        self._position_covariance = covariance[:, :3, :3].copy()  # contiguous, as sent
        if not self._single_integrator:
            return posterior_state, np.ascontiguousarray(posterior_state[:, 3:6])
        if self._communicated_velocity is not None:
            return posterior_state, np.ascontiguousarray(self._communicated_velocity)
        return posterior_state, np.zeros((m, 3))

    def _barrier_terms(self, estimates: Array, target_velocities: Array
                       ) -> tuple[Array, list[list[float]], list[float]]:
        """Perception weights and barrier terms from the estimates (SPEC §3, §8), one row per
        target through the compiled kernel (``kernels.perception_barrier_rows``: the array and
        its rows as lists, read by ``kernels.ROW``), and the weight sums S_w = N · s_w of the
        consensus."""
        layout = self._layout
        cons_array = self._cons_array
        terms = kernels.perception_barrier_rows(
            self._position, estimates, target_velocities, cons_array[layout.gramian],
            cons_array[layout.projector_mean], self._barrier_constants)
        weight_sums = [self._swarm_size * w for w in cons_array[layout.weight_mean].tolist()]
        return terms, terms.tolist(), weight_sums

    def _kernel_constants(self, n_agents: int) -> Array:
        est, gram = self.setup.estimation, self.setup.gramian
        return kernels.barrier_constants(
            self.setup.perception, n_agents=n_agents, forgetting=gram.forgetting,
            epsilon=gram.epsilon, exponent=gram.smooth_min_exponent, info_gain=est.info_gain)

    def _qp_row_constants(self, n_agents: int) -> list[float]:
        """``kernels.qp_rows``' constants for N = ``n_agents``: N, γ, R_ca, Δ, α_ca, ē and the
        localization share (``control.localization_share``)."""
        ctrl = self.setup.control
        return kernels.qp_row_constants({
            "n_agents": float(n_agents), "gamma": ctrl.gamma,
            "collision_radius_m": ctrl.collision_radius_m,
            "collision_distance_m": ctrl.collision_distance_m,
            "collision_gain": ctrl.collision_gain,
            "tracking_error_bound_m_s": ctrl.tracking_error_bound_m_s,
            "localization_share": kernels.LOCALIZATION_SHARES[ctrl.localization_share]})

    # -- helpers ------------------------------------------------------------------------

    @property
    def gramian_copies(self) -> Array:
        m = self.setup.n_targets
        return self._cons_array[self._layout.gramian].reshape(m, 3, 3).copy()

    @property
    def target_estimates(self) -> Array:
        return self._posterior_state.copy()

    def snapshot(self) -> AgentSnapshot:
        """A read-only copy of the filter and consensus state as it is now (for tests and
        tools; it copies every array, so the step never calls it)."""
        return AgentSnapshot(
            phase=self._phase, step=self._step, rounds_done=self._round,
            position=_frozen(self._position), last_command=self._last_command,
            prior=TargetPrior(_frozen(self._prior_state), _frozen(self._prior_information)),
            posterior_state=_frozen(self._posterior_state), icf_pair=_frozen(self._icf),
            consensus_states=_frozen(self._cons_array),
            disagreement=_frozen(self._disagreement),
            missing_this_step=self._missing, rejected_this_step=self._rejected)

    @property
    def section_us(self) -> dict[str, float]:
        """Compute time of the last step by section [µs] (estimation: ICF local steps;
        consensus: rounds and the consensus/Gramian update; barrier: perception, barrier and
        constraint rows; qp: solver matrices, the solver's update and solve, feasibility check;
        other: the rest), for benchmarks/bench_step.py."""
        return {name: 1e6 * t for name, t in zip(SECTIONS, self._clock.seconds, strict=True)}

    def _message(self, rnd: int, *, with_states: bool) -> ConsensusMessage:
        """The message of round ``rnd``: the ICF pair and, in round 0, the consensus states,
        one concatenation of the packed vectors (``swarm.core.consensus_message``)."""
        if not with_states:
            data = self._icf.copy()
        elif self._reach is None:
            data = np.concatenate((self._icf, self._cons_array))
        else:
            data = np.concatenate((self._icf, self._cons_array, self._reach.stamps))
        return record(ConsensusMessage, {
            "sender": self.setup.drone_id, "step": self._step, "round": rnd,
            "n_targets": self.setup.n_targets, "n_state": self._n_state, "data": data})

    def _gather(self, inbox: Mapping[int, ConsensusMessage],
                first: bool) -> tuple[list[Array], list[float]]:
        """The usable neighbours' data this round, each ``data`` as it came (the ICF pair,
        then in round 0 the consensus states, packed as the own state is:
        ``swarm.core.consensus_message``), and their weights a_ij, in neighbour order.

        A neighbour missing from the inbox is counted missing; a message from the wrong
        sender, of the wrong round or sizes is counted rejected (one with a non-finite number
        by ``consensus_round``). A later-round message that carries the round-0 states gives
        its pair.
        """
        m, n = self.setup.n_targets, self._n_state
        pair = self._icf.shape[0]
        full = self._message_size
        weight_of = self.setup.neighbour_weights
        reach = self._reach
        blocks: list[Array] = []
        weights: list[float] = []
        heard: list[int] = []
        for j in self._neighbours:
            msg = inbox.get(j)
            if msg is None:
                self._missing += reach is None  # on a range graph: not heard, not linked
                continue
            data = msg.data
            if (msg.sender != j or msg.round != self._round or msg.n_targets != m
                    or msg.n_state != n or type(data) is not np.ndarray
                    or data.dtype is not _F64 or data.ndim != 1):
                self._rejected += 1
                continue
            size = data.shape[0]
            if size == full:
                if reach is not None and first:
                    if not np.isfinite(data).all():  # the kernel sees the rest of no other
                        self._rejected += 1
                        continue
                    reach.merge(data[full - self.setup.n_drones:])
                blocks.append(data if first else data[:pair])
            elif size == pair and not first:
                blocks.append(data)
            else:
                self._rejected += 1
                continue
            weights.append(weight_of[j])
            heard.append(j)
        if first:
            self._heard = tuple(heard)
        return blocks, weights

    def _clean_beacons(self, beacons: Mapping[int, Sequence[float]]
                       ) -> dict[int, list[float]]:
        """Other drones' positions as floats; a non-finite or malformed one is counted
        rejected (the own id is skipped). A position may be an array or a list of 3 floats
        (``LockstepExchange.beacons`` gives lists: one ``tolist`` for all)."""
        own_id = self.setup.drone_id
        clean: dict[int, list[float]] = {}
        for j, p_j in beacons.items():
            if j == own_id:
                continue
            if (type(p_j) is list and len(p_j) == 3 and type(p_j[0]) is float
                    and type(p_j[1]) is float and type(p_j[2]) is float):
                xyz = p_j
            else:
                array = np.asarray(p_j, dtype=float)
                if array.shape != (3,):
                    self._rejected += 1
                    continue
                xyz = array.tolist()
            if not _finite3(xyz):
                self._rejected += 1
                continue
            clean[j] = xyz
        return clean

    def _advance_consensus(self, rows: list[list[float]], weights: list[float]) -> None:
        """One Euler step of the PI consensus (3.30) for wΠ̂ and w and of the Gramian copies
        (3.29), symmetrized, on the packed state.

        The step is linear in (x, Σ_j (x − x_j), u), so each new entry is a sum of at most
        six precomputed coefficients times entries of [x, Σ_j (x − x_j), u]
        (``_consensus_operator``): one gather, one product, one sum, the same update as
        ``pi_consensus_step`` and ``gramian_step`` up to round-off.
        """
        local_input = [w * x for w, row in zip(weights, rows, strict=True)
                       for x in row[ROW.PROJECTOR]]
        local_input += weights  # u_i = [w Π̂ (9M), w (M)]
        disagreement = self._disagreement
        if self._reach is not None and self.setup.network.integral == "own":
            # A range graph: the integral enters s as it is, K_i η_i, where (3.30) has
            # K_i Σ_j (η_i − η_j) over the neighbours (docs/network.md, "The filters on a
            # changing graph"): the operator's η-difference entries get η itself.
            disagreement = disagreement.copy()
            disagreement[self._layout.integrals] = self._cons_array[self._layout.integrals]
        self._cons_array = consensus_step(self._operator, self._cons_array, disagreement,
                                          local_input)

    def _initialise_consensus_states(self) -> None:
        """s_i(0) = u_i(0) from the initial estimate, η_i(0) = 0 (SPEC §6)."""
        m, layout = self.setup.n_targets, self._layout
        terms = [perception_terms(self._position, self._prior_state[r, :3],
                                  self.setup.perception) for r in range(m)]
        cons = self._cons_array.copy()
        cons[layout.projector_mean] = np.array([t.weight * t.projector
                                                for t in terms]).ravel()
        cons[layout.weight_mean] = [t.weight for t in terms]
        self._cons_array = cons
        self._consensus_started = True

    def _nominal_velocity(
        self, position: list[float], beacons: Mapping[int, list[float]]
    ) -> tuple[tuple[float, float, float], float | None]:
        ctrl = self.setup.control
        if ctrl.task == "zero":
            return _ZERO3, None
        desired = self._desired_bearings
        neighbours = [(beacons[j], desired[j]) for j in self._neighbours if j in beacons]
        return bearing_formation_scalars(position, neighbours, ctrl.formation_gain)

    def _qp_rows(self, terms: Array, target_velocities: Array, weight_sums: list[float],
                 position: list[float], beacons: Mapping[int, list[float]]
                 ) -> tuple[list[float], list[float]]:
        """Velocity parts (column-major: x, y, z coefficients of every row) and lower bounds
        of the QP rows: localization (3.32), weight-sum (3.34-3.36), one collision row
        (4.1-4.2) per drone within R_ca (in the order of their ids), and the safety
        envelope's rows last (``swarm.core.safety``), each bound tightened by ē‖a‖ for the
        vehicle's tracking error (``robust_lower_bound``; ē =
        ``control.tracking_error_bound_m_s``). Collision and envelope rows carry no slack:
        hard in either QP. Assembled in one compiled call (``kernels.qp_rows``)."""
        others = [beacons[j] for j in sorted(beacons)]
        if self._n_safety_rows:
            envelope_rows, envelope_lower = safety_rows(position, self.setup.safety)
        else:
            envelope_rows, envelope_lower = [], []
        if self._kept:
            keep_rows, keep_lower = self._keep_rows(position, beacons)
            envelope_rows, envelope_lower = envelope_rows + keep_rows, envelope_lower + keep_lower
        return kernels.qp_rows(terms, target_velocities, weight_sums, position, others,
                               envelope_rows, envelope_lower, self._row_constants)

    def _keep_rows(self, position: list[float], beacons: Mapping[int, list[float]]
                   ) -> tuple[list[tuple[float, float, float]], list[float]]:
        """Drone i's halves of the keep-link barriers (``network.keep_row``), one per kept
        drone whose position this step has, in id order: the last rows of the QP. Sets
        ``_n_keep_rows`` and ``_keep_margin_m`` (R_keep − the longest kept distance)."""
        rows: list[tuple[float, float, float]] = []
        lower: list[float] = []
        longest_m = 0.0
        for j in self._kept:
            other = beacons.get(j)
            if other is None:
                continue
            a, bound, h = keep_row(position, other, self._keep_range_m, self._keep_gain)
            rows.append(a)
            lower.append(bound)
            longest_m = max(longest_m, math.sqrt(max(self._keep_range_m ** 2 - h, 0.0)))
        self._n_keep_rows = len(rows)
        self._keep_margin_m = self._keep_range_m - longest_m if rows else math.inf
        return rows, lower

    def _solve(self, nominal: tuple[float, float, float], u_columns: list[float],
               lower: list[float], weights: list[float],
               box: tuple[list[float], list[float]] | None) -> tuple[QpSolution, bool, bool]:
        """Hard QP (3.37) or relaxed QP (3.36); hard failures fall back to relaxed (SPEC §9).

        With a rate box: both within it first; if the relaxed QP has no solution there (its
        only hard rows are the collision rows), it is solved once more in the full box — the
        barriers before smoothness — and that counts as a release. Returns (solution,
        fallback, released)."""
        if self._qp_hard is not None:
            hard = self._qp_hard.solve(nominal, u_columns, lower, weights, box)
            if hard.found:
                return hard, False, False
            self._keep_failure("hard", self._qp_hard, hard)
        relaxed = self._qp_relaxed.solve(nominal, u_columns, lower, weights, box)
        if relaxed.found:
            return relaxed, self._qp_hard is not None, False
        self._keep_failure("relaxed", self._qp_relaxed, relaxed)
        if box is None:
            return relaxed, True, False
        released = self._qp_relaxed.solve(nominal, u_columns, lower, weights)
        if not released.found:
            self._keep_failure("relaxed, full box", self._qp_relaxed, released)
        return released, True, True

    def _keep_failure(self, attempt: str, workspace: LocalQpWorkspace,
                      solution: QpSolution) -> None:
        """Keep a QP that was not solved, as the solver had it, in ``qp_failures``."""
        self.qp_failures.append(FailedQp(
            self.setup.drone_id, self._step, attempt, workspace.current_qp(), solution.status,
            solution.iterations, solution.max_violation))


_ZERO3 = (0.0, 0.0, 0.0)
_F64 = np.dtype(np.float64)  # native: what the agent and the decoder make


def _consensus_operator(layout: ConsensusLayout, dt: float, gram: GramianParams,
                        rate_gain: float) -> tuple[NDArray[np.intp], Array]:
    """Gather index and coefficients of the consensus step on z = [x, D, u, 0] (SPEC §6),
    its parts where ``kernels.consensus_step`` takes them (``kernels.z_starts``).

    x is the packed state (``ConsensusLayout``: s, η, G), D = Σ_j (x − x_j) over the
    round-0 neighbours, u = [wΠ̂, w] the local input. With K = (ζ, K_p, K_i) per entry:
    s' = (1 − ΔTζ) s + ΔTζ u − ΔT K_p D_s + ΔT K_i D_η (3.30), η' = η − ΔT K_i D_s, and
    G' = ½(Ĝ + Ĝᵀ) with Ĝ = (1 − ΔTρ) G + ΔT bN s_wΠ̂ − ΔT c D_G (3.29, Σ_j (G_j − G) = −D_G).
    Returns (index, coefficients), each (6, 29M); unused terms point at the 0 that ends z.
    """
    m, n = layout.n_targets, layout.size
    means, integrals, gramian = layout.means, layout.integrals, layout.gramian
    z = kernels.z_starts(n, means.stop)  # where x, D, u and the 0 start in z
    x0, d0, u0 = z["state"], z["disagreement"], z["input"]
    index = np.full((6, n), z["zero"], dtype=np.intp)
    coefficients = np.zeros((6, n))

    def put(row: int, entry: int, source: int, coefficient: float) -> None:
        index[row, entry], coefficients[row, entry] = source, coefficient

    pc, wc = gram.projector_consensus, gram.weight_consensus
    for i in range(means.start, means.stop):
        gains = pc if i < layout.projector_mean.stop else wc
        e = integrals.start + i  # the matching η entry
        put(0, i, x0 + i, 1.0 - dt * gains.zeta)
        put(1, i, u0 + i, dt * gains.zeta)
        put(2, i, d0 + i, -dt * gains.kp)
        put(3, i, d0 + e, dt * gains.ki)
        put(0, e, x0 + e, 1.0)
        put(1, e, d0 + i, -dt * gains.ki)
    keep, rate, couple = 1.0 - dt * gram.forgetting, dt * rate_gain, -dt * gram.consensus_gain
    for r in range(m):
        for a in range(3):
            for b in range(3):
                k, kt = 9 * r + 3 * a + b, 9 * r + 3 * b + a  # G[a, b] and G[b, a] in the block
                i, it = gramian.start + k, gramian.start + kt
                put(0, i, x0 + i, 0.5 * keep)
                put(1, i, x0 + it, 0.5 * keep)
                put(2, i, x0 + layout.projector_mean.start + k, 0.5 * rate)  # s of wΠ̂ (3.29)
                put(3, i, x0 + layout.projector_mean.start + kt, 0.5 * rate)
                put(4, i, d0 + i, 0.5 * couple)
                put(5, i, d0 + it, 0.5 * couple)
    return index, coefficients


def consensus_step(operator: tuple[NDArray[np.intp], Array], x: Array, disagreement: Array,
                   local_input: list[float]) -> Array:
    """The packed consensus state after one step (SPEC §6, 3.29-3.30): each entry the sum of
    its precomputed terms over z = [x, Σ_j (x − x_j), u, 0], ``np.add.reduce(z[index] *
    coefficients, axis=0)`` for ``operator`` = (index, coefficients) of
    ``_consensus_operator``, in one compiled call (``kernels.consensus_step``)."""
    index, coefficients = operator
    updated = np.empty_like(x)
    kernels.consensus_step(x, disagreement, local_input, index, coefficients, updated)
    return updated


def _checked_prior(prior: TargetPrior, drone_id: int, m: int, n: int) -> tuple[Array, Array]:
    """Copies of a given prior's arrays, checked: finite, (M, n) and (M, n, n)."""
    state = np.array(prior.state, dtype=float)
    information = np.array(prior.information, dtype=float)
    if (state.shape != (m, n) or information.shape != (m, n, n)
            or not (np.isfinite(state).all() and np.isfinite(information).all())):
        raise ValueError(f"drone {drone_id}: a prior must be finite, its state ({m}, {n}) and "
                         f"its information ({m}, {n}, {n}); got {state.shape} and "
                         f"{information.shape}")
    return state, information


def _frozen(values: Array) -> Array:
    """A read-only copy."""
    copy = np.array(values, dtype=float)
    copy.flags.writeable = False
    return copy


def _clip3(u: tuple[float, float, float] | list[float],
           box: tuple[list[float], list[float]]) -> tuple[float, float, float]:
    (l0, l1, l2), (h0, h1, h2) = box
    return (min(max(u[0], l0), h0), min(max(u[1], l1), h1), min(max(u[2], l2), h2))


def _all_finite(values: list[float]) -> bool:
    return all(map(math.isfinite, values))


def _finite3(xyz: list[float]) -> bool:
    """All three finite: x − x is 0 for a finite x and NaN for ±inf or NaN."""
    x, y, z = xyz
    return (x - x) + (y - y) + (z - z) == 0.0
