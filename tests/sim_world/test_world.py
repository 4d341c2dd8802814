"""sim_world.world.World in one process: what it puts on world/clock and when."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

import sim_world.world as world_module
from sim_world.world import CLOCK_PERIOD_S, World, WorldOptions
from swarm.config import load_config
from swarm.launcher import choose_mavlink_base, free_tcp_port

CASE1 = Path(__file__).resolve().parents[2] / "configs" / "case1.toml"


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def world() -> Iterator[World]:
    config = load_config(CASE1)
    made = World(WorldOptions(
        config=config, seed=0, run_id="clocktest",
        listen=(f"tcp/127.0.0.1:{free_tcp_port()}",),
        mavlink_base=choose_mavlink_base(0, config.swarm.n_drones), log=lambda _line: None))
    try:
        yield made
    finally:
        made.close()


def test_running_is_published_at_the_start_then_every_clock_period(
        world: World, monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(world_module.time, "monotonic", clock)
    published: list[tuple[int, str]] = []
    real_publish = world.publish_clock

    def record(step: int, state: str, detail: str = "") -> None:
        published.append((step, state))
        real_publish(step, state, detail)

    monkeypatch.setattr(world, "publish_clock", record)
    for step in range(50):  # a fast lockstep: 50 steps within one clock period
        clock.now += CLOCK_PERIOD_S / 100
        world.publish_running(step)
    assert published == [(0, "running")]
    clock.now += CLOCK_PERIOD_S
    world.publish_running(50)
    world.publish_running(51)
    assert published == [(0, "running"), (50, "running")]
