"""Central finite differences and a fixed-step RK4 integrator for the core tests.

Error model used to justify the tolerances in the tests: a central difference with step h has
truncation error h²·|f'''|/6 and round-off error about ε_mach·|f|/h (ε_mach ≈ 2.2e-16); the
Richardson combination of steps h and h/2 cancels the h² term, leaving O(h⁴) truncation.

The perception weight is only piecewise smooth (SPEC §3: kinks in its second derivative at
d̂ = D_m^th, D_M^th and c = cos α_M^th), so finite-difference probes are placed inside one
regime, away from every threshold by far more than the step: ``REGIMES`` and ``drone_at``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

# (distance range [m], off-axis cosine range) of each regime of w = w_D(d̂)·w_β(c) with the
# default PerceptionParams (D_m^th = 1 m, D_M^th = 6 m, cos α_M^th = cos 35° ≈ 0.8192).
# Every range keeps ≥ 0.02 from a threshold, ≫ the largest finite-difference step used.
DISTANCE_RANGES = {"near": (0.4, 0.97), "nominal": (1.03, 5.97), "far": (6.03, 9.0)}
COSINE_RANGES = {"off_axis": (-0.6, 0.79), "on_axis": (0.84, 0.999)}
REGIMES = [(d, c) for d in DISTANCE_RANGES for c in COSINE_RANGES]


def drone_at(target: Array, distance: float, cos_off_axis: float, azimuth: float) -> Array:
    """Drone position p_i with d̂ = ‖p̂ − p_i‖ = distance and c = −β̂_z = cos_off_axis."""
    sin_off_axis = np.sqrt(1.0 - cos_off_axis**2)
    unit = np.array([sin_off_axis * np.cos(azimuth), sin_off_axis * np.sin(azimuth),
                     -cos_off_axis])
    return target - distance * unit


def random_drone_in_regime(
    rng: np.random.Generator, target: Array, distance_regime: str, cosine_regime: str
) -> Array:
    """A drone placed uniformly at random inside one regime of the perception weight."""
    distance = rng.uniform(*DISTANCE_RANGES[distance_regime])
    cos_off_axis = rng.uniform(*COSINE_RANGES[cosine_regime])
    return drone_at(target, distance, cos_off_axis, rng.uniform(0.0, 2.0 * np.pi))


def central_gradient(f: Callable[[Array], Array | float], x: Array, step: float) -> Array:
    """[∂f/∂x_k]_k by central differences; for an array-valued f, indexed [k, ...]."""
    x = np.asarray(x, dtype=float)
    columns = []
    for k in range(x.shape[0]):
        offset = np.zeros_like(x)
        offset[k] = step
        columns.append((np.asarray(f(x + offset)) - np.asarray(f(x - offset))) / (2.0 * step))
    return np.array(columns)


def central_derivative(f: Callable[[float], float], step: float) -> float:
    """df/dt at t = 0 by a central difference, O(h²)."""
    return (f(step) - f(-step)) / (2.0 * step)


def richardson_derivative(f: Callable[[float], float], step: float) -> float:
    """df/dt at t = 0 from central differences with steps h and h/2, O(h⁴)."""
    coarse = central_derivative(f, step)
    fine = central_derivative(f, 0.5 * step)
    return (4.0 * fine - coarse) / 3.0


def rk4(rate: Callable[[float, Array], Array], y0: Array, t_end: float, n_steps: int) -> Array:
    """y(t_end) of ẏ = rate(t, y), y(0) = y0, by classic RK4 (t_end may be negative)."""
    h = t_end / n_steps
    y = np.array(y0, dtype=float)
    t = 0.0
    for _ in range(n_steps):
        k1 = rate(t, y)
        k2 = rate(t + 0.5 * h, y + 0.5 * h * k1)
        k3 = rate(t + 0.5 * h, y + 0.5 * h * k2)
        k4 = rate(t + h, y + h * k3)
        y = y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        t += h
    return y
