"""The two xdist workers' share of the machine: tests marked ``alone`` run with the other
worker idle (``tests/conftest.py``).

Real autopilot firmware simulates its sensors against the wall clock. Three PX4 SIH
instances beside six agents, a world, a launcher and the other worker's CPU-bound tests on
two cores starved one instance's simulator: on a slow day of the host, a CI run's PX4 mission
lost "valid data from Baro 0" and "Compass 0" right after arming, PX4 blind-landed and
terminated the flight, and the handshake never finished the climb. An ``alone`` test
therefore waits until the other worker's test in progress ends and keeps it from starting
another until it is done.

Two ``flock`` locks in a directory both workers share: every test holds the *machine* lock,
shared, for its duration; an ``alone`` test holds it exclusive. A shared holder takes the
*turnstile* first and lets it go at once; an ``alone`` test holds the turnstile while it
waits for and then holds the machine, so that the other worker's stream of short tests cannot
keep it waiting for ever (``flock`` gives no priority to a waiting exclusive lock).
"""

from __future__ import annotations

import contextlib
import fcntl
from collections.abc import Iterator
from pathlib import Path

TURNSTILE_NAME = "machine.turnstile"
MACHINE_NAME = "machine.lock"


@contextlib.contextmanager
def machine_share(shared_dir: Path, *, alone: bool) -> Iterator[None]:
    """Hold the machine shared with the other worker's tests, or alone (module docstring)."""
    with (open(shared_dir / TURNSTILE_NAME, "ab") as turnstile,
          open(shared_dir / MACHINE_NAME, "ab") as machine):
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        try:
            fcntl.flock(machine, fcntl.LOCK_EX if alone else fcntl.LOCK_SH)
        finally:
            if not alone:
                fcntl.flock(turnstile, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(machine, fcntl.LOCK_UN)
            if alone:
                fcntl.flock(turnstile, fcntl.LOCK_UN)
