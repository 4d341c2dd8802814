"""Perception weight w = w_D(d̂)·w_β(c) and its gradient (SPEC §3)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.params import PerceptionParams
from swarm.core.perception import perception_terms, perception_weight

from .finite_difference import REGIMES, central_gradient, drone_at, random_drone_in_regime

PARAMS = PerceptionParams()
# Step 1e-6 m: the narrowest Gaussian (σ_Dm = 0.2 m) gives |w'''| ≲ 1e3 m⁻³, so truncation
# ≲ 1e-12·1e3/6 ≈ 2e-10 and round-off ≲ 1e-16/1e-6 = 1e-10; 1e-8 leaves a 30× margin while
# a wrong factor in any gradient term (|∂w| up to ~10 m⁻¹) would miss by orders of magnitude.
FD_STEP_M = 1e-6
FD_ATOL = 1e-8


def test_defaults_are_the_spec_values() -> None:
    """SPEC §3 / Fig. 3.1: D_m^th 1, D_M^th 6 m; σ_Dm² 0.04, σ_DM² 1.8; α_M^th 35°; σ_β² 0.015."""
    assert (PARAMS.d_min_th_m, PARAMS.d_max_th_m) == (1.0, 6.0)
    assert (PARAMS.sigma_dmin_sq_m2, PARAMS.sigma_dmax_sq_m2) == (0.04, 1.8)
    assert (PARAMS.alpha_th_deg, PARAMS.sigma_beta_sq) == (35.0, 0.015)
    assert PARAMS.cos_alpha_th == pytest.approx(math.cos(math.radians(35.0)), rel=1e-15)


def _weight(drone: np.ndarray, target: np.ndarray) -> float:
    return perception_weight(drone, target, PARAMS)


@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_weight_gradient_matches_central_differences_in_every_regime(
    distance_regime: str, cosine_regime: str
) -> None:
    """∂w/∂p_i equals the central difference of w inside each of the six regimes."""
    rng = np.random.default_rng(REGIMES.index((distance_regime, cosine_regime)))
    for _ in range(10):
        target = rng.uniform(-2.0, 2.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        terms = perception_terms(drone, target, PARAMS)
        numeric = central_gradient(lambda p, t=target: _weight(p, t), drone, FD_STEP_M)
        np.testing.assert_allclose(terms.weight_grad_drone, numeric, rtol=0, atol=FD_ATOL)


@pytest.mark.parametrize(("distance_regime", "cosine_regime"), REGIMES)
def test_weight_gradient_wrt_target_estimate_is_the_negative(
    distance_regime: str, cosine_regime: str
) -> None:
    """∂w/∂p̂_r (central differences in the estimate) equals −∂w/∂p_i (SPEC §3)."""
    rng = np.random.default_rng(100 + REGIMES.index((distance_regime, cosine_regime)))
    for _ in range(10):
        target = rng.uniform(-2.0, 2.0, 3)
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        terms = perception_terms(drone, target, PARAMS)
        numeric = central_gradient(lambda t, p=drone: _weight(p, t), target, FD_STEP_M)
        np.testing.assert_allclose(-terms.weight_grad_drone, numeric, rtol=0, atol=FD_ATOL)


def test_regimes_are_what_they_claim() -> None:
    """The FD probes really sit where intended: w = 1 only in the nominal/on-axis regime."""
    rng = np.random.default_rng(3)
    target = np.zeros(3)
    for distance_regime, cosine_regime in REGIMES:
        drone = random_drone_in_regime(rng, target, distance_regime, cosine_regime)
        terms = perception_terms(drone, target, PARAMS)
        nominal = (distance_regime, cosine_regime) == ("nominal", "on_axis")
        assert (terms.weight == 1.0) == nominal
        assert (np.all(terms.weight_grad_drone == 0.0)) == nominal


def test_weight_formula_values() -> None:
    """Spot values of w_D·w_β written straight from SPEC §3."""
    target = np.array([0.3, -0.2, 0.0])
    cos_th = math.cos(math.radians(35.0))
    cases = [  # (d̂, c, expected w)
        (0.8, 0.95, math.exp(-(0.8 - 1.0) ** 2 / 0.04)),
        (3.0, 0.95, 1.0),
        (7.5, 0.95, math.exp(-(7.5 - 6.0) ** 2 / 1.8)),
        (3.0, 0.5, math.exp(-(0.5 - cos_th) ** 2 / 0.015)),
        (7.5, 0.5, math.exp(-(7.5 - 6.0) ** 2 / 1.8 - (0.5 - cos_th) ** 2 / 0.015)),
    ]
    for distance, cosine, expected in cases:
        drone = drone_at(target, distance, cosine, 0.7)
        terms = perception_terms(drone, target, PARAMS)
        assert terms.weight == pytest.approx(expected, rel=1e-12)
        assert terms.distance_m == pytest.approx(distance, rel=1e-12)
        assert -terms.unit_bearing[2] == pytest.approx(cosine, rel=1e-12)


offsets = st.tuples(*[st.floats(-11.0, 11.0)] * 3)


@settings(deadline=None, max_examples=200, derandomize=True)
@given(offsets, offsets)
def test_weight_lies_in_unit_interval(drone_offset: tuple, target_offset: tuple) -> None:
    """0 < w ≤ 1 for drone and estimate in a 22 m box, so d̂ < 20 m.

    Below 20 m the exponents stay above −(14²/1.8 + 1.82²/0.015) ≈ −330, far from the
    underflow at −745; in exact arithmetic w > 0 everywhere.
    """
    drone, target = np.array(drone_offset), np.array(target_offset)
    if np.linalg.norm(drone - target) < 1e-3:
        return
    w = _weight(drone, target)
    assert 0.0 < w <= 1.0


@settings(deadline=None, max_examples=200, derandomize=True)
@given(st.floats(1.0, 6.0), st.floats(math.cos(math.radians(35.0)), 1.0),
       st.floats(0.0, 2.0 * math.pi))
def test_weight_is_one_in_the_nominal_region(distance: float, cosine: float,
                                             azimuth: float) -> None:
    """w = 1 and ∂w/∂p_i = 0 for D_m^th ≤ d̂ ≤ D_M^th and c ≥ cos α_M^th (closed region)."""
    target = np.array([0.5, 0.5, 0.0])
    drone = drone_at(target, distance, cosine, azimuth)
    terms = perception_terms(drone, target, PARAMS)
    # The round trip through positions moves d̂ and c by ~1e-15, so stay 1e-12 inside.
    if not (1.0 + 1e-12 < terms.distance_m < 6.0 - 1e-12
            and -terms.unit_bearing[2] > PARAMS.cos_alpha_th + 1e-12):
        return
    assert terms.weight == 1.0
    assert np.all(terms.weight_grad_drone == 0.0)


@pytest.mark.parametrize(
    ("distance", "cosine", "moved"),
    [(1.0, 0.95, "distance"), (6.0, 0.95, "distance"), (3.0, PARAMS.cos_alpha_th, "cosine"),
     (6.0, PARAMS.cos_alpha_th, "distance"), (6.0, PARAMS.cos_alpha_th, "cosine")],
)
def test_weight_and_gradient_are_continuous_at_thresholds(distance: float, cosine: float,
                                                          moved: str) -> None:
    """w and ∂w/∂p_i are continuous across each threshold (w is C¹ with ∂w = 0 there).

    Moving d̂ or c by ±1e-9 across a threshold changes w by O(|∂²w|·gap²) ≈ 1e-16 (bound
    1e-8) and ∂w by ≤ |∂²w|·2·gap with |∂²w| ≲ 2/σ_Dm² = 50 m⁻² and 2/σ_β²/d̂ ≈ 133/d̂: ≲ 1e-7
    (bound 1e-6). A jump of the kind a wrong case split would cause is O(1).
    """
    target = np.array([0.1, 0.0, 0.0])
    gap = 1e-9
    below = (distance - gap, cosine) if moved == "distance" else (distance, cosine - gap)
    above = (distance + gap, cosine) if moved == "distance" else (distance, min(cosine + gap, 1))
    t_below = perception_terms(drone_at(target, *below, 0.3), target, PARAMS)
    t_above = perception_terms(drone_at(target, *above, 0.3), target, PARAMS)
    assert abs(t_below.weight - t_above.weight) <= 1e-8
    np.testing.assert_allclose(t_below.weight_grad_drone, t_above.weight_grad_drone,
                               rtol=0, atol=1e-6)


@settings(deadline=None, max_examples=100, derandomize=True)
@given(st.floats(0.3, 10.0), st.floats(-0.9, 0.999), st.floats(0.0, 2.0 * math.pi))
def test_projector_and_bearing_in_terms_are_consistent(distance: float, cosine: float,
                                                       azimuth: float) -> None:
    """β̂ points from drone to estimate, d̂ is the distance and Π̂ = I − β̂β̂ᵀ."""
    target = np.array([1.0, -1.0, 0.2])
    drone = drone_at(target, distance, cosine, azimuth)
    terms = perception_terms(drone, target, PARAMS)
    np.testing.assert_allclose(drone + terms.distance_m * terms.unit_bearing, target,
                               atol=1e-12)
    np.testing.assert_allclose(terms.projector,
                               np.eye(3) - np.outer(terms.unit_bearing, terms.unit_bearing),
                               atol=1e-15)
