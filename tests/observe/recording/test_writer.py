"""Writing recordings (swarm.observe.recording.writer): ``--record DIR`` writes ``DIR/run.mcap``
as the run goes.

- what is read back equals what the run returned, bit for bit (in-process and a real lockstep
  process swarm), and the metadata gives back the resolved config;
- a launcher killed with ``kill -9`` mid-run leaves a readable file holding everything up to
  at most 1 s before the kill, and no process behind;
- a disk too small or filling up is one clear error, never a silent gap.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.messages.wire import BeaconWire
from swarm.observe.recording.reader import iter_messages, read_recording
from swarm.observe.recording.schema import (
    RECORDING_FILE,
    RecordingError,
    RecordingMetadata,
    git_commit,
    package_version,
)
from swarm.observe.recording.writer import Recorder, record_reference
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from tests.helpers.scene_tools import read_scenes

ROOT = Path(__file__).resolve().parents[3]
CONFIGS = ROOT / "configs"
CASE1 = CONFIGS / "case1.toml"
KILL_AFTER_SIM_S = 2.0
DT_S = 0.02  # Case 1's step
CASE1_DURATION_S = 30.0  # Case 1's mission
DURABILITY_S = 1.0  # at most this much before a kill -9 may be lost


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


# -- the recorder on its own ---------------------------------------------------------------------


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


# -- whole runs ----------------------------------------------------------------------------------


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


# -- crashes -------------------------------------------------------------------------------------


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
        # Cut short either way: swarm-report never says OK of it.
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


# -- a full disk ---------------------------------------------------------------------------------


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
