"""Live dashboard of a running swarm, fed by telemetry like any other consumer.

``Dashboard`` takes ``TelemetryWire`` messages (``on_telemetry``, from any thread — Zenoh
callbacks included) and the simulation clock (``advance(step)``). On a terminal it shows, at
a bounded refresh rate, a table per drone (λ̄, ψ0 and w per target, ‖u‖, slack, step time,
age of the freshest neighbour message, MAVLink state, event counters) and per target (min λ̄
and its margin to ε, min ψ0, drones sensing, spread of the estimates), with a progress bar in
simulated time. Headless — asked for, or the console is not a terminal — it prints one line
every few simulated seconds instead. In both, a warning line appears when a drone's late
steps, stale neighbour messages, QP fallbacks or rejected messages go up, at most one line per
drone per ``warning_period_s`` (the counts are aggregated, never dropped).

Feeds: ``SwarmLauncher.run(telemetry_listeners=[dashboard.on_telemetry])`` in the process
swarm, ``InProcessFeed`` as ``run_reference``'s ``on_step`` for ``--inprocess``, and
``swarm-observe`` (``swarm.observe.observe_cli``; ``watch`` here, and ``python -m
swarm.observe.dashboard`` under its former name) as a Zenoh client of a swarm running elsewhere.

Rendering is cheap by construction: telemetry callbacks only store the newest message per
drone; the tables are built from those messages only on refresh (≤ ``refresh_hz``, and not
at all when nothing changed), as plain styled text rather than rich ``Table``s, which cost
ten times more per frame (about 1.5 ms per frame instead of 16 for six drones).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import TracebackType

import numpy as np
from rich.cells import cell_len
from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.text import Text

from swarm.core.drone_step import StepDiagnostics
from swarm.messages.wire import TelemetryCounters, TelemetryWire, telemetry_from_diagnostics
from swarm.observe.events import URGENT_LABELS, WARNED_COUNTERS, increased_counters
from swarm.scenario.config import ScenarioConfig

# Short labels of the same counters in the drone table's "events" column.
_EVENT_LABELS = {"late_steps": "late", "stale_neighbour_messages": "stale",
                 "qp_fallbacks": "fb", "rejected_messages": "rej", "vehicle_events": "veh",
                 "rate_limit_releases": "rel", "reference_resets": "rst",
                 "lambda_breaches": "λ̄", "safety_conflicts": "env", "link_conflicts": "link",
                 "splits_said": "split"}

TARGET_COLUMNS = ("target", "min λ̄ (drone)", "λ̄−ε", "min ψ0", "sensing", "spread [m]")
DRONE_COLUMNS = ("drone", "λ̄", "ψ0", "w", "‖u‖ [m/s]", "slack", "step [µs]", "nbr age [ms]",
                 "nbrs", "MAVLink", "events")
# The order in which a narrow console leaves columns out (first listed, first out); the
# events and the vehicle's state are the last to go, the id never.
TARGET_DROP_ORDER = ("spread [m]", "min ψ0", "sensing")
DRONE_DROP_ORDER = ("step [µs]", "nbr age [ms]", "slack", "ψ0", "‖u‖ [m/s]", "w", "nbrs",
                    "λ̄", "MAVLink")
PROGRESS_BAR_CELLS = 30


@dataclass(frozen=True)
class DashboardSettings:
    """How often the dashboard draws and talks."""

    refresh_hz: float = 4.0  # live redraws per second at most (the swarm shares the cores)
    log_period_s: float = 5.0  # headless: simulated seconds between one-line logs
    warning_period_s: float = 1.0  # wall seconds: at most one warning line per drone
    sensing_weight: float = 0.1  # a drone "senses" a target when its w exceeds this
    lagging_s: float = 1.0  # a drone whose telemetry is this far behind the newest is flagged

    def __post_init__(self) -> None:
        for name in ("refresh_hz", "log_period_s", "lagging_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"DashboardSettings.{name} must be finite and > 0, "
                                 f"got {value!r}")
        if not (math.isfinite(self.warning_period_s) and self.warning_period_s >= 0):
            raise ValueError("DashboardSettings.warning_period_s must be finite and >= 0")


@dataclass(frozen=True)
class DashboardStats:
    """What the dashboard cost and saw (CPU seconds are thread CPU time)."""

    telemetry_messages: int
    telemetry_cpu_s: float  # inside on_telemetry, summed over the calling threads
    renders: int
    render_cpu_s: float  # building and writing the live display
    warning_lines: int
    log_lines: int


@dataclass(frozen=True)
class DroneRow:
    """One drone as the table shows it (numbers, not text: tests read these)."""

    drone: int
    time_s: float
    lambda_bar: tuple[float, ...]
    psi0: tuple[float, ...]
    weights: tuple[float, ...]
    speed_m_s: float
    max_slack: float
    step_us: float
    neighbour_age_ms: float | None
    mavlink_state: str
    counters: TelemetryCounters
    neighbours: int | None = None  # heard this step (None: not sent)
    reached: int = 0  # drones its news reaches, itself included (0: not sent)


@dataclass(frozen=True)
class TargetRow:
    """One target over the drones that reported."""

    target: int
    min_lambda_bar: float
    min_lambda_drone: int
    margin: float  # min λ̄ − ε
    min_psi0: float
    sensing: int  # drones with w > sensing_weight
    reporting: int
    spread_m: float  # largest distance between two drones' position estimates


def drone_row(tel: TelemetryWire) -> DroneRow:
    """The numbers of one drone's newest telemetry."""
    velocity = tel.velocity.to_array()
    slacks = tel.slacks.to_array()
    return DroneRow(
        drone=tel.drone, time_s=tel.time_s,
        lambda_bar=tuple(tel.lambda_bar.to_array().tolist()),
        psi0=tuple(tel.psi0.to_array().tolist()),
        weights=tuple(tel.weights.to_array().tolist()),
        speed_m_s=float(np.linalg.norm(velocity)),
        max_slack=float(slacks.max()) if slacks.size else 0.0,
        step_us=tel.step_us, neighbour_age_ms=tel.counters.neighbour_age_ms,
        mavlink_state=tel.counters.mavlink_state, counters=tel.counters,
        neighbours=None if tel.neighbours_heard is None else sum(tel.neighbours_heard),
        reached=tel.reached)


def target_rows(latest: Sequence[TelemetryWire], epsilon: float,
                sensing_weight: float) -> list[TargetRow]:
    """Per target: the worst λ̄ and ψ0 over the drones, how many sense it, how far apart
    the drones' estimates are (consensus not yet reached shows as a large spread)."""
    if not latest:
        return []
    lam = np.array([t.lambda_bar.to_array() for t in latest])  # (N, M)
    psi0 = np.array([t.psi0.to_array() for t in latest])
    weights = np.array([t.weights.to_array() for t in latest])
    positions = np.array([t.estimates.to_array()[:, :3] for t in latest])  # (N, M, 3)
    rows = []
    for r in range(lam.shape[1]):
        worst = int(np.argmin(lam[:, r]))
        p = positions[:, r]
        spread = float(np.linalg.norm(p[:, None] - p[None], axis=-1).max())
        rows.append(TargetRow(
            target=r, min_lambda_bar=float(lam[worst, r]), min_lambda_drone=latest[worst].drone,
            margin=float(lam[worst, r]) - epsilon, min_psi0=float(psi0[:, r].min()),
            sensing=int((weights[:, r] > sensing_weight).sum()), reporting=len(latest),
            spread_m=spread))
    return rows


class Dashboard:
    """Live tables on a terminal, one-line logs otherwise; a context manager.

    Thread-safe: ``on_telemetry`` may be called from any number of threads while the display
    refreshes; ``advance`` and the context methods belong to one (the caller's) thread.
    """

    def __init__(self, config: ScenarioConfig, console: Console, *, headless: bool = False,
                 settings: DashboardSettings | None = None, title: str = "",
                 wall_clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.console = console
        self.settings = settings or DashboardSettings()
        self.headless = headless or not console.is_terminal
        self.title = title or config.scenario.name
        self._clock = wall_clock
        self._lock = threading.Lock()
        self._latest: dict[int, TelemetryWire] = {}
        self._reported: dict[int, TelemetryCounters] = {}  # counters as of the last warning
        self._last_warning: dict[int, float] = {}  # wall time of each drone's last warning
        self._step = -1
        self._changed = True
        self._next_log_s = 0.0
        self._last_shown = -math.inf  # wall time of the last step ``shows`` let through
        self._started_wall: float | None = None
        self._telemetry_messages = 0
        self._telemetry_cpu_s = 0.0
        self._renders = 0
        self._render_cpu_s = 0.0
        self._warning_lines = 0
        self._log_lines = 0
        self._live: Live | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- feeding ------------------------------------------------------------------------------

    def on_telemetry(self, tel: TelemetryWire) -> None:
        """Keep the newest message per drone; any thread (a ``TelemetryListener``)."""
        started = time.thread_time()
        with self._lock:
            held = self._latest.get(tel.drone)
            if held is None or tel.step >= held.step:  # realtime may deliver out of order
                self._latest[tel.drone] = tel
                self._changed = True
            self._telemetry_messages += 1
            self._telemetry_cpu_s += time.thread_time() - started

    def on_telemetry_sample(self, _key: str, tel: TelemetryWire) -> None:
        """``on_telemetry`` with the ``(key, value)`` signature of ``subscriptions.subscribe``."""
        self.on_telemetry(tel)

    def advance(self, step: int) -> None:
        """The simulation clock reached ``step``: warnings, and the headless log when due."""
        with self._lock:
            if step != self._step:
                self._changed = True
            self._step = max(self._step, step)
        self.flush_warnings()
        if self.headless:
            self._maybe_log(step)

    def shows(self, step: int) -> bool:
        """Would telemetry of ``step`` be seen? For feeds that pay to build messages.

        Headless: only at a log step (and the last step). Live: at most twice per refresh
        period of wall time — and then it counts as taken, so ask once per step.
        """
        if step >= self.config.n_steps - 1:
            return True
        if self.headless:
            return step * self.config.scenario.dt_s + 1e-9 >= self._next_log_s
        now = self._clock()
        if now - self._last_shown < 0.5 / self.settings.refresh_hz:
            return False
        self._last_shown = now
        return True

    # -- warnings and logs ----------------------------------------------------------------------

    def flush_warnings(self, *, force: bool = False) -> None:
        """Print a line per drone whose counters went up, unless that drone had a line less
        than ``warning_period_s`` ago and none of the increases is urgent (``URGENT_COUNTERS``;
        ``force``: regardless); increases add up meanwhile."""
        now = self._clock()
        lines = []
        with self._lock:
            for drone in sorted(self._latest):
                tel = self._latest[drone]
                increases = increased_counters(self._reported.get(drone), tel.counters)
                if not increases:
                    continue
                last = self._last_warning.get(drone)
                urgent = any(label in URGENT_LABELS for label, _, _ in increases)
                if not (force or urgent) and last is not None and (
                        now - last < self.settings.warning_period_s):
                    continue
                self._reported[drone] = tel.counters
                self._last_warning[drone] = now
                status = "; ".join(filter(None, (tel.counters.localization_status,
                                                 tel.counters.vehicle_status)))
                lines.append(warning_line(drone, tel.time_s, increases, status))
            self._warning_lines += len(lines)
        for line in lines:
            self.console.print(line, highlight=False)

    def _maybe_log(self, step: int) -> None:
        time_s = step * self.config.scenario.dt_s
        if time_s + 1e-9 < self._next_log_s:
            return
        with self._lock:
            latest = list(self._latest.values())
        if not latest:
            return  # nothing to say yet; log as soon as there is
        self.console.print(headless_line(time_s, latest), highlight=False, markup=False)
        self._log_lines += 1
        self._next_log_s = time_s + self.settings.log_period_s

    # -- display ----------------------------------------------------------------------------------

    def render(self) -> RenderableType:
        """The whole live display: progress in sim time, the target and the drone tables."""
        with self._lock:
            latest = [self._latest[d] for d in sorted(self._latest)]
            step = self._step
        cfg = self.config
        eps = cfg.gramian.epsilon
        time_s = max(step, 0) * cfg.scenario.dt_s
        parts = [self._progress(step, time_s, len(latest))]
        if not latest:
            parts.append(Text("waiting for telemetry…", style="dim"))
        else:
            parts.append(self._target_table(
                target_rows(latest, eps, self.settings.sensing_weight)))
            parts.append(self._drone_table([drone_row(t) for t in latest]))
        # Cropped rather than wrapped: a live frame must keep its height. (The Group keeps
        # console.print from merging the Text into one of its own, which would wrap.)
        return Group(Text("\n", no_wrap=True, overflow="ellipsis").join(parts))

    def _progress(self, step: int, time_s: float, reporting: int) -> Text:
        cfg = self.config
        wall = "" if self._started_wall is None else \
            f"  wall {self._clock() - self._started_wall:.1f} s"
        line = Text()
        line.append(self.title, style="bold")
        line.append(" ")
        line.append_text(progress_bar(max(step + 1, 0) / cfg.n_steps, PROGRESS_BAR_CELLS))
        line.append(f" t = {time_s:.2f} / {cfg.scenario.duration_s:.2f} s{wall}  "
                    f"{reporting}/{cfg.swarm.n_drones} drones reporting")
        return line

    def _target_table(self, rows: list[TargetRow]) -> Text:
        eps = self.config.gramian.epsilon
        cells = []
        for r in rows:
            bad = "bold red" if r.margin < 0 else ""
            cells.append([
                Text(str(r.target)),
                Text(f"{r.min_lambda_bar:.3f} ({r.min_lambda_drone})", style=bad),
                Text(f"{r.margin:+.3f}", style=bad),
                Text(f"{r.min_psi0:+.3f}", style="red" if r.min_psi0 < 0 else ""),
                Text(f"{r.sensing}/{r.reporting}"), Text(f"{r.spread_m:.3f}")])
        return text_table(f"targets (ε = {eps:g})", TARGET_COLUMNS, cells,
                          width=self.console.width, drop_order=TARGET_DROP_ORDER)

    def _drone_table(self, rows: list[DroneRow]) -> Text:
        eps = self.config.gramian.epsilon
        # Against the newest drone, not the clock: feeds may thin out messages (InProcessFeed)
        # and the world's clock may run ahead of telemetry in transit; a stuck drone stands out.
        newest_s = max(d.time_s for d in rows)
        sensing = self.settings.sensing_weight
        stale_ms = 1000.0 * self.config.runtime.stale_timeout_s
        cells = []
        for d in rows:
            lagging = newest_s - d.time_s >= self.settings.lagging_s
            cells.append([
                Text(f"{d.drone}" + (f" @{d.time_s:.1f}s" if lagging else ""),
                     style="bold red" if lagging else ""),
                _values(d.lambda_bar, "{:.3f}", lambda v: "bold red" if v < eps else ""),
                _values(d.psi0, "{:+.3f}", lambda v: "red" if v < 0 else ""),
                _values(d.weights, "{:.2f}", lambda v: "green" if v > sensing else "dim"),
                Text(f"{d.speed_m_s:.2f}"),
                Text(f"{d.max_slack:.3f}", style="yellow" if d.max_slack > 1e-6 else ""),
                Text(f"{d.step_us:.0f}"),
                _age(d.neighbour_age_ms, stale_ms),
                _neighbours(d, self.config.swarm.n_drones),
                Text(d.counters.vehicle_status or d.mavlink_state or "—",
                     style="red" if d.counters.vehicle_status
                     or d.mavlink_state.startswith("disarmed") else ""),
                _events(d.counters)])
        return text_table("drones", DRONE_COLUMNS, cells, width=self.console.width,
                          drop_order=DRONE_DROP_ORDER)

    # -- lifecycle --------------------------------------------------------------------------------

    def __enter__(self) -> Dashboard:
        self._started_wall = self._clock()
        if not self.headless:
            self._live = Live(console=self.console, auto_refresh=False, transient=False)
            self._live.start()
            self._refresh()
            self._thread = threading.Thread(target=self._refresh_loop, name="dashboard",
                                            daemon=True)
            self._thread.start()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Stop refreshing, draw the last frame and report what is still pending."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.flush_warnings(force=True)
        if self._live is not None:
            self._refresh()
            self._live.stop()
            self._live = None

    def _refresh_loop(self) -> None:
        period = 1.0 / self.settings.refresh_hz
        while not self._stop.wait(period):
            try:
                self._refresh()
            except Exception as exc:  # a display bug must not take the mission down
                print(f"dashboard: display stopped: {type(exc).__name__}: {exc}",
                      file=sys.__stderr__)
                return

    def _refresh(self) -> None:
        """Redraw if anything changed (the wall-clock field alone does not count)."""
        with self._lock:
            changed, self._changed = self._changed, False
        live = self._live
        if not changed or live is None:
            return
        started = time.thread_time()
        live.update(self.render(), refresh=True)
        self._renders += 1
        self._render_cpu_s += time.thread_time() - started

    @property
    def stats(self) -> DashboardStats:
        with self._lock:
            return DashboardStats(
                telemetry_messages=self._telemetry_messages,
                telemetry_cpu_s=self._telemetry_cpu_s, renders=self._renders,
                render_cpu_s=self._render_cpu_s, warning_lines=self._warning_lines,
                log_lines=self._log_lines)


# -- text pieces ---------------------------------------------------------------------------------


def text_table(title: str, headers: Sequence[str], rows: Sequence[Sequence[Text]], *,
               width: int | None = None, drop_order: Sequence[str] = ()) -> Text:
    """A borderless table as one Text: title, bold header, rule, right-aligned columns.

    Rich's ``Table`` measures and wraps every cell on every frame — about ten times the cost
    of this for the same picture — and the live display redraws several times a second next
    to a realtime swarm. Cells never wrap. Wider than ``width``, the columns named in
    ``drop_order`` are left out in that order until it fits (the title says how many); what
    still does not fit is cropped by the display.
    """
    widths = [cell_len(h) for h in headers]
    for row in rows:
        for k, cell in enumerate(row):
            widths[k] = max(widths[k], cell.cell_len)
    keep = list(range(len(headers)))
    if width is not None:
        for name in drop_order:
            if sum(widths[k] for k in keep) + 2 * (len(keep) - 1) <= width:
                break
            keep.remove(headers.index(name))
    if len(keep) < len(headers):
        title = f"{title} ({len(headers) - len(keep)} columns left out: too narrow)"
        headers = [headers[k] for k in keep]
        widths = [widths[k] for k in keep]
        rows = [[row[k] for k in keep] for row in rows]
    out = Text()
    out.append(title, style="italic")
    out.append("\n")
    out.append_text(_join_cells([Text(h, style="bold") for h in headers], widths))
    out.append("\n" + "─" * (sum(widths) + 2 * (len(widths) - 1)))
    for row in rows:
        out.append("\n")
        out.append_text(_join_cells(row, widths))
    return out


def _join_cells(cells: Sequence[Text], widths: Sequence[int]) -> Text:
    line = Text()
    for k, (cell, width) in enumerate(zip(cells, widths, strict=True)):
        line.append(" " * (width - cell.cell_len + (2 if k else 0)))
        line.append_text(cell)
    return line


def progress_bar(fraction: float, cells: int) -> Text:
    """A bar of ``cells`` characters in rich's progress-bar colours."""
    fraction = min(max(fraction, 0.0), 1.0)
    done = round(fraction * cells)
    bar = Text("━" * done, style="bar.finished" if done == cells else "bar.complete")
    bar.append("━" * (cells - done), style="bar.back")
    return bar


def _values(values: Sequence[float], fmt: str, style: Callable[[float], str]) -> Text:
    """Per-target values in one cell, each styled on its own."""
    text = Text()
    for k, v in enumerate(values):
        if k:
            text.append(" ")
        text.append(fmt.format(v), style=style(v))
    return text


def _neighbours(d: DroneRow, n_drones: int) -> Text:
    """The neighbours heard this step, and in bold red the part of the swarm the drone's news
    reaches when the swarm has split."""
    if d.neighbours is None:
        return Text("—")
    if 0 < d.reached < n_drones:
        return Text(f"{d.neighbours} ({d.reached}/{n_drones})", style="bold red")
    return Text(str(d.neighbours))


def _age(age_ms: float | None, stale_ms: float) -> Text:
    if age_ms is None:
        return Text("—", style="dim")
    return Text(f"{age_ms:.0f}", style="yellow" if age_ms > stale_ms else "")


def _events(counters: TelemetryCounters) -> Text:
    """Non-zero warned counters, e.g. "late 3 fb 1"; empty when all is well."""
    parts = [f"{_EVENT_LABELS[name]} {getattr(counters, name)}"
             for name, _ in WARNED_COUNTERS if getattr(counters, name)]
    return Text(" ".join(parts), style="yellow" if parts else "")


def warning_line(drone: int, time_s: float, increases: list[tuple[str, int, int]],
                 status: str = "") -> Text:
    """``t=  12.34s  warning: drone 3: +5 late steps (12 total), +1 QP fallbacks (1 total)``,
    then what the drone says is wrong now (``status``), if anything."""
    what = ", ".join(f"+{inc} {label} ({total} total)" for label, inc, total in increases)
    line = Text(f"t={time_s:6.2f}s  ")
    line.append("warning:", style="bold yellow")
    line.append(f" drone {drone}: {what}")
    if status:
        line.append(f"; now: {status}", style="bold red")
    return line


def headless_line(time_s: float, latest: Sequence[TelemetryWire]) -> str:
    """One log line: λ̄ min per target, fastest drone, and the swarm's event totals."""
    lam = np.min([t.lambda_bar.to_array() for t in latest], axis=0)
    speed = max(float(np.linalg.norm(t.velocity.to_array())) for t in latest)
    total = {name: sum(getattr(t.counters, name) for t in latest) for name, _ in WARNED_COUNTERS}
    return (f"t={time_s:6.2f}s  λ̄ min {' '.join(f'{v:.3f}' for v in lam)}  "
            f"max|u| {speed:.2f} m/s  fallbacks {total['qp_fallbacks']}  "
            f"late {total['late_steps']}  stale {total['stale_neighbour_messages']}")


# -- feeds ----------------------------------------------------------------------------------------


class InProcessFeed:
    """``run_reference``'s ``on_step``: telemetry as each agent process would publish it.

    The reference has no MAVLink link, no neighbour clock and no position in
    ``StepDiagnostics``: those fields stay empty (position NaN, never displayed). Building a
    message costs about as much as a tenth of the drone's step, and the reference runs many
    steps per frame, so messages are built only for steps the dashboard shows and for steps
    where a warned counter went up (so every warning still comes at its step).
    """

    def __init__(self, dashboard: Dashboard) -> None:
        self.dashboard = dashboard
        n = dashboard.config.swarm.n_drones
        self._fallbacks = [0] * n
        self._missing = [0] * n
        self._rejected = [0] * n
        self._link_conflicts = [0] * n
        self._splits = [0] * n
        self._reached = [n] * n

    def __call__(self, step: int, diagnostics: list[StepDiagnostics]) -> None:
        warned = False
        for d in diagnostics:
            i = d.drone_id
            self._fallbacks[i] += int(d.qp_fallback)
            self._missing[i] += d.missing_neighbour_messages
            self._rejected[i] += d.rejected_inputs
            self._link_conflicts[i] += int(d.link_conflict)
            split = 0 < d.reached < self._reached[i] == len(self._reached)
            self._splits[i] += int(split)
            self._reached[i] = d.reached or len(self._reached)
            warned = (warned or bool(d.qp_fallback) or d.rejected_inputs > 0
                      or d.link_conflict or split)
        if self.dashboard.shows(step) or warned:
            nowhere = (math.nan, math.nan, math.nan)
            for d in diagnostics:
                i = d.drone_id
                self.dashboard.on_telemetry(telemetry_from_diagnostics(
                    d, nowhere, n_drones=len(self._reached), qp_fallbacks=self._fallbacks[i],
                    missing_neighbour_messages=self._missing[i],
                    rejected_messages=self._rejected[i], steps=step + 1,
                    link_conflicts=self._link_conflicts[i], splits_said=self._splits[i]))
        self.dashboard.advance(step)


# -- standalone ----------------------------------------------------------------------------------


def watch(connect_endpoint: str, run_id: str, config: ScenarioConfig, *,
          console: Console | None = None, headless: bool = False,
          settings: DashboardSettings | None = None,
          stop: threading.Event | None = None, connect_timeout_s: float = 30.0,
          foxglove: tuple[str, int] | None = None) -> str:
    """Show the dashboard of the swarm ``run_id`` behind the Zenoh router at
    ``connect_endpoint`` until its world says done or aborted, falls silent, or ``stop`` is
    set: ``swarm-observe``'s watch without its recording and summary
    (``swarm.observe.observe_cli.observe_run``, which says what it raises).

    Returns how watching ended: "done", "aborted", "silent" or "interrupted".
    ``foxglove``: also serve the live 3D view there (``swarm.observe.live_view``).
    """
    from swarm.observe.observe_cli import observe_run

    return observe_run([connect_endpoint], run_id, config, console=console or Console(),
                       headless=headless, settings=settings, stop=stop,
                       connect_timeout_s=connect_timeout_s, foxglove=foxglove,
                       prog="swarm-dashboard").ending


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m swarm.observe.dashboard``: ``swarm-observe`` under its former name (the
    same options, tables, verdict, recording and exit codes)."""
    from swarm.observe.observe_cli import main as observe_main

    return observe_main(argv, prog="swarm-dashboard")


if __name__ == "__main__":
    sys.exit(main())
