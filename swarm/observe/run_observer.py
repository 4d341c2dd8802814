"""One observer of a running swarm: a Zenoh client of the world's router that builds the run's
record (``swarm.observe.collector``), records it to MCAP (``swarm.observe.recording``), serves
the live 3D view (``swarm.observe.live_view``) and hands each telemetry message to listeners
(the dashboard), from one decode.

``launch-swarm``'s ``SwarmLauncher`` is one (it also starts and supervises the processes);
``swarm-observe`` (``swarm.observe.observe_cli``) is one for a swarm started elsewhere. Both
end with the same summary: ``print_process_counters``, then ``print_summary`` (the tables and
verdict of ``swarm.observe.report``, as ``swarm-report`` prints them).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from swarm.messages.wire import (
    BeaconWire,
    CameraFrameWire,
    CameraImageWire,
    ClockWire,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
)
from swarm.net.keys import Keys
from swarm.net.observer import FEED_BACKLOG, ObserverFeed, join_router, subscribe_observer
from swarm.net.security import OBSERVER_ROLE
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import RejectionCounter
from swarm.observe.collector import TelemetryCollector
from swarm.observe.live_view import LiveView
from swarm.observe.recording.schema import RecordingMetadata
from swarm.observe.recording.writer import Recorder
from swarm.observe.report import build_report, render_report
from swarm.runs.record import RunRecord
from swarm.scenario.config import ScenarioConfig

# Extra consumers of the telemetry stream (e.g. the live dashboard), called on the feed's
# thread with each decoded message after the collector has stored it.
TelemetryListener = Callable[[TelemetryWire], None]


class RunObserver:
    """The run ``run_id`` as seen through the world's router: its clock (``clock``, source 0),
    its record (``collector``), optionally its recording and live view.

    Order of use: ``open_recorder`` / ``open_live_view`` (optional), ``connect``,
    ``subscribe``; then ``stop_observing`` on every way out (idempotent). ``log`` gets each
    line worth telling the user, prefixed with ``prog``.
    """

    def __init__(self, config: ScenarioConfig, run_id: str, *, prog: str,
                 log: Callable[[str], None] = print) -> None:
        self.config = config
        self.run_id = run_id
        self.prog = prog
        self.log = log
        self.keys = Keys(run_id)
        self.codec = config.wire_codec()
        self.collector = TelemetryCollector(config)
        self.rejections = RejectionCounter()
        self.clock: LatestValues[ClockWire] = LatestValues()
        self._state_changed = threading.Event()  # the world's clock changed state
        self.session: Any = None  # a zenoh.Session (opened through swarm.net only)
        self._feed: ObserverFeed | None = None
        self.recorder: Recorder | None = None
        self.live_view: LiveView | None = None
        self.recording_problem: str | None = None  # the recording is incomplete, and why
        self.telemetry_listeners: tuple[TelemetryListener, ...] = ()

    # -- before connecting ---------------------------------------------------------------------

    def open_recorder(self, directory: Path, metadata: RecordingMetadata, *,
                      autopilots: bool = False) -> None:
        """Record to ``directory/run.mcap`` from now on; ``RecordingError`` if it cannot."""
        self.recorder = Recorder(directory, metadata, autopilots=autopilots)
        self.log(f"{self.prog}: recording to {self.recorder.path}")

    def open_live_view(self, address: tuple[str, int]) -> None:
        """Serve the live 3D view at ``address``; ``LiveViewError`` if it cannot."""
        self.live_view = LiveView(self.config, *address)
        self.log(f"{self.prog}: live 3D view for Foxglove at {self.live_view.url} "
                 f"(Open connection → Foxglove WebSocket)")

    # -- zenoh ---------------------------------------------------------------------------------

    def connect(self, endpoints: Sequence[str], timeout_s: float, *,
                before_each_try: Callable[[], None] = lambda: None,
                pause: Callable[[float], Any] = time.sleep) -> None:
        """A client session on the world's router, tried until ``timeout_s`` has passed (the
        world may still be starting; ``join_router``); then ``TransportError``."""
        self.session = join_router(endpoints, timeout_s,
                                   tls=self.config.security.identity(OBSERVER_ROLE),
                                   before_each_try=before_each_try, pause=pause)

    def subscribe(self) -> None:
        """Telemetry, truth and clock (and, when recording, beacons and camera frames; with
        rendered cameras and a recording or a live view, the images and camera frames), taken
        in batches by one thread (``ObserverFeed``): nothing received is dropped."""
        assert self.session is not None, "connect first"
        recording = self.recorder is not None
        cameras = self.config.camera.rendered and (recording or self.live_view is not None)
        self._feed = ObserverFeed(subscribe_observer(
            self.session, self.keys, self.codec, self.rejections,
            on_telemetry=self._on_telemetry, on_truth=self._on_truth, on_clock=self._on_clock,
            on_beacon=self._record if recording else None,
            on_camera=self._on_camera if recording or cameras else None,
            on_image=self._on_camera if cameras else None, backlog=FEED_BACKLOG))

    def _on_clock(self, _key: str, clock: ClockWire) -> None:
        latest = self.clock.get(0)
        self.clock.put(0, clock)
        if latest is None or latest[0].state != clock.state:
            self._state_changed.set()  # the supervisor reacts now, not at its next poll

    def _on_telemetry(self, key: str, tel: TelemetryWire) -> None:
        """One decode, every consumer: the collector, then each listener."""
        self.collector.on_telemetry(key, tel)
        self._record(key, tel)
        if self.live_view is not None:
            self.live_view.put(tel)
        for listener in self.telemetry_listeners:
            listener(tel)

    def _on_truth(self, key: str, truth: TruthWire) -> None:
        self.collector.on_truth(key, truth)
        self._record(key, truth)
        if self.live_view is not None:
            self.live_view.put(truth)

    def _on_camera(self, key: str, message: CameraFrameWire | CameraImageWire) -> None:
        self._record(key, message)
        if self.live_view is not None:
            self.live_view.put_camera(message)

    def _record(self, _key: str, message: TelemetryWire | TruthWire | BeaconWire
                | CameraFrameWire | CameraImageWire) -> None:
        """Hand a message to the recorder's queue (its own thread writes it)."""
        if self.recorder is not None:
            self.recorder.put(message)

    def _mission_state(self) -> str:
        latest = self.clock.get(0)
        return "starting" if latest is None else latest[0].state

    # -- the end -------------------------------------------------------------------------------

    def _leave_zenoh(self) -> None:
        feed, self._feed = self._feed, None
        if feed is not None:
            feed.close()  # what came before this is handed over; nothing after it
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None

    def _close_recorder(self) -> None:
        recorder, self.recorder = self.recorder, None
        if recorder is None:
            return
        recorder.close()
        problem = f"; {recorder.dropped} not written: {recorder.error}" if recorder.error else ""
        if recorder.error:
            self.recording_problem = (f"{recorder.path}: {recorder.dropped} messages not "
                                      f"written: {recorder.error}")
        self.log(f"{self.prog}: recorded {recorder.written} messages to {recorder.path}"
                 f"{problem}")

    def stop_observing(self) -> None:
        """Leave Zenoh (no message arrives after this: record and recording agree), finish
        the recording and stop the live view; safe to call more than once."""
        self._leave_zenoh()
        self._close_recorder()
        view, self.live_view = self.live_view, None
        if view is not None:
            view.close()


# -- the end-of-mission summary -------------------------------------------------------------------


def print_summary(record: RunRecord, console: Console, mode: str = "inprocess",
                  counters: Mapping[int, TelemetryCounters] | None = None) -> int:
    """The run's report (the same tables and verdict as ``swarm-report``); its exit code."""
    report = build_report(record, mode, counters)
    render_report(report, console)
    return report.exit_code


def print_process_counters(collector: TelemetryCollector, console: Console) -> None:
    """One line of the agents' running totals, as the processes reported them."""
    counts = collector.counters()
    steps = max(counts["agent_steps"], 1)
    console.print(
        f"agent steps {counts['agent_steps']} (telemetry received "
        f"{counts['telemetry_received']}), late {counts['late_steps']} "
        f"({100.0 * counts['late_steps'] / steps:.2f} %), stale neighbour messages "
        f"{counts['stale_neighbour_messages']}, rejected messages "
        f"{counts['rejected_messages']}, QP fallbacks {counts['qp_fallbacks']}, vehicle "
        f"events {counts['vehicle_events']}, rate-box releases "
        f"{counts['rate_limit_releases']}, reference resets {counts['reference_resets']}, "
        f"λ̄ breaches said by the agents {counts['lambda_breaches']}, steps the safety "
        f"envelope overruled localization {counts['safety_conflicts']}, a keep row "
        f"{counts['link_conflicts']}, splits said {counts['splits_said']}",
        highlight=False)
