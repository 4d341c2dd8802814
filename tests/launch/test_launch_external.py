"""launch-swarm supervising agents that fly autopilots it did not start (issue 13, point 8).

A separate ``sim-vehicles`` process plays three autopilots (as SITL instances or real vehicles
started by someone else would); ``launch-swarm --mavlink I=URL`` starts the world (virtual
targets, no vehicles of its own) and one agent per drone on those URLs, supervises and
records them, and leaves the vehicles running. Every agent commands zero velocity and then
the config's end action when it leaves — at the end of the mission and on SIGTERM — and the
vehicle obeys (its mode changes: PX4 Hold). Real processes, Zenoh and MAVLink over UDP.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers.process_tools import console_script, free_udp_block

pytestmark = pytest.mark.wallclock

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "tests" / "configs" / "case1_three.toml"  # three px4 drones, end_action hold
N_DRONES = 3
LAUNCH = [sys.executable, "-m", "swarm.launch.cli"]


def _start_vehicles(base: int, log_path: Path) -> subprocess.Popen:
    log = log_path.open("w")
    process = subprocess.Popen(
        [*console_script("sim-vehicles", "sim_world.vehicles_cli"), str(CONFIG),
         "--mavlink-base", str(base)],
        stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT)
    log.close()
    deadline = time.monotonic() + 30.0
    while "vehicles sending to" not in log_path.read_text():
        assert process.poll() is None, log_path.read_text()
        assert time.monotonic() < deadline, "sim-vehicles never came up"
        time.sleep(0.05)  # polling its log for the start-up line
    return process


def _agent_logs(log_dir: Path) -> dict[int, str]:
    return {i: (log_dir / f"agent{i}.log").read_text(errors="replace")
            for i in range(N_DRONES)}


@pytest.mark.slow
@pytest.mark.parametrize("ending", ["mission end", "SIGTERM"])
def test_launch_swarm_supervises_and_records_agents_on_autopilots_it_did_not_start(
        ending: str, tmp_path: Path) -> None:
    base = free_udp_block(N_DRONES)
    vehicles = _start_vehicles(base, tmp_path / "vehicles.log")
    log_dir, record_dir = tmp_path / "logs", tmp_path / "record"
    urls = [arg for i in range(N_DRONES)
            for arg in ("--mavlink", f"{i}=udpin:127.0.0.1:{base + i}")]
    duration = "6" if ending == "mission end" else "60"
    run_id = f"ext{os.getpid()}{ending[0]}"
    launcher = subprocess.Popen(
        [*LAUNCH, str(CONFIG), "--mode", "realtime", "--headless", "--duration", duration,
         "--log-dir", str(log_dir), "--record", str(record_dir), "--run-id", run_id, *urls],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
        cwd=ROOT)
    try:
        lines: list[str] = []
        assert launcher.stdout is not None
        if ending == "SIGTERM":
            deadline = time.monotonic() + 90.0
            while time.monotonic() < deadline and not any("mission running" in line
                                                          for line in lines):
                line = launcher.stdout.readline()
                if not line:
                    break
                lines.append(line)
            assert any("mission running" in line for line in lines), "".join(lines)
            launcher.send_signal(signal.SIGTERM)
        out, _ = launcher.communicate(timeout=120)
        output = "".join(lines) + out
        assert launcher.returncode == (0 if ending == "mission end" else 130), output
        assert "Traceback" not in output
        logs = _agent_logs(log_dir)
        for i, text in logs.items():
            assert f"udpin:127.0.0.1:{base + i}" in text, text
            stop = text.index("mission over: zero velocity sent")
            assert f"drone {i}: end action hold (Hold) accepted" in text[stop:], text
        assert "launch-swarm: drones 0, 1, 2: end action hold (Hold) accepted" in output, output
        assert (record_dir / "run.mcap").stat().st_size > 0
        # Nothing the launcher started is left; the vehicles it did not start still run.
        assert vehicles.poll() is None
        leftover = subprocess.run(["pgrep", "-f", run_id], capture_output=True,
                                  text=True).stdout.split()
        assert leftover == [], leftover
    finally:
        if launcher.poll() is None:
            os.killpg(launcher.pid, signal.SIGKILL)
        os.killpg(vehicles.pid, signal.SIGTERM)
        vehicles.wait(timeout=10)
