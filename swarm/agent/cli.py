"""``swarm-agent``: one drone's process (the core's step between Zenoh and MAVLink).

Its ``udpin`` MAVLink socket is bound first, before pymavlink, numpy, the core and Zenoh are
imported (``swarm.mavlink.udpin``): the link's listening window for a second autopilot then
runs while they load instead of after.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

# pymavlink.mavutil imports its MAVLink 1 "all" dialect (every dialect in one module) at import
# time only so that PyInstaller bundles it: ~6 MB of RSS and ~0.1 s of CPU per agent, which
# speaks MAVLink 2 ardupilotmega only. None in sys.modules makes that optional import fail
# quietly (mavutil allows for its absence), and mavutil's own default dialect becomes ours.
sys.modules.setdefault("pymavlink.dialects.v10.all", None)  # type: ignore[arg-type]
os.environ.setdefault("MAVLINK20", "1")
os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")

from swarm.children import follow_parent  # noqa: E402
from swarm.errors import run_main  # noqa: E402
from swarm.mavlink.udpin import DEFAULT_MAVLINK_BASE, BoundSocket, bind_early  # noqa: E402

if TYPE_CHECKING:
    from swarm.scenario.cli_common import OneLineParser

PROG = "swarm-agent"


def build_parser() -> OneLineParser:
    from swarm.scenario.cli_common import (
        OneLineParser,
        add_run_arguments,
        fraction,
        step_count,
    )

    parser = OneLineParser(prog=PROG, description=(
        "Run drone I: estimate and keep every target localized, talking to graph neighbours "
        "over Zenoh and commanding the autopilot over MAVLink."))
    parser.add_argument("--id", type=int, required=True, metavar="I", help="drone id, 0..N-1")
    parser.add_argument("--config", required=True, metavar="FILE", help="scenario file")
    parser.add_argument("--mavlink", default=None, metavar="URL",
                        help="pymavlink connection string (default "
                             f"udpin:127.0.0.1:<{DEFAULT_MAVLINK_BASE}+I>)")
    parser.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                        help="Zenoh endpoint of the world's router (default tcp/127.0.0.1:7447; "
                             "tls/... with [security])")
    parser.add_argument("--listen", action="append", default=[], metavar="ENDPOINT")
    parser.add_argument("--qp-dump-dir", type=Path, default=None, metavar="DIR",
                        help="save the first QPs the solver fails on there, one .npz each "
                             "(python -m swarm.runs.failed_qp FILE solves one again); "
                             "default: only log them")
    add_run_arguments(parser, run_id_help="the world's --run-id (default: vigil)")
    faults = parser.add_argument_group(
        "fault injection (tests; realtime only; off by default)")
    faults.add_argument("--drop-consensus", type=fraction, default=0.0, metavar="P",
                        help="lose each outgoing consensus message with probability P")
    faults.add_argument("--delay-consensus", type=step_count, default=0, metavar="K",
                        help="send each outgoing consensus message K steps late")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    follow_parent(PROG)  # started by launch-swarm: die with it (swarm.children)
    argv = sys.argv[1:] if argv is None else list(argv)
    early = bind_early(argv)
    try:
        return run_main(PROG, lambda: _main(argv, early))
    finally:
        if early is not None:
            early.close()  # a no-op once the link took it over and closed it


def _main(argv: list[str], early: BoundSocket | None) -> int:
    """``main`` once the MAVLink socket is bound: input that cannot be used raises a
    ``UsageError`` (a ``ConfigError`` for the config), which ``run_main`` prints as one line."""
    # Imported now, with the MAVLink socket already bound (module docstring).
    from swarm.agent.process import AgentOptions, AgentProcess
    from swarm.net.faults import LinkFaults
    from swarm.net.session import check_tls_endpoints, local_endpoint
    from swarm.scenario.cli_common import (
        UsageError,
        fail_on,
        load_scenario,
        terminate_on_sigterm,
    )
    from swarm.scenario.config import realtime_only_reason

    args = build_parser().parse_args(argv)
    config = load_scenario(args.config, args.duration)
    if not 0 <= args.id < config.swarm.n_drones:
        raise UsageError(f"--id {args.id} is out of range 0..{config.swarm.n_drones - 1} "
                         f"for {config.source}")
    if config.security.enabled and args.listen:
        raise UsageError("--listen (peer mode) is not available with [security]: agents join "
                         "the world's router as clients")
    check_tls_endpoints([*args.listen, *(args.connect or [])], tls=config.security.enabled)
    faults = LinkFaults(drop_rate=args.drop_consensus, delay_steps=args.delay_consensus,
                        seed=(args.seed or 0) * 1000 + args.id)
    reason = realtime_only_reason(config.vehicles, mode=args.mode,
                                  faulty_consensus=faults.active)
    if reason is not None:
        raise UsageError(reason)
    terminate_on_sigterm()
    url = args.mavlink or f"udpin:127.0.0.1:{DEFAULT_MAVLINK_BASE + args.id}"
    options = AgentOptions(
        config=config, drone_id=args.id,
        seed=config.scenario.seed if args.seed is None else args.seed,
        run_id=args.run_id,
        mavlink_url=url,
        connect=tuple(args.connect or [local_endpoint(7447, tls=config.security.enabled)]),
        listen=tuple(args.listen),
        mode=args.mode, log=lambda line: print(line, flush=True), consensus_faults=faults,
        qp_dump_dir=args.qp_dump_dir,
        mavlink_socket=early if early is not None and early.url == url else None)
    process = None
    try:
        process = AgentProcess(options)
        return process.run()
    except OSError as err:  # the OS refused a socket or file: not ours, but said in one line
        return fail_on(PROG, err, f"drone {args.id}: ")
    finally:
        if process is not None:
            process.close()


if __name__ == "__main__":
    sys.exit(main())
