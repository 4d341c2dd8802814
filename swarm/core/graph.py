"""The fixed, undirected communication graph and its consensus weights (SPEC §5-§6)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from swarm.core.params import ConsensusGains, ConsensusWeighting


@dataclass(frozen=True)
class CommunicationGraph:
    """N drones (ids 0..N−1) and the undirected edges between them."""

    n_nodes: int
    edges: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        if self.n_nodes < 1:
            raise ValueError(f"n_drones must be >= 1 (got {self.n_nodes})")
        seen: set[frozenset[int]] = set()
        for a, b in self.edges:
            for node in (a, b):
                if not 0 <= node < self.n_nodes:
                    raise ValueError(
                        f"edges: drone id {node} in edge [{a}, {b}] is out of range "
                        f"0..{self.n_nodes - 1}"
                    )
            if a == b:
                raise ValueError(f"edges: self-loop [{a}, {b}] is not allowed")
            key = frozenset((a, b))
            if key in seen:
                raise ValueError(f"edges: edge [{a}, {b}] is listed twice")
            seen.add(key)

    @cached_property
    def neighbours(self) -> tuple[tuple[int, ...], ...]:
        adjacent: list[set[int]] = [set() for _ in range(self.n_nodes)]
        for a, b in self.edges:
            adjacent[a].add(b)
            adjacent[b].add(a)
        return tuple(tuple(sorted(nodes)) for nodes in adjacent)

    def degree(self, node: int) -> int:
        return len(self.neighbours[node])

    @cached_property
    def laplacian(self) -> NDArray[np.float64]:
        lap = np.zeros((self.n_nodes, self.n_nodes))
        for a, b in self.edges:
            lap[a, b] = lap[b, a] = -1.0
        lap[np.diag_indices(self.n_nodes)] = -lap.sum(axis=1)
        return lap

    @cached_property
    def laplacian_max_eigenvalue(self) -> float:
        return float(np.linalg.eigvalsh(self.laplacian)[-1])

    def is_connected(self) -> bool:
        reached = {0}
        frontier = [0]
        while frontier:
            node = frontier.pop()
            for other in self.neighbours[node]:
                if other not in reached:
                    reached.add(other)
                    frontier.append(other)
        return len(reached) == self.n_nodes

    def consensus_weights(
        self, node: int, weighting: ConsensusWeighting, laplacian_step: float
    ) -> dict[int, float]:
        """a_ij for the neighbours j of ``node`` (SPEC §5).

        Metropolis–Hastings a_ij = 1/(1 + max(deg_i, deg_j)) needs only the neighbours'
        degrees and is doubly stochastic; the thesis' Laplacian form uses a_ij = ε < 1/Δ_max.
        """
        if weighting == "laplacian":
            return {j: laplacian_step for j in self.neighbours[node]}
        own = self.degree(node)
        return {j: 1.0 / (1.0 + max(own, self.degree(j))) for j in self.neighbours[node]}


def pi_consensus_is_stable(
    graph: CommunicationGraph, gains: ConsensusGains, dt_s: float
) -> tuple[bool, float]:
    """Spectral radius of the Euler-discretized PI consensus error dynamics (SPEC §6).

    For each Laplacian eigenvalue λ the (s, η) pair evolves by
    [[1 − ΔT(ζ + K_pλ), ΔT K_iλ], [−ΔT K_iλ, 1]]. For λ = 0 the η mode is a pure integrator
    of a zero input (the η sum is invariant), so only the s-part counts there. Stable when
    every mode has spectral radius < 1.
    """
    radius = 0.0
    for lam in np.linalg.eigvalsh(graph.laplacian):
        if lam < 1e-9:
            radius = max(radius, abs(1.0 - dt_s * gains.zeta))
            continue
        mode = np.array(
            [[1.0 - dt_s * (gains.zeta + gains.kp * lam), dt_s * gains.ki * lam],
             [-dt_s * gains.ki * lam, 1.0]]
        )
        radius = max(radius, float(np.max(np.abs(np.linalg.eigvals(mode)))))
    return radius < 1.0, radius


def pi_consensus_is_stable_on_every_graph(
        n_nodes: int, gains: ConsensusGains, dt_s: float, *, own_integral: bool = False,
        samples: int = 2000) -> tuple[bool, float]:
    """The spectral radius of ``pi_consensus_is_stable`` over every graph of ``n_nodes``
    (a range graph may become any): each graph's Laplacian eigenvalues lie in [0, N], so λ
    is sampled there (``samples`` points, N included), λ = 0 counting for its s-part only.

    ``own_integral``: the form of ``dynamic_consensus.switching_pi_consensus_step``, where
    the integral enters as K_i η_i: its mode is [[1 − ΔT(ζ + K_pλ), ΔT K_i], [−ΔT K_i λ, 1]]
    (3.30's has ΔT K_i λ in the corner)."""
    lam = np.linspace(0.0, float(n_nodes), samples)[1:]
    modes = np.empty((lam.shape[0], 2, 2))  # one mode per λ, their eigenvalues in one call
    modes[:, 0, 0] = 1.0 - dt_s * (gains.zeta + gains.kp * lam)
    modes[:, 0, 1] = dt_s * gains.ki * (1.0 if own_integral else lam)
    modes[:, 1, 0] = -dt_s * gains.ki * lam
    modes[:, 1, 1] = 1.0
    radius = max(abs(1.0 - dt_s * gains.zeta),
                 float(np.max(np.abs(np.linalg.eigvals(modes)), initial=0.0)))
    return radius < 1.0, radius
