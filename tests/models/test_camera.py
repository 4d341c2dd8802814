"""Downward camera: detection region, image point, image-plane noise (SPEC §2, 1.6-1.10).

Geometry is built so that the quantities compared with a threshold are computed exactly in
floating point: with the drone at height h above a target at z = 0, p_ir = [x, y, −h] is exact,
depth = h, and for h = 1 the image point is [x, y] bit for bit; for a target straight below,
d = sqrt(h²) = h exactly (IEEE sqrt is correctly rounded). Boundary cases then use the
neighbouring doubles (np.nextafter) to probe "just inside" and "just outside".
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarm.models.camera import CameraParams, detect, ideal_image_point

EXACT = CameraParams(image_noise_std=0.0)
LIMIT = EXACT.image_half_width  # tan α_M = tan 50°
ORIGIN = np.zeros(3)


def above(height: float, x: float = 0.0, y: float = 0.0) -> np.ndarray:
    """Drone position such that p_ir = target(origin) − drone = [x, y, −height]."""
    return np.array([-x, -y, height])


def up(value: float) -> float:
    return float(np.nextafter(value, math.inf))


def down(value: float) -> float:
    return float(np.nextafter(value, -math.inf))


def visible(drone: np.ndarray, target: np.ndarray = ORIGIN, camera: CameraParams = EXACT) -> bool:
    seen = ideal_image_point(drone, target, camera) is not None
    # detect() must agree with ideal_image_point() on visibility.
    detections = detect(drone, target[None, :], camera, np.random.default_rng(0))
    assert (len(detections) == 1) == seen
    return seen


def test_image_half_width_is_tan_of_half_fov() -> None:
    assert EXACT.image_half_width == math.tan(math.radians(50.0))
    assert CameraParams(half_fov_deg=45.0).image_half_width == pytest.approx(1.0, abs=1e-15)


# -- behind / level / above ----------------------------------------------------------------


@pytest.mark.parametrize("relative_z", [0.0, -0.0, 1e-12, 0.3, 2.0, 7.0])
def test_target_level_with_or_above_the_camera_is_not_detected(relative_z: float) -> None:
    """p_ir,z ≥ 0 (level or above the camera) is never detected, even in range and 'on axis'."""
    drone = np.array([0.0, 0.0, 3.0])
    for offset in ([0.0, 0.0], [1.0, 0.0], [0.3, -0.2], [2.0, 2.0]):
        target = drone + np.array([*offset, relative_z])
        if np.linalg.norm(target - drone) == 0.0:
            continue
        assert not visible(drone, target)


def test_target_just_below_the_camera_plane_uses_the_fov_not_the_sign() -> None:
    # Depth 1e-3 m at 2 m lateral: |x̄| = 2000 ≫ tan α_M, so out of the field of view.
    drone = np.array([0.0, 0.0, 1e-3])
    assert not visible(drone, np.array([2.0, 0.0, 0.0]))
    # Directly below at 1 m: detected.
    assert visible(np.array([0.0, 0.0, 1.0]))


# -- range: D_m < d < D_M (strict) ---------------------------------------------------------


def test_range_limits_are_strict() -> None:
    d_min, d_max = EXACT.range_min_m, EXACT.range_max_m
    assert not visible(above(d_min))
    assert not visible(above(d_max))
    assert visible(above(up(d_min)))
    assert visible(above(down(d_max)))
    assert not visible(above(down(d_min)))
    assert not visible(above(up(d_max)))
    assert not visible(above(0.3))
    assert not visible(above(8.5))
    assert visible(above(4.0))


def test_range_uses_the_euclidean_distance_not_the_depth() -> None:
    # [x, y, h] = [3, 4, 5]: d = sqrt(50) ≈ 7.07 < 8, seen; [3, 4, 6]: d = sqrt(61) ≈ 7.81, seen;
    # [4.5, 4.5, 6]: |x̄| = |ȳ| = 0.75 (inside the FoV), depth 6 < 8 but d = sqrt(76.5) ≈ 8.75.
    assert visible(above(5.0, 3.0, 4.0))
    assert visible(above(6.0, 3.0, 4.0))
    assert not visible(above(6.0, 4.5, 4.5))
    # Same geometry, larger range: now seen (so it was the range, not the FoV).
    assert visible(above(6.0, 4.5, 4.5), camera=CameraParams(range_max_m=9.0,
                                                             image_noise_std=0.0))


# -- field of view: |x̄|, |ȳ| ≤ tan α_M ------------------------------------------------------


@pytest.mark.parametrize("sx, sy", [(1, 0), (-1, 0), (0, 1), (0, -1)])
def test_fov_edge_is_inclusive(sx: int, sy: int) -> None:
    """At height 1 the image point is [x, y] exactly: |x̄| = tan α_M is detected (≤)."""
    assert visible(above(1.0, sx * LIMIT, sy * LIMIT))
    assert visible(above(1.0, sx * down(LIMIT), sy * down(LIMIT)))
    assert not visible(above(1.0, sx * up(LIMIT), sy * up(LIMIT)))


@pytest.mark.parametrize("sx, sy", [(1, 1), (1, -1), (-1, 1), (-1, -1)])
def test_fov_corners(sx: int, sy: int) -> None:
    """Square FoV: both |x̄| and |ȳ| at the limit is still inside; one ulp out on either is not."""
    assert visible(above(1.0, sx * LIMIT, sy * LIMIT))
    assert not visible(above(1.0, sx * up(LIMIT), sy * LIMIT))
    assert not visible(above(1.0, sx * LIMIT, sy * up(LIMIT)))
    assert not visible(above(1.0, sx * up(LIMIT), sy * up(LIMIT)))


def test_fov_is_square_not_conical() -> None:
    # The corner direction is at off-axis angle atan(√2·tan 50°) ≈ 59.3° > 50° and is seen.
    drone = above(1.0, 0.99 * LIMIT, 0.99 * LIMIT)
    relative = ORIGIN - drone
    off_axis = math.degrees(math.acos(-relative[2] / np.linalg.norm(relative)))
    assert off_axis > 59.0
    assert visible(drone)


def test_fov_limit_scales_with_depth() -> None:
    for height in (0.7, 2.0, 3.7, 5.0):
        inside = above(height, 0.999 * LIMIT * height, 0.0)
        outside = above(height, 1.001 * LIMIT * height, 0.0)
        assert visible(inside)
        assert not visible(outside)


# -- image point ---------------------------------------------------------------------------


def test_noise_free_image_point_is_relative_position_over_depth() -> None:
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(500):
        drone = rng.uniform([-3.0, -3.0, 1.0], [3.0, 3.0, 6.0])
        target = np.array([*rng.uniform(-3.0, 3.0, 2), 0.0])
        relative = target - drone
        point = ideal_image_point(drone, target, EXACT)
        detections = detect(drone, target[None, :], EXACT, np.random.default_rng(1))
        if point is None:
            assert detections == []
            continue
        checked += 1
        np.testing.assert_array_equal(point, relative[:2] / -relative[2])
        assert len(detections) == 1
        assert detections[0].target == 0
        np.testing.assert_array_equal(detections[0].image_point, point)
    assert checked > 100


def test_detections_carry_the_ids_of_the_visible_targets_in_order() -> None:
    drone = np.array([0.0, 0.0, 3.0])
    targets = np.array([
        [0.0, 0.0, 0.0],  # 0: below, visible
        [0.0, 0.0, 5.0],  # 1: above the camera
        [1.0, -1.0, 0.0],  # 2: visible
        [20.0, 0.0, 0.0],  # 3: out of range and FoV
        [-2.0, 0.5, 0.5],  # 4: visible
    ])
    detections = detect(drone, targets, EXACT, np.random.default_rng(0))
    assert [d.target for d in detections] == [0, 2, 4]
    for d in detections:
        relative = targets[d.target] - drone
        np.testing.assert_array_equal(d.image_point, relative[:2] / -relative[2])


def test_no_targets_gives_no_detections() -> None:
    assert detect(np.array([0.0, 0.0, 3.0]), np.zeros((0, 3)), EXACT,
                  np.random.default_rng(0)) == []


def test_image_noise_has_the_configured_standard_deviation() -> None:
    """Image-point error ν ~ N(0, σ²) per axis, independent, σ = image_noise_std.

    40 000 draws per axis: the sample std has relative standard error 1/sqrt(2n) ≈ 0.35 %, the
    mean σ/sqrt(n) = 2.5e-5, the x-y correlation 1/sqrt(n) = 0.005. Tolerances are 6 standard
    errors (2.1 %, 1.5e-4, 0.03): a wrong σ (e.g. variance used as std, or σ·√2) fails by
    far, and with the fixed seed the test is deterministic.
    """
    sigma = 0.005
    camera = CameraParams(image_noise_std=sigma)
    n = 40_000
    drone = np.array([0.0, 0.0, 3.0])
    target = np.array([0.3, -0.2, 0.0])
    ideal = ideal_image_point(drone, target, camera)
    assert ideal is not None
    detections = detect(drone, np.tile(target, (n, 1)), camera, np.random.default_rng(2024))
    assert len(detections) == n
    errors = np.array([d.image_point for d in detections]) - ideal
    assert np.all(np.abs(errors.mean(axis=0)) < 6 * sigma / math.sqrt(n))
    std = errors.std(axis=0, ddof=1)
    np.testing.assert_allclose(std, sigma, rtol=6 / math.sqrt(2 * n))
    assert abs(np.corrcoef(errors.T)[0, 1]) < 6 / math.sqrt(n)
    # Gaussian tails: about 0.27 % beyond 3σ (binomial sd ≈ 0.018 % for 80 000 draws).
    beyond = np.mean(np.abs(errors) > 3 * sigma)
    assert 0.0027 - 6 * 0.00018 < beyond < 0.0027 + 6 * 0.00018


def test_image_noise_does_not_change_visibility() -> None:
    """Detection is decided on the noise-free point: a target at the FoV edge stays visible."""
    camera = CameraParams(image_noise_std=0.5)
    drone = above(1.0, LIMIT, LIMIT)
    for seed in range(20):
        assert len(detect(drone, ORIGIN[None, :], camera, np.random.default_rng(seed))) == 1
    assert detect(above(1.0, up(LIMIT), 0.0), ORIGIN[None, :], camera,
                  np.random.default_rng(0)) == []


# -- random stream -------------------------------------------------------------------------


@pytest.mark.parametrize("sigma", [0.0, 0.005])
def test_random_stream_does_not_depend_on_visibility(sigma: float) -> None:
    camera = CameraParams(image_noise_std=sigma)
    drone = np.array([0.0, 0.0, 3.0])
    scenes = {
        "all visible": np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]),
        "none visible": np.array([[0.0, 0.0, 9.0], [50.0, 0.0, 0.0]]),
        "mixed": np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]]),
    }
    next_draws = {}
    noise = {}
    for name, targets in scenes.items():
        rng = np.random.default_rng(77)
        detections = detect(drone, targets, camera, rng)
        next_draws[name] = rng.random(8)
        noise[name] = {d.target: d.image_point - ideal_image_point(drone, targets[d.target], camera)
                       for d in detections}
    first = next_draws["all visible"]
    for draws in next_draws.values():
        np.testing.assert_array_equal(draws, first)
    # Target 0 gets the same noise whether target 1 is visible or not.
    np.testing.assert_array_equal(noise["mixed"][0], noise["all visible"][0])


def test_random_stream_advances_by_two_normals_per_target() -> None:
    """The same draws as rng.normal(0, σ, (M, 2)): a process-based world can reproduce them."""
    sigma = 0.005
    camera = CameraParams(image_noise_std=sigma)
    drone = np.array([0.0, 0.0, 3.0])
    targets = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 9.0]])
    rng, reference = np.random.default_rng(3), np.random.default_rng(3)
    detections = detect(drone, targets, camera, rng)
    expected_noise = reference.normal(0.0, sigma, size=(3, 2))
    for d in detections:
        np.testing.assert_array_equal(
            d.image_point, ideal_image_point(drone, targets[d.target], camera)
            + expected_noise[d.target])
    np.testing.assert_array_equal(rng.random(4), reference.random(4))


# -- parameter validation ------------------------------------------------------------------


def test_defaults_are_the_spec_values() -> None:
    camera = CameraParams()
    assert (camera.range_min_m, camera.range_max_m, camera.half_fov_deg,
            camera.image_noise_std) == (0.5, 8.0, 50.0, 0.005)


@pytest.mark.parametrize("kwargs, field", [
    ({"range_min_m": -0.5}, "range_min_m"),
    ({"range_min_m": 0.0}, "range_min_m"),
    ({"range_min_m": math.nan}, "range_min_m"),
    ({"range_max_m": -1.0}, "range_max_m"),
    ({"range_max_m": 0.5}, "range_max_m"),  # = range_min_m
    ({"range_max_m": 0.4}, "range_max_m"),
    ({"range_max_m": math.inf}, "range_max_m"),
    ({"half_fov_deg": 90.0}, "half_fov_deg"),
    ({"half_fov_deg": 120.0}, "half_fov_deg"),
    ({"half_fov_deg": 0.0}, "half_fov_deg"),
    ({"half_fov_deg": -10.0}, "half_fov_deg"),
    ({"half_fov_deg": math.nan}, "half_fov_deg"),
    ({"image_noise_std": math.nan}, "image_noise_std"),
    ({"image_noise_std": -0.001}, "image_noise_std"),
    ({"image_noise_std": math.inf}, "image_noise_std"),
])
def test_camera_params_reject_invalid_values(kwargs: dict[str, float], field: str) -> None:
    with pytest.raises(ValueError, match=field) as info:
        CameraParams(**kwargs)
    assert "\n" not in str(info.value)


def test_camera_params_accept_edge_values() -> None:
    """Values at the edges of the valid ranges are accepted and do what they say: σ_img = 0
    detects exactly, a half field of view just under 90° sees a target almost level with the
    camera, and a range band of a micrometre still detects inside it."""
    drone, target = np.array([0.0, 0.0, 5.0]), np.array([[1.0, -0.5, 0.0]])
    exact = CameraParams(image_noise_std=0.0)
    [detection] = detect(drone, target, exact, np.random.default_rng(0))
    np.testing.assert_array_equal(detection.image_point,
                                  ideal_image_point(drone, target[0], exact))
    far_to_the_side = np.array([300.0, 0.0, 4.0])  # 1 m below, 300 m east: x̄ = 300
    wide = CameraParams(half_fov_deg=89.9, range_max_m=1000.0)
    assert wide.image_half_width == pytest.approx(math.tan(math.radians(89.9)))
    assert ideal_image_point(drone, far_to_the_side, wide) is not None
    assert ideal_image_point(drone, far_to_the_side, CameraParams(range_max_m=1000.0)) is None
    thin = CameraParams(range_min_m=1e-6, range_max_m=2e-6)
    assert ideal_image_point(drone, drone - [0.0, 0.0, 1.5e-6], thin) is not None
    assert ideal_image_point(drone, drone - [0.0, 0.0, 3e-6], thin) is None
