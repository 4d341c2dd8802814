"""The report of one run: a typed summary, its JSON form and its rich tables.

``build_report(record, mode, counters)`` is a pure function of a ``RunRecord`` (from the
in-process runner, the launcher or a recording), the timing mode and the agents' running
counters (``TelemetryCounters`` per drone; none for an in-process run). It returns a frozen
``RunReport``; ``report_to_json`` turns it into one JSON-ready dict (no NaN: a figure with no
sample at all is ``None``) and ``render_report`` prints its tables and verdict to a rich
Console — ``swarm-report`` and the end-of-run summary of ``launch-swarm`` share it.

Margins are λ − ε. "Final" is each drone's last step with a sample (a realtime or truncated
recording can miss steps); every figure is taken over the samples present, and the report
says how many were missing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from swarm.errors import EXIT_FAILED, EXIT_INCOMPLETE, EXIT_OK
from swarm.messages.wire import TelemetryCounters
from swarm.runs.checks import (
    SENSING_WEIGHT,
    Coverage,
    Violation,
    check_invariants,
    coverage,
    max_abs_velocity,
    min_envelope_margins,
    min_pairwise_distance,
    summarize_drones,
    summarize_targets,
)
from swarm.runs.network import NetworkSummary, network_summary
from swarm.runs.record import RunRecord

Mode = Literal["lockstep", "realtime", "inprocess"]
MODES: tuple[str, ...] = ("lockstep", "realtime", "inprocess")
EXIT_VIOLATION = EXIT_FAILED
MISSING = "—"  # how a figure without any sample is shown in a table
# A realtime run whose world ran slower than this (simulated s per wall s) is said to have
# fallen behind: its agents' wall-clock steps no longer match the world's.
REALTIME_CLOCK_RATE_FLOOR = 0.95


def finite_or_none(value: float | None) -> float | None:
    """A float for JSON: NaN and ±inf (no sample at all) become None."""
    if value is None or not math.isfinite(value):
        return None
    return float(value)


@dataclass(frozen=True)
class Provenance:
    """Where a run came from; everything is optional for an in-process record."""

    run_id: str = ""
    version: str = ""
    git_commit: str = ""
    source: str = ""  # recording path
    truncated: bool = False  # the recording ends before the run did (crash, kill)


@dataclass(frozen=True)
class TargetReport:
    id: int
    min_lambda_bar_margin: float | None  # min over drones and steps ≥ start of λ̄ − ε
    time_below_epsilon_s: float  # time after start during which some copy had λ̄ < ε
    min_true_lambda_margin: float | None  # min of λ_min(true G) − ε after start
    min_measured_lambda: float | None  # min of λ_min(measured G) after start
    final_position_error_m: float | None  # max over drones of each one's last error
    rms_position_error_m: float | None  # over drones and steps ≥ start
    drones_sensing_final: int  # drones with a final w > SENSING_WEIGHT for this target
    missing_samples: int  # drone-steps without this target's λ̄
    lambda_copy_spread: float | None = None  # worst max_i λ̄ − min_i λ̄ after start


@dataclass(frozen=True)
class DroneReport:
    id: int
    final_speed_mps: float | None
    final_weights: tuple[float | None, ...]
    idle_final: bool  # final w ≤ SENSING_WEIGHT for every target
    sensing_targets: tuple[int, ...]  # targets with a final w > SENSING_WEIGHT
    mean_step_us: float | None
    p99_step_us: float | None
    final_bearing_error: float | None  # None without a formation task
    qp_fallbacks: int
    late_steps: int | None  # None: not measured (in-process run, or no counters received)
    rejected_messages: int | None
    stale_neighbour_messages: int | None
    missing_neighbour_messages: int | None
    steps_run: int | None  # as counted by the agent process
    missing_samples: int  # steps whose telemetry never reached the recorder
    # Changes of the vehicle the agent did not ask for (swarm.watch.vehicle_watch) and what was
    # still wrong at the end ("" = nothing); None: not measured (in-process run).
    vehicle_events: int | None = None
    vehicle_status: str | None = None
    # Breaches of λ̄ ≥ ε − tol the agent saw in its own copies and said at once
    # (swarm.watch.localization_watch), when the first began [s], and what was still below at
    # the end.
    lambda_breaches: int | None = None
    first_lambda_breach_s: float | None = None
    localization_status: str | None = None


@dataclass(frozen=True)
class RunReport:
    scenario: str
    seed: int
    mode: str
    n_drones: int
    n_targets: int
    duration_s: float  # what the record covers (steps × ΔT)
    planned_duration_s: float  # scenario.duration_s
    steps: int
    dt_s: float
    epsilon: float
    lambda_tolerance: float
    start_s: float
    collision_distance_m: float
    u_max_mps: float
    min_pairwise_distance_m: float | None
    max_abs_velocity_mps: float | None  # largest |u_k| of one axis, as bounded by u_max
    qp_fallbacks: int
    late_steps: int | None
    rejected_messages: int | None
    wall_time_s: float | None
    targets: tuple[TargetReport, ...]
    drones: tuple[DroneReport, ...]
    violations: tuple[Violation, ...]
    coverage: Coverage
    warnings: tuple[str, ...]
    provenance: Provenance = field(default_factory=Provenance)
    # The [safety] envelope: the smallest distance of any drone to each kind of boundary [m]
    # (negative: outside; None: no position), {} without an envelope; the tolerance; and the
    # steps whose QP gave up localization to it (None: not recorded).
    envelope_margins_m: dict[str, float | None] = field(default_factory=dict)
    envelope_tolerance_m: float = 0.0
    safety_conflicts: int | None = None
    # The radio ([network] with a range; None for the fixed graph): components, λ₂, splits,
    # kept links (swarm.runs.network).
    network: NetworkSummary | None = None

    @property
    def ok(self) -> bool:
        """Every SPEC invariant held over the whole mission."""
        return not self.violations and not self.incomplete

    @property
    def incomplete(self) -> bool:
        """The record ends before the mission did (its steps < the planned steps)."""
        return self.coverage.cut_short

    @property
    def verdict(self) -> str:
        """"ok", "violated" (an invariant broken on the steps recorded, cut short or not) or
        "incomplete" (none broken, but the run was cut short: nothing to say of the rest)."""
        if self.violations:
            return "violated"
        return "incomplete" if self.incomplete else "ok"

    @property
    def exit_code(self) -> int:
        """0: every SPEC invariant held over the whole mission; 1: one did not (on the steps
        recorded); 4 (``EXIT_INCOMPLETE``): none broken, but the run was cut short."""
        return {"ok": EXIT_OK, "violated": EXIT_VIOLATION,
                "incomplete": EXIT_INCOMPLETE}[self.verdict]


# -- building ------------------------------------------------------------------------------


def _target_reports(record: RunRecord) -> tuple[TargetReport, ...]:
    return tuple(TargetReport(
        id=s.target,
        min_lambda_bar_margin=finite_or_none(s.min_lambda_bar_margin),
        time_below_epsilon_s=s.time_below_epsilon_s,
        min_true_lambda_margin=finite_or_none(s.min_true_lambda_margin),
        min_measured_lambda=finite_or_none(s.min_measured_lambda),
        final_position_error_m=finite_or_none(s.final_position_error_m),
        rms_position_error_m=finite_or_none(s.rms_position_error_m),
        drones_sensing_final=s.drones_sensing_final,
        missing_samples=s.missing_samples,
        lambda_copy_spread=finite_or_none(s.lambda_copy_spread),
    ) for s in summarize_targets(record))


def _drone_reports(record: RunRecord,
                   counters: Mapping[int, TelemetryCounters]) -> tuple[DroneReport, ...]:
    out = []
    for s in summarize_drones(record):
        c = counters.get(s.drone)
        out.append(DroneReport(
            id=s.drone,
            final_speed_mps=finite_or_none(s.final_speed_m_s),
            final_weights=tuple(finite_or_none(w) for w in s.final_weights),
            idle_final=s.idle_final,
            sensing_targets=tuple(r for r, w in enumerate(s.final_weights)
                                  if w > SENSING_WEIGHT),
            mean_step_us=finite_or_none(s.mean_step_us),
            p99_step_us=finite_or_none(s.p99_step_us),
            final_bearing_error=finite_or_none(s.final_bearing_error),
            # The agent's running total also counts steps whose telemetry was dropped.
            qp_fallbacks=max(s.qp_fallbacks, c.qp_fallbacks) if c else s.qp_fallbacks,
            late_steps=c.late_steps if c else None,
            rejected_messages=c.rejected_messages if c else None,
            stale_neighbour_messages=c.stale_neighbour_messages if c else None,
            missing_neighbour_messages=c.missing_neighbour_messages if c else None,
            steps_run=c.steps if c else None,
            missing_samples=s.missing_samples,
            vehicle_events=c.vehicle_events if c else None,
            vehicle_status=c.vehicle_status if c else None,
            lambda_breaches=c.lambda_breaches if c else None,
            first_lambda_breach_s=c.first_lambda_breach_s if c else None,
            localization_status=c.localization_status if c else None,
        ))
    return tuple(out)


def _sum_known(values: Sequence[int | None]) -> int | None:
    """Total over drones; None when no drone reported the counter at all."""
    known = [v for v in values if v is not None]
    return sum(known) if known else None


def _warnings(record: RunRecord, mode: str, cov: Coverage, drones: Sequence[DroneReport],
              provenance: Provenance) -> tuple[str, ...]:
    out = []
    planned = record.config.n_steps
    if provenance.truncated:
        out.append(f"the recording is truncated: {cov.steps} of {planned} steps; the verdict "
                   f"covers the steps present")
    elif cov.steps < planned:
        out.append(f"the record holds {cov.steps} of {planned} planned steps")
    if cov.missing_telemetry:
        per_drone = ", ".join(f"drone {i}: {n}" for i, n in enumerate(cov.missing_per_drone)
                              if n)
        out.append(f"{cov.missing_telemetry} of {cov.drone_steps} drone-step samples missing "
                   f"({per_drone}); figures use the samples present")
    if cov.missing_truth:
        out.append(f"{cov.missing_truth} of {cov.steps} steps without ground truth")
    if mode != "inprocess":
        silent = [d.id for d in drones if d.steps_run is None]
        if silent:
            out.append(f"no counters from drone(s) {', '.join(map(str, silent))}: late steps "
                       f"and rejected messages unknown for them")
        for d in drones:
            if d.vehicle_events:
                out.append(f"drone {d.id}: its vehicle left the state the agent asked for "
                           f"{d.vehicle_events} time(s) (the agent log has when and why)"
                           + (f"; at the end: {d.vehicle_status}" if d.vehicle_status else ""))
            if d.lambda_breaches:
                out.append(f"drone {d.id}: said it could not hold λ̄ ≥ ε − tol from t = "
                           f"{_fmt(d.first_lambda_breach_s, '.2f')} s ({d.lambda_breaches} "
                           f"breach(es) by target; the agent log has each)"
                           + (f"; at the end: {d.localization_status}"
                              if d.localization_status else ""))
    rate = record.world_clock_rate
    if mode == "realtime" and rate is not None and rate < REALTIME_CLOCK_RATE_FLOOR:
        out.append(f"the world's clock ran at {rate:.2f} of the wall's: this machine could not "
                   f"keep up in realtime. The agents count their steps on the wall clock, so "
                   f"their filters predicted the targets ahead of the world; estimates and "
                   f"margins are not those of a real-time mission (run it in lockstep)")
    network = network_summary(record)
    if network is not None and network.first_split_s is not None:
        parts = " and ".join(str(list(part)) for part in network.split_parts)
        said = ("said by a drone at t = " + _fmt(network.first_said_s, ".2f") + " s"
                if network.first_said_s is not None else "no drone said it")
        out.append(f"the swarm split at t = {network.first_split_s:.2f} s: its radios no longer "
                   f"connect {parts} ({said})")
    return tuple(out)


def build_report(record: RunRecord, mode: str = "inprocess",
                 counters: Mapping[int, TelemetryCounters] | None = None,
                 provenance: Provenance | None = None) -> RunReport:
    """Summaries, counters and the SPEC invariant checks of one run."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)} (got {mode!r})")
    cfg = record.config
    provenance = provenance or Provenance()
    drones = _drone_reports(record, counters or {})
    cov = coverage(record)
    dt = cfg.scenario.dt_s
    return RunReport(
        scenario=cfg.scenario.name,
        seed=record.seed,
        mode=mode,
        n_drones=cfg.swarm.n_drones,
        n_targets=len(cfg.targets),
        duration_s=round(record.n_steps * dt, 9),
        planned_duration_s=cfg.scenario.duration_s,
        steps=record.n_steps,
        dt_s=dt,
        epsilon=cfg.gramian.epsilon,
        lambda_tolerance=cfg.checks.lambda_tolerance,
        start_s=cfg.control.start_s,
        collision_distance_m=cfg.control.collision_distance_m,
        u_max_mps=cfg.control.u_max_m_s,
        min_pairwise_distance_m=finite_or_none(min_pairwise_distance(record)),
        max_abs_velocity_mps=finite_or_none(max_abs_velocity(record)),
        qp_fallbacks=sum(d.qp_fallbacks for d in drones),
        late_steps=_sum_known([d.late_steps for d in drones]),
        rejected_messages=_sum_known([d.rejected_messages for d in drones]),
        wall_time_s=finite_or_none(record.wall_time_s),
        targets=_target_reports(record),
        drones=drones,
        violations=tuple(check_invariants(record)),
        coverage=cov,
        warnings=_warnings(record, mode, cov, drones, provenance),
        provenance=provenance,
        envelope_margins_m={kind: finite_or_none(margin)
                            for kind, margin in min_envelope_margins(record).items()},
        envelope_tolerance_m=cfg.checks.envelope_tolerance_m,
        safety_conflicts=(None if record.safety_conflict is None
                          else int(record.safety_conflict.sum())),
        network=network_summary(record),
    )


# -- JSON ----------------------------------------------------------------------------------


def _target_json(t: TargetReport) -> dict[str, Any]:
    return {
        "id": t.id,
        "min_lambda_bar_margin": t.min_lambda_bar_margin,
        "time_below_epsilon_s": t.time_below_epsilon_s,
        "min_true_lambda_margin": t.min_true_lambda_margin,
        "min_measured_lambda": t.min_measured_lambda,
        "final_position_error_m": t.final_position_error_m,
        "rms_position_error_m": t.rms_position_error_m,
        "drones_sensing_final": t.drones_sensing_final,
        "missing_samples": t.missing_samples,
        "lambda_copy_spread": t.lambda_copy_spread,
    }


def _drone_json(d: DroneReport) -> dict[str, Any]:
    return {
        "id": d.id,
        "final_speed_mps": d.final_speed_mps,
        "final_weights": list(d.final_weights),
        "idle_final": d.idle_final,
        "sensing_targets": list(d.sensing_targets),
        "mean_step_us": d.mean_step_us,
        "p99_step_us": d.p99_step_us,
        "final_bearing_error": d.final_bearing_error,
        "qp_fallbacks": d.qp_fallbacks,
        "late_steps": d.late_steps,
        "rejected_messages": d.rejected_messages,
        "stale_neighbour_messages": d.stale_neighbour_messages,
        "missing_neighbour_messages": d.missing_neighbour_messages,
        "steps_run": d.steps_run,
        "missing_samples": d.missing_samples,
        "vehicle_events": d.vehicle_events,
        "vehicle_status": d.vehicle_status,
        "lambda_breaches": d.lambda_breaches,
        "first_lambda_breach_s": d.first_lambda_breach_s,
        "localization_status": d.localization_status,
    }


def report_to_json(report: RunReport) -> dict[str, Any]:
    """One JSON-ready dict (``json.dumps(..., allow_nan=False)`` accepts it)."""
    cov, prov = report.coverage, report.provenance
    return {
        "scenario": report.scenario,
        "seed": report.seed,
        "mode": report.mode,
        "run_id": prov.run_id,
        "version": prov.version,
        "git_commit": prov.git_commit,
        "truncated": prov.truncated,
        "n_drones": report.n_drones,
        "n_targets": report.n_targets,
        "duration_s": report.duration_s,
        "planned_duration_s": report.planned_duration_s,
        "steps": report.steps,
        "dt_s": report.dt_s,
        "epsilon": report.epsilon,
        "lambda_tolerance": report.lambda_tolerance,
        "start_s": report.start_s,
        "collision_distance_m": report.collision_distance_m,
        "u_max_mps": report.u_max_mps,
        "min_pairwise_distance_m": report.min_pairwise_distance_m,
        "max_abs_velocity_mps": report.max_abs_velocity_mps,
        "qp_fallbacks": report.qp_fallbacks,
        "late_steps": report.late_steps,
        "rejected_messages": report.rejected_messages,
        "wall_time_s": report.wall_time_s,
        "missing_samples": {"telemetry": cov.missing_telemetry, "truth": cov.missing_truth,
                            "drone_steps": cov.drone_steps},
        "targets": [_target_json(t) for t in report.targets],
        "drones": [_drone_json(d) for d in report.drones],
        "envelope_margins_m": report.envelope_margins_m,
        "envelope_tolerance_m": report.envelope_tolerance_m,
        "safety_conflicts": report.safety_conflicts,
        "network": None if report.network is None else _network_json(report.network),
        "planned_steps": cov.planned_steps,
        "complete": not report.incomplete,
        "violations": [_violation_json(v) for v in report.violations],
        "warnings": list(report.warnings),
        "verdict": report.verdict,
    }


def _network_json(n: NetworkSummary) -> dict[str, Any]:
    return {
        "topology": n.topology, "keep": n.keep, "range_m": n.range_m,
        "max_components": n.max_components,
        "min_algebraic_connectivity": finite_or_none(n.min_algebraic_connectivity),
        "first_split_s": n.first_split_s, "split_parts": [list(p) for p in n.split_parts],
        "first_said_s": n.first_said_s, "min_kept_margin_m": finite_or_none(n.min_kept_margin_m),
        "link_conflicts": n.link_conflicts,
    }


def _violation_json(v: Violation) -> dict[str, Any]:
    """Which, when and by how much; None where the invariant could not be checked at all."""
    return {
        "invariant": v.invariant, "detail": v.detail, "subject": v.subject or None,
        "worst_value": finite_or_none(v.worst_value), "limit": finite_or_none(v.limit),
        "excess": finite_or_none(v.excess), "worst_time_s": finite_or_none(v.worst_time_s),
        "first_time_s": finite_or_none(v.first_time_s),
        "first_subject": v.first_subject or None,
        "time_beyond_s": finite_or_none(v.time_beyond_s),
    }


# -- rich tables ---------------------------------------------------------------------------


def _fmt(value: float | None, spec: str) -> str:
    return MISSING if value is None else format(value, spec)


def _count(value: int | None) -> str:
    return MISSING if value is None else str(value)


def _late(d: DroneReport) -> str:
    if d.late_steps is None:
        return MISSING
    if not d.steps_run:
        return str(d.late_steps)
    return f"{d.late_steps} ({100.0 * d.late_steps / d.steps_run:.2f} %)"


# Which columns a narrow console keeps longest (0: never left out). The events column (vehicle
# events, λ̄ breaches) is the last to go; figures --json always has go first.
# Headers break into two lines where they are wider than their figures.
_TARGET_PRIORITY = {"target": 0, "min λ̄−ε": 1, "time λ̄<ε\n[s]": 2, "final err\n[m]": 3,
                    f"sensing\n(w>{SENSING_WEIGHT})": 4, "RMS err\n[m]": 5,
                    "min true\nλ−ε": 6, "min meas.\nλ": 7, "missing": 8}
_DRONE_PRIORITY = {"drone": 0, "state": 1, "vehicle\nevents": 2, "λ̄\nbreaches": 2,
                   "QP\nfallbacks": 3, "final |u|\n[m/s]": 4, "final w": 5, "late\nsteps": 6,
                   "rejected": 7, "bearing\nerr": 8, "missing": 9, "step µs\nmean/p99": 10}


@dataclass(frozen=True)
class FittedTable:
    """A table as wide as the console allows: the columns it had to leave out, by name."""

    table: Table
    left_out: tuple[str, ...]


def fitted_table(title: str, columns: Sequence[str], rows: Sequence[Sequence[str]],
                 priority: Mapping[str, int], width: int | None) -> FittedTable:
    """A table of ``columns`` no wider than ``width`` (None: all columns): columns without any
    figure (every cell MISSING) are left out first, then by ``priority`` (highest number
    first), never one of priority 0; cells are never wrapped."""
    keep = list(range(len(columns)))

    def build() -> Table:
        table = Table(title=title, title_justify="left")
        for k in keep:
            table.add_column(escape(columns[k]), justify="right", no_wrap=True)
        for row in rows:
            table.add_row(*(row[k] for k in keep))
        return table

    table = build()
    if width is None:
        return FittedTable(table, ())
    empty = [all(row[k] == MISSING for row in rows) for k in range(len(columns))]
    order = sorted((k for k in keep if priority[columns[k]] > 0),
                   key=lambda k: (not empty[k], -priority[columns[k]]))
    measure = Console(width=10_000).measure
    left_out: list[str] = []
    for k in order:
        if measure(table).maximum <= width:
            break
        keep.remove(k)
        left_out.append(columns[k])
        table = build()
    return FittedTable(table, tuple(left_out))


def target_table(report: RunReport, width: int | None = None) -> FittedTable:
    """The per-target table, within ``width`` console columns (None: every column)."""
    title = (f"{report.scenario}: targets (ε = {report.epsilon}; margins λ − ε after t = "
             f"{report.start_s} s)")
    columns = ["target", "min λ̄−ε", "time λ̄<ε\n[s]", "min true\nλ−ε", "min meas.\nλ",
               "final err\n[m]", "RMS err\n[m]", f"sensing\n(w>{SENSING_WEIGHT})"]
    incomplete = not report.coverage.complete
    if incomplete:
        columns.append("missing")
    rows = []
    for t in report.targets:
        row = [str(t.id), _fmt(t.min_lambda_bar_margin, "+.4f"),
               f"{t.time_below_epsilon_s:.2f}", _fmt(t.min_true_lambda_margin, "+.4f"),
               _fmt(t.min_measured_lambda, ".4f"), _fmt(t.final_position_error_m, ".4f"),
               _fmt(t.rms_position_error_m, ".4f"), str(t.drones_sensing_final)]
        if incomplete:
            row.append(str(t.missing_samples))
        rows.append(row)
    return fitted_table(title, columns, rows, _TARGET_PRIORITY, width)


def drone_table(report: RunReport, width: int | None = None) -> FittedTable:
    """The per-drone table, within ``width`` console columns (None: every column)."""
    columns = ["drone", "final |u|\n[m/s]", "final w", "state", "QP\nfallbacks", "late\nsteps",
               "rejected", "step µs\nmean/p99", "bearing\nerr", "vehicle\nevents",
               "λ̄\nbreaches"]
    incomplete = not report.coverage.complete
    if incomplete:
        columns.append("missing")
    rows = []
    for d in report.drones:
        weights = " ".join(_fmt(w, ".2f") for w in d.final_weights)
        state = ("sensing " + ",".join(f"T{r}" for r in d.sensing_targets)
                 if d.sensing_targets else "idle")
        row = [str(d.id), _fmt(d.final_speed_mps, ".3f"), weights, state, str(d.qp_fallbacks),
               _late(d), _count(d.rejected_messages),
               f"{_fmt(d.mean_step_us, '.0f')}/{_fmt(d.p99_step_us, '.0f')}",
               _fmt(d.final_bearing_error, ".4f"), _vehicle(d), _breaches(d)]
        if incomplete:
            row.append(str(d.missing_samples))
        rows.append(row)
    return fitted_table("drones", columns, rows, _DRONE_PRIORITY, width)


def _vehicle(d: DroneReport) -> str:
    """Vehicle events (not asked for), and what was still wrong at the end."""
    if d.vehicle_events is None:
        return MISSING
    return f"{d.vehicle_events} ({d.vehicle_status})" if d.vehicle_status \
        else str(d.vehicle_events)


def _breaches(d: DroneReport) -> str:
    """λ̄ breaches the agent said, and from when."""
    if d.lambda_breaches is None:
        return MISSING
    if not d.lambda_breaches:
        return "0"
    return f"{d.lambda_breaches} (from {_fmt(d.first_lambda_breach_s, '.2f')} s)"


def _envelope_figures(report: RunReport) -> list[str]:
    """The [safety] envelope's margins and conflicts, when the run had one."""
    if not report.envelope_margins_m:
        return []
    closest = ", ".join(f"{kind} {_fmt(margin, '.4f')} m"
                        for kind, margin in report.envelope_margins_m.items())
    return [f"envelope: closest to the {closest} (tolerance {report.envelope_tolerance_m} m)",
            f"steps the envelope overruled localization {_count(report.safety_conflicts)}"]


def _network_figures(report: RunReport) -> list[str]:
    """The radio's figures, when the run had a range."""
    n = report.network
    if n is None:
        return []
    keep = "" if n.keep == "none" else f", keeping {n.keep}"
    split = ("connected throughout" if n.first_split_s is None
             else f"SPLIT at t = {n.first_split_s:.2f} s")
    figures = [f"radio range {n.range_m:g} m{keep}: {split} (components ≤ "
               f"{_count(n.max_components)}, min λ₂ {_fmt(n.min_algebraic_connectivity, '.3f')})"]
    if n.keep != "none":
        figures.append(f"kept links ≥ {_fmt(n.min_kept_margin_m, '.3f')} m inside R; steps a "
                       f"keep row overruled localization {_count(n.link_conflicts)}")
    return figures


def run_lines(report: RunReport) -> tuple[str, str]:
    """Two lines: the swarm-wide figures, then where the run came from."""
    figures = "; ".join([
        f"min pairwise distance {_fmt(report.min_pairwise_distance_m, '.4f')} m "
        f"(Δ = {report.collision_distance_m} m)",
        f"max |u_k| {_fmt(report.max_abs_velocity_mps, '.3f')} m/s "
        f"(u_max = {report.u_max_mps} m/s)",
        f"QP fallbacks {report.qp_fallbacks}",
        f"late steps {_count(report.late_steps)}",
        f"rejected messages {_count(report.rejected_messages)}",
        *_envelope_figures(report),
        *_network_figures(report),
    ])
    origin = (f"mode {report.mode}; seed {report.seed}; {report.steps} steps "
              f"({report.duration_s:g} s simulated")
    origin += f", {report.wall_time_s:.1f} s wall)" if report.wall_time_s is not None else ")"
    prov = report.provenance
    for label, value in (("run", prov.run_id), ("version", prov.version),
                         ("commit", prov.git_commit[:12])):
        if value:
            origin += f"; {label} {value}"
    return figures, origin


def verdict_line(report: RunReport) -> str:
    """OK only for a whole mission with every invariant held; a run cut short is
    INCOMPLETE (with how much it holds), or FAILED when it broke one on what it holds."""
    steps = f"{report.steps} of {report.coverage.planned_steps} steps"
    if report.verdict == "ok":
        return "verdict: OK (every SPEC invariant within tolerance)"
    if report.verdict == "incomplete":
        return (f"verdict: INCOMPLETE: {steps} (no SPEC invariant violated on the steps "
                f"recorded; the rest of the mission was not run)")
    names = sorted({v.invariant for v in report.violations})
    line = f"verdict: FAILED ({', '.join(names)}: a SPEC invariant was violated or not checked)"
    return f"{line} in an INCOMPLETE run: {steps}" if report.incomplete else line


def render_report(report: RunReport, console: Console) -> None:
    """Tables per target and per drone (as wide as the console: columns left out by
    priority, and said), warnings, violations and the verdict line."""
    left_out: list[str] = []
    for fitted in (target_table(report, console.width), drone_table(report, console.width)):
        console.print(fitted.table)
        left_out += fitted.left_out
    if left_out:
        names = ", ".join(name.replace("\n", " ") for name in left_out)
        console.print(f"(left out at {console.width} columns: {names}; "
                      "--json has every figure)", highlight=False, markup=False)
    for line in run_lines(report):
        console.print(line, highlight=False, markup=False)
    for warning in report.warnings:
        console.print(f"[bold yellow]warning[/] {escape(warning)}", highlight=False)
    for v in report.violations:
        console.print(f"[bold red]VIOLATION[/] {escape(str(v))}", highlight=False)
    style = {"ok": "bold green", "incomplete": "bold yellow"}.get(report.verdict, "bold red")
    console.print(f"[{style}]{verdict_line(report)}[/]", highlight=False)
