"""The compiled kernels of the agent's step (``swarm/core/_kernels.c``), with typed results.

``DroneAgent`` runs its perception terms, barrier terms and ICF local steps through these,
on float64 arrays, one call per step for all targets: the same formulas as the readable
forms of ``swarm.core`` (``perception_terms``, ``smooth_min_eigenvalue``,
``localization_barrier``, ``icf.posterior``/``posterior_covariance``/``predict``), which the
finite-difference tests check and ``tests/core/test_kernels.py`` binds these to (parity in
every regime, derivatives by central differences on this very path).

The extension is built by ``pip install -e .`` (setuptools, the machine's C compiler).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from swarm.compiled import check_built_from_current_source, not_built
from swarm.core.params import PerceptionParams
from swarm.core.smooth_min import EIGENVALUE_FLOOR, NEAR_REPEATED_LOG_GAP

try:
    from swarm.core import _kernels
except ImportError as exc:  # pragma: no cover - a source tree that was never installed
    raise not_built("swarm.core._kernels", "swarm/core/_kernels.c") from exc

check_built_from_current_source(Path(_kernels.__file__), Path(__file__).with_name("_kernels.c"))

Array = NDArray[np.float64]
Vec3 = tuple[float, float, float]

PERCEPTION_SIZE: int = _kernels.PERCEPTION_SIZE  # floats of one pair's perception terms
BARRIER_SIZE: int = _kernels.BARRIER_SIZE  # floats of one target's barrier terms
ROW_SIZE = PERCEPTION_SIZE + BARRIER_SIZE


class ROW:
    """Where each quantity sits in a row of ``perception_barrier_rows`` (as the named tuples
    below take them apart)."""

    WEIGHT = 0  # w_ir
    WEIGHT_GRAD = slice(1, 4)  # ∂w/∂p_i
    UNIT_BEARING = slice(4, 7)  # β̂
    DISTANCE = 7  # d̂
    PROJECTOR = slice(8, 17)  # Π̂, row-major
    LAMBDA_BAR = 17
    PSI0 = 18
    PSI1 = 19
    LIE_G = slice(20, 23)
    LOWER = 23


class PerceptionScalars(NamedTuple):
    """``perception_terms`` of one drone-target pair as plain floats (Π̂ row-major)."""

    weight: float  # w_ir
    weight_grad_drone: Vec3  # ∂w/∂p_i
    unit_bearing: Vec3  # β̂
    distance_m: float  # d̂
    projector: tuple[float, ...]  # Π̂, 9 floats


class BarrierScalars(NamedTuple):
    """What ``localization_barrier`` gives the QP, as plain floats."""

    lambda_bar: float  # λ̄
    psi0: float  # ψ0 = λ̄ − ε
    psi1: float  # ψ1 = ⟨Γ, Ġ⟩ + ψ0
    lie_g: Vec3  # L_gi ψ1
    lower_bound: float  # −(c + ψ1)/N − d_i (3.32)


class SmoothMinScalars(NamedTuple):
    """``smooth_min_eigenvalue``'s coefficients as plain floats."""

    value: float  # λ̄
    eigenvalues: Vec3  # λ_k clipped to EIGENVALUE_FLOOR, ascending
    eigen_gradient: Vec3  # g_k
    eigen_hessian: tuple[float, ...]  # h00, h11, h22, h01, h02, h12
    divided_differences: Vec3  # θ01, θ02, θ12


def perception_constants(params: PerceptionParams) -> list[float]:
    """The perception parameters in the kernels' order."""
    return [params.d_min_th_m, params.d_max_th_m, params.sigma_dmin_sq_m2,
            params.sigma_dmax_sq_m2, params.cos_alpha_th, params.sigma_beta_sq]


def barrier_constants(params: PerceptionParams, *, n_agents: int, forgetting: float,
                      epsilon: float, exponent: float, info_gain: float) -> Array:
    """Everything ``perception_barrier`` takes besides the state (SPEC §3, §7, §8)."""
    return np.array([*perception_constants(params), n_agents, forgetting, epsilon, exponent,
                     info_gain, EIGENVALUE_FLOOR, NEAR_REPEATED_LOG_GAP])


def _perception_of(row: list[float]) -> PerceptionScalars:
    return PerceptionScalars(row[ROW.WEIGHT], tuple(row[ROW.WEIGHT_GRAD]),
                             tuple(row[ROW.UNIT_BEARING]), row[ROW.DISTANCE],
                             tuple(row[ROW.PROJECTOR]))


def _barrier_of(row: list[float]) -> BarrierScalars:
    return BarrierScalars(row[ROW.LAMBDA_BAR], row[ROW.PSI0], row[ROW.PSI1],
                          tuple(row[ROW.LIE_G]), row[ROW.LOWER])


def perception_barrier_rows(drone: Array, estimates: Array, velocities: Array,
                            gramians: Array, projector_means: Array, constants: Array) -> Array:
    """Perception terms (SPEC §3) and localization barrier (SPEC §8) of every target, one row
    of ``ROW_SIZE`` floats per target: ``PerceptionScalars`` then ``BarrierScalars``, flat
    (``ROW`` names the entries). The agent reads these rows as they are.

    ``drone`` (3,); per target r: the estimate ``estimates[r, :3]`` (M × n), its velocity
    ``velocities[r]`` (M × 3), the Gramian copy ``gramians`` (M·9) and the consensus mean s of
    wΠ̂ ``projector_means`` (M·9); ``constants`` from ``barrier_constants``. All float64,
    C-contiguous. Raises ``np.linalg.LinAlgError`` for a Gramian copy with a non-finite entry,
    as ``np.linalg.eigh`` does.
    """
    out = np.empty((estimates.shape[0], ROW_SIZE))
    if not _kernels.perception_barrier(drone, estimates, velocities, gramians,
                                       projector_means, constants, out):
        raise np.linalg.LinAlgError("a Gramian copy has a non-finite entry")
    return out


def perception_barrier(drone: Array, estimates: Array, velocities: Array, gramians: Array,
                       projector_means: Array, constants: Array
                       ) -> tuple[list[PerceptionScalars], list[BarrierScalars]]:
    """``perception_barrier_rows`` as named tuples, per target."""
    rows = perception_barrier_rows(drone, estimates, velocities, gramians, projector_means,
                                   constants).tolist()
    return [_perception_of(r) for r in rows], [_barrier_of(r) for r in rows]


def perception(drone: Array, target: Array, params: PerceptionParams) -> PerceptionScalars:
    """``perception_terms`` of one pair, through the kernel the agent runs."""
    out = np.empty(PERCEPTION_SIZE)
    _kernels.perception(np.asarray(drone, dtype=float), np.asarray(target, dtype=float),
                        np.array(perception_constants(params)), out)
    return _perception_of(out.tolist())


def symmetric_eigen(matrix: Array) -> tuple[Array, Array]:
    """``np.linalg.eigh`` of a symmetric 3×3 (eigenvalues ascending, eigenvectors as columns),
    through the kernel the agent runs."""
    values, vectors = np.empty(3), np.empty((3, 3))
    if not _kernels.symmetric_eigen(np.ascontiguousarray(matrix, dtype=float), values, vectors):
        raise np.linalg.LinAlgError("the matrix has a non-finite entry")
    return values, vectors


def smooth_min(eigenvalues: Array, exponent: float) -> SmoothMinScalars:
    """``smooth_min_eigenvalue``'s coefficients from ascending eigenvalues, through the kernel
    the agent runs."""
    out = np.empty(_kernels.SMOOTH_MIN_SIZE)
    _kernels.smooth_min(np.asarray(eigenvalues, dtype=float), float(exponent),
                        EIGENVALUE_FLOOR, NEAR_REPEATED_LOG_GAP, out)
    v = out.tolist()
    return SmoothMinScalars(v[0], (v[1], v[2], v[3]), (v[4], v[5], v[6]), tuple(v[7:13]),
                            (v[13], v[14], v[15]))


def barrier(drone: Array, estimate: Array, velocity: Array, gramian: Array,
            projector_mean: Array, constants: Array) -> tuple[PerceptionScalars, BarrierScalars]:
    """``perception_barrier`` for one target (tests, figures)."""
    terms, barriers = perception_barrier(
        np.asarray(drone, dtype=float), np.asarray(estimate, dtype=float).reshape(1, -1),
        np.asarray(velocity, dtype=float).reshape(1, 3),
        np.ascontiguousarray(gramian, dtype=float).reshape(9),
        np.ascontiguousarray(projector_mean, dtype=float).reshape(9), constants)
    return terms[0], barriers[0]


# ``LocalQp.max_violation`` of the local QP from its row inputs (lists of floats, as
# ``LocalQpWorkspace`` holds them): ``qp_max_violation(z, columns, lower, low, high)``.
# ``tests/core/test_qp.py`` binds it to ``LocalQp.max_violation`` through the workspace.
qp_max_violation = _kernels.qp_max_violation
# The local QP of one solve written into ``LocalQpWorkspace``'s arrays (rows, bounds, q, the
# slack penalties on P's diagonal): ``qp_load(...) -> P changed``. ``tests/core/test_qp.py``
# holds the workspace's matrices to ``build_local_qp`` after every solve.
qp_load = _kernels.qp_load
# The rows of the local QP (SPEC §8) from ``perception_barrier_rows`` and the drone's
# surroundings, as ``LocalQpWorkspace.solve`` takes them: ``qp_rows(terms, velocities,
# weight_sums, position, others, envelope_rows, envelope_lower, constants) -> (columns,
# lower)``, constants = [N, γ, R_ca, Δ, α_ca, ē, share] (share: ``LOCALIZATION_SHARES``).
# ``tests/core/test_kernels.py`` binds it to ``localization_barrier`` with
# ``localization_share``, ``weight_sum_row``, ``collision_row``, ``safety_rows`` and
# ``robust_lower_bound``.
qp_rows = _kernels.qp_rows
# ``qp_rows``' last constant for each ``control.localization_share``.
LOCALIZATION_SHARES: dict[str, float] = {"equal": 0.0, "weighted": 1.0}
# Whether every float64 of native-order bytes is finite: ``native_finite(*parts)``, the wire
# rules' check of every float a peer sends (``swarm.messages.rules``).
native_finite = _kernels.native_finite
# ``b"".join(a.tobytes() for a in arrays)`` when every array is a C-contiguous native float64
# array of its shape in ``shapes``, else None: ``join_native(arrays, shapes)``, the telemetry's
# packing of a step's arrays (``swarm.messages.wire``; ``tests/core/test_kernels.py``).
join_native = _kernels.join_native
# The agent's consensus arithmetic on its packed vectors (``DroneAgent.consensus_round``,
# ``agent.consensus_step``): ``consensus_sums(own_icf, own_cons, blocks, weights, icf_out,
# disagreement_out) -> dropped`` is ``icf.consensus_iteration`` of the ICF pair (and the
# round-0 disagreement Σ_j (x − x_j)); ``consensus_step(x, d, u, index, coefficients, out)``
# the sum of ``agent._consensus_operator``'s terms. ``tests/core/test_fast_paths.py`` binds
# both, bit for bit, to their numpy forms and to the readable steps.
consensus_sums = _kernels.consensus_sums
# The ICF's local step for all M targets, from the measured image points (SPEC §4-§5):
# ``initial_information(prior_information, prior_state, n_agents, info_gain, seen_from,
# image_points, detected, out)`` is ``icf.initial_information`` of each target with the
# projector of its measured bearing; ``tests/core/test_icf.py`` binds the agent's round-0
# message to it.
initial_information = _kernels.initial_information
consensus_step = _kernels.consensus_step
# The other drones a step can use, as the core takes them (``swarm.agent.exchange``):
# ``nearby(rows, width, ids, skip, carry, around, radius, always) -> {id: [x, y, z]}``.
# ``tests/agent/test_exchange.py`` binds it to each relayed beacon's carry-forward formula
# computed alone, bit for bit, and to the QP rows the core builds from every drone.
nearby = _kernels.nearby
# The columns of a BeaconRelayWire row that ``nearby`` reads (after position 0-2 and velocity
# 3-5): the wire's layout is these (``swarm.messages.wire.RELAY_*``).
RELAY_SAMPLE_AGE: int = _kernels.RELAY_SAMPLE_AGE
RELAY_HELD: int = _kernels.RELAY_HELD
RELAY_WIDTH: int = _kernels.RELAY_WIDTH


def filter_stack(information: Array, vector: Array, transition: Array, process_noise: float,
                 n_agents: int) -> tuple[Array, Array, Array, Array] | None:
    """(x̂⁺, x̂⁻ without the communicated velocity, W⁻, P⁺) of M targets (SPEC §5,
    2.8-2.11): information (M, n, n), vector (M, n), transition A (n, n). None if some V (or
    A P⁺ Aᵀ + Q) is not positive definite: the caller takes the pseudo-inverse path."""
    m, n = vector.shape
    outputs = (np.empty((m, n)), np.empty((m, n)), np.empty((m, n, n)), np.empty((m, n, n)))
    if not _kernels.filter_stack(information, vector, transition, process_noise,
                                 float(n_agents), *outputs):
        return None
    return outputs
