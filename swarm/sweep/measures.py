"""What a process mission's recording says beyond its report: how its vehicles tracked the
commands, and, when drones were lost, what the survivors held and said. Row keys
``tracking``, ``rate_limit_releases``, ``reference_resets`` and ``loss``
(``swarm.sweep.rows``); in-process missions have no vehicles to measure and no losses.

``tracking``: the agents' own per-step measures of their vehicles after control start —
‖v − u‖ of the velocity against the command in effect and ‖p − r‖ against the command
reference — as RMS and 95th percentile over drones and steps (None: never measured, e.g.
ideal vehicles).

``loss``: the drones killed (``kill_agents``) are lost from the step after their last
telemetry; over the survivors and the steps from the first loss on: the smallest λ̄ − ε per
target, how long some copy was below ε − tol and when first, when a survivor first said a
breach (``lambda_breaches`` in its telemetry), whether they said it (None: nothing to say),
the survivors' largest final estimation error, and the first survivor QP fallback.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from swarm.messages.wire import TelemetryWire
from swarm.observe.recording.reader import Recording, iter_messages
from swarm.runs.checks import start_index


def _rms_p95(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    array = np.asarray(values)
    return float(np.sqrt(np.mean(array**2))), float(np.percentile(array, 95))


def _rounded(value: float | None, digits: int = 6) -> float | None:
    return None if value is None or not math.isfinite(value) else round(float(value), digits)


def recording_measures(recording: Recording, victims: Sequence[int]) -> dict[str, Any]:
    """The row keys of a process mission (module docstring); ``victims``: the drones whose
    agents the mission killed."""
    start_s = recording.metadata.config.control.start_s
    velocity: list[float] = []
    position: list[float] = []
    said_step: dict[int, int] = {}
    fallback_steps: dict[int, list[int]] = {}
    last_step: dict[int, int] = {}
    for item in iter_messages(recording.path, ("telemetry",)):
        tel, drone = item.message, item.drone
        if not isinstance(tel, TelemetryWire) or drone is None:
            continue  # not asked for: telemetry comes from a drone's own topic
        last_step[drone] = max(last_step.get(drone, -1), tel.step)
        if tel.qp_fallback:
            fallback_steps.setdefault(drone, []).append(tel.step)
        if tel.counters.lambda_breaches and drone not in said_step:
            said_step[drone] = tel.step
        if tel.time_s < start_s:
            continue
        if tel.counters.velocity_error_m_s is not None:
            velocity.append(tel.counters.velocity_error_m_s)
        if tel.counters.tracking_error_m is not None:
            position.append(tel.counters.tracking_error_m)
    velocity_rms, velocity_p95 = _rms_p95(velocity)
    position_rms, position_p95 = _rms_p95(position)
    counters = recording.drone_counters.values()
    out: dict[str, Any] = {
        "tracking": {"velocity_error_rms_m_s": _rounded(velocity_rms),
                     "velocity_error_p95_m_s": _rounded(velocity_p95),
                     "position_error_rms_m": _rounded(position_rms),
                     "position_error_p95_m": _rounded(position_p95)},
        "rate_limit_releases": sum(c.rate_limit_releases for c in counters),
        "reference_resets": sum(c.reference_resets for c in counters),
    }
    if victims:
        out["loss"] = _loss(recording, victims, last_step, said_step, fallback_steps)
    return out


def _loss(recording: Recording, victims: Sequence[int], last_step: dict[int, int],
          said_step: dict[int, int], fallback_steps: dict[int, list[int]]) -> dict[str, Any]:
    record, config = recording.record, recording.metadata.config
    eps, tol = config.gramian.epsilon, config.checks.lambda_tolerance
    dt = config.scenario.dt_s
    survivors = [i for i in range(config.swarm.n_drones) if i not in victims]
    loss = min(last_step.get(v, -1) + 1 for v in victims)
    loss = max(loss, start_index(record))
    lam = record.lambda_bar[loss:, survivors, :]  # (K', S, M)
    margins = [_rounded(float(np.nanmin(lam[:, :, r])) - eps)
               if np.isfinite(lam[:, :, r]).any() else None for r in range(lam.shape[2])]
    below = np.any(lam < eps - tol, axis=(1, 2))
    first_below = int(np.argmax(below)) + loss if below.any() else None
    first_said = min((k for i, k in said_step.items() if i in survivors), default=None)
    first_fallback = min((k for i in survivors for k in fallback_steps.get(i, ()) if k >= loss),
                         default=None)
    end = record.n_steps - 1
    errors = [float(np.linalg.norm(record.estimates[end, i, r, :3]
                                   - record.target_positions_m[end, r]))
              for i in survivors for r in range(record.target_positions_m.shape[1])
              if np.all(np.isfinite(record.estimates[end, i, r, :3]))]

    def seconds(step: int | None) -> float | None:
        return None if step is None else round(step * dt, 3)

    return {
        "victims": list(victims),
        "at_s": seconds(loss),
        "min_lambda_margin": margins,  # per target, survivors, from the loss on
        "below_s": round(float(below.sum()) * dt, 3),
        "first_below_s": seconds(first_below),
        "first_said_s": seconds(first_said),
        # whether a survivor said the breach its copies had (None: no copy below the floor)
        "said": None if first_below is None else first_said is not None,
        "first_fallback_s": seconds(first_fallback),
        "final_error_m": _rounded(max(errors)) if errors else None,
    }
