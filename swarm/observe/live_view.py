"""The running swarm, live in Foxglove: a WebSocket server of Foxglove's own SDK.

``LiveView(config, host, port)`` serves, on Foxglove's WebSocket protocol (open
``ws://HOST:PORT`` in Foxglove or Lichtblick):

* ``scene``: the 3D scene (``swarm.observe.scene``: ``foxglove.SceneUpdate``, 10 Hz of sim
  time), the same one every recording holds;
* ``log``: ``foxglove.Log`` lines when a drone's warned counters rise (``LogBook``);
* ``drone/<i>/plot`` (JSON): per drone, at the scene's rate, what a Plot panel shows —
  ``lambda_margin`` (λ̄ − ε per target), ``weights``, ``slacks`` and ``speed_m_s`` (‖u‖);

stamped in sim time (ns since the mission started), which the server also broadcasts as its
clock. It is fed like any observer, by ``put`` with the telemetry and truth messages the
launcher (or the standalone watcher) already receives, so the swarm publishes nothing more
for it. ``put`` only enqueues; a thread of its own builds and sends, so a slow viewer never
holds up a Zenoh callback (the SDK drops the oldest messages for a client that falls
behind). ``close`` stops the thread and the server.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Final

import foxglove
from foxglove import Capability
from foxglove.channels import LogChannel, SceneUpdateChannel

from swarm.errors import VigilError
from swarm.messages.wire import TelemetryWire, TruthWire
from swarm.observe.scene import (
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
_STOP: Final = object()


class LiveViewError(VigilError, RuntimeError):
    """The live view cannot be served (e.g. its port is taken)."""


class LiveView:
    """A Foxglove WebSocket server of the running swarm (see the module docstring)."""

    def __init__(self, config: ScenarioConfig, host: str = DEFAULT_HOST,
                 port: int = DEFAULT_PORT) -> None:
        self.config, self.host = config, host
        self._dt_ns = round(config.scenario.dt_s * 1e9)
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=SERVER_NAME, host=host, port=port, context=self._context,
                capabilities=[Capability.Time])
        except Exception as err:  # the SDK raises its own error types for a taken port
            raise LiveViewError(f"cannot serve the Foxglove live view on {host}:{port}: "
                                f"{err}") from None
        self._scene = SceneUpdateChannel(SCENE_TOPIC, context=self._context)
        self._log = LogChannel(LOG_TOPIC, context=self._context)
        self._log_book = LogBook()
        schema = plot_schema(len(config.targets))
        self._plots = [foxglove.Channel(plot_topic(i), schema=schema, context=self._context)
                       for i in range(config.swarm.n_drones)]
        self._assembler = SceneAssembler(config, self._send)
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="vigil-live-view", daemon=True)
        self._closed = False
        self.sent = 0
        self._thread.start()

    @property
    def port(self) -> int:
        return int(self._server.port)

    @property
    def url(self) -> str:
        """Where Foxglove connects (Open connection → Foxglove WebSocket)."""
        return f"ws://{self.host}:{self.port}"

    def put(self, message: TelemetryWire | TruthWire) -> None:
        """Hand over a telemetry or truth message (any thread; returns at once). Only the
        scene steps' messages are queued: waking the view's thread for the other four in
        five cost the launcher 0.6 % of a core more at N = 6 (3.1 against 2.5 %,
        ``benchmarks/live_view_cost.py``, two runs each way)."""
        if not self._closed and self._assembler.wants(message.step):
            self._queue.put(message)

    def _run(self) -> None:
        while (message := self._queue.get()) is not _STOP:
            if isinstance(message, TelemetryWire):
                self._assembler.on_telemetry(message)
            elif isinstance(message, TruthWire):
                self._assembler.on_truth(message)

    def _send(self, state: SceneState) -> None:
        stamp = state.step * self._dt_ns
        self._server.broadcast_time(stamp)
        self._scene.log(scene_update(self.config, state), log_time=stamp)
        for i, channel in enumerate(self._plots):
            channel.log(plot_values(state, i), log_time=stamp)
        for line in self._log_book.lines(state):
            self._log.log(line, log_time=stamp)
        self.sent += 1

    def close(self) -> None:
        """Stop building and serving; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(_STOP)
        self._thread.join(timeout=5.0)
        self._server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
