"""Information Consensus Filter for bearing measurements (SPEC §5, thesis Algorithm 1, 2.4-2.22).

The filter of one drone for one target is split at the points where it talks to neighbours:
``initial_information`` (2.4-2.5), K calls of ``consensus_iteration`` (2.6-2.7) done by the
caller with whatever neighbour data it has, then ``posterior`` (2.8-2.9) and ``predict``
(2.10-2.11, or 2.21-2.22 for the single-integrator model).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from swarm.core import kernels
from swarm.core.params import TargetModel

Array = NDArray[np.float64]


def state_dimension(model: TargetModel) -> int:
    """6 for [p; v] (double integrator, 2.2), 3 for p (single integrator, 2.17)."""
    return 6 if model == "double_integrator" else 3


def transition_matrix(model: TargetModel, dt_s: float) -> Array:
    """A_d = [[I, ΔT I], [0, I]] (2.2), or I for the single-integrator model (2.17)."""
    n = state_dimension(model)
    a = np.eye(n)
    if model == "double_integrator":
        a[0:3, 3:6] = dt_s * np.eye(3)
    return a


def initial_information(
    prior_state: Array,
    prior_information: Array,
    measured_projector: Array | None,
    drone_position: Array,
    n_agents: int,
    info_gain: float,
) -> tuple[Array, Array]:
    """V⁰ = W⁻/N + bμ[[Π,0],[0,0]], v⁰ = W⁻x̂⁻/N + bμ[Πp_i; 0] (2.4-2.5, 2.19-2.20).

    ``measured_projector`` is Π of the *measured* bearing, or None when μ = 0. The position
    term uses Πz = Πp_i (2.12, 2.15), so the target position itself is never needed.
    """
    info = prior_information / n_agents
    vector = info @ prior_state
    if measured_projector is not None:
        info = info.copy()
        info[0:3, 0:3] += info_gain * measured_projector
        vector = vector.copy()
        vector[0:3] += info_gain * (measured_projector @ drone_position)
    return info, vector


def consensus_iteration(own: Array, neighbours: Iterable[tuple[float, Array]]) -> Array:
    """a ← a + Σ_j a_ij (a_j − a) over the neighbours whose data is at hand (2.6-2.7).

    A neighbour left out (stale or lost) simply contributes nothing, which keeps the update a
    convex combination.
    """
    total = own.copy()
    for weight, value in neighbours:
        total += weight * (value - own)
    return total


def pseudo_inverse_psd(matrix: Array) -> Array:
    """pinv of a symmetric positive semi-definite matrix (2.8, 2.10).

    The information matrices here are positive definite in practice (W⁻ is an inverse of a
    covariance with Q > 0 added), so the plain inverse, much cheaper than an SVD, is the
    pseudo-inverse; the Cholesky factorization is the test, and the SVD path remains for the
    singular case.
    """
    try:
        np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        # numpy's stubs type pinv and inv of float64 as NDArray[floating]: float64 here.
        return np.linalg.pinv(matrix, hermitian=True)  # type: ignore[return-value]
    return np.linalg.inv(matrix)  # type: ignore[return-value]


def posterior(information: Array, vector: Array, n_agents: int) -> tuple[Array, Array]:
    """x̂⁺ = pinv(V)v, W⁺ = N V (2.8-2.9)."""
    return pseudo_inverse_psd(information) @ vector, n_agents * information


def posterior_covariance(posterior_information: Array) -> Array:
    """P⁺ = pinv(W⁺): the covariance the drone believes x̂⁺ has (the inverse of 2.9); its
    position block is the uncertainty ellipsoid a viewer draws."""
    return pseudo_inverse_psd(posterior_information)


def predict(
    posterior_state: Array,
    posterior_information: Array,
    transition: Array,
    process_noise: float,
    communicated_velocity: Array | None = None,
    dt_s: float = 0.0,
) -> tuple[Array, Array]:
    """W⁻ = (A pinv(W⁺) Aᵀ + Q)⁻¹, x̂⁻ = A x̂⁺ (2.10-2.11).

    For the single-integrator model A = I and the communicated target velocity is added:
    x̂⁻ = x̂⁺ + ΔT u_r (2.21-2.22).
    """
    covariance = transition @ pseudo_inverse_psd(posterior_information) @ transition.T
    covariance[np.diag_indices_from(covariance)] += process_noise
    prior_information = np.linalg.inv(covariance)
    prior_information = 0.5 * (prior_information + prior_information.T)
    prior_state = transition @ posterior_state
    if communicated_velocity is not None:
        prior_state = prior_state + dt_s * communicated_velocity
    return prior_state, prior_information


class StackedFilter:
    """``posterior`` then ``predict`` for a stack of M targets, with the constants of one drone
    (N, A_d, Q, ΔT) prepared once (SPEC §5); also ``posterior_covariance``.

    The compiled kernel (``kernels.filter_stack``) takes the stack: one Cholesky factorization
    per V tests that it is positive definite, where its inverse is the pseudo-inverse, and
    serves all three results, pinv(W⁺) = pinv(N V) = pinv(V)/N. If one V is not (or a factor
    is not finite), every target takes the per-target path with its SVD fallback.
    """

    def __init__(self, transition: Array, process_noise: float, n_agents: int,
                 dt_s: float = 0.0) -> None:
        self.transition = np.ascontiguousarray(transition, dtype=float)
        self.process_noise, self.n_agents, self.dt_s = float(process_noise), n_agents, dt_s

    def __call__(
        self, information: Array, vector: Array, communicated_velocity: Array | None = None
    ) -> tuple[Array, Array, Array, Array]:
        """(x̂⁺, x̂⁻, W⁻, P⁺) of the stack (M, n, n), (M, n); ``communicated_velocity`` (M, 3)
        is the single-integrator input."""
        result = kernels.filter_stack(information, vector, self.transition, self.process_noise,
                                      self.n_agents)
        if result is None:
            return _posterior_and_predict_each(
                information, vector, self.n_agents, self.transition, self.process_noise,
                communicated_velocity, self.dt_s)
        posterior_state, prior_state, prior_information, posterior_cov = result
        if communicated_velocity is not None:
            prior_state += self.dt_s * communicated_velocity
        return posterior_state, prior_state, prior_information, posterior_cov


def _posterior_and_predict_each(
    information: Array,
    vector: Array,
    n_agents: int,
    transition: Array,
    process_noise: float,
    communicated_velocity: Array | None,
    dt_s: float,
) -> tuple[Array, Array, Array, Array]:
    posterior_state = np.empty_like(vector)
    prior_state = np.empty_like(vector)
    prior_information = np.empty_like(information)
    posterior_cov = np.empty_like(information)
    for r in range(information.shape[0]):
        posterior_state[r], info = posterior(information[r], vector[r], n_agents)
        posterior_cov[r] = posterior_covariance(info)
        prior_state[r], prior_information[r] = predict(
            posterior_state[r], info, transition, process_noise,
            communicated_velocity=(None if communicated_velocity is None
                                   else communicated_velocity[r]),
            dt_s=dt_s)
    return posterior_state, prior_state, prior_information, posterior_cov
