"""Agent start-up and memory (issue 5): launch → every drone streaming, RSS, import time.

    python benchmarks/bench_startup.py [--profile quick] [--out FILE]
    (or as the ``startup`` section of ``python benchmarks/run_all.py``)

- Launch: ``--repeats`` short lockstep missions of Case 2 (6 drones) through
  ``SwarmLauncher``; launch → every drone armed and streaming setpoints is the time from
  ``SwarmLauncher.run`` to the world's first "running" clock message (``swarm_probe``; the
  launcher's own "armed and streaming after X s" line is kept next to it). Per agent, from
  its process start: set up (imports, config, Zenoh session, MAVLink socket: its "waiting
  for HEARTBEAT" line), HEARTBEAT, first setpoints, armed and streaming.
- Memory per agent process: peak resident set (VmHWM) and RSS from /proc/<pid>/status, and
  the proportional set size (Pss, shared library pages split between the processes that map
  them) from /proc/<pid>/smaps_rollup, sampled through the mission; in MiB.
- Imports: ``python -X importtime -c "import swarm.agent.process"`` (what ``swarm-agent``
  loads once its MAVLink socket is bound; its entry module ``swarm.agent.cli`` loads only the
  standard library before that),
  its wall time against a bare interpreter, the self time summed per top-level package, and
  the heaviest modules the project imports directly (who pulls in what).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from typing import Any

from common import (
    PROFILES,
    ROOT,
    Profile,
    SectionClock,
    fmt,
    fmt_spread,
    new_table,
    over_runs,
    report_section,
    section_parser,
    spread,
)
from rich.table import Table
from swarm_configs import load_scaled
from swarm_probe import AGENT_PHASES, attempt_swarm

# What swarm-agent imports after binding its socket: everything but the light entry module.
ENTRY_MODULE = "swarm.agent.process"
PROJECT_PACKAGES = ("swarm", "sim_world")
TOP_PACKAGES = 12
TOP_EDGES = 12


# -- imports ------------------------------------------------------------------------------


def parse_importtime(text: str) -> list[dict[str, Any]]:
    """The ``-X importtime`` lines as {module, level, self_us, cumulative_us, parent}.

    A module's line follows its children's; a line at level L adopts the pending lines at
    level L + 1 as its children.
    """
    entries: list[dict[str, Any]] = []
    pending: list[dict[str, Any]] = []
    for line in text.splitlines():
        if not line.startswith("import time:") or "self [us]" in line:
            continue
        head, cumulative, name_field = line.split("|", 2)
        self_us, cumulative_us = int(head.split(":", 1)[1]), int(cumulative)
        indent = len(name_field) - len(name_field.lstrip())
        entry = {"module": name_field.strip(), "level": (indent - 1) // 2,
                 "self_us": self_us, "cumulative_us": cumulative_us, "parent": None}
        while pending and pending[-1]["level"] == entry["level"] + 1:
            pending.pop()["parent"] = entry["module"]
        pending.append(entry)
        entries.append(entry)
    return entries


def _timed_run(argv: list[str], env: dict[str, str]) -> tuple[float, str]:
    """Wall time of a child interpreter and its stderr."""
    started = time.perf_counter()
    done = subprocess.run(argv, check=True, env=env, cwd=ROOT, capture_output=True, text=True)
    return time.perf_counter() - started, done.stderr


def import_profile(repeats: int) -> dict[str, Any]:
    """Import time of the agent's entry module: wall time (with the environment as it is,
    and with a warm bytecode cache), per package, heaviest edges."""
    env = dict(os.environ)
    with tempfile.TemporaryDirectory(prefix="vigil-pyc-") as cache:
        # PYTHONDONTWRITEBYTECODE (set in some sandboxes) makes every agent compile the
        # project's modules from source; a private cache directory shows what that costs.
        cached_env = {k: v for k, v in env.items() if k != "PYTHONDONTWRITEBYTECODE"}
        cached_env["PYTHONPYCACHEPREFIX"] = cache
        import_argv = [sys.executable, "-c", f"import {ENTRY_MODULE}"]
        _timed_run(import_argv, cached_env)  # fills the cache
        wall_bare, wall_import, wall_cached, runs = [], [], [], []
        for _ in range(repeats):
            wall_bare.append(_timed_run([sys.executable, "-c", "pass"], env)[0])
            wall_import.append(_timed_run(import_argv, env)[0])
            wall_cached.append(_timed_run(import_argv, cached_env)[0])
            runs.append(parse_importtime(_timed_run(
                [sys.executable, "-X", "importtime", "-c", f"import {ENTRY_MODULE}"], env)[1]))
    # The run with the median total stands for all of them.
    totals = [_entry_total(entries) for entries in runs]
    entries = runs[sorted(range(len(runs)), key=totals.__getitem__)[len(runs) // 2]]
    by_package: dict[str, int] = defaultdict(int)
    for e in entries:
        by_package[e["module"].split(".")[0]] += e["self_us"]
    packages = sorted(by_package.items(), key=lambda kv: -kv[1])[:TOP_PACKAGES]
    edges = [e for e in entries
             if e["parent"] and e["parent"].split(".")[0] in PROJECT_PACKAGES
             and e["module"].split(".")[0] not in PROJECT_PACKAGES]
    edges.sort(key=lambda e: -e["cumulative_us"])
    return {
        "module": ENTRY_MODULE,
        "dont_write_bytecode": bool(env.get("PYTHONDONTWRITEBYTECODE")),
        "wall_s": spread(wall_import), "wall_bytecode_cached_s": spread(wall_cached),
        "bare_interpreter_s": spread(wall_bare),
        "importtime_total_ms": spread([t / 1e3 for t in totals]),
        "by_package_self_ms": [{"package": p, "self_ms": us / 1e3} for p, us in packages],
        "heaviest_third_party_imports": [
            {"module": e["module"], "imported_by": e["parent"],
             "cumulative_ms": e["cumulative_us"] / 1e3} for e in edges[:TOP_EDGES]],
    }


def _entry_total(entries: list[dict[str, Any]]) -> int:
    """Cumulative µs of the entry module (0 when it is missing)."""
    return next((e["cumulative_us"] for e in entries if e["module"] == ENTRY_MODULE), 0)


# -- launches -----------------------------------------------------------------------------


def run(profile: Profile) -> dict[str, Any]:
    clock = SectionClock()
    path, config = load_scaled(6)
    config = config.with_duration(profile.startup_duration_s)
    launches = [attempt_swarm(path, config, "lockstep", check=False)
                for _ in range(profile.startup_repeats)]

    def over(get: Any) -> dict[str, Any]:
        return over_runs(launches, get)

    summary = {
        "launch_to_streaming_s": over(lambda r: r["startup"]["launch_to_streaming_s"]),
        "launcher_reported_s": over(lambda r: r["startup"]["launcher_reported_s"]),
        "agent_spawn_after_launch_s": over(
            lambda r: r["startup"]["agent_spawn_after_launch_s"]["median"]),
        "first_setpoint_after_launch_s": over(
            lambda r: r["startup"]["first_setpoint_after_launch_s"]["median"]),
        "agent_cpu_until_ready_s": over(
            lambda r: r["startup"]["agent_cpu_until_ready_s"]["median"]),
        "world_cpu_until_running_s": over(lambda r: r["startup"]["world_cpu_until_running_s"]),
        **{f"agent_{phase}_s": over(
            lambda r, p=phase: r["startup"]["agent_phases_s"][p]["median"])
           for phase in AGENT_PHASES},
        "agent_hwm_mib_max": over(lambda r: r["memory_mib"]["agent_hwm"]["max"]),
        "agent_hwm_mib_median": over(lambda r: r["memory_mib"]["agent_hwm"]["median"]),
        "agent_rss_mib_median": over(lambda r: r["memory_mib"]["agent_rss"]["median"]),
        "agent_pss_mib_median": over(lambda r: r["memory_mib"]["agent_pss"]["median"]),
        "world_hwm_mib": over(lambda r: r["memory_mib"]["world_hwm"]),
        "failed_launches": [r["error"] for r in launches if "error" in r],
    }
    return {"section": "startup", "profile": profile.name, "n_drones": 6,
            "repeats": profile.startup_repeats, "launches": launches, "summary": summary,
            "imports": import_profile(profile.import_repeats), **clock.done()}


def tables(result: dict[str, Any]) -> list[Table]:
    s = result["summary"]
    launch = new_table(
        f"Start-up and memory, Case 2 ({result['n_drones']} drones, lockstep)",
        ["figure", "median (min–max)"],
        caption=(f"over {result['repeats']} launches; agent phases from each agent's process "
                 "start (median over the agents); memory in MiB"))
    rows = [
        ("launch → every drone armed and streaming [s]", s["launch_to_streaming_s"], 2),
        ("  (the launcher's own figure) [s]", s["launcher_reported_s"], 1),
        ("launch → agents spawned (world up, router reachable) [s]",
         s["agent_spawn_after_launch_s"], 2),
        ("agent start → set up, waiting for HEARTBEAT [s]", s["agent_setup_done_s"], 2),
        ("agent start → HEARTBEAT [s]", s["agent_heartbeat_s"], 2),
        ("agent start → first setpoints [s]", s["agent_first_setpoint_s"], 2),
        ("agent start → armed and streaming [s]", s["agent_ready_s"], 2),
        ("launch → an agent's first setpoints [s]", s["first_setpoint_after_launch_s"], 2),
        ("agent CPU time until armed and streaming [s]", s["agent_cpu_until_ready_s"], 2),
        ("world CPU time until the mission runs [s]", s["world_cpu_until_running_s"], 2),
        ("agent peak RSS (VmHWM), largest agent", s["agent_hwm_mib_max"], 1),
        ("agent peak RSS (VmHWM), median agent", s["agent_hwm_mib_median"], 1),
        ("agent PSS (shared pages split), median agent", s["agent_pss_mib_median"], 1),
        ("world peak RSS", s["world_hwm_mib"], 1),
    ]
    imports = result["imports"]
    cache_note = " (PYTHONDONTWRITEBYTECODE set)" if imports["dont_write_bytecode"] else ""
    rows += [
        (f"python -c 'import {imports['module']}' wall{cache_note} [s]", imports["wall_s"], 2),
        ("  the same with a warm bytecode cache [s]", imports["wall_bytecode_cached_s"], 2),
        ("  bare interpreter (python -c pass) [s]", imports["bare_interpreter_s"], 2),
        ("  -X importtime total [ms]", imports["importtime_total_ms"], 0),
    ]
    for label, figure, digits in rows:
        launch.add_row(label, fmt_spread(figure, digits))
    packages = new_table(f"-X importtime of {imports['module']}: self time per package",
                         ["package", "self ms"])
    for row in imports["by_package_self_ms"]:
        packages.add_row(row["package"], fmt(row["self_ms"], 1))
    edges = new_table("Heaviest third-party imports made by the project's modules",
                      ["module", "first imported by", "cumulative ms"])
    for row in imports["heaviest_third_party_imports"]:
        edges.add_row(row["module"], row["imported_by"], fmt(row["cumulative_ms"], 1))
    return [launch, packages, edges]


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "startup.json")
    args = parser.parse_args(argv)
    return report_section(run(PROFILES[args.profile]), tables, "bench_startup.py", argv, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
