"""The rendered camera's images (docs/camera.md, "Rendering"): the textured ground and each
target's fiducial marker as a drone's downward camera sees them, through its lens, with
sensor noise. Deterministic: the same pose, targets and noise stream give the same pixels.

The ground is the plane z = 0 covered by a fixed grey texture (smooth blobs, no edges that
could read as a marker); each target carries a flat marker of side ``marker_size_m`` centred
on it, level at its height, its top edge towards +y, with a one-module white quiet zone. A
plane seen through a pinhole is a homography: the ground and each marker are warped into
the ideal (undistorted) image with ``cv2.warpPerspective``, the homography found from four
points projected by ``cv2.projectPoints``; the lens is then applied by ``cv2.remap`` through
the map of ``cv2.undistortPoints`` (each output pixel looks up its ideal position), on an
ideal canvas wide enough for what the lens pulls in from beyond the edges. Everything is
drawn at ``SUPERSAMPLING`` times the resolution and averaged down (``cv2.INTER_AREA``), as a
sensor's pixel integrates its light: drawn once at the sensor's resolution, the warp's and
the lens's interpolations blur a marker of 15 pixels past reading (measured at 320 px with
k1 = −0.15: 63 % of the markers at 3.5-4.5 m read drawn once, 83 % supersampled).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RectBivariateSpline

from swarm.models.camera import CameraParams
from swarm.vision.geometry import (
    Calibration,
    calibration_for,
    invertible_lens_rays,
    pixels_of_rays,
    project_to_pixels,
)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

TEXTURE_HALF_SIDE_M = 60.0  # the texture covers [−60, 60]² m; mirrored beyond
TEXTURE_M_PER_PX = 0.05
TEXTURE_SEED = 20_251_206  # one ground for every run (it is scenery, not noise)
MARKER_TILE_MODULE_PX = 16  # pixels per marker module in the tile that is warped
QUIET_ZONE_MODULES = 1
SUPERSAMPLING = 2  # rendered at this many times the resolution, then averaged down


def ground_texture(seed: int = TEXTURE_SEED) -> Image:
    """The ground's grey texture: blobs at three scales (≈ 6 m, 1.2 m, 0.3 m), grey levels
    in [70, 185], smooth (no edge that a marker detector could take for a marker's)."""
    rng = np.random.default_rng(seed)
    side = round(2 * TEXTURE_HALF_SIDE_M / TEXTURE_M_PER_PX)
    texture = np.zeros((side, side), dtype=np.float32)
    for cells, weight in ((20, 0.55), (100, 0.3), (400, 0.15)):
        coarse = rng.uniform(-1.0, 1.0, size=(cells, cells)).astype(np.float32)
        texture += weight * cv2.resize(coarse, (side, side), interpolation=cv2.INTER_CUBIC)
    grey = 128.0 + 55.0 * np.clip(texture, -1.05, 1.05)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)


def marker_tile(dictionary_name: str, marker_id: int) -> Image:
    """Marker ``marker_id`` of OpenCV's ``dictionary_name`` with its white quiet zone
    (``cv2.aruco.generateImageMarker``)."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary_name))
    modules = dictionary.markerSize + 2  # the bits and the black border
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id,
                                           modules * MARKER_TILE_MODULE_PX)
    margin = QUIET_ZONE_MODULES * MARKER_TILE_MODULE_PX
    return np.asarray(cv2.copyMakeBorder(marker, margin, margin, margin, margin,
                                         cv2.BORDER_CONSTANT, value=255), dtype=np.uint8)


class CameraRenderer:
    """Renders one camera model's images (the same for every drone: each call gives the
    drone's position, the targets and that drone's noise stream)."""

    def __init__(self, camera: CameraParams, n_targets: int,
                 texture: Image | None = None) -> None:
        self.camera = camera
        self.calibration = calibration_for(camera)
        # The sensor drawn SUPERSAMPLING times finer: the same field of view and lens.
        fine = calibration_for(dataclasses.replace(
            camera, resolution_px=camera.resolution_px * SUPERSAMPLING))
        self.texture = ground_texture() if texture is None else texture
        self.tiles = [marker_tile(camera.marker_dictionary, r) for r in range(n_targets)]
        modules = self.tiles[0].shape[0] / MARKER_TILE_MODULE_PX if self.tiles else 1.0
        # The tile's world side: the marker's (its black square) plus the quiet zone.
        self.tile_side_m = camera.marker_size_m * modules / (modules - 2 * QUIET_ZONE_MODULES)
        self.canvas_calibration, self._lens_maps = _lens(fine)

    def render(self, camera_position_w: Array, target_positions_w: Array,
               rng: np.random.Generator) -> Image:
        """The drone's greyscale image (H, W) uint8."""
        canvas_cal = self.canvas_calibration
        size = (canvas_cal.width_px, canvas_cal.height_px)
        position = np.asarray(camera_position_w, dtype=np.float64)
        canvas = np.asarray(cv2.warpPerspective(
            self.texture, self._ground_homography(position), size, flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT_101), dtype=np.uint8)
        for tile, target in zip(self.tiles, np.asarray(target_positions_w), strict=True):
            self._draw_marker(canvas, tile, position, target)
        fine = canvas if self._lens_maps is None else cv2.remap(
            canvas, *self._lens_maps, interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE)
        side = self.calibration.width_px
        image = cv2.resize(fine, (side, side), interpolation=cv2.INTER_AREA)
        noise = rng.normal(0.0, self.camera.pixel_noise_std, size=image.shape)
        return np.clip(np.rint(image + noise), 0, 255).astype(np.uint8)

    def _ground_homography(self, position: Array) -> Array:
        """Texture pixel → ideal canvas pixel, from four ground points around the nadir."""
        height = max(float(position[2]), 0.1)
        offsets = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]]) * height
        ground = np.column_stack([position[:2] + offsets, np.zeros(4)])
        texture_px = np.column_stack([
            (ground[:, 0] + TEXTURE_HALF_SIDE_M) / TEXTURE_M_PER_PX - 0.5,
            (TEXTURE_HALF_SIDE_M - ground[:, 1]) / TEXTURE_M_PER_PX - 0.5])
        image_px = project_to_pixels(ground, position, self.canvas_calibration)
        return np.asarray(cv2.getPerspectiveTransform(texture_px.astype(np.float32),
                                                      image_px.astype(np.float32)),
                          dtype=np.float64)

    def _draw_marker(self, canvas: Image, tile: Image, position: Array,
                     target: Array) -> None:
        """The target's marker warped onto the canvas where it is in view (in place)."""
        half = self.tile_side_m / 2.0
        if not float(position[2] - target[2]) > 0.05:  # the marker is not below the camera
            return
        corners_w = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0],
                              [-half, -half, 0.0]]) + target
        corners_px = project_to_pixels(corners_w, position, self.canvas_calibration)
        height, width = canvas.shape
        x0, y0 = np.floor(corners_px.min(axis=0)).astype(int)
        x1, y1 = np.ceil(corners_px.max(axis=0)).astype(int) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if x0 >= x1 or y0 >= y1:
            return
        side = tile.shape[0]
        src = np.array([[-0.5, -0.5], [side - 0.5, -0.5], [side - 0.5, side - 0.5],
                        [-0.5, side - 0.5]], dtype=np.float32)
        dst = (corners_px - np.array([x0, y0])).astype(np.float32)
        window = canvas[y0:y1, x0:x1].copy()
        cv2.warpPerspective(tile, cv2.getPerspectiveTransform(src, dst), (x1 - x0, y1 - y0),
                            dst=window, flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_TRANSPARENT)
        canvas[y0:y1, x0:x1] = window


LENS_KNOT_SPACING_PX = 8  # the lens's table is exact at knots this far apart, splined between


def lens_ideal_positions(calibration: Calibration, knot_spacing_px: int = LENS_KNOT_SPACING_PX
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each image pixel's ideal (undistorted) position, (H, W) x and y tables [px].

    Exact (``cv2.undistortPoints``, checked invertible, ``invertible_lens_rays``) on knots every
    ``knot_spacing_px`` pixels and on the last row and column, a bicubic spline between: the
    lens polynomial is smooth, and undistorting every pixel of a supersampled image costs
    seconds (0.9 M points, iterated) where the knots cost milliseconds. ``tests/vision/
    test_geometry.py`` binds the spline to the exact positions at every pixel of a lens."""
    width, height = calibration.width_px, calibration.height_px
    xs = np.unique(np.append(np.arange(0, width, knot_spacing_px), width - 1)).astype(float)
    ys = np.unique(np.append(np.arange(0, height, knot_spacing_px), height - 1)).astype(float)
    grid_x, grid_y = np.meshgrid(xs, ys)
    knots = np.stack([grid_x.ravel(), grid_y.ravel()], axis=1)
    rays = invertible_lens_rays(calibration, knots)
    ideal = pixels_of_rays(rays, calibration, lens=False).reshape(ys.size, xs.size, 2)
    order = min(3, xs.size - 1, ys.size - 1)
    every_x, every_y = np.arange(width, dtype=float), np.arange(height, dtype=float)
    tables = [RectBivariateSpline(ys, xs, ideal[:, :, axis], kx=order, ky=order)(every_y,
                                                                                 every_x)
              for axis in (0, 1)]
    return tables[0], tables[1]


def _lens(calibration: Calibration) -> tuple[Calibration, tuple[NDArray[np.float32],
                                                                   NDArray[np.float32]] | None]:
    """The ideal canvas's calibration and the lens's remap tables (None: no distortion).

    Each output pixel's ideal position comes from ``lens_ideal_positions``; the canvas is
    widened by the margin those positions need beyond the image's edges."""
    if not calibration.distorted:
        return calibration, None
    width, height = calibration.width_px, calibration.height_px
    ideal_x, ideal_y = lens_ideal_positions(calibration)
    low = min(float(ideal_x.min()), float(ideal_y.min()), 0.0)
    high = max(float(ideal_x.max()) - (width - 1), float(ideal_y.max()) - (height - 1), 0.0)
    margin = math.ceil(max(-low, high)) + 2
    matrix = calibration.camera_matrix.copy()
    matrix[0, 2] += margin
    matrix[1, 2] += margin
    canvas = Calibration(matrix, np.zeros(5), width + 2 * margin, height + 2 * margin)
    return canvas, ((ideal_x + margin).astype(np.float32), (ideal_y + margin).astype(np.float32))
