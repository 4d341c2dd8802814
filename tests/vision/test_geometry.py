"""The rendered camera's geometry (swarm.vision.geometry): its pixels are OpenCV's projection
of the thesis' image-plane points, and back (issue 45, point 6).

On random poses and lenses: a world point projected by ``cv2.projectPoints`` through the
calibration and undistorted back (``image_points_from_pixels``) is the bearing model's ideal
image point (``swarm.models.camera.ideal_image_point``, SPEC §2 1.8) to 1e-9, and that point
goes back to its pixel (``pixels_from_image_points``) to 1e-6 px; the pinhole's
pixels are K times those points, written out; the field of view's edge is the image's edge.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from swarm.models.camera import CameraParams, ideal_image_point
from swarm.vision.geometry import (
    CAMERA_FROM_WORLD,
    Calibration,
    CalibrationError,
    calibration_for,
    image_point_from_camera_vector,
    image_points_from_pixels,
    invertible_lens_rays,
    pixel_grid,
    pixels_from_image_points,
    project_to_pixels,
    undistorted_rays,
)
from swarm.vision.render import CameraRenderer, lens_ideal_positions

coordinate = st.floats(-20.0, 20.0)
lens = st.tuples(st.floats(-0.2, 0.05), st.floats(-0.02, 0.02), st.floats(-0.002, 0.002),
                 st.floats(-0.002, 0.002), st.just(0.0))


@settings(max_examples=150, deadline=None)
@given(drone_xy=st.tuples(coordinate, coordinate), height=st.floats(1.0, 8.0),
       along=st.tuples(st.floats(-0.95, 0.95), st.floats(-0.95, 0.95)),
       target_z=st.floats(-0.5, 0.5), distortion=lens,
       resolution=st.integers(64, 1280), half_fov=st.floats(20.0, 60.0))
def test_projection_and_undistortion_round_trip_to_the_thesis_image_point(
        drone_xy, height, along, target_z, distortion, resolution, half_fov) -> None:
    # The range does not matter here (the target 0.5 m below a drone 1 m up is in it).
    camera = CameraParams(model="rendered", resolution_px=resolution, half_fov_deg=half_fov,
                          distortion=distortion, range_min_m=0.01, range_max_m=100.0)
    calibration = calibration_for(camera)
    try:  # only lenses a config accepts (one that folds over the image is refused at load)
        invertible_lens_rays(calibration, pixel_grid(resolution, resolution,
                                                     max(resolution // 32, 1)))
    except CalibrationError:
        assume(False)
    drone = np.array([*drone_xy, height])
    depth = height - target_z
    # A target inside the field of view (0.95 of its half-width each way).
    limit = math.tan(math.radians(half_fov))
    target = np.array([drone[0] + along[0] * limit * depth,
                       drone[1] + along[1] * limit * depth, target_z])
    expected = ideal_image_point(drone, target, camera)
    assert expected is not None
    pixels = project_to_pixels(target[None, :], drone, calibration)
    back = image_points_from_pixels(pixels, calibration)
    assert np.allclose(back[0], expected, atol=1e-9, rtol=0.0)
    # and the image point back to its pixel (how a recording draws a detection)
    assert np.allclose(pixels_from_image_points(back, calibration), pixels, atol=1e-6,
                       rtol=0.0)
    if not calibration.distorted:  # the pinhole: u = f x̄ + c, v = −f ȳ + c
        f, c = calibration.camera_matrix[0, 0], calibration.camera_matrix[0, 2]
        assert np.allclose(pixels[0], [f * expected[0] + c, -f * expected[1] + c],
                           atol=1e-9 * max(1.0, f))


@pytest.mark.parametrize("resolution", [32, 480, 1001])
def test_the_field_of_view_ends_at_the_images_edges(resolution: int) -> None:
    camera = CameraParams(model="rendered", resolution_px=resolution, half_fov_deg=50.0,
                          range_max_m=100.0)
    calibration = calibration_for(camera)
    edge = math.tan(math.radians(50.0))
    drone = np.array([0.0, 0.0, 5.0])
    corners = np.array([[edge * 5.0, edge * 5.0, 0.0], [-edge * 5.0, -edge * 5.0, 0.0]])
    pixels = project_to_pixels(corners, drone, calibration)
    # +x̄ is the right edge, +ȳ the top (image rows grow downward).
    assert np.allclose(pixels, [[resolution - 0.5, -0.5], [-0.5, resolution - 0.5]],
                       atol=1e-9)
    assert calibration.width_px == calibration.height_px == resolution


def test_the_camera_frame_looks_down_with_x_along_the_worlds() -> None:
    assert np.allclose(CAMERA_FROM_WORLD @ [0.0, 0.0, -1.0], [0.0, 0.0, 1.0])  # optical axis
    assert np.linalg.det(CAMERA_FROM_WORLD) == pytest.approx(1.0)  # a rotation
    # A point below and to +x, +y of the camera: x̄ > 0, ȳ > 0, as ideal_image_point has it.
    drone, target = np.array([1.0, 2.0, 4.0]), np.array([2.0, 4.0, 0.0])
    point = image_point_from_camera_vector(CAMERA_FROM_WORLD @ (target - drone))
    assert np.allclose(point, ideal_image_point(drone, target, CameraParams()))


@pytest.mark.parametrize(("matrix", "distortion", "size", "said"), [
    (np.eye(2), np.zeros(5), (10, 10), "camera matrix must be 3 x 3"),
    (np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, np.nan]]), np.zeros(5), (10, 10),
     "camera matrix must be 3 x 3 finite"),
    (np.array([[-1.0, 0, 50], [0, 100, 50], [0, 0, 1]]), np.zeros(5), (10, 10),
     "with fx, fy > 0"),
    (np.array([[100.0, 0, 50], [3, 100, 50], [0, 0, 1]]), np.zeros(5), (10, 10),
     "[[fx, s, cx], [0, fy, cy], [0, 0, 1]]"),
    (np.diag([100.0, 100.0, 1.0]), np.zeros(3), (10, 10), "4, 5 or 8 finite coefficients"),
    (np.diag([100.0, 100.0, 1.0]), np.array([0, 0, 0, np.inf]), (10, 10), "finite"),
    (np.diag([100.0, 100.0, 1.0]), np.zeros(5), (0, 10), "image size must be positive"),
])
def test_a_bad_calibration_is_one_line(matrix, distortion, size, said) -> None:
    with pytest.raises(CalibrationError) as caught:
        Calibration(matrix, distortion, *size)
    assert said in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("distortion", [(-0.5, 0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0, -1.0)])
def test_a_lens_that_folds_the_image_is_refused_in_one_line(distortion) -> None:
    """Over a 50° half-field, k1 = −0.5 (or k3 = −1) is not one-to-one: the renderer cannot
    invert it, and says so rather than drawing a wrong image."""
    camera = CameraParams(model="rendered", distortion=distortion)
    with pytest.raises(CalibrationError) as caught:
        CameraRenderer(camera, 1)
    assert "cannot be inverted over the image" in str(caught.value)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("distortion", [(-0.15, 0.03, 0.001, -0.001, 0.0),
                                        (0.08, -0.02, -0.002, 0.001, 0.004)])
def test_the_lens_table_is_the_exact_undistortion_at_every_pixel(distortion) -> None:
    """The renderer's lens table (exact on knots, splined between) against OpenCV's
    undistortion of every pixel: within 0.01 px, a third of what ``cv2.remap`` resolves (it
    interpolates on a 1/32-pixel grid). Measured: 1e-4 px for the barrel lens, 0.002 px for
    the pincushion one with tangential terms (its corners bend faster)."""
    calibration = calibration_for(CameraParams(model="rendered", resolution_px=320,
                                               distortion=distortion))
    table_x, table_y = lens_ideal_positions(calibration)
    rays = undistorted_rays(pixel_grid(320, 320), calibration)
    exact, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                                 calibration.camera_matrix, np.zeros(5))
    exact = exact.reshape(320, 320, 2)
    assert np.abs(exact[..., 0] - table_x).max() < 0.01
    assert np.abs(exact[..., 1] - table_y).max() < 0.01
