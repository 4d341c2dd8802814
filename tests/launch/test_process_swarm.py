"""The process swarm: real world and agent processes, real Zenoh sessions, real MAVLink/UDP.

- lockstep runs reproduce the in-process reference bit for bit (issue 3, point 5);
- two swarms at once never see each other (point 7);
- SIGTERM / SIGINT stop every child within 5 s and free every port; a dying child is
  reported with its exit code and last log lines (point 4).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from swarm.agent.exchange import LOCKSTEP_TELEMETRY_STEPS
from swarm.launch import launcher as launcher_module
from swarm.launch.launcher import Child, LaunchOptions, SwarmLauncher, choose_mavlink_base
from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config, write_resolved_config
from tests.helpers.process_tools import free_udp_block
from tests.helpers.reference_tools import (
    assert_matches_reference,
)

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
LAUNCH = [sys.executable, "-m", "swarm.launch.cli"]


def lockstep_record(case: str, duration_s: float, seed: int, **options):
    config = load_config(CONFIGS / f"{case}.toml").with_duration(duration_s)
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(CONFIGS / f"{case}.toml"), seed=seed, **options),
        log=lambda _line: None)
    return config, launcher.run()




@pytest.mark.slow
@pytest.mark.parametrize(("case", "duration_s", "response"),
                         [("case1", 20.0, "arducopter"), ("case2", 10.0, "ideal")])
def test_lockstep_process_swarm_reproduces_the_in_process_reference(
        case: str, duration_s: float, response: str, tmp_path: Path) -> None:
    """Case 1 for 20 s (the barrier QP is active from ~14 s) on vehicles that lag as the fitted
    ArduCopter does ([vehicles] response = "arducopter": τ = 0.57 s, a_max = 1.65 m/s², in
    the world's emulated autopilots and in the reference alike), and Case 2 for 10 s on the
    thesis' ideal vehicles: bit for bit either way."""
    base = load_config(CONFIGS / f"{case}.toml").with_duration(duration_s)
    config = dataclasses.replace(base, vehicles=dataclasses.replace(base.vehicles,
                                                                    response=response))
    path = write_resolved_config(config, tmp_path / f"{case}_{response}.json")
    record = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0),
                           log=lambda _line: None).run()
    assert record.n_steps == config.n_steps
    assert_matches_reference(config, record, seed=0)
    assert check_invariants(record) == []
    if response != "ideal":  # the response does change the flight
        ideal = run_reference(base, seed=0)
        assert np.max(np.abs(record.drone_positions_m - ideal.drone_positions_m)) > 1e-3


@pytest.mark.slow
def test_two_swarms_at_once_never_see_each_other() -> None:
    """Different run ids, ports and seeds, started together: each still reproduces its own
    reference exactly, which any crossed message (consensus, beacon, camera) would break.
    153 steps: the agents' telemetry goes in batches of ``LOCKSTEP_TELEMETRY_STEPS`` (10), so
    the last 3 steps' are sent as the agents end; a step's telemetry lost would show as NaN."""
    assert 153 % LOCKSTEP_TELEMETRY_STEPS != 0  # a batch is left to send at the end
    results: dict[int, tuple] = {}
    errors: list[BaseException] = []
    # Two blocks drawn at random below the ephemeral range: the default block (24540) may be
    # reserved by a launch of the other xdist worker between a choice and this launch.
    first_base, second_base = free_udp_block(6), free_udp_block(6)
    while abs(second_base - first_base) < 6:
        second_base = free_udp_block(6)

    def run(seed: int, base: int) -> None:
        try:
            results[seed] = lockstep_record("case2", 3.06, seed=seed, mavlink_base=base,
                                            run_id=f"iso{seed}")
        except BaseException as err:  # reported below
            errors.append(err)

    threads = [threading.Thread(target=run, args=(1, first_base)),
               threading.Thread(target=run, args=(2, second_base))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=240)
    assert not errors, errors
    for seed, (config, record) in results.items():
        assert_matches_reference(config, record, seed)
    assert not np.array_equal(results[1][1].drone_positions_m, results[2][1].drone_positions_m)


# -- stopping and supervision ---------------------------------------------------------------


def processes_of(run_id: str) -> list[int]:
    """Pids whose command line carries this run id (our children pass --run-id)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if run_id.encode() in argv and int(entry.name) != os.getpid():
            pids.append(int(entry.name))
    return pids


def start_launcher(run_id: str, *extra: str) -> tuple[subprocess.Popen, list[str]]:
    """launch-swarm in the background; returns it once every drone is armed and streaming."""
    process = subprocess.Popen(
        [*LAUNCH, str(CONFIGS / "case1.toml"), "--headless", "--run-id", run_id, *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        cwd=ROOT)
    lines: list[str] = []
    deadline = time.monotonic() + 90
    assert process.stdout is not None
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            break
        lines.append(line)
        if "mission running" in line:
            return process, lines
    process.kill()
    pytest.fail(f"the swarm never started: {''.join(lines)}")


def ports_from(lines: list[str]) -> tuple[int, list[int]]:
    header = next(line for line in lines if "zenoh tcp/" in line)
    zenoh_port = int(re.search(r"zenoh tcp/127\.0\.0\.1:(\d+)", header).group(1))
    first, last = map(int, re.search(r"MAVLink (\d+)\.\.(\d+)", header).groups())
    return zenoh_port, list(range(first, last + 1))


@contextlib.contextmanager
def no_other_launcher_on(base: int, timeout_s: float = 120.0) -> Iterator[None]:
    """Hold the launchers' lock on the MAVLink block from ``base`` (``mavlink_lock_path``).

    Once our launcher has stopped, a launcher of another test (the CPU-bound xdist worker
    runs swarms too) may take the freed block at once and bind its ports: found by a CI run.
    Launchers skip a locked block, so while this lock is held a bound port can only be ours.
    Waits for a launcher that holds the block to finish its mission."""
    with open(launcher_module.mavlink_lock_path(base), "ab") as handle:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    pytest.fail(f"the MAVLink block from {base} stayed reserved for "
                                f"{timeout_s:g} s")
                time.sleep(0.1)  # another test's swarm flies on these ports: wait for it
        yield


def assert_ports_free(zenoh_port: int, udp_ports: list[int]) -> None:
    """Nobody listens on the router port and nobody holds the MAVLink ports. (SO_REUSEADDR
    lets the bind ignore connections in TIME_WAIT, which the kernel keeps after any close,
    but it still fails while a socket listens on the port.)"""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
        tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        tcp.bind(("127.0.0.1", zenoh_port))
        tcp.listen()
    with no_other_launcher_on(udp_ports[0]):
        for port in udp_ports:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                udp.bind(("127.0.0.1", port))


@pytest.mark.wallclock
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_every_child_within_5_s_and_frees_every_port(signum: int) -> None:
    run_id = f"stop{signum}x{os.getpid()}"
    process, lines = start_launcher(run_id, "--mode", "realtime")
    try:
        children = [pid for pid in processes_of(run_id) if pid != process.pid]
        assert len(children) == 7, children  # world + 6 agents
        sent = time.monotonic()
        process.send_signal(signum)
        out, _ = process.communicate(timeout=10)
        elapsed = time.monotonic() - sent
        assert elapsed < 5.0, f"stopping took {elapsed:.2f} s"
        assert process.returncode == 130
        assert "interrupted" in out
        assert processes_of(run_id) == []
        assert_ports_free(*ports_from(lines))
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        for pid in processes_of(run_id):
            os.kill(pid, signal.SIGKILL)


def test_a_dying_agent_is_reported_with_exit_code_and_log_lines() -> None:
    run_id = f"death{os.getpid()}"
    process, _ = start_launcher(run_id)
    try:
        victim = next(pid for pid in processes_of(run_id) if pid != process.pid
                      and b"--id\x002\x00" in Path(f"/proc/{pid}/cmdline").read_bytes())
        os.kill(victim, signal.SIGKILL)
        out, _ = process.communicate(timeout=30)
        assert process.returncode == 1
        assert "agent2" in out and "signal 9" in out and "last lines" in out
        assert "drone 2: armed and streaming" in out  # the tail of its log is shown
        assert processes_of(run_id) == []
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        for pid in processes_of(run_id):
            os.kill(pid, signal.SIGKILL)


def test_a_clean_exit_waits_for_the_worlds_done_before_it_counts_as_a_failure(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An agent exits 0 only once it has seen "done", which may reach it before it reaches
    the launcher: exit 0 is not a failure while "done" may still arrive, nor after it did;
    exit 0 with no "done" within the grace period is, and so is any other exit code."""
    config = load_config(CONFIGS / "case1.toml")
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CONFIGS / "case1.toml"),
                                           seed=0, log_dir=tmp_path), log=lambda _line: None)
    state = ["running"]
    monkeypatch.setattr(launcher, "_mission_state", lambda: state[0])
    clean = subprocess.Popen([sys.executable, "-c", "pass"])
    clean.wait()
    launcher.children.append(Child("agent0", clean, tmp_path / "agent0.log"))
    assert launcher._dead_child() is None  # within the grace period
    state[0] = "done"
    assert launcher._dead_child() is None
    state[0] = "running"
    monkeypatch.setattr(launcher_module, "CLEAN_EXIT_GRACE_S", 0.0)
    assert launcher._dead_child() is launcher.children[0]  # "done" never came
    failed = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    failed.wait()
    launcher.children[:] = [Child("agent1", failed, tmp_path / "agent1.log")]
    monkeypatch.setattr(launcher_module, "CLEAN_EXIT_GRACE_S", 60.0)
    state[0] = "done"
    assert launcher._dead_child() is launcher.children[0]
    launcher.close()


def test_launchers_started_together_reserve_different_mavlink_blocks() -> None:
    """The ports are bound by the children only later: the reservation lock keeps a second
    launcher off a block the first one chose, and a requested base that is reserved is a
    clear error."""
    first_base, first_lock = launcher_module.reserve_mavlink_base(0, 6)
    try:
        second_base, second_lock = launcher_module.reserve_mavlink_base(0, 6)
        second_lock.close()
        assert second_base != first_base
        with pytest.raises(launcher_module.MissionError, match="reserved by another"):
            launcher_module.reserve_mavlink_base(first_base, 6)
    finally:
        first_lock.close()
    # Released, free again: shown on a block of its own, off the grid that launches without
    # a requested base search (a launch in a test on the other xdist worker may take the
    # first free grid block the moment this test releases it, and bind its ports).
    own = next(base for base in range(launcher_module.DEFAULT_MAVLINK_BASE + 70, 32768 - 6, 100)
               if launcher_module.udp_ports_free(base, 6))
    held, lock = launcher_module.reserve_mavlink_base(own, 6)
    try:
        assert held == own
        with pytest.raises(launcher_module.MissionError, match="reserved by another"):
            launcher_module.reserve_mavlink_base(own, 6)
    finally:
        lock.close()
    again, lock = launcher_module.reserve_mavlink_base(own, 6)
    lock.close()
    assert again == own


# -- command lines ---------------------------------------------------------------------------


@pytest.mark.parametrize("argv", [
    ["sim_world.cli", str(CONFIGS / "case1.toml"), "--mavlink-base", "70000"],
    ["sim_world.cli", str(CONFIGS / "case1.toml"), "--run-id", "bad/id"],
    ["sim_world.cli", str(ROOT / "tests" / "configs_invalid" / "nan_forgetting.toml")],
    ["swarm.agent.cli", "--id", "9", "--config", str(CONFIGS / "case1.toml")],
    ["swarm.agent.cli", "--id", "0"],
    ["swarm.agent.cli", "--id", "0", "--config", str(ROOT / "missing.toml")],
    # Fault injection is for realtime tests; in lockstep a lost message stalls everyone.
    ["swarm.agent.cli", "--id", "0", "--config", str(CONFIGS / "case1.toml"),
     "--drop-consensus", "0.1"],
    ["swarm.agent.cli", "--id", "0", "--config", str(CONFIGS / "case1.toml"), "--mode",
     "realtime", "--drop-consensus", "1"],
    ["swarm.agent.cli", "--id", "0", "--config", str(CONFIGS / "case1.toml"), "--mode",
     "realtime", "--delay-consensus", "-2"],
    ["swarm.launch.cli", str(CONFIGS / "case1.toml"), "--agent-restarts", "1"],
    ["swarm.launch.cli", str(CONFIGS / "case1.toml"), "--mode", "realtime",
     "--agent-restarts", "x"],
    ["swarm.launch.cli", str(CONFIGS / "case1.toml"), "--mode", "realtime", "--kill-agent", "1"],
    ["swarm.launch.cli", str(CONFIGS / "case1.toml"), "--mode", "realtime", "--kill-agent", "6@5"],
])
def test_process_command_lines_fail_in_one_line(argv: list[str]) -> None:
    result = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True,
                            timeout=60, cwd=ROOT)
    assert result.returncode == 2, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr + result.stdout


def test_an_agent_without_a_world_says_what_is_missing(tmp_path: Path) -> None:
    config = tmp_path / "impatient.toml"
    config.write_text((CONFIGS / "case1.toml").read_text().replace(
        "start_timeout_s = 60.0", "start_timeout_s = 2.0"))
    port = choose_mavlink_base(0, 1) + 7
    started = time.monotonic()
    result = subprocess.run(
        [sys.executable, "-m", "swarm.agent.cli", "--id", "0", "--config", str(config),
         "--mavlink", f"udpin:127.0.0.1:{port}", "--connect", "tcp/127.0.0.1:9",
         "--run-id", "lonely"],
        capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 1
    output = result.stdout + result.stderr
    assert "cannot reach the world's Zenoh router at tcp/127.0.0.1:9" in output
    assert "Traceback" not in output
    assert time.monotonic() - started < 30


@pytest.mark.wallclock
@pytest.mark.slow
def test_external_vehicles_fly_against_virtual_targets() -> None:
    """sim-world --vehicles external takes positions from beacons; a separate sim-vehicles
    process plays N real autopilots (realtime). The swarm still localizes the target."""
    config = load_config(CONFIGS / "case1.toml").with_duration(6.0)
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(CONFIGS / "case1.toml"), seed=0, mode="realtime",
        external_vehicles=True), log=lambda _line: None)
    record = launcher.run()
    assert {child.name for child in launcher.children} >= {"world", "vehicles", "agent0"}
    assert record.n_steps == config.n_steps
    assert check_invariants(record) == []
    assert record.position_errors()[-1].max() < 0.05  # lockstep: 0.01 m; realtime measured 0.019
    counts = launcher.collector.counters()
    assert counts["agent_steps"] >= 0.9 * config.n_steps * config.swarm.n_drones


def test_external_vehicles_need_realtime() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "sim_world.cli", str(CONFIGS / "case1.toml"), "--vehicles",
         "external"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert result.returncode == 2
    assert "--mode realtime" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.wallclock
def test_realtime_leaves_stale_neighbour_data_out_and_counts_it(tmp_path: Path) -> None:
    """With a stale timeout below one step, every neighbour message is too old by the time
    it is used: the agents leave them out of the consensus sums and count them."""
    config_path = tmp_path / "stale.toml"
    config_path.write_text((CONFIGS / "case1.toml").read_text().replace(
        "stale_timeout_s = 0.1", "stale_timeout_s = 0.0001"))
    config = load_config(config_path).with_duration(2.0)
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(config_path), seed=0, mode="realtime"),
        log=lambda _line: None)
    record = launcher.run()
    counts = launcher.collector.counters()
    assert counts["stale_neighbour_messages"] > 0.5 * counts["agent_steps"]
    assert counts["missing_neighbour_messages"] > 0
    assert np.all(np.isfinite(record.estimates))
