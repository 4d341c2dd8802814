"""``swarm-report DIR``: the report of a recorded run (``launch-swarm --record DIR``).

Prints a table per target and per drone and a verdict line; ``--json`` prints one JSON object
instead (warnings also go to stderr); ``--plots OUT`` writes the thesis figures as PNG files.

Exit codes: 0 every SPEC invariant held over the whole mission, 1 one was violated beyond
its tolerance (or had no sample to be checked on), 2 bad command line, unreadable recording
or unwritable plot directory (one line on stderr, no traceback), 4 the recording holds fewer
steps than the mission (Ctrl-C, a crash, a killed launcher, or still being written) and no
invariant was violated on the steps it holds: verdict INCOMPLETE, never OK. A violation in
such a run is exit 1, and its verdict says both.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from swarm.observe.recording.reader import Recording, read_recording
from swarm.observe.report import Provenance, RunReport, build_report, render_report, report_to_json
from swarm.scenario.cli_common import OneLineParser, UsageError, run_main

PROG = "swarm-report"


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog=PROG,
        description="Summarize a recorded Vigil run: per-target and per-drone tables, the "
                    "SPEC invariants, and optionally the thesis figures.")
    parser.add_argument("recording", metavar="DIR",
                        help="run directory holding run.mcap (launch-swarm --record DIR), or "
                             "the .mcap file itself")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object instead of the tables")
    parser.add_argument("--plots", metavar="OUT", type=Path, default=None,
                        help="write the figures (position_error.png, psi.png, weights.png, "
                             "speed.png, bearing_error.png with a formation task, view3d.png) "
                             "into OUT")
    return parser


def report_from_recording(recording: Recording) -> RunReport:
    """The report of a recording: its record, mode and the drones' own counters."""
    meta = recording.metadata
    return build_report(
        recording.record, meta.mode, recording.drone_counters,
        Provenance(run_id=meta.run_id, version=meta.version, git_commit=meta.git_commit,
                   source=str(recording.path), truncated=recording.truncated))


def _console() -> Console:
    console = Console()
    if not console.is_terminal:
        console = Console(width=140)  # pipes and CI: keep table columns unwrapped
    return console


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_main(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """``main`` after parsing: a recording that cannot be read raises a ``RecordingFileError``
    (a ``UsageError``), which ``run_main`` prints as one line."""
    recording = read_recording(Path(args.recording))
    report = report_from_recording(recording)
    written: list[Path] = []
    if args.plots is not None:
        # Before any output: a directory we cannot write is a usage error with empty stdout.
        try:
            from swarm.observe.plots import write_plots  # matplotlib loads only when asked for

            written = write_plots(recording.record, args.plots)
        except OSError as err:
            raise UsageError(f"cannot write plots to {args.plots}: "
                             f"{err.strerror or err}") from None
    if args.json:
        document = report_to_json(report)
        if args.plots is not None:
            document["plots"] = [str(path) for path in written]
        print(json.dumps(document, allow_nan=False))
        for warning in report.warnings:
            print(f"{PROG}: warning: {warning}", file=sys.stderr)
    else:
        console = _console()
        render_report(report, console)
        if written:
            console.print(f"wrote {len(written)} figures to {args.plots}: "
                          f"{', '.join(path.name for path in written)}", highlight=False,
                          markup=False)
    return report.exit_code


if __name__ == "__main__":
    sys.exit(main())
