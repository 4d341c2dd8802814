"""The communication graph: validation, Laplacian, connectivity, consensus weights (SPEC §5-§6)."""

from __future__ import annotations

import numpy as np
import pytest

from swarm.core.graph import CommunicationGraph

RING_EDGES = tuple((i, (i + 1) % 6) for i in range(6))
SCENARIO = CommunicationGraph(6, (*RING_EDGES, (0, 3), (1, 4)))  # SPEC §11


@pytest.mark.parametrize(
    "graph",
    [SCENARIO, CommunicationGraph(6, RING_EDGES), CommunicationGraph(4, ((0, 1), (1, 2))),
     CommunicationGraph(1, ())],
    ids=["scenario", "ring", "path+isolated", "single"],
)
def test_laplacian_is_symmetric_psd_with_zero_row_sums(graph: CommunicationGraph) -> None:
    """L = D − A: symmetric, rows sum to 0, diagonal = degree, eigenvalues ≥ 0."""
    lap = graph.laplacian
    np.testing.assert_array_equal(lap, lap.T)
    np.testing.assert_array_equal(lap.sum(axis=1), 0.0)
    np.testing.assert_array_equal(np.diag(lap), [graph.degree(i) for i in range(graph.n_nodes)])
    eigenvalues = np.linalg.eigvalsh(lap)
    assert eigenvalues[0] > -1e-12
    assert graph.laplacian_max_eigenvalue == pytest.approx(eigenvalues[-1])


def test_known_spectra() -> None:
    """Ring C6: λ_max = 4; scenario graph: λ_max = (7 + √17)/2 ≈ 5.56 (checked numerically)."""
    assert CommunicationGraph(6, RING_EDGES).laplacian_max_eigenvalue == pytest.approx(4.0)
    assert SCENARIO.laplacian_max_eigenvalue == pytest.approx((7 + np.sqrt(17)) / 2)


def test_neighbours_and_degrees() -> None:
    assert SCENARIO.neighbours[0] == (1, 3, 5)
    assert SCENARIO.neighbours[2] == (1, 3)
    assert [SCENARIO.degree(i) for i in range(6)] == [3, 3, 2, 3, 3, 2]


def test_connectivity() -> None:
    assert SCENARIO.is_connected()
    assert CommunicationGraph(1, ()).is_connected()
    assert not CommunicationGraph(4, ((0, 1), (2, 3))).is_connected()
    assert not CommunicationGraph(3, ((0, 1),)).is_connected()


@pytest.mark.parametrize(
    ("n_nodes", "edges", "fragments"),
    [
        (3, ((0, 3),), ["drone id 3", "[0, 3]", "out of range", "0..2"]),
        (3, ((-1, 2),), ["drone id -1", "out of range"]),
        (3, ((1, 1),), ["self-loop", "[1, 1]"]),
        (3, ((0, 1), (0, 1)), ["[0, 1]", "twice"]),
        (3, ((0, 1), (1, 0)), ["[1, 0]", "twice"]),  # the same undirected edge
        (0, (), ["must be >= 1", "got 0"]),
    ],
    ids=["id-too-large", "negative-id", "self-loop", "duplicate", "reversed-duplicate",
         "no-nodes"],
)
def test_invalid_graphs_are_refused_with_a_message_naming_the_problem(
    n_nodes: int, edges: tuple, fragments: list[str]
) -> None:
    with pytest.raises(ValueError) as error:
        CommunicationGraph(n_nodes, edges)
    for fragment in fragments:
        assert fragment in str(error.value)


def test_metropolis_weights() -> None:
    """a_ij = 1/(1 + max(deg_i, deg_j)), only for neighbours; symmetric in i, j."""
    weights = [SCENARIO.consensus_weights(i, "metropolis", 0.2) for i in range(6)]
    assert weights[2] == {1: 0.25, 3: 0.25}  # deg 2 next to two deg-3 nodes
    assert weights[0] == {1: 0.25, 3: 0.25, 5: 0.25}
    for i in range(6):
        for j, a in weights[i].items():
            assert weights[j][i] == a
        assert sum(weights[i].values()) < 1.0  # keeps a positive self-weight


def test_laplacian_weights_option() -> None:
    """The thesis form a_ij = ε for every neighbour (SPEC §5 option)."""
    assert SCENARIO.consensus_weights(0, "laplacian", 0.2) == {1: 0.2, 3: 0.2, 5: 0.2}
