"""The root of every error the project raises on purpose, the exit codes of the executables,
and the one way an executable ends on an error (``run_main``).

Each module keeps its own error class (``ConfigError``, ``WireError``, ``LinkError``, ...) next
to the code that raises it, also deriving from the built-in exception it stood for before
(``ValueError``, ``RuntimeError``), so ``except VigilError`` catches anything of ours and
nothing else: a ``VigilError`` is a refusal or a failure we expected and worded; anything else
reaching a command line is a bug. Each executable's ``main`` runs its body in ``run_main``,
which prints such an error as one line and exits with the code its class carries.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import ClassVar

# Exit codes of every executable (launch-swarm, swarm-agent, sim-world, sim-vehicles,
# swarm-report, swarm-observe, swarm-sweep, the tools); ``exit_code`` maps what ended one to
# its code.
EXIT_OK = 0
EXIT_FAILED = 1  # the run failed (a mission, a link, a recording, a socket)
EXIT_USAGE = 2  # input that cannot be used (UsageError, bad arguments)
EXIT_END_MISSION = 3  # an agent's vehicle policy "end" ends the mission (the launcher stops all)
EXIT_INCOMPLETE = 4  # a report of a run cut short with no invariant violated on what it holds
EXIT_INTERRUPTED = 130  # 128 + SIGINT


class VigilError(Exception):
    """An error raised on purpose by Vigil (swarm, sim_world), with a message for a user.

    ``exit_status``: the exit code of an executable it ends (``EXIT_FAILED``: a run that
    failed; ``UsageError`` carries ``EXIT_USAGE``). ``label``: what a command line says before
    the message (``ConfigError``: "config error: "), empty by default."""

    exit_status: ClassVar[int] = EXIT_FAILED
    label: ClassVar[str] = ""


class UsageError(VigilError):
    """Input that cannot be used as given: a config, a command-line value, a key, certificate
    or firmware path, a file to read. The executables exit with ``EXIT_USAGE`` on it; every
    other ``VigilError`` is a run that failed (``EXIT_FAILED``)."""

    exit_status: ClassVar[int] = EXIT_USAGE


def exit_code(error: BaseException) -> int:
    """The exit code of an executable that ``error`` ends: interrupted 130, one of ours the
    code its class carries (input that cannot be used 2, any other failure 1), anything else
    (a bug) 1."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(error, VigilError):
        return error.exit_status
    return EXIT_FAILED


def fail(prog: str, message: str, code: int = EXIT_USAGE) -> int:
    """One plain line on stderr (``prog: message``): never wrapped, never styled, no
    traceback; returns ``code``."""
    print(f"{prog}: {' '.join(message.split())}", file=sys.stderr)
    return code


def fail_on(prog: str, error: BaseException, context: str = "") -> int:
    """``error`` as one line on stderr (after ``context``, e.g. "report: ", and the error's
    ``label``), and the exit code ``exit_code`` gives it."""
    label = error.label if isinstance(error, VigilError) else ""
    return fail(prog, f"{context}{label}{error}", exit_code(error))


def run_main(prog: str, body: Callable[[], int], *, context: str = "") -> int:
    """``body()``'s exit code, or, when it raises, the code of what ended it: a
    ``VigilError`` as one line on stderr (``fail_on``) and the code its class carries, Ctrl-C
    (or SIGTERM turned into it) 130. Anything else is a bug and keeps its traceback."""
    try:
        return body()
    except VigilError as err:
        return fail_on(prog, err, context)
    except KeyboardInterrupt as err:
        return exit_code(err)
