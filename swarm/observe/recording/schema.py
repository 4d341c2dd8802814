"""What a recording holds: its channels, its metadata, the JSON Schema of each kind of message
and the converters between the wire structs and that JSON.

The file is MCAP (what Foxglove and the robotics tools read). Every wire message a consumer
can see is one MCAP message on a channel named like its Zenoh key without the run prefix:
``agent/<i>/telemetry``, ``agent/<i>/beacon``, ``world/camera/<i>`` (detections) and
``world/truth``; runs that watch real autopilots add ``autopilot/<i>/state``. Messages are
JSON objects with a JSON Schema per kind, so Foxglove can plot any field
(``agent/0/telemetry.lambda_bar[0]``): named fields, numbers, and arrays as plain (nested)
lists — the converters turn the array-like msgpack wire structs into such objects and back,
bit-exact (JSON floats are written in their shortest round-trip form). ``log_time`` is the sim
time of the message's step (step·ΔT, ns), ``publish_time`` the wall-clock time of receipt
(ns since the Unix epoch).

A metadata record ``vigil`` holds the resolved config (after CLI overrides), seed, mode
(lockstep, realtime, inprocess), package version, git commit, run id and start time.

Writing: ``swarm.observe.recording.writer``; reading: ``swarm.observe.recording.reader``.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as distribution_version
from pathlib import Path
from typing import Any, ClassVar, Final

import msgspec
import numpy as np

from swarm.errors import UsageError, VigilError
from swarm.messages.wire import (
    TELEMETRY_ARRAYS,
    BeaconWire,
    CameraFrameWire,
    DetectionWire,
    F64Array,
    TelemetryCounters,
    TelemetryWire,
    TruthWire,
)
from swarm.scenario.config import ConfigError, ScenarioConfig, config_from_dict, config_to_data

RECORDING_FILE: Final = "run.mcap"
FORMAT: Final = "vigil-recording/1"
METADATA_NAME: Final = "vigil"
DISTRIBUTION: Final = "vigil-swarm"
MODES: Final = ("lockstep", "realtime", "inprocess")
KINDS: Final = ("telemetry", "beacon", "camera", "truth", "autopilot")
_GIT_TIMEOUT_S: Final = 5.0


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

    label: ClassVar[str] = "recording failed: "


class RecordingFileError(RecordingError, UsageError):
    """A file given to be read that is not a readable Vigil recording: input that cannot be
    used (``swarm-report DIR``), not a run that failed."""

    label: ClassVar[str] = ""


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
    # The ``swarm`` package (this module is swarm/observe/recording/schema.py).
    package_dir = (source_dir or Path(__file__).resolve().parents[2]).resolve()
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
        """Parse ``to_mcap``'s map; RecordingFileError (naming ``where``) if it is not one."""
        if not data.get("format", "").startswith("vigil-recording/"):
            raise RecordingFileError(f"{where}: metadata '{METADATA_NAME}' is not a Vigil "
                                 f"recording's (format {data.get('format')!r})")
        try:
            config = config_from_dict(json.loads(data["config"]),
                                      source=data.get("config_path") or "<recording>")
            if data["mode"] not in MODES:
                raise RecordingFileError(f"{where}: Vigil metadata is invalid: mode must be "
                                         f"one of {', '.join(MODES)}, got {data['mode']!r}")
            return cls(config=config, seed=int(data["seed"]), mode=data["mode"],
                       version=data["version"], git_commit=data["git_commit"],
                       run_id=data["run_id"], start_time_ns=int(data["start_time_ns"]),
                       config_path=data.get("config_path", ""))
        except KeyError as err:
            raise RecordingFileError(f"{where}: Vigil metadata lacks {err}") from None
        except (ValueError, ConfigError) as err:  # JSONDecodeError is a ValueError
            raise RecordingFileError(f"{where}: Vigil metadata is invalid: {err}") from None


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
                           "rate_limit_released", "safety_conflict", "reached",
                           "keep_margin_m", "link_conflict")
_COUNTER_FIELDS: Final = TelemetryCounters.__struct_fields__
# Fields that older recordings lack: read as their defaults.
_ADDED_LATER: Final = {"rate_limit_released": False, "safety_conflict": False,
                       "reached": 0, "keep_margin_m": None, "link_conflict": False,
                       **{name: getattr(TelemetryCounters(), name)
                          for name in ("rate_limit_releases", "reference_resets",
                                       "vehicle_events", "tracking_error_m",
                                       "velocity_error_m_s", "vehicle_status",
                                       "lambda_breaches", "first_lambda_breach_s",
                                       "localization_status", "safety_conflicts",
                                       "link_conflicts", "splits_said")}}


def telemetry_to_json(tel: TelemetryWire) -> dict[str, Any]:
    out: dict[str, Any] = {name: getattr(tel, name) for name in _TELEMETRY_PLAIN}
    out["position_m"] = list(tel.position_m)
    out.update({name: _floats(getattr(tel, name)) for name in _TELEMETRY_ARRAYS})
    out["detected"] = list(tel.detected)
    # one 0/1 per drone (the wire's mask), None when the agent sent none
    out["neighbours_heard"] = (None if tel.neighbours_heard is None
                               else list(tel.neighbours_heard))
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
        detected=tuple(bool(v) for v in data["detected"]), counters=counters,
        neighbours_heard=(None if data.get("neighbours_heard") is None  # absent before
                          else bytes(data["neighbours_heard"])))


def beacon_to_json(beacon: BeaconWire) -> dict[str, Any]:
    return {"sender": beacon.sender, "step": beacon.step, "time_s": beacon.time_s,
            "position_m": list(beacon.position_m), "velocity_m_s": list(beacon.velocity_m_s),
            "sample_age_s": beacon.sample_age_s, "vehicle_time_ms": beacon.vehicle_time_ms}


def beacon_from_json(data: dict[str, Any]) -> BeaconWire:
    return BeaconWire(sender=data["sender"], step=data["step"], time_s=data["time_s"],
                      position_m=_vector3(data["position_m"]),
                      velocity_m_s=_vector3(data["velocity_m_s"]),
                      sample_age_s=data["sample_age_s"],
                      vehicle_time_ms=data.get("vehicle_time_ms", 0))  # absent in older files


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
            "target_velocities": _floats(truth.target_velocities),
            "radio_links": (None if truth.radio_links is None
                            else truth.radio_links.to_array().astype(bool).tolist())}


def truth_from_json(data: dict[str, Any]) -> TruthWire:
    return TruthWire(step=data["step"], time_s=data["time_s"],
                     drone_positions=_array(data["drone_positions"]),
                     target_positions=_array(data["target_positions"]),
                     target_velocities=_array(data["target_velocities"]),
                     radio_links=(None if data.get("radio_links") is None  # absent before
                                  else _array(data["radio_links"])))


def autopilot_to_json(state: AutopilotState) -> dict[str, Any]:
    return msgspec.to_builtins(state)


def autopilot_from_json(data: dict[str, Any]) -> AutopilotState:
    return msgspec.convert(data, AutopilotState)


@dataclass(frozen=True)
class MessageKind:
    """How one kind of message is named, timed and converted."""

    name: str
    to_json: Callable[[Any], dict[str, Any]]
    from_json: Callable[[dict[str, Any]], Recordable]
    source: Callable[[Any], int | None]  # the drone id in the topic (None: world-wide)


KIND_OF_TYPE: Final[dict[type, MessageKind]] = {
    TelemetryWire: MessageKind("telemetry", telemetry_to_json, telemetry_from_json,
                         lambda m: m.drone),
    BeaconWire: MessageKind("beacon", beacon_to_json, beacon_from_json, lambda m: m.sender),
    CameraFrameWire: MessageKind("camera", camera_to_json, camera_from_json, lambda m: m.drone),
    TruthWire: MessageKind("truth", truth_to_json, truth_from_json, lambda _m: None),
    AutopilotState: MessageKind("autopilot", autopilot_to_json, autopilot_from_json,
                          lambda m: m.drone),
}
KIND_NAMED: Final[dict[str, MessageKind]] = {kind.name: kind for kind in KIND_OF_TYPE.values()}


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
        "rate_limit_released": _BOOL, "safety_conflict": _BOOL, "reached": _COUNT,
        "keep_margin_m": {"type": ["number", "null"]}, "link_conflict": _BOOL,
        "neighbours_heard": {"anyOf": [_list(_COUNT), {"type": "null"}]},
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
            "localization_status": {"type": "string"}, "safety_conflicts": _COUNT,
            "link_conflicts": _COUNT, "splits_said": _COUNT}),
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
                          "target_velocities": _list(vec3),
                          "radio_links": {"anyOf": [_list(_list(_BOOL)), {"type": "null"}]}},
                         "vigil.Truth", "Ground truth of one step (world frame) [m], [m/s]."),
        "autopilot": _object({"drone": _COUNT, "time_s": _NUMBER, "position_m": vec3,
                              "velocity_m_s": vec3, "mode": {"type": "string"},
                              "armed": _BOOL, "landed_state": _COUNT},
                             "vigil.AutopilotState",
                             "A real autopilot's own state as its monitor link reports it: "
                             "its position estimate in the world frame [m], [m/s], mode, "
                             "armed, MAV_LANDED_STATE."),
    }
