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
them. A process started by hand (no variables) is left alone. No imports from the rest of the
project but ``swarm.errors``: the agent calls this before its imports.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
from collections.abc import Mapping

from swarm.errors import EXIT_FAILED

PARENT_PID_VARIABLE = "VIGIL_PARENT_PID"
SCHED_BATCH_VARIABLE = "VIGIL_SCHED_BATCH"
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Ask the kernel for SIGKILL when the parent dies (``PR_SET_PDEATHSIG``; also the
    ``preexec_fn`` of the autopilot SITLs, which cannot ask for themselves)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def child_environment(base: Mapping[str, str], *, parent_pid: int,
                      sched_batch: bool) -> dict[str, str]:
    """``base`` plus what ``follow_parent`` reads in the child."""
    env = dict(base)
    env[PARENT_PID_VARIABLE] = str(parent_pid)
    env.pop(SCHED_BATCH_VARIABLE, None)
    if sched_batch:
        env[SCHED_BATCH_VARIABLE] = "1"
    return env


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
