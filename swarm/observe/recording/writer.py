"""Writing a recording: ``Recorder`` writes one run to ``DIR/run.mcap`` as the run goes
(``swarm.observe.recording.schema`` says what it holds), ``record_reference`` records an
in-process run.

Durability: messages go into small zstd chunks, and a writer thread finishes the chunk in
progress and flushes the file at least every ``FLUSH_PERIOD_S`` (also when nothing arrives),
so a launcher killed with ``kill -9`` leaves a file that holds everything up to about that
long before the kill. ``Recorder.close`` writes the summary and footer. Besides the messages,
the recorder writes the 3D scene, the log lines and each drone's plot values
(``swarm.observe.foxglove_scene``) of every ``SCENE_PERIOD_S`` of sim time, and with rendered
cameras each drone's images, calibration and detections every ``RECORDED_IMAGE_PERIOD_S``
and the cameras' frames (``swarm.observe.camera_view``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import shutil
import threading
import time
from pathlib import Path
from typing import IO, Any, Final

import msgspec
from foxglove.messages import Log, SceneUpdate
from mcap.writer import CompressionType, Writer

from swarm.messages.wire import CameraFrameWire, CameraImageWire, TelemetryWire, TruthWire
from swarm.observe.camera_view import (
    RECORDED_IMAGE_PERIOD_S,
    CameraMessage,
    CameraView,
    ImageSchedule,
)
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
from swarm.observe.recording.schema import (
    DISTRIBUTION,
    KIND_OF_TYPE,
    METADATA_NAME,
    RECORDING_FILE,
    AutopilotState,
    Recordable,
    RecordingError,
    RecordingMetadata,
    schemas,
    topic,
)
from swarm.runs.record import RunRecord
from swarm.runs.reference import StepCallback, run_reference
from swarm.scenario.config import ScenarioConfig

FLUSH_PERIOD_S: Final = 0.5  # newest data on disk is at most this old (plus one message)
CHUNK_BYTES: Final = 256 * 1024  # a chunk also ends at every flush
DRAIN_PERIOD_S: Final = 0.1  # the writer thread wakes this often (and at close)
# msgspec's JSON is ~10x faster than the json module, with the same exact shortest-repr
# floats; the recorder's thread shares the launcher's GIL with its callbacks.
_JSON_ENCODER: Final = msgspec.json.Encoder()


def record_directory(text: str) -> Path:
    """argparse type of ``--record DIR``: DIR is created if needed and must be writable, so
    that a bad DIR is a usage error before anything starts, not a failure mid-run."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} exists and is not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise argparse.ArgumentTypeError(f"cannot create {text!r}: {err.strerror or err}"
                                         ) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{text!r} is not writable")
    return path


_STOP: Final = object()


# What a recording takes on disk per drone and simulated second, with room to spare: Case 2
# (6 drones, 2 targets) writes ~160 kB per simulated second, i.e. ~27 kB per drone.
RECORDING_BYTES_PER_DRONE_SECOND: Final = 40_000
# A recorded camera image, generously: a 480 px JPEG at quality 90 is ~27 KiB; the bytes grow
# with the pixels and the quality (8 bits a pixel is an uncompressed grey image).
IMAGE_BYTES_PER_PIXEL: Final = 0.25


def estimated_recording_bytes(cfg: ScenarioConfig) -> int:
    """Disk space a recording of ``cfg`` needs, generously (checked before a run starts)."""
    n_targets = len(cfg.targets)
    per_drone_s = RECORDING_BYTES_PER_DRONE_SECOND * max(1.0, n_targets / 2)
    if cfg.camera.rendered:
        images_per_s = ImageSchedule(cfg, RECORDED_IMAGE_PERIOD_S).rate_hz
        per_drone_s += images_per_s * IMAGE_BYTES_PER_PIXEL * cfg.camera.resolution_px ** 2
    return int(per_drone_s * cfg.swarm.n_drones * cfg.scenario.duration_s) + 1_000_000


class Recorder:
    """Writes one run to ``directory/run.mcap``; ``put`` is safe from any thread.

    ``put`` only enqueues: a writer thread converts to JSON and writes in batches, and
    flushes at least every ``flush_period_s``. Use as a context manager, or call ``close``
    (idempotent) on every way out so that the file gets its summary and footer.
    """

    def __init__(self, directory: Path, metadata: RecordingMetadata, *,
                 flush_period_s: float = FLUSH_PERIOD_S, autopilots: bool = False) -> None:
        self.path = Path(directory) / RECORDING_FILE
        self.metadata = metadata
        self.flush_period_s = flush_period_s
        cfg = metadata.config
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            free = shutil.disk_usage(self.path.parent).free
        except OSError as err:
            raise RecordingError(f"cannot record to {self.path}: {err.strerror or err}"
                                 ) from None
        needed = estimated_recording_bytes(cfg)
        if free < needed:  # say so now, not minutes into the mission
            raise RecordingError(
                f"cannot record to {self.path}: {free / 1e6:.1f} MB free, a "
                f"{cfg.scenario.duration_s:g} s run of {cfg.swarm.n_drones} drones needs "
                f"about {needed / 1e6:.1f} MB")
        try:
            self._file: IO[bytes] = self.path.open("wb")
        except OSError as err:
            raise RecordingError(f"cannot record to {self.path}: {err.strerror or err}"
                                 ) from None
        self._dt_ns = round(cfg.scenario.dt_s * 1e9)
        self._scene = SceneAssembler(cfg, self._write_scene)
        self._camera = (CameraView(cfg, RECORDED_IMAGE_PERIOD_S) if cfg.camera.rendered
                        else None)
        self._log_book = LogBook()
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES,
                              compression=CompressionType.ZSTD)
        try:  # header, schemas, channels and metadata are on disk before any message
            self._writer.start(library=f"{DISTRIBUTION}/{metadata.version}")
            self._register_channels(cfg, autopilots)
            self._writer.add_metadata(METADATA_NAME, metadata.to_mcap())
            self._writer.flush()
        except OSError as err:
            with contextlib.suppress(OSError):  # closing flushes again, into the same error
                self._file.close()
            raise RecordingError(f"cannot record to {self.path}: {err.strerror or err}"
                                 ) from None
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._lock = threading.Lock()  # guards _closed against put/close races
        self._wake = threading.Event()  # set by close: write the rest now
        self._closed = False
        self.written = 0
        self.dropped = 0  # put after close, or not writable (the reason is in ``error``)
        self.error: str | None = None  # the first problem, if any
        self._io_failed = False  # the file cannot be written any more
        self._thread = threading.Thread(target=self._run, name="vigil-recorder", daemon=True)
        self._thread.start()

    def _register_channels(self, cfg: ScenarioConfig, autopilots: bool) -> None:
        """``autopilots``: also ``autopilot/<i>/state`` (runs that watch real autopilots)."""
        ids = {kind: self._writer.register_schema(
                   name=schema["title"], encoding="jsonschema",
                   data=json.dumps(schema).encode())
               for kind, schema in schemas(len(cfg.targets), cfg.state_dimension).items()}
        # Every channel up front, so that a viewer lists every topic from the start.
        channels = [("truth", topic("truth"))] + [
            (kind, topic(kind, i)) for i in range(cfg.swarm.n_drones)
            for kind in ("telemetry", "beacon", "camera")]
        if autopilots:
            channels += [("autopilot", topic("autopilot", i)) for i in range(cfg.swarm.n_drones)]
        for kind, name in channels:
            self._channels[name] = self._writer.register_channel(
                topic=name, message_encoding="json", schema_id=ids[kind])
        scene = SceneUpdate.get_schema()  # Foxglove's well-known schema, as its SDK has it
        self._channels[SCENE_TOPIC] = self._writer.register_channel(
            topic=SCENE_TOPIC, message_encoding=scene.encoding,
            schema_id=self._writer.register_schema(name=scene.name, encoding="protobuf",
                                                   data=scene.data))
        log = Log.get_schema()
        self._channels[LOG_TOPIC] = self._writer.register_channel(
            topic=LOG_TOPIC, message_encoding=log.encoding,
            schema_id=self._writer.register_schema(name=log.name, encoding="protobuf",
                                                   data=log.data))
        plot = plot_schema(len(cfg.targets))
        plot_id = self._writer.register_schema(name=plot["title"], encoding="jsonschema",
                                               data=json.dumps(plot).encode())
        for i in range(cfg.swarm.n_drones):
            self._channels[plot_topic(i)] = self._writer.register_channel(
                topic=plot_topic(i), message_encoding="json", schema_id=plot_id)
        if self._camera is not None:
            schema_ids: dict[str, int] = {}
            for name, message_type in self._camera.topics():
                schema = message_type.get_schema()
                if schema.name not in schema_ids:
                    schema_ids[schema.name] = self._writer.register_schema(
                        name=schema.name, encoding="protobuf", data=schema.data)
                self._channels[name] = self._writer.register_channel(
                    topic=name, message_encoding=schema.encoding,
                    schema_id=schema_ids[schema.name])

    def put(self, message: Recordable | CameraImageWire, received_ns: int | None = None) -> None:
        """Queue a message for writing; ``received_ns``: wall time of receipt (default now).
        A camera image is kept only on the steps the recording's ``ImageSchedule`` keeps."""
        if isinstance(message, CameraImageWire) and not (
                self._camera is not None and self._camera.wants(message.step)):
            return
        stamp = time.time_ns() if received_ns is None else received_ns
        with self._lock:
            if self._closed:
                self.dropped += 1
                return
            self._queue.put((message, stamp))

    def _add(self, name: str, data: bytes, log_time: int, publish_time: int) -> None:
        channel = self._channels[name]
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        self._writer.add_message(channel_id=channel, log_time=log_time, data=data,
                                 publish_time=publish_time, sequence=sequence)

    def _add_camera(self, items: list[tuple[str, CameraMessage]], step: int,
                    publish_time: int) -> None:
        for name, message in items:
            if name not in self._channels:  # a drone outside the config: the codec refuses it
                self._count_dropped()
                continue
            self._add(name, message.encode(), step * self._dt_ns, publish_time)

    def _write(self, message: Recordable | CameraImageWire, received_ns: int) -> None:
        if isinstance(message, CameraImageWire):
            if self._camera is not None:
                self._add_camera(self._camera.of_image(message), message.step, received_ns)
                self.written += 1
            return
        kind = KIND_OF_TYPE[type(message)]
        name = topic(kind.name, kind.source(message))
        if name not in self._channels:  # a drone outside the config: the codec refuses it
            self._count_dropped()
            return
        log_time = (round(message.time_s * 1e9) if isinstance(message, AutopilotState)
                    else message.step * self._dt_ns)
        self._add(name, _JSON_ENCODER.encode(kind.to_json(message)), log_time, received_ns)
        self.written += 1
        if isinstance(message, TelemetryWire):
            self._scene.on_telemetry(message)
        elif isinstance(message, TruthWire):
            self._scene.on_truth(message)
        elif isinstance(message, CameraFrameWire) and self._camera is not None:
            self._add_camera(self._camera.of_frame(message), message.step, received_ns)

    def _write_scene(self, state: SceneState) -> None:
        """The 3D scene of one instant and each drone's plot values, beside the messages
        they were built from."""
        log_time, now = state.step * self._dt_ns, time.time_ns()
        items = [(SCENE_TOPIC, scene_update(self.metadata.config, state).encode())]
        items += [(plot_topic(i), _JSON_ENCODER.encode(plot_values(state, i)))
                  for i in range(state.weights.shape[0])]
        items += [(LOG_TOPIC, line.encode()) for line in self._log_book.lines(state)]
        if self._camera is not None:
            items += [(name, message.encode())
                      for name, message in self._camera.of_scene(state.drones_m, state.time_s)]
        for name, data in items:
            self._add(name, data, log_time, now)

    def _run(self) -> None:
        """Writer thread: every ``DRAIN_PERIOD_S`` write what is queued, flush on schedule,
        stop at the sentinel. Waking per batch rather than per message keeps this thread
        from contending for the GIL a thousand times a second with Zenoh's callbacks."""
        next_flush = time.monotonic() + self.flush_period_s
        while True:
            self._wake.wait(min(DRAIN_PERIOD_S, max(next_flush - time.monotonic(), 0.0)))
            while True:
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is _STOP:
                    return
                self._write_or_count(*item)
            if time.monotonic() >= next_flush:
                self._flush()
                next_flush = time.monotonic() + self.flush_period_s

    def _write_or_count(self, message: Recordable, received_ns: int) -> None:
        if self._io_failed:
            self._count_dropped()
            return
        try:
            self._write(message, received_ns)
        except (ValueError, TypeError, msgspec.EncodeError) as err:
            self._count_dropped()  # this message only; the first reason is kept
            self.error = self.error or f"unwritable {type(message).__name__}: {err}"
        except OSError as err:  # disk full: stop writing, keep the run going
            self._io_failure(err)

    def _count_dropped(self) -> None:
        with self._lock:
            self.dropped += 1

    def _io_failure(self, err: OSError) -> None:
        self._count_dropped()
        self._io_failed = True
        self.error = f"write failed: {err}"

    def _flush(self) -> None:
        if self._io_failed:
            return
        try:
            self._writer.flush()
        except OSError as err:
            self._io_failure(err)

    def close(self) -> None:
        """Write what is queued, then the summary and footer; safe to call more than once."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._queue.put(_STOP)
        self._wake.set()
        self._thread.join()
        try:
            if not self._io_failed:
                self._writer.finish()
        except OSError as err:
            self._io_failed, self.error = True, f"write failed: {err}"
        finally:
            self._file.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def record_reference(config: ScenarioConfig, seed: int | None, record_dir: Path,
                     on_step: StepCallback | None = None) -> RunRecord:
    """``run_reference`` that also writes ``record_dir/run.mcap`` with the channels a process
    swarm's recording holds; a message the recorder could not write (e.g. the disk filled up
    during the run) is a ``RecordingError``, never a silent gap."""
    seed = config.scenario.seed if seed is None else seed
    metadata = RecordingMetadata.for_run(config, seed, "inprocess", run_id="inprocess",
                                         config_path=config.source)
    with Recorder(record_dir, metadata) as recorder:
        record = run_reference(config, seed, on_step, sink=recorder)
    if recorder.error:
        raise RecordingError(f"{recorder.path}: {recorder.dropped} messages not written: "
                             f"{recorder.error}")
    return record
