"""``launch-swarm`` as a user runs it: in a process with a non-interactive environment, or
through its ``main`` in this process (a fraction of a second instead of a process start;
tests that use it also check, on a sample, that a process answers the same)."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_INTERACTIVE = ("COLUMNS", "LINES", "FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE",
                "CLICOLOR_FORCE", "NO_COLOR")


def cli_env(**extra: str) -> dict[str, str]:
    """Environment of a non-interactive run (CI, logs): no forced width, colour or tty; one
    BLAS thread (faster start-up, same results); then ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in _INTERACTIVE}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return env | extra


def run_cli(*args: str, command: list[str] | None = None,
            timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """``python -m swarm.launch.cli ARGS`` (or ``command ARGS``) from the repository root."""
    command = command or [sys.executable, "-m", "swarm.launch.cli"]
    return subprocess.run([*command, *args], cwd=ROOT, env=cli_env(), capture_output=True,
                          text=True, timeout=timeout, check=False)


def launch_swarm_in_process(*args: str) -> subprocess.CompletedProcess[str]:
    """``launch-swarm ARGS`` through ``swarm.launch.cli.main`` in this process: its exit code
    and what it wrote; an exception escaping ``main`` fails the test that asked."""
    from swarm.launch import cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(args))
        except SystemExit as stop:  # argparse
            code = stop.code if isinstance(stop.code, int) else 2
    return subprocess.CompletedProcess(list(args), code, out.getvalue(), err.getvalue())
