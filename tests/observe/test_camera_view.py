"""swarm.observe.camera_view: each drone's rendered camera in Foxglove, in recordings and live
(issue 45, point 4).

Read back as any MCAP tool reads it (the MCAP project's protobuf decoder) and as a viewer
receives it (a Foxglove WebSocket client): every kept frame's JPEG is the world's, decodes to
the configured size and shows the markers where the camera's geometry puts the targets; the
calibration is the renderer's; each annotation sits, in Foxglove's image coordinates, where
OpenCV's projection of the true target puts it, within the detector's bound; the cameras'
frames are where the drones are, looking down.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from foxglove.messages import (
    CameraCalibration,
    CompressedImage,
    FrameTransforms,
    ImageAnnotations,
)
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from swarm.messages.wire import CameraFrameWire, CameraImageWire, TelemetryWire, TruthWire
from swarm.observe.camera_view import (
    LIVE_IMAGE_PERIOD_S,
    RECORDED_IMAGE_PERIOD_S,
    TRANSFORMS_TOPIC,
    ImageSchedule,
    annotations_topic,
    calibration_topic,
    camera_calibration,
    camera_frame_id,
    camera_transforms,
    image_topic,
)
from swarm.observe.live_view import LiveView
from swarm.observe.recording.writer import estimated_recording_bytes, record_reference
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import ScenarioConfig, load_config
from swarm.scenario.overrides import parse_assignment
from swarm.vision.geometry import CAMERA_FROM_WORLD, calibration_for, project_to_pixels
from tests.helpers.foxglove_client import FoxgloveClient
from tests.helpers.scene_tools import _decode
from tests.helpers.waiting import wait_until

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
# The detector's marker centre is within 1 px of the truth (tests/vision/test_render_detect.py
# derives it); a recorded annotation is that point back through the lens.
DETECTION_BOUND_PX = 1.0


def rendered(*assignments: str, duration_s: float = 1.5) -> ScenarioConfig:
    return load_config(CASE1, overrides=[parse_assignment('camera.model="rendered"'),
                                         *map(parse_assignment, assignments)]
                       ).with_duration(duration_s)


@pytest.mark.parametrize(("frame_rate", "period_s", "period_steps"), [
    (None, 0.5, 25), (25.0, 0.5, 26), (10.0, 0.5, 25), (50.0, 0.1, 5), (25.0, 0.1, 6),
    (10.0, 0.01, 5)])
def test_the_schedule_keeps_frames_only_at_least_the_period_apart(
        frame_rate: float | None, period_s: float, period_steps: int) -> None:
    config = rendered(*([] if frame_rate is None else [f"camera.frame_rate_hz={frame_rate}"]))
    schedule = ImageSchedule(config, period_s)
    assert schedule.period_steps == period_steps
    assert schedule.period_steps % config.camera_steps_per_frame == 0  # a frame on each
    assert schedule.period_steps * config.scenario.dt_s >= period_s - 1e-12
    assert schedule.rate_hz == pytest.approx(1.0 / (period_steps * config.scenario.dt_s))
    assert [k for k in range(60) if schedule.wants(k)] == list(range(0, 60, period_steps))
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="image period"):
            ImageSchedule(config, bad)


def test_a_cameras_frame_is_at_its_drone_looking_down_with_x_along_the_worlds() -> None:
    positions = np.array([[1.0, 2.0, 3.5], [np.nan, np.nan, np.nan], [-4.0, 0.5, 2.0]])
    transforms = _decode(FrameTransforms, camera_transforms(positions, 1.25).encode()
                         ).transforms
    assert [t.child_frame_id for t in transforms] == [camera_frame_id(0), camera_frame_id(2)]
    for transform, drone in zip(transforms, positions[[0, 2]], strict=True):
        assert transform.parent_frame_id == "world"
        q = transform.rotation
        rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
        assert np.allclose(rotation, CAMERA_FROM_WORLD.T)  # R_wc: the camera's axes in W
        translation = transform.translation
        assert [translation.x, translation.y, translation.z] == drone.tolist()
        # A point 2 m along the optical axis is 2 m below the drone.
        assert np.allclose(rotation @ [0.0, 0.0, 2.0] + drone, drone - [0.0, 0.0, 2.0])


def test_the_calibration_message_projects_as_the_renderer_does() -> None:
    config = rendered("camera.distortion=[-0.15, 0.03, 0.001, -0.001, 0.0]")
    calibration = calibration_for(config.camera)
    message = _decode(CameraCalibration, camera_calibration(calibration, 3, 0.5).encode())
    assert (message.frame_id, message.width, message.height) == (camera_frame_id(3), 480, 480)
    assert message.distortion_model == "plumb_bob"
    assert message.D == [-0.15, 0.03, 0.001, -0.001, 0.0]
    k = np.array(message.K).reshape(3, 3)
    assert np.array_equal(k, calibration.camera_matrix)
    # A pinhole projects with P = [K | 0] as the renderer's cv2.projectPoints does.
    pinhole = calibration_for(rendered().camera)
    projection = np.array(_decode(CameraCalibration, camera_calibration(pinhole, 0, 0.0)
                                  .encode()).P).reshape(3, 4)
    drone, target = np.array([0.3, -0.2, 4.0]), np.array([1.1, 0.9, 0.0])
    in_camera = CAMERA_FROM_WORLD @ (target - drone)
    projected = projection @ np.append(in_camera, 1.0)
    assert np.allclose(projected[:2] / projected[2],
                       project_to_pixels(target[None], drone, pinhole)[0], atol=1e-9)


def _check_frame(config: ScenarioConfig, record: RunRecord, drone: int, step: int,
                 image: Any, calibration: Any, annotations: Any) -> list[np.ndarray]:
    """One kept frame of ``drone`` as a viewer shows it, against the truth of ``step``; each
    annotation's offset from OpenCV's pixel of the true target."""
    cal = calibration_for(config.camera)
    pixels = cv2.imdecode(np.frombuffer(image.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.format == "jpeg" and image.frame_id == camera_frame_id(drone)
    assert pixels.shape[:2] == (cal.height_px, cal.width_px)
    assert calibration.frame_id == image.frame_id
    assert np.array_equal(np.array(calibration.K).reshape(3, 3), cal.camera_matrix)
    seen = np.flatnonzero(record.detected[step, drone])
    assert len(annotations.circles) == len(annotations.texts) == len(seen)
    offsets = []
    for circle, text in zip(annotations.circles, annotations.texts, strict=True):
        target = int(text.text.removeprefix("T"))
        assert target in seen
        truth = project_to_pixels(record.target_positions_m[step, target][None],
                                  record.drone_positions_m[step, drone], cal)[0]
        shown = np.array([circle.position.x, circle.position.y])
        assert np.linalg.norm(shown - (truth + 0.5)) <= DETECTION_BOUND_PX, (drone, step)
        offsets.append(shown - truth)
    return offsets


def _check_corner_convention(offsets: list[np.ndarray]) -> None:
    """Foxglove's origin is the top-left pixel's corner: on average the annotations sit half
    a pixel right of and below OpenCV's (pixel-centre) coordinates; the detector's own error
    (median 0.11 px, docs/camera.md) averages out."""
    assert len(offsets) >= 10
    assert np.allclose(np.mean(offsets, axis=0), [0.5, 0.5], atol=0.15), np.mean(offsets, 0)


def test_a_recording_holds_each_cameras_images_calibration_detections_and_frame(
        tmp_path: Path) -> None:
    config = rendered()
    record = record_reference(config, 0, tmp_path)
    n, dt_ns = config.swarm.n_drones, round(config.scenario.dt_s * 1e9)
    kept = [k for k in range(config.n_steps)
            if ImageSchedule(config, RECORDED_IMAGE_PERIOD_S).wants(k)]
    assert kept == [0, 25, 50]
    decoders = DecoderFactory()
    offsets: list[np.ndarray] = []
    by_topic: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    with (tmp_path / "run.mcap").open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[decoders])
        schemas = {c.topic: reader.get_summary().schemas[c.schema_id].name
                   for c in reader.get_summary().channels.values()}
        for _schema, channel, message, decoded in reader.iter_decoded_messages(
                topics=[t for t in schemas if t.startswith("camera/") or t == TRANSFORMS_TOPIC]):
            by_topic[channel.topic].append((message.log_time // dt_ns, decoded))
    for i in range(n):
        assert schemas[image_topic(i)] == "foxglove.CompressedImage"
        assert schemas[calibration_topic(i)] == "foxglove.CameraCalibration"
        assert schemas[annotations_topic(i)] == "foxglove.ImageAnnotations"
        for name in (image_topic(i), calibration_topic(i), annotations_topic(i)):
            assert [k for k, _ in by_topic[name]] == kept, name
        for (k, image), (_, cal), (_, notes) in zip(
                by_topic[image_topic(i)], by_topic[calibration_topic(i)],
                by_topic[annotations_topic(i)], strict=True):
            offsets += _check_frame(config, record, i, k, image, cal, notes)
    _check_corner_convention(offsets)
    assert schemas[TRANSFORMS_TOPIC] == "foxglove.FrameTransforms"
    assert [k for k, _ in by_topic[TRANSFORMS_TOPIC]] == list(range(0, config.n_steps, 5))
    for k, frames in by_topic[TRANSFORMS_TOPIC]:
        assert [[t.translation.x, t.translation.y, t.translation.z]
                for t in frames.transforms] == record.drone_positions_m[k].tolist()
    # The disk check before a run counts the images, generously.
    size = (tmp_path / "run.mcap").stat().st_size
    assert size < estimated_recording_bytes(config) - 1_000_000


def test_a_bearing_camera_records_no_camera_topic(tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(1.1)
    record_reference(config, 0, tmp_path)
    with (tmp_path / "run.mcap").open("rb") as handle:
        topics = {c.topic for c in make_reader(handle).get_summary().channels.values()}
    assert not [t for t in topics if t.startswith("camera/") or t == TRANSFORMS_TOPIC]


class _ToLiveView:
    """An in-process run's messages, handed to a live view as the launcher hands them."""

    def __init__(self, view: LiveView) -> None:
        self.view = view

    def put(self, message: object) -> None:
        if isinstance(message, TelemetryWire | TruthWire):
            self.view.put(message)
        elif isinstance(message, CameraImageWire | CameraFrameWire):
            self.view.put_camera(message)


def test_a_viewer_sees_each_cameras_images_and_detections_live() -> None:
    config = rendered(duration_s=1.2)
    n, dt_ns = config.swarm.n_drones, round(config.scenario.dt_s * 1e9)
    schedule = ImageSchedule(config, LIVE_IMAGE_PERIOD_S)
    kept = [k for k in range(config.n_steps) if schedule.wants(k)]
    with LiveView(config, port=0) as view:
        client = FoxgloveClient(view.url)
        client.start()
        topics = {image_topic(i) for i in range(n)} | {TRANSFORMS_TOPIC}
        wait_until(lambda: topics <= {c["topic"] for c in client.channels.values()},
                   timeout_s=20.0, what="the camera topics advertised")
        record: list[RunRecord] = []
        runner = threading.Thread(target=lambda: record.append(
            run_reference(config, 0, sink=_ToLiveView(view))))
        runner.start()
        runner.join(timeout=120)
        wait_until(lambda: all(client.messages[annotations_topic(i)]
                               and client.messages[annotations_topic(i)][-1][0] // dt_ns
                               == kept[-1] for i in range(n)),
                   timeout_s=20.0, what="the last kept frame's annotations")
    client.wait_closed()
    schemas = {c["topic"]: c["schemaName"] for c in client.channels.values()}
    assert schemas[image_topic(0)] == "foxglove.CompressedImage"
    offsets: list[np.ndarray] = []
    for i in range(n):
        received = {}
        for kind, name in ((CompressedImage, image_topic(i)),
                           (CameraCalibration, calibration_topic(i)),
                           (ImageAnnotations, annotations_topic(i))):
            steps = [t // dt_ns for t, _ in client.messages[name]]
            # Subscribed before the run's first frame left: every kept frame, in order (at
            # worst the first ones, sent before the server had the subscription, are missing).
            assert steps == kept[len(kept) - len(steps):] and len(steps) >= len(kept) - 1
            received[name] = {t // dt_ns: _decode(kind, data) for t, data in
                              client.messages[name]}
        for k in received[image_topic(i)]:
            offsets += _check_frame(config, record[0], i, k, received[image_topic(i)][k],
                                    received[calibration_topic(i)][k],
                                    received[annotations_topic(i)][k])
    _check_corner_convention(offsets)
    frames = [(t // dt_ns, _decode(FrameTransforms, data))
              for t, data in client.messages[TRANSFORMS_TOPIC]]
    assert frames and all(len(f.transforms) == n for _, f in frames)
