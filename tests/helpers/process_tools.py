"""What the tests that start third-party MAVLink programs share: finding their console
scripts, a block of UDP ports nobody else will take, and MAVProxy as a relay on a link."""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from swarm.launch.launcher import udp_ports_free


def console_script(name: str, module: str) -> list[str]:
    """The console script ``name`` of this interpreter's environment, or ``python -m module``."""
    script = shutil.which(name, path=str(Path(sys.executable).parent))
    return [script] if script else [sys.executable, "-m", module]


def free_tcp_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS's pick)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_udp_block(count: int) -> int:
    """A base port p with UDP p..p+count-1 free on 127.0.0.1. Drawn at random below Linux's
    ephemeral range (32768+), so that no socket bound to port 0 later (the world's vehicle
    sockets, Zenoh, MAVSDK) can land in the block, and concurrent runs rarely pick the same."""
    rng = random.SystemRandom()
    for _ in range(500):
        base = rng.randrange(20000, 32768 - count)
        if udp_ports_free(base, count):
            return base
    raise RuntimeError("no free block of UDP ports on 127.0.0.1")


MAVPROXY_SYSTEM_ID = 255


@dataclass
class MavProxy:
    process: subprocess.Popen
    log_path: Path
    tlog_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def wait_for(self, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.log():
                return
            if self.process.poll() is not None:
                break
            time.sleep(0.05)
        raise AssertionError(f"MAVProxy never printed {text!r} (exit code "
                             f"{self.process.poll()}):\n{self.log()}")

    def stop(self) -> None:
        """SIGTERM the group (MAVProxy then unloads its modules and flushes its logs)."""
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(timeout=5)
        with contextlib.suppress(ProcessLookupError):  # anything left in the group
            os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait()


def start_mavproxy(master_port: int, out_port: int, state_dir: Path) -> MavProxy:
    state_dir.mkdir(parents=True, exist_ok=True)
    log_path, tlog_path = state_dir / "mavproxy.log", state_dir / "relay.tlog"
    argv = [*console_script("mavproxy.py", "MAVProxy.mavproxy"),
            f"--master=udpin:127.0.0.1:{master_port}",  # where vehicle 0 sends
            f"--out=udp:127.0.0.1:{out_port}",  # to agent 0, which listens (udpin) there
            "--non-interactive", "--default-modules=", "--streamrate=-1",
            f"--source-system={MAVPROXY_SYSTEM_ID}",
            f"--state-basedir={state_dir}", f"--logfile={tlog_path}",
            # The log writer thread otherwise flushes every 10 s only, and not at exit.
            "--cmd=set flushlogs True"]
    env = dict(os.environ, HOME=str(state_dir), PYTHONUNBUFFERED="1",
               MPLCONFIGDIR=str(state_dir / "mpl"))
    with log_path.open("wb") as out:
        process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=True,
                                   cwd=state_dir, env=env)
    return MavProxy(process, log_path, tlog_path)
