"""One drone's detector process: image in, camera frame out (docs/camera.md, "Where the
detector runs").

It runs beside the drone's agent, as a detector runs on a drone's companion computer: its
own process, so that the agent's control loop neither waits on nor dies with OpenCV. It reads
the drone's images on ``world/image/<i>`` (``CameraImageWire``), finds the markers
(``swarm.vision.detect``) and publishes the same frame with its detections on
``world/camera/<i>`` (``CameraFrameWire``), the key and message of the bearing camera: the
agent does not know which camera it has. With ``[security]`` it speaks with the drone's own
identity (``agent-<i>``), which may read that drone's images and write its frames.

A real camera (``source``): the pixels come from OpenCV's ``VideoCapture`` (a device, a file,
an image sequence, a GStreamer or RTSP URL) with its calibration from a file, in place of the
images' own: each image message that carries a frame takes the source's next frame (its
other fields, the step and the poses, still come from the message). When the source ends, the
frames go out without detections, said once in the log.

Lockstep: every image, in order (the agent waits for the frame of each step). Realtime: the
newest image; any older one still waiting is dropped and counted (a frame late by a detection
is worth less than the next one). What the detector cannot use is counted by reason
(``RejectionCounter``, kind "image") and logged the first time, and the frame goes out with
no detections: the agent's step then goes on without a measurement, as with a target out of
view. The process ends when the world's clock says "done" (exit 0) or "aborted" (exit 1).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from swarm.errors import VigilError
from swarm.messages.wire import CameraImageWire, ClockWire, WireCodec
from swarm.net.keys import Keys
from swarm.net.security import agent_role
from swarm.net.session import (
    TransportError,
    declare_publisher,
    join_router,
    put_stamped,
)
from swarm.net.subscriptions import (
    BlockingReceives,
    DrainedSubscriber,
    RejectionCounter,
    subscribe,
)
from swarm.scenario.config import ScenarioConfig
from swarm.vision.calibration import read_calibration
from swarm.vision.capture import CaptureSource
from swarm.vision.detect import MarkerDetector
from swarm.vision.geometry import calibration_for

IMAGE_BACKLOG = 64  # images waiting in zenoh at most (lockstep: one per step)
ROUTER_RETRY_S = 0.2


def realtime_choice(pending: list[CameraImageWire]) -> tuple[list[CameraImageWire], int, int]:
    """What a realtime detector sends of the images that waited: the newest one that carries
    a frame, alone; (it, the older frames skipped, the image-less steps not sent).

    An image-less message (a step between two frames, ``camera.frame_rate_hz``) has no
    detections to give. Sent, it would hide the frame before it: a realtime agent reads the
    newest camera frame at each tick (``RealtimeExchange``), and measures from the pose that
    frame was taken at, however old. At 10 frames per second in realtime (Case 1, 10 s),
    sending every step let the agents measure with none of the 600 frames (the world, busy
    rendering, sends a frame late and the next step's message right after it; the detector
    also skipped a third of the frames for such a newer message). Without them the agent's
    step has no
    new frame, as between the bearing camera's frames in realtime; its radio neighbours are
    those of the newest frame.
    """
    framed = [image for image in pending if image.image]
    between = len(pending) - len(framed)
    if not framed:
        return [], 0, between
    return framed[-1:], len(framed) - 1, between


class CameraProcessError(VigilError, RuntimeError):
    """The camera process cannot run (no router, a lost session); one line."""


@dataclass(frozen=True)
class CameraOptions:
    config: ScenarioConfig
    drone_id: int
    run_id: str
    connect: tuple[str, ...]
    mode: Literal["lockstep", "realtime"]
    log: Callable[[str], None]
    source: str | None = None  # a VideoCapture source in place of the images' pixels
    calibration_file: Path | None = None  # its calibration (needed with ``source``)


class CameraProcess:
    """Drone ``drone_id``'s detector between the world's images and its agent."""

    def __init__(self, options: CameraOptions) -> None:
        config = options.config
        self.options = options
        self.id = options.drone_id
        self.keys = Keys(options.run_id)
        self.codec = WireCodec(config.swarm.n_drones, len(config.targets),
                               config.state_dimension)
        calibration = (calibration_for(config.camera) if options.calibration_file is None
                       else read_calibration(options.calibration_file))
        self.detector = MarkerDetector(config.camera, calibration, len(config.targets))
        self.capture = None if options.source is None else CaptureSource(options.source)
        self._source_ended = False
        self.rejections = RejectionCounter()
        self.frames = 0  # images turned into camera frames
        self.skipped = 0  # realtime: older images dropped for a newer one
        self.between_frames = 0  # realtime: image-less steps between frames, not sent
        self._pending: list[CameraImageWire] = []
        self._state: str = "waiting"
        self._lock = threading.Lock()
        self.session = self._open_session()
        self._pub_camera = declare_publisher(self.session, self.keys.camera(self.id),
                                             block=True)
        sub = subscribe(self.session, self.keys.image(self.id), self.codec.decode_image,
                        self._on_image, self.rejections, "image", backlog=IMAGE_BACKLOG,
                        max_payload_bytes=self.codec.max_payload_bytes)
        assert isinstance(sub, DrainedSubscriber)
        self._images = sub
        self._waits = BlockingReceives([sub])
        self._clock_sub = subscribe(self.session, self.keys.clock, self.codec.decode_clock,
                                    self._on_clock, self.rejections, "clock")

    def _open_session(self):
        opts = self.options
        try:
            return join_router(opts.connect, opts.config.runtime.start_timeout_s,
                               tls=opts.config.security.identity(agent_role(self.id)),
                               retry_s=ROUTER_RETRY_S)
        except TransportError as err:
            raise CameraProcessError(
                f"camera {self.id}: cannot reach the world's Zenoh router at "
                f"{', '.join(opts.connect)} within {opts.config.runtime.start_timeout_s} s "
                f"({err})") from None

    # -- zenoh's side ---------------------------------------------------------------------

    def _on_image(self, key: str, image: CameraImageWire) -> None:
        if image.drone != self.id:
            self.rejections.reject("image", f"image of drone {image.drone} on {key}")
            return
        self._pending.append(image)  # this process's own thread, in drain/receive_one

    def _on_clock(self, _key: str, clock: ClockWire) -> None:
        if clock.state in ("done", "aborted"):
            with self._lock:
                self._state = clock.state
            self._waits.close()  # whatever the loop waits for is not coming

    # -- the loop -------------------------------------------------------------------------

    def run(self) -> int:
        """Detect until the mission ends; 0 when it ended "done", 1 when "aborted"."""
        opts = self.options
        source = ("the world's images" if self.capture is None
                  else f"{self.capture.source!r} calibrated by {opts.calibration_file}")
        opts.log(f"camera {self.id}: detecting {opts.config.camera.marker_dictionary} "
                 f"markers of {opts.config.camera.marker_size_m:g} m in "
                 f"{self.detector.calibration.width_px} px frames of {source} ({opts.mode})")
        while self._images.receive_one():
            if opts.mode == "realtime":
                self._images.drain()  # anything newer that came meanwhile
            images, self._pending = self._pending, []
            if opts.mode == "realtime":
                images, skipped, between = realtime_choice(images)
                self.skipped += skipped
                self.between_frames += between
            for image in images:
                self._detect_and_publish(image)
        with self._lock:
            state = self._state
        realtime = (f", {self.skipped} images skipped for newer ones, {self.between_frames} "
                    f"steps between frames not sent" if opts.mode == "realtime" else "")
        opts.log(f"camera {self.id}: mission {state}: {self.frames} frames, "
                 f"{self.rejections.total()} rejected inputs{realtime}")
        for line in self.rejections.lines():
            opts.log(f"camera {self.id}: {line}")
        return 0 if state == "done" else 1

    def _detect_and_publish(self, image: CameraImageWire) -> None:
        found = None
        if image.image and self.capture is None:
            found = self.detector.detect_encoded(image.image)
        elif image.image and self.capture is not None and not self._source_ended:
            pixels = self.capture.read()
            if pixels is None:
                self._source_ended = True
                self.options.log(f"camera {self.id}: step {image.step}: the source "
                                 f"{self.capture.source!r} ended after {self.capture.frames} "
                                 f"frames; frames go out without detections")
            else:
                found = self.detector.detect(pixels)
        if found is not None:
            for reason, count in found.rejected.items():
                if not self.rejections.snapshot().get("image", {}).get("rules", {}).get(reason):
                    self.options.log(f"camera {self.id}: step {image.step}: {reason} "
                                     f"(counted; further ones only in the summary)")
                for _ in range(count):
                    self.rejections.reject("image", f"step {image.step}: {reason}", reason)
        frame = image.frame([] if found is None else found.detections)
        put_stamped(self.session, self._pub_camera, self.codec.encode(frame))
        self.frames += 1

    def close(self) -> None:
        if self.capture is not None:
            self.capture.close()
        self._waits.close()
        self._images.undeclare()
        self.session.close()
