"""Recordings: one run as ``DIR/run.mcap``, written as the run goes and read back.

The file is MCAP (what Foxglove and the robotics tools read). Every wire message a consumer
can see is one MCAP message on a channel named like its Zenoh key without the run prefix:
``agent/<i>/telemetry``, ``agent/<i>/beacon``, ``world/camera/<i>`` (detections) and
``world/truth``. Messages are JSON objects with a JSON Schema per kind, so Foxglove can plot
any field (``agent/0/telemetry.lambda_bar[0]``): named fields, numbers, and arrays as plain
(nested) lists — the converters below turn the array-like msgpack wire structs into such
objects and back, bit-exact (JSON floats are written in their shortest round-trip form).
``log_time`` is the sim
time of the message's step (step·ΔT, ns), ``publish_time`` the wall-clock time of receipt
(ns since the Unix epoch).

A metadata record ``vigil`` holds the resolved config (after CLI overrides), seed, mode
(lockstep, realtime, inprocess), package version, git commit, run id and start time.

Durability: messages go into small zstd chunks, and a writer thread finishes the chunk in
progress and flushes the file at least every ``FLUSH_PERIOD_S`` (also when nothing arrives),
so a launcher killed with ``kill -9`` leaves a file that holds everything up to about that
long before the kill. ``Recorder.close`` writes the summary and footer. ``read_recording``
reads the records sequentially, so it also reads a file cut short by a crash (no footer, a
partial last record) up to the cut, and says so (``truncated``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import queue
import re
import shutil
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as distribution_version
from pathlib import Path
from typing import IO, Any, Final

import msgspec
import numpy as np
from foxglove.messages import Log, SceneUpdate
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, DataEnd, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from swarm.errors import VigilError
from swarm.messages.wire import (
    TELEMETRY_ARRAYS,
    BeaconWire,
    CameraFrameWire,
    DetectionWire,
    F64Array,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
    WireCodec,
    WireError,
)
from swarm.observe.collector import TelemetryCollector
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
from swarm.runs.record import RunRecord
from swarm.runs.reference import StepCallback, run_reference
from swarm.scenario.config import ConfigError, ScenarioConfig, config_from_dict, config_to_data

RECORDING_FILE: Final = "run.mcap"
FORMAT: Final = "vigil-recording/1"
METADATA_NAME: Final = "vigil"
DISTRIBUTION: Final = "vigil-swarm"
FLUSH_PERIOD_S: Final = 0.5  # newest data on disk is at most this old (plus one message)
CHUNK_BYTES: Final = 256 * 1024  # a chunk also ends at every flush
DRAIN_PERIOD_S: Final = 0.1  # the writer thread wakes this often (and at close)
MODES: Final = ("lockstep", "realtime", "inprocess")
KINDS: Final = ("telemetry", "beacon", "camera", "truth", "autopilot")
_GIT_TIMEOUT_S: Final = 5.0
# msgspec's JSON is ~10x faster than the json module both ways, with the same exact
# shortest-repr floats; the recorder's thread shares the launcher's GIL with its callbacks.
_JSON_ENCODER: Final = msgspec.json.Encoder()
_JSON_DECODER: Final = msgspec.json.Decoder()



class AutopilotState(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """What the launcher's own link to a real autopilot (SITL, ``swarm.mavlink.sitl.SitlMonitor``)
    heard from it during the mission: its own estimate of where it is, in W, its mode and
    armed state. Recorded on ``autopilot/<i>/state`` (about 10 Hz per drone), beside what the
    agents say, so a run shows what the vehicle did when its agent did not (lost, killed)."""

    drone: int
    time_s: float  # mission time of the newest truth step when heard [s]
    position_m: tuple[float, float, float]  # W [m]
    velocity_m_s: tuple[float, float, float]  # W [m/s]
    mode: str  # pymavlink's name of the autopilot's mode, e.g. "GUIDED", "BRAKE", "OFFBOARD"
    armed: bool
    landed_state: int  # MAV_LANDED_STATE (0 unknown, 1 ground, 2 air, 3 takeoff, 4 landing)

    def __post_init__(self) -> None:
        if not all(map(math.isfinite, (self.time_s, *self.position_m, *self.velocity_m_s))):
            raise ValueError("non-finite autopilot state")


Recordable = TelemetryWire | BeaconWire | CameraFrameWire | TruthWire | AutopilotState


class RecordingError(VigilError, RuntimeError):
    """A recording that cannot be written or read; ``str()`` is one line naming the file."""


# -- provenance ----------------------------------------------------------------------------------


def package_version() -> str:
    """The installed version of vigil-swarm ("unknown" when it is not installed)."""
    try:
        return distribution_version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


def git_commit(source_dir: Path | None = None) -> str:
    """HEAD of the source tree this package runs from, or "unknown".

    Only when the package directory sits at the top of a git checkout (an editable install
    or a run from the repository); never fails, e.g. when git is not installed.
    """
    # The ``swarm`` package (this module is swarm/observe/recording.py).
    package_dir = (source_dir or Path(__file__).resolve().parents[1]).resolve()
    try:
        result = subprocess.run(
            ["git", "-C", str(package_dir), "rev-parse", "--show-toplevel", "HEAD"],
            capture_output=True, text=True, timeout=_GIT_TIMEOUT_S, check=False)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    lines = result.stdout.split()
    if result.returncode != 0 or len(lines) != 2:
        return "unknown"
    top, commit = Path(lines[0]).resolve(), lines[1]
    if top != package_dir.parent or not re.fullmatch(r"[0-9a-f]{40}", commit):
        return "unknown"
    return commit


# -- metadata ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordingMetadata:
    """What a recording says about its run."""

    config: ScenarioConfig  # resolved: after --duration and other overrides
    seed: int
    mode: str  # "lockstep", "realtime" or "inprocess"
    version: str  # of vigil-swarm
    git_commit: str  # 40 hex digits, or "unknown"
    run_id: str
    start_time_ns: int  # wall clock at the start [ns since the Unix epoch]
    config_path: str = ""

    @classmethod
    def for_run(cls, config: ScenarioConfig, seed: int, mode: str, run_id: str,
                config_path: str = "") -> RecordingMetadata:
        """Metadata of a run starting now, with this checkout's version and commit."""
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        return cls(config=config, seed=int(seed), mode=mode, version=package_version(),
                   git_commit=git_commit(), run_id=run_id, start_time_ns=time.time_ns(),
                   config_path=config_path)

    @property
    def start_time_utc(self) -> str:
        return datetime.fromtimestamp(self.start_time_ns / 1e9, UTC).isoformat()

    def to_mcap(self) -> dict[str, str]:
        """MCAP metadata is a map of strings; the config travels as JSON."""
        return {
            "format": FORMAT, "run_id": self.run_id, "mode": self.mode, "seed": str(self.seed),
            "version": self.version, "git_commit": self.git_commit,
            "start_time_ns": str(self.start_time_ns), "start_time": self.start_time_utc,
            "config_path": self.config_path, "scenario": self.config.scenario.name,
            "config": json.dumps(config_to_data(self.config), allow_nan=False),
        }

    @classmethod
    def from_mcap(cls, data: dict[str, str], where: str) -> RecordingMetadata:
        """Parse ``to_mcap``'s map; RecordingError (naming ``where``) if it is not one."""
        if not data.get("format", "").startswith("vigil-recording/"):
            raise RecordingError(f"{where}: metadata '{METADATA_NAME}' is not a Vigil "
                                 f"recording's (format {data.get('format')!r})")
        try:
            config = config_from_dict(json.loads(data["config"]),
                                      source=data.get("config_path") or "<recording>")
            return cls(config=config, seed=int(data["seed"]), mode=data["mode"],
                       version=data["version"], git_commit=data["git_commit"],
                       run_id=data["run_id"], start_time_ns=int(data["start_time_ns"]),
                       config_path=data.get("config_path", ""))
        except KeyError as err:
            raise RecordingError(f"{where}: Vigil metadata lacks {err}") from None
        except (ValueError, ConfigError) as err:  # JSONDecodeError is a ValueError
            raise RecordingError(f"{where}: Vigil metadata is invalid: {err}") from None


# -- JSON converters, one per kind ---------------------------------------------------------------


def _floats(array: F64Array) -> list[Any]:
    """A float64 wire array as (nested) lists of floats."""
    return array.to_list()


def _array(values: Any) -> F64Array:
    return F64Array.from_array(np.asarray(values, dtype=np.float64))


def _vector3(values: Any) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


_TELEMETRY_ARRAYS: Final = TELEMETRY_ARRAYS
_TELEMETRY_PLAIN: Final = ("drone", "step", "time_s", "control_active", "qp_status",
                           "qp_iterations", "qp_fallback", "qp_solve_us", "step_us",
                           "bearing_error", "missing_neighbour_messages", "rejected_inputs",
                           "rate_limit_released", "safety_conflict")
_COUNTER_FIELDS: Final = TelemetryCounters.__struct_fields__
# Fields added after recordings were first written (issue 14): absent in older files, read
# as their defaults.
_ADDED_LATER: Final = {"rate_limit_released": False, "safety_conflict": False,
                       **{name: getattr(TelemetryCounters(), name)
                          for name in ("rate_limit_releases", "reference_resets",
                                       "vehicle_events", "tracking_error_m",
                                       "velocity_error_m_s", "vehicle_status",
                                       "lambda_breaches", "first_lambda_breach_s",
                                       "localization_status", "safety_conflicts")}}


def telemetry_to_json(tel: TelemetryWire) -> dict[str, Any]:
    out: dict[str, Any] = {name: getattr(tel, name) for name in _TELEMETRY_PLAIN}
    out["position_m"] = list(tel.position_m)
    out.update({name: _floats(getattr(tel, name)) for name in _TELEMETRY_ARRAYS})
    out["detected"] = list(tel.detected)
    out["counters"] = {name: getattr(tel.counters, name) for name in _COUNTER_FIELDS}
    return out


def telemetry_from_json(data: dict[str, Any]) -> TelemetryWire:
    given = data["counters"]
    counters = TelemetryCounters(**{
        name: given[name] if name in given or name not in _ADDED_LATER else _ADDED_LATER[name]
        for name in _COUNTER_FIELDS})
    return TelemetryWire.build(
        **{name: data[name] if name in data or name not in _ADDED_LATER else _ADDED_LATER[name]
           for name in _TELEMETRY_PLAIN},
        position_m=_vector3(data["position_m"]),
        **{name: np.asarray(data[name], dtype=np.float64) for name in _TELEMETRY_ARRAYS
           if name in data},
        **({} if "estimate_covariance" in data else  # absent before wire version 4: unknown
           {"estimate_covariance": np.full((len(data["lambda_bar"]), 3, 3), np.nan)}),
        detected=tuple(bool(v) for v in data["detected"]), counters=counters)


def beacon_to_json(beacon: BeaconWire) -> dict[str, Any]:
    return {"sender": beacon.sender, "step": beacon.step, "time_s": beacon.time_s,
            "position_m": list(beacon.position_m), "velocity_m_s": list(beacon.velocity_m_s),
            "sample_age_s": beacon.sample_age_s, "vehicle_time_ms": beacon.vehicle_time_ms}


def beacon_from_json(data: dict[str, Any]) -> BeaconWire:
    return BeaconWire(sender=data["sender"], step=data["step"], time_s=data["time_s"],
                      position_m=_vector3(data["position_m"]),
                      velocity_m_s=_vector3(data["velocity_m_s"]),
                      sample_age_s=data["sample_age_s"],
                      vehicle_time_ms=data.get("vehicle_time_ms", 0))  # absent before 2026-11


def camera_to_json(frame: CameraFrameWire) -> dict[str, Any]:
    return {"drone": frame.drone, "step": frame.step, "time_s": frame.time_s,
            "vehicle_time_ms": frame.vehicle_time_ms,
            "detections": [{"target": d.target, "x": d.x, "y": d.y} for d in frame.detections],
            "target_velocities": (None if frame.target_velocities is None
                                  else _floats(frame.target_velocities))}


def camera_from_json(data: dict[str, Any]) -> CameraFrameWire:
    velocities = data["target_velocities"]
    return CameraFrameWire(
        drone=data["drone"], step=data["step"], time_s=data["time_s"],
        vehicle_time_ms=data["vehicle_time_ms"],
        detections=tuple(DetectionWire(d["target"], d["x"], d["y"])
                         for d in data["detections"]),
        target_velocities=None if velocities is None else _array(velocities))


def truth_to_json(truth: TruthWire) -> dict[str, Any]:
    return {"step": truth.step, "time_s": truth.time_s,
            "drone_positions": _floats(truth.drone_positions),
            "target_positions": _floats(truth.target_positions),
            "target_velocities": _floats(truth.target_velocities)}


def truth_from_json(data: dict[str, Any]) -> TruthWire:
    return TruthWire(step=data["step"], time_s=data["time_s"],
                     drone_positions=_array(data["drone_positions"]),
                     target_positions=_array(data["target_positions"]),
                     target_velocities=_array(data["target_velocities"]))


def autopilot_to_json(state: AutopilotState) -> dict[str, Any]:
    return msgspec.to_builtins(state)


def autopilot_from_json(data: dict[str, Any]) -> AutopilotState:
    return msgspec.convert(data, AutopilotState)


@dataclass(frozen=True)
class _Kind:
    """How one kind of message is named, timed and converted."""

    name: str
    to_json: Callable[[Any], dict[str, Any]]
    from_json: Callable[[dict[str, Any]], Recordable]
    source: Callable[[Any], int | None]  # the drone id in the topic (None: world-wide)


_BY_TYPE: Final[dict[type, _Kind]] = {
    TelemetryWire: _Kind("telemetry", telemetry_to_json, telemetry_from_json,
                         lambda m: m.drone),
    BeaconWire: _Kind("beacon", beacon_to_json, beacon_from_json, lambda m: m.sender),
    CameraFrameWire: _Kind("camera", camera_to_json, camera_from_json, lambda m: m.drone),
    TruthWire: _Kind("truth", truth_to_json, truth_from_json, lambda _m: None),
    AutopilotState: _Kind("autopilot", autopilot_to_json, autopilot_from_json,
                          lambda m: m.drone),
}
_BY_NAME: Final[dict[str, _Kind]] = {kind.name: kind for kind in _BY_TYPE.values()}


def topic(kind: str, drone: int | None = None) -> str:
    """The channel of a kind of message (and drone)."""
    if kind == "truth":
        return "world/truth"
    if kind == "camera":
        return f"world/camera/{drone}"
    if kind == "autopilot":
        return f"autopilot/{drone}/state"
    return f"agent/{drone}/{kind}"


_TOPIC = re.compile(r"^(?:agent/(\d+)/(telemetry|beacon)|world/(camera)/(\d+)|world/(truth)"
                    r"|autopilot/(\d+)/state)$")


def parse_topic(name: str) -> tuple[str, int | None] | None:
    """(kind, drone id) of a recording's topic, None for any other topic."""
    match = _TOPIC.match(name)
    if match is None:
        return None
    if match.group(5):
        return "truth", None
    if match.group(6):
        return "autopilot", int(match.group(6))
    if match.group(3):
        return "camera", int(match.group(4))
    return match.group(2), int(match.group(1))


# -- JSON Schemas (Foxglove's "jsonschema" encoding) ---------------------------------------------

_NUMBER: Final = {"type": "number"}
_COUNT: Final = {"type": "integer", "minimum": 0}
_BOOL: Final = {"type": "boolean"}


def _list(items: dict[str, Any], length: int | None = None) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": "array", "items": items}
    if length is not None:
        schema["minItems"] = schema["maxItems"] = length
    return schema


def _object(properties: dict[str, Any], title: str = "", description: str = ""
            ) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": "object", "properties": properties,
                              "required": list(properties)}
    if title:
        schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
                  "description": description, **schema}
    return schema


def schemas(n_targets: int, n_state: int) -> dict[str, dict[str, Any]]:
    """The JSON Schema of each kind for a swarm with these sizes."""
    vec3, per_target = _list(_NUMBER, 3), _list(_NUMBER, n_targets)
    telemetry = {
        "drone": _COUNT, "step": _COUNT, "time_s": _NUMBER, "control_active": _BOOL,
        "qp_status": {"type": "string"}, "qp_iterations": _COUNT, "qp_fallback": _BOOL,
        "rate_limit_released": _BOOL, "safety_conflict": _BOOL,
        "qp_solve_us": _NUMBER, "step_us": _NUMBER,
        "bearing_error": {"type": ["number", "null"]},
        "missing_neighbour_messages": _COUNT, "rejected_inputs": _COUNT,
        "position_m": vec3, "velocity": vec3, "nominal_velocity": vec3,
        "estimates": _list(_list(_NUMBER, n_state), n_targets),
        "estimate_covariance": _list(_list(_list(_NUMBER, 3), 3), n_targets),
        **{name: per_target for name in ("lambda_bar", "psi0", "psi1", "weights",
                                         "weight_sum_estimate", "slacks", "weight_slacks")},
        "detected": _list(_BOOL, n_targets),
        "counters": _object({
            **{name: _COUNT for name in ("qp_fallbacks", "rejected_messages",
                                         "missing_neighbour_messages",
                                         "stale_neighbour_messages", "late_steps", "steps")},
            "neighbour_age_ms": {"type": ["number", "null"]},
            "mavlink_state": {"type": "string"}, "swarm_size": _COUNT,
            **{name: _COUNT for name in ("rate_limit_releases", "reference_resets",
                                         "vehicle_events")},
            **{name: {"type": ["number", "null"]} for name in ("tracking_error_m",
                                                               "velocity_error_m_s")},
            "vehicle_status": {"type": "string"}, "lambda_breaches": _COUNT,
            "first_lambda_breach_s": {"type": ["number", "null"]},
            "localization_status": {"type": "string"}, "safety_conflicts": _COUNT}),
    }
    return {
        "telemetry": _object(telemetry, "vigil.Telemetry",
                             "One agent step: filter estimates per target ([x y z vx vy vz] "
                             "or [x y z]) and the covariance of their position [m²], "
                             "barrier terms, perception weights, QP result; "
                             "positions in the world frame (x east, y north, z up) [m]."),
        "beacon": _object({"sender": _COUNT, "step": _COUNT, "time_s": _NUMBER,
                           "position_m": vec3, "velocity_m_s": vec3, "sample_age_s": _NUMBER,
                           "vehicle_time_ms": _COUNT},
                          "vigil.Beacon", "A drone's position and velocity for its peers."),
        "camera": _object({"drone": _COUNT, "step": _COUNT, "time_s": _NUMBER,
                           "vehicle_time_ms": _COUNT,
                           "detections": _list(_object({"target": _COUNT, "x": _NUMBER,
                                                        "y": _NUMBER})),
                           "target_velocities": {"anyOf": [_list(vec3, n_targets),
                                                           {"type": "null"}]}},
                          "vigil.CameraFrame",
                          "A drone's detections: image-plane points per target."),
        "truth": _object({"step": _COUNT, "time_s": _NUMBER,
                          "drone_positions": _list(vec3), "target_positions": _list(vec3),
                          "target_velocities": _list(vec3)},
                         "vigil.Truth", "Ground truth of one step (world frame) [m], [m/s]."),
        "autopilot": _object({"drone": _COUNT, "time_s": _NUMBER, "position_m": vec3,
                              "velocity_m_s": vec3, "mode": {"type": "string"},
                              "armed": _BOOL, "landed_state": _COUNT},
                             "vigil.AutopilotState",
                             "A real autopilot's own state as its monitor link reports it: "
                             "its position estimate in the world frame [m], [m/s], mode, "
                             "armed, MAV_LANDED_STATE."),
    }


# -- writing -------------------------------------------------------------------------------------


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


def estimated_recording_bytes(cfg: ScenarioConfig) -> int:
    """Disk space a recording of ``cfg`` needs, generously (checked before a run starts)."""
    n_targets = len(cfg.targets)
    per_drone_s = RECORDING_BYTES_PER_DRONE_SECOND * max(1.0, n_targets / 2)
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

    def put(self, message: Recordable, received_ns: int | None = None) -> None:
        """Queue a message for writing; ``received_ns``: wall time of receipt (default now)."""
        stamp = time.time_ns() if received_ns is None else received_ns
        with self._lock:
            if self._closed:
                self.dropped += 1
                return
            self._queue.put((message, stamp))

    def _write(self, message: Recordable, received_ns: int) -> None:
        kind = _BY_TYPE[type(message)]
        channel = self._channels.get(topic(kind.name, kind.source(message)))
        if channel is None:  # a drone id outside the config: the codec would have refused it
            self._count_dropped()
            return
        data = _JSON_ENCODER.encode(kind.to_json(message))
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        log_time = (round(message.time_s * 1e9) if isinstance(message, AutopilotState)
                    else message.step * self._dt_ns)
        self._writer.add_message(channel_id=channel, log_time=log_time,
                                 data=data, publish_time=received_ns,
                                 sequence=sequence)
        self.written += 1
        if isinstance(message, TelemetryWire):
            self._scene.on_telemetry(message)
        elif isinstance(message, TruthWire):
            self._scene.on_truth(message)

    def _write_scene(self, state: SceneState) -> None:
        """The 3D scene of one instant and each drone's plot values, beside the messages
        they were built from."""
        log_time, now = state.step * self._dt_ns, time.time_ns()
        items = [(SCENE_TOPIC, scene_update(self.metadata.config, state).encode())]
        items += [(plot_topic(i), _JSON_ENCODER.encode(plot_values(state, i)))
                  for i in range(state.weights.shape[0])]
        items += [(LOG_TOPIC, line.encode()) for line in self._log_book.lines(state)]
        for name, data in items:
            channel = self._channels[name]
            sequence = self._sequence.get(channel, 0)
            self._sequence[channel] = sequence + 1
            self._writer.add_message(channel_id=channel, log_time=log_time, data=data,
                                     publish_time=now, sequence=sequence)

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


# -- reading -------------------------------------------------------------------------------------


class _WholeReads:
    """File reads that never return a short piece: a record cut by a crash raises EndOfFile
    (the end of the usable data) instead of becoming a garbled record."""

    def __init__(self, handle: IO[bytes]) -> None:
        self._handle = handle

    def read(self, size: int) -> bytes:
        data = self._handle.read(size)
        if len(data) < size:
            raise EndOfFile()
        return data


@dataclass(frozen=True)
class RecordedMessage:
    """One message of a recording, converted back to its wire struct."""

    topic: str
    kind: str  # "telemetry", "beacon", "camera", "truth" or "autopilot"
    drone: int | None  # from the topic; None for world/truth
    log_time_ns: int  # sim time of its step
    publish_time_ns: int  # wall time of receipt
    message: Recordable


class _RecordStream:
    """Sequential MCAP records of a file, stopping cleanly where a crash cut it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.truncated = True  # until the end of the data section is seen

    def __iter__(self) -> Iterator[Metadata | Channel | Message]:
        with self.path.open("rb") as handle:
            reader = StreamReader(_WholeReads(handle), record_size_limit=1 << 30)
            try:
                for record in reader.records:
                    if isinstance(record, DataEnd):
                        self.truncated = False
                        return  # the summary after it repeats what was already read
                    if isinstance(record, Metadata | Channel | Message):
                        yield record
            except EndOfFile:
                if handle.tell() < 8:
                    raise RecordingError(f"{self.path}: empty or cut before the MCAP header "
                                         "(is the run still starting?)") from None
            except InvalidMagic:
                raise RecordingError(f"{self.path}: not an MCAP file") from None
            except (McapError, ValueError, KeyError) as err:
                raise RecordingError(f"{self.path}: corrupt MCAP data: {err}") from None


def locate(path: Path) -> Path:
    """The .mcap file of a recording given as its directory or as the file itself."""
    path = Path(path)
    if path.is_dir():
        path = path / RECORDING_FILE
        if not path.is_file():
            raise RecordingError(f"{path.parent}: no {RECORDING_FILE} in this directory "
                                 "(not a recording made with --record?)")
        return path
    if not path.exists():
        raise RecordingError(f"{path}: no such file or directory")
    return path


def _decode(kind: str, data: bytes, codec: WireCodec | None, where: str) -> Recordable:
    """JSON → the wire struct, checked like a received payload when a codec is given."""
    try:
        message = _BY_NAME[kind].from_json(_JSON_DECODER.decode(data))
        if codec is not None and not isinstance(message, AutopilotState):
            codec.validate(message)
        return message
    except WireError as err:
        raise RecordingError(f"{where}: invalid {kind} message: {err.reason}") from None
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError, KeyError,
            TypeError) as err:
        raise RecordingError(f"{where}: malformed {kind} message: "
                             f"{type(err).__name__}: {err}") from None


def _codec(config: ScenarioConfig) -> WireCodec:
    return config.wire_codec()


def iter_messages(path: Path, kinds: tuple[str, ...] = KINDS) -> Iterator[RecordedMessage]:
    """Every message of the given kinds in file order (a cut-short file: up to the cut)."""
    file = locate(path)
    channels: dict[int, tuple[str, str, int | None]] = {}
    codec: WireCodec | None = None
    for record in _RecordStream(file):
        if isinstance(record, Metadata) and record.name == METADATA_NAME:
            codec = _codec(RecordingMetadata.from_mcap(record.metadata, str(file)).config)
        elif isinstance(record, Channel):
            parsed = parse_topic(record.topic)
            if parsed is not None:
                channels[record.id] = (record.topic, *parsed)
        elif isinstance(record, Message) and record.channel_id in channels:
            name, kind, drone = channels[record.channel_id]
            if kind in kinds:
                yield RecordedMessage(name, kind, drone, record.log_time, record.publish_time,
                                      _decode(kind, record.data, codec, f"{file}: {name}"))


@dataclass(frozen=True)
class Recording:
    """A recording read back: metadata, the run record and what the drones reported."""

    path: Path  # the .mcap file
    metadata: RecordingMetadata
    record: RunRecord  # up to the newest truth step; NaN where a message is missing
    drone_counters: dict[int, TelemetryCounters]  # newest running totals per drone
    message_counts: dict[str, int]  # per topic
    truncated: bool  # no clean end: the writer was killed, or is still writing
    missing_samples: int  # (step, positions or velocities) samples with no message
    last_publish_time_ns: int  # wall time of receipt of the newest message (0: none)
    sim_time_s: float  # sim time of the newest message (0 without messages)

    @property
    def config(self) -> ScenarioConfig:
        return self.metadata.config


def read_recording(path: Path, *, fill_gaps: bool = False) -> Recording:
    """Read ``DIR`` (or ``DIR/run.mcap``), also while it is written or after a crash.

    The record is built exactly as the launcher builds its own (``TelemetryCollector``);
    ``fill_gaps`` fills missing steps as the launcher's summary does instead of leaving NaN.
    Raises RecordingError (one line) for a missing path, a non-MCAP file, a file without
    Vigil metadata or a malformed message.
    """
    file = locate(path)
    stream = _RecordStream(file)
    metadata: RecordingMetadata | None = None
    collector: TelemetryCollector | None = None
    codec: WireCodec | None = None
    channels: dict[int, tuple[str, str]] = {}
    counts: dict[str, int] = {}
    last_publish, last_log = 0, 0
    for record in stream:
        if isinstance(record, Metadata) and record.name == METADATA_NAME:
            metadata = RecordingMetadata.from_mcap(record.metadata, str(file))
            collector = TelemetryCollector(metadata.config)
            codec = _codec(metadata.config)
        elif isinstance(record, Channel):
            parsed = parse_topic(record.topic)
            if parsed is not None:
                channels[record.id] = (record.topic, parsed[0])
                counts.setdefault(record.topic, 0)
        elif isinstance(record, Message) and record.channel_id in channels:
            name, kind = channels[record.channel_id]
            if collector is None:
                break  # reported below: messages before any Vigil metadata
            counts[name] += 1
            last_publish = max(last_publish, record.publish_time)
            last_log = max(last_log, record.log_time)
            if kind == "telemetry":
                collector.on_telemetry(name, _decode(kind, record.data, codec, f"{file}: {name}"))
            elif kind == "truth":
                collector.on_truth(name, _decode(kind, record.data, codec, f"{file}: {name}"))
    if metadata is None or collector is None:
        raise RecordingError(f"{file}: no Vigil metadata (an MCAP file, but not a recording "
                             "made by launch-swarm --record)")
    wall_s = max(last_publish - metadata.start_time_ns, 0) / 1e9 if last_publish else 0.0
    record = collector.record(metadata.seed, wall_s, fill=fill_gaps)
    return Recording(
        path=file, metadata=metadata, record=record, drone_counters=collector.drone_counters(),
        message_counts=counts, truncated=stream.truncated,
        missing_samples=collector.missing_samples, last_publish_time_ns=last_publish,
        sim_time_s=last_log / 1e9)


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
