"""Telemetry and truth messages → the run's ``RunRecord``.

One collector serves both the launcher (fed live from Zenoh callback threads) and the
recording reader (fed from a file), so a run and its recording give the same arrays. The
true and measured Gramians are integrated here from the ground truth, as the in-process
reference does it (``swarm.runs.ground_truth``).
"""

from __future__ import annotations

import threading
import time

import numpy as np
from numpy.typing import NDArray

from swarm.messages.wire import F64Array, TelemetryCounters, TelemetryWire, TruthWire
from swarm.runs.ground_truth import ReferenceGramians
from swarm.runs.record import RunRecord
from swarm.scenario.config import ScenarioConfig

Array = NDArray[np.float64]

# The float arrays of the record, by collector attribute (bool arrays are handled apart).
_FLOAT_ARRAYS = ("positions", "targets", "target_vel", "velocities", "estimates", "lambda_bar",
                 "psi0", "psi1", "weights", "slacks", "weight_slacks", "bearing", "step_us")


# The world's clock rate is taken over at least this much wall time (the truth comes in
# batches every 20 ms, ``swarm.net.observer.FEED_PERIOD_S``).
CLOCK_RATE_MIN_WALL_S = 1.0


def fill_gaps(values: Array) -> None:
    """In place, along axis 0: a NaN takes the previous step's value, leading NaNs the next
    available one."""
    for k in range(1, values.shape[0]):
        gap = np.isnan(values[k])
        values[k][gap] = values[k - 1][gap]
    for k in range(values.shape[0] - 2, -1, -1):
        gap = np.isnan(values[k])
        values[k][gap] = values[k + 1][gap]


def wire_values(array: F64Array) -> Array:
    """A read-only view of a wire array's bytes (copied when stored into the record)."""
    return np.frombuffer(array.data, dtype="<f8").reshape(array.shape)


def _missing_steps(values: Array) -> int:
    """Steps where any entry is NaN (a message that never arrived)."""
    return int(np.isnan(values).any(axis=tuple(range(1, values.ndim))).sum())


class TelemetryCollector:
    """Fills the run arrays from telemetry and truth messages; thread-safe (the launcher calls
    it from Zenoh callback threads)."""

    def __init__(self, config: ScenarioConfig) -> None:
        n, m, k = config.swarm.n_drones, len(config.targets), config.n_steps
        n_state = config.state_dimension
        self.config = config
        self.lock = threading.Lock()
        self.positions = np.full((k, n, 3), np.nan)
        self.targets = np.full((k, m, 3), np.nan)
        self.target_vel = np.full((k, m, 3), np.nan)
        self.velocities = np.full((k, n, 3), np.nan)
        self.estimates = np.full((k, n, m, n_state), np.nan)
        self.lambda_bar = np.full((k, n, m), np.nan)
        self.psi0 = np.full((k, n, m), np.nan)
        self.psi1 = np.full((k, n, m), np.nan)
        self.weights = np.full((k, n, m), np.nan)
        self.slacks = np.full((k, n, m), np.nan)
        self.weight_slacks = np.full((k, n, m), np.nan)
        self.detected = np.zeros((k, n, m), dtype=bool)
        self.bearing = np.full((k, n), np.nan)
        self.fallback = np.zeros((k, n), dtype=bool)
        self.safety_conflict = np.zeros((k, n), dtype=bool)
        # The radio (network.topology = "range"): the world's links, each drone's reach and
        # its keep-row conflicts; links stay all False where no truth step arrived.
        self.ranged = config.network.ranged
        self.links = np.zeros((k, n, n), dtype=bool)
        self.reached = np.zeros((k, n), dtype=np.int64)
        self.link_conflict = np.zeros((k, n), dtype=bool)
        self.step_us = np.full((k, n), np.nan)
        self.latest: dict[int, TelemetryWire] = {}
        self.telemetry_received = np.zeros(n, dtype=int)
        self.last_truth_step = -1
        self.missing_samples = 0  # truth or telemetry steps that never arrived (realtime)
        # (step, wall time it arrived [s]) of the first and the newest truth: how fast the
        # world's clock ran against the wall's (``RunRecord.world_clock_rate``).
        self._first_truth: tuple[int, float] | None = None
        self._newest_truth: tuple[int, float] | None = None

    def on_telemetry(self, _key: str, tel: TelemetryWire) -> None:
        with self.lock:
            self.latest[tel.drone] = tel
            self.telemetry_received[tel.drone] += 1
            k, i = tel.step, tel.drone
            if not 0 <= k < self.velocities.shape[0]:
                return
            # Straight from the wire bytes (decoded messages are checked): no StepDiagnostics
            # and no array copies on Zenoh's callback thread.
            self.velocities[k, i] = wire_values(tel.velocity)
            self.estimates[k, i] = wire_values(tel.estimates)
            self.lambda_bar[k, i] = wire_values(tel.lambda_bar)
            self.psi0[k, i], self.psi1[k, i] = wire_values(tel.psi0), wire_values(tel.psi1)
            self.weights[k, i] = wire_values(tel.weights)
            self.slacks[k, i] = wire_values(tel.slacks)
            self.weight_slacks[k, i] = wire_values(tel.weight_slacks)
            self.detected[k, i] = tel.detected
            self.fallback[k, i] = tel.qp_fallback
            self.safety_conflict[k, i] = tel.safety_conflict
            self.reached[k, i], self.link_conflict[k, i] = tel.reached, tel.link_conflict
            self.step_us[k, i] = tel.step_us
            if tel.bearing_error is not None:
                self.bearing[k, i] = tel.bearing_error

    def on_truth(self, _key: str, truth: TruthWire, received_s: float | None = None) -> None:
        """``received_s``: the wall time it arrived [s] (default now; a recording's reader
        passes the time the recorder received it)."""
        arrived_s = time.monotonic() if received_s is None else received_s
        with self.lock:
            k = truth.step
            if not 0 <= k < self.positions.shape[0]:
                return
            if self._first_truth is None or k < self._first_truth[0]:
                self._first_truth = (k, arrived_s)
            if self._newest_truth is None or k > self._newest_truth[0]:
                self._newest_truth = (k, arrived_s)
            arrays = truth.arrays()
            self.positions[k] = arrays["drone_positions"]
            self.targets[k] = arrays["target_positions"]
            self.target_vel[k] = arrays["target_velocities"]
            links = truth.radio_link_matrix()
            if links is not None:
                self.links[k] = links
            self.last_truth_step = max(self.last_truth_step, k)

    def record(self, seed: int, wall_time_s: float, *, fill: bool = True) -> RunRecord:
        """The run up to the newest truth step as a RunRecord.

        A step can be missing (realtime: the world's truth publisher drops rather than
        queues; a recording cut short). ``fill``: gaps take the previous value (the first
        steps the next one), as the launcher's summary wants; otherwise they stay NaN. The
        reference Gramians are integrated over gap-filled positions either way, so that one
        missing truth sample does not turn every later λ into NaN. ``missing_samples`` says
        how many (step, positions or velocities) samples were missing.
        """
        with self.lock:
            arrays = {name: getattr(self, name).copy() for name in _FLOAT_ARRAYS}
            detected, fallback = self.detected.copy(), self.fallback.copy()
            conflict = self.safety_conflict.copy()
            links, reached = self.links.copy(), self.reached.copy()
            link_conflict = self.link_conflict.copy()
            steps = max(self.last_truth_step + 1, 0)
            clock_rate = self._world_clock_rate()
        arrays = {name: values[:steps] for name, values in arrays.items()}
        self.missing_samples = (_missing_steps(arrays["positions"])
                                + _missing_steps(arrays["velocities"]))
        filled = arrays if fill else {name: v.copy() for name, v in arrays.items()}
        for values in filled.values():
            fill_gaps(values)
        true_min, measured_min = self._reference_lambdas(
            filled["positions"], filled["targets"], detected[:steps])
        return RunRecord(
            config=self.config, seed=seed,
            times_s=np.arange(steps, dtype=np.float64) * self.config.scenario.dt_s,
            drone_positions_m=arrays["positions"], velocities_m_s=arrays["velocities"],
            target_positions_m=arrays["targets"], target_velocities_m_s=arrays["target_vel"],
            estimates=arrays["estimates"], lambda_bar=arrays["lambda_bar"],
            psi0=arrays["psi0"], psi1=arrays["psi1"], weights=arrays["weights"],
            slacks=arrays["slacks"], weight_slacks=arrays["weight_slacks"],
            detected=detected[:steps], true_lambda_min=true_min,
            measured_lambda_min=measured_min, bearing_errors=arrays["bearing"],
            qp_fallback=fallback[:steps], step_us=arrays["step_us"], wall_time_s=wall_time_s,
            safety_conflict=conflict[:steps],
            links=links[:steps] if self.ranged else None,
            reached=reached[:steps] if self.ranged else None,
            link_conflict=link_conflict[:steps] if self.ranged else None,
            world_clock_rate=clock_rate)

    def _world_clock_rate(self) -> float | None:
        """Simulated seconds per wall second between the first and the newest truth, when
        they came at least ``CLOCK_RATE_MIN_WALL_S`` apart (None otherwise)."""
        if self._first_truth is None or self._newest_truth is None:
            return None
        wall_s = self._newest_truth[1] - self._first_truth[1]
        if wall_s < CLOCK_RATE_MIN_WALL_S:
            return None
        return (self._newest_truth[0] - self._first_truth[0]) * self.config.scenario.dt_s / wall_s

    def _reference_lambdas(self, positions: Array, targets: Array,
                           detected: NDArray[np.bool_]) -> tuple[Array, Array]:
        """λ_min of the true and measured Gramians per step and target, from ground truth."""
        cfg = self.config
        truth = ReferenceGramians(len(cfg.targets), cfg.gramian, cfg.perception,
                                  cfg.estimation.info_gain, cfg.scenario.dt_s)
        true_min = np.zeros((positions.shape[0], len(cfg.targets)))
        measured_min = np.zeros_like(true_min)
        for k in range(positions.shape[0]):
            true_min[k], measured_min[k] = truth.lambda_min()
            truth.advance(positions[k], targets[k], detected[k])
        return true_min, measured_min

    def drone_counters(self) -> dict[int, TelemetryCounters]:
        """The newest running totals each drone reported, by drone id."""
        with self.lock:
            return {i: self.latest[i].counters for i in sorted(self.latest)}

    def counters(self) -> dict[str, int]:
        with self.lock:
            latest = [t.counters for t in self.latest.values()]
            received = int(self.telemetry_received.sum())
        return {
            "agent_steps": sum(c.steps for c in latest),  # as counted by the agents
            "telemetry_received": received,
            "late_steps": sum(c.late_steps for c in latest),
            "rejected_messages": sum(c.rejected_messages for c in latest),
            "stale_neighbour_messages": sum(c.stale_neighbour_messages for c in latest),
            "missing_neighbour_messages": sum(c.missing_neighbour_messages for c in latest),
            "qp_fallbacks": sum(c.qp_fallbacks for c in latest),
            "vehicle_events": sum(c.vehicle_events for c in latest),
            "rate_limit_releases": sum(c.rate_limit_releases for c in latest),
            "reference_resets": sum(c.reference_resets for c in latest),
            "lambda_breaches": sum(c.lambda_breaches for c in latest),
            "safety_conflicts": sum(c.safety_conflicts for c in latest),
            "link_conflicts": sum(c.link_conflicts for c in latest),
            "splits_said": sum(c.splits_said for c in latest),
        }
