"""The xdist workers' share of the machine (tests.helpers.machine_share): an ``alone`` test
waits for the test in progress on the other worker and holds off the next one. ``flock``
locks belong to each open file, so threads that open the files themselves contend as the two
workers do."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from pathlib import Path

from tests.helpers.machine_share import machine_share

BLOCKED_S = 0.3  # long enough for an acquisition that is not blocked to happen


class Holder:
    """A thread that takes its share, says so, and lets it go when told."""

    def __init__(self, shared: Path, *, alone: bool) -> None:
        self.holding = threading.Event()
        self.release = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(shared, alone), daemon=True)
        self._thread.start()

    def _run(self, shared: Path, alone: bool) -> None:
        with machine_share(shared, alone=alone):
            self.holding.set()
            self.release.wait(30)

    def done(self) -> None:
        self.release.set()
        self._thread.join(10)
        assert not self._thread.is_alive()


@contextlib.contextmanager
def holding(shared: Path, *, alone: bool) -> Iterator[Holder]:
    holder = Holder(shared, alone=alone)
    try:
        assert holder.holding.wait(10)
        yield holder
    finally:
        holder.done()


def test_tests_that_share_the_machine_run_together(tmp_path: Path) -> None:
    with holding(tmp_path, alone=False) as first, holding(tmp_path, alone=False) as second:
        # Both hold their share at once: neither waited for the other to let go.
        assert first.holding.is_set() and second.holding.is_set()
        assert not first.release.is_set() and not second.release.is_set()


def test_an_alone_test_keeps_the_others_out_until_it_ends(tmp_path: Path) -> None:
    with holding(tmp_path, alone=True) as alone:
        other = Holder(tmp_path, alone=False)
        assert not other.holding.wait(BLOCKED_S)
        alone.done()
        assert other.holding.wait(10)
        other.done()


def test_an_alone_test_waits_for_the_test_in_progress_and_goes_before_the_next(
        tmp_path: Path) -> None:
    with holding(tmp_path, alone=False) as running:
        alone = Holder(tmp_path, alone=True)
        assert not alone.holding.wait(BLOCKED_S)
        # The other worker's next test, asked for while the alone test waits, comes after it.
        following = Holder(tmp_path, alone=False)
        assert not following.holding.wait(BLOCKED_S)
        running.done()
        assert alone.holding.wait(10)
        assert not following.holding.wait(BLOCKED_S)
        alone.done()
        assert following.holding.wait(10)
        following.done()
