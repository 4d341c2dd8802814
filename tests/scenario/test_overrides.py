"""``--set key=value`` (swarm.scenario.overrides): applied to the document before it is
validated, so a value given so is checked as one in the file."""

from __future__ import annotations

import math

import pytest

from swarm.core.graph import CommunicationGraph
from swarm.scenario.config import ConfigError, load_config
from swarm.scenario.overrides import (
    OverrideError,
    apply_overrides,
    parse_assignment,
    ring_with_chords,
)

CASE1 = "configs/case1.toml"
CASE2 = "configs/case2.toml"


def test_values_parse_as_toml_and_bare_words_as_strings() -> None:
    assert parse_assignment("gramian.epsilon=0.06") == ("gramian.epsilon", 0.06)
    assert parse_assignment("targets.0.velocity_m_s=[0.4, 0, 0]") == (
        "targets.0.velocity_m_s", [0.4, 0, 0])
    assert parse_assignment("vehicles.response=arducopter") == ("vehicles.response", "arducopter")
    assert parse_assignment('scenario.name="a b"') == ("scenario.name", "a b")
    assert parse_assignment("swarm.n_drones=9") == ("swarm.n_drones", 9)


@pytest.mark.parametrize("text", ["gramian", "gramian.epsilon=", "epsilon=1", "=1",
                                  "gramian..epsilon=1", "gramian.epsilon=[1,"])
def test_malformed_assignments_are_one_line(text: str) -> None:
    with pytest.raises(OverrideError) as err:
        parse_assignment(text)
    assert "\n" not in str(err.value)


def test_overrides_reach_the_config_and_leave_the_document_alone() -> None:
    data = {"gramian": {"epsilon": 0.05}, "targets": [{"start_m": [0, 0, 0]}]}
    out = apply_overrides(data, [("gramian.epsilon", 0.07), ("targets.0.start_m", [1, 2, 0]),
                                 ("camera.image_noise_std", 0.0)])
    assert out == {"gramian": {"epsilon": 0.07}, "targets": [{"start_m": [1, 2, 0]}],
                   "camera": {"image_noise_std": 0.0}}
    assert data == {"gramian": {"epsilon": 0.05}, "targets": [{"start_m": [0, 0, 0]}]}
    config = load_config(CASE1, overrides=[("gramian.epsilon", 0.06),
                                           ("targets.0.velocity_m_s", [0.4, 0.0, 0.0])])
    assert config.gramian.epsilon == 0.06
    assert config.targets[0].velocity_m_s == (0.4, 0.0, 0.0)


@pytest.mark.parametrize(("override", "named"), [
    (("gramian.epsilonn", 0.05), "gramian.epsilonn: unknown key"),
    (("gramian.epsilon", "high"), "gramian.epsilon: Expected `float`, got `str`"),
    (("gramian.epsilon", math.nan), "gramian.epsilon must be a finite number > 0"),
    (("gramian.epsilon", -1.0), "gramian.epsilon must be a finite number > 0"),
    (("targets.2.start_m", [0, 0, 0]), "targets.2: index 2 out of range"),
    (("scenario.duration_s.x", 1), "scenario.duration_s is a value, not a table"),
])
def test_a_bad_override_is_the_config_error_a_file_gives(override: tuple[str, object],
                                                          named: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(CASE1, overrides=[override])
    text = str(err.value)
    assert named in text and "\n" not in text
    assert text.startswith(CASE1)


@pytest.mark.parametrize("n", [2, 3, 4, 5, 7, 12, 31, 48])
def test_ring_with_chords_is_connected_with_degree_at_most_three(n: int) -> None:
    edges = ring_with_chords(n)
    graph = CommunicationGraph(n, tuple(tuple(e) for e in edges))
    assert graph.is_connected()
    assert max(graph.degree(i) for i in range(n)) <= 3
    assert len({frozenset(e) for e in edges}) == len(edges)


def test_a_new_swarm_size_gets_its_graph_and_start_box() -> None:
    """Case 2 scaled to 12 drones as benchmarks/swarm_configs.py did (configs/bench)."""
    config = load_config(CASE2, overrides=[("swarm.n_drones", 12)])
    bench = load_config("configs/bench/case2_n12.toml")
    assert config.swarm.n_drones == 12
    assert config.swarm.initial_box_size_m == bench.swarm.initial_box_size_m
    assert set(map(frozenset, config.swarm.edges)) == set(map(frozenset, bench.swarm.edges))
    same = load_config(CASE1, overrides=[("swarm.n_drones", 6)])
    assert same.swarm.edges == load_config(CASE1).swarm.edges  # the file's N: its own graph
    given = load_config(CASE1, overrides=[("swarm.n_drones", 3),
                                          ("swarm.edges", [[0, 1], [1, 2]])])
    assert given.swarm.edges == ((0, 1), (1, 2))
