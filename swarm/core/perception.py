"""Perception-awareness weight w = w_D(d̂)·w_β(c) and its gradient (SPEC §3, thesis 3.6-3.7).

Computed from the drone's *estimate* of the target position, so that a drone that does not
see a target still knows which way to move to see it again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarm.core.params import PerceptionParams
from swarm.core.projector import (
    Mat3,
    Vec3,
    bearing,
    projector,
    projector_derivative_wrt_drone,
)


def distance_weight(distance_m: float, params: PerceptionParams) -> tuple[float, float]:
    """w_D(d̂) and dw_D/dd̂ (thesis 3.7, first case split)."""
    if distance_m < params.d_min_th_m:
        gap = distance_m - params.d_min_th_m
        value = math.exp(-gap * gap / params.sigma_dmin_sq_m2)
        return value, -2.0 * gap / params.sigma_dmin_sq_m2 * value
    if distance_m > params.d_max_th_m:
        gap = distance_m - params.d_max_th_m
        value = math.exp(-gap * gap / params.sigma_dmax_sq_m2)
        return value, -2.0 * gap / params.sigma_dmax_sq_m2 * value
    return 1.0, 0.0


def angle_weight(cos_off_axis: float, params: PerceptionParams) -> tuple[float, float]:
    """w_β(c) and dw_β/dc, c = −β̂_z the cosine to the optical axis (thesis 3.7)."""
    threshold = params.cos_alpha_th
    if cos_off_axis < threshold:
        gap = cos_off_axis - threshold
        value = math.exp(-gap * gap / params.sigma_beta_sq)
        return value, -2.0 * gap / params.sigma_beta_sq * value
    return 1.0, 0.0


@dataclass(frozen=True)
class PerceptionTerms:
    """Everything the barrier needs about one drone-target pair, from the estimate."""

    weight: float  # w_ir
    weight_grad_drone: Vec3  # ∂w/∂p_i (the gradient w.r.t. p̂_r is its negative)
    unit_bearing: Vec3  # β̂ = (p̂_r − p_i)/d̂
    distance_m: float  # d̂
    projector: Mat3  # Π̂


def perception_terms(
    drone_position: Vec3, target_position_estimate: Vec3, params: PerceptionParams
) -> PerceptionTerms:
    """w, ∂w/∂p_i, β̂, d̂ and Π̂ for drone i and its estimate of target r (SPEC §3).

    ∂d̂/∂p_i = −β̂ᵀ and ∂c/∂p_i = e_3ᵀ Π̂ / d̂ (SPEC §3; thesis B.18 drops the e_3ᵀ).
    """
    unit, distance = bearing(target_position_estimate - drone_position)
    proj = projector(unit)
    w_d, dw_d = distance_weight(distance, params)
    w_b, dw_b = angle_weight(-float(unit[2]), params)
    grad = -(w_b * dw_d) * unit + (w_d * dw_b / distance) * proj[2]
    return PerceptionTerms(w_d * w_b, grad, unit, distance, proj)


def perception_weight(
    drone_position: Vec3, target_position_estimate: Vec3, params: PerceptionParams
) -> float:
    """w_ir alone (SPEC §3)."""
    return perception_terms(drone_position, target_position_estimate, params).weight


def weighted_projector_derivative(terms: PerceptionTerms) -> NDArray[np.float64]:
    """∂(wΠ̂)/∂p_i,k = Π̂ ∂w/∂p_i,k + w ∂Π̂/∂p_i,k as a (3, 3, 3) array indexed [k] (SPEC §8)."""
    d_proj = projector_derivative_wrt_drone(terms.unit_bearing, terms.distance_m)
    return terms.weight_grad_drone[:, None, None] * terms.projector[None] + terms.weight * d_proj
