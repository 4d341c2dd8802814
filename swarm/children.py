"""How a process started by ``launch-swarm`` ties its life to the launcher's.

The launcher starts the world and the agents with plain ``subprocess.Popen`` (no
``preexec_fn``), so Python spawns them with ``vfork``: ~0.3 ms per child instead of 6-8 ms for a
fork of the ~100 MB launcher, and on two busy cores (the agents already importing, in the
launcher's own scheduling group) the sixth agent used to start up to 0.3 s after the first.
What ``preexec_fn`` did in the child before ``exec`` each child now does for itself, first
thing (``follow_parent``), from two environment variables the launcher sets
(``child_environment``):

- ``VIGIL_PARENT_PID``: the child asks the kernel for SIGKILL when the launcher dies
  (``PR_SET_PDEATHSIG``), then checks that its parent is still that launcher: one that died
  before the request was made leaves the child to init, and the child exits at once. Either
  way no child outlives a launcher killed with ``kill -9``.
- ``VIGIL_SCHED_BATCH`` = 1 (lockstep): SCHED_BATCH for the process and every thread it starts
  (why: ``swarm.launch.launcher``).

Both variables are taken out of the child's environment, so nothing the child starts inherits
them. A process started by hand (no variables) is left alone. ``child_environment`` also
makes a Python child import the launcher's own code (``code_path``), wherever the launcher
was started. No imports from the rest of the project but ``swarm.errors``: the agent calls
this before its imports.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import site
import sys
from collections.abc import Mapping
from pathlib import Path

from swarm.errors import EXIT_FAILED

PARENT_PID_VARIABLE = "VIGIL_PARENT_PID"
SCHED_BATCH_VARIABLE = "VIGIL_SCHED_BATCH"
PR_SET_PDEATHSIG = 1
CODE_ROOT = Path(__file__).resolve().parents[1]  # holds swarm/ (and sim_world/ beside it)


def die_with_parent() -> None:
    """Ask the kernel for SIGKILL when the parent dies (``PR_SET_PDEATHSIG``; also the
    ``preexec_fn`` of the autopilot SITLs, which cannot ask for themselves)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def child_environment(base: Mapping[str, str], *, parent_pid: int,
                      sched_batch: bool) -> dict[str, str]:
    """``base`` plus what ``follow_parent`` reads in the child, and the path of the code
    the parent runs (``code_path``)."""
    env = dict(base)
    env[PARENT_PID_VARIABLE] = str(parent_pid)
    env.pop(SCHED_BATCH_VARIABLE, None)
    if sched_batch:
        env[SCHED_BATCH_VARIABLE] = "1"
    env.update(code_path(base))
    return env


def code_path(base: Mapping[str, str]) -> dict[str, str]:
    """The variables that make a Python child (``python -m swarm.agent.cli`` …) import the
    code this process runs. ``python -m`` puts the working directory first on the path, so a
    launcher started in another checkout (or anywhere a ``swarm/`` folder lies) gave its
    children that other code: side-by-side benchmark runs of two commits from one directory
    measured the same code twice. ``PYTHONSAFEPATH`` leaves the working directory out, and the
    directory that holds this package goes first on ``PYTHONPATH`` (unless it is a
    site-packages directory, where the child finds the installed package anyway, and which
    must not go before the standard library)."""
    root = str(CODE_ROOT)
    paths = [p for p in base.get("PYTHONPATH", "").split(os.pathsep) if p]
    installed = {*site.getsitepackages(), site.getusersitepackages()}
    if root not in installed and (not paths or paths[0] != root):
        paths = [root, *paths]
    out = {"PYTHONSAFEPATH": "1"}
    if paths:
        out["PYTHONPATH"] = os.pathsep.join(paths)
    return out


def follow_parent(prog: str) -> None:
    """In a child of the launcher: die with it, and run as SCHED_BATCH if asked (module
    docstring); exits (``EXIT_FAILED``) if the launcher is already gone. A malformed
    parent pid is one line on stderr and an exit, never a child left unbound."""
    parent = os.environ.pop(PARENT_PID_VARIABLE, None)
    batch = os.environ.pop(SCHED_BATCH_VARIABLE, None) == "1"
    if parent is None:
        return
    if not parent.isdigit():
        print(f"{prog}: {PARENT_PID_VARIABLE}={parent!r} is not a process id", file=sys.stderr)
        sys.exit(EXIT_FAILED)
    die_with_parent()
    if os.getppid() != int(parent):  # it died before the request: nobody would signal us
        print(f"{prog}: the launcher (pid {parent}) is gone; exiting", file=sys.stderr)
        sys.exit(EXIT_FAILED)
    if batch:
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
