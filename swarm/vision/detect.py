"""The marker detector (docs/camera.md, "Detecting"): a camera frame's pixels to the
detections the agents use, ``Detection(target, [x̄, ȳ])``.

Each frame is decoded (``cv2.imdecode``), its markers found by OpenCV's ArUco detector with
sub-pixel corners, and each marker's pose solved from its four corners through the
calibration (``cv2.solvePnP``, ``SOLVEPNP_IPPE_SQUARE``, the planar-square solver): the
translation is the marker centre, i.e. the target, in the camera frame, whose image point
(``geometry.image_point_from_camera_vector``) is what the bearing camera sends. The pose also
gives the marker's distance, so that the detector keeps the camera's working range
(``range_min_m`` < d < ``range_max_m``) as the bearing camera does. What cannot be used is
counted with its reason, never passed on: an image that does not decode or has the wrong
size, a marker id that is no target, an id seen twice in one frame, a pose that does not
solve, a marker outside the working range.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from swarm.core.drone_step import Detection
from swarm.models.camera import CameraParams
from swarm.vision.geometry import Calibration, image_point_from_camera_vector

Image = NDArray[np.uint8]

# The reasons a frame or a marker is rejected (counted per reason).
UNDECODABLE = "undecodable image"
WRONG_SIZE = "wrong image size"
UNKNOWN_ID = "marker id is no target"
DUPLICATE_ID = "marker id seen twice"
NO_POSE = "marker pose did not solve"
OUT_OF_RANGE = "marker outside the camera's range"


@dataclass(frozen=True)
class FrameDetections:
    """One frame's detections (sorted by target), the marker corners found [px] (for the
    annotations), and what was rejected, by reason."""

    detections: list[Detection]
    corners_px: dict[int, NDArray[np.float64]] = field(default_factory=dict)
    rejected: Counter[str] = field(default_factory=Counter)


class MarkerDetector:
    """One camera's detector: its marker family and size, its calibration, the targets."""

    def __init__(self, camera: CameraParams, calibration: Calibration, n_targets: int) -> None:
        self.camera = camera
        self.calibration = calibration
        self.n_targets = n_targets
        dictionary = cv2.aruco.getPredefinedDictionary(
            getattr(cv2.aruco, camera.marker_dictionary))
        parameters = cv2.aruco.DetectorParameters()
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.ArucoDetector(dictionary, parameters)
        half = camera.marker_size_m / 2.0
        # IPPE_SQUARE's corner order: top left, top right, bottom right, bottom left.
        self._square = np.array([[-half, half, 0.0], [half, half, 0.0], [half, -half, 0.0],
                                 [-half, -half, 0.0]])

    def detect_encoded(self, data: bytes) -> FrameDetections:
        """Decode a frame (any format OpenCV reads) and ``detect`` it."""
        buffer = np.frombuffer(data, dtype=np.uint8)
        image = cv2.imdecode(buffer, cv2.IMREAD_GRAYSCALE) if buffer.size else None
        if image is None:
            return FrameDetections([], rejected=Counter({UNDECODABLE: 1}))
        return self.detect(np.asarray(image, dtype=np.uint8))

    def detect(self, image: Image) -> FrameDetections:
        """The detections of one greyscale frame of the calibration's size."""
        cal = self.calibration
        if image.ndim != 2 or image.shape != (cal.height_px, cal.width_px):
            return FrameDetections([], rejected=Counter({WRONG_SIZE: 1}))
        corners, ids, _ = self._detector.detectMarkers(image)
        rejected: Counter[str] = Counter()
        if ids is None:
            return FrameDetections([], rejected=rejected)
        found = [int(i) for i in np.asarray(ids).reshape(-1)]
        seen = Counter(found)
        detections: list[Detection] = []
        kept_corners: dict[int, NDArray[np.float64]] = {}
        for marker_id, marker_corners in zip(found, corners, strict=True):
            if not 0 <= marker_id < self.n_targets:
                rejected[UNKNOWN_ID] += 1
                continue
            if seen[marker_id] > 1:
                rejected[DUPLICATE_ID] += 1
                continue
            pixels = np.asarray(marker_corners, dtype=np.float64).reshape(4, 2)
            solved, _rvec, tvec = cv2.solvePnP(self._square, pixels, cal.camera_matrix,
                                               cal.distortion, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            centre = np.asarray(tvec, dtype=np.float64).reshape(3)
            if not solved or not np.isfinite(centre).all() or not centre[2] > 0.0:
                rejected[NO_POSE] += 1
                continue
            distance = float(np.linalg.norm(centre))
            if not self.camera.range_min_m < distance < self.camera.range_max_m:
                rejected[OUT_OF_RANGE] += 1
                continue
            detections.append(Detection(marker_id, image_point_from_camera_vector(centre)))
            kept_corners[marker_id] = pixels
        detections.sort(key=lambda d: d.target)
        return FrameDetections(detections, kept_corners, rejected)
