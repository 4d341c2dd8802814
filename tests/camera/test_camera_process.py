"""A drone's detector process (swarm.camera, issue 45 point 2): a real ``swarm-camera``
process joined to a Zenoh router of this test; images put on its drone's image key come back
as camera frames on the camera key, with the detector's detections, every other field as
the image carried it. What it cannot use is counted by reason and said in its log; an image
of another drone is refused; it ends with the world's clock."""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

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


def test_images_come_back_as_the_detectors_frames_and_bad_ones_are_counted(
        rendered, tmp_path: Path) -> None:
    config, path = rendered
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

    def wait_frames(count: int, timeout_s: float = 20.0) -> None:
        with arrived:
            assert arrived.wait_for(lambda: len(frames) >= count, timeout_s), frames

    subscriber = router.declare_subscriber(keys.camera(DRONE), on_frame)
    log = tmp_path / "camera.log"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [*console_script("swarm-camera", "swarm.camera.cli"), "--id", str(DRONE),
             "--config", str(path), "--connect", endpoint, "--run-id", RUN_ID],
            stdout=out, stderr=subprocess.STDOUT)
    try:
        renderer = CameraRenderer(config.camera, len(config.targets))
        positions = initial_drone_positions(config, 0)
        targets = np.array([t.build().position(0.0) for t in config.targets])
        image = encode_jpeg(renderer.render(positions[DRONE], targets,
                                            np.random.default_rng(0)), 90)
        expected = MarkerDetector(config.camera, renderer.calibration,
                                  len(config.targets)).detect_encoded(image).detections
        assert expected  # drone 1 sees a target at the start of Case 1 seed 0
        frame = CameraFrameWire.build(DRONE, 0, 0.0, 0, [], drone_positions=positions)
        good = codec.encode(CameraImageWire.of_frame(frame, image))
        # Until the process has subscribed, puts go nowhere: put the first image again
        # until its frame comes back.
        deadline = time.monotonic() + 30.0
        while not frames:
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            router.put(keys.image(DRONE), good)
            with arrived:
                arrived.wait_for(lambda: bool(frames), 0.5)
        first = frames[0]
        assert [d.target for d in first.detections] == [d.target for d in expected]
        for ours, theirs in zip(first.detections, expected, strict=True):
            assert (ours.x, ours.y) == tuple(theirs.image_point)
        assert first.drone_position_array() is not None
        assert np.array_equal(first.drone_position_array(), positions)
        seen = len(frames)
        for step, data in ((1, b"\xff\xd8 corrupt"), (2, b"")):
            router.put(keys.image(DRONE), codec.encode(CameraImageWire.of_frame(
                CameraFrameWire.build(DRONE, step, 0.02 * step, 20 * step, []), data)))
        # Another drone's image on this drone's key: refused, no frame.
        router.put(keys.image(DRONE), codec.encode(CameraImageWire.of_frame(
            CameraFrameWire.build(DRONE + 1, 3, 0.06, 60, []), image)))
        router.put(keys.image(DRONE), b"not a message")
        router.put(keys.image(DRONE), codec.encode(CameraImageWire.of_frame(
            CameraFrameWire.build(DRONE, 4, 0.08, 80, []), image)))
        wait_frames(seen + 3)
        assert [f.step for f in frames[seen:]] == [1, 2, 4]
        assert [f.detections for f in frames[seen:seen + 2]] == [(), ()]
        assert frames[-1].detections == first.detections
        router.put(keys.clock, codec.encode(ClockWire(step=5, time_s=0.1, state="done",
                                                      mode="lockstep")))
        assert process.wait(timeout=20) == 0, log.read_text()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        subscriber.undeclare()
        router.close()
    text = log.read_text()
    assert "step 1: undecodable image (counted" in text, text
    assert "mission done:" in text and "3 rejected inputs" in text, text
    # by rule: the wrong drone's image ("source"), the bytes that are no message
    # ("malformed"), the frame that does not decode
    assert "image: 3 rejected, 0 unexpected (malformed 1, source 1, undecodable image 1" in text
