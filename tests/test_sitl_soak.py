"""The soak script (benchmarks/sitl_soak.py, issue 14 point 6) run as a user runs it: one
short mission on ArduCopter SITL, its table and its JSON rows. The full figures (10 missions
per autopilot) are in the README; this keeps the script working."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.sitl_tools import firmware_or_skip, sitl_processes

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent


def test_one_soak_mission_on_arducopter_reports_its_figures(tmp_path: Path) -> None:
    firmware_or_skip("ardupilot")
    rows = tmp_path / "rows.json"
    done = subprocess.run(
        [sys.executable, "benchmarks/sitl_soak.py", "--autopilot", "ardupilot", "--runs", "1",
         "--duration", "8", "--json", str(rows), "--keep", str(tmp_path / "runs")],
        capture_output=True, text=True, cwd=ROOT, timeout=300)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    assert "ardupilot, tracked setpoints: 1 of 1 missions held every invariant" in out, out
    (row,) = json.loads(rows.read_text())
    assert row["ok"] and row["exit_code"] == 0 and row["autopilot"] == "ardupilot"
    assert row["min_lambda_margin"] >= -row["lambda_tolerance"]
    assert row["tracking_error_bound_m_s"] > 0 and row["command_accel_limit_m_s2"] > 0
    # The agents measured their vehicles against the command reference every step.
    assert 0.0 < row["velocity_error_rms_m_s"] < 0.5 and 0.0 < row["position_error_rms_m"] < 0.5
    assert row["steps"] == 3 * 400
    assert sitl_processes(containing=str(tmp_path)) == []
