"""A real camera's frames through OpenCV's ``VideoCapture``: a device (``0``, ``/dev/video0``),
a video file, an image sequence (``frames/frame_%05d.png``), a GStreamer pipeline or an RTSP
URL, whatever the OpenCV build reads. The seam where a camera replaces the world's rendered
images (``swarm-camera --source``, docs/camera.md, "A real camera")."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from swarm.errors import VigilError


class CaptureError(VigilError, RuntimeError):
    """A source OpenCV cannot open; one line."""


class CaptureSource:
    """Frames of one source, greyscale, in order; ``read()`` is None at its end."""

    def __init__(self, source: str) -> None:
        self.source = source
        target: int | str = int(source) if source.isdigit() else source
        self._capture = cv2.VideoCapture(target)
        if not self._capture.isOpened():
            raise CaptureError(f"OpenCV cannot open the video source {source!r} (a device "
                               f"number, a file, an image pattern such as frame_%05d.png, a "
                               f"GStreamer pipeline or an RTSP URL)")
        self.frames = 0

    def read(self) -> NDArray[np.uint8] | None:
        """The next frame (H, W) uint8, None when the source has ended."""
        ok, frame = self._capture.read()
        if not ok or frame is None:
            return None
        self.frames += 1
        if frame.ndim == 3:
            frame = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        return np.asarray(frame, dtype=np.uint8)

    def close(self) -> None:
        self._capture.release()
