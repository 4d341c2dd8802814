"""``swarm-sweep``: thousands of missions from one file, on Dask (docs/sweeps.md).

    swarm-sweep SWEEP.toml --out DIR [--scheduler tcp://HOST:8786] [--workers N]
    swarm-sweep report DIR [--heatmap AXIS [AXIS]] [--columns KEY ...]

The first validates every point of the sweep (one line and exit 2 for the first bad one,
nothing started), runs the points ``DIR/results.jsonl`` does not hold yet, appending a row as
each mission ends, then prints the per-cell summary and writes the figures into DIR. The
second prints the summary and redraws the figures from ``DIR/results.jsonl`` alone.

Exit codes: 0 every mission of the sweep OK (with a ``[gate]``: the gate held,
``swarm.sweep.gate``); 1 one VIOLATED or FAILED (the gate not held); 2 bad command line,
sweep file, point or results file (one line on stderr, no traceback); 130 interrupted
(Ctrl-C or SIGTERM: the missions stopped, the rows written so far kept; the same command
again runs the rest).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from swarm.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, UsageError, run_main
from swarm.scenario.cli_common import OneLineParser, fail
from swarm.sweep.driver import new_stop_event, run_sweep
from swarm.sweep.gate import judge_gate
from swarm.sweep.plan import local_workers, plan_sweep
from swarm.sweep.results import RESULTS_FILE, ResultsWriter, read_rows
from swarm.sweep.rows import OK
from swarm.sweep.spec import GateSpec, check_columns
from swarm.sweep.stats import cell_stats
from swarm.sweep.summary import render_summary, write_figures, write_summary

PROG = "swarm-sweep"


def worker_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 1 <= value <= 1024:
        raise argparse.ArgumentTypeError(f"must be in [1, 1024], got {text!r}")
    return value


def scheduler_address(text: str) -> str:
    if not text.startswith(("tcp://", "tls://", "ws://", "wss://", "inproc://")) \
            or ":" not in text.split("://", 1)[1]:
        raise argparse.ArgumentTypeError(f"expected a Dask scheduler address such as "
                                         f"tcp://HOST:8786, got {text!r}")
    return text


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog=PROG, description="Run a sweep of Vigil missions on Dask (local by default); "
                               "'swarm-sweep report DIR' redraws a sweep's summary.")
    parser.add_argument("sweep", help="the sweep file (docs/sweeps.md, 'A sweep file')")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="where results.jsonl, the summary and the figures go; a DIR "
                             "holding results of this sweep is resumed")
    parser.add_argument("--scheduler", type=scheduler_address, default=None,
                        metavar="tcp://HOST:PORT",
                        help="run on this Dask scheduler's workers (dask scheduler / dask "
                             "worker, dask-jobqueue) instead of a local cluster")
    parser.add_argument("--workers", type=worker_count, default=None, metavar="N",
                        help="the local cluster's worker processes (default: one per CPU; one "
                             "for realtime and SITL missions)")
    return parser


def build_report_parser() -> OneLineParser:
    parser = OneLineParser(prog=f"{PROG} report",
                           description="The summary and figures of a sweep, from its "
                                       "results.jsonl alone.")
    parser.add_argument("directory", type=Path, metavar="DIR")
    parser.add_argument("--heatmap", nargs="+", default=None, metavar="AXIS",
                        help="the heatmap's one or two axes (default: the first two axes "
                             "with more than one value)")
    parser.add_argument("--columns", nargs="+", default=[], metavar="KEY",
                        help="row keys shown per cell as ranges, dotted into a row's tables "
                             "(e.g. tracking.velocity_error_rms_m_s loss.said)")
    return parser


def _console() -> Console:
    console = Console()
    if not console.is_terminal:
        console = Console(width=160)
    return console


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["report"]:
        report_argv = argv[1:]
        return run_main(PROG, lambda: report_main(report_argv), context="report: ")
    args = build_parser().parse_args(argv)
    return run_main(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """The sweep after parsing: a sweep file, point or results file that cannot be used raises
    a ``UsageError``, which ``run_main`` prints as one line."""
    if args.scheduler is not None and args.workers is not None:
        raise UsageError("--workers sizes the local cluster; with --scheduler the cluster is "
                         "the one its workers make")
    console = _console()
    stop_event = new_stop_event()
    plan = plan_sweep(Path(args.sweep), args.out, stop_event=stop_event,
                      check_firmware=args.scheduler is None)
    writer = ResultsWriter(args.out)
    keys = {t.key for t in plan.tasks}
    already = len(keys & writer.keys)
    workers = args.workers or local_workers(plan.spec)
    where = args.scheduler or f"a local Dask cluster of {workers} worker process(es)"
    console.print(f"{PROG}: {len(plan.tasks)} missions ({plan.spec.mode}, code "
                  f"{plan.code_version}); {already} done already in "
                  f"{writer.path}; {len(plan.tasks) - already} to run on {where}",
                  highlight=False)
    try:
        with writer:
            outcome = run_sweep(plan, writer, console, scheduler=args.scheduler,
                                workers=workers, stop_event=stop_event)
            rows = [row for row in writer.rows if row["key"] in keys]
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted again: left at once; the rows written are whole",
              file=sys.stderr)
        raise
    if outcome.interrupted:
        print(f"{PROG}: interrupted: {len(rows)} of {len(plan.tasks)} missions in "
              f"{writer.path}; run the same command to run the rest", file=sys.stderr)
        return EXIT_INTERRUPTED
    return _summarize(rows, args.out, console, plan.spec.heatmap,
                      f"{plan.path.name}: {len(rows)} missions", plan.spec.gate,
                      plan.spec.columns)


def _summarize(rows: list[dict], out: Path, console: Console, heatmap: Sequence[str],
               title: str, gate: GateSpec | None = None, columns: Sequence[str] = ()) -> int:
    cells = cell_stats(rows, columns=columns)
    render_summary(cells, console, title)
    try:
        written = [write_summary(cells, out), *write_figures(cells, out, heatmap)]
    except OSError as err:  # the run is done and its rows kept: not the input's fault
        return fail(PROG, f"{out}: cannot write the summary: {err.strerror or err}",
                    EXIT_FAILED)
    console.print("wrote " + ", ".join(str(p) for p in written), highlight=False)
    if gate is not None:
        verdict = judge_gate(gate, rows, cells)
        for line in verdict.lines:
            console.print(line, highlight=False, markup=False)
        return EXIT_OK if verdict.held else EXIT_FAILED
    return EXIT_OK if all(row["verdict"] == OK for row in rows) else EXIT_FAILED


def report_main(argv: Sequence[str]) -> int:
    """``swarm-sweep report DIR``; its ``UsageError``s are said after "report: "."""
    args = build_report_parser().parse_args(argv)
    path = args.directory / RESULTS_FILE
    if not path.is_file():
        raise UsageError(f"{path}: no such file (swarm-sweep SWEEP.toml --out "
                         f"{args.directory} writes it)")
    rows = read_rows(path)
    if not rows:
        raise UsageError(f"{path}: no rows")
    axes = rows[0].get("axes", [])
    for key in args.heatmap or ():
        if key not in axes:
            raise UsageError(f"--heatmap {key}: not an axis of this sweep (axes: "
                             f"{', '.join(axes) or 'none'})")
    if args.heatmap is not None and len(args.heatmap) > 2:
        raise UsageError("--heatmap takes one or two axes")
    columns = check_columns(args.columns, where="--columns")
    return _summarize(rows, args.directory, _console(), args.heatmap or (),
                      f"{path}: {len(rows)} missions", columns=columns)


if __name__ == "__main__":
    sys.exit(main())
