"""Reference Gramians integrated from ground truth, for checking a run (never used to steer).

- *true*: Ġ = −ρG + bΣ_i w_i Π_i with weights and projectors from the true positions: what
  every copy would be with perfect estimation and consensus (SPEC §6, thesis 3.4);
- *measured*: Ġ = −ρG + bΣ_{i detects} Π_i: the information the cameras actually delivered.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from swarm.core.gramian import initial_gramian, true_gramian_step
from swarm.core.params import GramianParams, PerceptionParams
from swarm.core.perception import perception_terms
from swarm.core.projector import bearing, projector

Array = NDArray[np.float64]


class ReferenceGramians:
    """True and measured Gramians of every target, advanced one step at a time."""

    def __init__(self, n_targets: int, gramian: GramianParams, perception: PerceptionParams,
                 info_gain: float, dt_s: float) -> None:
        self._gramian_params = gramian
        self._perception = perception
        self._info_gain = info_gain
        self._dt_s = dt_s
        self.true = np.broadcast_to(initial_gramian(gramian.epsilon), (n_targets, 3, 3)).copy()
        self.measured = self.true.copy()

    def lambda_min(self) -> tuple[Array, Array]:
        """λ_min of the true and of the measured Gramian of every target, at this step."""
        # numpy's stubs type eigvalsh of float64 as NDArray[floating]: float64 here.
        return (np.linalg.eigvalsh(self.true)[:, 0],  # type: ignore[return-value]
                np.linalg.eigvalsh(self.measured)[:, 0])

    def advance(self, drone_positions: Array, target_positions: Array, detected: Array) -> None:
        """Euler step with the drones and targets of this step; ``detected`` is (N, M) bool."""
        rho, b = self._gramian_params.forgetting, self._info_gain
        for r, target in enumerate(target_positions):
            true_rate = np.zeros((3, 3))
            measured_rate = np.zeros((3, 3))
            for i, p_i in enumerate(drone_positions):
                terms = perception_terms(p_i, target, self._perception)
                true_rate += terms.weight * terms.projector
                if detected[i, r]:
                    measured_rate += projector(bearing(target - p_i)[0])
            self.true[r] = true_gramian_step(self.true[r], b * true_rate, forgetting=rho,
                                             dt_s=self._dt_s)
            self.measured[r] = true_gramian_step(self.measured[r], b * measured_rate,
                                                 forgetting=rho, dt_s=self._dt_s)
