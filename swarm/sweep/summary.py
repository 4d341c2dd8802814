"""The answer of a sweep, from its rows alone: the per-cell table and the figures.

``pass_rate.png``: the pass rate over two grid axes as a heatmap, each cell annotated with
OK/judged and its 95 % Wilson interval (one axis: a single row of cells). ``margins.png``:
each cell's distribution of the smallest λ̄ − ε margin (one point per mission, and the box of
its quartiles). ``summary.json``: the table's figures.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from rich.console import Console
from rich.table import Table

from swarm.sweep.stats import (
    CellStats,
    describe_cell,
    format_value,
    wilson_interval,
)

HEATMAP_FILE = "pass_rate.png"
MARGINS_FILE = "margins.png"
SUMMARY_FILE = "summary.json"


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None else format(value, spec)


def summary_table(cells: Sequence[CellStats], title: str = "sweep") -> Table:
    table = Table(title=title, title_justify="left")
    for name in ("cell", "missions", "OK", "VIOLATED", "FAILED", "pass rate", "95 % Wilson",
                 "median λ̄−ε", "worst λ̄−ε", "min dist [m]"):
        table.add_column(name, justify="left" if name == "cell" else "right", no_wrap=True)
    for c in cells:
        table.add_row(describe_cell(c.cell), str(c.missions), str(c.ok), str(c.violated),
                      str(c.failed), _fmt(c.pass_rate, ".3f"),
                      f"[{c.interval[0]:.3f}, {c.interval[1]:.3f}]",
                      _fmt(c.median_margin, "+.4f"), _fmt(c.worst_margin, "+.4f"),
                      _fmt(c.worst_distance_m, ".3f"))
    return table


def columns_table(cells: Sequence[CellStats]) -> Table | None:
    """The sweep's ``columns`` per cell (their ranges), a table of its own beside the
    summary's, so that neither is too wide for a terminal; None without columns."""
    paths = [path for path, _shown in cells[0].columns] if cells else []
    if not paths:
        return None
    table = Table(title="per cell (smallest … largest; per target; k of n)",
                  title_justify="left")
    table.add_column("cell", no_wrap=True)
    for path in paths:
        table.add_column(path, justify="right")
    for c in cells:
        table.add_row(describe_cell(c.cell), *(shown for _path, shown in c.columns))
    return table


def render_summary(cells: Sequence[CellStats], console: Console, title: str) -> None:
    console.print(summary_table(cells, title))
    extra = columns_table(cells)
    if extra is not None:
        console.print(extra)
    total = sum(c.missions for c in cells)
    ok = sum(c.ok for c in cells)
    violated = sum(c.violated for c in cells)
    failed = sum(c.failed for c in cells)
    console.print(f"{total} missions: {ok} OK, {violated} VIOLATED, {failed} FAILED; pass rate "
                  f"= OK / (OK + VIOLATED), FAILED missions (crash, timeout, cut short) apart",
                  highlight=False)


def summary_data(cells: Sequence[CellStats]) -> list[dict[str, Any]]:
    return [{"cell": {k: v for k, v in c.cell}, "missions": c.missions, "ok": c.ok,
             "violated": c.violated, "failed": c.failed, "pass_rate": c.pass_rate,
             "wilson_95": list(c.interval), "median_lambda_margin": c.median_margin,
             "worst_lambda_margin": c.worst_margin, "worst_distance_m": c.worst_distance_m,
             **({"columns": dict(c.columns)} if c.columns else {})}
            for c in cells]


def heatmap_axes(cells: Sequence[CellStats], wanted: Sequence[str] = ()) -> tuple[str, ...]:
    """The (at most two) axes of the heatmap: ``wanted``, else the first two axes with more
    than one value."""
    if wanted:
        return tuple(wanted)
    keys = [key for key, _value in cells[0].cell] if cells else []
    varied = [k for i, k in enumerate(keys) if len({c.cell[i][1] for c in cells}) > 1]
    return tuple(varied[:2])


def write_figures(cells: Sequence[CellStats], out: Path, axes: Sequence[str] = ()
                  ) -> list[Path]:
    """``pass_rate.png`` (with at least one axis) and ``margins.png`` into ``out``."""
    written = []
    chosen = heatmap_axes(cells, axes)
    if chosen and cells:
        written.append(_heatmap(cells, chosen, out / HEATMAP_FILE))
    if any(c.margins for c in cells):
        written.append(_margins(cells, out / MARGINS_FILE))
    return written


def _values(cells: Sequence[CellStats], key: str) -> list[Any]:
    seen: list[Any] = []
    for c in cells:
        value = dict(c.cell)[key]
        if value not in seen:
            seen.append(value)
    return seen


def _heatmap(cells: Sequence[CellStats], axes: Sequence[str], path: Path) -> Path:
    x_key = axes[0]
    y_key = axes[1] if len(axes) > 1 else None
    xs = _values(cells, x_key)
    ys = _values(cells, y_key) if y_key else [None]
    ok = [[0] * len(xs) for _ in ys]
    judged = [[0] * len(xs) for _ in ys]
    for c in cells:  # cells of other axes are pooled into the shown ones
        values = dict(c.cell)
        i, j = ys.index(values[y_key]) if y_key else 0, xs.index(values[x_key])
        ok[i][j] += c.ok
        judged[i][j] += c.judged
    rates = [[ok[i][j] / judged[i][j] if judged[i][j] else float("nan")
              for j in range(len(xs))] for i in range(len(ys))]
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(xs), 1.4 + 0.9 * len(ys)))
    image = ax.imshow(rates, vmin=0.0, vmax=1.0, cmap="RdYlGn", origin="lower",
                      aspect="auto")
    for i in range(len(ys)):
        for j in range(len(xs)):
            low, high = wilson_interval(ok[i][j], judged[i][j])
            ax.text(j, i, f"{ok[i][j]}/{judged[i][j]}\n[{low:.2f}, {high:.2f}]",
                    ha="center", va="center", fontsize=8)
    ax.set_xticks(range(len(xs)), [format_value(v) for v in xs], rotation=30, ha="right")
    ax.set_xlabel(x_key)
    if y_key:
        ax.set_yticks(range(len(ys)), [format_value(v) for v in ys])
        ax.set_ylabel(y_key)
    else:
        ax.set_yticks([])
    ax.set_title("pass rate (OK / judged, 95 % Wilson interval)")
    fig.colorbar(image, ax=ax, label="pass rate")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _margins(cells: Sequence[CellStats], path: Path) -> Path:
    shown = [c for c in cells if c.margins]
    fig, ax = plt.subplots(figsize=(max(4.5, 0.9 * len(shown) + 2.0), 4.5))
    ax.boxplot([list(c.margins) for c in shown], showfliers=False)
    for k, c in enumerate(shown, start=1):
        offsets = [k + 0.18 * ((n % 7) / 3.0 - 1.0) for n in range(len(c.margins))]
        ax.plot(offsets, c.margins, ".", alpha=0.6, color="tab:blue")
    ax.axhline(0.0, color="tab:red", linewidth=0.8)
    ax.set_xticks(range(1, len(shown) + 1),
                  ["\n".join(format_value(v) for _k, v in c.cell) or "all" for c in shown],
                  fontsize=7)
    ax.set_xlabel(" / ".join(key for key, _v in shown[0].cell))
    ax.set_ylabel("min λ̄ − ε over the mission [s]")
    ax.set_title("margin per cell (one point per mission)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_summary(cells: Sequence[CellStats], out: Path) -> Path:
    path = out / SUMMARY_FILE
    path.write_text(json.dumps(summary_data(cells), indent=1, allow_nan=False) + "\n")
    return path
