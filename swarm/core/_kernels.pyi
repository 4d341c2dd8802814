# The interface of swarm/core/_kernels.c (its methods table and PyInit__kernels), for mypy.
# Arrays are C-contiguous float64 (np.intp for consensus_step's index); outputs are written in
# place. Layouts and constant orders: the tuples below, as the module exports them.
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

_Array = NDArray[np.float64]
_Field = tuple[str, int, int]

PERCEPTION_SIZE: int
BARRIER_SIZE: int
SMOOTH_MIN_SIZE: int
CONSTANTS_SIZE: int
MAX_STATE: int
ROW_FIELDS: tuple[_Field, ...]
SMOOTH_MIN_FIELDS: tuple[_Field, ...]
PERCEPTION_CONSTANTS: tuple[str, ...]
BARRIER_CONSTANTS: tuple[str, ...]
QP_ROW_CONSTANTS: tuple[str, ...]
LOCALIZATION_SHARES: tuple[str, ...]
ICF_PAIR: tuple[str, ...]
CONSENSUS_STEP_Z: tuple[str, ...]

def perception(drone: _Array, target: _Array, constants: _Array, out: _Array, /) -> None: ...
def symmetric_eigen(matrix: _Array, values: _Array, vectors: _Array, /) -> bool: ...
def smooth_min(eigenvalues: _Array, exponent: float, floor: float, log_gap: float,
               out: _Array, /) -> None: ...
def perception_barrier(drone: _Array, estimates: _Array, velocities: _Array, gramians: _Array,
                       projector_means: _Array, constants: _Array, out: _Array, /) -> bool: ...
def filter_stack(information: _Array, vector: _Array, transition: _Array,
                 process_noise: float, n_agents: float, posterior_state: _Array,
                 prior_state: _Array, prior_information: _Array,
                 posterior_covariance: _Array, /) -> bool: ...
def qp_load(columns: Sequence[float], lower: Sequence[float], nominal: Sequence[float],
            low: Sequence[float], high: Sequence[float], weights: Sequence[float],
            slack_weight: float, weight_floor: float, rows: _Array, bounds_lower: _Array,
            bounds_upper: _Array, linear: _Array, hessian: _Array, /) -> bool: ...
def qp_max_violation(z: Sequence[float], columns: Sequence[float], lower: Sequence[float],
                     low: Sequence[float], high: Sequence[float], /) -> float: ...
def qp_rows(terms: _Array, velocities: _Array, weight_sums: Sequence[float],
            position: Sequence[float], others: Sequence[Sequence[float]],
            envelope_rows: Sequence[Sequence[float]], envelope_lower: Sequence[float],
            constants: Sequence[float], /) -> tuple[list[float], list[float]]: ...
def initial_information(prior_information: _Array, prior_state: _Array, n_agents: float,
                        info_gain: float, seen_from: Sequence[float],
                        image_points: Sequence[float], detected: Sequence[float],
                        out: _Array, /) -> None: ...
def consensus_sums(own_icf: _Array, own_cons: _Array | None, blocks: Sequence[_Array],
                   weights: Sequence[float], icf_out: _Array,
                   disagreement_out: _Array | None, /) -> int: ...
def consensus_step(x: _Array, d: _Array, u: Sequence[float], index: NDArray[np.intp],
                   coefficients: _Array, out: _Array, /) -> None: ...
