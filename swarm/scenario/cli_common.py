"""What every command-line entry point shares: one-line errors, config loading, signals."""

from __future__ import annotations

import argparse
import math
import re
import signal
import socket
import sys
import typing
from collections.abc import Sequence

from swarm.errors import (  # noqa: F401 (the executables import these from here too)
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    VigilError,
    exit_code,
    fail,
    fail_on,
    run_main,
)
from swarm.mavlink.udpin import DEFAULT_MAVLINK_BASE  # noqa: F401 (the executables' default)
from swarm.scenario.config import ConfigError, ScenarioConfig, load_config
from swarm.scenario.overrides import Override, OverrideError, parse_assignment

RUN_ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


class OneLineParser(argparse.ArgumentParser):
    """argparse prints the usage block before an error; our errors are one line."""

    def error(self, message: str) -> typing.NoReturn:
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def _int_in(text: str, low: int, high: int, what: str, bounds: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not {what}: {text!r}") from None
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"must be in {bounds}, got {text!r}")
    return value


def seed(text: str) -> int:
    return _int_in(text, 0, 2**63 - 1, "an integer", "[0, 2^63)")


def fraction(text: str) -> float:
    """A probability in [0, 1)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and 0.0 <= value < 1.0):
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {text!r}")
    return value


def step_count(text: str) -> int:
    return _int_in(text, 0, 1000, "an integer", "[0, 1000]")


def restart_count(text: str) -> int:
    return _int_in(text, 0, 100, "an integer", "[0, 100]")


def port(text: str) -> int:
    return _int_in(text, 1, 65535, "a port number", "[1, 65535]")


def gcs_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``--gcs``, ``--foxglove``), or ``PORT`` alone for 127.0.0.1; the host
    must resolve to IPv4 (the vehicles' sockets are IPv4, as SITL's links)."""
    host, sep, number = text.rpartition(":")
    host = host if sep else "127.0.0.1"
    try:
        checked = port(number)
        if not host:
            raise argparse.ArgumentTypeError("no host")
        socket.getaddrinfo(host, checked, socket.AF_INET, socket.SOCK_DGRAM)
    except (argparse.ArgumentTypeError, OSError) as err:
        raise argparse.ArgumentTypeError(
            f"want HOST:PORT with an IPv4 host and a port in [1, 65535], e.g. "
            f"127.0.0.1:14550 (got {text!r}: {err})") from None
    return host, checked


FOXGLOVE_DEFAULT: typing.Final = ("127.0.0.1", 8765)  # Foxglove's default WebSocket port


def add_foxglove_argument(parser: argparse.ArgumentParser) -> None:
    """``--foxglove [HOST:PORT]``: serve the live 3D view (``swarm.observe.live_view``)."""
    parser.add_argument("--foxglove", type=gcs_address, nargs="?", const=FOXGLOVE_DEFAULT,
                        default=None, metavar="HOST:PORT",
                        help="serve a live 3D view to Foxglove/Lichtblick (Open connection → "
                             "Foxglove WebSocket, ws://HOST:PORT; default 127.0.0.1:8765). The "
                             "server speaks foxglove.sdk.v1 only: Lichtblick 1.22.0 or later, or "
                             "a current Foxglove app; older Lichtblick and @foxglove/ws-protocol "
                             "tools (foxglove.websocket.v1) are refused")


def add_gcs_arguments(parser: argparse.ArgumentParser) -> None:
    """``--gcs HOST:PORT`` and ``--gcs-control``: each emulated vehicle's ground-station link
    (``sim_world.gcs_link``), for ``sim-world``, ``sim-vehicles`` and ``launch-swarm``."""
    parser.add_argument("--gcs", type=gcs_address, default=None, metavar="HOST:PORT",
                        help="every emulated vehicle also streams to a ground station there "
                             "(QGroundControl, or mavproxy.py --master udpin:HOST:PORT), "
                             "which may only watch")
    parser.add_argument("--gcs-control", action="store_true",
                        help="let that ground station command the vehicles (arm, modes, "
                             "setpoints): it can then disturb the mission")


def gcs_problem(gcs: tuple[str, int] | None, control: bool, *, signing: bool) -> str | None:
    """Why ``--gcs``/``--gcs-control`` cannot be served as given (None: they can)."""
    if control and gcs is None:
        return "--gcs-control needs --gcs HOST:PORT"
    if control and signing:
        return ("--gcs-control: the vehicles sign their MAVLink and the ground-station link "
                "holds no key; drop --gcs-control or the signing")
    return None


def run_id(text: str) -> str:
    if not RUN_ID_PATTERN.match(text):
        raise argparse.ArgumentTypeError(
            f"must be 1-64 characters of A-Z a-z 0-9 _ - (got {text!r})")
    return text


def add_run_arguments(parser: argparse.ArgumentParser, *, run_id_help: str) -> None:
    """The options that name one run, shared by the world and the agent processes."""
    parser.add_argument("--run-id", type=run_id, default="vigil", help=run_id_help)
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep")
    parser.add_argument("--seed", type=seed, default=None, help="default: scenario.seed")
    parser.add_argument("--duration", type=positive_float, default=None, metavar="S")


def load_scenario(path: str, duration_s: float | None, *, autopilot: str | None = None,
                  overrides: Sequence[Override] = ()) -> ScenarioConfig:
    """Config file plus an optional --duration; ConfigError (one line) when unusable.
    ``autopilot``: real autopilots of that flavour fly the drones; ``overrides``: ``--set``
    (``load_config``)."""
    config = load_config(path, autopilot=autopilot, overrides=overrides)
    if duration_s is not None:
        config = config.with_duration(duration_s)
    return config


def config_assignment(text: str) -> Override:
    """argparse type of ``--set KEY=VALUE`` (``swarm.scenario.overrides``)."""
    try:
        return parse_assignment(text)
    except OverrideError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def terminate_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt so ``finally`` blocks close sessions and sockets;
    and make SIGINT (Ctrl-C) do the same even when the process inherited it ignored — a shell
    starts background commands so, and Python then leaves it ignored: the swarm would fly on
    through a Ctrl-C sent to it (seen: a launch-swarm under a backgrounded test run)."""

    def _raise(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)
    signal.signal(signal.SIGINT, signal.default_int_handler)


__all__ = ["ConfigError", "OneLineParser", "UsageError", "add_run_arguments", "fail", "fail_on",
           "load_scenario", "port", "positive_float", "run_id", "run_main", "seed",
           "terminate_on_sigterm"]
