"""Radios with a range, seen (issue 44, point 5): the dashboard's neighbour count and split
warning, the 3D scene's links coloured kept / in range / lost, the report's plot of the
radio's graph, a recording read back with its links and reach."""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from swarm.observe.dashboard import Dashboard, DashboardSettings, InProcessFeed, drone_row
from swarm.observe.foxglove_scene import (
    GRAPH_COLOUR,
    KEPT_COLOUR,
    LOST_COLOUR,
    SceneState,
    scene_update,
)
from swarm.observe.plots import figures_for, plot_network
from swarm.observe.recording.reader import read_recording
from swarm.observe.recording.writer import record_reference
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from swarm.scenario.overrides import parse_assignment
from tests.helpers.scene_tools import decode_scene

ROOT = Path(__file__).resolve().parents[2]
RANGE = ROOT / "configs" / "case2_range.toml"


def _config(*assignments: str, duration_s: float = 50.0):
    return load_config(RANGE, overrides=[parse_assignment(a) for a in assignments]
                       ).with_duration(duration_s)


@pytest.fixture(scope="module")
def split_run():
    """R = 8 m without keeping, 36 s: the swarm splits at ~33 s."""
    return run_reference(_config("network.range_m=8", "network.keep=none", duration_s=36.0),
                         seed=0)


def test_the_dashboard_counts_neighbours_and_warns_of_a_split_at_once(split_run) -> None:
    config = split_run.config
    console = Console(record=True, width=200, force_terminal=False, file=io.StringIO())
    dashboard = Dashboard(config, console, settings=DashboardSettings(log_period_s=1000.0))
    run_reference(config, seed=0, on_step=InProcessFeed(dashboard))
    text = console.export_text(clear=False)
    warnings = [line for line in text.splitlines() if "times its radio found the swarm split"
                in line]
    assert warnings, text[-3000:]
    assert "drone " in warnings[0]
    rows = [drone_row(t) for t in dashboard._latest.values()]  # each drone's newest
    assert len(rows) == config.swarm.n_drones
    assert all(r.neighbours is not None for r in rows)
    assert sorted({r.reached for r in rows}) == [2, 4]
    console.print(dashboard.render())
    assert "split" in console.export_text()  # the events column


def _state(links: np.ndarray) -> SceneState:
    n = links.shape[0]
    drones = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.full(n, 3.0)])
    return SceneState(step=0, time_s=0.0, drones_m=drones, targets_m=np.zeros((2, 3)),
                      weights=np.zeros((n, 2)), estimates_m=np.zeros((n, 2, 3)), links=links)


def _graph_colours(config, links: np.ndarray) -> dict[tuple, int]:
    update = decode_scene(scene_update(config, _state(links)))
    (graph,) = [e for e in update.entities if e.id == "graph"]
    return {(round(line.color.r, 2), round(line.color.g, 2), round(line.color.b, 2)):
            len(line.points) // 2 for line in graph.lines}


def _rgb(colour) -> tuple:
    return tuple(round(c, 2) for c in colour[:3])


def test_the_scene_colours_kept_links_in_range_other_links_and_kept_links_lost() -> None:
    config = _config()  # keeps the tree (0,1) (0,3) (0,5) (1,2) (1,4)
    links = np.ones((6, 6), dtype=bool)
    np.fill_diagonal(links, False)
    links[0, 3] = links[3, 0] = False  # a kept link lost
    colours = _graph_colours(config, links)
    assert colours == {_rgb(KEPT_COLOUR): 4, _rgb(LOST_COLOUR): 1, _rgb(GRAPH_COLOUR): 10}
    fixed = dataclasses.replace(config, network=dataclasses.replace(
        config.network, topology="fixed", keep="none"))
    assert _graph_colours(fixed, links) == {_rgb(GRAPH_COLOUR): 8}  # swarm.edges


def test_the_report_plots_the_radio_graph_only_with_a_range(split_run) -> None:
    assert "network.png" in figures_for(split_run)
    figure = plot_network(split_run)
    assert len(figure.axes) >= 2
    plain = run_reference(load_config(ROOT / "configs" / "case2.toml").with_duration(1.2))
    assert "network.png" not in figures_for(plain)


def test_a_recording_reads_back_with_the_links_and_the_reach(tmp_path: Path) -> None:
    config = _config("network.range_m=8", "network.keep=none", duration_s=34.0)
    reference = record_reference(config, 0, tmp_path)
    back = read_recording(tmp_path / "run.mcap").record
    assert back.links is not None and back.reached is not None
    np.testing.assert_array_equal(back.links, reference.links)
    np.testing.assert_array_equal(back.reached, reference.reached)
    np.testing.assert_array_equal(back.link_conflict, reference.link_conflict)
