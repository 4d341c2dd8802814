"""A child of launch-swarm binds its life to the launcher's by itself (swarm.children): real
processes, the kernel's own answers (PR_GET_PDEATHSIG, the scheduling policy)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import swarm
from swarm.children import (
    PARENT_PID_VARIABLE,
    SCHED_BATCH_VARIABLE,
    child_environment,
    follow_parent,
)

# A child that follows its parent, then says what the kernel says of it, then waits.
REPORT = """
import ctypes, json, os, sys, time
from swarm.children import follow_parent
follow_parent("child")
signal_number = ctypes.c_int(0)
ctypes.CDLL("libc.so.6").prctl(2, ctypes.byref(signal_number))  # PR_GET_PDEATHSIG
print(json.dumps({"pid": os.getpid(), "deathsig": signal_number.value,
                  "policy": os.sched_getscheduler(0),
                  "env": sorted(k for k in os.environ if k.startswith("VIGIL_"))}), flush=True)
time.sleep(float(sys.argv[1]))
"""


def child(env: dict[str, str], wait_s: float = 0.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", REPORT, str(wait_s)], env=env,
                          capture_output=True, text=True, timeout=30)


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(") ")[1][0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("batch", [True, False])
def test_a_child_asks_for_sigkill_and_its_policy_and_passes_neither_on(batch: bool) -> None:
    env = child_environment(os.environ, parent_pid=os.getpid(), sched_batch=batch)
    done = child(env)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["deathsig"] == signal.SIGKILL
    assert report["policy"] == (os.SCHED_BATCH if batch else os.SCHED_OTHER)
    assert report["env"] == []  # nothing it starts inherits them


def test_a_process_started_by_hand_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    env = {k: v for k, v in os.environ.items()
           if k not in (PARENT_PID_VARIABLE, SCHED_BATCH_VARIABLE)}
    report = json.loads(child(env).stdout)
    assert report["deathsig"] == 0 and report["policy"] == os.SCHED_OTHER
    monkeypatch.delenv(PARENT_PID_VARIABLE, raising=False)
    follow_parent("test")  # in this very process: nothing happens


def test_a_child_whose_launcher_is_already_gone_exits_at_once() -> None:
    """The launcher died between the spawn and the child's request: the child has another
    parent by then, says so in one line and exits before doing anything else."""
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    done = child(child_environment(os.environ, parent_pid=gone.pid, sched_batch=False))
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.strip() == f"child: the launcher (pid {gone.pid}) is gone; exiting"


def test_a_malformed_parent_pid_is_one_line_and_an_exit() -> None:
    env = dict(os.environ, **{PARENT_PID_VARIABLE: "12x"})
    done = child(env)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr.strip() == f"child: {PARENT_PID_VARIABLE}='12x' is not a process id"


def test_a_child_dies_with_its_launcher_killed_by_sigkill() -> None:
    """A stand-in launcher spawns a child as launch-swarm does (no preexec_fn) and is killed
    with -9 once the child has followed it: the kernel kills the child."""
    launcher = subprocess.Popen(
        [sys.executable, "-c",
         "import os, subprocess, sys, time\n"
         "from swarm.children import child_environment\n"
         f"subprocess.Popen([sys.executable, '-c', {REPORT!r}, '60'],\n"
         "    env=child_environment(os.environ, parent_pid=os.getpid(), sched_batch=False))\n"
         "time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True)
    pid = None
    try:
        assert launcher.stdout is not None
        report = json.loads(launcher.stdout.readline())  # the child followed its launcher
        pid = report["pid"]
        assert alive(pid)
        launcher.kill()
        launcher.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not alive(pid), "the child outlived its launcher"
    finally:
        launcher.kill()
        if pid is not None and alive(pid):
            os.kill(pid, signal.SIGKILL)


def test_a_child_runs_the_launchers_code_whatever_its_working_directory(
        tmp_path: Path) -> None:
    """A launcher started in another checkout: ``python -m`` would import that directory's
    ``swarm`` in the child (here a decoy that says so), not the code the launcher runs."""
    decoy = tmp_path / "swarm"
    decoy.mkdir()
    (decoy / "__init__.py").write_text("raise SystemExit('the decoy swarm was imported')\n")
    (decoy / "errors.py").write_text("")
    probe = [sys.executable, "-m", "swarm.errors"]
    plain = subprocess.run(probe, cwd=tmp_path, env=dict(os.environ), capture_output=True,
                           text=True, timeout=60)
    assert "the decoy swarm was imported" in plain.stderr  # what the fix is for
    env = child_environment(os.environ, parent_pid=os.getpid(), sched_batch=False)
    where = subprocess.run([sys.executable, "-c", "import swarm; print(swarm.__file__)"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()) == Path(swarm.__file__).resolve()
    assert env["PYTHONSAFEPATH"] == "1"
    again = child_environment(env, parent_pid=os.getpid(), sched_batch=False)
    assert again["PYTHONPATH"] == env.get("PYTHONPATH")  # not prepended twice
