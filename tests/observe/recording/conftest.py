"""An in-process Case 1 recording, made once for the tests of this package."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarm.observe.recording.writer import record_reference
from swarm.runs.record import RunRecord
from swarm.scenario.config import load_config

CASE1 = Path(__file__).resolve().parents[3] / "configs" / "case1.toml"


@pytest.fixture(scope="package")
def inprocess_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[RunRecord, Path]:
    config = load_config(CASE1).with_duration(3.0)
    directory = tmp_path_factory.mktemp("inprocess")
    return record_reference(config, 3, directory), directory
