"""The root of every error the project raises on purpose, and the exit codes of the executables.

Each module keeps its own error class (``ConfigError``, ``WireError``, ``LinkError``, ...) next
to the code that raises it, also deriving from the built-in exception it stood for before
(``ValueError``, ``RuntimeError``), so ``except VigilError`` catches anything of ours and
nothing else: a ``VigilError`` is a refusal or a failure we expected and worded; anything else
reaching a command line is a bug.
"""

from __future__ import annotations


class VigilError(Exception):
    """An error raised on purpose by Vigil (swarm, sim_world), with a message for a user."""


class UsageError(VigilError):
    """Input that cannot be used as given: a config, a command-line value, a key, certificate
    or firmware path. The executables exit with ``EXIT_USAGE`` on it; every other
    ``VigilError`` is a run that failed (``EXIT_FAILED``)."""


# Exit codes of every executable (launch-swarm, swarm-agent, sim-world, sim-vehicles,
# swarm-report, the dashboard); ``exit_code`` maps what ended one to its code.
EXIT_OK = 0
EXIT_FAILED = 1  # the run failed (a mission, a link, a recording, a socket)
EXIT_USAGE = 2  # input that cannot be used (UsageError, bad arguments)
EXIT_END_MISSION = 3  # an agent's vehicle policy "end" ends the mission (the launcher stops all)
EXIT_INCOMPLETE = 4  # a report of a run cut short with no invariant violated on what it holds
EXIT_INTERRUPTED = 130  # 128 + SIGINT


def exit_code(error: BaseException) -> int:
    """The exit code of an executable that ``error`` ends: interrupted 130, input that cannot
    be used 2, any other failure 1."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(error, UsageError):
        return EXIT_USAGE
    return EXIT_FAILED

