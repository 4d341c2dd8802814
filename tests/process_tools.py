"""What the tests that start third-party MAVLink programs share: finding their console
scripts and a block of UDP ports nobody else will take."""

from __future__ import annotations

import random
import shutil
import sys
from pathlib import Path

from swarm.launcher import udp_ports_free


def console_script(name: str, module: str) -> list[str]:
    """The console script ``name`` of this interpreter's environment, or ``python -m module``."""
    script = shutil.which(name, path=str(Path(sys.executable).parent))
    return [script] if script else [sys.executable, "-m", module]


def free_udp_block(count: int) -> int:
    """A base port p with UDP p..p+count-1 free on 127.0.0.1. Drawn at random below Linux's
    ephemeral range (32768+), so that no socket bound to port 0 later (the world's vehicle
    sockets, Zenoh, MAVSDK) can land in the block, and concurrent runs rarely pick the same."""
    rng = random.SystemRandom()
    for _ in range(500):
        base = rng.randrange(20000, 32768 - count)
        if udp_ports_free(base, count):
            return base
    raise RuntimeError("no free block of UDP ports on 127.0.0.1")
