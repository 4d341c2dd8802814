"""``swarm.observe.report`` and ``swarm-report``: figures checked against independent
computations on
short in-process runs, NaN (missing) samples, violated invariants, JSON keys, exit codes."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from swarm.messages.wire import TelemetryCounters
from swarm.observe.report import build_report, render_report, report_to_json
from swarm.runs.checks import check_invariants, start_index
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config

ROOT = Path(__file__).resolve().parents[2]

TOP_KEYS = {"scenario", "seed", "mode", "n_drones", "n_targets", "duration_s", "steps",
            "epsilon", "min_pairwise_distance_m", "max_abs_velocity_mps", "qp_fallbacks",
            "late_steps", "rejected_messages", "targets", "drones"}
TARGET_KEYS = {"id", "min_lambda_bar_margin", "time_below_epsilon_s", "min_true_lambda_margin",
               "min_measured_lambda", "final_position_error_m", "rms_position_error_m",
               "drones_sensing_final"}
DRONE_KEYS = {"id", "final_speed_mps", "final_weights", "idle_final", "mean_step_us",
              "p99_step_us", "final_bearing_error"}


def short_record(case: str, duration_s: float) -> RunRecord:
    config = load_config(ROOT / "configs" / f"{case}.toml").with_duration(duration_s)
    return run_reference(config)


@pytest.fixture(scope="module")
def case2() -> RunRecord:
    """Two targets, past control.start_s = 1 s so the QP runs."""
    return short_record("case2", 2.0)


@pytest.fixture(scope="module")
def case3() -> RunRecord:
    """One target and a bearing formation task."""
    return short_record("case3", 1.5)


def with_arrays(record: RunRecord, **arrays: np.ndarray) -> RunRecord:
    return dataclasses.replace(record, **arrays)


def lowered_lambda(record: RunRecord, value: float, step: int, drone: int,
                   target: int) -> RunRecord:
    lam = record.lambda_bar.copy()
    lam[step, drone, target] = value
    return with_arrays(record, lambda_bar=lam)


def json_roundtrip(report_dict: dict) -> dict:
    """What a consumer sees: strict JSON (a NaN would raise here)."""
    return json.loads(json.dumps(report_dict, allow_nan=False))


# -- figures against independent computations ----------------------------------------------


def test_target_figures_match_independent_computation(case2: RunRecord) -> None:
    report = build_report(case2)
    eps = case2.config.gramian.epsilon
    k0 = round(case2.config.control.start_s / case2.config.scenario.dt_s)
    errors = np.linalg.norm(case2.estimates[..., :3] - case2.target_positions_m[:, None],
                            axis=-1)
    assert len(report.targets) == 2
    for r, t in enumerate(report.targets):
        assert t.id == r
        assert t.min_lambda_bar_margin == pytest.approx(case2.lambda_bar[k0:, :, r].min() - eps)
        assert t.min_true_lambda_margin == pytest.approx(case2.true_lambda_min[k0:, r].min()
                                                         - eps)
        assert t.min_measured_lambda == pytest.approx(case2.measured_lambda_min[k0:, r].min())
        assert t.final_position_error_m == pytest.approx(errors[-1, :, r].max())
        assert t.rms_position_error_m == pytest.approx(np.sqrt(np.mean(errors[k0:, :, r]**2)))
        assert t.drones_sensing_final == int((case2.weights[-1, :, r] > 0.1).sum())
        assert t.missing_samples == 0


def test_time_below_epsilon_counts_steps_where_any_copy_is_below(case2: RunRecord) -> None:
    eps, dt = case2.config.gramian.epsilon, case2.config.scenario.dt_s
    k0 = start_index(case2)
    lam = case2.lambda_bar.copy()
    lam[k0 + 3, 1, 0] = eps - 1e-4  # three steps below ε, two of them at one step
    lam[k0 + 3, 4, 0] = eps - 2e-4
    lam[k0 + 7, 0, 0] = eps - 1e-4
    lam[k0 - 1, 0, 0] = eps - 1e-4  # before the QP starts: not counted
    report = build_report(with_arrays(case2, lambda_bar=lam))
    assert report.targets[0].time_below_epsilon_s == pytest.approx(2 * dt)
    assert report.targets[0].min_lambda_bar_margin == pytest.approx(-2e-4)
    assert report.targets[1].time_below_epsilon_s == 0.0
    assert report.ok  # 2e-4 is within the tolerance


def test_drones_sensing_final_counts_weights_above_one_tenth(case2: RunRecord) -> None:
    weights = case2.weights.copy()
    weights[-1, :, 0] = [0.05, 0.1, 0.11, 0.5, 1.0, 0.0]  # 0.1 itself is not "sensing"
    weights[-1, :, 1] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.2]
    report = build_report(with_arrays(case2, weights=weights))
    assert [t.drones_sensing_final for t in report.targets] == [3, 1]
    assert [d.idle_final for d in report.drones] == [True, True, False, False, False, False]
    assert report.drones[5].sensing_targets == (1,)
    assert report.drones[3].final_weights == (0.5, 0.0)


def test_drone_figures(case2: RunRecord) -> None:
    report = build_report(case2)
    for i, d in enumerate(report.drones):
        assert d.id == i
        assert d.final_speed_mps == pytest.approx(np.linalg.norm(case2.velocities_m_s[-1, i]))
        assert d.mean_step_us == pytest.approx(case2.step_us[:, i].mean())
        assert d.p99_step_us == pytest.approx(np.percentile(case2.step_us[:, i], 99))
        assert d.qp_fallbacks == int(case2.qp_fallback[:, i].sum())
        assert d.late_steps is None and d.rejected_messages is None  # in-process: not measured
    assert report.max_abs_velocity_mps == pytest.approx(np.abs(case2.velocities_m_s).max())
    assert report.min_pairwise_distance_m == pytest.approx(case2.min_pairwise_distance())
    assert report.steps == case2.n_steps == 100
    assert report.duration_s == pytest.approx(2.0)


def test_bearing_error_is_null_without_a_formation_task(case2: RunRecord,
                                                        case3: RunRecord) -> None:
    assert case2.config.control.task == "zero"
    assert all(d["final_bearing_error"] is None for d in report_to_json(build_report(case2))
               ["drones"])
    assert case3.config.control.task == "bearing_formation"
    drones = report_to_json(build_report(case3))["drones"]
    for i, d in enumerate(drones):
        assert d["final_bearing_error"] == pytest.approx(case3.bearing_errors[-1, i])
        assert d["final_bearing_error"] > 0.0


def test_counters_of_a_process_run_are_summed(case2: RunRecord) -> None:
    counters = {i: TelemetryCounters(qp_fallbacks=i, rejected_messages=2, late_steps=i % 2,
                                     steps=100) for i in range(6)}
    report = build_report(case2, "realtime", counters)
    assert report.mode == "realtime"
    assert report.late_steps == 3
    assert report.rejected_messages == 12
    assert report.qp_fallbacks == 15
    assert report.drones[5].late_steps == 1 and report.drones[5].steps_run == 100
    with pytest.raises(ValueError, match="mode"):
        build_report(case2, "bogus")


def test_drones_that_said_they_could_not_hold_a_target_are_named(case2: RunRecord) -> None:
    counters = {i: TelemetryCounters(steps=100) for i in range(6)}
    counters[4] = TelemetryCounters(steps=100, lambda_breaches=2, first_lambda_breach_s=21.54,
                                    localization_status="λ̄ < ε − tol: target 1 since 30.2 s")
    report = build_report(case2, "realtime", counters)
    said = [w for w in report.warnings if "could not hold" in w]
    assert said == ["drone 4: said it could not hold λ̄ ≥ ε − tol from t = 21.54 s (2 breach(es) "
                    "by target; the agent log has each); at the end: λ̄ < ε − tol: target 1 "
                    "since 30.2 s"]
    assert [d.lambda_breaches for d in report.drones] == [0, 0, 0, 0, 2, 0]
    assert report_to_json(report)["drones"][4]["first_lambda_breach_s"] == 21.54
    console = Console(record=True, width=250)
    render_report(report, console)
    assert "2 (from 21.54 s)" in console.export_text()
    assert build_report(case2).drones[4].lambda_breaches is None  # in-process: not measured


def test_the_tables_stay_readable_at_80_columns(case2: RunRecord) -> None:
    """A narrow console leaves columns out, the empty and the least wanted first, the events
    last, and says which (issue 41, point 6); a wide one shows them all."""
    counters = {i: TelemetryCounters(steps=100, late_steps=3, vehicle_events=1,
                                     vehicle_status="mode LOITER") for i in range(6)}
    report = build_report(case2, "realtime", counters)
    narrow = Console(record=True, width=80)
    render_report(report, narrow)
    text = narrow.export_text()
    tables = text[:text.index("(left out at 80 columns: ")]
    assert max(len(line.rstrip()) for line in tables.splitlines()) <= 80
    assert "1 (mode LOITER)" in tables and "vehicle" in tables and "state" in tables
    left_out = text[text.index("(left out at 80 columns: "):text.index("--json has")]
    assert "bearing err" in left_out and "step µs mean/p99" in left_out  # empty, then least
    assert "vehicle events" not in left_out and "λ̄ breaches" not in left_out
    wide = Console(record=True, width=250)
    render_report(report, wide)
    text = wide.export_text()
    assert "(left out at" not in text and "mean/p99" in text


# -- violated invariants -------------------------------------------------------------------


def test_lambda_below_epsilon_minus_tolerance_is_a_violation(case2: RunRecord) -> None:
    cfg = case2.config
    eps, tol = cfg.gramian.epsilon, cfg.checks.lambda_tolerance
    k = start_index(case2) + 10
    bad = lowered_lambda(case2, eps - tol - 1e-3, k, 4, 1)
    report = build_report(bad)
    assert not report.ok and report.exit_code == 1
    (violation,) = report.violations
    assert violation.invariant == "lambda_bar"
    assert "target 1: drone 4" in violation.detail
    assert f"t = {case2.times_s[k]:.2f} s" in violation.detail
    assert report.targets[1].min_lambda_bar_margin == pytest.approx(-tol - 1e-3)
    assert json_roundtrip(report_to_json(report))["verdict"] == "violated"
    # Exactly at the tolerance is not a violation.
    assert build_report(lowered_lambda(case2, eps - tol + 1e-9, k, 4, 1)).ok


def test_collision_and_velocity_bound_violations(case2: RunRecord) -> None:
    positions = case2.drone_positions_m.copy()
    positions[30, 2] = positions[30, 3] + [0.1, 0.0, 0.0]
    velocities = case2.velocities_m_s.copy()
    velocities[40, 0, 2] = -3.5
    report = build_report(with_arrays(case2, drone_positions_m=positions,
                                      velocities_m_s=velocities))
    assert {v.invariant for v in report.violations} == {"collision", "velocity_bound"}
    assert report.min_pairwise_distance_m == pytest.approx(0.1)
    assert report.max_abs_velocity_mps == pytest.approx(3.5)


def test_the_envelope_margins_and_conflicts_are_reported_and_a_crossing_is_a_violation(
        ) -> None:
    """configs/case2_envelope.toml for 2 s: the report holds the closest approach to each
    boundary (computed here from the positions) and the conflict count; a drone put 0.1 m
    above the ceiling at one step is an ``envelope`` violation, shown in the figures line."""
    record = short_record("case2_envelope", 2.0)
    safety = record.config.safety
    report = build_report(record)
    assert report.ok and report.safety_conflicts == 0
    z = record.drone_positions_m[..., 2]
    assert report.envelope_margins_m["ceiling"] == pytest.approx(safety.ceiling_m - z.max())
    assert report.envelope_margins_m["floor"] == pytest.approx(z.min() - safety.floor_m)
    y = record.drone_positions_m[..., 1]
    assert report.envelope_margins_m["fence"] == pytest.approx(
        min(safety.keep_in_box_m[3] - y.max(), y.min() - safety.keep_in_box_m[1],
            safety.keep_in_box_m[2] - record.drone_positions_m[..., 0].max(),
            record.drone_positions_m[..., 0].min() - safety.keep_in_box_m[0]))
    document = json_roundtrip(report_to_json(report))
    assert document["envelope_margins_m"].keys() == {"floor", "ceiling", "fence", "obstacle"}
    assert document["safety_conflicts"] == 0
    positions = record.drone_positions_m.copy()
    positions[60, 4, 2] = safety.ceiling_m + 0.1
    crossed = build_report(with_arrays(record, drone_positions_m=positions))
    assert [v.invariant for v in crossed.violations] == ["envelope"]
    assert "0.1000 m beyond the ceiling" in crossed.violations[0].detail
    assert "ceiling -0.1000 m" in render(with_arrays(record, drone_positions_m=positions))
    without = dataclasses.replace(record, config=load_config(ROOT / "configs" / "case2.toml"))
    assert build_report(without).envelope_margins_m == {}
    assert "envelope" not in render(without)


# -- missing samples (NaN rows) ------------------------------------------------------------


def drop_telemetry(record: RunRecord, steps: slice | int, drone: int) -> RunRecord:
    """What a recording holds when drone ``drone``'s telemetry of ``steps`` never arrived."""
    arrays = {}
    for name in ("velocities_m_s", "estimates", "lambda_bar", "psi0", "psi1", "weights",
                 "slacks", "weight_slacks", "step_us", "bearing_errors"):
        values = getattr(record, name).copy()
        values[steps, drone] = np.nan
        arrays[name] = values
    return with_arrays(record, **arrays)


def test_missing_samples_are_counted_and_never_reported_as_nan(case2: RunRecord) -> None:
    holed = drop_telemetry(drop_telemetry(case2, slice(50, 60), 2), -1, 1)
    positions = holed.drone_positions_m.copy()
    targets = holed.target_positions_m.copy()
    positions[70], targets[70] = np.nan, np.nan  # one step without ground truth
    holed = with_arrays(holed, drone_positions_m=positions, target_positions_m=targets)
    report = build_report(holed, "realtime")
    assert report.ok, report.violations
    assert report.coverage.missing_telemetry == 11
    assert report.coverage.missing_per_drone == (0, 1, 10, 0, 0, 0)
    assert report.coverage.missing_truth == 1
    assert report.drones[2].missing_samples == 10
    assert report.targets[0].missing_samples == 11
    assert any("11 of 600 drone-step samples missing" in w for w in report.warnings)
    # Drone 1's last sample is the step before the last one.
    assert report.drones[1].final_speed_mps == pytest.approx(
        np.linalg.norm(case2.velocities_m_s[-2, 1]))
    assert report.drones[1].final_weights == pytest.approx(tuple(case2.weights[-2, 1]))
    # NaN-aware figures over the samples present.
    assert report.drones[2].mean_step_us == pytest.approx(
        np.mean(np.delete(case2.step_us[:, 2], range(50, 60))))
    document = json_roundtrip(report_to_json(report))
    assert document["missing_samples"] == {"telemetry": 11, "truth": 1, "drone_steps": 600}
    for target in document["targets"]:
        assert all(target[key] is not None for key in TARGET_KEYS)


def test_nan_never_passes_an_invariant_silently(case2: RunRecord) -> None:
    k0 = start_index(case2)
    # All λ̄ of target 0 missing after the start: nothing checked, so not held.
    lam = case2.lambda_bar.copy()
    lam[k0:, :, 0] = np.nan
    velocities = case2.velocities_m_s.copy()
    velocities[k0:] = np.nan
    report = build_report(with_arrays(case2, lambda_bar=lam, velocities_m_s=velocities))
    messages = [str(v) for v in report.violations]
    assert any(m.startswith("lambda_bar: target 0: not checked") for m in messages), messages
    assert report.targets[0].min_lambda_bar_margin is None
    # A NaN inside a sample that did arrive (its command is there) is a computation gone bad.
    lam = case2.lambda_bar.copy()
    lam[k0 + 5, 3, 1] = np.nan
    assert [v.invariant for v in check_invariants(with_arrays(case2, lambda_bar=lam))] == [
        "finite"]
    # ±inf is never "missing".
    positions = case2.drone_positions_m.copy()
    positions[10, 0, 0] = np.inf
    assert "finite" in {v.invariant for v in
                        check_invariants(with_arrays(case2, drone_positions_m=positions))}


def test_an_empty_record_is_not_ok(case2: RunRecord) -> None:
    arrays = {f.name: getattr(case2, f.name)[:0] for f in dataclasses.fields(RunRecord)
              if isinstance(getattr(case2, f.name), np.ndarray)}
    report = build_report(with_arrays(case2, **arrays))
    assert not report.ok
    assert {v.invariant for v in report.violations} >= {"lambda_bar", "collision",
                                                        "velocity_bound"}
    json_roundtrip(report_to_json(report))


# -- JSON and tables -----------------------------------------------------------------------


def test_json_has_every_required_key(case2: RunRecord) -> None:
    document = json_roundtrip(report_to_json(build_report(case2)))
    assert document.keys() >= TOP_KEYS
    assert document["scenario"] == "case2" and document["mode"] == "inprocess"
    assert document["n_drones"] == 6 and document["n_targets"] == 2
    assert document["epsilon"] == 0.05 and document["verdict"] == "ok"
    assert len(document["targets"]) == 2 and len(document["drones"]) == 6
    for target in document["targets"]:
        assert target.keys() >= TARGET_KEYS
    for drone in document["drones"]:
        assert drone.keys() >= DRONE_KEYS
        assert len(drone["final_weights"]) == 2


def render(report_record: RunRecord, **kwargs: object) -> str:
    buffer = io.StringIO()
    render_report(build_report(report_record, **kwargs), Console(file=buffer, width=150))
    return buffer.getvalue()


def test_rendered_tables_and_verdict(case2: RunRecord) -> None:
    text = render(case2)
    assert "case2: targets" in text and "drones" in text
    assert "time λ̄<ε" in text and "[s]" in text  # units survive rich markup
    assert "sensing T" in text
    assert text.rstrip().endswith("verdict: OK (every SPEC invariant within tolerance)")
    eps, tol = case2.config.gramian.epsilon, case2.config.checks.lambda_tolerance
    bad = render(lowered_lambda(case2, eps - 2 * tol, start_index(case2), 0, 0))
    assert "VIOLATION lambda_bar: target 0: drone 0" in bad
    assert "verdict: FAILED" in bad


# -- the command line ----------------------------------------------------------------------


def cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "FORCE_COLOR")}
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    return subprocess.run([sys.executable, "-m", "swarm.observe.report_cli", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=timeout,
                          check=False)


def assert_usage_error(result: subprocess.CompletedProcess[str], *words: str) -> None:
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    assert result.stdout == ""
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("swarm-report: "), lines
    for word in words:
        assert word in lines[0]


def run_main(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """``swarm-report`` in this process (argparse exits through SystemExit)."""
    from swarm.observe import report_cli

    try:
        code = report_cli.main(list(args))
    except SystemExit as stop:
        code = int(stop.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("case", ["missing", "no_mcap_in_dir", "garbage_dir", "garbage_file",
                                  "no_argument", "unknown_option"])
def test_unreadable_recordings_and_bad_usage_exit_2_with_one_line(
        case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    garbage = tmp_path / "garbage" / "run.mcap"
    garbage.parent.mkdir()
    garbage.write_bytes(b"this is not an MCAP file at all" * 10)
    args = {"missing": [str(tmp_path / "nowhere")], "no_mcap_in_dir": [str(empty)],
            "garbage_dir": [str(garbage.parent)], "garbage_file": [str(garbage), "--json"],
            "no_argument": [], "unknown_option": [str(garbage.parent), "--bogus"]}[case]
    code, out, err = run_main(capsys, *args)
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("swarm-report: "), lines
    if case in ("missing", "no_mcap_in_dir"):
        assert args[0] in lines[0]


def test_garbage_recording_exits_2_without_traceback_as_a_process(tmp_path: Path) -> None:
    (tmp_path / "run.mcap").write_bytes(b"\x00garbage" * 50)
    assert_usage_error(cli(str(tmp_path)))


def test_unwritable_plot_directory_exits_2(recorded_run: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    code, out, err = run_main(capsys, str(recorded_run), "--plots", str(blocker / "sub"))
    assert code == 2 and out == ""
    assert err.startswith("swarm-report: cannot write plots to ") and err.count("\n") == 1


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s Case 1 recorded by launch-swarm (in-process)."""
    directory = tmp_path_factory.mktemp("recorded") / "case1"
    result = subprocess.run(
        [sys.executable, "-m", "swarm.launch.cli", "configs/case1.toml", "--inprocess",
         "--headless",
         "--duration", "3", "--record", str(directory)],
        cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    assert (directory / "run.mcap").is_file()
    return directory


def test_cli_tables_of_a_recorded_run(recorded_run: Path) -> None:
    result = cli(str(recorded_run))
    assert result.returncode == 0, result.stderr
    assert "case1: targets" in result.stdout
    assert "verdict: OK" in result.stdout
    assert "mode inprocess; seed 0; 150 steps" in result.stdout
    assert result.stderr == ""


def test_cli_json_of_a_recorded_run_matches_the_run(recorded_run: Path, tmp_path: Path) -> None:
    result = cli(str(recorded_run / "run.mcap"), "--json", "--plots", str(tmp_path / "figs"))
    assert result.returncode == 0, result.stderr
    document = json.loads(result.stdout)
    assert document.keys() >= TOP_KEYS
    assert document["steps"] == 150 and document["truncated"] is False
    assert document["late_steps"] == 0 and document["rejected_messages"] == 0
    # The recording reproduces the in-process run: same figures as a fresh run.
    fresh = report_to_json(build_report(short_record("case1", 3.0)))
    for key in ("min_lambda_bar_margin", "final_position_error_m", "rms_position_error_m"):
        assert document["targets"][0][key] == pytest.approx(fresh["targets"][0][key])
    assert sorted(Path(p).name for p in document["plots"]) == [
        "position_error.png", "psi.png", "speed.png", "view3d.png", "weights.png"]


def test_cli_exit_1_when_the_recording_violates_an_invariant(
        recorded_run: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from swarm.observe import report_cli
    from swarm.observe.recording.reader import read_recording

    recording = read_recording(recorded_run)
    record = recording.record
    eps, tol = record.config.gramian.epsilon, record.config.checks.lambda_tolerance
    bad = lowered_lambda(record, eps - tol - 0.01, start_index(record) + 5, 2, 0)
    monkeypatch.setattr(report_cli, "read_recording",
                        lambda _path: dataclasses.replace(recording, record=bad,
                                                          truncated=True))
    assert report_cli.main([str(recorded_run)]) == 1
    out = capsys.readouterr().out
    assert "VIOLATION lambda_bar: target 0: drone 2" in out
    assert "warning the recording is truncated" in out
    assert report_cli.main([str(recorded_run), "--json"]) == 1
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert document["verdict"] == "violated" and document["truncated"] is True
    assert "warning: the recording is truncated" in captured.err


def test_a_realtime_world_that_fell_behind_the_wall_is_said(case2: RunRecord) -> None:
    """Realtime agents count steps on the wall clock: a world running slower than it (a
    machine that could not keep up) leaves their filters ahead of the targets."""
    def warned(record: RunRecord, mode: str) -> list[str]:
        return [w for w in build_report(record, mode).warnings if "world's clock ran" in w]

    behind = dataclasses.replace(case2, world_clock_rate=0.52)
    (line,) = warned(behind, "realtime")
    assert "ran at 0.52 of the wall's" in line and "lockstep" in line
    assert build_report(behind, "realtime").ok  # said, not a SPEC invariant
    assert warned(dataclasses.replace(case2, world_clock_rate=0.96), "realtime") == []
    assert warned(behind, "lockstep") == []  # lockstep runs as fast as it can
    assert warned(case2, "realtime") == []  # not measured (in process)
