"""A real camera's seam (swarm.vision.calibration, swarm.vision.capture; issue 45 point 3):
calibration files in OpenCV's format round-trip and bad ones are refused in one line naming
the file; OpenCV's VideoCapture reads a video file of the world's frames, whose detections
are those of the live frames within the video codec's loss."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from swarm.models.camera import CameraParams
from swarm.vision.calibration import read_calibration, write_calibration
from swarm.vision.capture import CaptureError, CaptureSource
from swarm.vision.codec import encode_jpeg
from swarm.vision.detect import MarkerDetector
from swarm.vision.geometry import CalibrationError, calibration_for
from swarm.vision.render import CameraRenderer

LENS = CameraParams(model="rendered", distortion=(-0.1, 0.01, 0.0005, -0.0005, 0.0))


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_a_calibration_file_round_trips(tmp_path: Path, suffix: str) -> None:
    calibration = calibration_for(LENS)
    path = tmp_path / f"camera{suffix}"
    write_calibration(path, calibration)
    back = read_calibration(path)
    assert np.array_equal(back.camera_matrix, calibration.camera_matrix)
    assert np.array_equal(back.distortion, calibration.distortion)
    assert (back.width_px, back.height_px) == (calibration.width_px, calibration.height_px)


@pytest.mark.parametrize(("text", "said"), [
    (None, "no such calibration file"),
    ("this is not yaml: [", "not an OpenCV calibration file"),
    ("%YAML:1.0\n---\nimage_width: 480\nimage_height: 480\n", "no camera_matrix"),
    ("%YAML:1.0\n---\nimage_width: 480\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
     "   rows: 2\n   cols: 2\n   dt: d\n   data: [1., 0., 0., 1.]\n"
     "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
     "   data: [0., 0., 0., 0., 0.]\n", "camera matrix must be 3 x 3"),
    ("%YAML:1.0\n---\nimage_width: 0\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
     "   rows: 3\n   cols: 3\n   dt: d\n   data: [200., 0., 240., 0., 200., 240., 0., 0., 1.]\n"
     "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 3\n   dt: d\n"
     "   data: [0., 0., 0.]\n", "distortion must be 4, 5 or 8"),
])
def test_a_bad_calibration_file_is_one_line_naming_it(tmp_path: Path, text: str | None,
                                                      said: str) -> None:
    path = tmp_path / "camera.yaml"
    if text is not None:
        path.write_text(text)
    with pytest.raises(CalibrationError) as caught:
        read_calibration(path)
    message = str(caught.value)
    assert message.startswith(str(path)) and said in message and "\n" not in message


def test_a_source_opencv_cannot_open_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="cannot open the video source"):
        CaptureSource(str(tmp_path / "missing.avi"))


def test_a_video_file_of_the_worlds_frames_gives_the_live_detections(tmp_path: Path) -> None:
    """Ten rendered frames (a target each, in view), written to an MJPG AVI by OpenCV's
    VideoWriter and read back by VideoCapture in colour: every marker found again, its image
    point within half a pixel of the live one: MJPG re-encodes each frame, which moves the
    refined corners by a few tenths of a pixel (measured: 0.26 px at most)."""
    renderer = CameraRenderer(LENS, 1)
    detector = MarkerDetector(LENS, renderer.calibration, 1)
    rng = np.random.default_rng(3)
    side = renderer.calibration.width_px
    video = tmp_path / "camera.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (side, side))
    assert writer.isOpened()
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
    live = []
    for k in range(10):
        drone = np.array([0.3 * k, -0.2 * k, 3.5])
        target = drone + np.array([0.5 - 0.1 * k, 0.4, -3.5])
        image = cv2.imdecode(np.frombuffer(encode_jpeg(renderer.render(
            drone, target[None, :], rng), 90), np.uint8), cv2.IMREAD_GRAYSCALE)
        live.append(detector.detect(image).detections)
        writer.write(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    source = CaptureSource(str(video))
    gaps: list[float] = []
    try:
        for k, expected in enumerate(live):
            frame = source.read()
            assert frame is not None and frame.shape == (side, side), k
            found = detector.detect(frame).detections
            assert [d.target for d in found] == [d.target for d in expected] == [0], k
            focal = renderer.calibration.camera_matrix[0, 0]
            gap_px = np.abs(found[0].image_point - expected[0].image_point).max() * focal
            gaps.append(gap_px)
        assert source.read() is None and source.frames == 10
    finally:
        source.close()
    assert max(gaps) < 0.5, gaps
