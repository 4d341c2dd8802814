"""What every command-line entry point shares: one-line errors, config loading, signals."""

from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import typing

from swarm.config import ConfigError, ScenarioConfig, load_config

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT
RUN_ID_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


class OneLineParser(argparse.ArgumentParser):
    """argparse prints the usage block before an error; our errors are one line."""

    def error(self, message: str) -> typing.NoReturn:
        print(f"{self.prog}: error: {message} (see --help)", file=sys.stderr)
        sys.exit(EXIT_USAGE)


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> int:
    """One plain line on stderr: never wrapped, never styled, no traceback."""
    print(f"{prog}: {' '.join(message.split())}", file=sys.stderr)
    return code


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63), got {text!r}")
    return value


def port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be in [1, 65535], got {text!r}")
    return value


def run_id(text: str) -> str:
    if not RUN_ID_PATTERN.match(text):
        raise argparse.ArgumentTypeError(
            f"must be 1-64 characters of A-Z a-z 0-9 _ - (got {text!r})")
    return text


def load_scenario(path: str, duration_s: float | None) -> ScenarioConfig:
    """Config file plus an optional --duration; ConfigError (one line) when unusable."""
    config = load_config(path)
    if duration_s is not None:
        config = config.with_duration(duration_s)
    return config


def terminate_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt so ``finally`` blocks close sessions and sockets."""

    def _raise(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)


__all__ = ["ConfigError", "OneLineParser", "fail", "load_scenario", "port", "positive_float",
           "run_id", "seed", "terminate_on_sigterm"]
