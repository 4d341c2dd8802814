"""``sim-vehicles``: N emulated PX4/ArduPilot autopilots and nothing else, at 50 Hz.

A stand-in for N SITL instances: run ``sim-world --vehicles external --mode realtime`` for
the targets and cameras, this for the autopilots, and one ``swarm-agent`` per drone. Vehicle
i starts at the position the world would give drone i for the same config and seed, in the
air or on the ground below it (``[vehicles] start``), moving as ``[vehicles] response`` says.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from sim_world.fleet import VehicleFleet, serve_forever
from swarm.children import follow_parent
from swarm.models.frames import GeoPoint
from swarm.scenario.cli_common import (
    DEFAULT_MAVLINK_BASE,
    EXIT_OK,
    OneLineParser,
    UsageError,
    add_gcs_arguments,
    fail_on,
    gcs_problem,
    load_scenario,
    port,
    run_main,
    seed,
    terminate_on_sigterm,
)
from swarm.scenario.setup import initial_drone_positions

PROG = "sim-vehicles"


def build_parser() -> OneLineParser:
    parser = OneLineParser(prog=PROG, description=(
        "Serve one emulated PX4/ArduPilot-style MAVLink vehicle per drone (no targets, no "
        "cameras): a stand-in for SITL autopilots."))
    parser.add_argument("config", help="scenario file (drones, flavour, origins, u_max)")
    parser.add_argument("--seed", type=seed, default=None, help="default: scenario.seed")
    parser.add_argument("--mavlink-host", default="127.0.0.1")
    parser.add_argument("--mavlink-base", type=port, default=DEFAULT_MAVLINK_BASE,
                        help=f"vehicle i sends to UDP port base+i (default "
                             f"{DEFAULT_MAVLINK_BASE}: no autopilot SITL sends there)")
    add_gcs_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    follow_parent(PROG)  # started by launch-swarm: die with it (swarm.children)
    args = build_parser().parse_args(argv)
    return run_main(PROG, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    """``main`` after parsing: input that cannot be used raises a ``UsageError`` (a
    ``ConfigError`` for the config and its signing key), which ``run_main`` prints as one
    line."""
    config = load_scenario(args.config, None)
    signing_key = config.vehicles.signing_key()
    problem = gcs_problem(args.gcs, args.gcs_control, signing=signing_key is not None)
    if problem is not None:
        raise UsageError(problem)
    terminate_on_sigterm()
    seed_value = config.scenario.seed if args.seed is None else args.seed
    started = time.monotonic()
    try:
        fleet = VehicleFleet(
            initial_drone_positions(config, seed_value),
            [config.vehicles.origin_w(i) for i in range(config.swarm.n_drones)],
            config.vehicles.flavour, host=args.mavlink_host, base_port=args.mavlink_base,
            u_max_m_s=config.control.u_max_m_s,
            setpoint_timeout_s=config.vehicles.failsafe_timeout_s,
            clock=lambda: time.monotonic() - started, signing_key=signing_key,
            start=config.vehicles.start, response=config.vehicles.velocity_response,
            gcs=args.gcs, gcs_control=args.gcs_control,
            geo_origin=GeoPoint(*config.vehicles.geo_origin),
            log=lambda line: print(line, flush=True))
    except OSError as err:  # the OS refused a socket: not ours, but said in one line
        return fail_on(PROG, err, "cannot open the vehicles' sockets: ")
    print(f"sim-vehicles: {len(fleet)} {config.vehicles.flavour} vehicles sending to "
          f"{args.mavlink_host}:{args.mavlink_base}..{args.mavlink_base + len(fleet) - 1}"
          f"{', MAVLink 2 signing on' if signing_key is not None else ''}"
          f"{'' if args.gcs is None else ', ground station at {}:{}'.format(*args.gcs)}",
          flush=True)
    try:
        serve_forever(fleet, config.scenario.dt_s, started)
    finally:
        fleet.close()
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
