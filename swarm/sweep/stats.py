"""What a sweep's rows say, per grid cell: pass rate with its Wilson interval, margins. Pure.

The pass rate of a cell is OK / (OK + VIOLATED): the missions that ran to their end and were
judged. FAILED missions (a crash, a timeout, a run cut short) say nothing of the guarantee
and are counted apart.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

Row = Mapping[str, Any]


def wilson_interval(successes: int, trials: int, confidence: float = 0.95
                    ) -> tuple[float, float]:
    """The Wilson score interval of a binomial proportion: the p for which the normal test
    of p̂ = k/n against p does not reject at 1 − ``confidence``, i.e. the roots of
    (p̂ − p)² = z² p (1 − p) / n with z the two-sided normal quantile. Solving the quadratic:
    centre (p̂ + z²/2n) / (1 + z²/n), half-width z / (1 + z²/n) · √(p̂(1 − p̂)/n + z²/4n²).
    Unlike p̂ ± z√(p̂(1 − p̂)/n) it stays inside [0, 1] and is not empty at k = 0 or k = n.
    No trials: (0, 1), nothing is known."""
    if trials < 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials (got {successes} of {trials})")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1) (got {confidence})")
    if trials == 0:
        return 0.0, 1.0
    z = statistics.NormalDist().inv_cdf(0.5 + confidence / 2.0)
    n, p = float(trials), successes / trials
    denominator = 1.0 + z * z / n
    centre = (p + z * z / (2.0 * n)) / denominator
    half = z / denominator * math.sqrt(p * (1.0 - p) / n + z * z / (4.0 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


@dataclass(frozen=True)
class CellStats:
    cell: tuple[tuple[str, Any], ...]  # the grid axes' values
    missions: int
    ok: int
    violated: int
    failed: int
    pass_rate: float | None  # ok / (ok + violated); None when none was judged
    interval: tuple[float, float]  # 95 % Wilson interval of the pass rate
    median_margin: float | None  # of min_lambda_margin over the missions that have one
    worst_margin: float | None
    worst_distance_m: float | None  # the smallest min_distance_m
    margins: tuple[float, ...]  # every mission's min_lambda_margin (the distribution)
    columns: tuple[tuple[str, str], ...] = ()  # (row key, its range over the cell, shown)

    @property
    def judged(self) -> int:
        return self.ok + self.violated


def cell_of(row: Row) -> tuple[tuple[str, Any], ...]:
    """The grid cell of a row: the values of its axes (``row["axes"]``), in axis order."""
    params = row.get("params", {})
    return tuple((key, _hashable(params.get(key))) for key in row.get("axes", []))


def _hashable(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_hashable(v) for v in value)
    return value


def row_value(row: Row, path: str) -> Any:
    """The value at ``path`` in a row (``margins.collision_m``: a key of a key), or None."""
    value: Any = row
    for part in path.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def column_range(rows: Sequence[Row], path: str) -> str:
    """A row key's values over a cell, for the table: numbers as their smallest … largest,
    arrays of numbers (one per target) element by element joined by "; ", true/false as how
    many are true of those that say ("2 of 3"); "—" where no row has one."""
    values = [v for v in (row_value(r, path) for r in rows) if v is not None]
    if not values:
        return "—"
    if all(isinstance(v, bool) for v in values):
        return f"{sum(values)} of {len(values)}"
    if all(isinstance(v, list) for v in values):
        width = max(len(v) for v in values)
        return "; ".join(_span([v[i] for v in values if i < len(v)]) for i in range(width))
    return _span(values)


def _span(values: Sequence[Any]) -> str:
    numbers = [float(v) for v in values if _finite(v)]
    if not numbers:
        return "—"
    low, high = min(numbers), max(numbers)
    return format_value(low) if low == high else f"{format_value(low)} … {format_value(high)}"


def cell_stats(rows: Sequence[Row], confidence: float = 0.95,
               columns: Sequence[str] = ()) -> list[CellStats]:
    """One ``CellStats`` per grid cell, in the order the cells first appear; ``columns``: row
    keys (dotted into a row's tables) whose range per cell the table shows too."""
    groups: dict[tuple[tuple[str, Any], ...], list[Row]] = {}
    for row in rows:
        groups.setdefault(cell_of(row), []).append(row)
    out = []
    for cell, members in groups.items():
        verdicts = [r.get("verdict") for r in members]
        ok, violated = verdicts.count("OK"), verdicts.count("VIOLATED")
        margins = tuple(float(r["min_lambda_margin"]) for r in members
                        if _finite(r.get("min_lambda_margin")))
        distances = [float(r["min_distance_m"]) for r in members
                     if _finite(r.get("min_distance_m"))]
        judged = ok + violated
        out.append(CellStats(
            cell=cell, missions=len(members), ok=ok, violated=violated,
            failed=len(members) - judged,
            pass_rate=ok / judged if judged else None,
            interval=wilson_interval(ok, judged, confidence),
            median_margin=statistics.median(margins) if margins else None,
            worst_margin=min(margins) if margins else None,
            worst_distance_m=min(distances) if distances else None,
            margins=margins,
            columns=tuple((path, column_range(members, path)) for path in columns)))
    return out


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) \
        and math.isfinite(value)


def describe_cell(cell: Sequence[tuple[str, Any]]) -> str:
    """``key=value key=value``, or "all" for a sweep without axes."""
    if not cell:
        return "all"
    return " ".join(f"{key}={format_value(value)}" for key, value in cell)


def format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    return str(value)
