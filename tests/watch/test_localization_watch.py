"""The localization guarantee watched every step (swarm.watch.localization_watch), and said at once
by a process swarm: agent log, telemetry, dashboard and report (issue 14, point 5)."""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rich.console import Console

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.messages.wire import TelemetryWire
from swarm.observe.dashboard import Dashboard, DashboardSettings
from swarm.observe.report import build_report
from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config, write_resolved_config
from swarm.watch.localization_watch import LocalizationWatch

ROOT = Path(__file__).resolve().parents[2]
CASE1_THREE = ROOT / "tests" / "configs" / "case1_three.toml"


def test_a_breach_is_said_when_it_starts_and_when_it_ends() -> None:
    watch = LocalizationWatch(2, epsilon=0.05, tolerance=0.005)
    assert watch.update(0.5, [0.01, 0.01], control_active=False) == []  # before the QP runs
    assert watch.update(1.0, [0.06, 0.046], control_active=True) == []
    started = watch.update(1.02, [0.06, 0.0449], control_active=True, swarm_size=5)
    assert [(e.target, e.below, e.time_s) for e in started] == [(1, True, 1.02)]
    assert "cannot hold target 1 localized: λ̄ = 0.0449 < ε − tol = 0.0450 (swarm of 5)" \
        in started[0].describe(3)
    assert watch.breaches == 1 and watch.first_breach_s == 1.02 and watch.below == (1,)
    assert watch.status() == "λ̄ < ε − tol: target 1 since 1.0 s"
    assert watch.update(1.04, [0.06, 0.030], control_active=True) == []  # still the same one
    ended = watch.update(1.50, [0.06, 0.0451], control_active=True)
    assert [(e.target, e.below) for e in ended] == [(1, False)]
    assert "back to λ̄ = 0.0451 ≥ ε − tol after 0.48 s (lowest 0.0300)" in ended[0].describe(3)
    assert watch.status() == "" and watch.breaches == 1 and watch.first_breach_s == 1.02


def test_a_copy_that_is_not_a_number_guarantees_nothing() -> None:
    watch = LocalizationWatch(1, epsilon=0.05, tolerance=0.0)
    events = watch.update(2.0, [math.nan], control_active=True)
    assert len(events) == 1 and events[0].below and watch.below == (0,)


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="n_targets"):
        LocalizationWatch(0, 0.05, 0.005)
    with pytest.raises(ValueError, match="tolerance"):
        LocalizationWatch(1, 0.05, -0.001)
    with pytest.raises(ValueError, match="expected 2"):
        LocalizationWatch(2, 0.05, 0.005).update(1.0, [0.1], control_active=True)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.floats(0.0, 0.1), min_size=2, max_size=2), min_size=1,
                max_size=60),
       st.floats(0.0, 0.02))
def test_breaches_count_the_falls_below_the_floor(series: list[list[float]],
                                                  tolerance: float) -> None:
    """Per target, a breach is a step below ε − tol after one that was not (or the first)."""
    eps = 0.05
    watch = LocalizationWatch(2, eps, tolerance)
    floor = eps - tolerance
    for k, values in enumerate(series):
        watch.update(0.02 * k, values, control_active=True)
        assert watch.below == tuple(j for j in range(2) if values[j] < floor)
    below = np.array(series) < floor
    falls = below[0].sum() + (below[1:] & ~below[:-1]).sum()
    assert watch.breaches == falls
    first = np.flatnonzero(below.any(axis=1))
    assert watch.first_breach_s == (0.02 * first[0] if first.size else None)


@pytest.mark.slow
def test_the_agents_say_at_the_very_step_their_copy_falls_below_the_floor(
        tmp_path: Path) -> None:
    """Case 1 with three drones, checked with no tolerance (λ̄ ≥ ε itself): the in-process
    reference dips 4e-4 below ε from ~21.6 s. The lockstep process swarm reproduces it; each
    agent says so in its telemetry at the step its own copy falls below and when it comes
    back (the same episodes a watch replayed on the reference finds), logs it, and the
    dashboard and the report repeat it."""
    base = load_config(CASE1_THREE).with_duration(24.0)
    config = dataclasses.replace(base, checks=dataclasses.replace(base.checks,
                                                                  lambda_tolerance=0.0))
    path = write_resolved_config(config, tmp_path / "case1_three_no_tolerance.json")
    eps, dt, n = config.gramian.epsilon, config.scenario.dt_s, config.swarm.n_drones
    received: dict[int, dict[int, TelemetryWire]] = defaultdict(dict)
    lock = threading.Lock()

    def keep(tel: TelemetryWire) -> None:
        with lock:
            received[tel.drone][tel.step] = tel

    logs = tmp_path / "logs"
    record = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0,
                                         log_dir=logs), log=lambda _line: None).run(
        telemetry_listeners=[keep])
    reference = run_reference(config, seed=0)
    assert np.max(np.abs(record.lambda_bar - reference.lambda_bar)) <= 1e-9

    for i in range(n):
        steps = received[i]
        assert sorted(steps) == list(range(config.n_steps)), i
        replay = LocalizationWatch(1, eps, 0.0)
        for k in range(config.n_steps):
            tel = steps[k]
            replay.update(k * dt, reference.lambda_bar[k, i], control_active=k * dt >= 1.0)
            own = tel.arrays()["lambda_bar"][0]
            below_now = tel.control_active and own < eps
            assert bool(tel.counters.localization_status) == below_now, (i, k, own)
            assert tel.counters.lambda_breaches == replay.breaches, (i, k)
            assert tel.counters.first_lambda_breach_s == replay.first_breach_s, (i, k)
        assert replay.breaches >= 1, "the scenario must dip below ε for this test to mean it"
        log = (logs / f"agent{i}.log").read_text()
        first = steps[round(replay.first_breach_s / dt)]
        assert (f"drone {i}: t = {first.time_s:.2f} s: cannot hold target 0 localized"
                in log), log[-2000:]

    # The verdict fails on the same dip the agents said.
    assert [v.invariant for v in check_invariants(record)] == ["lambda_bar"]

    # The dashboard warns at the first breach of each drone, naming the target.
    console = Console(record=True, width=200, force_terminal=False)
    clock = iter(range(10**6))
    with Dashboard(config, console, headless=True,
                   settings=DashboardSettings(log_period_s=1e6),
                   wall_clock=lambda: float(next(clock))) as dashboard:
        for k in range(config.n_steps):
            for i in range(n):
                dashboard.on_telemetry(received[i][k])
            dashboard.advance(k)
    lines = console.export_text().splitlines()
    for i in range(n):
        first_s = received[i][config.n_steps - 1].counters.first_lambda_breach_s
        said = [line for line in lines if line.startswith(f"t={first_s:6.2f}s  warning: "
                                                          f"drone {i}: ")]
        assert len(said) == 1 and "+1 targets its λ̄ copy let fall below ε − tol (1 total)" \
            in said[0] and said[0].endswith("now: λ̄ < ε − tol: target 0 since "
                                            f"{first_s:.1f} s"), (said, lines[-20:])

    # The report says which drones said it, and from when.
    counters = {i: received[i][config.n_steps - 1].counters for i in range(n)}
    report = build_report(record, "lockstep", counters)
    for i in range(n):
        d = report.drones[i]
        assert d.lambda_breaches == counters[i].lambda_breaches >= 1
        assert any(w.startswith(f"drone {i}: said it could not hold λ̄ ≥ ε − tol from t = "
                                f"{d.first_lambda_breach_s:.2f} s") for w in report.warnings)


# -- what mutation testing found untested (issue 46, point 2; docs/mutation.md) ------------


def test_a_copy_exactly_at_the_floor_holds() -> None:
    watch = LocalizationWatch(1, epsilon=0.05, tolerance=0.0)
    assert watch.update(1.0, [0.05], control_active=True) == [] and watch.below == ()


def test_events_carry_the_copy_the_floor_the_swarm_and_the_breach() -> None:
    watch = LocalizationWatch(2, epsilon=0.05, tolerance=0.005)
    [start] = watch.update(1.0, [0.06, 0.03], control_active=True)  # swarm size not given
    assert (start.time_s, start.target, start.below, start.lambda_bar, start.floor,
            start.swarm_size, start.lowest, start.since_s) == (
        1.0, 1, True, 0.03, watch.floor, 0, 0.03, 1.0)
    assert start.describe(0).endswith("< ε − tol = 0.0450")  # no "(swarm of 0)"
    watch.update(1.2, [0.01, 0.02], control_active=True, swarm_size=4)
    assert watch.status() == "λ̄ < ε − tol: target 0 since 1.2 s, 1 since 1.0 s"
    back = watch.update(1.5, [0.01, 0.05], control_active=True, swarm_size=4)
    assert [(e.target, e.below, e.lambda_bar, e.floor, e.swarm_size, e.lowest, e.since_s)
            for e in back] == [(1, False, 0.05, watch.floor, 4, 0.02, 1.0)]
