"""``launch-swarm``: run a scenario — as a process swarm, or in-process — and summarize it.

Exit codes: 0 mission completed with every SPEC invariant within tolerance, 1 an invariant
was violated or the mission failed (a process died, the world aborted), 2 bad command line or
config (one line on stderr, no traceback), 130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from sim_world.kinematics import InitialPlacementError
from swarm.checks import check_invariants, summarize_drones, summarize_targets
from swarm.cli_common import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    ConfigError,
    OneLineParser,
    fail,
    load_scenario,
    port,
    positive_float,
    run_id,
    seed,
    terminate_on_sigterm,
)
from swarm.config import ScenarioConfig
from swarm.core.agent import StepDiagnostics
from swarm.launcher import LaunchOptions, MissionError, SwarmLauncher, TelemetryCollector
from swarm.reference import RunRecord, run_reference

EXIT_VIOLATION = EXIT_FAILED
HEADLESS_LOG_PERIOD_S = 5.0  # sim seconds between one-line progress logs
PROG = "launch-swarm"


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog=PROG,
        description="Run a Vigil scenario: N camera drones keeping M targets localized.")
    parser.add_argument("config", help="scenario file, e.g. configs/case1.toml")
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                        help="process swarm timing: deterministic lockstep (default) or 50 Hz "
                             "wall clock")
    parser.add_argument("--inprocess", action="store_true",
                        help="run every drone in this process (the reference simulator)")
    parser.add_argument("--seed", type=seed, default=None,
                        help="random seed (default: scenario.seed of the config)")
    parser.add_argument("--duration", type=positive_float, default=None, metavar="S",
                        help="simulated seconds (default: scenario.duration_s)")
    parser.add_argument("--headless", action="store_true",
                        help="no live display: a one-line log every few simulated seconds")
    parser.add_argument("--mavlink-base", type=port, default=0, metavar="PORT",
                        help="vehicle i talks to agent i on UDP PORT+i (default: 14540, or "
                             "the next free block)")
    parser.add_argument("--run-id", type=run_id, default=None,
                        help="Zenoh key prefix vigil/<run-id>/ (default: random)")
    parser.add_argument("--log-dir", default=None, metavar="DIR",
                        help="where each process writes its log (default: a temp dir)")
    return parser


class _ProgressReporter:
    """Rich progress bar on a terminal, periodic one-line logs otherwise."""

    def __init__(self, config: ScenarioConfig, console: Console, headless: bool) -> None:
        self._config = config
        self._console = console
        self._headless = headless or not console.is_terminal
        self._next_log_s = 0.0
        self._progress: Progress | None = None
        self._task = None

    def __enter__(self) -> _ProgressReporter:
        if not self._headless:
            self._progress = Progress(
                TextColumn("[bold]{task.description}"), BarColumn(),
                TextColumn("{task.fields[status]}"), TimeRemainingColumn(),
                console=self._console, transient=True)
            self._progress.__enter__()
            self._task = self._progress.add_task(
                self._config.scenario.name, total=self._config.n_steps, status="")
        return self

    def __exit__(self, *exc: object) -> None:
        if self._progress is not None:
            self._progress.__exit__(None, None, None)

    def from_diagnostics(self, step: int, diagnostics: list[StepDiagnostics]) -> None:
        lam = [min(float(d.lambda_bar[r]) for d in diagnostics)
               for r in range(len(diagnostics[0].lambda_bar))]
        speeds = [float((d.velocity @ d.velocity) ** 0.5) for d in diagnostics]
        self.update(step, lam, max(speeds), sum(d.qp_fallback for d in diagnostics))

    def from_collector(self, step: int, collector: TelemetryCollector) -> None:
        if step < 0:
            return
        with collector.lock:
            latest = list(collector.latest.values())
        if not latest:
            return
        diags = [t.to_diagnostics() for t in latest]
        self.from_diagnostics(step, diags)

    def update(self, step: int, lambda_min: list[float], max_speed: float,
               fallbacks: int) -> None:
        time_s = step * self._config.scenario.dt_s
        status = "λ̄ min " + " ".join(f"{v:.3f}" for v in lambda_min)
        if self._progress is not None:
            self._progress.update(self._task, completed=step + 1,
                                  status=f"t={time_s:5.1f}s {status}")
        elif time_s + 1e-9 >= self._next_log_s:
            self._console.print(
                f"t={time_s:6.2f}s  {status}  max|u| {max_speed:.2f} m/s  fallbacks {fallbacks}",
                highlight=False)
            self._next_log_s = time_s + HEADLESS_LOG_PERIOD_S


def print_summary(record: RunRecord, console: Console) -> int:
    cfg = record.config
    eps = cfg.gramian.epsilon
    targets = Table(title=f"{cfg.scenario.name}: targets (ε = {eps})", title_justify="left")
    for column in ("target", "min λ̄−ε", "time λ̄<ε [s]", "min true λ−ε", "min measured λ",
                   "final err [m]", "RMS err [m]", "sensing (w>0.1)"):
        targets.add_column(column, justify="right")
    for t in summarize_targets(record):
        targets.add_row(str(t.target), f"{t.min_lambda_bar_margin:+.4f}",
                        f"{t.time_below_epsilon_s:.2f}", f"{t.min_true_lambda_margin:+.4f}",
                        f"{t.min_measured_lambda:.4f}", f"{t.final_position_error_m:.4f}",
                        f"{t.rms_position_error_m:.4f}", str(t.drones_sensing_final))
    drones = Table(title="drones", title_justify="left")
    for column in ("drone", "final |u| [m/s]", "final w", "idle", "QP fallbacks",
                   "mean step [µs]", "p99 step [µs]", "bearing err"):
        drones.add_column(column, justify="right")
    for d in summarize_drones(record):
        drones.add_row(str(d.drone), f"{d.final_speed_m_s:.3f}",
                       " ".join(f"{w:.2f}" for w in d.final_weights), "yes" if d.idle_final else "",
                       str(d.qp_fallbacks), f"{d.mean_step_us:.0f}", f"{d.p99_step_us:.0f}",
                       "" if d.final_bearing_error is None else f"{d.final_bearing_error:.4f}")
    console.print(targets)
    console.print(drones)
    console.print(f"min pairwise distance {record.min_pairwise_distance():.4f} m "
                  f"(Δ = {cfg.control.collision_distance_m} m); seed {record.seed}; "
                  f"{record.n_steps} steps in {record.wall_time_s:.1f} s wall", highlight=False)
    violations = check_invariants(record)
    if violations:
        for v in violations:
            console.print(f"[bold red]VIOLATION[/] {v}", highlight=False)
        console.print("[bold red]verdict: FAILED[/] (a SPEC invariant was violated)")
        return EXIT_VIOLATION
    console.print("[bold green]verdict: OK[/] (every SPEC invariant within tolerance)")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    console = Console()
    if not console.is_terminal:
        console = Console(width=140)  # logs and CI: keep table columns unwrapped
    try:
        config = load_scenario(args.config, args.duration)
    except ConfigError as err:
        return fail(PROG, f"config error: {err}")
    seed_value = config.scenario.seed if args.seed is None else args.seed
    terminate_on_sigterm()
    try:
        if args.inprocess:
            with _ProgressReporter(config, console, args.headless) as reporter:
                record = run_reference(config, seed_value, on_step=reporter.from_diagnostics)
        else:
            options = LaunchOptions(
                config=config, config_path=str(Path(args.config).resolve()), seed=seed_value,
                mode=args.mode, run_id=args.run_id or "", mavlink_base=args.mavlink_base,
                log_dir=Path(args.log_dir) if args.log_dir else None)
            launcher = SwarmLauncher(options, log=lambda line: console.print(
                line, highlight=False, markup=False))
            with _ProgressReporter(config, console, args.headless) as reporter:
                record = launcher.run(on_progress=reporter.from_collector)
            print_process_counters(launcher.collector, console)
    except InitialPlacementError as err:
        return fail(PROG, f"config error: {config.source}: swarm.initial_box_size_m: {err}")
    except MissionError as err:
        print(f"{PROG}: mission failed: {err}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; every process stopped", file=sys.stderr)
        return EXIT_INTERRUPTED
    return print_summary(record, console)


def print_process_counters(collector: TelemetryCollector, console: Console) -> None:
    counts = collector.counters()
    steps = max(counts["agent_steps"], 1)
    console.print(
        f"agent steps {counts['agent_steps']} (telemetry received "
        f"{counts['telemetry_received']}), late {counts['late_steps']} "
        f"({100.0 * counts['late_steps'] / steps:.2f} %), stale neighbour messages "
        f"{counts['stale_neighbour_messages']}, rejected messages "
        f"{counts['rejected_messages']}, QP fallbacks {counts['qp_fallbacks']}",
        highlight=False)


if __name__ == "__main__":
    sys.exit(main())
