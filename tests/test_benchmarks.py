"""The benchmark harness (benchmarks/run_all.py) in its smallest form: every section runs and
writes the fields the report is made of. Timings are measured, never asserted here."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

pytest.importorskip("cvxpy", reason="the benchmarks need the 'bench' extra (cvxpy)")

import bench_host  # noqa: E402
import bench_startup  # noqa: E402
import run_all  # noqa: E402
import swarm_configs  # noqa: E402

pytestmark = pytest.mark.wallclock
CPUS = sorted(os.sched_getaffinity(0))


def test_scaled_configs_are_generated_from_case2_and_valid() -> None:
    for n in swarm_configs.SCALED_SIZES:
        path, config = swarm_configs.load_scaled(n)
        assert path.read_text() == swarm_configs.scaled_toml(n), (
            f"{path} is stale: run python benchmarks/swarm_configs.py --write")
        assert config.swarm.n_drones == n
        assert config.swarm.graph.is_connected()
        assert {config.swarm.graph.degree(i) for i in range(n)} == {3}


def test_importtime_lines_are_parsed_with_their_importer() -> None:
    text = ("import time: self [us] | cumulative | imported package\n"
            "import time:       100 |        100 |     numpy.core\n"
            "import time:        50 |        150 |   numpy\n"
            "import time:        10 |        160 | swarm.agent.cli\n")
    entries = {e["module"]: e for e in bench_startup.parse_importtime(text)}
    assert entries["numpy"]["parent"] == "swarm.agent.cli"
    assert entries["numpy.core"]["parent"] == "numpy"
    assert entries["numpy"]["cumulative_us"] == 150 and entries["numpy"]["self_us"] == 50


def test_every_section_runs_and_writes_its_fields(tmp_path: Path) -> None:
    assert run_all.main(["--profile", "smoke", "--out", str(tmp_path)]) == 0
    load = lambda name: json.loads((tmp_path / f"{name}.json").read_text())  # noqa: E731

    summary = load("summary")
    assert summary["machine"]["cpus"] >= 1 and "numpy" in summary["machine"]["versions"]
    assert set(summary["sections"]) == set(run_all.SECTIONS)
    assert len(summary["targets"]) == 10
    assert (tmp_path / "scaling.png").stat().st_size > 0
    for section in run_all.SECTIONS:
        assert "load_before" in summary["sections"][section]

    step = load("step")
    ours = next(r for r in step["results"] if r["qp"] == "ours")
    for name in ("total", "core", "estimation", "consensus", "barrier", "qp", "encode",
                 "decode"):
        assert ours["summary"][name]["median"]["median"] > 0, name
        assert ours["summary"][name]["p99"]["median"] > 0, name
    for kind in ("encode consensus", "encode beacon", "encode telemetry", "decode camera",
                 "decode consensus", "drone positions"):
        assert ours["summary"][kind]["median"]["median"] > 0, kind
    assert step["cvxpy_step_ratio"]["total"]["median"] > 0

    qp = load("qp")
    methods = {r["method"]: r for r in qp["results"]}
    assert "CVXPY rebuilt, PIQP" in methods and "CVXPY parametrized, PIQP" in methods
    for result in methods.values():
        assert result["median_us"]["median"] > 0 and result["ratio_to_ours"] > 0
        assert result["max_du_norm"] < 1e-5  # the solutions agree
    assert qp["whole_step"]["ratio"] > 0

    lockstep = load("lockstep")["results"][0]
    assert lockstep["summary"]["failed_runs"] == []
    run = lockstep["runs"][0]
    assert run["mission"]["sim_steps_per_s"] > 0 and run["mission"]["real_time_factor"] > 0
    assert run["cpu"]["agent_cores"]["n"] == 6

    realtime = load("realtime")["results"][0]
    assert realtime["summary"]["failed_runs"] == []
    run = realtime["runs"][0]
    assert 0.0 <= run["late_fraction"] <= 1.0
    for key in ("step_us", "neighbour_age_ms"):
        assert "p99" in run[key]
    assert run["counters"]["agent_steps"] > 0

    startup = load("startup")
    assert startup["summary"]["launch_to_streaming_s"]["median"] > 0
    assert startup["summary"]["agent_hwm_mib_max"]["median"] > 0
    assert startup["imports"]["by_package_self_ms"]

    sweep = load("sweep")
    for workers in (1, 2):
        run = sweep["sweep"][f"workers_{workers}"]
        assert run["missions"] == 4 and 1 <= run["workers"] <= workers
        assert 0 < run["mission_wall_s_sum"] < run["wall_s"] * workers
    assert sweep["sweep"]["speedup_2_workers"] > 0
    cvxpy = sweep["cvxpy"]
    assert cvxpy["ours"]["wall_s"] > 0 and cvxpy["ratio"] > 0
    assert cvxpy["max_final_position_difference_m"] < 1e-3  # the same mission, either QP
    issue42 = [t for t in summary["targets"] if "issue 42" in t["target"]]
    assert [t["status"] != "not measured" for t in issue42] == [True, True]

    camera = load("camera")
    assert [p["resolution_px"] for p in camera["pipelines"]] == [480, 480, 320]
    for pipeline in camera["pipelines"]:
        assert pipeline["frames"] == 8 and pipeline["wrong_ids"] == 0
        assert all(pipeline["stage_ms"][s]["median"] > 0
                   for s in ("render", "encode", "decode", "detect"))
        assert sum(b["n"] for b in pipeline["by_distance_m"]) <= pipeline["in_view"]
    assert [(r["mode"], r["camera"]) for r in camera["swarm"]] == [
        ("lockstep", "bearing"), ("lockstep", "rendered")]
    assert all(r["error"] is None and r["real_time_factor"] > 0 for r in camera["swarm"])
    assert all(0 < r["frames_measured"] <= 1 and r["final_error_m"] >= 0
               for r in camera["swarm"])

    # The host, at both ends of the run.
    for figures in (load("host")["figures"], summary["host_after"]):
        assert figures["python_loop_us_per_1000"] > 0
        assert figures["timer_wakeup_cpu_us"] > 0
        bounces = [figures["one_cpu"]] + ([figures["two_cpus"]] if len(CPUS) > 1 else [])
        assert figures["two_cpus"] is None or len(CPUS) > 1
        for bounce in bounces:
            assert 0 < bounce["round_trip_median_us"] <= bounce["round_trip_p90_us"]
            assert bounce["cpu_per_hop_us"] > 0


def test_the_host_bounces_give_back_the_cpus_and_leave_no_process() -> None:
    """The bounce child is gone after the call, and this thread has the CPUs it had
    before."""
    cpu = CPUS[-1]
    before = set(live_children())
    figures = bench_host.udp_round_trips(20, CPUS[0], cpu)
    assert figures["round_trip_median_us"] > 0 and figures["cpu_per_hop_us"] > 0
    assert os.sched_getaffinity(0) == set(CPUS)
    assert set(live_children()) == before


def test_a_failed_second_host_measurement_keeps_the_run_and_fails_its_exit_code(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    measure = bench_host.measure
    calls = []

    def second_fails(profile: object) -> dict:
        calls.append(profile)
        if len(calls) > 1:
            raise OSError("no loopback here")
        return measure(profile)

    monkeypatch.setattr(bench_host, "measure", second_fails)
    assert run_all.main(["--profile", "smoke", "--only", "host", "--out", str(tmp_path)]) == 1
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["host_after"] == {"error": "OSError: no loopback here"}
    host = json.loads((tmp_path / "host.json").read_text())
    assert host["figures"]["python_loop_us_per_1000"] > 0
    assert len(calls) == 2


def live_children() -> list[int]:
    """This process's live children, from /proc."""
    me = str(os.getpid())
    children = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[1] == me and fields[0] != "Z":
            children.append(int(pid))
    return children


@pytest.mark.slow
def test_the_live_view_cost_benchmark_feeds_a_real_viewer_and_prints_the_difference() -> None:
    """benchmarks/live_view_cost.py at its smallest: two realtime Case 2 seconds each way;
    the viewer process got every scene (10 Hz) and every drone's plot; the figure is printed
    (never asserted: timings belong to the benchmark)."""
    import re
    import subprocess

    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "live_view_cost.py"), "--duration", "2",
         "--repeat", "1", "--port", "8797"],
        cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    # "viewer got [log N, ]scene N, plots N": a busy machine's late steps add the log topic
    (got,) = re.findall(r"viewer got (?:log \d+, )?scene (\d+), plots (\d+)", done.stdout)
    scenes, plots = int(got[0]), int(got[1])
    # 20 scenes (t = 0.0 … 1.9 s) and a plot per drone each; realtime may give up a scene whose
    # telemetry came too late (completeness is tested in lockstep: tests/observe/test_live_view)
    assert 15 <= scenes <= 20 and plots == 6 * scenes
    assert re.search(r"the live view costs [+-]\d+\.\d % of one core", done.stdout)
