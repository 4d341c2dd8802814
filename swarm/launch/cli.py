"""``launch-swarm``: run a scenario — as a process swarm, or in-process — and summarize it.

Exit codes: 0 mission completed with every SPEC invariant within tolerance, 1 an invariant
was violated or the mission failed (a process died, the world aborted) or, in realtime, went
on after losing an agent, 2 bad command line or config (one line on stderr, no traceback),
130 interrupted (Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import argparse
import atexit
import dataclasses
import math
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.mavlink.sitl import (
    ENV_ARDUCOPTER,
    ENV_PX4,
    ENV_VARIABLE,
    KINDS,
    Firmware,
    FirmwareError,
    firmware_from_env,
)
from swarm.observe.dashboard import Dashboard, DashboardSettings, InProcessFeed
from swarm.observe.live_view import check_address
from swarm.observe.recording.schema import RECORDING_FILE
from swarm.observe.recording.writer import record_directory, record_reference
from swarm.observe.run_observer import print_process_counters, print_summary
from swarm.runs.reference import run_reference
from swarm.scenario.cli_common import (
    DEFAULT_MAVLINK_BASE,
    EXIT_FAILED,
    EXIT_OK,
    ConfigError,
    OneLineParser,
    UsageError,
    VigilError,
    add_foxglove_argument,
    add_gcs_arguments,
    config_assignment,
    exit_code,
    fail_on,
    gcs_problem,
    load_scenario,
    port,
    positive_float,
    restart_count,
    run_id,
    run_main,
    seed,
    terminate_on_sigterm,
)
from swarm.scenario.config import (
    ScenarioConfig,
    config_to_toml,
    realtime_only_reason,
    write_resolved_config,
)

PROG = "launch-swarm"
# Live tables at 4 Hz at most on a terminal; a line every 5 simulated seconds otherwise.
DASHBOARD = DashboardSettings(refresh_hz=4.0, log_period_s=5.0)


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
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        type=config_assignment, dest="overrides",
                        help="change one config value by its dotted key, checked as if the "
                             "file said so (repeatable; e.g. gramian.epsilon=0.06, "
                             "targets.0.velocity_m_s=[0.4,0,0], swarm.n_drones=12: the graph "
                             "and start box fitted; docs/sweeps.md, 'A sweep file')")
    parser.add_argument("--headless", action="store_true",
                        help="no live display: a one-line log every few simulated seconds")
    parser.add_argument("--mavlink-base", type=port, default=0, metavar="PORT",
                        help=f"vehicle i talks to agent i on UDP PORT+i (default: "
                             f"{DEFAULT_MAVLINK_BASE}, or the next free, quiet block)")
    add_gcs_arguments(parser)
    add_foxglove_argument(parser)
    parser.add_argument("--run-id", type=run_id, default=None,
                        help="Zenoh key prefix vigil/<run-id>/ (default: random)")
    parser.add_argument("--log-dir", default=None, metavar="DIR",
                        help="where each process writes its log (default: a temp dir)")
    parser.add_argument("--agent-restarts", type=restart_count, default=0, metavar="N",
                        help="realtime: restart an agent that dies during the mission (same "
                             "id; it rejoins the swarm) up to N times (default 0: the mission "
                             "goes on without it)")
    parser.add_argument("--agent-restart-delay", type=positive_float, default=2.0, metavar="S",
                        help="seconds between an agent's loss and its restart (default 2)")
    parser.add_argument("--kill-agent", action="append", default=[], metavar="I@S",
                        type=agent_kill, dest="kill_agents",
                        help="realtime fault injection: SIGKILL drone I's agent at mission time "
                             "S seconds, as if its companion computer died (repeatable; with "
                             "--agent-restarts it comes back)")
    parser.add_argument("--sitl", default=None, metavar="PATH",
                        help="fly real autopilot firmware: one SITL instance per drone, started "
                             "and stopped here: PATH is the arducopter SITL binary or a PX4 "
                             "SITL build directory (bin/px4, etc/); 'ardupilot' or 'px4' take "
                             f"it from ${ENV_ARDUCOPTER} or ${ENV_PX4} (realtime)")
    parser.add_argument("--sitl-param", action="append", default=[], metavar="NAME=VALUE",
                        type=sitl_parameter, dest="sitl_params",
                        help="--sitl: set this autopilot parameter at boot on every instance, "
                             "after the swarm's own (repeatable; e.g. a failsafe to try)")
    parser.add_argument("--mavlink", action="append", default=[], metavar="I=URL",
                        type=mavlink_assignment,
                        help="drone I flies the autopilot at this pymavlink URL, started "
                             "elsewhere (repeat for every drone; or vehicles.mavlink_urls in "
                             "the config); the world then serves no vehicles (realtime)")
    parser.add_argument("--record", type=record_directory, default=None, metavar="DIR",
                        help="write DIR/run.mcap as the run goes: telemetry, beacons, "
                             "detections and truth with their sim time, and the resolved "
                             "config (MCAP, JSON; Foxglove reads it)")
    parser.add_argument("--overwrite", action="store_true",
                        help="with --record: replace the recording DIR already holds (without "
                             "it, such a DIR is refused before anything starts)")
    parser.add_argument("--print-config", action="store_true",
                        help="print the resolved config as TOML (every value the run would "
                             "use: the defaults filled in, --seed, --duration and the tracking "
                             "margins fitted to --sitl/--mavlink applied) and exit 0; nothing "
                             "is started")
    return parser


def sitl_parameter(text: str) -> tuple[str, float]:
    """argparse type of ``--sitl-param NAME=VALUE``."""
    name, sep, value = text.partition("=")
    name = name.strip()
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not sep or not name or not name.replace("_", "").isalnum() or len(name) > 16 \
            or not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE with a parameter name of at "
                                         f"most 16 letters, digits or _ and a finite number "
                                         f"(e.g. BATT_LOW_VOLT=11.5), got {text!r}")
    return name.upper(), number


def agent_kill(text: str) -> tuple[int, float]:
    """argparse type of ``--kill-agent I@S``."""
    drone, sep, when = text.partition("@")
    try:
        time_s = float(when)
    except ValueError:
        time_s = math.nan
    if not sep or not drone.strip().isdigit() or not (math.isfinite(time_s) and time_s > 0):
        raise argparse.ArgumentTypeError(f"expected I@S, a drone id and a mission time in "
                                         f"seconds > 0 (e.g. 1@12.5), got {text!r}")
    return int(drone), time_s


def mavlink_assignment(text: str) -> tuple[int, str]:
    """argparse type of ``--mavlink I=URL``."""
    drone, sep, url = text.partition("=")
    if not sep or not drone.strip().isdigit() or not url.strip() or " " in url.strip():
        raise argparse.ArgumentTypeError(f"expected I=URL (e.g. 0=udpin:127.0.0.1:14540), "
                                         f"got {text!r}")
    return int(drone), url.strip()


def sitl_firmware(value: str | None) -> Firmware | None:
    """``--sitl``: a path, or 'ardupilot'/'px4' for the build named by its environment
    variable; SitlError (one line) when unusable."""
    if value is None:
        return None
    if value in KINDS:
        firmware = firmware_from_env(value)
        if firmware is None:
            variable = ENV_VARIABLE[value]
            raise FirmwareError(f"--sitl {value}: ${variable} is not set (give the path of the "
                                f"build instead)")
        return firmware
    return Firmware.at(value)


def with_mavlink_urls(config: ScenarioConfig, urls: dict[int, str]) -> ScenarioConfig:
    """The config with ``--mavlink I=URL`` for every drone in ``vehicles.mavlink_urls``."""
    if not urls:
        return config
    n = config.swarm.n_drones
    missing = sorted(set(range(n)) - set(urls))
    extra = sorted(set(urls) - set(range(n)))
    if extra:
        raise ConfigError(f"--mavlink: drone ids {extra} out of range 0..{n - 1}")
    if missing:
        raise ConfigError(f"--mavlink: give a connection string for every drone (missing "
                          f"{missing})")
    vehicles = dataclasses.replace(config.vehicles,
                                   mavlink_urls=tuple(urls[i] for i in range(n)))
    return dataclasses.replace(config, vehicles=vehicles)


def resolved_config_file(config: ScenarioConfig) -> str:
    """``config`` written where the world and agents read it (removed at exit)."""
    directory = Path(tempfile.mkdtemp(prefix="vigil-set-"))
    atexit.register(shutil.rmtree, directory, ignore_errors=True)
    return str(write_resolved_config(config, directory / "config.json"))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_main(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """``main`` after parsing: input that cannot be used raises a ``UsageError`` (a
    ``ConfigError`` for the config), which ``run_main`` prints as one line."""
    console = Console()
    if not console.is_terminal:
        console = Console(width=140)  # logs and CI: keep table columns unwrapped
    config = load_scenario(args.config, args.duration, overrides=args.overrides)
    seed_value = config.scenario.seed if args.seed is None else args.seed
    sitl = sitl_firmware(args.sitl)
    config = with_mavlink_urls(config, dict(args.mavlink))
    real = sitl is not None or bool(config.vehicles.mavlink_urls)
    if real:  # the tracking margins the config leaves out: the firmware's fitted ones
        autopilot = sitl.kind if sitl is not None else config.vehicles.flavour
        config = with_mavlink_urls(load_scenario(args.config, args.duration,
                                                 autopilot=autopilot, overrides=args.overrides),
                                   dict(args.mavlink))
    if args.print_config:
        sys.stdout.write(config_to_toml(config.with_seed(seed_value)))
        return EXIT_OK
    reason = realtime_only_reason(config.vehicles, mode=args.mode, inprocess=args.inprocess,
                                  external=real, restarts_agents=bool(args.agent_restarts),
                                  kills_agents=bool(args.kill_agents))
    if reason is not None:
        raise UsageError(reason)
    if args.sitl_params and sitl is None:
        raise UsageError("--sitl-param needs --sitl (it sets parameters on the SITL "
                         "autopilots launch-swarm starts)")
    problem = record_dir_problem(args.record, overwrite=args.overwrite)
    if problem is not None:
        raise UsageError(problem)
    if sitl is not None and config.vehicles.mavlink_urls:
        raise UsageError("--sitl starts its own autopilots: leave out --mavlink and "
                         "vehicles.mavlink_urls")
    problem = gcs_problem(args.gcs, args.gcs_control,
                          signing=bool(config.vehicles.signing_key_file))
    if problem is not None:
        raise UsageError(problem)
    if args.gcs is not None and (args.inprocess or sitl is not None
                                 or config.vehicles.mavlink_urls):
        raise UsageError("--gcs gives the world's emulated vehicles a ground-station link; "
                         "with --inprocess there are none, and real autopilots have their own "
                         "(PX4 SITL sends to 14550)")
    if args.foxglove is not None and args.inprocess:
        raise UsageError("--foxglove serves a process swarm as it runs; --inprocess runs as "
                         "fast as it can: record it (--record DIR) and open DIR/run.mcap in "
                         "Foxglove")
    if args.foxglove is not None:  # before any process starts: a taken port is found now,
        check_address(*args.foxglove)  # not after SITL boots
    options = None
    if not args.inprocess:
        config_path = str(Path(args.config).resolve())
        if args.overrides:  # the children read the config as resolved here, --set applied
            config_path = resolved_config_file(config)
        options = LaunchOptions(
            config=config, config_path=config_path, seed=seed_value,
            mode=args.mode, run_id=args.run_id or "", mavlink_base=args.mavlink_base,
            log_dir=Path(args.log_dir) if args.log_dir else None, record_dir=args.record,
            agent_restarts=args.agent_restarts,
            agent_restart_delay_s=args.agent_restart_delay, sitl=sitl,
            sitl_params=tuple(args.sitl_params), kill_agents=tuple(args.kill_agents),
            defer_log_cleanup=True,  # removed below if the run succeeds, verdict and all
            gcs=args.gcs, gcs_control=args.gcs_control, foxglove=args.foxglove)
    terminate_on_sigterm()
    launcher: SwarmLauncher | None = None

    def failed(code: int) -> int:
        """A run that did not succeed keeps the temporary log directory, and says so."""
        if launcher is not None:
            launcher.finish_log_dir(success=False)
        return code

    try:
        if args.inprocess:
            with Dashboard(config, console, headless=args.headless,
                           settings=DASHBOARD) as dashboard:
                feed = InProcessFeed(dashboard)
                record = run_reference(config, seed_value, on_step=feed) \
                    if args.record is None else \
                    record_reference(config, seed_value, args.record, on_step=feed)
        else:
            assert options is not None
            launcher = SwarmLauncher(options, log=lambda line: console.print(
                line, highlight=False, markup=False))
            with Dashboard(config, console, headless=args.headless,
                           settings=DASHBOARD) as dashboard:
                # The dashboard is one more telemetry consumer; the truth step is its clock.
                record = launcher.run(on_progress=lambda step, _c: dashboard.advance(step),
                                      telemetry_listeners=[dashboard.on_telemetry])
            print_process_counters(launcher.collector, console)
            counters = launcher.collector.drone_counters()
    except VigilError as err:  # said here, before the log directory kept is said
        return failed(fail_on(PROG, err))
    except KeyboardInterrupt as err:
        print(f"{PROG}: interrupted; every process stopped", file=sys.stderr)
        return failed(exit_code(err))
    if args.inprocess:
        return print_summary(record, console)
    assert launcher is not None
    code = print_summary(record, console, args.mode, counters)
    if launcher.recording_problem is not None:  # the run is fine, its record is not whole
        print(f"{PROG}: recording incomplete: {launcher.recording_problem}", file=sys.stderr)
        code = EXIT_FAILED
    elif launcher.agent_losses:  # the mission went on, degraded: not a clean run
        lost = ", ".join(f"drone {loss.drone} at {loss.time_s:.1f} s ({loss.how}"
                         f"{', restarted' if loss.restarted else ''})"
                         for loss in launcher.agent_losses)
        print(f"{PROG}: the mission went on after losing agents: {lost}", file=sys.stderr)
        code = EXIT_FAILED
    launcher.finish_log_dir(success=code == 0)
    return code


def record_dir_problem(directory: Path | None, *, overwrite: bool) -> str | None:
    """Why ``--record DIR`` cannot be used as given (None: it can): DIR already holds a
    recording and ``--overwrite`` was not given, or ``--overwrite`` without ``--record``."""
    if directory is None:
        return "--overwrite needs --record DIR (it replaces the recording in DIR)" \
            if overwrite else None
    existing = directory / RECORDING_FILE
    if existing.exists() and not overwrite:
        return (f"--record {directory}: {existing} holds a recording already; record to "
                f"another directory, or add --overwrite to replace it")
    return None


if __name__ == "__main__":
    sys.exit(main())
