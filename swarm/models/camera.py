"""Downward gimballed camera: range, square field of view, image-plane noise (SPEC §2, 1.6-1.9).

``model = "bearing"`` (the thesis', the default): the world hands each drone the image-plane
point of every target in view plus Gaussian noise. ``model = "rendered"``: the world renders
each drone's image and a marker detector turns its pixels into those points
(``swarm.vision``, docs/camera.md); the settings below ``model`` are that camera's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from swarm.core.drone_step import Detection
from swarm.core.params import require, require_finite_positive

Array = NDArray[np.float64]
CameraModel = Literal["bearing", "rendered"]
# OpenCV's predefined marker families a rendered camera may use (marker id = target index);
# the smallest has 30 markers, more than the 16 targets a scenario may have.
MARKER_DICTIONARIES = ("DICT_4X4_50", "DICT_5X5_50", "DICT_6X6_50", "DICT_APRILTAG_16h5",
                       "DICT_APRILTAG_36h11")


@dataclass(frozen=True)
class CameraParams:
    range_min_m: float = 0.5  # D_m, targets nearer than this are not detected [m]
    range_max_m: float = 8.0  # D_M, targets farther than this are not detected [m]
    half_fov_deg: float = 50.0  # α_M, half-angle of the square field of view [deg]
    image_noise_std: float = 0.005  # σ_img on the normalized image plane [1]; 0 = exact
    # "bearing": the thesis' noisy image points; "rendered": images and a marker detector
    model: CameraModel = "bearing"
    # The rendered camera (model = "rendered"; ignored by "bearing"):
    resolution_px: int = 480  # square image, this many pixels a side [px]
    frame_rate_hz: float | None = None  # frames per second; None: one every step [Hz]
    # OpenCV's (k1, k2, p1, p2, k3) lens distortion; zeros: an ideal pinhole [1]
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    pixel_noise_std: float = 2.0  # Gaussian sensor noise on each pixel [grey levels]
    marker_size_m: float = 0.5  # side of each target's marker (its black square) [m]
    marker_dictionary: str = "DICT_4X4_50"  # OpenCV's marker family (MARKER_DICTIONARIES)
    jpeg_quality: int = 90  # of the encoded frames [1-100]

    def __post_init__(self) -> None:
        require_finite_positive("range_min_m", self.range_min_m)
        require(math.isfinite(self.range_max_m) and self.range_max_m > self.range_min_m,
                "range_max_m", "must be a finite number > range_min_m", self.range_max_m)
        require(math.isfinite(self.half_fov_deg) and 0 < self.half_fov_deg < 90,
                "half_fov_deg", "must lie in (0, 90) degrees", self.half_fov_deg)
        require(math.isfinite(self.image_noise_std) and self.image_noise_std >= 0,
                "image_noise_std", "must be a finite number >= 0", self.image_noise_std)
        require(self.model in ("bearing", "rendered"), "model",
                "must be 'bearing' or 'rendered'", self.model)
        require(32 <= self.resolution_px <= 4096, "resolution_px",
                "must be an integer in [32, 4096]", self.resolution_px)
        if self.frame_rate_hz is not None:
            require_finite_positive("frame_rate_hz", self.frame_rate_hz)
        require(all(math.isfinite(k) and abs(k) <= 1.0 for k in self.distortion),
                "distortion", "must be five finite numbers in [-1, 1] (k1, k2, p1, p2, k3)",
                self.distortion)
        require(math.isfinite(self.pixel_noise_std) and 0 <= self.pixel_noise_std <= 64,
                "pixel_noise_std", "must be a finite number in [0, 64]", self.pixel_noise_std)
        require_finite_positive("marker_size_m", self.marker_size_m)
        require(self.marker_dictionary in MARKER_DICTIONARIES, "marker_dictionary",
                f"must be one of {', '.join(MARKER_DICTIONARIES)}", self.marker_dictionary)
        require(1 <= self.jpeg_quality <= 100, "jpeg_quality", "must be an integer in [1, 100]",
                self.jpeg_quality)

    @property
    def rendered(self) -> bool:
        return self.model == "rendered"

    @property
    def image_half_width(self) -> float:
        return math.tan(math.radians(self.half_fov_deg))


def ideal_image_point(drone_position: Array, target_position: Array,
                      camera: CameraParams) -> Array | None:
    """Noise-free [x̄, ȳ] if the target is detected, else None (SPEC §2, 1.8).

    Detected iff D_m < d < D_M, the target is below the camera (p_ir,z < 0) and
    |x̄|, |ȳ| ≤ tan α_M.
    """
    relative = target_position - drone_position
    depth = -float(relative[2])
    if depth <= 0.0:
        return None
    distance = float(np.sqrt(relative @ relative))
    if not camera.range_min_m < distance < camera.range_max_m:
        return None
    point = relative[:2] / depth
    limit = camera.image_half_width
    if abs(point[0]) > limit or abs(point[1]) > limit:
        return None
    return point


def detect(drone_position: Array, target_positions: Array, camera: CameraParams,
           rng: np.random.Generator) -> list[Detection]:
    """Detections of every visible target with image-plane noise ν ~ N(0, σ_img²) (1.7, 1.9).

    Noise is drawn for every target, visible or not, so the random stream of one drone does
    not depend on what it happens to see.
    """
    noise = rng.normal(0.0, camera.image_noise_std, size=(len(target_positions), 2))
    detections = []
    for r, target in enumerate(target_positions):
        point = ideal_image_point(drone_position, target, camera)
        if point is not None:
            detections.append(Detection(r, point + noise[r]))
    return detections


def fov_segments(position: Array, half_fov_deg: float, range_max_m: float,
                 ground_z: float) -> list[Array]:
    """Edges of one camera's square FoV pyramid (SPEC §2), apex at the drone.

    The optical axis is −z; the four edges run to the ground plane, or stop at the sensing
    range D_M along the edge when the ground is farther. Returns 8 segments (4 edges, 4 sides
    of the base), none when the drone is not above the ground.
    """
    depth = float(position[2] - ground_z)
    if not depth > 0.0:
        return []
    half = math.tan(math.radians(half_fov_deg))
    edge_per_depth = math.sqrt(2.0 * half * half + 1.0)  # edge length per metre of depth
    depth = min(depth, range_max_m / edge_per_depth)
    corners = [position + depth * np.array([sx * half, sy * half, -1.0])
               for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    edges = [np.array([position, c]) for c in corners]
    base = [np.array([corners[k], corners[(k + 1) % 4]]) for k in range(4)]
    return edges + base
