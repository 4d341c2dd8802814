"""``swarm-observe`` (swarm.observe.observe_cli): a swarm started elsewhere gets launch-swarm's
end-of-mission tables, verdict and recording (issue 41, point 7).

Against real swarms: one started by hand (sim-world and swarm-agent processes, as
docs/across_machines.md, "By hand on one host", runs them, on loopback), and one started by
``launch-swarm`` in realtime; and against stand-in worlds (a Zenoh router publishing the clock)
for how watching ends.
"""

from __future__ import annotations

import io
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from rich.console import Console

from swarm.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE
from swarm.launch.launcher import free_tcp_port, reserve_mavlink_base
from swarm.messages.wire import ClockWire
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.observe import observe_cli
from swarm.observe.observe_cli import ObserveError, observe_run, summarize
from swarm.observe.recording.reader import read_recording
from swarm.observe.run_observer import print_summary
from swarm.scenario.config import load_config
from tests.helpers.cli_tools import cli_env
from tests.helpers.netns_tools import OBSERVER_READY, Proc, spawn, stop
from tests.helpers.reference_tools import assert_matches_reference

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
PYTHON = sys.executable
OBSERVE = [PYTHON, "-m", "swarm.observe.observe_cli"]
SEED = 0


def wait_for_line(proc: Proc, pattern: str, others: list[Proc], timeout_s: float) -> str:
    """The first match of the regular expression ``pattern`` in ``proc``'s log; the test
    fails if any of the processes ends first or the time is up."""
    deadline = time.monotonic() + timeout_s
    while (match := re.search(pattern, proc.log())) is None:
        for p in [proc, *others]:
            if p.process.poll() is not None:
                pytest.fail(f"{p.name} ended with {p.process.returncode} before {proc.name} "
                            f"said {pattern!r}:\n    {p.tail()}")
        if time.monotonic() > deadline:
            pytest.fail(f"{proc.name} did not say {pattern!r} within {timeout_s} s:\n    "
                        f"{proc.tail()}")
        time.sleep(0.05)
    return match.group(0)


def summary_block(text: str) -> list[str]:
    """The end-of-mission tables and verdict in a command's output (from the target table's
    title to the verdict), without the line that gives the wall time."""
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if ": targets (ε =" in line)
    last = next(i for i, line in enumerate(lines) if line.startswith("verdict:"))
    return [line.rstrip() for line in lines[first:last + 1] if not line.startswith("mode ")]


# -- a real swarm ------------------------------------------------------------------------------


def test_a_swarm_started_by_hand_gets_the_tables_verdict_and_recording_of_launch_swarm(
        tmp_path: Path) -> None:
    """World and agents started by hand in lockstep, the observer before the agents: it sees
    the whole mission, prints what launch-swarm prints for that run and records what
    launch-swarm --record records (the run reproduces the in-process reference)."""
    duration_s = 4.0
    config = load_config(CASE1).with_duration(duration_s)
    n = config.swarm.n_drones
    run_id = f"observe{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    base, port_lock = reserve_mavlink_base(0, n)  # no launcher of another test takes them
    common = ["--run-id", run_id, "--mode", "lockstep", "--seed", str(SEED),
              "--duration", repr(duration_s)]
    procs: list[Proc] = []
    try:
        world = spawn("world", [PYTHON, "-m", "sim_world.cli", str(CASE1), *common,
                                "--listen", endpoint, "--mavlink-base", str(base)],
                      tmp_path, ROOT)
        procs.append(world)
        # No --mode: the world's clock says it.
        observer = spawn("observer", [*OBSERVE, str(CASE1), "--connect", endpoint,
                                      "--run-id", run_id, "--seed", str(SEED), "--duration",
                                      repr(duration_s), "--record", str(tmp_path / "rec")],
                         tmp_path, ROOT)
        procs.append(observer)
        wait_for_line(observer, re.escape(OBSERVER_READY), [world], timeout_s=60)
        procs += [spawn(f"agent{i}", [
            PYTHON, "-m", "swarm.agent.cli", "--id", str(i), "--config", str(CASE1), *common,
            "--connect", endpoint, "--mavlink", f"udpin:127.0.0.1:{base + i}"], tmp_path, ROOT)
            for i in range(n)]
        try:
            code = observer.process.wait(timeout=120)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the observer did not end:\n    {observer.tail()}\nworld:\n    "
                        f"{world.tail()}")
    finally:
        stop(procs)
        port_lock.close()
    out = observer.log()
    assert code == 0, out
    assert f"{OBSERVER_READY} {run_id} at {endpoint} (lockstep, world waiting)" in out
    assert re.search(r"^t= +\d+\.\d\ds  λ̄ min", out, re.MULTILINE), out  # headless dashboard

    recording = read_recording(tmp_path / "rec")
    assert not recording.truncated and recording.missing_samples == 0
    assert recording.metadata.mode == "lockstep" and recording.metadata.run_id == run_id
    assert recording.record.n_steps == config.n_steps
    assert_matches_reference(config, recording.record, SEED)
    # What launch-swarm prints at the end of this run (its print_summary, on the same record
    # and counters), line for line.
    expected = io.StringIO()
    code = print_summary(recording.record, Console(file=expected, width=140), "lockstep",
                         recording.drone_counters)
    assert code == 0
    assert summary_block(out) == summary_block(expected.getvalue())
    assert "verdict: OK" in summary_block(out)[-1]
    assert f"agent steps {n * config.n_steps} " in out  # launch-swarm's process counters


@pytest.mark.wallclock
def test_ctrl_c_prints_the_tables_of_the_steps_seen_and_exits_130(tmp_path: Path) -> None:
    """A launch-swarm run in realtime, watched from another process: Ctrl-C mid-mission stops
    the observer (not the swarm) with the tables of what it saw and a whole recording; an
    observer told the wrong mode stops in one line."""
    duration_s = 20.0
    run_id = f"observert{os.getpid()}"
    procs: list[Proc] = []
    try:
        launcher = spawn("launcher", [PYTHON, "-m", "swarm.launch.cli", str(CASE1), "--mode",
                                      "realtime", "--duration", repr(duration_s), "--headless",
                                      "--run-id", run_id, "--log-dir", str(tmp_path / "logs")],
                      tmp_path, ROOT)
        procs.append(launcher)
        endpoint = wait_for_line(launcher, r"tcp/127\.0\.0\.1:\d+", [], timeout_s=60)
        watch = [str(CASE1), "--connect", endpoint, "--run-id", run_id, "--duration",
                 repr(duration_s)]
        observer = spawn("observer", [*OBSERVE, *watch, "--record", str(tmp_path / "rec")],
                         tmp_path, ROOT)
        wrong = spawn("wrong", [*OBSERVE, *watch, "--mode", "lockstep"], tmp_path, ROOT)
        procs += [observer, wrong]
        wait_for_line(observer, r"(?m)^t=", [launcher], timeout_s=60)  # running, and shown
        observer.process.send_signal(signal.SIGINT)
        code = observer.process.wait(timeout=15)
        wrong_code = wrong.process.wait(timeout=30)
        assert launcher.process.poll() is None, launcher.tail()  # the swarm goes on
    finally:
        stop(procs)
    out = observer.log()
    assert code == EXIT_INTERRUPTED, out
    assert "(realtime, world " in out
    block = summary_block(out)
    assert block[0].startswith("case1: targets") and block[-1].startswith("verdict:")
    assert re.search(r"swarm-observe: interrupted at t = \d+\.\d\d s; the tables cover the "
                     r"steps seen \(the swarm goes on\)", out), out
    recording = read_recording(tmp_path / "rec")
    assert not recording.truncated  # closed on the way out
    assert recording.metadata.mode == "realtime"
    assert 0 < recording.record.n_steps < load_config(CASE1).with_duration(duration_s).n_steps
    assert wrong_code == EXIT_USAGE, wrong.log()
    assert wrong.log().splitlines()[-1] == (f"swarm-observe: run {run_id} runs in realtime, "
                                            f"not lockstep: give --mode realtime (or leave "
                                            f"--mode out)")


# -- stand-in worlds: how watching ends ---------------------------------------------------------


class StandInWorld:
    """A Zenoh router that publishes run ``run_id``'s clock every 20 ms (``state``), while
    ``publishing`` is set."""

    def __init__(self, run_id: str, state: str, detail: str = "") -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.config = load_config(CASE1).with_duration(2.0)
        self.keys = Keys(run_id)
        self.state, self.detail = state, detail
        self.publishing = threading.Event()
        self.publishing.set()
        self._done = threading.Event()
        self.session = open_session(zenoh_config(mode="router", listen=[self.endpoint]))
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        codec = self.config.wire_codec()
        while not self._done.wait(0.02):
            if self.publishing.is_set():
                self.session.put(self.keys.clock, codec.encode(ClockWire(
                    step=0, time_s=0.0, state=self.state, mode="realtime",
                    detail=self.detail)))

    def close(self) -> None:
        self._done.set()
        self._thread.join()
        self.session.close()


def test_an_aborted_mission_is_one_line_and_exit_code_1(
        capsys: pytest.CaptureFixture[str]) -> None:
    world = StandInWorld("abort", "aborted", "drones [3] not heard (no beacon) within 30.0 s")
    try:
        seen = observe_run([world.endpoint], "abort", world.config,
                           console=Console(file=io.StringIO()), silence_s=10.0)
    finally:
        world.close()
    assert (seen.ending, seen.mode) == ("aborted", "realtime")
    assert summarize(seen, Console(file=io.StringIO())) == EXIT_FAILED
    assert capsys.readouterr().err == ("swarm-observe: mission failed: the world aborted the "
                                       "mission: drones [3] not heard (no beacon) within "
                                       "30.0 s\n")


def test_a_world_that_falls_silent_ends_the_watch(capsys: pytest.CaptureFixture[str]) -> None:
    world = StandInWorld("silent", "running")
    console = Console(file=io.StringIO(), record=True)
    result: dict[str, observe_cli.Observation] = {}
    watcher = threading.Thread(target=lambda: result.update(seen=observe_run(
        [world.endpoint], "silent", world.config, console=console, silence_s=0.5)),
        daemon=True)
    try:
        watcher.start()
        deadline = time.monotonic() + 30.0
        while OBSERVER_READY not in console.export_text(clear=False):
            assert time.monotonic() < deadline and watcher.is_alive()
            time.sleep(0.02)
        world.publishing.clear()  # the world is gone; its router stays up
        watcher.join(timeout=30.0)
    finally:
        world.close()
    seen = result["seen"]
    assert (seen.ending, seen.detail) == ("silent", "no clock from the world for 0.5 s")
    assert summarize(seen, Console(file=io.StringIO())) == EXIT_FAILED
    assert capsys.readouterr().err == ("swarm-observe: mission failed: the world is gone: no "
                                       "clock from the world for 0.5 s\n")


def test_a_router_without_the_run_is_said_and_no_recording_is_begun(tmp_path: Path) -> None:
    world = StandInWorld("other", "waiting")  # a router serving another run
    try:
        with pytest.raises(ObserveError, match=r"^no clock of run 'mine' within 0.5 s: is the "
                                               r"run id right, and is its world running\?$"):
            observe_run([world.endpoint], "mine", world.config,
                        console=Console(file=io.StringIO()), silence_s=0.5,
                        record_dir=tmp_path / "rec")
    finally:
        world.close()
    assert not (tmp_path / "rec").exists()


def test_ctrl_c_before_the_mission_started_says_so_and_exits_130(
        capsys: pytest.CaptureFixture[str]) -> None:
    world = StandInWorld("early", "waiting")
    stopped = threading.Event()
    console = Console(file=io.StringIO(), record=True)
    result: dict[str, observe_cli.Observation] = {}
    watcher = threading.Thread(target=lambda: result.update(seen=observe_run(
        [world.endpoint], "early", world.config, console=console, stop=stopped)),
        daemon=True)
    try:
        watcher.start()
        deadline = time.monotonic() + 30.0
        while OBSERVER_READY not in console.export_text(clear=False):
            assert time.monotonic() < deadline and watcher.is_alive()
            time.sleep(0.02)
        stopped.set()  # what Ctrl-C does on the main thread
        watcher.join(timeout=30.0)
    finally:
        world.close()
    seen = result["seen"]
    assert seen.ending == "interrupted" and seen.record.n_steps == 0
    assert summarize(seen, Console(file=io.StringIO())) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "swarm-observe: interrupted before the mission started\n"


# -- the command line ------------------------------------------------------------------------------


@pytest.fixture
def own_signal_handlers() -> Iterator[None]:
    """``main`` turns SIGTERM and SIGINT into KeyboardInterrupt: not for the test process
    after the test."""
    saved = {signum: signal.getsignal(signum) for signum in (signal.SIGTERM, signal.SIGINT)}
    yield
    for signum, handler in saved.items():
        signal.signal(signum, handler)


@pytest.mark.usefixtures("own_signal_handlers")
def test_an_unreachable_router_is_one_line_and_exit_code_1(
        capsys: pytest.CaptureFixture[str]) -> None:
    nobody = f"tcp/127.0.0.1:{free_tcp_port()}"
    code = observe_cli.main([str(CASE1), "--connect", nobody, "--run-id", "x",
                             "--connect-timeout", "0.3"])
    err = capsys.readouterr().err
    assert code == EXIT_FAILED, err
    assert len(err.splitlines()) == 1 and err.startswith("swarm-observe: ") and nobody in err


@pytest.mark.parametrize(("args", "says"), [
    (["--run-id", "x"], "the following arguments are required: --connect"),
    (["--connect", "tcp/127.0.0.1:7447", "--run-id", "a b"],
     "argument --run-id: must be 1-64 characters"),
    (["--connect", "tls/127.0.0.1:7447"], "tls needs certificates"),
    (["--connect", "tcp/127.0.0.1:7447", "--mode", "fast"], "argument --mode: invalid choice"),
])
def test_bad_command_lines_are_one_line_and_exit_code_2(args: list[str], says: str) -> None:
    """Through the installed console script, as a user types it."""
    script = Path(PYTHON).with_name("swarm-observe")
    result = subprocess.run([str(script), str(CASE1), *args], cwd=ROOT, env=cli_env(),
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == EXIT_USAGE, result
    assert len(result.stderr.splitlines()) == 1 and says in result.stderr, result.stderr
    assert result.stderr.startswith("swarm-observe: ") and result.stdout == ""


@pytest.mark.usefixtures("own_signal_handlers")
def test_a_config_that_cannot_be_read_is_one_line_and_exit_code_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = observe_cli.main([str(tmp_path / "none.toml"), "--connect", "tcp/127.0.0.1:7447"])
    err = capsys.readouterr().err
    assert code == EXIT_USAGE
    assert len(err.splitlines()) == 1 and err.startswith("swarm-observe: config error: ")
