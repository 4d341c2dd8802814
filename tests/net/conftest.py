"""The ``spawn`` fixture: Zenoh peers in child processes, all stopped (process groups included)
at the end of the test."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator

import pytest

from tests.helpers.zenoh_tools import Child


@pytest.fixture
def spawn() -> Iterator[Callable[..., Child]]:
    children: list[Child] = []

    def start(*args: str) -> Child:
        children.append(Child(*args))
        return children[-1]

    try:
        yield start
    finally:
        for child in children:
            child.stop()
        for child in children:  # the whole process group is gone, not just the child
            with pytest.raises(ProcessLookupError):
                os.killpg(child.proc.pid, 0)
