"""The thesis figures of one run (Figs. 4.3-4.18), as PNG files, headless.

``write_plots(record, out_dir)`` writes:

- ``position_error.png`` ‖p̂_ir − p_r‖ per drone, one panel per target (4.3, 4.8, 4.13);
- ``psi.png`` ψ0 (solid) and ψ1 (dotted) per drone, one row per target, with ψ0 = 0
  (λ̄ = ε) and the checks' tolerance ε − tol marked, and a zoom on ψ0 = 0 (4.4, 4.9, 4.14);
- ``weights.png`` perception weights w_ir, one panel per target (4.5, 4.10, 4.15);
- ``speed.png`` ‖u_i‖ with the targets' speeds for reference (4.6, 4.11, 4.16);
- ``bearing_error.png`` e_β,i, only when a formation task runs (4.17);
- ``view3d.png`` the final instant: drones (X when idle), trajectories, camera FoV
  pyramids, targets, every drone's estimate of every target and the communication graph
  (4.7, 4.12, 4.18).

Every time plot marks when the QP starts (``control.start_s``). Figures are built with the
object API on the Agg canvas, so no pyplot state and no display are involved; NaN samples
(missing in a recording) show as gaps.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Line3DCollection
from numpy.typing import NDArray

from swarm.core.network import algebraic_connectivity, components
from swarm.models.camera import fov_segments
from swarm.runs.checks import (
    SENSING_WEIGHT,
    envelope_margin_series,
    last_present,
    nanmax,
    nanmin,
    start_index,
)
from swarm.runs.network import kept_link_distances, kept_links
from swarm.runs.record import RunRecord

Array = NDArray[np.float64]
DPI = 110
MIN_Z_BOX = 0.4  # the 3D view's height is at least this fraction of its width
MAX_LEGEND_DRONES = 12  # beyond this, drones are told apart by a colour map, not a legend
TARGET_COLOUR = "tab:red"
ESTIMATE_COLOUR = "tab:green"
EDGE_COLOUR = "tab:green"


def drone_colours(n_drones: int) -> list[tuple[float, float, float, float]]:
    """Colours per drone, the same in every figure (matplotlib's cycle, as the thesis' 4.1)."""
    if n_drones <= 10:
        return [to_rgba(f"C{i}") for i in range(n_drones)]
    from matplotlib import colormaps  # only needed for big swarms

    cmap = colormaps["viridis"]
    return [cmap(i / max(n_drones - 1, 1)) for i in range(n_drones)]


MAX_HEIGHT_IN = 20.0  # many targets share this height rather than grow the image


def _figure(rows: int, height_per_row: float = 2.6, width: float = 9.0) -> Figure:
    height = 0.8 + min(height_per_row, MAX_HEIGHT_IN / max(rows, 1)) * rows
    figure = Figure(figsize=(width, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _drone_legend(figure: Figure, record: RunRecord,
                  extra: Sequence[Line2D] = ()) -> None:
    """One legend per figure, outside the axes on the right."""
    n = record.drone_positions_m.shape[1]
    handles = list(extra)
    if n <= MAX_LEGEND_DRONES:
        colours = drone_colours(n)
        handles = [Line2D([], [], color=colours[i], label=f"drone {i}") for i in range(n)] + \
            handles
    if handles:
        figure.legend(handles=handles, loc="outside right upper", fontsize="small")


QP_START_STYLE: dict[str, Any] = {"color": "tab:gray", "ls": "-.", "lw": 1.0}
TARGET_SPEED_STYLES = ("--", (0, (1, 1.5)), "-.", (0, (5, 1, 1, 1)))


def _qp_start(ax: Axes, record: RunRecord) -> None:
    ax.axvline(record.config.control.start_s, **QP_START_STYLE)


def _qp_start_handle(record: RunRecord) -> Line2D:
    return Line2D([], [], **QP_START_STYLE,
                  label=f"QP starts ({record.config.control.start_s:g} s)")


def _per_drone_lines(ax: Axes, times: Array, values: Array, style: str = "-",
                     lw: float = 1.1) -> None:
    """One line per drone (columns of ``values``), in the drone colours, in one call."""
    lines = ax.plot(times, values, style, lw=lw)
    for line, colour in zip(lines, drone_colours(values.shape[1]), strict=True):
        line.set_color(colour)


def _time_panels(figure: Figure, record: RunRecord, rows: int) -> list[Axes]:
    """``rows`` stacked panels over the run's time, gridded, sharing t [s]."""
    axes = figure.subplots(rows, 1, sharex=True, squeeze=False)[:, 0]
    axes[-1].set_xlabel("t [s]")
    for ax in axes:
        ax.grid(True, lw=0.4, alpha=0.5)
        ax.set_xlim(record.times_s[0] if record.n_steps else 0.0,
                    record.times_s[-1] if record.n_steps else 1.0)
    return list(axes)


def _target_panels(figure: Figure, record: RunRecord) -> list[Axes]:
    """One panel per target (the thesis: upper target 1, lower target 2)."""
    return _time_panels(figure, record, record.target_positions_m.shape[1])


def _title(figure: Figure, record: RunRecord, what: str) -> None:
    figure.suptitle(f"{record.config.scenario.name}: {what}")


# -- time plots ----------------------------------------------------------------------------


def plot_position_error(record: RunRecord) -> Figure:
    """Figs. 4.3 / 4.8 / 4.13."""
    errors = record.position_errors()
    figure = _figure(errors.shape[2])
    for r, ax in enumerate(_target_panels(figure, record)):
        _per_drone_lines(ax, record.times_s, errors[:, :, r])
        _qp_start(ax, record)
        ax.set_ylabel(f"target {r}\n‖p̂ − p‖ [m]")
        ax.set_ylim(bottom=0.0)
    _title(figure, record, "position estimation error per drone")
    _drone_legend(figure, record, [_qp_start_handle(record)])
    return figure


def _psi_limits(record: RunRecord, r: int) -> tuple[float, float]:
    """y range of a ψ panel: everything but ψ1 before the QP starts, whose first samples
    (G(0) = 2εI is isotropic) would squash the rest; the panel says when it clips them."""
    k0 = start_index(record)
    tol = record.config.checks.lambda_tolerance
    shown = np.concatenate([record.psi0[:, :, r].ravel(), record.psi1[k0:, :, r].ravel()])
    low, high = nanmin(shown), nanmax(shown)
    if math.isnan(low):
        return -1.5 * tol, 1.0
    pad = 0.05 * max(high - low, 1e-3)
    return min(low, -tol) - pad, high + pad


def _psi_zoom_limits(record: RunRecord, r: int) -> tuple[float, float]:
    """A close look at ψ0 = 0, where the barrier acts and the tolerance is checked."""
    tol, eps = record.config.checks.lambda_tolerance, record.config.gramian.epsilon
    low = nanmin(record.psi0[start_index(record):, :, r])
    low = -1.5 * tol if math.isnan(low) else min(-1.5 * tol, low - 0.2 * tol)
    return low, max(eps, 2.0 * tol)


def plot_psi(record: RunRecord) -> Figure:
    """Figs. 4.4 / 4.9 / 4.14: ψ0 = λ̄ − ε (solid) and ψ1 (dotted); ψ0 = 0 is λ̄ = ε.

    Left: the whole run; right: a zoom on ψ0 = 0 with the checks' tolerance ε − tol.
    """
    tol = record.config.checks.lambda_tolerance
    m = record.psi0.shape[2]
    figure = _figure(m, height_per_row=3.0, width=11.0)
    axes = figure.subplots(m, 2, sharex="col", squeeze=False, width_ratios=(2, 1))
    for r in range(m):
        for column, ax in enumerate(axes[r]):
            ax.grid(True, lw=0.4, alpha=0.5)
            _per_drone_lines(ax, record.times_s, record.psi1[:, :, r], ":", lw=1.0)
            _per_drone_lines(ax, record.times_s, record.psi0[:, :, r], "-")
            ax.axhline(0.0, color="k", lw=0.9)
            ax.axhline(-tol, color="tab:red", lw=0.8, ls="--")
            _qp_start(ax, record)
            ax.set_ylim(*(_psi_zoom_limits if column else _psi_limits)(record, r))
        axes[r, 0].set_ylabel(f"target {r}\nψ0, ψ1 [s]")
        axes[r, 1].set_title("zoom on ψ0 = 0", fontsize="small")
        axes[r, 1].locator_params(axis="x", nbins=5)
        _note_clipped_psi1(axes[r, 0], record, r)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    if record.n_steps:
        for ax in axes[0]:
            ax.set_xlim(record.times_s[0], record.times_s[-1])
    _title(figure, record,
           f"ψ0 = λ̄ − ε (solid) and ψ1 (dotted), ε = {record.config.gramian.epsilon:g} s")
    _drone_legend(figure, record, [
        Line2D([], [], color="0.2", ls="-", label="ψ0"),
        Line2D([], [], color="0.2", ls=":", label="ψ1"),
        Line2D([], [], color="k", lw=0.9, label="ψ0 = 0 (λ̄ = ε)"),
        Line2D([], [], color="tab:red", lw=0.8, ls="--", label=f"λ̄ = ε − tol ({tol:g})"),
        _qp_start_handle(record)])
    return figure


def _note_clipped_psi1(ax: Axes, record: RunRecord, r: int) -> None:
    early = record.psi1[: start_index(record), :, r]
    top = nanmax(early)
    if not math.isnan(top) and top > ax.get_ylim()[1]:
        ax.text(0.99, 0.97, f"ψ1 up to {top:.2f} before the QP starts (off scale)",
                transform=ax.transAxes, va="top", ha="right", fontsize="x-small", color="0.3")


def plot_weights(record: RunRecord) -> Figure:
    """Figs. 4.5 / 4.10 / 4.15."""
    figure = _figure(record.weights.shape[2])
    for r, ax in enumerate(_target_panels(figure, record)):
        _per_drone_lines(ax, record.times_s, record.weights[:, :, r])
        ax.axhline(SENSING_WEIGHT, color="0.5", lw=0.8, ls=":")
        _qp_start(ax, record)
        ax.set_ylim(-0.03, 1.05)
        ax.set_ylabel(f"target {r}\nw [1]")
    _title(figure, record, "perception weights w_ir")
    _drone_legend(figure, record, [
        Line2D([], [], color="0.5", lw=0.8, ls=":",
               label=f"sensing threshold (w = {SENSING_WEIGHT:g})"),
        _qp_start_handle(record)])
    return figure


def plot_speed(record: RunRecord) -> Figure:
    """Figs. 4.6 / 4.11 / 4.16: ‖u_i‖, with each target's speed (dashed) for reference."""
    figure = _figure(1, height_per_row=3.4)
    (ax,) = _time_panels(figure, record, 1)
    speed = np.linalg.norm(record.velocities_m_s, axis=-1)
    _per_drone_lines(ax, record.times_s, speed)
    target_speed = np.linalg.norm(record.target_velocities_m_s, axis=-1)
    handles = []
    for r in range(target_speed.shape[1]):
        style = TARGET_SPEED_STYLES[r % len(TARGET_SPEED_STYLES)]
        ax.plot(record.times_s, target_speed[:, r], ls=style, color="k", lw=0.9)
        handles.append(Line2D([], [], ls=style, color="k", lw=0.9, label=f"target {r} speed"))
    _qp_start(ax, record)
    ax.set_ylim(bottom=0.0)
    ax.set_ylabel("‖u_i‖ [m/s]")
    _title(figure, record, "norm of the velocity commands")
    _drone_legend(figure, record, [*handles, _qp_start_handle(record)])
    return figure


def plot_bearing_error(record: RunRecord) -> Figure:
    """Fig. 4.17: e_β,i = (1/|N_i|) Σ_j ‖g_ij − g*_ij‖."""
    figure = _figure(1, height_per_row=3.4)
    (ax,) = _time_panels(figure, record, 1)
    _per_drone_lines(ax, record.times_s, record.bearing_errors)
    _qp_start(ax, record)
    ax.set_ylim(bottom=0.0)
    ax.set_ylabel("e_β [1]")
    _title(figure, record, "formation bearing error per drone")
    _drone_legend(figure, record, [_qp_start_handle(record)])
    return figure


def plot_envelope(record: RunRecord) -> Figure:
    """The [safety] envelope: each drone's distance to each kind of boundary (negative:
    outside; the dashed line is −tolerance), and the steps where the envelope overruled
    localization (dots at the bottom of the panel of the boundary nearest that drone)."""
    margins = envelope_margin_series(record)
    figure = _figure(len(margins))
    tolerance = record.config.checks.envelope_tolerance_m
    conflict = record.safety_conflict
    nearest = np.argmin(np.stack([np.nan_to_num(v, nan=np.inf) for v in margins.values()]),
                        axis=0) if margins else None
    handles = [Line2D([], [], ls="--", color="k", lw=0.8, label="− tolerance")]
    for index, (ax, (kind, values)) in enumerate(zip(_time_panels(figure, record, len(margins)),
                                                     margins.items(), strict=True)):
        _per_drone_lines(ax, record.times_s, values)
        ax.axhline(-tolerance, ls="--", color="k", lw=0.8)
        _qp_start(ax, record)
        ax.set_ylabel(f"{kind}\ndistance [m]")
        ax.set_yscale("symlog", linthresh=0.01)
        if conflict is not None and nearest is not None:
            steps, drones = np.nonzero(conflict & (nearest == index))
            colours = drone_colours(values.shape[1])
            ax.scatter(record.times_s[steps], np.full(steps.shape, -tolerance), s=4,
                       c=[colours[i] for i in drones], zorder=3)
    if conflict is not None:
        handles.append(Line2D([], [], ls="", marker=".", color="k",
                              label="envelope overruled localization"))
    _title(figure, record, "distance to the safety envelope per drone")
    _drone_legend(figure, record, [*handles, _qp_start_handle(record)])
    return figure


def plot_network(record: RunRecord) -> Figure:
    """Radios with a range (docs/network.md): the components of the radio's graph over time
    with each drone's count of its part, λ₂ of that graph (0: split), and with keep rows each
    kept link's length against R with the steps a keep row overruled localization."""
    links = record.links
    assert links is not None, "plot_network needs a record with the radio's links"
    cfg = record.config
    kept = kept_links(record)
    rows = 3 if kept else 2
    figure = _figure(rows)
    axes = _time_panels(figure, record, rows)
    times = record.times_s
    parts = np.array([len(components(links[k])) for k in range(links.shape[0])])
    ax = axes[0]
    if record.reached is not None:
        _per_drone_lines(ax, times, record.reached.astype(float))
    ax.step(times, parts, where="post", color="k", lw=1.2)
    ax.set_ylabel("components (black)\ndrones reached")
    ax.set_ylim(0, cfg.swarm.n_drones + 0.5)
    lambda2 = np.array([algebraic_connectivity(links[k]) for k in range(links.shape[0])])
    axes[1].plot(times, lambda2, color="k", lw=1.0)
    axes[1].set_ylabel("λ₂ of the\nradio graph")
    axes[1].set_ylim(bottom=0.0)
    handles = [Line2D([], [], color="k", lw=1.2, label="radio graph")]
    if kept:
        ax = axes[2]
        distances = kept_link_distances(record)
        for column, (i, j) in enumerate(kept):
            ax.plot(times, distances[:, column], lw=0.8, label=f"{i}–{j}")
        ax.axhline(cfg.network.range_m, ls="--", color="k", lw=0.8)
        ax.axhline(cfg.network.kept_range_m, ls=":", color="k", lw=0.8)
        ax.set_ylabel("kept link\nlength [m]")
        conflict = record.link_conflict
        if conflict is not None and conflict.any():
            steps = np.flatnonzero(conflict.any(axis=1))
            ax.scatter(times[steps], np.zeros(steps.shape), s=4, c="k", zorder=3)
            handles.append(Line2D([], [], ls="", marker=".", color="k",
                                  label="a keep row overruled localization"))
        handles += [Line2D([], [], ls="--", color="k", lw=0.8, label="R"),
                    Line2D([], [], ls=":", color="k", lw=0.8, label="R_keep")]
        ax.legend(loc="upper left", fontsize="x-small", ncol=3)
    for ax in axes:
        _qp_start(ax, record)
    _title(figure, record, f"radios of {cfg.network.range_m:g} m range")
    _drone_legend(figure, record, [*handles, _qp_start_handle(record)])
    return figure


# -- 3D view -------------------------------------------------------------------------------


def _final_step(record: RunRecord) -> int | None:
    return last_present(record.drone_positions_m)


def _set_aspect_3d(ax: Axes3D, points: Array) -> float:
    """Same scale on x and y; z stretched to at least MIN_Z_BOX of the horizontal box when the
    swarm is spread out (else the drones sit on a flat slab). Returns the z stretch factor."""
    points = points[np.isfinite(points).all(axis=1)]
    if points.size == 0:
        return 1.0
    low, high = points.min(axis=0), points.max(axis=0)
    centre, span = (low + high) / 2.0, np.maximum(high - low, 1.0) * 1.05
    for setter, c, s in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, span,
                            strict=True):
        setter(c - s / 2.0, c + s / 2.0)
    box_z = max(span[2], MIN_Z_BOX * max(span[0], span[1]))
    ax.set_box_aspect((span[0], span[1], box_z), zoom=1.25)
    return float(box_z / span[2])


def plot_view3d(record: RunRecord, step: int | None = None) -> Figure:
    """Figs. 4.7 / 4.12 / 4.18: the swarm at one instant (default: the last one)."""
    cfg = record.config
    figure = Figure(figsize=(9.0, 6.6), dpi=DPI, layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot(projection="3d")
    ax.computed_zorder = False  # draw in call order: markers over lines, estimates on top
    k = _final_step(record) if step is None else step
    if k is None:
        ax.set_title("no drone position in the record")
        return figure
    n = record.drone_positions_m.shape[1]
    colours = drone_colours(n)
    drones = record.drone_positions_m[k]
    targets = record.target_positions_m[k]
    ground_z = float(np.nanmean(targets[:, 2])) if np.isfinite(targets[:, 2]).any() else 0.0

    # Trajectories up to this instant: thin lines, drones in their colours, targets red.
    trail = record.drone_positions_m[: k + 1]
    ax.add_collection3d(Line3DCollection([trail[:, i] for i in range(n)], colors=colours,
                                         linewidths=0.7, alpha=0.55))
    target_trail = record.target_positions_m[: k + 1]
    ax.add_collection3d(Line3DCollection(
        [target_trail[:, r] for r in range(targets.shape[0])], colors=TARGET_COLOUR,
        linewidths=0.9, alpha=0.6))

    # Communication graph and FoV pyramids, each one collection.
    edges = [drones[[i, j]] for i, j in cfg.swarm.graph.edges]
    ax.add_collection3d(Line3DCollection(edges, colors=EDGE_COLOUR, linestyles=":",
                                         linewidths=1.0))
    fov, fov_colours = [], []
    for i in range(n):
        segments = fov_segments(drones[i], cfg.camera.half_fov_deg, cfg.camera.range_max_m,
                                ground_z) if np.isfinite(drones[i]).all() else []
        fov += segments
        fov_colours += [colours[i]] * len(segments)
    if fov:
        ax.add_collection3d(Line3DCollection(fov, colors=fov_colours, linewidths=0.5,
                                             alpha=0.5))

    # Drop lines to the ground make the drones' horizontal positions readable.
    drops = [np.array([p, [p[0], p[1], ground_z]]) for p in drones if np.isfinite(p).all()]
    ax.add_collection3d(Line3DCollection(drops, colors="0.55", linewidths=0.6,
                                         linestyles="--"))

    # Drones: a dot when sensing some target, an X when idle (Fig. 4.12).
    weights = record.weights[k]
    sensing = np.nan_to_num(weights, nan=0.0).max(axis=1) > SENSING_WEIGHT
    for mask, marker in ((sensing, "o"), (~sensing, "X")):
        if mask.any():
            ax.scatter(*drones[mask].T, c=[colours[i] for i in np.flatnonzero(mask)],
                       marker=marker, s=60, depthshade=False, edgecolors="k", linewidths=0.5)
    ax.scatter(*targets.T, c=TARGET_COLOUR, marker="o", s=45, depthshade=False)
    estimates = record.estimates[k, :, :, :3].reshape(-1, 3)  # on top: they sit on the targets
    ax.scatter(*estimates.T, c=ESTIMATE_COLOUR, marker=".", s=30, depthshade=False)
    for r, target in enumerate(targets):
        ax.text(*target, f"  T{r}", color=TARGET_COLOUR, fontsize=9)
    for i in range(n):
        ax.text(*drones[i], f" {i}", fontsize=8, color="k")

    every = np.concatenate([trail.reshape(-1, 3), target_trail.reshape(-1, 3),
                            np.concatenate(fov) if fov else np.empty((0, 3))])
    stretch = _set_aspect_3d(ax, every)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.view_init(elev=22, azim=-60)
    idle = int((~sensing).sum())
    stretched = f"; z scale ×{stretch:.1f}" if stretch > 1.05 else ""
    ax.set_title(f"{cfg.scenario.name} at t = {record.times_s[k]:.2f} s "
                 f"({idle} of {n} drones idle{stretched})")
    figure.legend(handles=[
        Line2D([], [], ls="", marker="o", color="0.5", markeredgecolor="k",
               label=f"drone, sensing (w > {SENSING_WEIGHT:g})"),
        Line2D([], [], ls="", marker="X", color="0.5", markeredgecolor="k",
               label=f"drone, idle (w ≤ {SENSING_WEIGHT:g} for every target)"),
        Line2D([], [], ls="", marker="o", color=TARGET_COLOUR, label="target"),
        Line2D([], [], ls="", marker=".", color=ESTIMATE_COLOUR, label="estimates p̂_ir"),
        Line2D([], [], ls=":", color=EDGE_COLOUR, label="communication edge"),
        Line2D([], [], lw=0.6, color="0.4", label="camera FoV (to ground / D_M)"),
    ], loc="outside lower center", ncols=3, fontsize="small")
    return figure


# -- files ---------------------------------------------------------------------------------

FigureMaker = Callable[[RunRecord], Figure]


def figures_for(record: RunRecord) -> dict[str, FigureMaker]:
    """File name → figure maker; the bearing error only when a formation task ran, the
    envelope's margins only when the run had one, the radio's graph only with a range."""
    makers: dict[str, FigureMaker] = {
        "position_error.png": plot_position_error,
        "psi.png": plot_psi,
        "weights.png": plot_weights,
        "speed.png": plot_speed,
    }
    if record.config.control.task == "bearing_formation":
        makers["bearing_error.png"] = plot_bearing_error
    if not record.config.safety.params.empty:
        makers["envelope.png"] = plot_envelope
    if record.links is not None:
        makers["network.png"] = plot_network
    makers["view3d.png"] = plot_view3d
    return makers


def write_plots(record: RunRecord, out_dir: Path) -> list[Path]:
    """Write every figure of the run into ``out_dir`` (created); returns the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, make in figures_for(record).items():
        path = out_dir / name
        make(record).savefig(path)
        written.append(path)
    return written
