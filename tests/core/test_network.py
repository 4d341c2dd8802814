"""The radio's pure parts: the disk graph with hysteresis, components and λ₂, the spanning
tree every drone derives, the keep row against finite differences, the reach stamps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarm.core.network import (
    NetworkParams,
    RadioRange,
    ReachTracker,
    algebraic_connectivity,
    components,
    keep_row,
    pair_distances,
    range_links,
    spanning_tree,
)

RING_AND_CHORDS = ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 3), (1, 4))


def _adjacency(n: int, edges) -> np.ndarray:
    links = np.zeros((n, n), dtype=bool)
    for a, b in edges:
        links[a, b] = links[b, a] = True
    return links


@st.composite
def connected_graphs(draw, n_min: int = 2, n_max: int = 8):
    """A connected graph: a random tree (each node hangs on an earlier one) plus random
    extra edges."""
    n = draw(st.integers(n_min, n_max))
    edges = {(draw(st.integers(0, k - 1)), k) for k in range(1, n)}
    extra = draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)),
                          max_size=2 * n))
    edges |= {(min(a, b), max(a, b)) for a, b in extra if a != b}
    return n, tuple(sorted(edges))


def test_a_link_comes_up_within_r_minus_h_and_drops_beyond_r() -> None:
    """The hysteresis band: a pair drifting out and back in does not chatter at the edge."""
    r, h = 10.0, 1.0
    states = []
    previous = None
    for d in (8.0, 9.5, 10.0, 10.01, 9.5, 9.01, 9.0, 9.99, 10.5):
        distances = np.array([[0.0, d], [d, 0.0]])
        previous = range_links(distances, previous, r, h)
        states.append(bool(previous[0, 1]))
    assert states == [True, True, True, False, False, False, True, True, False]


def test_the_first_step_links_every_pair_within_r() -> None:
    distances = np.array([[0.0, 9.5, 10.5], [9.5, 0.0, 3.0], [10.5, 3.0, 0.0]])
    links = range_links(distances, None, 10.0, 1.0)
    assert links.tolist() == [[False, True, False], [True, False, True], [False, True, False]]


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 9), st.integers(0, 2**32 - 1))
def test_the_radio_is_symmetric_without_self_links_and_deterministic(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    radio_a, radio_b = RadioRange(NetworkParams("range", 5.0, 0.5)), RadioRange(
        NetworkParams("range", 5.0, 0.5))
    positions = rng.uniform(-5, 5, size=(n, 3))
    for _ in range(20):
        positions += rng.normal(0, 0.5, size=(n, 3))
        links = radio_a.step(positions)
        assert np.array_equal(links, links.T) and not links.diagonal().any()
        assert np.array_equal(links, radio_b.step(positions.copy()))
        distances = pair_distances(positions)
        np.fill_diagonal(distances, np.inf)
        assert links[distances <= 4.5].all() and not links[distances > 5.0].any()


def test_pair_distances_are_the_norms() -> None:
    p = np.array([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0], [0.0, 0.0, -2.0]])
    np.testing.assert_allclose(pair_distances(p), [[0, 5, 2], [5, 0, math.sqrt(29)],
                                                   [2, math.sqrt(29), 0]], rtol=0, atol=1e-15)


def test_components_and_algebraic_connectivity_of_known_graphs() -> None:
    n = 5
    path = _adjacency(n, [(k, k + 1) for k in range(n - 1)])
    complete = _adjacency(n, [(a, b) for a in range(n) for b in range(a + 1, n)])
    assert components(path) == [[0, 1, 2, 3, 4]]
    assert math.isclose(algebraic_connectivity(path), 2 * (1 - math.cos(math.pi / n)),
                        abs_tol=1e-12)
    assert math.isclose(algebraic_connectivity(complete), n, abs_tol=1e-12)
    split = _adjacency(6, [(0, 4), (4, 5), (1, 2)])
    assert components(split) == [[0, 4, 5], [1, 2], [3]]
    assert algebraic_connectivity(split) == pytest.approx(0.0, abs=1e-12)


@settings(max_examples=80, deadline=None)
@given(st.integers(2, 8), st.lists(st.tuples(st.integers(0, 7), st.integers(0, 7)),
                                   max_size=20))
def test_lambda2_is_zero_exactly_when_there_are_several_components(n, pairs) -> None:
    links = _adjacency(n, [(a % n, b % n) for a, b in pairs if a % n != b % n])
    parts = components(links)
    assert sorted(i for part in parts for i in part) == list(range(n))
    for part in parts:  # no link leaves a component
        outside = np.setdiff1d(np.arange(n), part)
        assert not links[np.ix_(part, outside)].any()
    assert (algebraic_connectivity(links) > 1e-9) == (len(parts) == 1)


@settings(max_examples=80, deadline=None)
@given(connected_graphs())
def test_the_spanning_tree_is_n_minus_one_configured_edges_that_connect_all(graph) -> None:
    n, edges = graph
    tree = spanning_tree(n, edges)
    assert len(tree) == n - 1
    configured = {frozenset(e) for e in edges}
    assert all(frozenset(e) in configured for e in tree)
    assert len(components(_adjacency(n, tree))) == 1
    assert spanning_tree(n, tuple(reversed(edges))) == tree  # the same whatever the order


def test_the_kept_edges_of_each_rule() -> None:
    ranged = NetworkParams("range", 12.0, 1.0)
    assert ranged.kept_edges(6, RING_AND_CHORDS) == ()
    edges = NetworkParams("range", 12.0, 1.0, keep="edges").kept_edges(6, RING_AND_CHORDS)
    assert edges == tuple(sorted((min(a, b), max(a, b)) for a, b in RING_AND_CHORDS))
    tree = NetworkParams("range", 12.0, 1.0, keep="tree").kept_edges(6, RING_AND_CHORDS)
    assert tree == ((0, 1), (0, 3), (0, 5), (1, 2), (1, 4))
    assert NetworkParams("range", 12.0, 1.0, keep="tree").kept_range_m == 11.0
    assert NetworkParams("range", 12.0, 1.0, keep="tree", keep_range_m=9.0).kept_range_m == 9.0


@pytest.mark.parametrize(("fields", "says"), [
    ({"topology": "mesh"}, "topology must be 'fixed' or 'range'"),
    ({"keep": "all"}, "keep must be 'none', 'edges' or 'tree'"),
    ({"range_m": math.nan}, "range_m must be a finite number > 0"),
    ({"range_m": 0.0}, "range_m must be a finite number > 0"),
    ({"hysteresis_m": 30.0}, "hysteresis_m must be a finite number in [0, range_m)"),
    ({"hysteresis_m": -1.0}, "hysteresis_m must be a finite number in [0, range_m)"),
    ({"keep_range_m": 31.0}, "keep_range_m must be a finite number in (0, range_m]"),
    ({"keep_gain": math.inf}, "keep_gain must be a finite number > 0"),
    ({"reach_slack_steps": -1}, "reach_slack_steps must be an integer in [0, 10000]"),
    ({"topology": "fixed", "keep": "edges"}, "keep needs topology = 'range'"),
])
def test_bad_network_params_are_refused_naming_the_field(fields, says) -> None:
    arguments = {"topology": "range", **fields}
    with pytest.raises(ValueError, match="^" + says.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]")):
        NetworkParams(**arguments)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_keep_row_is_half_the_cbf_of_h_with_its_gradient_by_finite_differences(seed) -> None:
    """a = ∂h/∂p_i for h = R² − ‖p_i − p_j‖² (central differences, exact for a quadratic up
    to round-off), lower = −α h / 2, and h itself."""
    rng = np.random.default_rng(seed)
    own, other = rng.uniform(-10, 10, 3), rng.uniform(-10, 10, 3)
    keep_m, gain = float(rng.uniform(1, 20)), float(rng.uniform(0.1, 3))
    a, lower, h = keep_row(own.tolist(), other.tolist(), keep_m, gain)

    def barrier(p: np.ndarray) -> float:
        return keep_m ** 2 - float(np.sum((p - other) ** 2))

    step = 1e-3
    gradient = [(barrier(own + step * e) - barrier(own - step * e)) / (2 * step)
                for e in np.eye(3)]
    np.testing.assert_allclose(a, gradient, rtol=1e-9, atol=1e-9)
    assert h == pytest.approx(barrier(own), rel=1e-12, abs=1e-12)
    assert lower == pytest.approx(-0.5 * gain * h, rel=1e-12, abs=1e-12)


def _flood(trackers: list[ReachTracker], links: np.ndarray, step: int) -> None:
    """One step as the agents do it: each stamps the step (begin_step), sends its stamps in
    round 0, and takes those of the neighbours it hears."""
    for tracker in trackers:
        tracker.stamp(step)
    sent = [tracker.stamps.copy() for tracker in trackers]
    for i, tracker in enumerate(trackers):
        for j in np.flatnonzero(links[i]):
            tracker.merge(sent[j])


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 8), st.integers(0, 2**32 - 1), st.integers(0, 3))
def test_on_graphs_connected_at_every_step_no_drone_is_ever_counted_cut_off(n, seed, slack):
    """Each step the set of drones holding a stamp grows by one at least while the graph is
    connected: every stamp reaches everyone within N − 1 steps, whatever the switching."""
    rng = np.random.default_rng(seed)
    trackers = [ReachTracker(i, n, slack) for i in range(n)]
    for step in range(60):
        order = rng.permutation(n)  # a random spanning path, plus random extra links
        links = _adjacency(n, [(order[k], order[k + 1]) for k in range(n - 1)])
        extra = rng.random((n, n)) < 0.2
        links |= extra | extra.T
        np.fill_diagonal(links, False)
        _flood(trackers, links, step)
        for tracker in trackers:
            assert tracker.reached(step + 1).all()  # what begin_step of the next step sees


@settings(max_examples=40, deadline=None)
@given(st.integers(3, 8), st.integers(0, 2**32 - 1), st.integers(0, 3))
def test_a_split_is_counted_by_every_drone_within_its_window_and_healed_when_joined(
        n, seed, slack):
    rng = np.random.default_rng(seed)
    cut = int(rng.integers(1, n))  # drones below ``cut`` and the rest: two paths
    whole = _adjacency(n, [(k, k + 1) for k in range(n - 1)])
    split = whole.copy()
    split[cut - 1, cut] = split[cut, cut - 1] = False
    trackers = [ReachTracker(i, n, slack) for i in range(n)]
    window = n - 1 + slack
    for step in range(20):
        _flood(trackers, whole, step)
    for step in range(20, 20 + window + 1):
        _flood(trackers, split, step)
        for i, tracker in enumerate(trackers):
            reached = tracker.reached(step + 1)
            own_part = np.arange(n) < cut if i < cut else np.arange(n) >= cut
            assert reached[own_part].all()
            if step + 1 - 20 > window:  # the other part's newest stamp is step 19 or older
                assert not reached[~own_part].any()
    for step in range(20 + window + 1, 20 + 2 * window + 2):
        _flood(trackers, whole, step)
    assert all(tracker.reached(20 + 2 * window + 2).all() for tracker in trackers)


def test_every_drone_counts_as_reached_at_the_first_step_whenever_it_comes() -> None:
    """A realtime agent's first step is the world's step of its first frame, not 0: the
    others count as reached from there, and age out only a window later."""
    tracker = ReachTracker(1, 4, 2)
    tracker.stamp(500)
    assert tracker.reached(500).all()
    for step in range(501, 506):
        tracker.stamp(step)
    assert tracker.reached(505).all()  # window 3 + 2 = 5 steps
    tracker.stamp(506)
    assert tracker.reached(506).tolist() == [False, True, False, False]
