"""The rendered camera's geometry: its pinhole calibration and how its pixels relate to the
thesis' image-plane points (docs/camera.md, "The camera's frames").

The camera is gimballed and looks straight down, its image axes fixed in W (the bearing
model's camera, ``swarm.core.projector.bearing_from_image_point``): OpenCV's camera frame has
x_c = x_W, y_c = −y_W and z_c = −z_W (the optical axis). A point at p_W relative to the camera
is at p_c = R_cw p_W, R_cw = diag(1, −1, −1), and its thesis image point is
[x̄, ȳ] = [p_W,x, p_W,y] / (−p_W,z) = [x_n, −y_n] with (x_n, y_n) = (p_c,x, p_c,y) / p_c,z
OpenCV's normalized coordinates. The intrinsics follow from the configured field of view: a
square image of W pixels whose edges (pixel −0.5 and W − 0.5) are the half-angle α_M off the
axis, so f = (W / 2) / tan α_M and the principal point is ((W − 1) / 2, (W − 1) / 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from swarm.errors import VigilError
from swarm.models.camera import CameraParams

Array = NDArray[np.float64]

CAMERA_FROM_WORLD = np.diag([1.0, -1.0, -1.0])  # R_cw: the nadir camera's frame in W
_RVEC_CAMERA_FROM_WORLD = cv2.Rodrigues(CAMERA_FROM_WORLD)[0]


class CalibrationError(VigilError, ValueError):
    """A calibration that cannot describe this camera (shape, values, size); one line."""


@dataclass(frozen=True, eq=False)
class Calibration:
    """OpenCV's pinhole model of one camera: K (3, 3), the (k1, k2, p1, p2, k3) distortion
    and the image size it was made for."""

    camera_matrix: Array
    distortion: Array
    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        k = np.asarray(self.camera_matrix, dtype=np.float64)
        d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        if k.shape != (3, 3) or not np.isfinite(k).all():
            raise CalibrationError(f"camera matrix must be 3 x 3 finite numbers (got shape "
                                   f"{k.shape})")
        if not (k[0, 0] > 0 and k[1, 1] > 0 and k[2, 2] == 1.0 and k[1, 0] == k[2, 0]
                == k[2, 1] == 0.0):
            raise CalibrationError("camera matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] "
                                   "with fx, fy > 0")
        if d.shape[0] not in (4, 5, 8) or not np.isfinite(d).all():
            raise CalibrationError(f"distortion must be 4, 5 or 8 finite coefficients (got "
                                   f"{d.shape[0]})")
        if not (self.width_px > 0 and self.height_px > 0):
            raise CalibrationError(f"image size must be positive (got {self.width_px} x "
                                   f"{self.height_px})")
        object.__setattr__(self, "camera_matrix", k)
        object.__setattr__(self, "distortion", d)

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.distortion != 0.0))


def calibration_for(camera: CameraParams) -> Calibration:
    """The rendered camera's calibration from its field of view and resolution (module
    docstring)."""
    width = camera.resolution_px
    focal = (width / 2.0) / math.tan(math.radians(camera.half_fov_deg))
    centre = (width - 1) / 2.0
    matrix = np.array([[focal, 0.0, centre], [0.0, focal, centre], [0.0, 0.0, 1.0]])
    return Calibration(matrix, np.array(camera.distortion, dtype=np.float64), width, width)


def world_to_camera_pose(camera_position_w: Array) -> tuple[Array, Array]:
    """OpenCV's (rvec, tvec) of the world in the camera at ``camera_position_w``:
    p_c = R_cw (p_W − c_W)."""
    tvec = -CAMERA_FROM_WORLD @ np.asarray(camera_position_w, dtype=np.float64)
    return np.asarray(_RVEC_CAMERA_FROM_WORLD, dtype=np.float64).copy(), tvec


def project_to_pixels(points_w: Array, camera_position_w: Array,
                      calibration: Calibration) -> Array:
    """Pixels (K, 2) of world points (K, 3) in front of the camera, through its lens
    (``cv2.projectPoints``)."""
    rvec, tvec = world_to_camera_pose(camera_position_w)
    pixels, _ = cv2.projectPoints(np.asarray(points_w, dtype=np.float64).reshape(-1, 1, 3),
                                  rvec, tvec, calibration.camera_matrix,
                                  calibration.distortion)
    return np.asarray(pixels, dtype=np.float64).reshape(-1, 2)


def image_points_from_pixels(pixels: Array, calibration: Calibration) -> Array:
    """The thesis' image-plane points [x̄, ȳ] (K, 2) of pixels (K, 2) seen through the lens:
    their ``undistorted_rays`` (OpenCV's normalized coordinates), then [x_n, −y_n] (module
    docstring)."""
    rays = undistorted_rays(pixels, calibration)
    return np.column_stack([rays[:, 0], -rays[:, 1]])


def pixels_from_image_points(image_points: Array, calibration: Calibration) -> Array:
    """Pixels (K, 2) of the thesis' image-plane points [x̄, ȳ] (K, 2), through the lens: the
    inverse of ``image_points_from_pixels`` (the rays (x̄, −ȳ, 1) in the camera frame,
    ``cv2.projectPoints``)."""
    points = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    return pixels_of_rays(np.column_stack([points[:, 0], -points[:, 1],
                                           np.ones(points.shape[0])]), calibration)


def pixels_of_rays(rays: Array, calibration: Calibration, *, lens: bool = True) -> Array:
    """Pixels (K, 2) of rays (K, 3) in the camera frame (``cv2.projectPoints``), through the
    lens or, ``lens=False``, through the bare pinhole."""
    distortion = calibration.distortion if lens else np.zeros(5)
    pixels, _ = cv2.projectPoints(np.asarray(rays, dtype=np.float64).reshape(-1, 1, 3),
                                  np.zeros(3), np.zeros(3), calibration.camera_matrix,
                                  distortion)
    return np.asarray(pixels, dtype=np.float64).reshape(-1, 2)


def pixel_grid(width_px: int, height_px: int, step_px: int = 1) -> Array:
    """Pixel centres (K, 2) every ``step_px`` across the image, its last row and column
    always included."""
    xs = np.unique(np.append(np.arange(0, width_px, step_px), width_px - 1)).astype(np.float64)
    ys = np.unique(np.append(np.arange(0, height_px, step_px), height_px - 1)).astype(np.float64)
    grid_x, grid_y = np.meshgrid(xs, ys)
    return np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)


def undistorted_rays(pixels: Array, calibration: Calibration) -> Array:
    """The rays (K, 3) = (x_n, y_n, 1) in the camera frame of pixels (K, 2) seen through the
    lens (``cv2.undistortPoints``, iterated to convergence)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    normalized = cv2.undistortPoints(np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2),
                                     calibration.camera_matrix, calibration.distortion,
                                     criteria=criteria)
    flat = np.asarray(normalized, dtype=np.float64).reshape(-1, 2)
    return np.concatenate([flat, np.ones((flat.shape[0], 1))], axis=1)


def invertible_lens_rays(calibration: Calibration, pixels: Array) -> Array:
    """``undistorted_rays`` of ``pixels``, checked: each must come back to its pixel through
    the lens (projected with the distortion) within 0.01 px, else ``CalibrationError``: where
    the polynomial folds (is not one-to-one over the image) the inversion lands elsewhere."""
    rays = undistorted_rays(pixels, calibration)
    if not calibration.distorted:
        return rays
    worst = float(np.max(np.abs(pixels_of_rays(rays, calibration) - pixels)))
    if not worst < 0.01:
        raise CalibrationError(f"the lens (distortion {calibration.distortion.tolist()}) "
                               f"cannot be inverted over the image: a pixel's ray comes back "
                               f"{worst:.3g} px away (the polynomial folds)")
    return rays


def image_point_from_camera_vector(vector_c: Array) -> Array:
    """[x̄, ȳ] of a point at ``vector_c`` in the camera frame (in front of it: z_c > 0)."""
    x, y, z = (float(v) for v in np.asarray(vector_c, dtype=np.float64).reshape(3))
    return np.array([x / z, -y / z])
