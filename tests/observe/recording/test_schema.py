"""What a recording holds (swarm.observe.recording.schema): the config and metadata round-trip
through MCAP's strings, the git commit of this checkout, and every message kind converts to JSON
that matches its channel's JSON Schema and back exactly."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

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
from swarm.observe.recording.schema import (
    RecordingMetadata,
    beacon_from_json,
    beacon_to_json,
    camera_from_json,
    camera_to_json,
    git_commit,
    package_version,
    schemas,
    telemetry_from_json,
    telemetry_to_json,
    truth_from_json,
    truth_to_json,
)
from swarm.scenario.config import config_from_dict, config_to_data, load_config

ROOT = Path(__file__).resolve().parents[3]
CONFIGS = ROOT / "configs"
CASE1 = CONFIGS / "case1.toml"


# -- config and metadata -------------------------------------------------------------------------


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("*.toml"))
                         + sorted((ROOT / "tests" / "configs").glob("*.toml")),
                         ids=lambda p: p.stem)
def test_config_round_trips_through_plain_json_data(path: Path) -> None:
    config = load_config(path).with_duration(7.5)
    data = json.loads(json.dumps(config_to_data(config)))
    assert config_from_dict(data) == config


def test_metadata_round_trips_through_mcap_strings() -> None:
    config = load_config(CASE1).with_duration(4.0)
    metadata = RecordingMetadata.for_run(config, 7, "realtime", "abc", str(CASE1))
    strings = metadata.to_mcap()
    assert all(isinstance(v, str) for v in strings.values())
    assert RecordingMetadata.from_mcap(strings, "x") == metadata
    assert metadata.version == package_version() != "unknown"


def test_git_commit_is_this_checkouts_head_or_unknown(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # The tests import the package from this checkout: its HEAD, wherever git can say it
    # (git_commit finds the package dir from its module's depth in the package: one level off
    # and a checkout says "unknown").
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--show-toplevel", "HEAD"],
                          capture_output=True, text=True, check=False) \
        if shutil.which("git") else None
    lines = head.stdout.split() if head is not None and head.returncode == 0 else []
    at_top = len(lines) == 2 and Path(lines[0]).resolve() == ROOT.resolve()
    assert git_commit() == (lines[1] if at_top else "unknown")
    assert git_commit(tmp_path / "pkg") == "unknown"  # not a checkout
    monkeypatch.setenv("PATH", str(tmp_path))  # no git at all
    assert git_commit() == "unknown"


# -- message conversions -------------------------------------------------------------------------

AWKWARD = [-0.0, 5e-324, 0.1 + 0.2, 1.7976931348623157e308, -1e-300]  # must survive exactly


def sample_messages() -> list[Any]:
    counters = TelemetryCounters(qp_fallbacks=1, late_steps=2, steps=3, neighbour_age_ms=0.25,
                                 mavlink_state="armed OFFBOARD")
    m, n = 2, 6
    arr = F64Array.from_array
    telemetry = TelemetryWire.build(
        drone=1, step=42, time_s=0.84, position_m=(AWKWARD[0], 1.0, 3.5),
        velocity=arr(AWKWARD[:3]), nominal_velocity=arr([0.0, 0.0, 0.0]),
        estimates=arr(np.arange(m * n, dtype=float).reshape(m, n) / 3.0),
        estimate_covariance=arr(np.array([np.eye(3) * AWKWARD[2], np.diag(AWKWARD[1:4])])),
        lambda_bar=arr([0.06, AWKWARD[2]]), psi0=arr([1.0, 2.0]), psi1=arr([3.0, 4.0]),
        weights=arr([0.5, AWKWARD[1]]), weight_sum_estimate=arr([1.0, 1.5]),
        slacks=arr([0.0, 0.0]), weight_slacks=arr([0.0, -0.0]), detected=(True, False),
        control_active=True, qp_status="solved", qp_iterations=7, qp_fallback=False,
        qp_solve_us=12.5, step_us=450.0, bearing_error=None, missing_neighbour_messages=1,
        rejected_inputs=0, counters=counters)
    return [
        telemetry,
        with_fields(telemetry, bearing_error=0.125,
                                 counters=TelemetryCounters()),
        BeaconWire.build(3, 9, 0.18, [1.0, AWKWARD[4], 2.0], velocity_m_s=[0.1, 0.2, 0.3],
                         sample_age_s=0.004),
        CameraFrameWire(drone=0, step=5, time_s=0.1, vehicle_time_ms=1234,
                        detections=(DetectionWire(1, 0.25, AWKWARD[0]),)),
        CameraFrameWire(drone=2, step=5, time_s=0.1, vehicle_time_ms=1234,
                        target_velocities=arr([[0.1, 0.2, 0.0], [0.0, 0.0, AWKWARD[3]]])),
        TruthWire.build(5, 0.1, np.ones((6, 3)) * 0.3, [[0.0, 0.0, 0.0], [1.0, 2.0, 0.0]],
                        [[AWKWARD[1], 0.0, 0.0], [0.0, 0.0, 0.0]]),
    ]


def with_fields(message: TelemetryWire, **changes: Any) -> TelemetryWire:
    """A copy with some fields or arrays changed (the arrays packed again)."""
    fields = {name: getattr(message, name) for name in message.__struct_fields__
              if name not in ("version", "n_targets", "n_state", "data")}
    arrays = {name: getattr(message, name) for name in TELEMETRY_ARRAYS}
    return TelemetryWire.build(**{**fields, **arrays, **changes})


CONVERTERS = {
    TelemetryWire: ("telemetry", telemetry_to_json, telemetry_from_json),
    BeaconWire: ("beacon", beacon_to_json, beacon_from_json),
    CameraFrameWire: ("camera", camera_to_json, camera_from_json),
    TruthWire: ("truth", truth_to_json, truth_from_json),
}


def conforms(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """The subset of JSON Schema the recording's schemas use (no jsonschema dependency)."""
    if "anyOf" in schema:
        errors = []
        for option in schema["anyOf"]:
            try:
                conforms(value, option, where)
                return
            except AssertionError as err:
                errors.append(str(err))
        raise AssertionError(f"{where}: matches no anyOf option: {errors}")
    types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
    checks = {"object": lambda v: isinstance(v, dict), "array": lambda v: isinstance(v, list),
              "number": lambda v: type(v) in (int, float), "integer": lambda v: type(v) is int,
              "boolean": lambda v: type(v) is bool, "string": lambda v: type(v) is str,
              "null": lambda v: v is None}
    assert any(checks[t](value) for t in types), f"{where}: {value!r:.60} is not {types}"
    if isinstance(value, dict):
        assert set(value) == set(schema["required"]) == set(schema["properties"]), where
        for key, item in value.items():
            conforms(item, schema["properties"][key], f"{where}.{key}")
    elif isinstance(value, list):
        assert schema.get("minItems", 0) <= len(value) <= schema.get("maxItems", 1 << 30), where
        for k, item in enumerate(value):
            conforms(item, schema["items"], f"{where}[{k}]")
    elif "minimum" in schema:
        assert value >= schema["minimum"], where


@pytest.mark.parametrize("message", sample_messages(), ids=lambda m: type(m).__name__)
def test_each_kind_converts_to_schema_json_and_back_exactly(message: Any) -> None:
    kind, to_json, from_json = CONVERTERS[type(message)]
    text = json.dumps(to_json(message), allow_nan=False)
    conforms(json.loads(text), schemas(n_targets=2, n_state=6)[kind])
    back = from_json(json.loads(text))
    assert back == message  # msgspec compares every field; F64Array compares the bytes


def test_telemetry_recorded_before_the_covariance_was_sent_reads_back_as_unknown() -> None:
    """Recordings of wire version 3 have no ``estimate_covariance``: it reads back as NaN of
    the right shape (unknown, not zero: no viewer draws an ellipsoid of it); the rest as it
    was."""
    telemetry = sample_messages()[0]
    older = telemetry_to_json(telemetry)
    del older["estimate_covariance"]
    back = telemetry_from_json(json.loads(json.dumps(older)))
    covariance = back.estimate_covariance.to_array()
    assert covariance.shape == (2, 3, 3) and np.isnan(covariance).all()
    assert back == with_fields(telemetry, estimate_covariance=back.estimate_covariance)
