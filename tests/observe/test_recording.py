"""Recordings (issue 4, point 1): ``--record DIR`` writes ``DIR/run.mcap`` as the run goes.

- what is read back equals what the run returned, bit for bit (in-process and a real lockstep
  process swarm), and the metadata gives back the resolved config;
- every message kind converts to JSON that matches its channel's JSON Schema and back
  exactly;
- a launcher killed with ``kill -9`` mid-run leaves a readable file holding everything up to
  at most 1 s before the kill, and no process behind;
- a file cut anywhere reads up to the cut; bad inputs give one-line RecordingErrors.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.writer import Writer

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
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
from swarm.observe.recording import (
    RECORDING_FILE,
    Recorder,
    RecordingError,
    RecordingMetadata,
    beacon_from_json,
    beacon_to_json,
    camera_from_json,
    camera_to_json,
    git_commit,
    iter_messages,
    package_version,
    read_recording,
    record_reference,
    schemas,
    telemetry_from_json,
    telemetry_to_json,
    truth_from_json,
    truth_to_json,
)
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import config_from_dict, config_to_data, load_config
from tests.helpers.scene_tools import read_scenes

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
CASE1 = CONFIGS / "case1.toml"
KILL_AFTER_SIM_S = 2.0
DT_S = 0.02  # Case 1's step
CASE1_DURATION_S = 30.0  # Case 1's mission
DURABILITY_S = 1.0  # what the issue allows to be lost before a kill -9


def assert_same_record(ours: RunRecord, theirs: RunRecord, skip: tuple[str, ...] = ()) -> None:
    """Every array equal bit for bit (NaN where both have NaN); wall time aside."""
    assert ours.config == theirs.config and ours.seed == theirs.seed
    for field in dataclasses.fields(RunRecord):
        if field.name in skip:
            continue
        a, b = getattr(ours, field.name), getattr(theirs, field.name)
        if isinstance(a, np.ndarray):
            assert a.shape == b.shape, field.name
            assert a.dtype == b.dtype, field.name
            assert np.array_equal(a, b, equal_nan=True), field.name


# -- config and metadata --------------------------------------------------------------------


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
    # (a recording once said "unknown" from a checkout: the package dir was taken one level
    # too deep after recording.py moved into swarm/observe/).
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--show-toplevel", "HEAD"],
                          capture_output=True, text=True, check=False) \
        if shutil.which("git") else None
    lines = head.stdout.split() if head is not None and head.returncode == 0 else []
    at_top = len(lines) == 2 and Path(lines[0]).resolve() == ROOT.resolve()
    assert git_commit() == (lines[1] if at_top else "unknown")
    assert git_commit(tmp_path / "pkg") == "unknown"  # not a checkout
    monkeypatch.setenv("PATH", str(tmp_path))  # no git at all
    assert git_commit() == "unknown"


# -- message conversions --------------------------------------------------------------------

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


# -- the recorder on its own ----------------------------------------------------------------


def small_metadata() -> RecordingMetadata:
    return RecordingMetadata.for_run(load_config(CASE1).with_duration(2.0), 0, "inprocess",
                                     "unit")


def poll(condition, timeout_s: float, what: str, period_s: float = 0.02,
         on_timeout=lambda: "") -> Any:
    """The condition's first truthy value (a RecordingError counts as not yet); fails at the
    deadline, with ``on_timeout()`` in the message."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            value = condition()
        except RecordingError:
            value = None
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what} {on_timeout()}")
        time.sleep(period_s)


def test_the_recorder_flushes_on_its_own_while_nothing_arrives(tmp_path: Path) -> None:
    beacon = BeaconWire.build(0, 3, 0.06, [1.0, 2.0, 3.0])
    with Recorder(tmp_path, small_metadata(), flush_period_s=0.1) as recorder:
        recorder.put(beacon, received_ns=123)
        found = poll(lambda: list(iter_messages(tmp_path)), 5.0, "the beacon on disk")
        still_open = read_recording(tmp_path)
    assert [(m.topic, m.log_time_ns, m.publish_time_ns, m.message) for m in found] == [
        ("agent/0/beacon", 60_000_000, 123, beacon)]
    assert still_open.truncated
    done = read_recording(tmp_path / RECORDING_FILE)
    assert not done.truncated and done.message_counts["agent/0/beacon"] == 1
    assert done.record.n_steps == 0  # no truth: an empty record, not an error


def test_puts_from_many_threads_are_all_written(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path, small_metadata())

    def send(drone: int) -> None:
        for step in range(300):
            recorder.put(BeaconWire.build(drone, step, step * 0.02, [drone, step, 1.0]))

    threads = [threading.Thread(target=send, args=(i,)) for i in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    recorder.close()
    recorder.close()  # idempotent
    recorder.put(BeaconWire.build(0, 0, 0.0, [0.0, 0.0, 0.0]))  # after close: counted, no error
    assert (recorder.written, recorder.dropped, recorder.error) == (1800, 1, None)
    counts = read_recording(tmp_path).message_counts
    assert [counts[f"agent/{i}/beacon"] for i in range(6)] == [300] * 6


# -- whole runs ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def inprocess_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunRecord, Path]:
    config = load_config(CASE1).with_duration(3.0)
    directory = tmp_path_factory.mktemp("inprocess")
    return record_reference(config, 3, directory), directory


def test_inprocess_recording_reads_back_as_the_reference_record(
        inprocess_recording: tuple[RunRecord, Path]) -> None:
    record, directory = inprocess_recording
    # Recording changes nothing but the timings.
    assert_same_record(record, run_reference(record.config, seed=3), skip=("step_us",))
    recording = read_recording(directory)
    assert_same_record(recording.record, record)
    meta = recording.metadata
    assert (meta.config, meta.seed, meta.mode) == (record.config, 3, "inprocess")
    assert (meta.version, meta.git_commit) == (package_version(), git_commit())
    assert not recording.truncated and recording.missing_samples == 0
    assert set(recording.message_counts.values()) == {150}
    assert len(recording.message_counts) == 1 + 3 * 6  # truth + telemetry, beacon, camera
    assert {c.steps for c in recording.drone_counters.values()} == {150}
    assert recording.sim_time_s == pytest.approx(149 * 0.02)


def test_inprocess_camera_and_beacon_channels_hold_what_the_agents_saw(
        inprocess_recording: tuple[RunRecord, Path]) -> None:
    record, directory = inprocess_recording
    beacons = [m for m in iter_messages(directory, kinds=("beacon",)) if m.drone == 2]
    assert [m.message.step for m in beacons] == list(range(150))
    np.testing.assert_allclose([m.message.position_m for m in beacons],
                               record.drone_positions_m[:, 2], atol=1e-5)  # float32 link
    frames = [m.message for m in iter_messages(directory, kinds=("camera",))]
    detected = np.zeros_like(record.detected)
    for frame in frames:
        for d in frame.detections:
            detected[frame.step, frame.drone, d.target] = True
    assert np.array_equal(detected, record.detected)


def test_lockstep_recording_reads_back_as_the_launchers_record(tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(3.0)
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CASE1), seed=0,
                                           record_dir=tmp_path / "rec"), log=lambda _l: None)
    record = launcher.run()
    recording = read_recording(tmp_path / "rec")
    assert_same_record(recording.record, record)
    assert recording.record.n_steps == config.n_steps
    meta = recording.metadata
    assert (meta.mode, meta.run_id, meta.seed, meta.config) == ("lockstep", launcher.run_id,
                                                                 0, config)
    assert not recording.truncated
    assert set(recording.message_counts.values()) == {config.n_steps}  # nothing lost
    assert recording.drone_counters == launcher.collector.drone_counters()
    # The 3D scene of every tenth of a second (10 Hz), from the process swarm's messages.
    scenes = read_scenes(tmp_path / "rec")
    assert [t for t, *_ in scenes] == [k * 20_000_000 for k in range(0, config.n_steps, 5)]


def test_the_cli_records_the_resolved_config_and_refuses_a_file_as_dir(tmp_path: Path) -> None:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    command = [sys.executable, "-m", "swarm.launch.cli", str(CASE1), "--inprocess", "--headless",
               "--duration", "1.5", "--seed", "5"]
    done = subprocess.run([*command, "--record", str(tmp_path / "a" / "b")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    meta = read_recording(tmp_path / "a" / "b").metadata
    assert (meta.config.scenario.duration_s, meta.seed, meta.mode) == (1.5, 5, "inprocess")
    (tmp_path / "file").write_text("x")
    bad = subprocess.run([*command, "--record", str(tmp_path / "file")], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1 and "not a directory" in bad.stderr


# -- crashes --------------------------------------------------------------------------------


def processes_of(run_id: str) -> list[int]:
    """Live pids whose command line carries this run id (zombies count as gone)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if run_id.encode() in argv and state != "Z":
            pids.append(int(entry.name))
    return pids


def describe(pids: list[int]) -> str:
    """Command line and state of each pid, for a failure message."""
    lines = []
    for pid in pids:
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        lines.append(f"{pid} [{state}] {argv[:120]}")
    return "; ".join(lines)


@contextlib.contextmanager
def recording_launcher(tmp_path: Path, run_id: str):
    """A realtime Case 1 launch-swarm recording to ``tmp_path/rec``, yielded as
    (process, recording directory, output file) once the steps of KILL_AFTER_SIM_S are on
    disk (the record's steps, which the world's truth makes: the newest message's sim time
    can be the agents' telemetry, ahead of a world running late — a SIGTERM then found 99
    steps of truth on disk with telemetry at 2.62 s); afterwards nothing of the run is left
    running."""
    directory = tmp_path / "rec"
    output = tmp_path / "launcher.log"
    with output.open("wb") as sink:
        process = subprocess.Popen(
            [sys.executable, "-m", "swarm.launch.cli", str(CASE1), "--mode", "realtime",
             "--headless",
             "--record", str(directory), "--run-id", run_id, "--log-dir", str(tmp_path / "logs")],
            cwd=ROOT, stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        # Reading the whole file costs CPU the swarm needs: a few reads a second suffice.
        poll(lambda: read_recording(directory).record.n_steps >= KILL_AFTER_SIM_S / DT_S
             or process.poll() is not None, 90.0, f"{KILL_AFTER_SIM_S} s of steps on disk",
             period_s=0.25)
        assert process.poll() is None, f"the launcher ended early:\n{output.read_text()}"
        yield process, directory, output
    finally:
        if process.poll() is None:
            process.kill()
        for pid in processes_of(run_id):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.wallclock
@pytest.mark.parametrize("signum", [signal.SIGKILL, signal.SIGTERM], ids=["kill-9", "sigterm"])
def test_a_stopped_launcher_leaves_a_readable_recording(tmp_path: Path, signum: int) -> None:
    """kill -9: the file is cut short but holds everything up to at most 1 s before the kill.
    SIGTERM: the launcher finishes the file (summary, footer) on its way out."""
    run_id = f"rec{signum}x{os.getpid()}"
    with recording_launcher(tmp_path, run_id) as (process, directory, _output):
        assert len(processes_of(run_id)) == 8  # launcher, world, six agents
        sent_ns = time.time_ns()
        process.send_signal(signum)
        code = process.wait(timeout=10)
        recording = read_recording(directory)
        assert recording.last_publish_time_ns >= sent_ns - DURABILITY_S * 1e9, (
            f"newest message {(sent_ns - recording.last_publish_time_ns) / 1e9:.2f} s "
            "before the signal")
        assert recording.record.n_steps >= KILL_AFTER_SIM_S / DT_S
        assert recording.metadata.mode == "realtime"
        if signum == signal.SIGKILL:
            assert recording.truncated
        else:
            assert (code, recording.truncated) == (130, False)
        # Cut short either way: swarm-report never says OK of it (issue 41, point 2).
        result = subprocess.run([sys.executable, "-m", "swarm.observe.report_cli",
                                 str(directory), "--json"], cwd=ROOT, capture_output=True,
                                text=True, timeout=120, check=False)
        document = json.loads(result.stdout)
        planned = round(CASE1_DURATION_S / DT_S)
        assert (document["complete"], document["planned_steps"]) == (False, planned)
        assert document["steps"] == recording.record.n_steps < planned
        assert (document["verdict"], result.returncode) in {("incomplete", 4),
                                                            ("violated", 1)}, result.stderr
        poll(lambda: not processes_of(run_id), 5.0, "every child of the launcher gone:",
             on_timeout=lambda: describe(processes_of(run_id)))


@pytest.mark.wallclock
def test_a_killed_world_ends_the_mission_with_a_complete_recording(tmp_path: Path) -> None:
    """kill -9 of the world in the middle of a realtime run: the launcher says so (exit 1,
    the world's signal), finishes the file (not truncated), with the messages up to the kill
    in it, and leaves no process behind."""
    run_id = f"recworld{os.getpid()}"
    with recording_launcher(tmp_path, run_id) as (process, directory, output):
        world = next(pid for pid in processes_of(run_id)
                     if b"sim_world.cli" in Path(f"/proc/{pid}/cmdline").read_bytes())
        killed_ns = time.time_ns()
        os.kill(world, signal.SIGKILL)
        code = process.wait(timeout=20)
        text = output.read_text()
        assert code == 1, text
        assert "world" in text and "signal 9" in text, text
        recording = read_recording(directory)
        assert not recording.truncated  # the launcher closed the file properly
        assert recording.record.n_steps >= KILL_AFTER_SIM_S / DT_S
        assert recording.last_publish_time_ns >= killed_ns - DURABILITY_S * 1e9
        poll(lambda: not processes_of(run_id), 5.0, "every child of the launcher gone:",
             on_timeout=lambda: describe(processes_of(run_id)))


def test_a_file_cut_anywhere_reads_up_to_the_cut(
        inprocess_recording: tuple[RunRecord, Path], tmp_path: Path) -> None:
    _, directory = inprocess_recording
    data = (directory / RECORDING_FILE).read_bytes()
    full = read_recording(directory)
    # Cut inside the data section: a cut in the summary after it loses no message (and is
    # not reported as truncated). The footer (29 bytes before the 8-byte closing magic)
    # holds summary_start; the 13-byte DataEnd record sits just before it.
    summary_start = int.from_bytes(data[-8 - 29 + 9:-8 - 29 + 17], "little")
    data_end = summary_start - 13
    assert data[data_end] == 0x0F  # DataEnd opcode
    totals = []
    for fraction in (0.3, 0.55, 0.8, 0.97):
        cut = tmp_path / f"cut{fraction}.mcap"
        cut.write_bytes(data[:int(data_end * fraction)])
        part = read_recording(cut)
        assert part.truncated
        totals.append(sum(part.message_counts.values()))
        steps = part.record.n_steps
        for name in ("drone_positions_m", "target_positions_m", "true_lambda_min"):
            assert np.array_equal(getattr(part.record, name), getattr(full.record, name)[:steps])
    assert totals == sorted(totals) and totals[0] < totals[-1] <= sum(full.message_counts.values())
    # Cut in the summary: every message is there, and the data section ended cleanly.
    summary_cut = tmp_path / "summary_cut.mcap"
    summary_cut.write_bytes(data[:summary_start + (len(data) - summary_start) // 2])
    whole = read_recording(summary_cut)
    assert not whole.truncated and whole.message_counts == full.message_counts


def test_bad_inputs_give_one_line_recording_errors(tmp_path: Path) -> None:
    (tmp_path / "empty_dir").mkdir()
    (tmp_path / "garbage.mcap").write_bytes(b"this is not an mcap file at all" * 10)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with (tmp_path / "foreign.mcap").open("wb") as handle:  # valid MCAP, not ours
        writer = Writer(handle)
        writer.start()
        writer.add_metadata("other", {"a": "b"})
        writer.finish()
    cases = {
        tmp_path / "missing": "no such file or directory",
        tmp_path / "empty_dir": "no run.mcap in this directory",
        tmp_path / "garbage.mcap": "not an MCAP file",
        tmp_path / "empty.mcap": "empty",
        tmp_path / "foreign.mcap": "no Vigil metadata",
    }
    for path, message in cases.items():
        with pytest.raises(RecordingError) as caught:
            read_recording(path)
        text = str(caught.value)
        assert message in text and str(path) in text and "\n" not in text


# -- a full disk ------------------------------------------------------------------------------


@contextlib.contextmanager
def small_filesystem(where: Path, size: str):
    """A tmpfs of ``size`` mounted at ``where`` (root only: skipped elsewhere)."""
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({mounted.stderr.strip() or 'not root'})")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_full_disk_at_start_is_one_clear_error(tmp_path: Path) -> None:
    with small_filesystem(tmp_path / "fs", "16k") as fs:
        (fs / "filler").write_bytes(b"\0" * 16 * 1024)  # tmpfs rounds to pages: may not all fit
        with pytest.raises(RecordingError) as info:
            Recorder(fs / "run", small_metadata())
    message = str(info.value)
    assert "\n" not in message and str(fs / "run") in message
    assert "MB free" in message or "No space left" in message


def test_too_little_space_for_the_whole_run_is_refused_before_it_starts(
        tmp_path: Path) -> None:
    config = load_config(CONFIGS / "case2.toml")  # 50 s of 6 drones: several MB
    with small_filesystem(tmp_path / "fs", "1m") as fs:
        with pytest.raises(RecordingError, match=r"MB free, a 50 s run of 6 drones needs "
                                                 r"about \d+\.\d MB"):
            record_reference(config, 0, fs / "run")
        assert not (fs / "run" / "run.mcap").exists()  # refused before anything was written


def test_a_disk_that_fills_during_the_run_is_an_error_not_a_silent_gap(tmp_path: Path) -> None:
    """The recorder stops writing at the first failed write, the run finishes, and then the
    run fails with the count of messages that are not on disk."""
    config = load_config(CONFIGS / "case1.toml").with_duration(1.5)
    with small_filesystem(tmp_path / "fs", "4m") as fs:
        filled = []

        def fill_the_disk(step: int, *_args: Any) -> None:
            if step == 20 and not filled:
                with contextlib.suppress(OSError), (fs / "filler").open("wb") as handle:
                    while True:  # to the last byte
                        handle.write(b"\0" * 65536)
                filled.append(step)

        with pytest.raises(RecordingError, match=r"messages not written: write failed: .*No "
                                                 r"space left"):
            record_reference(config, 0, fs / "run", on_step=fill_the_disk)
        assert filled == [20]
