"""What each drone's rendered camera sees, in Foxglove's well-known schemas
(``camera.model = "rendered"``; docs/camera.md, "Seen: images in Foxglove and in
recordings"): live (``swarm.observe.live_view``) and in recordings
(``swarm.observe.recording.writer``) alike.

Per drone i, on the frames ``ImageSchedule`` picks:

* ``camera/<i>/image``: the world's JPEG as the drone's detector read it, unchanged
  (``foxglove.CompressedImage``, ``compressed_image``);
* ``camera/<i>/calibration``: the camera's pinhole and lens (``foxglove.CameraCalibration``,
  OpenCV's ``plumb_bob`` model: ``camera_calibration``), so the Image panel can rectify and
  the 3D panel can draw the camera's frustum and the image in the scene;
* ``camera/<i>/annotations``: what the drone's detector reported for that frame, a circle
  and the target's name at each marker's centre (``foxglove.ImageAnnotations``,
  ``image_annotations``), from the ``CameraFrameWire`` the agent received;

and with the 3D scene, ``transforms``: where each camera is (``foxglove.FrameTransforms``,
``camera_transforms``), frame ``camera_<i>`` in ``world``. Foxglove's camera frame is OpenCV's
(x right, y down, z along the optical axis), so the nadir camera's rotation in W is
R_wc = R_cwᵀ = diag(1, −1, −1) (``swarm.vision.geometry.CAMERA_FROM_WORLD``), a half turn
about x (``CAMERA_IN_WORLD``). Foxglove's image coordinates start at the top-left *corner* of
the top-left pixel, OpenCV's at its centre: an annotation is drawn at OpenCV's pixel + 0.5.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np
from foxglove.messages import (
    CameraCalibration,
    CircleAnnotation,
    Color,
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    ImageAnnotations,
    Point2,
    Quaternion,
    TextAnnotation,
    Vector3,
)
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from swarm.messages.wire import CameraFrameWire, CameraImageWire
from swarm.observe.foxglove_scene import FRAME, sim_stamp
from swarm.scenario.config import ScenarioConfig
from swarm.vision.geometry import (
    CAMERA_FROM_WORLD,
    Calibration,
    calibration_for,
    pixels_from_image_points,
)

Array = NDArray[np.float64]

TRANSFORMS_TOPIC: Final = "transforms"
# A recording keeps about two images per drone and simulated second (a 480 px JPEG is ~27 KiB:
# ~0.35 MB per simulated second for six drones, 1.7 times the rest of a Case 2 recording); the live
# view, whose images go nowhere but the screen, ten (the 3D scene's rate).
RECORDED_IMAGE_PERIOD_S: Final = 0.5
LIVE_IMAGE_PERIOD_S: Final = 0.1
DETECTION_DIAMETER_PX: Final = 14.0
DETECTION_COLOUR: Final = Color(r=0.10, g=0.90, b=0.20, a=1.0)
LABEL_BACKGROUND: Final = Color(r=0.0, g=0.0, b=0.0, a=0.6)
FONT_SIZE_PX: Final = 14.0
# R_wc = R_cwᵀ as a quaternion (x, y, z, w): the half turn about x that diag(1, −1, −1) is.
_QUATERNION: Final = Rotation.from_matrix(CAMERA_FROM_WORLD.T).as_quat()
CAMERA_IN_WORLD: Final = Quaternion(x=float(_QUATERNION[0]), y=float(_QUATERNION[1]),
                                    z=float(_QUATERNION[2]), w=float(_QUATERNION[3]))
# Foxglove's (ROS's) name of OpenCV's lens model by its number of coefficients.
DISTORTION_MODELS: Final = {5: "plumb_bob", 8: "rational_polynomial"}


def image_topic(drone: int) -> str:
    return f"camera/{drone}/image"


def calibration_topic(drone: int) -> str:
    return f"camera/{drone}/calibration"


def annotations_topic(drone: int) -> str:
    return f"camera/{drone}/annotations"


def camera_frame_id(drone: int) -> str:
    return f"camera_{drone}"


class ImageSchedule:
    """Which of a rendered camera's frames an observer keeps: one every ``period_steps`` steps,
    the smallest multiple of the camera's frame period (``camera_steps_per_frame``) that spans
    at least ``period_s``, so that every kept step has a frame (25 Hz frames and 0.5 s: every
    26th step at 50 Hz steps, 1.92 Hz)."""

    def __init__(self, config: ScenarioConfig, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"image period must be a positive number of seconds, got "
                             f"{period_s!r}")
        frame_steps = config.camera_steps_per_frame
        wanted_steps = max(round(period_s / config.scenario.dt_s), 1)
        self.period_steps = frame_steps * math.ceil(wanted_steps / frame_steps)
        self.rate_hz = 1.0 / (self.period_steps * config.scenario.dt_s)

    def wants(self, step: int) -> bool:
        return step % self.period_steps == 0


def compressed_image(image: CameraImageWire) -> CompressedImage:
    """The world's frame as it went to the drone's detector (JPEG bytes, not re-encoded)."""
    return CompressedImage(timestamp=sim_stamp(image.time_s),
                           frame_id=camera_frame_id(image.drone), data=image.image,
                           format="jpeg")


def camera_calibration(calibration: Calibration, drone: int, time_s: float
                       ) -> CameraCalibration:
    """The camera's calibration in ROS's CameraInfo form, as Foxglove reads it: K, the lens
    (OpenCV's k1, k2, p1, p2, k3: ``plumb_bob``; with k4-k6: ``rational_polynomial``; four
    coefficients are five with k3 = 0), R = I and P = [K | 0] (a monocular camera)."""
    matrix = calibration.camera_matrix
    projection = np.zeros((3, 4))
    projection[:, :3] = matrix
    distortion = np.pad(calibration.distortion, (0, max(5 - calibration.distortion.size, 0)))
    return CameraCalibration(
        timestamp=sim_stamp(time_s), frame_id=camera_frame_id(drone),
        width=calibration.width_px, height=calibration.height_px,
        distortion_model=DISTORTION_MODELS[distortion.size], D=distortion.tolist(),
        K=matrix.reshape(-1).tolist(),
        R=np.eye(3).reshape(-1).tolist(), P=projection.reshape(-1).tolist())


def detection_pixels(frame: CameraFrameWire, calibration: Calibration) -> Array:
    """OpenCV pixels (K, 2) of the frame's detections, in their order: each image-plane point
    back through the lens (``pixels_from_image_points``)."""
    if not frame.detections:
        return np.zeros((0, 2))
    points = np.array([[d.x, d.y] for d in frame.detections], dtype=np.float64)
    return pixels_from_image_points(points, calibration)


def image_annotations(frame: CameraFrameWire, calibration: Calibration) -> ImageAnnotations:
    """A circle and the target's name (T0, T1, …) where the detector put each marker's
    centre, in Foxglove's image coordinates (OpenCV's + 0.5)."""
    pixels = detection_pixels(frame, calibration) + 0.5
    when = sim_stamp(frame.time_s)
    circles = [CircleAnnotation(timestamp=when, position=Point2(x=float(u), y=float(v)),
                                diameter=DETECTION_DIAMETER_PX, thickness=2.0,
                                outline_color=DETECTION_COLOUR)
               for u, v in pixels]
    texts = [TextAnnotation(timestamp=when,
                            position=Point2(x=float(u) + DETECTION_DIAMETER_PX / 2,
                                            y=float(v) - DETECTION_DIAMETER_PX / 2),
                            text=f"T{d.target}", font_size=FONT_SIZE_PX,
                            text_color=DETECTION_COLOUR, background_color=LABEL_BACKGROUND)
             for d, (u, v) in zip(frame.detections, pixels, strict=True)]
    return ImageAnnotations(timestamp=when, circles=circles, texts=texts)


def camera_transforms(drones_m: Array, time_s: float) -> FrameTransforms:
    """Frame ``camera_<i>`` in ``world`` for every drone with a position (its camera sits at
    its centre and looks down)."""
    when = sim_stamp(time_s)
    return FrameTransforms(transforms=[
        FrameTransform(timestamp=when, parent_frame_id=FRAME,
                       child_frame_id=camera_frame_id(i),
                       translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                       rotation=CAMERA_IN_WORLD)
        for i, p in enumerate(np.asarray(drones_m, dtype=np.float64))
        if np.isfinite(p).all()])


CameraMessage = CompressedImage | CameraCalibration | ImageAnnotations | FrameTransforms


class CameraView:
    """The camera topics of one observer (a recorder, a live view): which messages each
    image, camera frame and scene instant becomes, on the frames ``schedule`` keeps."""

    def __init__(self, config: ScenarioConfig, period_s: float) -> None:
        self.schedule = ImageSchedule(config, period_s)
        self.calibration = calibration_for(config.camera)
        self.n_drones = config.swarm.n_drones

    def topics(self) -> list[tuple[str, type[CameraMessage]]]:
        """Every topic with its message type, so that a viewer lists them from the start."""
        per_drone: list[tuple[str, type[CameraMessage]]] = [
            (topic(i), kind) for i in range(self.n_drones)
            for topic, kind in ((image_topic, CompressedImage),
                                (calibration_topic, CameraCalibration),
                                (annotations_topic, ImageAnnotations))]
        return [*per_drone, (TRANSFORMS_TOPIC, FrameTransforms)]

    def wants(self, step: int) -> bool:
        return self.schedule.wants(step)

    def of_image(self, image: CameraImageWire) -> list[tuple[str, CameraMessage]]:
        """A kept frame's image and the calibration it was taken with; nothing for a step
        without a frame or one not kept."""
        if not image.image or not self.wants(image.step):
            return []
        return [(image_topic(image.drone), compressed_image(image)),
                (calibration_topic(image.drone),
                 camera_calibration(self.calibration, image.drone, image.time_s))]

    def of_frame(self, frame: CameraFrameWire) -> list[tuple[str, CameraMessage]]:
        """The detections of a kept frame, as annotations of its image."""
        if not self.wants(frame.step):
            return []
        return [(annotations_topic(frame.drone), image_annotations(frame, self.calibration))]

    def of_scene(self, drones_m: Array, time_s: float) -> list[tuple[str, CameraMessage]]:
        return [(TRANSFORMS_TOPIC, camera_transforms(drones_m, time_s))]
