"""The live dashboard: what its tables show, when it warns, headless lines, threads, the CLI.

Telemetry comes from a short in-process run of Case 2 (two targets, so every per-target
column holds two values), turned into ``TelemetryWire`` exactly as an agent process does.
"""

from __future__ import annotations

import dataclasses
import io
import os
import pty
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
from rich.console import Console

from swarm.core.drone_step import StepDiagnostics
from swarm.launch.launcher import LaunchOptions, SwarmLauncher, free_tcp_port
from swarm.messages.wire import ClockWire, TelemetryWire, telemetry_from_diagnostics
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.observe.dashboard import (
    Dashboard,
    DashboardSettings,
    InProcessFeed,
    drone_row,
    target_rows,
    watch,
)
from swarm.runs.reference import run_reference
from swarm.scenario.config import ScenarioConfig, load_config
from tests.helpers.cli_tools import cli_env

ROOT = Path(__file__).resolve().parents[2]
CASE2 = ROOT / "configs" / "case2.toml"
WIDTH = 160


@pytest.fixture(scope="module")
def config() -> ScenarioConfig:
    return load_config(CASE2).with_duration(2.0)


@pytest.fixture(scope="module")
def final_diagnostics(config: ScenarioConfig) -> list[StepDiagnostics]:
    """Every drone's diagnostics at the last step of a 2 s run."""
    last: dict[str, list[StepDiagnostics]] = {}
    run_reference(config, on_step=lambda _k, diags: last.update(diags=diags))
    return last["diags"]


def telemetry(diag: StepDiagnostics, **counters: object) -> TelemetryWire:
    return telemetry_from_diagnostics(diag, [0.0, 0.0, 3.0], **counters)


def at_step(tel: TelemetryWire, step: int, dt_s: float, **counters: object) -> TelemetryWire:
    """The same message as if sent at ``step``, with some counters changed."""
    changed = msgspec.structs.replace(tel.counters, **counters)
    return msgspec.structs.replace(tel, step=step, time_s=step * dt_s, counters=changed)


def recording_console(*, terminal: bool = True) -> Console:
    return Console(record=True, width=WIDTH, force_terminal=terminal, file=io.StringIO(),
                   color_system="standard")


def rows_of(text: str, title: str) -> dict[int, str]:
    """Table body lines under ``title`` (up to the next blank line or title), by first number."""
    lines = text.splitlines()
    start = next(k for k, line in enumerate(lines) if line.startswith(title))
    rows: dict[int, str] = {}
    for line in lines[start + 3:]:  # title, header, rule
        first = line.split()[0] if line.strip() else ""
        if not first.isdigit():
            break
        rows[int(first)] = line
    return rows


# -- tables ------------------------------------------------------------------------------------


def test_tables_show_every_drone_and_target_with_their_numbers(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    console = recording_console()
    dashboard = Dashboard(config, console, headless=True)
    for d in final_diagnostics:
        dashboard.on_telemetry(telemetry(d, neighbour_age_ms=12.0 + d.drone_id,
                                         mavlink_state="armed OFFBOARD", late_steps=d.drone_id))
    dashboard.advance(final_diagnostics[0].step)
    console.print(dashboard.render())
    text = console.export_text()

    drones = rows_of(text, "drones")
    assert sorted(drones) == list(range(config.swarm.n_drones))
    for d in final_diagnostics:
        cells = drones[d.drone_id].split()
        row = " ".join(cells)
        for values, fmt in ((d.lambda_bar, "{:.3f}"), (d.psi0, "{:+.3f}"),
                            (d.weights, "{:.2f}")):
            assert " ".join(fmt.format(v) for v in values) in row, (d.drone_id, row)
        assert f"{np.linalg.norm(d.velocity):.2f}" in cells
        assert f"{d.slacks.max():.3f}" in cells
        assert f"{d.step_us:.0f}" in cells
        assert f"{12 + d.drone_id}" in cells  # freshest neighbour message [ms]
        assert "armed OFFBOARD" in row
        assert (f"late {d.drone_id}" in row) == (d.drone_id > 0)  # only non-zero events

    targets = rows_of(text, "targets")
    assert sorted(targets) == [0, 1]
    lam = np.array([d.lambda_bar for d in final_diagnostics])
    est = np.array([d.estimates[:, :3] for d in final_diagnostics])
    w = np.array([d.weights for d in final_diagnostics])
    for r, row in targets.items():
        worst = int(np.argmin(lam[:, r]))
        assert f"{lam[worst, r]:.3f} ({worst})" in row
        assert f"{lam[worst, r] - config.gramian.epsilon:+.3f}" in row
        assert f"{min(d.psi0[r] for d in final_diagnostics):+.3f}" in row
        assert f"{int((w[:, r] > 0.1).sum())}/6" in row
        spread = max(np.linalg.norm(a - b) for a in est[:, r] for b in est[:, r])
        assert f"{spread:.3f}" in row.split()
    assert "6/6 drones reporting" in text
    assert f"t = {final_diagnostics[0].time_s:.2f} / 2.00 s" in text


def test_at_80_columns_the_events_and_vehicle_state_stay(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    """A narrow terminal leaves out the step time and the neighbour age first, never the
    events or the vehicle's state, and says so in the title (issue 41, point 6)."""
    console = Console(record=True, width=80, force_terminal=True, file=io.StringIO(),
                      color_system="standard")
    dashboard = Dashboard(config, console, headless=True)
    for d in final_diagnostics:
        dashboard.on_telemetry(telemetry(d, neighbour_age_ms=12.0, late_steps=d.drone_id + 1,
                                         mavlink_state="armed OFFBOARD"))
    dashboard.advance(final_diagnostics[0].step)
    console.print(dashboard.render())
    text = console.export_text()
    assert max(len(line.rstrip()) for line in text.splitlines()) <= 80
    title = next(line for line in text.splitlines() if line.startswith("drones"))
    assert "columns left out: too narrow" in title
    header = text.splitlines()[text.splitlines().index(title) + 1]
    assert "events" in header and "MAVLink" in header and "step [µs]" not in header
    for drone, row in rows_of(text, "drones").items():
        assert f"late {drone + 1}" in row and "armed OFFBOARD" in row


def test_row_numbers_match_the_diagnostics(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    tels = [telemetry(d) for d in final_diagnostics]
    for d, tel in zip(final_diagnostics, tels, strict=True):
        row = drone_row(tel)
        assert row.lambda_bar == tuple(d.lambda_bar) and row.weights == tuple(d.weights)
        assert row.speed_m_s == pytest.approx(np.linalg.norm(d.velocity))
        assert row.neighbour_age_ms is None and row.mavlink_state == ""
    rows = target_rows(tels, config.gramian.epsilon, 0.1)
    lam = np.array([d.lambda_bar for d in final_diagnostics])
    assert [r.min_lambda_bar for r in rows] == list(lam.min(axis=0))
    assert [r.reporting for r in rows] == [6, 6]


def test_lambda_below_epsilon_is_red_and_sensing_weights_green(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    low = dataclasses.replace(final_diagnostics[2], lambda_bar=np.array([0.01234, 0.9]),
                              weights=np.array([0.5, 0.05]))
    console = recording_console()
    dashboard = Dashboard(config, console, headless=True)
    dashboard.on_telemetry(telemetry(low))
    console.print(dashboard.render())
    styled = console.export_text(styles=True, clear=False)
    assert "\x1b[1;31m0.012\x1b[0m" in styled  # bold red: λ̄ < ε
    assert "\x1b[32m0.50\x1b[0m" in styled  # green: w > 0.1, sensing
    assert "\x1b[2m0.05\x1b[0m" in styled  # dim: not sensing
    assert "\x1b[1;31m0.900" not in styled
    assert "1/1" in console.export_text()  # target 0 sensed by the one drone reporting


def test_before_any_telemetry_it_says_it_is_waiting(config: ScenarioConfig) -> None:
    console = recording_console()
    console.print(Dashboard(config, console, headless=True).render())
    assert "waiting for telemetry" in console.export_text()


# -- warnings ----------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def warnings_in(console: Console) -> list[str]:
    return [line for line in console.export_text(clear=False).splitlines()
            if "warning:" in line]


def test_warnings_appear_exactly_when_a_counter_increases(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    dt = config.scenario.dt_s
    console = recording_console(terminal=False)
    clock = FakeClock()
    dashboard = Dashboard(config, console, wall_clock=clock,
                          settings=DashboardSettings(log_period_s=1000.0))
    base = [telemetry(d) for d in final_diagnostics]

    def step(k: int, **counters_of: dict[str, int]) -> list[str]:
        """Every drone reports step k (drone i with counters_of[str(i)]); new warning lines."""
        before = len(warnings_in(console))
        for tel in base:
            dashboard.on_telemetry(at_step(tel, k, dt, **counters_of.get(str(tel.drone), {})))
        dashboard.advance(k)
        return warnings_in(console)[before:]

    assert step(1) == []  # all counters zero: silence
    assert step(2, **{"3": {"late_steps": 2}}) == [
        "t=  0.04s  warning: drone 3: +2 late steps (2 total)"]
    assert step(3, **{"3": {"late_steps": 2}}) == []  # no increase, no line
    clock.now += 2.0
    assert step(4, **{"1": {"stale_neighbour_messages": 5, "qp_fallbacks": 1},
                      "3": {"late_steps": 2, "rejected_messages": 1}}) == [
        "t=  0.08s  warning: drone 1: +5 stale neighbour messages (5 total), "
        "+1 QP fallbacks (1 total)",
        "t=  0.08s  warning: drone 3: +1 rejected messages (1 total)"]
    # A storm on drone 1 within the rate-limit period: one aggregated line, later.
    for k in range(5, 10):
        assert step(k, **{"1": {"stale_neighbour_messages": 5 + k,
                                "qp_fallbacks": 1}}) == []
    clock.now += 1.0
    assert step(10, **{"1": {"stale_neighbour_messages": 15, "qp_fallbacks": 1}}) == [
        "t=  0.20s  warning: drone 1: +10 stale neighbour messages (15 total)"]
    # Pending increases are not lost at the end: closing reports them at once.
    step(11, **{"1": {"stale_neighbour_messages": 16, "qp_fallbacks": 1}})
    before = len(warnings_in(console))
    dashboard.close()
    assert warnings_in(console)[before:] == [
        "t=  0.22s  warning: drone 1: +1 stale neighbour messages (16 total)"]
    assert dashboard.stats.warning_lines == 5


def test_a_drone_saying_it_cannot_hold_a_target_is_printed_at_once(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    """A λ̄ breach (or a vehicle event) is not held back by the warning period: its line
    comes at its step, with what the drone says is wrong now; other counters wait."""
    dt = config.scenario.dt_s
    console = recording_console(terminal=False)
    clock = FakeClock()
    dashboard = Dashboard(config, console, wall_clock=clock,
                          settings=DashboardSettings(log_period_s=1000.0))
    tel = telemetry(final_diagnostics[2])
    dashboard.on_telemetry(at_step(tel, 1, dt, qp_fallbacks=1))
    dashboard.advance(1)
    assert warnings_in(console) == ["t=  0.02s  warning: drone 2: +1 QP fallbacks (1 total)"]
    dashboard.on_telemetry(at_step(tel, 2, dt, qp_fallbacks=2))
    dashboard.advance(2)  # within the period: held back
    assert len(warnings_in(console)) == 1
    dashboard.on_telemetry(at_step(
        tel, 3, dt, qp_fallbacks=3, lambda_breaches=1, first_lambda_breach_s=0.06,
        localization_status="λ̄ < ε − tol: target 1 since 0.1 s"))
    dashboard.advance(3)  # a breach: at once, with the pending fallbacks
    assert warnings_in(console)[1:] == [
        "t=  0.06s  warning: drone 2: +2 QP fallbacks (3 total), +1 targets its λ̄ copy let "
        "fall below ε − tol (1 total); now: λ̄ < ε − tol: target 1 since 0.1 s"]
    console.print(dashboard.render())
    assert "fb 3 λ̄ 1" in console.export_text()  # the drone's events column


def test_steps_the_safety_envelope_overruled_localization_are_warned_and_shown(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    """A drone's ``safety_conflicts`` counter (issue 18) rising: a warning line saying so,
    and ``env`` in its events column."""
    dt = config.scenario.dt_s
    console = recording_console(terminal=False)
    dashboard = Dashboard(config, console, settings=DashboardSettings(warning_period_s=0.0))
    tel = telemetry(final_diagnostics[4])
    dashboard.on_telemetry(at_step(tel, 1, dt, safety_conflicts=5))
    dashboard.advance(1)
    assert warnings_in(console) == [
        "t=  0.02s  warning: drone 4: +5 steps the safety envelope overruled localization "
        "(5 total)"]
    console.print(dashboard.render())
    assert "env 5" in console.export_text()


def test_inprocess_feed_counts_fallbacks_and_warns(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    console = recording_console(terminal=False)
    dashboard = Dashboard(config, console, settings=DashboardSettings(warning_period_s=0.0))
    feed = InProcessFeed(dashboard)
    failing = [dataclasses.replace(d, qp_fallback=d.drone_id == 4) for d in final_diagnostics]
    for k in range(3):
        feed(k, [dataclasses.replace(d, step=k) for d in failing])
    assert [w.split("warning: ")[1] for w in warnings_in(console)] == [
        f"drone 4: +1 QP fallbacks ({n} total)" for n in (1, 2, 3)]
    first = console.export_text().splitlines()[1]  # the warning of step 0 comes first
    assert first.startswith("t=  0.00s  λ̄ min") and "fallbacks 1" in first


def test_inprocess_feed_builds_only_the_messages_that_are_shown(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    """Headless: the log steps, the last step and steps with a warning; live: by wall time."""
    n_steps = config.n_steps  # 100
    dashboard = Dashboard(config, recording_console(terminal=False))
    feed = InProcessFeed(dashboard)
    for k in range(n_steps):
        feed(k, [dataclasses.replace(d, step=k, qp_fallback=k == 40 and d.drone_id == 0)
                 for d in final_diagnostics])
    assert dashboard.stats.telemetry_messages == 6 * 3  # steps 0, 40 and 99

    clock = FakeClock()
    live = Dashboard(config, recording_console(), wall_clock=clock,
                     settings=DashboardSettings(refresh_hz=4.0))
    assert [live.shows(k) for k in range(3)] == [True, False, False]
    clock.now += 0.125  # half a refresh period
    assert live.shows(3) and not live.shows(4)
    assert live.shows(n_steps - 1)  # the last step is always shown


# -- headless ----------------------------------------------------------------------------------


def test_headless_prints_one_line_every_few_simulated_seconds(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    dt = config.scenario.dt_s
    console = recording_console(terminal=False)
    dashboard = Dashboard(config, console, settings=DashboardSettings(log_period_s=5.0))
    base = [telemetry(d) for d in final_diagnostics]
    with dashboard:
        for k in range(int(12.0 / dt)):
            for tel in base:
                dashboard.on_telemetry(at_step(tel, k, dt))
            dashboard.advance(k)
    lines = console.export_text().splitlines()
    assert [line.split("s ")[0] for line in lines] == ["t=  0.00", "t=  5.00", "t= 10.00"]
    lam = np.min([d.lambda_bar for d in final_diagnostics], axis=0)
    assert f"λ̄ min {lam[0]:.3f} {lam[1]:.3f}" in lines[0]
    assert lines[0].endswith("fallbacks 0  late 0  stale 0")
    assert dashboard.stats.renders == 0


def test_without_a_terminal_it_is_headless_with_no_live_display(
        config: ScenarioConfig) -> None:
    plain = Console(file=io.StringIO())
    assert not plain.is_terminal
    dashboard = Dashboard(config, plain)
    assert dashboard.headless
    with dashboard:
        assert dashboard._thread is None and dashboard._live is None
    terminal = Dashboard(config, recording_console())
    assert not terminal.headless
    assert Dashboard(config, recording_console(), headless=True).headless


# -- threads -----------------------------------------------------------------------------------


def test_feeding_from_several_threads_while_rendering(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    dt = config.scenario.dt_s
    console = recording_console()
    base = [telemetry(d) for d in final_diagnostics]
    per_thread = 400
    errors: list[BaseException] = []

    def feed(offset: int) -> None:
        try:
            for k in range(per_thread):
                for tel in base[offset::2]:
                    dashboard.on_telemetry(at_step(tel, k, dt, late_steps=k))
        except BaseException as exc:
            errors.append(exc)

    dashboard = Dashboard(config, console, settings=DashboardSettings(refresh_hz=100.0))
    with dashboard:
        threads = [threading.Thread(target=feed, args=(i % 2,)) for i in range(4)]
        for t in threads:
            t.start()
        k = 0
        while any(t.is_alive() for t in threads):
            dashboard.advance(k)
            k += 1
        for t in threads:
            t.join()
    assert errors == []
    stats = dashboard.stats
    assert stats.telemetry_messages == 4 * per_thread * 3
    assert stats.renders >= 2
    last = rows_of(console.export_text().split("t = ")[-1], "drones")
    assert sorted(last) == list(range(6))
    assert all(f"late {per_thread - 1}" in row for row in last.values())


# -- the launcher hook -------------------------------------------------------------------------


def test_the_launcher_passes_each_telemetry_message_to_its_listeners(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics], tmp_path: Path) -> None:
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CASE2), seed=0,
                                           log_dir=tmp_path))
    seen: list[TelemetryWire] = []
    launcher.telemetry_listeners = (seen.append,)
    tel = telemetry(final_diagnostics[1])
    launcher._on_telemetry("vigil/x/agent/1/telemetry", tel)
    assert seen == [tel]
    assert launcher.collector.latest[1] is tel


@pytest.mark.wallclock
def test_watch_shows_a_swarm_running_elsewhere(
        config: ScenarioConfig, final_diagnostics: list[StepDiagnostics]) -> None:
    """A stand-in world (a Zenoh router publishing clock and telemetry) and ``watch``."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("watchtest")
    codec = config.wire_codec()
    console = recording_console(terminal=False)
    result: dict[str, str] = {}
    router = open_session(zenoh_config(mode="router", listen=[endpoint]))
    try:
        watcher = threading.Thread(target=lambda: result.update(state=watch(
            endpoint, "watchtest", config, console=console,
            settings=DashboardSettings(log_period_s=0.5, warning_period_s=0.0))))
        watcher.start()
        dt = config.scenario.dt_s
        base = [telemetry(d) for d in final_diagnostics]
        deadline = time.monotonic() + 30.0
        k = 0
        # Publish until the watcher has warned (its subscription may come late).
        while "warning:" not in console.export_text(clear=False) and (
                time.monotonic() < deadline):
            for tel in base:
                router.put(keys.telemetry(tel.drone),
                           codec.encode(at_step(tel, k, dt, late_steps=k // 10)))
            router.put(keys.clock, codec.encode(ClockWire(step=k, time_s=k * dt,
                                                          state="running", mode="realtime")))
            k += 1
            time.sleep(0.02)
        router.put(keys.clock, codec.encode(ClockWire(step=k, time_s=k * dt, state="done",
                                                      mode="realtime")))
        watcher.join(timeout=30.0)
    finally:
        router.close()
    assert result.get("state") == "done"
    text = console.export_text()
    assert "λ̄ min" in text
    assert "warning: drone 0: +" in text


# -- the command line --------------------------------------------------------------------------


def test_headless_cli_logs_periodic_lines_and_the_verdict() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "swarm.launch.cli", "configs/case1.toml", "--inprocess",
         "--duration", "6", "--headless"], cwd=ROOT, env=cli_env(), capture_output=True, text=True,
        timeout=120, check=False)
    assert result.returncode == 0, result.stderr
    logs = [line for line in result.stdout.splitlines() if line.startswith("t=")]
    assert [line.split("s ")[0] for line in logs] == ["t=  0.00", "t=  5.00"]
    assert all("λ̄ min" in line and "late 0  stale 0" in line for line in logs)
    assert "verdict: OK" in result.stdout


def test_cli_on_a_terminal_shows_the_live_dashboard() -> None:
    """Through a pseudo-terminal, as a user at a terminal sees it."""
    leader, follower = pty.openpty()
    process = subprocess.Popen(
        [sys.executable, "-m", "swarm.launch.cli", "configs/case1.toml", "--inprocess",
         "--duration", "2"], cwd=ROOT, env=cli_env(COLUMNS="140", LINES="60"), stdin=follower,
        stdout=follower, stderr=follower, close_fds=True)
    os.close(follower)
    chunks = []
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    assert process.wait(timeout=120) == 0
    out = b"".join(chunks).decode(errors="replace")
    assert "drones reporting" in out and "nbr age [ms]" in out
    assert "verdict: OK" in out
