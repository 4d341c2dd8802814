"""Radios with a range: the disk graph with hysteresis, its components and λ₂, the links the
swarm keeps (as barrier rows) and how far each drone's news reaches (docs/network.md).

* ``NetworkParams``: ``topology`` "fixed" (``swarm.edges``, the thesis) or "range" (drones i
  and j are linked while within ``range_m``; a link comes up only within ``range_m −
  hysteresis_m``, so a pair at the edge does not chatter), and ``keep`` "none", "edges"
  (each configured edge kept within ``keep_range_m``) or "tree" (only the edges of
  ``spanning_tree``, the breadth-first tree of the configured graph from drone 0: every drone
  derives the same tree from the config, no agreement protocol needed, and N − 1 links are
  the fewest that keep N drones connected), each kept link by a hard barrier row in both
  drones' QPs: h_ij = R_keep² − ‖p_i − p_j‖² ≥ 0, split between the two drones as the
  collision rows are: −2(p_i − p_j)ᵀu_i ≥ −α_keep h_ij / 2.
* ``RadioRange``: the simulated radio (the one place a simulation decides who hears whom):
  links of a step from the positions and the links of the step before, deterministic.
* ``ReachTracker``: what a drone learns from the messages it hears, with no map of the swarm:
  for every drone j the newest step at which j's own stamp reached it (relayed hop by hop,
  one hop per step). On a graph connected at every step a stamp reaches everyone within
  N − 1 steps, so a drone whose stamp is older than that (plus a slack for lost messages) is
  not in this drone's component: the swarm has split, and the component's size is the
  number of drones still reached.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from swarm.core.params import require, require_finite_positive

Array = NDArray[np.float64]
BoolMatrix = NDArray[np.bool_]
Topology = Literal["fixed", "range"]
KeepRule = Literal["none", "edges", "tree"]
IntegralForm = Literal["differences", "own"]


@dataclass(frozen=True)
class NetworkParams:
    """The ``[network]`` section (module docstring); the default is the thesis' fixed graph."""

    topology: Topology = "fixed"  # "fixed": swarm.edges, always delivered; "range": a disk graph
    range_m: float = 30.0  # R: a link holds while the drones are within this [m]
    hysteresis_m: float = 1.0  # a link comes up within R − this only [m]
    # "edges": swarm.edges kept within keep_range_m by barrier rows; "tree": a spanning tree
    # of them (spanning_tree)
    keep: KeepRule = "none"
    keep_range_m: float | None = None  # R_keep [m]; None: R − hysteresis_m
    keep_gain: float = 1.0  # α_keep of the keep rows [1/s]
    # A drone not reached for N − 1 + this many steps is counted outside the component
    # (ReachTracker): room for lost or late messages (realtime, a real radio) [steps].
    reach_slack_steps: int = 25
    # How the PI consensus's integral enters on a range graph: "differences", K_i Σ_j (η_i −
    # η_j) as the thesis' (3.30), or "own", K_i η_i (dynamic_consensus.
    # switching_pi_consensus_step; exact on links heard both ways, biased by one-way ones)
    integral: IntegralForm = "differences"

    def __post_init__(self) -> None:
        require(self.topology in ("fixed", "range"), "topology", "must be 'fixed' or 'range'",
                self.topology)
        require(self.keep in ("none", "edges", "tree"), "keep",
                "must be 'none', 'edges' or 'tree'", self.keep)
        require_finite_positive("range_m", self.range_m)
        require(math.isfinite(self.hysteresis_m) and 0 <= self.hysteresis_m < self.range_m,
                "hysteresis_m", "must be a finite number in [0, range_m)", self.hysteresis_m)
        if self.keep_range_m is not None:
            require(math.isfinite(self.keep_range_m) and 0 < self.keep_range_m <= self.range_m,
                    "keep_range_m", "must be a finite number in (0, range_m]", self.keep_range_m)
        require_finite_positive("keep_gain", self.keep_gain)
        require(0 <= self.reach_slack_steps <= 10_000, "reach_slack_steps",
                "must be an integer in [0, 10000]", self.reach_slack_steps)
        require(self.integral in ("differences", "own"), "integral",
                "must be 'differences' or 'own'", self.integral)
        require(self.topology == "range" or self.keep == "none", "keep",
                "needs topology = 'range' (a fixed graph has no range to keep)", self.keep)

    @property
    def ranged(self) -> bool:
        return self.topology == "range"

    @property
    def keeps_links(self) -> bool:
        return self.keep != "none"

    def kept_edges(self, n_drones: int, edges: tuple[tuple[int, int], ...]
                   ) -> tuple[tuple[int, int], ...]:
        """The links this rule keeps: none, the configured ``edges``, or their
        ``spanning_tree``; each pair (low id, high id), sorted."""
        if self.keep == "none":
            return ()
        chosen = edges if self.keep == "edges" else spanning_tree(n_drones, edges)
        return tuple(sorted((min(a, b), max(a, b)) for a, b in chosen))

    @property
    def kept_range_m(self) -> float:
        """R_keep: ``keep_range_m``, or R − hysteresis_m (a kept pair never reaches the edge
        band, where its link could drop)."""
        return self.range_m - self.hysteresis_m if self.keep_range_m is None else self.keep_range_m


def spanning_tree(n_drones: int, edges: tuple[tuple[int, int], ...]
                  ) -> tuple[tuple[int, int], ...]:
    """The breadth-first spanning tree of the (connected) graph ``edges`` from drone 0,
    neighbours taken in id order: N − 1 of its edges, the same for every drone."""
    adjacent: list[list[int]] = [[] for _ in range(n_drones)]
    for a, b in edges:
        adjacent[a].append(b)
        adjacent[b].append(a)
    seen = {0}
    frontier = [0]
    tree: list[tuple[int, int]] = []
    while frontier:
        following: list[int] = []
        for node in frontier:
            for other in sorted(adjacent[node]):
                if other not in seen:
                    seen.add(other)
                    tree.append((node, other))
                    following.append(other)
        frontier = following
    return tuple(tree)


def pair_distances(positions: Array) -> Array:
    """‖p_i − p_j‖ for every pair, (N, N) [m]."""
    p = np.asarray(positions, dtype=float)
    diff = p[:, None, :] - p[None, :, :]
    distances: Array = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    return distances


def range_links(distances: Array, previous: BoolMatrix | None, range_m: float,
                hysteresis_m: float) -> BoolMatrix:
    """The disk graph with hysteresis: i–j linked when d_ij ≤ R − h, or when they were
    linked and d_ij ≤ R; with no previous step, when d_ij ≤ R. Symmetric, no self-links."""
    if previous is None:
        links = distances <= range_m
    else:
        links = (distances <= range_m - hysteresis_m) | (previous & (distances <= range_m))
    np.fill_diagonal(links, False)
    return links


class RadioRange:
    """The simulated radio of a run: each step's links from the drones' positions and the
    previous step's links (``range_links``); the same positions give the same links in
    every mode."""

    def __init__(self, params: NetworkParams) -> None:
        self.params = params
        self.links: BoolMatrix | None = None

    def step(self, positions: Array) -> BoolMatrix:
        p = self.params
        self.links = range_links(pair_distances(positions), self.links, p.range_m,
                                 p.hysteresis_m)
        return self.links


def components(links: BoolMatrix) -> list[list[int]]:
    """The connected components of the graph ``links`` (N, N), each sorted, ordered by their
    smallest id."""
    n = links.shape[0]
    label = [-1] * n
    found: list[list[int]] = []
    for start in range(n):
        if label[start] >= 0:
            continue
        label[start] = len(found)
        members, frontier = [start], [start]
        while frontier:
            node = frontier.pop()
            for other in np.flatnonzero(links[node]).tolist():
                if label[other] < 0:
                    label[other] = label[start]
                    members.append(other)
                    frontier.append(other)
        found.append(sorted(members))
    return found


def algebraic_connectivity(links: BoolMatrix) -> float:
    """λ₂ of the graph's Laplacian (0 exactly when it is disconnected; Fiedler)."""
    adjacency = links.astype(float)
    laplacian = np.diag(adjacency.sum(axis=1)) - adjacency
    eigenvalues = np.linalg.eigvalsh(laplacian)
    return float(eigenvalues[1]) if eigenvalues.shape[0] > 1 else 0.0


def keep_row(own: list[float], other: list[float], keep_range_m: float,
             gain: float) -> tuple[tuple[float, float, float], float, float]:
    """Drone i's half of the keep-link barrier with drone j: (a, lower, h) with a·u_i ≥ lower,
    h = R_keep² − ‖p_i − p_j‖², a = −2(p_i − p_j), lower = −α h / 2 (module docstring)."""
    dx, dy, dz = own[0] - other[0], own[1] - other[1], own[2] - other[2]
    h = keep_range_m * keep_range_m - (dx * dx + dy * dy + dz * dz)
    return (-2.0 * dx, -2.0 * dy, -2.0 * dz), -0.5 * gain * h, h


class ReachTracker:
    """How far a drone's news reaches (module docstring): ``stamps[j]`` is the newest step
    whose stamp of drone j reached this drone (its own: the current step). Every drone
    counts as reached at this drone's first step (the swarm starts connected, as the
    thesis' does; a realtime agent's first step need not be step 0)."""

    def __init__(self, drone_id: int, n_drones: int, slack_steps: int) -> None:
        self.drone_id = drone_id
        self.window = n_drones - 1 + slack_steps
        self.stamps = np.zeros(n_drones)
        self._started = False

    def stamp(self, step: int) -> None:
        if not self._started:
            self.stamps[:] = float(step)
            self._started = True
        self.stamps[self.drone_id] = float(step)

    def merge(self, heard: Array) -> None:
        """Take a neighbour's stamps (elementwise newest); non-finite entries are ignored by
        the caller (a message with one is rejected whole)."""
        np.maximum(self.stamps, heard, out=self.stamps)

    def reached(self, step: int) -> BoolMatrix:
        """Which drones are in this drone's component at ``step``."""
        reached: BoolMatrix = self.stamps >= step - self.window
        return reached
