"""Repeated missions on real autopilot firmware (issue 14, point 6): pass rate, margins and
tracking errors per autopilot and setpoint kind, in one table.

    python benchmarks/sitl_soak.py [--autopilot ardupilot px4] [--runs 10]
        [--setpoints tracked velocity] [--config tests/configs/case1_three.toml]
        [--duration S] [--set control.tracking_error_bound_m_s=0.1 ...] [--json out.json]

Each run is the one command a user runs, ``launch-swarm CONFIG --mode realtime --sitl KIND
--headless --record DIR`` with seed = run index, on the SITL builds of ``../shared/
autopilots/`` (or ``$VIGIL_ARDUCOPTER`` / ``$VIGIL_PX4``). From each recording: the verdict
(every SPEC invariant with the config's tolerances), the smallest λ̄ − ε after control start,
the smallest pairwise distance, QP fallbacks and rate-box releases, reference resets, and the
vehicles' tracking errors the agents measured (‖v − u‖ of the velocity against the command
in effect, ‖p − r‖ against the command reference: RMS and 95th percentile over drones and
steps after control start). ``--keep DIR`` keeps each mission's recording, logs and
``launch-swarm.log`` (its output) in ``DIR/<autopilot>_<config>_<seed>/``. A run that fails
to fly (exit code 2 or 130, no recording) is
counted as failed with its reason. Runs one mission at a time: the SITL instances and the
agents need both cores.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from swarm.observe.recording import iter_messages, read_recording  # noqa: E402
from swarm.runs.checks import check_invariants, min_pairwise_distance, nanmin, start_index  # noqa: E402
from tests.helpers.sitl_tools import find_firmware  # noqa: E402

DEFAULT_CONFIG = ROOT / "tests" / "configs" / "case1_three.toml"


def parse_setting(text: str) -> tuple[str, str, object]:
    """``section.key=value`` (value as TOML) → (section, key, value)."""
    name, sep, raw = text.partition("=")
    section, dot, key = name.strip().partition(".")
    if not sep or not dot:
        raise argparse.ArgumentTypeError(f"--set {text!r}: expected section.key=value")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError as err:
        raise argparse.ArgumentTypeError(f"--set {text!r}: {err}") from None
    return section, key, value


def write_config(source: Path, setpoints: str, settings: list[tuple[str, str, object]],
                 directory: Path) -> Path:
    """The config as JSON (``load_config`` reads it like the TOML) with the overrides."""
    data = tomllib.loads(source.read_text())
    data.setdefault("vehicles", {})["setpoints"] = setpoints
    for section, key, value in settings:
        data.setdefault(section, {})[key] = value
    path = directory / f"{source.stem}_{setpoints}.json"
    path.write_text(json.dumps(data))
    return path


def _rms_p95(values: list[float]) -> tuple[float, float]:
    if not values:
        return math.nan, math.nan
    array = np.asarray(values)
    return float(np.sqrt(np.mean(array**2))), float(np.percentile(array, 95))


def measure(recording: Path) -> dict[str, object]:
    """Figures of one recorded mission."""
    rec = read_recording(recording, fill_gaps=True)
    record, config = rec.record, rec.config
    k0 = start_index(record)
    start_s = config.control.start_s
    velocity_errors: list[float] = []
    position_errors: list[float] = []
    last: dict[int, object] = {}
    for item in iter_messages(recording, ("telemetry",)):
        tel = item.message
        last[item.drone] = tel.counters
        if tel.time_s < start_s:
            continue
        if tel.counters.velocity_error_m_s is not None:
            velocity_errors.append(tel.counters.velocity_error_m_s)
        if tel.counters.tracking_error_m is not None:
            position_errors.append(tel.counters.tracking_error_m)
    velocity_rms, velocity_p95 = _rms_p95(velocity_errors)
    position_rms, position_p95 = _rms_p95(position_errors)
    violations = check_invariants(record)
    return {
        "ok": not violations,
        "violations": [f"{v.invariant}: {v.detail}" for v in violations],
        "min_lambda_margin": float(nanmin(record.lambda_bar[k0:]) - config.gramian.epsilon),
        "lambda_tolerance": config.checks.lambda_tolerance,
        "min_distance_m": float(min_pairwise_distance(record)),
        "qp_fallbacks": int(sum(c.qp_fallbacks for c in last.values())),
        "rate_limit_releases": int(sum(c.rate_limit_releases for c in last.values())),
        "reference_resets": int(sum(c.reference_resets for c in last.values())),
        "late_steps": int(sum(c.late_steps for c in last.values())),
        "steps": int(sum(c.steps for c in last.values())),
        "velocity_error_rms_m_s": velocity_rms, "velocity_error_p95_m_s": velocity_p95,
        "position_error_rms_m": position_rms, "position_error_p95_m": position_p95,
        "tracking_error_bound_m_s": config.control.tracking_error_bound_m_s,
        "command_accel_limit_m_s2": config.control.command_accel_limit_m_s2,
    }


def fly_and_measure(config: Path, out_dir: Path, options: list[str],
                    measure_recording: Callable[[Path], dict[str, object]],
                    result: dict[str, object]) -> dict[str, object]:
    """One ``launch-swarm CONFIG --mode realtime --headless --record out_dir/rec`` mission
    (``options`` added), its output kept in ``out_dir/launch-swarm.log``; ``result`` updated
    with its exit code, wall time and ``measure_recording``'s figures, or ok=False and why it
    did not fly (exit code 2 or 130, no recording) or could not be read."""
    argv = [sys.executable, "-m", "swarm.launch.cli", str(config), "--mode", "realtime",
            "--headless",
            "--record", str(out_dir / "rec"), "--log-dir", str(out_dir / "logs"), *options]
    started = time.monotonic()
    done = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=900)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "launch-swarm.log").write_text(done.stdout + done.stderr)
    result.update(exit_code=done.returncode, wall_s=round(time.monotonic() - started, 1))
    if "verdict:" not in done.stdout or not (out_dir / "rec").exists():
        tail = (done.stdout + done.stderr).strip().splitlines()[-3:]
        result.update(ok=False, failed=" | ".join(tail))
        return result
    try:
        result.update(measure_recording(out_dir / "rec"))
    except Exception as err:  # an unreadable recording is a failed run, not a crash
        result.update(ok=False, failed=f"recording unreadable: {err}")
    return result


def run_mission(config: Path, autopilot: str, firmware: Path, seed: int,
                duration: float | None, directory: Path) -> dict[str, object]:
    options = ["--sitl", str(firmware), "--seed", str(seed)]
    if duration is not None:
        options += ["--duration", str(duration)]
    return fly_and_measure(config, directory / f"{autopilot}_{config.stem}_{seed}", options,
                           measure, {"autopilot": autopilot, "seed": seed})


def _fmt(value: object, digits: int = 3) -> str:
    if isinstance(value, float):
        return "—" if math.isnan(value) else f"{value:+.{digits}f}" if digits == 4 \
            else f"{value:.{digits}f}"
    return str(value)


def print_table(results: list[dict[str, object]], console: Console) -> None:
    table = Table(title="missions on SITL firmware")
    for column in ("autopilot", "setpoints", "seed", "verdict", "min λ̄ − ε", "min dist [m]",
                   "fallbacks", "releases", "resets", "late %", "‖v − u‖ rms/p95",
                   "‖p − r‖ rms/p95"):
        table.add_column(column)
    for r in results:
        if "failed" in r:
            table.add_row(str(r["autopilot"]), str(r["setpoints"]), str(r["seed"]),
                          f"did not fly (exit {r['exit_code']}): {r['failed']}")
            continue
        late = 100.0 * int(r["late_steps"]) / max(int(r["steps"]), 1)
        table.add_row(
            str(r["autopilot"]), str(r["setpoints"]), str(r["seed"]),
            "OK" if r["ok"] else "; ".join(r["violations"])[:60],
            _fmt(r["min_lambda_margin"], 4), _fmt(r["min_distance_m"], 2),
            str(r["qp_fallbacks"]), str(r["rate_limit_releases"]), str(r["reference_resets"]),
            f"{late:.1f}",
            f"{_fmt(r['velocity_error_rms_m_s'])}/{_fmt(r['velocity_error_p95_m_s'])}",
            f"{_fmt(r['position_error_rms_m'])}/{_fmt(r['position_error_p95_m'])}")
    console.print(table)
    groups: dict[tuple[str, str], list[dict[str, object]]] = {}
    for r in results:
        groups.setdefault((str(r["autopilot"]), str(r["setpoints"])), []).append(r)
    for (autopilot, setpoints), runs in groups.items():
        passed = sum(1 for r in runs if r.get("ok"))
        margins = [float(r["min_lambda_margin"]) for r in runs if "min_lambda_margin" in r]
        worst = f"{min(margins):+.4f}" if margins else "—"
        console.print(f"{autopilot}, {setpoints} setpoints: {passed} of {len(runs)} missions "
                      f"held every invariant; worst min λ̄ − ε {worst}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--autopilot", nargs="+", default=["ardupilot", "px4"],
                        choices=("ardupilot", "px4"))
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--setpoints", nargs="+", default=["tracked"],
                        choices=("tracked", "velocity"))
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--duration", type=float, default=None)
    parser.add_argument("--set", dest="settings", type=parse_setting, action="append",
                        default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep recordings and logs here (default: a temporary directory)")
    args = parser.parse_args(argv)
    console = Console(width=170)
    builds = {}
    for autopilot in args.autopilot:
        builds[autopilot] = find_firmware(autopilot)
        if builds[autopilot] is None:
            console.print(f"sitl_soak: no {autopilot} SITL build (../shared/autopilots/ or "
                          f"$VIGIL_{'ARDUCOPTER' if autopilot == 'ardupilot' else 'PX4'})")
            return 2
    results: list[dict[str, object]] = []
    with tempfile.TemporaryDirectory(prefix="vigil-soak-") as scratch:
        directory = args.keep or Path(scratch)
        directory.mkdir(parents=True, exist_ok=True)
        for setpoints in args.setpoints:
            config = write_config(args.config, setpoints, args.settings, directory)
            for autopilot in args.autopilot:
                for seed in range(args.first_seed, args.first_seed + args.runs):
                    result = run_mission(config, autopilot, builds[autopilot].path, seed,
                                         args.duration, directory)
                    result["setpoints"] = setpoints
                    results.append(result)
                    console.print(f"{autopilot} {setpoints} seed {seed}: "
                                  + ("OK" if result.get("ok") else "FAILED")
                                  + f" min λ̄ − ε {result.get('min_lambda_margin', math.nan):+.4f}"
                                  + f" ({result['wall_s']} s)", highlight=False)
                    if args.json is not None:
                        args.json.write_text(json.dumps(results, indent=1))
    print_table(results, console)
    return 0 if all(r.get("ok") for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
