"""``launch-swarm``: run a scenario and print its summary.

Exit codes: 0 mission completed with every SPEC invariant within tolerance, 1 an invariant
was violated, 2 bad command line or config (one line on stderr, no traceback), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import math
import sys
import typing
from collections.abc import Sequence

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from sim_world.kinematics import InitialPlacementError
from swarm.checks import check_invariants, summarize_drones, summarize_targets
from swarm.config import ConfigError, ScenarioConfig, load_config
from swarm.core.agent import StepDiagnostics
from swarm.reference import RunRecord, run_reference

EXIT_OK, EXIT_VIOLATION, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
HEADLESS_LOG_PERIOD_S = 5.0  # sim seconds between one-line progress logs


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63), got {text!r}")
    return value


class _OneLineParser(argparse.ArgumentParser):
    """argparse prints the usage block before an error; we keep errors to one line."""

    def error(self, message: str) -> typing.NoReturn:
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def fail(message: str) -> int:
    """One plain line on stderr: never wrapped, never styled, no traceback."""
    print(f"launch-swarm: {' '.join(message.split())}", file=sys.stderr)
    return EXIT_USAGE


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(
        prog="launch-swarm",
        description="Run a Vigil scenario: N camera drones keeping M targets localized.")
    parser.add_argument("config", help="scenario file, e.g. configs/case1.toml")
    parser.add_argument("--inprocess", action="store_true",
                        help="run every drone in this process (the reference simulator)")
    parser.add_argument("--seed", type=_seed, default=None,
                        help="random seed (default: scenario.seed of the config)")
    parser.add_argument("--duration", type=_positive_float, default=None, metavar="S",
                        help="simulated seconds (default: scenario.duration_s)")
    parser.add_argument("--headless", action="store_true",
                        help="no live display: a one-line log every few simulated seconds")
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

    def __call__(self, step: int, diagnostics: list[StepDiagnostics]) -> None:
        time_s = diagnostics[0].time_s
        lam = [min(float(d.lambda_bar[r]) for d in diagnostics)
               for r in range(len(diagnostics[0].lambda_bar))]
        status = "λ̄ min " + " ".join(f"{v:.3f}" for v in lam)
        if self._progress is not None:
            self._progress.update(self._task, advance=1, status=f"t={time_s:5.1f}s {status}")
        elif time_s + 1e-9 >= self._next_log_s:
            speeds = [float((d.velocity @ d.velocity) ** 0.5) for d in diagnostics]
            self._console.print(
                f"t={time_s:6.2f}s  {status}  max|u| {max(speeds):.2f} m/s  "
                f"fallbacks {sum(d.qp_fallback for d in diagnostics)}", highlight=False)
            self._next_log_s += HEADLESS_LOG_PERIOD_S


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
        config = load_config(args.config)
        if args.duration is not None:
            config = config.with_duration(args.duration)
    except ConfigError as err:
        return fail(f"config error: {err}")
    if not args.inprocess:
        return fail("the multi-process swarm is not available yet; run with --inprocess")
    try:
        with _ProgressReporter(config, console, args.headless) as reporter:
            record = run_reference(config, args.seed, on_step=reporter)
    except InitialPlacementError as err:
        return fail(f"config error: {config.source}: swarm.initial_box_size_m: {err}")
    except KeyboardInterrupt:
        print("launch-swarm: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    return print_summary(record, console)


if __name__ == "__main__":
    sys.exit(main())
