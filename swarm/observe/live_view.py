"""The running swarm, live in Foxglove: a WebSocket server of Foxglove's own SDK.

``LiveView(config, host, port)`` serves, on Foxglove's WebSocket protocol (open
``ws://HOST:PORT`` in Foxglove or Lichtblick):

* ``scene``: the 3D scene (``swarm.observe.foxglove_scene``: ``foxglove.SceneUpdate``, 10 Hz of sim
  time), the same one every recording holds;
* ``log``: ``foxglove.Log`` lines when a drone's warned counters rise (``LogBook``);
* ``drone/<i>/plot`` (JSON): per drone, at the scene's rate, what a Plot panel shows —
  ``lambda_margin`` (λ̄ − ε per target), ``weights``, ``slacks`` and ``speed_m_s`` (‖u‖);
* with rendered cameras, each drone's images, calibration and detections every
  ``LIVE_IMAGE_PERIOD_S`` and the cameras' frames (``swarm.observe.camera_view``);

stamped in sim time (ns since the mission started), which the server also broadcasts as its
clock. It is fed like any observer, by ``put`` with the telemetry and truth messages the
launcher (or the standalone watcher) already receives, so the swarm publishes nothing more
for it. ``put`` only enqueues; a thread of its own builds and sends, so a slow viewer never
holds up a Zenoh callback (the SDK drops the oldest messages for a client that falls
behind). ``close`` stops the thread and the server.

The SDK's server speaks the WebSocket subprotocol ``foxglove.sdk.v1`` only (``SUBPROTOCOL``;
foxglove-sdk 0.30 has no option for another): a viewer offering only the older
``foxglove.websocket.v1`` (Lichtblick before 1.22.0, tools on ``@foxglove/ws-protocol``) gets
HTTP 400, and the SDK logs each such connection through Python logging (``Dropping client
ADDR: handshake failed`` on ``foxglove.websocket.server``), which a viewer that retries
(Lichtblick 1.21: every 3 s) turns into a flood. A filter on that logger turns them into one
line per client host and view (``VIEWERS`` says which viewers connect), counts the rest
(``refused``) and lets every other SDK record through. ``check_address`` tells, before
anything starts, whether the port can be served.
"""

from __future__ import annotations

import errno
import logging
import queue
import re
import socket
import sys
import threading
from collections.abc import Callable
from typing import Any, Final

import foxglove
from foxglove import Capability
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    FrameTransformsChannel,
    ImageAnnotationsChannel,
    LogChannel,
    SceneUpdateChannel,
)
from foxglove.messages import CameraCalibration, CompressedImage, FrameTransforms, ImageAnnotations

from swarm.errors import UsageError, VigilError
from swarm.messages.wire import CameraFrameWire, CameraImageWire, TelemetryWire, TruthWire
from swarm.observe.camera_view import LIVE_IMAGE_PERIOD_S, CameraMessage, CameraView
from swarm.observe.foxglove_scene import (
    LOG_TOPIC,
    SCENE_TOPIC,
    LogBook,
    SceneAssembler,
    SceneState,
    plot_schema,
    plot_topic,
    plot_values,
    scene_update,
)
from swarm.scenario.config import ScenarioConfig

DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8765  # Foxglove's default for its WebSocket connection
SERVER_NAME: Final = "vigil"
SUBPROTOCOL: Final = "foxglove.sdk.v1"  # the only one foxglove-sdk's server accepts
# The viewers that offer it, and those that do not (Lichtblick added it in 1.22.0, 2025-12-17).
VIEWERS: Final = "Lichtblick 1.22.0 or later, or a current Foxglove app"
OLD_VIEWERS: Final = ("older Lichtblick and tools on @foxglove/ws-protocol offer only "
                      "foxglove.websocket.v1")
_STOP: Final = object()
# The SDK's typed channel of each camera message (swarm.observe.camera_view).
_CAMERA_CHANNELS: Final[dict[type, Any]] = {
    CompressedImage: CompressedImageChannel, CameraCalibration: CameraCalibrationChannel,
    ImageAnnotations: ImageAnnotationsChannel, FrameTransforms: FrameTransformsChannel}
# Where and how foxglove-sdk 0.30 logs a connection whose WebSocket handshake it refused.
_SDK_SERVER_LOGGER: Final = "foxglove.websocket.server"
_HANDSHAKE_FAILED: Final = re.compile(r"Dropping client (?P<host>.+):\d+: handshake failed$")


class LiveViewError(VigilError, RuntimeError):
    """The live view cannot be served (e.g. its port is taken)."""


class LiveViewAddressError(LiveViewError, UsageError):
    """``--foxglove HOST:PORT`` cannot be served: found before the swarm starts."""


def check_address(host: str, port: int) -> None:
    """``LiveViewAddressError`` (one line naming the address) when a server cannot listen on
    ``host:port`` now: taken by another program or not an address of this machine. The probe
    binds as the SDK's listener does (tokio, with SO_REUSEADDR), so a port a closed server left
    in TIME_WAIT counts as free, as it is for the SDK. Another program may still take the port
    between this check and the server's start; ``LiveView`` then raises ``LiveViewError``."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
            probe.listen(1)
        except OSError as err:
            why = ("the address is in use" if err.errno == errno.EADDRINUSE
                   else err.strerror or str(err))
            raise LiveViewAddressError(f"--foxglove {host}:{port}: cannot serve the live view "
                                       f"there: {why}") from None


class _Refusals(logging.Filter):
    """On the SDK server's logger: each refused handshake goes to every open view's
    ``_refused`` instead of the log (the record says which client, not which server); every
    other record passes."""

    def __init__(self) -> None:
        super().__init__()
        self.views: list[LiveView] = []
        self.lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        match = _HANDSHAKE_FAILED.match(record.getMessage())
        if match is None:
            return True
        with self.lock:
            views = list(self.views)
        for view in views:
            view._refused(match["host"])
        return not views


_REFUSALS: Final = _Refusals()


def _print_to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class LiveView:
    """A Foxglove WebSocket server of the running swarm (see the module docstring)."""

    def __init__(self, config: ScenarioConfig, host: str = DEFAULT_HOST,
                 port: int = DEFAULT_PORT, *,
                 log: Callable[[str], None] = _print_to_stderr) -> None:
        """``log`` gets one line for the first refused connection of each client host (default:
        stderr)."""
        self.config, self.host = config, host
        self._log_line = log
        self._refused_hosts: dict[str, int] = {}  # client host → connections refused
        self._refused_lock = threading.Lock()
        self._dt_ns = round(config.scenario.dt_s * 1e9)
        self._context = foxglove.Context()
        sdk_logger = logging.getLogger(_SDK_SERVER_LOGGER)
        if _REFUSALS not in sdk_logger.filters:
            sdk_logger.addFilter(_REFUSALS)
        try:
            self._server = foxglove.start_server(
                name=SERVER_NAME, host=host, port=port, context=self._context,
                capabilities=[Capability.Time])
        except Exception as err:  # the SDK raises its own error types for a taken port
            raise LiveViewError(f"cannot serve the Foxglove live view on {host}:{port}: "
                                f"{err}") from None
        self._port = int(self._server.port)  # the SDK says 0 once stopped
        with _REFUSALS.lock:
            _REFUSALS.views.append(self)
        self._scene = SceneUpdateChannel(SCENE_TOPIC, context=self._context)
        self._log = LogChannel(LOG_TOPIC, context=self._context)
        self._log_book = LogBook()
        schema = plot_schema(len(config.targets))
        self._plots = [foxglove.Channel(plot_topic(i), schema=schema, context=self._context)
                       for i in range(config.swarm.n_drones)]
        self._assembler = SceneAssembler(config, self._send)
        self._camera = (CameraView(config, LIVE_IMAGE_PERIOD_S) if config.camera.rendered
                        else None)
        self._camera_channels: dict[str, Any] = {
            name: _CAMERA_CHANNELS[kind](name, context=self._context)
            for name, kind in (self._camera.topics() if self._camera is not None else [])}
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="vigil-live-view", daemon=True)
        self._closed = False
        self.sent = 0
        self._thread.start()

    @property
    def port(self) -> int:
        return self._port

    @property
    def url(self) -> str:
        """Where Foxglove connects (Open connection → Foxglove WebSocket)."""
        return f"ws://{self.host}:{self.port}"

    @property
    def refused(self) -> int:
        """Connections refused at the handshake while this view was open (all hosts)."""
        with self._refused_lock:
            return sum(self._refused_hosts.values())

    def _refused(self, host: str) -> None:
        """A connection from ``host`` was refused (the SDK's server thread): the first from a
        host is said, the others counted."""
        with self._refused_lock:
            count = self._refused_hosts.get(host, 0)
            self._refused_hosts[host] = count + 1
        if count == 0:
            self._log_line(
                f"live view {self.url}: refused a viewer at {host}, its WebSocket handshake "
                f"failed (this server speaks {SUBPROTOCOL} only: use {VIEWERS}; {OLD_VIEWERS}); "
                f"further attempts from {host} are not shown")

    def put(self, message: TelemetryWire | TruthWire) -> None:
        """Hand over a telemetry or truth message (any thread; returns at once). Only the
        scene steps' messages are queued: waking the view's thread for the other four in
        five cost the launcher 0.6 % of a core more at N = 6 (3.1 against 2.5 %,
        ``benchmarks/live_view_cost.py``, two runs each way)."""
        if not self._closed and self._assembler.wants(message.step):
            self._queue.put(message)

    def put_camera(self, message: CameraImageWire | CameraFrameWire) -> None:
        """Hand over a rendered camera's image or its detector's frame (any thread; returns at
        once); only the frames the view shows are queued."""
        if not self._closed and self._camera is not None and self._camera.wants(message.step):
            self._queue.put(message)

    def _run(self) -> None:
        while (message := self._queue.get()) is not _STOP:
            if isinstance(message, TelemetryWire):
                self._assembler.on_telemetry(message)
            elif isinstance(message, TruthWire):
                self._assembler.on_truth(message)
            elif self._camera is not None:
                self._log_camera(message.step, self._camera.of_image(message)
                                 if isinstance(message, CameraImageWire)
                                 else self._camera.of_frame(message))

    def _log_camera(self, step: int, items: list[tuple[str, CameraMessage]]) -> None:
        for name, item in items:
            channel = self._camera_channels.get(name)
            if channel is not None:  # a drone outside the config: the codec refuses it
                channel.log(item, log_time=step * self._dt_ns)

    def _send(self, state: SceneState) -> None:
        stamp = state.step * self._dt_ns
        self._server.broadcast_time(stamp)
        self._scene.log(scene_update(self.config, state), log_time=stamp)
        for i, channel in enumerate(self._plots):
            channel.log(plot_values(state, i), log_time=stamp)
        for line in self._log_book.lines(state):
            self._log.log(line, log_time=stamp)
        if self._camera is not None:
            self._log_camera(state.step, self._camera.of_scene(state.drones_m, state.time_s))
        self.sent += 1

    def close(self) -> None:
        """Stop building and serving; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join(timeout=5.0)
        self._server.stop()
        with _REFUSALS.lock:
            _REFUSALS.views.remove(self)

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
