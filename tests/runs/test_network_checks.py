"""The radio's judge on its own: ``kept_link``, ``split_said`` and the network summary of
``swarm.runs.network`` on records built by hand (issue 44, point 5; the judge is judged).

Six drones hover on a line 2 m apart (``tests/runs/test_checks.clean_record``) under a radio
of R = 20 m that links everyone; each test moves a pair, cuts the graph or changes a count
where a bound, an index or a comparison is easy to get wrong: the first and the last step,
the first and the last kept link, exactly at R (holds) and one float past it (does not), the
reach window's first settled step, counts that never arrived. Seconds in all.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from swarm.core.network import NetworkParams, spanning_tree
from swarm.runs.checks import check_invariants
from swarm.runs.network import (
    check_network,
    component_series,
    kept_link_distances,
    kept_links,
    network_summary,
)
from swarm.runs.record import RunRecord
from tests.runs.test_checks import changed, clean_record, past

N = 6
RANGE_M = 20.0
SLACK_STEPS = 5
WINDOW = N - 1 + SLACK_STEPS  # steps the graph must hold before the counts are judged


def ranged(keep: str = "edges", **network: object) -> RunRecord:
    """The clean record under a range radio: complete graph, every count N, no conflict."""
    record = clean_record(N)
    params = NetworkParams(topology="range", range_m=RANGE_M, keep=keep,  # type: ignore[arg-type]
                           reach_slack_steps=SLACK_STEPS, **network)  # type: ignore[arg-type]
    k = record.n_steps
    links = np.ones((k, N, N), dtype=bool)
    links[:, np.arange(N), np.arange(N)] = False
    return dataclasses.replace(
        record, config=dataclasses.replace(record.config, network=params), links=links,
        reached=np.full((k, N), N, dtype=np.int64), link_conflict=np.zeros((k, N), bool))


def stretch(record: RunRecord, step: int, pair: tuple[int, int], distance_m: float
            ) -> RunRecord:
    """At ``step``, the pair ``distance_m`` apart along x and every other drone between
    them (x = 0, 1 m apart along y), so that only the pair's link is long."""
    positions = record.drone_positions_m.copy()
    i, j = pair
    others = [k for k in range(N) if k not in pair]
    positions[step, :, :2] = 0.0
    positions[step, others, 1] = np.arange(len(others)) - (len(others) - 1) / 2
    positions[step, i, 0], positions[step, j, 0] = -distance_m / 2, distance_m / 2
    return changed(record, drone_positions_m=positions)


def split(record: RunRecord, from_step: int, part: tuple[int, ...]) -> RunRecord:
    """The radio's graph cut between ``part`` and the rest from ``from_step`` on."""
    links = record.links.copy()
    rest = [i for i in range(N) if i not in part]
    for a in part:
        links[from_step:, a, rest] = False
        links[from_step:, rest, a] = False
    return changed(record, links=links)


def counted(record: RunRecord, from_step: int, part: tuple[int, ...]) -> RunRecord:
    """Every drone counts its side of the cut (``split``) from ``from_step`` on."""
    reached = record.reached.copy()
    rest = [i for i in range(N) if i not in part]
    reached[from_step:, list(part)] = len(part)
    reached[from_step:, rest] = len(rest)
    return changed(record, reached=reached)


def network_violations(record: RunRecord, invariant: str) -> list:
    return [v for v in check_network(record) if v.invariant == invariant]


def test_a_clean_ranged_record_holds_and_its_summary_is_exact() -> None:
    record = ranged()
    assert check_network(record) == []
    summary = network_summary(record)
    assert summary is not None
    assert (summary.topology, summary.keep, summary.range_m) == ("range", "edges", RANGE_M)
    assert summary.max_components == 1 and summary.first_split_s is None
    assert summary.min_algebraic_connectivity == pytest.approx(N)  # the complete graph's
    assert summary.split_parts == () and summary.first_said_s is None
    longest_kept = max(2.0 * abs(i - j) for i, j in record.config.swarm.edges)
    assert summary.min_kept_margin_m == pytest.approx(RANGE_M - longest_kept)
    assert summary.link_conflicts == 0


def test_the_kept_links_are_the_edges_their_tree_or_none() -> None:
    edges = clean_record(N).config.swarm.edges
    assert kept_links(ranged("edges")) == tuple(sorted((min(e), max(e)) for e in edges))
    assert kept_links(ranged("tree")) == tuple(sorted(spanning_tree(N, edges)))
    assert kept_links(ranged("none")) == ()
    assert kept_links(clean_record(N)) == ()  # the fixed graph keeps nothing
    assert kept_link_distances(ranged("none")).shape == (clean_record(N).n_steps, 0)


@pytest.mark.parametrize("step", [0, -1])
@pytest.mark.parametrize("which", ["first", "last"])
def test_kept_link_at_r_holds_and_one_float_past_it_does_not(step: int, which: str) -> None:
    record = ranged()
    links = kept_links(record)
    pair = links[0] if which == "first" else links[-1]
    assert check_network(stretch(record, step, pair, RANGE_M)) == []
    beyond = past(RANGE_M, below=False)
    broken = stretch(record, step, pair, beyond)
    (violation,) = network_violations(broken, "kept_link")
    t = float(record.times_s[step])
    assert violation.subject == violation.first_subject == f"drones {pair[0]} and {pair[1]}"
    assert violation.worst_value == pytest.approx(beyond, abs=1e-12)
    assert violation.limit == RANGE_M and violation.excess == pytest.approx(0, abs=1e-12)
    assert violation.worst_time_s == violation.first_time_s == t
    assert violation.time_beyond_s == pytest.approx(record.config.scenario.dt_s)
    assert violation.detail.startswith(f"kept link {pair[0]}–{pair[1]} stretched to ")
    assert f"at t = {t:.2f} s; first beyond at t = {t:.2f} s (link {pair[0]}–{pair[1]})" in \
        violation.detail


def test_kept_link_names_the_first_crossing_apart_from_the_worst() -> None:
    record = ranged()
    first, worst = kept_links(record)[0], kept_links(record)[-1]
    broken = stretch(stretch(stretch(record, 10, first, RANGE_M + 0.5), 11, first,
                             RANGE_M + 0.5), 70, worst, RANGE_M + 3.0)
    (violation,) = network_violations(broken, "kept_link")
    times = record.times_s
    assert violation.subject == f"drones {worst[0]} and {worst[1]}"
    assert violation.first_subject == f"drones {first[0]} and {first[1]}"
    assert violation.worst_value == pytest.approx(RANGE_M + 3.0)
    assert violation.excess == pytest.approx(3.0)
    assert (violation.worst_time_s, violation.first_time_s) == (times[70], times[10])
    assert violation.time_beyond_s == pytest.approx(3 * record.config.scenario.dt_s)
    assert violation.detail == (
        f"kept link {worst[0]}–{worst[1]} stretched to {RANGE_M + 3.0:.3f} m > R = "
        f"{RANGE_M} m (by 3.000 m) at t = {times[70]:.2f} s; first beyond at t = "
        f"{times[10]:.2f} s (link {first[0]}–{first[1]}), beyond for 0.06 s")


def test_every_run_is_judged_by_the_radios_invariants_too() -> None:
    broken = stretch(ranged(), 30, kept_links(ranged())[0], RANGE_M + 1.0)
    assert only_invariant(check_invariants(broken)) == "kept_link"
    reached = ranged().reached.copy()
    reached[70, 3] = 2
    assert only_invariant(check_invariants(changed(ranged(), reached=reached))) == "split_said"
    assert check_network(clean_record(N)) == []  # the fixed graph: nothing to judge


def only_invariant(violations: list) -> str:
    (violation,) = violations
    return str(violation.invariant)


def test_only_kept_links_are_judged() -> None:
    record = ranged("tree")
    tree = set(kept_links(record))
    (outside,) = [tuple(sorted(e)) for e in record.config.swarm.edges if
                  tuple(sorted(e)) not in tree][:1]
    assert check_network(stretch(record, 20, outside, RANGE_M + 5.0)) == []
    assert check_network(stretch(ranged("none"), 20, (0, 1), RANGE_M + 5.0)) == []


def test_a_missing_position_is_not_a_stretch_and_none_at_all_is_not_checked() -> None:
    record = ranged()
    positions = record.drone_positions_m.copy()
    positions[5:, 0] = np.nan  # drone 0 unseen after step 5: its links are not judged
    broken = stretch(changed(record, drone_positions_m=positions), 2, (0, 1), RANGE_M + 1.0)
    (violation,) = network_violations(broken, "kept_link")
    assert violation.first_time_s == violation.worst_time_s == record.times_s[2]
    assert check_network(changed(record, drone_positions_m=positions)) == []
    summary = network_summary(changed(record, drone_positions_m=positions))
    assert summary is not None and summary.min_kept_margin_m == pytest.approx(
        RANGE_M - max(2.0 * abs(i - j) for i, j in record.config.swarm.edges))
    positions[:] = np.nan
    (violation,) = network_violations(changed(record, drone_positions_m=positions),
                                      "kept_link")
    assert violation.detail == ("not checked: no step with the positions of a kept link's "
                                "two drones")
    unseen = network_summary(changed(record, drone_positions_m=positions))
    assert unseen is not None and unseen.min_kept_margin_m is None


def test_a_split_counted_on_the_first_settled_step_holds_one_step_later_does_not() -> None:
    cut = split(ranged(), 40, (4, 5))
    assert check_network(counted(cut, 40 + WINDOW, (4, 5))) == []
    assert check_network(counted(cut, 40, (4, 5))) == []  # said at once: not wrong either
    late = counted(cut, 40 + WINDOW + 1, (4, 5))
    (violation,) = network_violations(late, "split_said")
    t = float(cut.times_s[40 + WINDOW])
    assert violation.first_time_s == t
    assert violation.subject == violation.first_subject == "drone 0"
    assert violation.worst_value == N and violation.limit == N - 2
    assert violation.detail == (
        f"drone 0 counted {N} drones in its part of the swarm at t = {t:.2f} s where the "
        f"radio's graph, unchanged for {WINDOW} steps, gives {N - 2} ({N} drone-steps wrong)")


def test_the_last_drone_and_the_last_step_are_judged() -> None:
    record = ranged()
    reached = record.reached.copy()
    reached[-1, -1] = N - 1
    (violation,) = network_violations(changed(record, reached=reached), "split_said")
    assert violation.subject == f"drone {N - 1}"
    assert violation.first_time_s == record.times_s[-1]
    assert violation.worst_value == N - 1 and violation.limit == N


def test_the_first_window_and_a_changing_graph_are_not_judged() -> None:
    """Every drone counts the whole swarm at its first step, whatever the graph; a count is
    judged once the graph has held for the window."""
    cut_from_start = split(ranged(), 0, (5,))
    reached = cut_from_start.reached  # N everywhere: wrong once the window has passed
    (violation,) = network_violations(cut_from_start, "split_said")
    assert violation.first_time_s == cut_from_start.times_s[WINDOW]
    ok_later = counted(cut_from_start, WINDOW, (5,))
    assert np.array_equal(reached, cut_from_start.reached) and check_network(ok_later) == []
    # A link that flaps every WINDOW − 1 steps never lets the graph settle.
    links = ranged().links.copy()
    for k in range(0, links.shape[0], WINDOW - 1):
        if (k // (WINDOW - 1)) % 2:
            links[k:k + WINDOW - 1, 0, 1] = links[k:k + WINDOW - 1, 1, 0] = False
    assert check_network(changed(ranged(), links=links)) == []


def test_a_drone_counting_only_itself_is_judged_and_said() -> None:
    record = ranged()
    reached = record.reached.copy()
    reached[45, 5] = 1  # drone 5 alone, where the graph is whole
    lonely = changed(record, reached=reached)
    (violation,) = network_violations(lonely, "split_said")
    assert violation.subject == "drone 5" and violation.worst_value == 1
    summary = network_summary(lonely)
    assert summary is not None and summary.first_said_s == record.times_s[45]
    cut = counted(split(record, 40, (5,)), 40, (5,))
    assert check_network(cut) == []


def test_a_record_without_counts_or_without_links_has_no_split_to_judge() -> None:
    for missing in ("reached", "links"):
        record = changed(split(ranged(), 40, (4, 5)), **{missing: None})
        assert network_violations(record, "split_said") == [], missing


def test_a_count_never_sent_is_not_judged_and_not_said() -> None:
    record = ranged()
    reached = record.reached.copy()
    reached[60:, 2] = 0
    unsent = changed(record, reached=reached)
    assert check_network(unsent) == []
    summary = network_summary(unsent)
    assert summary is not None and summary.first_said_s is None


def test_the_summary_of_a_split_swarm() -> None:
    cut = counted(split(ranged(), 40, (4, 5)), 45, (4, 5))
    conflicts = cut.link_conflict.copy()
    conflicts[3, 1] = conflicts[90, 5] = conflicts[90, 4] = True
    summary = network_summary(changed(cut, link_conflict=conflicts))
    assert summary is not None
    assert summary.first_split_s == cut.times_s[40]
    assert summary.split_parts == ((0, 1, 2, 3), (4, 5))
    assert summary.first_said_s == cut.times_s[45]
    assert summary.max_components == 2 and summary.min_algebraic_connectivity == \
        pytest.approx(0.0, abs=1e-9)
    assert summary.link_conflicts == 3
    series = component_series(cut)
    assert series is not None and series[39] == [list(range(N))]
    assert series[40] == [[0, 1, 2, 3], [4, 5]]


def test_a_summary_without_links_or_counts_says_none() -> None:
    record = changed(ranged(), links=None, reached=None, link_conflict=None)
    summary = network_summary(record)
    assert summary is not None
    assert summary.max_components is None and summary.min_algebraic_connectivity is None
    assert summary.first_split_s is None and summary.first_said_s is None
    assert summary.link_conflicts is None and component_series(record) is None
    assert network_violations(record, "split_said") == []
    assert network_summary(clean_record(N)) is None
