"""What the benchmark sections share: run sizes, statistics, machine facts, output.

Every section module (``bench_host``, ``bench_step``, ``bench_qp``, ``bench_lockstep``,
``realtime_swarm``, ``bench_startup``) exposes ``run(profile) -> dict`` (JSON-ready) and
``tables(result) -> list[rich.table.Table]``; ``run_all.py`` strings them together.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table
from rich.text import Text

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
RESULTS = ROOT / "benchmarks" / "results"


@dataclass(frozen=True)
class Profile:
    """Run sizes of every section; ``full`` is the reference run, ``quick`` a few minutes,
    ``smoke`` the smallest form (the test suite)."""

    name: str
    step_duration_s: float  # simulated s per in-process step run
    step_repeats: int
    step_targets: tuple[int, ...]  # which M of 1, 2, 3
    cvxpy_step_start_s: float  # Case 2 runs our path until here (the QP rows are active
    cvxpy_step_duration_s: float  # from ~12 s), then the QP rebuilt in CVXPY for this long
    qp_count: int  # captured QPs solved by every method
    qp_passes: int  # passes over them (repeats)
    qp_capture_duration_s: float
    swarm_sizes: tuple[int, ...]  # N of the realtime section
    lockstep_sizes: tuple[int, ...]  # N of the lockstep section (up to 48: cost against N)
    lockstep_duration_s: float
    lockstep_repeats: int
    realtime_duration_s: float
    realtime_repeats: int
    startup_repeats: int
    startup_duration_s: float
    import_repeats: int
    host_round_trips: int  # datagrams bounced between two processes (bench_host)
    host_timer_ticks: int  # wake-ups of a 50 Hz sleeper (bench_host)
    sweep_missions: int  # in-process Case 1 missions per timed sweep (bench_sweep)
    sweep_duration_s: float  # their simulated length
    cvxpy_mission_duration_s: float  # Case 2 in-process, ours against CVXPY (bench_sweep)
    camera_frames: int = 300  # random frames per camera (bench_camera)
    camera_swarm_duration_s: float = 10.0  # simulated s of each Case 1 swarm (bench_camera)
    camera_frame_rates_hz: tuple[float, ...] = (50.0, 25.0, 10.0)
    camera_modes: tuple[str, ...] = ("lockstep", "realtime")


PROFILES: dict[str, Profile] = {
    "full": Profile("full", step_duration_s=30.0, step_repeats=3, step_targets=(1, 2, 3),
                    cvxpy_step_start_s=12.0, cvxpy_step_duration_s=3.0, qp_count=200,
                    qp_passes=3, qp_capture_duration_s=30.0, swarm_sizes=(6, 12, 24),
                    lockstep_sizes=(6, 12, 24, 48),
                    lockstep_duration_s=10.0, lockstep_repeats=3, realtime_duration_s=10.0,
                    realtime_repeats=3, startup_repeats=5, startup_duration_s=1.5,
                    import_repeats=5, host_round_trips=3000, host_timer_ticks=100,
                    sweep_missions=40, sweep_duration_s=30.0, cvxpy_mission_duration_s=50.0),
    "quick": Profile("quick", step_duration_s=15.0, step_repeats=2, step_targets=(1, 2, 3),
                     cvxpy_step_start_s=12.0, cvxpy_step_duration_s=1.0, qp_count=60,
                     qp_passes=2, qp_capture_duration_s=20.0, swarm_sizes=(6, 12, 24),
                     lockstep_sizes=(6, 12, 24, 48),
                     lockstep_duration_s=4.0, lockstep_repeats=2, realtime_duration_s=6.0,
                     realtime_repeats=2, startup_repeats=3, startup_duration_s=1.5,
                     import_repeats=3, host_round_trips=2000, host_timer_ticks=50,
                     sweep_missions=16, sweep_duration_s=30.0, cvxpy_mission_duration_s=10.0,
                     camera_frames=100, camera_swarm_duration_s=4.0),
    "smoke": Profile("smoke", step_duration_s=1.2, step_repeats=1, step_targets=(2,),
                     cvxpy_step_start_s=1.0, cvxpy_step_duration_s=0.1, qp_count=4,
                     qp_passes=1, qp_capture_duration_s=1.2, swarm_sizes=(6,),
                     lockstep_sizes=(6,),
                     lockstep_duration_s=1.2, lockstep_repeats=1, realtime_duration_s=2.0,
                     realtime_repeats=1, startup_repeats=1, startup_duration_s=1.2,
                     import_repeats=1, host_round_trips=300, host_timer_ticks=10,
                     sweep_missions=4, sweep_duration_s=1.2, cvxpy_mission_duration_s=1.2,
                     camera_frames=8, camera_swarm_duration_s=1.2,
                     camera_frame_rates_hz=(25.0,), camera_modes=("lockstep",)),
}


# -- statistics ---------------------------------------------------------------------------


def stats(values: Iterable[float]) -> dict[str, float | int | None]:
    """Median, p99, mean, min, max and count of ``values`` (None for an empty sample)."""
    array = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=float)
    if array.size == 0:
        return {"median": None, "p99": None, "mean": None, "min": None, "max": None, "n": 0}
    return {"median": float(np.median(array)), "p99": float(np.percentile(array, 99)),
            "mean": float(array.mean()), "min": float(array.min()), "max": float(array.max()),
            "n": int(array.size)}


def spread(values: Sequence[float | None]) -> dict[str, float | list | None]:
    """Median, min and max over the repeats of one figure, and the figures themselves."""
    clean = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not clean:
        return {"median": None, "min": None, "max": None, "values": list(values)}
    return {"median": float(np.median(clean)), "min": min(clean), "max": max(clean),
            "values": clean}


def over_runs(runs: Sequence[dict], get: Callable[[dict], float | None]) -> dict:
    """``spread`` of one figure over the runs; a failed run (or a missing figure) is None."""
    values = []
    for run in runs:
        if not run.get("usable", True):
            values.append(None)
            continue
        try:
            values.append(get(run))
        except (KeyError, TypeError, IndexError):
            values.append(None)
    return spread(values)


def fmt(value: float | None, digits: int = 0, unit: str = "") -> str:
    """A number for a table cell, '—' for None."""
    if value is None or not np.isfinite(value):
        return "—"
    return f"{value:,.{digits}f}{unit}"


def fmt_spread(figure: dict, digits: int = 0, scale: float = 1.0) -> str:
    """'median (min–max)' of a ``spread`` dict; only the median when there is one repeat."""
    if figure["median"] is None:
        return "—"
    median = fmt(figure["median"] * scale, digits)
    if len(figure["values"]) < 2:
        return median
    return (f"{median} ({fmt(figure['min'] * scale, digits)}–"
            f"{fmt(figure['max'] * scale, digits)})")


def progress(message: str) -> None:
    """One progress line on stderr (the tables go to stdout)."""
    print(f"  [{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


# -- machine ------------------------------------------------------------------------------


def load_average() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"],
                             capture_output=True, text=True, timeout=5, check=False)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--",
                                "swarm", "sim_world"], capture_output=True, text=True,
                               timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    commit = out.stdout.strip() or "unknown"
    if not dirty.stdout.strip():
        return commit
    # Uncommitted changes to the measured code: name them by a hash of the diff.
    try:
        diff = subprocess.run(["git", "-C", str(ROOT), "diff", "HEAD", "--", "swarm",
                               "sim_world"], capture_output=True, timeout=5, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return commit + "+dirty"
    return f"{commit}+dirty.{hashlib.sha1(diff.stdout).hexdigest()[:10]}"


def versions() -> dict[str, str]:
    """Versions of the interpreter and of the libraries on the measured paths."""
    found = {"python": platform.python_version()}
    for name in ("numpy", "scipy", "daqp", "piqp", "msgspec", "zenoh", "pymavlink", "cvxpy",
                 "clarabel", "osqp"):
        try:
            module = __import__(name)
        except ImportError:
            continue
        found[name] = str(getattr(module, "__version__", "?"))
    return found


def machine_info() -> dict[str, object]:
    cpu_model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "cpu_model": cpu_model or platform.processor(),
            "platform": platform.platform(), "git_commit": git_commit(),
            "versions": versions()}


def machine_cpu_s() -> tuple[float, float]:
    """(busy, steal) CPU seconds of the whole machine since boot, from /proc/stat."""
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(v) for v in fields[:8])
    tick = os.sysconf("SC_CLK_TCK")
    return (user + nice + system + irq + softirq) / tick, steal / tick


def own_cpu_s() -> float:
    """CPU seconds of this process and of its children that have ended (the swarms)."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


class SectionClock:
    """Wall time, load average and CPU use around one section.

    The load average counts our own swarm's threads too, so the CPU the rest of the machine
    used meanwhile is also given: machine busy time minus ours, in cores (and the time the
    hypervisor stole).
    """

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.load_before = load_average()
        self.machine_before = machine_cpu_s()
        self.own_before = own_cpu_s()

    def done(self) -> dict[str, object]:
        wall = time.perf_counter() - self.started
        busy, steal = (after - before for after, before in
                       zip(machine_cpu_s(), self.machine_before, strict=True))
        own = own_cpu_s() - self.own_before
        return {"wall_s": round(wall, 1), "load_before": self.load_before,
                "load_after": load_average(),
                "cpu_cores": {"ours": round(own / wall, 2),
                              "others": round(max(busy - own, 0.0) / wall, 2),
                              "steal": round(steal / wall, 2)}}


# -- output -------------------------------------------------------------------------------


def console() -> Console:
    """A console wide enough for the tables, also when stdout is a file or a pipe."""
    return Console(width=None if sys.stdout.isatty() else 180)


class PlainTable(Table):
    """A rich table of plain text: no markup in cells (a unit like "[s]" stays as it is)."""

    def add_row(self, *renderables: object, **kwargs: object) -> None:  # type: ignore[override]
        super().add_row(*(Text(r) if isinstance(r, str) else r for r in renderables),
                        **kwargs)  # type: ignore[arg-type]


def new_table(title: str, columns: Sequence[str], caption: str | None = None) -> Table:
    table = PlainTable(title=Text(title), caption=Text(caption) if caption else None,
                       title_justify="left", caption_justify="left")
    for index, column in enumerate(columns):
        table.add_column(Text(column), justify="left" if index == 0 else "right")
    return table


def write_json(path: Path, data: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return asdict(value)  # type: ignore[call-overload]
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


# -- the command line of one section -------------------------------------------------------------


def section_parser(doc: str, out_name: str) -> argparse.ArgumentParser:
    """``--profile`` and ``--out`` (default ``results/<out_name>``), the options every section
    script has; a script adds its own."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--profile", choices=sorted(PROFILES), default="full")
    parser.add_argument("--out", type=Path, default=RESULTS / out_name, help="JSON output")
    return parser


def report_section(result: dict, tables: Callable[[dict], list[Table]], script: str,
                   argv: Sequence[str] | None, out_path: Path) -> int:
    """Print a section's tables, then write its result with the command line and the
    machine to ``out_path``; exit code 0."""
    out = console()
    for table in tables(result):
        out.print(table)
    result["command"] = " ".join(["python", f"benchmarks/{script}", *(argv or sys.argv[1:])])
    result["machine"] = machine_info()
    write_json(out_path, result)
    out.print(f"wrote {out_path}")
    return 0
