"""The suite runs on two pytest-xdist workers (``-n 2 --dist loadgroup``, see pyproject.toml).

Tests marked ``wallclock`` run against the wall clock: autopilot SITL firmware, MAVSDK and
MAVProxy dialogues, realtime swarms of processes, timers. They form one xdist group, so they
run one at a time on one worker, in collection order (the conformance suite boots a SITL in one
test for the next, and at most one SITL instance may run), never two at once; the other worker
takes the CPU-bound tests (numerics, property tests, lockstep swarms) beside them. ``-n 0``
runs everything in one process. A wallclock test also marked ``alone`` (three PX4 SITL
instances) runs with the other worker idle: it waits for that worker's test in progress, and
the next one waits for it (``tests.helpers.machine_share``); those tests run first.

pytest-xdist marks a test's group by appending ``@group`` to its node id. pytest 9.2 keeps node
ids elsewhere, and the grouping silently stops (pytest-xdist issue 1386): pyproject.toml pins
pytest below 9.2, and a wallclock test that a worker finds ungrouped fails, saying why.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from tests.helpers.machine_share import machine_share

WALLCLOCK_GROUP = "wallclock"


@pytest.hookimpl(tryfirst=True)  # before xdist names each test's group from its marks
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("wallclock") is not None:
            item.add_marker(pytest.mark.xdist_group(WALLCLOCK_GROUP))
    # ``alone`` tests first (the rest keep their order): the wallclock group, which sets the
    # suite's length on 2 cores, then starts at once instead of waiting for the other
    # worker's test in progress (CI: 85 s for a gate sweep in the middle of the suite, 28 s at
    # its end; the other worker's idle time is the same anywhere).
    items.sort(key=lambda item: item.get_closest_marker("alone") is None)


def pytest_runtest_setup(item: pytest.Item) -> None:
    if (item.config.getoption("loadgroup", default=False)  # an xdist worker, by group
            and item.get_closest_marker("wallclock") is not None
            and not item.nodeid.endswith(f"@{WALLCLOCK_GROUP}")):
        pytest.fail("pytest-xdist did not put this wallclock test in its group, so wallclock "
                    "tests would run two at a time: its loadgroup fails silently with pytest "
                    ">= 9.2 (pytest-xdist issue 1386); pip install 'pytest<9.2' (as "
                    "pip install -e '.[dev]' does), or run with -n 0", pytrace=False)


@pytest.fixture(autouse=True)
def _machine_share(request: pytest.FixtureRequest,
                   tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Each test's share of the machine beside the other xdist worker (shared, or the whole
    of it for ``alone``); nothing to share with ``-n 0``."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        yield
        return
    shared = tmp_path_factory.getbasetemp().parent  # the session's, above each worker's own
    with machine_share(shared, alone=request.node.get_closest_marker("alone") is not None):
        yield
