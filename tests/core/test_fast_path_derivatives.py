"""Finite differences on the path ``DroneAgent`` calls (issue 15, point 1): the plain-float
forms it steps with (``perception_scalars``, ``localization_barrier_scalars``, eigenvectors from
``swarm.core._lapack.eigh_lists`` as the agent gets them) are checked against central
differences themselves, not only through their parity with the readable forms.

Same error budget as ``test_barrier.py`` / ``test_perception.py`` (``finite_difference``):
probes inside one regime of the perception weight, h = 1e-6 m, tolerance 1e-8.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import special_ortho_group

from swarm.core import _lapack
from swarm.core.barrier import localization_barrier_scalars
from swarm.core.params import PerceptionParams
from swarm.core.perception import perception_constants, perception_scalars

from .finite_difference import REGIMES, central_gradient, random_drone_in_regime

CONSTANTS = perception_constants(PerceptionParams())
FD_STEP_M = 1e-6
FD_ATOL = 1e-8


def _scalars(drone: np.ndarray, target: np.ndarray):
    return perception_scalars(tuple(drone.tolist()), tuple(target.tolist()), CONSTANTS)


@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_the_weight_gradient_the_agent_uses_is_the_weights_derivative(
        distance_regime: str, cosine_regime: str) -> None:
    """∂w/∂p_i of ``perception_scalars`` = central differences of its own w."""
    rng = np.random.default_rng(700 + REGIMES.index((distance_regime, cosine_regime)))
    for _ in range(5):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        numeric = central_gradient(lambda p, t=target: _scalars(p, t).weight, drone, FD_STEP_M)
        np.testing.assert_allclose(_scalars(drone, target).weight_grad_drone, numeric,
                                   rtol=0, atol=FD_ATOL)


@pytest.mark.parametrize("exponent", [-4.0, -10.0, -30.0])
@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_the_barrier_gradient_the_agent_uses_is_the_derivative_of_psi1(
        distance_regime: str, cosine_regime: str, exponent: float) -> None:
    """L_gi ψ1 of ``localization_barrier_scalars`` = ∂ψ1/∂p_i at a fixed Gramian, where the
    drone's own term w(p_i)Π̂(p_i) enters the mean s = (wΠ̂ + Σ others)/N of the Gramian's model
    rate, ψ1 = ⟨Γ, −ρG + bNs⟩ + λ̄ − ε: so ∂ψ1/∂p_i = b∂⟨Γ, wΠ̂⟩/∂p_i, the row the QP gets.
    ψ1 itself is taken from ``localization_barrier_scalars`` at every probe."""
    rng = np.random.default_rng(800 + 10 * REGIMES.index((distance_regime, cosine_regime))
                                - int(exponent))
    n_agents, forgetting, epsilon, info_gain = 4, 0.5, 0.05, 1.3
    for _ in range(3):
        target = rng.uniform(-1.0, 1.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        rotation = special_ortho_group.rvs(3, random_state=rng)
        gramian = rotation @ np.diag(rng.uniform(0.05, 3.0, 3)) @ rotation.T
        values, vectors = _lapack.eigh_lists(gramian[None])
        others = sum(t.weight * np.reshape(t.projector, (3, 3)) for t in (
            _scalars(random_drone_in_regime(rng, target, "nominal", "on_axis"), target)
            for _ in range(n_agents - 1)))

        def psi1(p: np.ndarray, t=target, rest=others, ev=values[0], vec=vectors[0]) -> float:
            own = _scalars(p, t)
            mean = (own.weight * np.reshape(own.projector, (3, 3)) + rest) / n_agents
            return localization_barrier_scalars(
                tuple(ev), vec, mean.ravel().tolist(), own, (0.0, 0.0, 0.0),
                n_agents=n_agents, forgetting=forgetting, epsilon=epsilon,
                exponent=exponent, info_gain=info_gain).psi1

        own = _scalars(drone, target)
        mean = (own.weight * np.reshape(own.projector, (3, 3)) + others) / n_agents
        barrier = localization_barrier_scalars(
            tuple(values[0]), vectors[0], mean.ravel().tolist(), own, (0.0, 0.0, 0.0),
            n_agents=n_agents, forgetting=forgetting, epsilon=epsilon, exponent=exponent,
            info_gain=info_gain)
        numeric = central_gradient(psi1, drone, FD_STEP_M)
        np.testing.assert_allclose(barrier.lie_g, numeric, rtol=0, atol=FD_ATOL)
