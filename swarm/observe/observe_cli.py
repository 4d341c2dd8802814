"""``swarm-observe``: watch, record and judge a swarm started elsewhere (by hand, across
machines, or by another ``launch-swarm``).

A Zenoh client of the world's router, as ``launch-swarm`` is (``RunObserver``): it shows the
dashboard (``--headless``: a line every few simulated seconds), records with ``--record DIR``
the same ``DIR/run.mcap`` as ``launch-swarm --record``, and when the world says "done" prints
the same end-of-mission tables and verdict (``print_process_counters``, ``print_summary``).
Ctrl-C (or SIGTERM) stops watching, not the swarm: the tables and verdict then cover the steps
seen so far.

It gets the run's ``--run-id``, ``--seed`` and ``--duration``, as every process of the swarm
does; ``--mode`` is taken from the world's clock unless given (a mode or duration that
disagrees with the world's is a usage error).

Exit codes, as ``launch-swarm``'s: 0 mission done with every SPEC invariant within tolerance,
1 an invariant was violated, the world aborted or went silent, the router could not be reached
or the recording is incomplete, 2 bad command line, config, or a run that is not the one
described, 130 interrupted (the tables of what was seen are printed first).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console

from swarm.errors import EXIT_FAILED, EXIT_INTERRUPTED, UsageError, VigilError, run_main
from swarm.messages.wire import ClockWire
from swarm.net.session import check_tls_endpoints
from swarm.net.subscriptions import subscribe
from swarm.observe.dashboard import Dashboard, DashboardSettings
from swarm.observe.live_view import check_address
from swarm.observe.recording.schema import RecordingMetadata
from swarm.observe.recording.writer import record_directory
from swarm.observe.run_observer import RunObserver, print_process_counters, print_summary
from swarm.runs.record import RunRecord
from swarm.scenario.cli_common import (
    OneLineParser,
    add_foxglove_argument,
    add_run_arguments,
    fail,
    load_scenario,
    positive_float,
    terminate_on_sigterm,
)
from swarm.scenario.config import ScenarioConfig

PROG = "swarm-observe"
READY = "subscribed to run"  # the line's words once every subscription is made
POLL_S = 0.1  # how often the clock is looked at (a state change wakes the loop at once)
# The world publishes its clock every 0.5 s while waiting for the drones, every 0.25 s (wall)
# while running and every 0.1 s after "done": this long without one, it is gone.
WORLD_SILENCE_S = 30.0
# After "done": wait this long at most for every drone's telemetry of the last step seen (an
# agent's last batch may follow the world's "done"; a drone lost in realtime never sends it).
DONE_GRACE_S = 5.0


class ObserveError(VigilError, RuntimeError):
    """The run could not be observed (no clock from the world); one line saying why."""


@dataclass(frozen=True)
class Observation:
    """How watching ended, and what was seen."""

    ending: str  # "done", "aborted", "silent" or "interrupted"
    detail: str  # the world's words for an abort; what went silent
    mode: str  # the run's timing mode, as its clock says (or as given)
    record: RunRecord  # the steps seen (gaps filled, as launch-swarm's)
    observer: RunObserver  # its collector's counters; its recording problem, if any


class RemoteObserver(RunObserver):
    """A ``RunObserver`` of a swarm it did not start: it follows the world's clock."""

    def __init__(self, config: ScenarioConfig, run_id: str, *, prog: str = PROG,
                 log: Callable[[str], None] = print) -> None:
        super().__init__(config, run_id, prog=prog, log=log)

    def first_clock(self, timeout_s: float, stop: threading.Event) -> ClockWire:
        """The world's clock, heard on a subscription of its own (before the others are made:
        the recording's metadata needs the run's mode), and kept as ``clock``;
        ``ObserveError`` if none comes within ``timeout_s``."""
        assert self.session is not None, "connect first"
        heard: list[ClockWire] = []
        came = threading.Event()

        def on_clock(_key: str, clock: ClockWire) -> None:
            heard.append(clock)
            came.set()

        sub = subscribe(self.session, self.keys.clock, self.codec.decode_clock, on_clock,
                        self.rejections, "clock")
        try:
            deadline = time.monotonic() + timeout_s
            while not came.wait(POLL_S):
                if stop.is_set():
                    raise KeyboardInterrupt
                if time.monotonic() > deadline:
                    raise ObserveError(f"no clock of run {self.run_id!r} within "
                                       f"{timeout_s:g} s: is the run id right, and is its world "
                                       f"running?")
        finally:
            sub.undeclare()
        self.clock.put(0, heard[0])  # the clock of record until the feed brings a newer one
        return heard[0]

    def check_clock(self, clock: ClockWire, mode: str) -> None:
        """``UsageError`` when the world's clock says the run has another mode (the
        recording would say the wrong one)."""
        if clock.mode != mode:
            raise UsageError(f"run {self.run_id} runs in {clock.mode}, not {mode}: give "
                             f"--mode {clock.mode} (or leave --mode out)")

    def _telemetry_caught_up(self) -> bool:
        """Every drone's telemetry has reached the last truth step seen."""
        collector = self.collector
        with collector.lock:
            steps = [tel.step for tel in collector.latest.values()]
            last = collector.last_truth_step
        return len(steps) == self.config.swarm.n_drones and min(steps) >= last

    def follow(self, mode: str, *, on_progress: Callable[[int], None], stop: threading.Event,
               silence_s: float = WORLD_SILENCE_S,
               done_grace_s: float = DONE_GRACE_S) -> tuple[str, str]:
        """Follow the world's clock until "done" (and the last telemetry, ``done_grace_s`` at
        most), "aborted", ``silence_s`` without a clock ("silent") or ``stop`` / Ctrl-C
        ("interrupted"); (that ending, detail). ``on_progress(step)`` runs on this thread
        whenever the step moves (the newest of the truth's and the running clock's)."""
        last_progress = -1
        done_at: float | None = None
        longer = False  # the run goes on past this observer's duration (said once)
        try:
            while not stop.is_set():
                self._state_changed.wait(POLL_S)
                self._state_changed.clear()
                latest = self.clock.get(0)
                if latest is None:
                    continue
                clock, age_s = latest
                self.check_clock(clock, mode)
                if clock.state == "aborted":
                    return "aborted", clock.detail
                if age_s > silence_s:
                    return "silent", f"no clock from the world for {silence_s:g} s"
                if clock.state == "running" and clock.step >= self.config.n_steps and not longer:
                    longer = True  # a shorter run ends early, which the report says
                    self.log(f"{self.prog}: run {self.run_id} lasts longer than "
                             f"{self.config.scenario.duration_s:g} s: the tables cover that "
                             f"much of it (give the world's --duration)")
                # The truth's step (as launch-swarm's dashboard), or the clock's if ahead.
                step = max(self.collector.last_truth_step,
                           clock.step if clock.state == "running" else -1)
                if step != last_progress:
                    last_progress = step
                    on_progress(step)
                if clock.state == "done":
                    done_at = done_at or time.monotonic()
                    if self._telemetry_caught_up() or time.monotonic() - done_at > done_grace_s:
                        return "done", clock.detail
        except KeyboardInterrupt:
            pass
        return "interrupted", ""


def observe_run(endpoints: Sequence[str], run_id: str, config: ScenarioConfig, *,
                console: Console, headless: bool = False,
                settings: DashboardSettings | None = None, mode: str | None = None,
                seed: int | None = None, config_path: str = "", record_dir: Path | None = None,
                foxglove: tuple[str, int] | None = None, connect_timeout_s: float = 30.0,
                silence_s: float = WORLD_SILENCE_S, stop: threading.Event | None = None,
                prog: str = PROG) -> Observation:
    """Watch the run ``run_id`` behind the router at ``endpoints`` until it ends (see
    ``RemoteObserver.follow``), with the dashboard on ``console``, recording to
    ``record_dir`` and serving the live view at ``foxglove`` if given; the record of what was
    seen. ``mode`` None: the world's. Raises ``TransportError`` (router not reached within
    ``connect_timeout_s``), ``ObserveError`` (no clock), ``RecordingError``,
    ``LiveViewError``, ``UsageError`` (mode or duration not the run's) and
    ``KeyboardInterrupt`` before the subscriptions are made."""
    stop = stop or threading.Event()
    seed = config.scenario.seed if seed is None else seed
    observer = RemoteObserver(config, run_id, prog=prog, log=lambda line: console.print(
        line, highlight=False, markup=False))
    started = time.monotonic()
    try:
        if foxglove is not None:
            observer.open_live_view(foxglove)
        def stopped() -> None:
            if stop.is_set():
                raise KeyboardInterrupt

        observer.connect(endpoints, connect_timeout_s, before_each_try=stopped, pause=stop.wait)
        clock = observer.first_clock(silence_s, stop)
        mode = mode or clock.mode
        observer.check_clock(clock, mode)
        if record_dir is not None:
            observer.open_recorder(record_dir, RecordingMetadata.for_run(
                config, seed, mode, run_id, config_path))
        with Dashboard(config, console, headless=headless, settings=settings,
                       title=f"{config.scenario.name} ({run_id})") as dashboard:
            observer.telemetry_listeners = (dashboard.on_telemetry,)
            observer.subscribe()
            observer.log(f"{prog}: {READY} {run_id} at {', '.join(endpoints)} ({mode}, world "
                         f"{clock.state})")
            ending, detail = observer.follow(mode, on_progress=dashboard.advance, stop=stop,
                                             silence_s=silence_s)
        observer.stop_observing()  # nothing arrives after this: record and recording agree
        record = observer.collector.record(seed, time.monotonic() - started)
    finally:
        observer.stop_observing()
    return Observation(ending, detail, mode, record, observer)


def build_parser(prog: str = PROG) -> OneLineParser:
    parser = OneLineParser(
        prog=prog, description="Watch a running Vigil swarm, record it, and print its "
                               "end-of-mission tables and verdict as launch-swarm does.")
    parser.add_argument("config", help="the scenario the swarm runs")
    parser.add_argument("--connect", required=True, action="append", metavar="ENDPOINT",
                        help="the world's Zenoh router, e.g. tcp/192.168.1.10:7447 "
                             "(repeatable)")
    add_run_arguments(parser, run_id_help="the swarm's run id (default: vigil, as sim-world's)")
    parser.set_defaults(mode=None)  # the world's clock says it
    parser.add_argument("--headless", action="store_true",
                        help="no live display: a one-line log every few simulated seconds")
    parser.add_argument("--record", type=record_directory, default=None, metavar="DIR",
                        help="write DIR/run.mcap as launch-swarm --record does")
    parser.add_argument("--connect-timeout", type=positive_float, default=30.0, metavar="S",
                        help="keep trying the router this long (default 30 s)")
    add_foxglove_argument(parser)
    return parser


def main(argv: Sequence[str] | None = None, *, prog: str = PROG) -> int:
    args = build_parser(prog).parse_args(argv)
    return run_main(prog, lambda: _run(args, prog))


def _run(args: argparse.Namespace, prog: str) -> int:
    """``main`` after parsing: input that cannot be used raises a ``UsageError`` (a
    ``ConfigError`` for the config), a run that cannot be watched another ``VigilError``,
    which ``run_main`` prints as one line."""
    console = Console()
    if not console.is_terminal:
        console = Console(width=140)  # logs and CI: keep table columns unwrapped
    config = load_scenario(args.config, args.duration)
    check_tls_endpoints(args.connect, tls=config.security.enabled)
    terminate_on_sigterm()
    try:
        if args.foxglove is not None:  # a taken port is said now, not after the router
            check_address(*args.foxglove)
        seen = observe_run(args.connect, args.run_id, config, console=console,
                           headless=args.headless, mode=args.mode, seed=args.seed,
                           config_path=str(Path(args.config).resolve()),
                           record_dir=args.record, foxglove=args.foxglove,
                           connect_timeout_s=args.connect_timeout, prog=prog)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted before the run was reached", file=sys.stderr)
        raise
    return summarize(seen, console, prog)


def summarize(seen: Observation, console: Console, prog: str = PROG) -> int:
    """The end of ``main``: launch-swarm's summary of what was seen, and the exit code."""
    if seen.ending in ("aborted", "silent"):
        what = "the world aborted the mission" if seen.ending == "aborted" else "the world is gone"
        return fail(prog, f"mission failed: {what}: {seen.detail}", EXIT_FAILED)
    interrupted = seen.ending == "interrupted"
    if seen.record.n_steps == 0:
        return fail(prog, "interrupted before the mission started" if interrupted else
                    "the mission ended before any of it was seen", EXIT_INTERRUPTED
                    if interrupted else EXIT_FAILED)
    collector = seen.observer.collector
    print_process_counters(collector, console)
    code = print_summary(seen.record, console, seen.mode, collector.drone_counters())
    if seen.observer.recording_problem is not None:
        print(f"{prog}: recording incomplete: {seen.observer.recording_problem}",
              file=sys.stderr)
        code = EXIT_FAILED
    if interrupted:
        print(f"{prog}: interrupted at t = {seen.record.times_s[-1]:.2f} s; the tables cover "
              f"the steps seen (the swarm goes on)", file=sys.stderr)
        return EXIT_INTERRUPTED
    return code


if __name__ == "__main__":
    sys.exit(main())
