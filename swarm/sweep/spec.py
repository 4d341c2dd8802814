"""The sweep file: its schema, its validation and its expansion into points. Pure: no I/O
beyond what the caller hands in (the parsed TOML document), no Dask.

    base = "configs/case1.toml"     # relative to the sweep file
    mode = "inprocess"              # "lockstep", "realtime", "sitl:ardupilot", "sitl:px4"
    seeds = [0, 19]                 # inclusive range
    record = false                  # keep every mission's recording (DIR/recordings/KEY/)
    kill_agents = ["1@12.5"]        # realtime fault injection, as launch-swarm --kill-agent
    timeout_s = 600                 # a mission still running then is stopped: FAILED
    heatmap = ["targets.0.velocity_m_s", "gramian.epsilon"]   # the figure's two axes
    keep = ["margins", "qp_fallbacks"]   # the optional row keys to keep (default: all)
    columns = ["tracking.velocity_error_rms_m_s"]   # row keys shown per cell, as ranges

    [set]                           # the same for every point (launch-swarm --set)
    "scenario.duration_s" = 20.0

    [axes]                          # the grid: every combination of these values
    "gramian.epsilon" = [0.04, 0.05, 0.06]
    "targets.0.velocity_m_s" = [[0.2, 0.0, 0.0], [0.4, 0.0, 0.0]]
    # "kill.at_s" = [0.0, 12.0]     # realtime: each drone lost in turn at that time, one
    #                               # mission per drone ("kill.drone"), 0 = none lost

    [samples]                       # optional: random points, crossed with the grid
    count = 10
    seed = 0
    [samples.ranges]                # uniform in [low, high]; integers if both are integers
    "camera.image_noise_std" = [0.0, 0.01]

    [gate]                          # optional: what the exit code holds the sweep to
    hard = ["collision", "envelope"]   # invariants no mission may break (no exception)
    min_pass_rate = 0.75            # each cell's OK / (OK + VIOLATED) at least this

A point is one grid cell × one sample × one seed; every point is one mission, except that a
cell with ``kill.at_s`` > 0 is one mission per drone lost (``swarm.sweep.plan``: the number
of drones is the point's config's). Keys are ``swarm.scenario.overrides`` keys: that module
applies them, and the scenario config validates every point as it validates a file;
``kill.at_s`` is the sweep's own.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TypeGuard

import numpy as np

from swarm.errors import UsageError
from swarm.mavlink.sitl import KINDS, Kind
from swarm.scenario.overrides import OverrideError, check_key

MODES = ("inprocess", "lockstep", "realtime", "sitl:ardupilot", "sitl:px4")
# The row keys beyond the ones every row has (swarm.sweep.rows.REQUIRED_KEYS).
OPTIONAL_KEYS = ("margins", "violations", "min_true_lambda_margin", "final_error_m",
                 "rms_error_m", "max_abs_velocity_m_s", "qp_fallbacks", "late_steps",
                 "rejected_messages", "safety_conflicts", "steps", "planned_steps",
                 "recording", "tracking", "rate_limit_releases", "reference_resets", "loss",
                 "split_s", "split_said_s", "min_lambda2", "link_conflicts",
                 "lambda_copy_spread")
TOP_KEYS = ("base", "mode", "seeds", "record", "kill_agents", "timeout_s", "heatmap", "keep",
            "columns", "set", "axes", "samples", "gate")
# Row keys every row has that a summary column may show (swarm.sweep.rows.REQUIRED_KEYS).
NUMBER_KEYS = ("min_lambda_margin", "min_distance_m", "wall_s", "exit_code")
SAMPLE_KEYS = ("count", "seed", "ranges")
GATE_KEYS = ("hard", "min_pass_rate")
# The invariants a report names (swarm.runs.checks.check_invariants); those needing no
# estimate are hard rows of every QP from the first step (SPEC §9), the gate's default.
INVARIANTS = ("finite", "lambda_bar", "collision", "envelope", "velocity_bound", "kept_link",
              "split_said")
SAFETY_INVARIANTS = ("collision", "envelope", "velocity_bound", "finite", "kept_link")
# The grid axis of drone losses: each drone's agent killed in turn at that mission time (one
# mission per drone, its id in the row's params as KILL_DRONE); 0: none lost.
KILL_AXIS = "kill.at_s"
KILL_DRONE = "kill.drone"
MAX_POINTS = 1_000_000

Value = object


class SweepError(UsageError, ValueError):
    """A sweep file that cannot be run; ``str()`` is one line naming the key."""


@dataclass(frozen=True)
class SampleSpec:
    count: int
    seed: int
    ranges: tuple[tuple[str, float | int, float | int], ...]  # (key, low, high)


@dataclass(frozen=True)
class GateSpec:
    """The sweep's pass/fail (its exit code): no mission FAILED, none broke a ``hard``
    invariant, and every cell's pass rate OK / (OK + VIOLATED) is at least
    ``min_pass_rate`` (0: no floor)."""

    hard: tuple[str, ...] = SAFETY_INVARIANTS
    min_pass_rate: float = 0.0


@dataclass(frozen=True)
class SweepSpec:
    base: str  # the scenario file, as written (relative to the sweep file)
    mode: str
    seeds: tuple[int, ...]
    axes: tuple[tuple[str, tuple[Value, ...]], ...]  # (key, values), in file order
    fixed: tuple[tuple[str, Value], ...] = ()  # [set]
    samples: SampleSpec | None = None
    record: bool = False
    kill_agents: tuple[tuple[int, float], ...] = ()
    timeout_s: float | None = None
    heatmap: tuple[str, ...] = ()
    keep: tuple[str, ...] = OPTIONAL_KEYS
    gate: GateSpec | None = None
    columns: tuple[str, ...] = ()  # row keys (dotted into a row's tables) shown per cell

    @property
    def axis_keys(self) -> tuple[str, ...]:
        return tuple(key for key, _values in self.axes)

    @property
    def sitl(self) -> Kind | None:
        """"ardupilot" or "px4" for a SITL mode, else None."""
        kind = self.mode.partition(":")[2]
        return kind if kind in KINDS else None

    @property
    def n_points(self) -> int:
        cells = math.prod(len(values) for _key, values in self.axes)
        return cells * (self.samples.count if self.samples else 1) * len(self.seeds)


@dataclass(frozen=True)
class Point:
    """One mission of the sweep: its grid cell, its sampled values and its seed."""

    cell: tuple[tuple[str, Value], ...]  # the grid axes' values
    sampled: tuple[tuple[str, Value], ...] = ()
    seed: int = 0
    overrides: tuple[tuple[str, Value], ...] = field(default=(), compare=False)

    @property
    def kill_at_s(self) -> float | None:
        """The ``kill.at_s`` of the point's cell: each drone lost in turn then (None: no
        such axis, or 0: none lost)."""
        value = dict(self.cell).get(KILL_AXIS)
        return float(value) if _number(value) and value else None

    @property
    def params(self) -> dict[str, Value]:
        """The point's dotted keys → values (grid axes, then sampled keys)."""
        return dict(self.cell + self.sampled)

    def describe(self) -> str:
        shown = " ".join(f"{k}={_short(v)}" for k, v in self.cell + self.sampled)
        return f"{shown} seed {self.seed}".strip()


def _short(value: Value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list | tuple):
        return "[" + ",".join(_short(v) for v in value) + "]"
    return str(value)


def parse_spec(data: Mapping[str, object], where: str = "sweep") -> SweepSpec:
    """The sweep file's document → ``SweepSpec``; SweepError (one line, prefixed by
    ``where``) naming the first key that is wrong."""
    try:
        return _parse(data)
    except (SweepError, OverrideError) as err:
        raise SweepError(f"{where}: {err}") from None


def _parse(data: Mapping[str, object]) -> SweepSpec:
    for key in data:
        if key not in TOP_KEYS:
            raise SweepError(f"{key}: unknown key (known keys: {', '.join(TOP_KEYS)})")
    base = _string(data, "base", None)
    mode = _string(data, "mode", "inprocess")
    if mode not in MODES:
        raise SweepError(f"mode: must be one of {', '.join(MODES)} (got {mode!r})")
    seeds = _seeds(data.get("seeds", [0, 0]))
    axes = _axes(_table(data, "axes"))
    fixed = tuple((check_key(k), _finite(f"set.{k!r}", v))
                  for k, v in _table(data, "set").items())
    samples = _samples(data["samples"]) if "samples" in data else None
    record = data.get("record", False)
    if not isinstance(record, bool):
        raise SweepError(f"record: must be true or false (got {record!r})")
    kills = _kills(data.get("kill_agents", []))
    timeout = data.get("timeout_s")
    timeout_s: float | None = None
    if timeout is not None:
        if not (_number(timeout) and math.isfinite(timeout) and timeout > 0):
            raise SweepError(f"timeout_s: must be a finite number of seconds > 0 (got "
                             f"{timeout!r})")
        timeout_s = float(timeout)
    if kills and any(k == KILL_AXIS for k, _v in axes):
        raise SweepError(f"kill_agents: and axes.{KILL_AXIS!r}: give one of the two")
    keys = [k for k, _v in axes] + ([k for k, _lo, _hi in samples.ranges] if samples else [])
    for key, _value in fixed:
        if key == KILL_AXIS:
            raise SweepError(f"set.{key!r}: {KILL_AXIS} is a grid axis ([axes]) or "
                             f"kill_agents")
        if key in keys:
            raise SweepError(f"set.{key!r}: also an axis or a sampled key: give it once")
    if len(set(keys)) != len(keys):
        raise SweepError("samples.ranges: a key is both an axis and sampled: give it once")
    heatmap = _heatmap(data.get("heatmap"), [k for k, _v in axes])
    keep = _keep(data.get("keep"))
    gate = _gate(data["gate"]) if "gate" in data else None
    columns = check_columns(data.get("columns", []), keep, "columns")
    if gate is not None and gate.hard and "violations" not in keep:
        raise SweepError("keep: the gate's hard invariants are read from each row's "
                         "violations: keep \"violations\"")
    spec = SweepSpec(base=base, mode=mode, seeds=seeds, axes=axes, fixed=fixed,
                     samples=samples, record=record, kill_agents=kills,
                     timeout_s=timeout_s,
                     heatmap=heatmap, keep=keep, gate=gate, columns=columns)
    if spec.n_points > MAX_POINTS:
        raise SweepError(f"{spec.n_points} points: more than {MAX_POINTS} missions in one "
                         f"sweep; split it")
    return spec


def _string(data: Mapping[str, object], key: str, default: str | None) -> str:
    if key not in data:
        if default is None:
            raise SweepError(f"{key}: missing (the scenario file the sweep starts from, "
                             f"relative to the sweep file)")
        return default
    value = data[key]
    if not isinstance(value, str) or not value.strip():
        raise SweepError(f"{key}: must be a non-empty string (got {value!r})")
    return value


def _table(data: Mapping[str, object], key: str) -> Mapping[str, object]:
    value = data.get(key, {})
    if not isinstance(value, Mapping):
        raise SweepError(f"{key}: must be a table ([{key}]) (got {value!r})")
    return value


def _number(value: object) -> TypeGuard[int | float]:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _finite(where: str, value: Value) -> Value:
    """``value`` unless it holds NaN or ±inf (anywhere in an array)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise SweepError(f"{where}: {value} is not a finite number")
    if isinstance(value, list):
        for item in value:
            _finite(where, item)
    if isinstance(value, Mapping):
        raise SweepError(f"{where}: a table is not a config value here")
    return value


def _seeds(value: object) -> tuple[int, ...]:
    if (not isinstance(value, list) or len(value) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)):
        raise SweepError(f"seeds: must be [first, last], two integers (got {value!r})")
    first, last = value
    if not 0 <= first <= last < 2**63:
        raise SweepError(f"seeds: need 0 <= first <= last < 2^63 (got {value!r})")
    if last - first >= MAX_POINTS:
        raise SweepError(f"seeds: {last - first + 1} seeds; at most {MAX_POINTS}")
    return tuple(range(first, last + 1))


def _axes(table: Mapping[str, object]) -> tuple[tuple[str, tuple[Value, ...]], ...]:
    out = []
    for key, values in table.items():
        where = f"axes.{key!r}"
        check_key(key)
        if not isinstance(values, list):
            raise SweepError(f"{where}: must be an array of the values to try (got {values!r})")
        if not values:
            raise SweepError(f"{where}: an empty axis (give at least one value)")
        for value in values:
            _finite(where, value)
        if len({repr(v) for v in values}) != len(values):
            raise SweepError(f"{where}: a value is given twice")
        if key == KILL_AXIS and not all(_number(v) and v >= 0 for v in values):
            raise SweepError(f"{where}: mission times in seconds >= 0 (0: no drone lost), "
                             f"got {values!r}")
        out.append((key, tuple(values)))
    return tuple(out)


def _samples(value: object) -> SampleSpec:
    if not isinstance(value, Mapping):
        raise SweepError(f"samples: must be a table ([samples]) (got {value!r})")
    for key in value:
        if key not in SAMPLE_KEYS:
            raise SweepError(f"samples.{key}: unknown key (known keys: "
                             f"{', '.join(SAMPLE_KEYS)})")
    count, seed = value.get("count"), value.get("seed", 0)
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise SweepError(f"samples.count: must be an integer >= 1 (got {count!r})")
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise SweepError(f"samples.seed: must be an integer >= 0 (got {seed!r})")
    ranges = value.get("ranges")
    if not isinstance(ranges, Mapping) or not ranges:
        raise SweepError("samples.ranges: a table of key = [low, high] with at least one key")
    out = []
    for key, bounds in ranges.items():
        where = f"samples.ranges.{key!r}"
        check_key(key)
        if key == KILL_AXIS:
            raise SweepError(f"{where}: {KILL_AXIS} is a grid axis ([axes]), not sampled")
        if (not isinstance(bounds, list) or len(bounds) != 2
                or not all(_number(b) for b in bounds)):
            raise SweepError(f"{where}: must be [low, high], two numbers (got {bounds!r})")
        _finite(where, bounds)
        low, high = bounds
        if not low < high:
            raise SweepError(f"{where}: need low < high (got {bounds!r})")
        out.append((key, low, high))
    return SampleSpec(count=count, seed=seed, ranges=tuple(out))


def _kills(value: object) -> tuple[tuple[int, float], ...]:
    if not isinstance(value, list):
        raise SweepError(f"kill_agents: must be an array of \"I@S\" (got {value!r})")
    out = []
    for item in value:
        drone, sep, when = str(item).partition("@")
        try:
            time_s = float(when)
        except ValueError:
            time_s = math.nan
        if (not isinstance(item, str) or not sep or not drone.strip().isdigit()
                or not (math.isfinite(time_s) and time_s > 0)):
            raise SweepError(f"kill_agents: expected \"I@S\", a drone id and a mission time "
                             f"in seconds > 0 (e.g. \"1@12.5\"), got {item!r}")
        out.append((int(drone), time_s))
    return tuple(out)


def check_columns(value: object, keep: Sequence[str] = OPTIONAL_KEYS,
                  where: str = "columns") -> tuple[str, ...]:
    """Summary columns: row keys, dotted into a row's tables (``loss.final_error_m``)."""
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise SweepError(f"{where}: must be an array of row keys (got {value!r})")
    for path in value:
        head = path.split(".")[0]
        if head not in (*NUMBER_KEYS, *OPTIONAL_KEYS):
            raise SweepError(f"{where}: {path!r} is not a row key (they are: "
                             f"{', '.join((*NUMBER_KEYS, *OPTIONAL_KEYS))})")
        if head in OPTIONAL_KEYS and head not in keep:
            raise SweepError(f"{where}: {path!r}: keep {head!r} too")
    return tuple(value)


def _gate(value: object) -> GateSpec:
    if not isinstance(value, Mapping):
        raise SweepError(f"gate: must be a table ([gate]) (got {value!r})")
    for key in value:
        if key not in GATE_KEYS:
            raise SweepError(f"gate.{key}: unknown key (known keys: {', '.join(GATE_KEYS)})")
    hard = value.get("hard", list(SAFETY_INVARIANTS))
    if not isinstance(hard, list) or not all(isinstance(v, str) for v in hard):
        raise SweepError(f"gate.hard: must be an array of invariant names (got {hard!r})")
    for name in hard:
        if name not in INVARIANTS:
            raise SweepError(f"gate.hard: {name!r} is not an invariant (they are: "
                             f"{', '.join(INVARIANTS)})")
    floor = value.get("min_pass_rate", 0.0)
    if not _number(floor) or not 0.0 <= floor <= 1.0:
        raise SweepError(f"gate.min_pass_rate: must be a number in [0, 1] (got {floor!r})")
    return GateSpec(hard=tuple(dict.fromkeys(hard)), min_pass_rate=float(floor))


def _heatmap(value: object, axes: Sequence[str]) -> tuple[str, ...]:
    if value is None:
        return ()
    if (not isinstance(value, list) or not 1 <= len(value) <= 2
            or not all(isinstance(v, str) for v in value)):
        raise SweepError(f"heatmap: must be one or two axis keys (got {value!r})")
    for key in value:
        if key not in axes:
            raise SweepError(f"heatmap: {key!r} is not an axis (axes: {', '.join(axes)})")
    return tuple(value)


def _keep(value: object) -> tuple[str, ...]:
    if value is None:
        return OPTIONAL_KEYS
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise SweepError(f"keep: must be an array of row keys (got {value!r})")
    for key in value:
        if key not in OPTIONAL_KEYS:
            raise SweepError(f"keep: {key!r} is not an optional row key (they are: "
                             f"{', '.join(OPTIONAL_KEYS)})")
    return tuple(value)


def expand(spec: SweepSpec) -> list[Point]:
    """Every point, grid cell by grid cell (file order, the last axis fastest), then sample,
    then seed. Sampled values are drawn once, from ``samples.seed``: the same file gives the
    same points."""
    cells = list(itertools.product(*[[(key, v) for v in values] for key, values in spec.axes]))
    samples: list[tuple[tuple[str, Value], ...]] = [()]
    if spec.samples is not None:
        rng = np.random.default_rng(spec.samples.seed)
        samples = []
        for _ in range(spec.samples.count):
            drawn: list[tuple[str, Value]] = []
            for key, low, high in spec.samples.ranges:
                if isinstance(low, int) and isinstance(high, int):
                    drawn.append((key, int(rng.integers(low, high, endpoint=True))))
                else:
                    drawn.append((key, float(rng.uniform(low, high))))
            samples.append(tuple(drawn))
    return [Point(cell=tuple(cell), sampled=sample, seed=seed,
                  overrides=spec.fixed + tuple(c for c in cell if c[0] != KILL_AXIS) + sample)
            for cell in cells for sample in samples for seed in spec.seeds]
