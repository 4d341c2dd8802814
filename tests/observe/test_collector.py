"""swarm.observe.collector: how fast the world's clock ran against the wall's, as an observer
received the truth, live and from a recording (the realtime report says when the world fell
behind: tests/observe/test_report.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarm.messages.wire import TruthWire
from swarm.observe.collector import CLOCK_RATE_MIN_WALL_S, TelemetryCollector
from swarm.observe.recording.reader import read_recording
from swarm.observe.recording.schema import RecordingMetadata
from swarm.observe.recording.writer import Recorder
from swarm.scenario.config import load_config

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


DRONES = np.array([[x, y, 3.5] for x in (-1.0, 1.0) for y in (-1.0, 0.0, 1.0)])


def truth(step: int, dt_s: float) -> TruthWire:
    return TruthWire.build(step, step * dt_s, DRONES, np.zeros((1, 3)), np.zeros((1, 3)))


@pytest.mark.parametrize("rate", [0.5, 1.0, 2.0])
def test_the_world_clock_rate_is_simulated_over_wall_time(rate: float) -> None:
    config = load_config(CASE1)
    dt = config.scenario.dt_s
    collector = TelemetryCollector(config)
    # Steps 10-159 arrive out of order around the ends; wall time 1000 s + step·ΔT / rate.
    for step in [11, 10, *range(12, 158), 159, 158]:
        collector.on_truth("t", truth(step, dt), received_s=1000.0 + step * dt / rate)
    assert collector.record(0, 1.0).world_clock_rate == pytest.approx(rate, rel=1e-9)


def test_no_rate_from_less_than_a_second_of_wall_time() -> None:
    config = load_config(CASE1)
    dt = config.scenario.dt_s
    collector = TelemetryCollector(config)
    assert collector.record(0, 0.0).world_clock_rate is None
    steps = round(CLOCK_RATE_MIN_WALL_S / dt)  # one step short of the minimum span
    for step in range(steps):
        collector.on_truth("t", truth(step, dt), received_s=step * dt)
    assert collector.record(0, 1.0).world_clock_rate is None
    collector.on_truth("t", truth(steps, dt), received_s=steps * dt)
    assert collector.record(0, 1.0).world_clock_rate == pytest.approx(1.0)


def test_a_recording_gives_the_rate_its_recorder_received(tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(4.0)
    dt = config.scenario.dt_s
    metadata = RecordingMetadata.for_run(config, 0, "realtime", run_id="r")
    with Recorder(tmp_path, metadata) as recorder:
        for step in range(config.n_steps):  # a world at 0.52 of the wall's pace
            recorder.put(truth(step, dt), received_ns=round(1e18 + step * dt / 0.52 * 1e9))
    record = read_recording(tmp_path).record
    assert record.world_clock_rate == pytest.approx(0.52, rel=1e-6)
