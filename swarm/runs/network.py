"""The radio's side of a finished run (``[network]``, ``swarm.core.network``): its invariants
and its summary.

Two invariants, checked like the envelope after every run whose config has a range:

* ``kept_link``: every kept link (``network.keep``) within R = ``network.range_m`` at every
  step, from the drones' true positions (beyond R the radio drops the link);
* ``split_said``: wherever the radio's graph has stayed the same for a drone's reach window
  (N − 1 + ``network.reach_slack_steps`` steps), each drone counts exactly the drones of its
  component (``DroneAgent``'s ``reached``): a split the swarm does not say, or a split it
  says that did not happen, is a violation. Needs the record's links and reach counts.

``network_summary`` gives the figures of the report: components and λ₂ of the radio's graph
over time, when the swarm first split and when a drone first said so, the smallest margin of
a kept link and the steps a keep row overruled localization.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarm.core.network import algebraic_connectivity, components
from swarm.runs.record import RunRecord
from swarm.runs.violation import Violation

FloatArray = NDArray[np.float64]


def kept_links(record: RunRecord) -> tuple[tuple[int, int], ...]:
    """The links the run's config keeps (none without a range)."""
    cfg = record.config
    if not cfg.network.ranged:
        return ()
    return cfg.network.kept_edges(cfg.swarm.n_drones, cfg.swarm.edges)


def kept_link_distances(record: RunRecord) -> FloatArray:
    """‖p_i − p_j‖ of every kept link at every step, (K, L) [m] (NaN where a position is
    missing)."""
    links = kept_links(record)
    p = record.drone_positions_m
    if not links:
        return np.zeros((p.shape[0], 0))
    a = np.array([i for i, _ in links])
    b = np.array([j for _, j in links])
    distances: FloatArray = np.linalg.norm(p[:, a] - p[:, b], axis=-1)
    return distances


def component_series(record: RunRecord) -> list[list[list[int]]] | None:
    """The radio graph's components at every step (None: the record has no links)."""
    if record.links is None:
        return None
    return [components(record.links[k]) for k in range(record.links.shape[0])]


def check_network(record: RunRecord) -> list[Violation]:
    """The ``kept_link`` and ``split_said`` invariants (module docstring); none on the fixed
    graph."""
    if not record.config.network.ranged:
        return []
    return [*_check_kept_links(record), *_check_split_said(record)]


def _check_kept_links(record: RunRecord) -> list[Violation]:
    links = kept_links(record)
    if not links:
        return []
    range_m = record.config.network.range_m
    distances = kept_link_distances(record)
    if np.isnan(distances).all():
        return [Violation("kept_link", "not checked: no step with the positions of a kept "
                                       "link's two drones")]
    beyond = distances > range_m  # NaN (a position missing): not beyond
    if not beyond.any():
        return []
    worst_step, worst_link = np.unravel_index(
        int(np.argmax(np.where(beyond, distances, -np.inf))), distances.shape)
    first_step = int(np.argmax(beyond.any(axis=1)))
    first_link = int(np.argmax(beyond[first_step]))
    times = record.times_s
    worst = float(distances[worst_step, worst_link])
    i, j = links[int(worst_link)]
    fi, fj = links[first_link]
    dt = record.config.scenario.dt_s
    return [Violation(
        "kept_link",
        f"kept link {i}–{j} stretched to {worst:.3f} m > R = {range_m} m (by "
        f"{worst - range_m:.3f} m) at t = {times[worst_step]:.2f} s; first beyond at "
        f"t = {times[first_step]:.2f} s (link {fi}–{fj}), beyond for "
        f"{int(beyond.any(axis=1).sum()) * dt:.2f} s",
        subject=f"drones {i} and {j}", worst_value=worst, limit=range_m,
        excess=worst - range_m, worst_time_s=float(times[worst_step]),
        first_time_s=float(times[first_step]), first_subject=f"drones {fi} and {fj}",
        time_beyond_s=int(beyond.any(axis=1).sum()) * dt)]


def _check_split_said(record: RunRecord) -> list[Violation]:
    if record.links is None or record.reached is None:
        return []
    cfg = record.config
    n = cfg.swarm.n_drones
    window = n - 1 + cfg.network.reach_slack_steps
    links, reached = record.links, record.reached
    sizes = np.zeros_like(reached)
    for k in range(links.shape[0]):
        for members in components(links[k]):
            sizes[k, members] = len(members)
    # Steps whose graph is the one of the window before them (the reach has settled). The
    # first window is never settled: every drone counts the whole swarm at its first step
    # (ReachTracker), whatever the graph.
    settled = np.zeros(links.shape[0], dtype=bool)
    unchanged = 0  # steps the graph has held, step 0 (never judged) not counted
    for k in range(1, links.shape[0]):
        unchanged = unchanged + 1 if np.array_equal(links[k], links[k - 1]) else 0
        settled[k] = unchanged >= window
    # A drone-step whose telemetry never arrived (realtime) says nothing either way: its
    # count is 0 (a drone counts itself, so every count sent is at least 1). The velocities
    # cannot tell: the launcher's record fills their gaps.
    present = reached > 0
    wrong = settled[:, None] & present & (reached != sizes)
    if not wrong.any():
        return []
    k, i = (int(v) for v in np.argwhere(wrong)[0])
    t = float(record.times_s[k])
    return [Violation(
        "split_said",
        f"drone {i} counted {int(reached[k, i])} drones in its part of the swarm at t = "
        f"{t:.2f} s where the radio's graph, unchanged for {window} steps, gives "
        f"{int(sizes[k, i])} ({int(wrong.sum())} drone-steps wrong)",
        subject=f"drone {i}", worst_value=float(reached[k, i]), limit=float(sizes[k, i]),
        first_time_s=t, first_subject=f"drone {i}")]


@dataclass(frozen=True)
class NetworkSummary:
    """The radio over a run (module docstring); times in s, None where it did not happen."""

    topology: str
    keep: str
    range_m: float
    max_components: int | None  # of the radio's graph (None: links not recorded)
    min_algebraic_connectivity: float | None  # λ₂ of the radio's graph, its smallest
    first_split_s: float | None  # the radio's graph first disconnected
    split_parts: tuple[tuple[int, ...], ...]  # its components then
    first_said_s: float | None  # a drone first counted fewer than N drones reached (0: unsent)
    min_kept_margin_m: float | None  # R − the longest kept link over the run [m]
    link_conflicts: int | None  # drone-steps a keep row overruled localization


def network_summary(record: RunRecord) -> NetworkSummary | None:
    """The figures of the radio (None for the fixed graph)."""
    cfg = record.config
    net = cfg.network
    if not net.ranged:
        return None
    parts = component_series(record)
    first_split = parts_then = None
    if parts is not None:
        split_steps = [k for k, p in enumerate(parts) if len(p) > 1]
        if split_steps:
            first_split = split_steps[0]
            parts_then = tuple(tuple(p) for p in parts[first_split])
    lambda2 = (None if record.links is None
               else min(algebraic_connectivity(record.links[k])
                        for k in range(record.links.shape[0])))
    said = (None if record.reached is None
            else np.flatnonzero(((record.reached > 0)
                                 & (record.reached < cfg.swarm.n_drones)).any(axis=1)))
    distances = kept_link_distances(record)
    kept_margin = (None if np.isnan(distances).all()  # also: no kept link
                   else float(net.range_m - np.nanmax(distances)))
    return NetworkSummary(
        topology=net.topology, keep=net.keep, range_m=net.range_m,
        max_components=None if parts is None else max(len(p) for p in parts),
        min_algebraic_connectivity=lambda2,
        first_split_s=None if first_split is None else float(record.times_s[first_split]),
        split_parts=parts_then or (),
        first_said_s=(None if said is None or said.size == 0
                      else float(record.times_s[said[0]])),
        min_kept_margin_m=kept_margin,
        link_conflicts=(None if record.link_conflict is None
                        else int(record.link_conflict.sum())))
