"""``sim-world``: the world process (targets, cameras, emulated MAVLink vehicles, Zenoh router)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from sim_world.fleet import mavlink_hosts
from sim_world.world import World, WorldOptions
from swarm.children import follow_parent
from swarm.net.session import check_tls_endpoints, local_endpoint
from swarm.scenario.cli_common import (
    DEFAULT_MAVLINK_BASE,
    OneLineParser,
    UsageError,
    add_gcs_arguments,
    add_run_arguments,
    fail_on,
    gcs_problem,
    load_scenario,
    port,
    run_main,
    terminate_on_sigterm,
)
from swarm.scenario.config import realtime_only_reason

PROG = "sim-world"


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog=PROG, description=(
        "Simulate targets, cameras and one PX4/ArduPilot-style MAVLink vehicle per drone; "
        "host the swarm's Zenoh router."))
    parser.add_argument("config", help="scenario file, e.g. configs/case1.toml")
    add_run_arguments(parser, run_id_help="Zenoh key prefix vigil/<run-id>/ (default: vigil)")
    parser.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                        help="Zenoh endpoint to listen on (default tcp/127.0.0.1:7447; "
                             "tls/... with [security])")
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to (another router), repeatable")
    parser.add_argument("--mavlink-host", default="127.0.0.1", metavar="HOST[,HOST...]",
                        help="where the agents listen for their vehicle: one address, or one "
                             "per drone comma-separated, drone 0 first (default 127.0.0.1)")
    parser.add_argument("--mavlink-base", type=port, default=DEFAULT_MAVLINK_BASE,
                        help=f"vehicle i sends to UDP port base+i (default "
                             f"{DEFAULT_MAVLINK_BASE}: no autopilot SITL sends there)")
    parser.add_argument("--vehicles", choices=("sim", "external"), default="sim",
                        help="external: serve no vehicles, take positions from beacons")
    add_gcs_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    follow_parent(PROG)  # started by launch-swarm: die with it (swarm.children)
    args = build_parser().parse_args(argv)
    return run_main(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """``main`` after parsing: input that cannot be used raises a ``UsageError`` (a
    ``ConfigError`` for the config), which ``run_main`` prints as one line."""
    config = load_scenario(args.config, args.duration)
    mavlink_hosts(args.mavlink_host, config.swarm.n_drones)
    gcs = args.gcs
    problem = gcs_problem(gcs, args.gcs_control,
                          signing=bool(config.vehicles.signing_key_file))
    if problem is not None:
        raise UsageError(problem)
    if gcs is not None and args.vehicles == "external":
        raise UsageError("--gcs: with --vehicles external the world serves no vehicles; "
                         "connect the ground station to the autopilots")
    reason = realtime_only_reason(config.vehicles, mode=args.mode,
                                  external=args.vehicles == "external")
    if reason is not None:
        raise UsageError(reason)
    check_tls_endpoints([*(args.listen or []), *args.connect], tls=config.security.enabled)
    terminate_on_sigterm()
    options = WorldOptions(
        config=config, seed=config.scenario.seed if args.seed is None else args.seed,
        run_id=args.run_id, mode=args.mode,
        listen=tuple(args.listen or [local_endpoint(7447, tls=config.security.enabled)]),
        connect=tuple(args.connect),
        mavlink_host=args.mavlink_host, mavlink_base=args.mavlink_base, vehicles=args.vehicles,
        gcs=gcs, gcs_control=args.gcs_control,
        log=lambda line: print(line, flush=True))
    world = None
    try:
        world = World(options)
        return world.run()
    except OSError as err:  # the OS refused a socket: not ours, but said in one line
        return fail_on(PROG, err, "cannot open the world's sockets: ")
    finally:
        if world is not None:
            world.close()


if __name__ == "__main__":
    sys.exit(main())
