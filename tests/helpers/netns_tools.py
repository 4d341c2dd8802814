"""Hosts for the multi-host test, on one machine: Linux network namespaces joined by veth links.

``NetnsLan`` builds a small LAN: the first namespace (the world's host) holds a bridge — the
LAN's switch — with the first address of the subnet, and every other namespace (the agents'
hosts) is linked to that bridge by a veth pair and has an address of its own::

        ns vigil-w-<tag>  (world)            ns vigil-a-<tag>          ns vigil-b-<tag>
        br0 10.77.0.1/24 ── vh0 ═══ veth ═══ eth0 10.77.0.2/24
                         └─ vh1 ═══ veth ══════════════════════════════ eth0 10.77.0.3/24

Each namespace has its own loopback, its own ports and sees only this LAN, like a separate
machine: nothing reaches the host's 127.0.0.1. Creating namespaces needs root or
CAP_NET_ADMIN (and the ``ip`` tool); ``NetnsUnavailable`` says why it could not.

``python -m tests.helpers.netns_tools observe ...`` is the package's ``swarm-observe``
(``swarm.observe.observe_cli``) under the options this helper always took: it watches, records
and judges a running swarm until the world says "done" (``--timeout S``: how long it keeps
trying the world's router).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from swarm.observe import observe_cli

NS_PATTERN = re.compile(r"^vigil-[a-z]-(\d+)(?:-\w+)?$")
PR_SET_PDEATHSIG = 1
STOP_GRACE_S = 4.0
OBSERVER_READY = f"{observe_cli.PROG}: {observe_cli.READY}"


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be created here; the message says why."""


def _ip(ip_command: str, *args: str, namespace: str | None = None) -> None:
    argv = [ip_command, *(["-n", namespace] if namespace else []), *args]
    result = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise NetnsUnavailable(f"`{' '.join(argv)}` failed: "
                               f"{(result.stderr or result.stdout).strip() or result.returncode}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale_namespaces(ip_command: str = "ip") -> list[str]:
    """Delete ``vigil-?-<pid>`` namespaces whose creating process is gone (a test killed
    with SIGKILL cannot run its ``finally``). Returns the names deleted."""
    if shutil.which(ip_command) is None:
        return []
    listing = subprocess.run([ip_command, "netns", "list"], capture_output=True, text=True,
                             timeout=30)
    deleted = []
    for line in listing.stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        match = NS_PATTERN.match(name)
        if match and not _pid_alive(int(match.group(1))):
            subprocess.run([ip_command, "netns", "del", name], capture_output=True, timeout=30)
            deleted.append(name)
    return deleted


@dataclass
class NetnsLan:
    """A world host and agent hosts on one /24 (see the module docstring)."""

    tag: str  # makes the namespace names unique: the creating process's pid first
    hosts: Sequence[str] = ("a", "b")  # one namespace per agent host
    subnet: str = "10.77.0"  # the namespaces are private: the same subnet in every run is fine
    ip_command: str = "ip"
    created: list[str] = field(default_factory=list)

    @property
    def world_ns(self) -> str:
        return f"vigil-w-{self.tag}"

    @property
    def world_ip(self) -> str:
        return f"{self.subnet}.1"

    def host_ns(self, host: str) -> str:
        return f"vigil-{host}-{self.tag}"

    def host_ip(self, host: str) -> str:
        return f"{self.subnet}.{2 + list(self.hosts).index(host)}"

    def create(self) -> NetnsLan:
        """Build the namespaces and links; NetnsUnavailable (after removing whatever was
        built) if this machine or user cannot."""
        if shutil.which(self.ip_command) is None:
            raise NetnsUnavailable(f"no `{self.ip_command}` command (iproute2) on PATH")
        sweep_stale_namespaces(self.ip_command)
        try:
            for name in (self.world_ns, *map(self.host_ns, self.hosts)):
                _ip(self.ip_command, "netns", "add", name)
                self.created.append(name)
                _ip(self.ip_command, "link", "set", "lo", "up", namespace=name)
            w = self.world_ns
            _ip(self.ip_command, "link", "add", "br0", "type", "bridge", namespace=w)
            _ip(self.ip_command, "addr", "add", f"{self.world_ip}/24", "dev", "br0", namespace=w)
            _ip(self.ip_command, "link", "set", "br0", "up", namespace=w)
            for k, host in enumerate(self.hosts):
                ns = self.host_ns(host)
                # Both ends are created directly in their namespaces: no name is ever taken
                # in the caller's namespace, so concurrent runs cannot clash.
                _ip(self.ip_command, "link", "add", f"vh{k}", "netns", w, "type", "veth",
                    "peer", "name", "eth0", "netns", ns)
                _ip(self.ip_command, "link", "set", f"vh{k}", "master", "br0", "up",
                    namespace=w)
                _ip(self.ip_command, "addr", "add", f"{self.host_ip(host)}/24", "dev", "eth0",
                    namespace=ns)
                _ip(self.ip_command, "link", "set", "eth0", "up", namespace=ns)
        except BaseException:
            self.destroy()
            raise
        return self

    def argv(self, namespace: str, argv: Sequence[str]) -> list[str]:
        return [self.ip_command, "netns", "exec", namespace, *argv]

    def destroy(self) -> None:
        """Delete every namespace created (their veth links go with them); idempotent. Stop
        the processes inside first: a namespace lives on while a process is in it."""
        for name in reversed(self.created):
            subprocess.run([self.ip_command, "netns", "del", name], capture_output=True,
                           timeout=30)
        self.created.clear()

    def __enter__(self) -> NetnsLan:
        return self.create()

    def __exit__(self, *exc: object) -> None:
        self.destroy()


def _child_setup() -> None:
    """In the child before exec: die with the test (however it dies), and run as a batch
    thread as launch-swarm's lockstep children do."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))


@dataclass
class Proc:
    name: str
    process: subprocess.Popen
    log_path: Path

    def log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 15) -> str:
        return "\n    ".join(self.log().splitlines()[-lines:])


def spawn(name: str, argv: Sequence[str], log_dir: Path, cwd: Path) -> Proc:
    """Start ``argv`` in a session (process group) of its own, output to ``log_dir/name.log``."""
    log_path = log_dir / f"{name}.log"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(variable, "1")
    with log_path.open("wb") as handle:
        process = subprocess.Popen(list(argv), stdout=handle, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=True, env=env,
                                   cwd=cwd, preexec_fn=_child_setup)
    return Proc(name, process, log_path)


def stop(procs: Sequence[Proc]) -> None:
    """SIGTERM every process group, SIGKILL what is left after a grace period."""
    for proc in procs:
        if proc.process.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.process.pid, signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    for proc in procs:
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.process.wait(timeout=max(deadline - time.monotonic(), 0.01))
    for proc in procs:  # whatever is left, and any grandchild in the group
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.process.pid, signal.SIGKILL)
        proc.process.wait()


# -- the observer ----------------------------------------------------------------------------


def observe(argv: Sequence[str]) -> int:
    """``swarm-observe ARGV``, with ``--timeout S`` for its ``--connect-timeout S``."""
    args = ["--connect-timeout" if arg == "--timeout" else arg for arg in argv]
    return observe_cli.main(args)


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] != "observe":
        sys.exit("usage: python -m tests.helpers.netns_tools observe CONFIG --connect EP "
                 "--run-id ID "
                 "[--seed S] [--record DIR] [--mode M] [--duration S] [--timeout S]")
    sys.exit(observe(sys.argv[2:]))
