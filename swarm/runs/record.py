"""A run's time series, whoever made it: the in-process reference (``swarm.runs.reference``),
the launcher's collector from a process swarm's telemetry and truth
(``swarm.observe.collector``), or a recording read back (``swarm.observe.recording.reader``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarm.scenario.config import ScenarioConfig

Array = NDArray[np.float64]


@dataclass(frozen=True)
class RunRecord:
    """Time series of a run; index k is step k (t = k·ΔT), before the motion of step k."""

    config: ScenarioConfig
    seed: int
    times_s: Array  # (K,)
    drone_positions_m: Array  # (K, N, 3)
    velocities_m_s: Array  # (K, N, 3) commanded
    target_positions_m: Array  # (K, M, 3)
    target_velocities_m_s: Array  # (K, M, 3)
    estimates: Array  # (K, N, M, n)
    lambda_bar: Array  # (K, N, M) λ̄ of each drone's copy
    psi0: Array  # (K, N, M)
    psi1: Array  # (K, N, M)
    weights: Array  # (K, N, M)
    slacks: Array  # (K, N, M)
    weight_slacks: Array  # (K, N, M)
    detected: Array  # (K, N, M) bool
    true_lambda_min: Array  # (K, M)
    measured_lambda_min: Array  # (K, M)
    bearing_errors: Array  # (K, N), NaN without a formation task
    qp_fallback: Array  # (K, N) bool
    step_us: Array  # (K, N)
    wall_time_s: float
    # (K, N) bool: the step's QP used localization slack while a safety-envelope row held
    # u back (swarm.core.safety.safety_conflict); None: not recorded (older recordings).
    safety_conflict: Array | None = None
    # The radio (network.topology = "range", swarm.core.network; None otherwise or not
    # recorded): (K, N, N) bool the links of each step as the simulated radio made them,
    # (K, N) how many drones each drone's news reached (itself included: < N, it said the
    # swarm had split; 0, its telemetry of that step never arrived), (K, N) bool a keep
    # row held u back while localization slack was used.
    links: NDArray[np.bool_] | None = None
    reached: NDArray[np.int64] | None = None
    link_conflict: NDArray[np.bool_] | None = None
    # Simulated seconds per wall second of the world's clock as an observer received its
    # truth (None: in process, or too short to tell); realtime holds it at 1.
    world_clock_rate: float | None = None

    @property
    def n_steps(self) -> int:
        return int(self.times_s.shape[0])

    def position_errors(self) -> Array:
        """‖p̂_ir − p_r‖ per step, drone and target, (K, N, M) [m]."""
        return np.linalg.norm(self.estimates[..., :3] - self.target_positions_m[:, None], axis=-1)

    def min_pairwise_distance(self) -> float:
        p = self.drone_positions_m
        diff = p[:, :, None, :] - p[:, None, :, :]
        dist = np.linalg.norm(diff, axis=-1)
        n = p.shape[1]
        dist[:, np.arange(n), np.arange(n)] = np.inf
        return float(dist.min())
