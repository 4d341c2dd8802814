"""A drone's detector process (swarm.camera, issue 45 points 2-3): a real ``swarm-camera``
process joined to a Zenoh router of this test; images put on its drone's image key come back
as camera frames on the camera key, with the detector's detections, every other field as the
image carried it. What it cannot use is counted by reason and said in its log; an image of
another drone is refused; it ends with the world's clock. With ``--source`` and
``--calibration`` it takes the pixels from OpenCV's VideoCapture instead: a replay of the
frames the world rendered gives the very detections the live frames gave."""

from __future__ import annotations

import contextlib
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from swarm.camera.process import realtime_choice
from swarm.messages.wire import (
    CameraFrameWire,
    CameraImageWire,
    ClockWire,
    WireCodec,
)
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.scenario.config import load_config, write_resolved_config
from swarm.scenario.overrides import parse_assignment
from swarm.scenario.setup import initial_drone_positions
from swarm.scenario.world_step import Scene
from swarm.vision.calibration import write_calibration
from swarm.vision.codec import encode_jpeg
from swarm.vision.detect import MarkerDetector
from swarm.vision.render import CameraRenderer
from tests.helpers.process_tools import console_script, free_tcp_port

ROOT = Path(__file__).resolve().parents[2]
RUN_ID = "camtest"
DRONE = 1


@pytest.fixture
def rendered(tmp_path: Path):
    config = load_config(ROOT / "configs" / "case1.toml",
                         overrides=[parse_assignment('camera.model="rendered"')])
    return config, write_resolved_config(config, tmp_path / "config.json")


@dataclass
class Camera:
    """A swarm-camera process on this test's router, and what came back from it."""

    router: Any
    process: subprocess.Popen
    log: Path
    keys: Keys
    codec: WireCodec
    frames: list[CameraFrameWire]
    arrived: threading.Condition

    def put(self, image: CameraImageWire | bytes) -> None:
        self.router.put(self.keys.image(DRONE), image if isinstance(image, bytes)
                        else self.codec.encode(image))

    def wait_frames(self, count: int, timeout_s: float = 20.0) -> None:
        with self.arrived:
            assert self.arrived.wait_for(lambda: len(self.frames) >= count, timeout_s), (
                self.frames, self.log.read_text())

    def until_subscribed(self, first: CameraImageWire) -> None:
        """Until the process has subscribed puts go nowhere: put ``first`` again until its
        frame comes back."""
        deadline = time.monotonic() + 30.0
        while not self.frames:
            assert self.process.poll() is None, self.log.read_text()
            assert time.monotonic() < deadline, self.log.read_text()
            self.put(first)
            with self.arrived:
                self.arrived.wait_for(lambda: bool(self.frames), 0.5)

    def end(self) -> int:
        self.router.put(self.keys.clock, self.codec.encode(
            ClockWire(step=0, time_s=0.0, state="done", mode="lockstep")))
        return self.process.wait(timeout=20)


@contextlib.contextmanager
def camera_process(config, path: Path, tmp_path: Path, *args: str) -> Iterator[Camera]:
    keys = Keys(RUN_ID)
    codec = WireCodec(config.swarm.n_drones, len(config.targets), config.state_dimension)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    frames: list[CameraFrameWire] = []
    arrived = threading.Condition()

    def on_frame(sample) -> None:
        with arrived:
            frames.append(codec.decode_camera(sample.payload.to_bytes()))
            arrived.notify_all()

    subscriber = router.declare_subscriber(keys.camera(DRONE), on_frame)
    log = tmp_path / "camera.log"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [*console_script("swarm-camera", "swarm.camera.cli"), "--id", str(DRONE),
             "--config", str(path), "--connect", endpoint, "--run-id", RUN_ID, *args],
            stdout=out, stderr=subprocess.STDOUT)
    try:
        yield Camera(router, process, log, keys, codec, frames, arrived)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        subscriber.undeclare()
        router.close()


def image_message(step: int, image: bytes, positions=None) -> CameraImageWire:
    frame = CameraFrameWire.build(DRONE, step, 0.02 * step, 20 * step, [],
                                  drone_positions=positions)
    return CameraImageWire.of_frame(frame, image)


def same_detections(ours: CameraFrameWire, theirs: list) -> bool:
    return [(d.target, d.x, d.y) for d in ours.detections] == [
        (d.target, *map(float, d.image_point)) for d in theirs]


def test_images_come_back_as_the_detectors_frames_and_bad_ones_are_counted(
        rendered, tmp_path: Path) -> None:
    config, path = rendered
    renderer = CameraRenderer(config.camera, len(config.targets))
    positions = initial_drone_positions(config, 0)
    targets = np.array([t.build().position(0.0) for t in config.targets])
    image = encode_jpeg(renderer.render(positions[DRONE], targets, np.random.default_rng(0)),
                        90)
    expected = MarkerDetector(config.camera, renderer.calibration,
                              len(config.targets)).detect_encoded(image).detections
    assert expected  # drone 1 sees a target at the start of Case 1 seed 0
    with camera_process(config, path, tmp_path) as camera:
        camera.until_subscribed(image_message(0, image, positions))
        first = camera.frames[0]
        assert same_detections(first, expected)
        assert np.array_equal(first.drone_position_array(), positions)
        seen = len(camera.frames)
        camera.put(image_message(1, b"\xff\xd8 corrupt"))
        camera.put(image_message(2, b""))
        # Another drone's image on this drone's key: refused, no frame.
        camera.put(CameraImageWire.of_frame(
            CameraFrameWire.build(DRONE + 1, 3, 0.06, 60, []), image))
        camera.put(b"not a message")
        camera.put(image_message(4, image))
        camera.wait_frames(seen + 3)
        frames = camera.frames
        assert [f.step for f in frames[seen:]] == [1, 2, 4]
        assert [f.detections for f in frames[seen:seen + 2]] == [(), ()]
        assert frames[-1].detections == first.detections
        assert camera.end() == 0, camera.log.read_text()
        text = camera.log.read_text()
    assert "step 1: undecodable image (counted" in text, text
    assert "mission done:" in text and "3 rejected inputs" in text, text
    # by rule: the wrong drone's image ("source"), the bytes that are no message
    # ("malformed"), the frame that does not decode
    assert "image: 3 rejected, 0 unexpected (malformed 1, source 1, undecodable image 1" in text


def test_a_replayed_video_of_the_worlds_frames_gives_the_live_detections(
        rendered, tmp_path: Path) -> None:
    """Drone 1's frames of 12 steps of Case 1 (the drones drifting so that the view
    changes), detected live by the scene, written as an image sequence (the decoded frames,
    losslessly) with the calibration; swarm-camera --source on them, fed the same image
    messages: the same detections, bit for bit. One message more than there are frames:
    the source's end is said, and that frame goes out without detections."""
    config, path = rendered
    scene = Scene(config, seed=0)
    start = initial_drone_positions(config, 0)
    frames_dir = tmp_path / "frames"
    frames_dir.mkdir()
    live, images = [], []
    for k in range(12):
        view = scene.at(k, start + np.array([0.08 * k, -0.05 * k, 0.0]))
        assert view.images is not None
        images.append(view.images[DRONE])
        live.append(view.detections[DRONE])
        decoded = cv2.imdecode(np.frombuffer(view.images[DRONE], np.uint8),
                               cv2.IMREAD_GRAYSCALE)
        assert cv2.imwrite(str(frames_dir / f"frame_{k:05d}.png"), decoded)
    assert sum(map(len, live)) >= 6  # targets in view in most frames
    write_calibration(tmp_path / "calibration.yaml", scene.renderer.calibration)
    with camera_process(config, path, tmp_path, "--source",
                        str(frames_dir / "frame_%05d.png"), "--calibration",
                        str(tmp_path / "calibration.yaml")) as camera:
        camera.until_subscribed(image_message(0, b""))  # no frame: takes none from the source
        seen = len(camera.frames)
        for k, image in enumerate(images):
            camera.put(image_message(k + 1, image))
        camera.put(image_message(len(images) + 1, images[0]))
        camera.wait_frames(seen + len(images) + 1)
        replayed = camera.frames[seen:]
        assert [f.step for f in replayed] == list(range(1, len(images) + 2))
        for k, detections in enumerate(live):
            assert same_detections(replayed[k], detections), k
        assert replayed[-1].detections == ()
        assert camera.end() == 0
        text = camera.log.read_text()
    assert "frame_%05d.png" in text and "calibrated by" in text, text
    assert f"the source '{frames_dir / 'frame_%05d.png'}' ended after 12 frames" in text, text


def test_a_realtime_detector_sends_the_newest_frame_and_never_an_image_less_step_after_it(
) -> None:
    """The images that waited, in order: the newest that carries a frame is detected, alone;
    older frames are skipped for it; image-less steps (between frames) are never sent, since
    sent after a frame they would hide it from the agent (which reads the newest)."""
    image, empty = b"\xff\xd8 a frame", b""
    waited = [image_message(k, data) for k, data in
              ((10, image), (11, empty), (12, empty), (15, image), (16, empty))]
    chosen, skipped, between = realtime_choice(waited)
    assert [m.step for m in chosen] == [15] and (skipped, between) == (1, 3)
    assert realtime_choice(waited[1:3]) == ([], 0, 2)
    assert realtime_choice([]) == ([], 0, 0)
    chosen, skipped, between = realtime_choice(waited[:1])
    assert [m.step for m in chosen] == [10] and (skipped, between) == (0, 0)
