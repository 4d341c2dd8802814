"""Per-drone step (issue 5): compute time of one drone's step for M = 1, 2, 3, wire included.

    python benchmarks/bench_step.py [--duration 20] [--repeats 3] [--out FILE]
    (or as the ``step`` section of ``python benchmarks/run_all.py``)

Scenarios: Case 1 (M = 1, hard QP), Case 2 (M = 2, relaxed QP), Case 2 with a third target
added in code (M = 3), and Case 2 with the QP rebuilt in CVXPY at every step as the thesis
did (``cvxpy_qp.CvxpyRebuiltWorkspace``, PIQP underneath). Each runs in process
(``swarm.runs.reference.run_reference``, 6 drones, seed 0); every drone and every step with the
barrier QP active (t ≥ ``control.start_s``) is one sample. The CVXPY scenario flies our path
until ``cvxpy_step_start_s`` (12 s: from about then on Case 2's QP rows are active), then
alternates step by step between the QP rebuilt in CVXPY and ours: the ratio compares the two
under the same load (a sequential comparison on a shared machine drifted from 17× to 50×).

Per sample, wall clock (``time.perf_counter``):

- core: the agent's own ``step_us`` (``begin_step`` + K × ``consensus_round`` +
  ``finish_step``, no waiting for neighbours), split by ``DroneAgent.section_us`` into
  estimation (ICF local steps), consensus (the K rounds and the PI-consensus/Gramian update),
  barrier (perception weights, HOCBF terms, constraint rows), qp (solver matrices, DAQP update
  and solve, feasibility check) and other;
- encode: what ``swarm.agent.process`` encodes for that step with ``swarm.messages.wire.WireCodec``:
  the consensus message of every round, the beacon and the telemetry (``encode_consensus``,
  ``encode_beacon``, ``encode_telemetry``: built from the core's types and checked);
- decode: what it decodes for that step, as a lockstep agent does: the camera frame (its
  detections and every drone's reported position, ``CameraFrameWire.drone_positions``),
  every neighbour's consensus message of every round, and the others' positions taken from
  the frame ("drone positions"; the world's own work is not timed). The agent runs on the
  decoded messages (bit-exact), as in the process swarm. (A realtime agent decodes the
  world's relay of beacons instead of the positions: ~9 µs at N = 6.)
- total = core + encode + decode ("everything included"); cpu = thread CPU time of the same
  work (leaves out waiting for a CPU on a loaded machine).

Per run: median and p99 of each; tables show the median over the repeats and its spread.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from common import (
    CONFIGS,
    PROFILES,
    Profile,
    SectionClock,
    fmt,
    fmt_spread,
    new_table,
    progress,
    report_section,
    section_parser,
    spread,
    stats,
)
from cvxpy_qp import CvxpyRebuiltWorkspace
from rich.table import Table
from rich.text import Text

import swarm.runs.reference as reference
from swarm.core.drone_step import ConsensusMessage, Detection, DroneAgent, StepResult
from swarm.messages.wire import CameraFrameWire, WireCodec
from swarm.scenario.config import ScenarioConfig, TargetSection, load_config

CORE_SECTIONS = ("estimation", "consensus", "barrier", "qp", "other")
# The wire work of one drone step, by message (all rounds, all neighbours, all beacons).
WIRE_KINDS = ("encode consensus", "encode beacon", "encode telemetry", "decode camera",
              "decode consensus", "drone positions")
SECTIONS = (*CORE_SECTIONS, "encode", "decode")
CVXPY_LABEL = "case2, QP rebuilt in CVXPY"


def three_target_config(case2: ScenarioConfig) -> ScenarioConfig:
    """Case 2 plus a third target: a line crossing between the other two."""
    third = TargetSection(trajectory="linear", start_m=(0.0, 0.8, 0.0),
                          velocity_m_s=(-0.1, 0.25, 0.0), ramp_s=5.0)
    return dataclasses.replace(case2, targets=(*case2.targets, third))


@dataclasses.dataclass(frozen=True)
class Scenario:
    label: str
    m_targets: int
    config: ScenarioConfig
    # "ours" (the agent's DAQP workspace) or "cvxpy" (rebuilt every step, from qp_switch_s on)
    qp: str = "ours"
    qp_switch_s: float = 0.0  # cvxpy: our path until here, samples only after


def scenarios(profile: Profile) -> list[Scenario]:
    case1 = load_config(CONFIGS / "case1.toml").with_duration(profile.step_duration_s)
    case2 = load_config(CONFIGS / "case2.toml").with_duration(profile.step_duration_s)
    by_m = {1: Scenario("case1 (hard QP)", 1, case1),
            2: Scenario("case2 (relaxed QP)", 2, case2),
            3: Scenario("case2 + 1 target", 3, three_target_config(case2))}
    chosen = [by_m[m] for m in profile.step_targets]
    # Case 2's QP rows become active from about 12 s: the CVXPY step is timed in that regime.
    cvxpy_case = case2.with_duration(profile.cvxpy_step_start_s + profile.cvxpy_step_duration_s)
    return [*chosen, Scenario(CVXPY_LABEL, 2, cvxpy_case, qp="cvxpy",
                              qp_switch_s=profile.cvxpy_step_start_s)]


# -- the wire work of one step ----------------------------------------------------------


class WireBus:
    """The payloads of the current step, as the process swarm would have them on Zenoh, and
    every drone's reported position of the step (``reference.position_over_link``'s N
    results, which come before any drone's step begins), as the world's frames carry them."""

    def __init__(self, codec: WireCodec, n_drones: int) -> None:
        self.codec, self.n_drones = codec, n_drones
        self.consensus: dict[tuple[int, int], bytes] = {}  # (round, sender) → payload
        self.beacons: dict[int, bytes] = {}  # sender → payload
        self._reported: list[np.ndarray] = []

    def report(self, position: np.ndarray) -> None:
        if len(self._reported) == self.n_drones:  # the first of the next step
            self._reported = []
        self._reported.append(position)

    def reported_positions(self) -> np.ndarray:
        assert len(self._reported) == self.n_drones, "a step's positions are not all in"
        return np.array(self._reported)


class StepProbe:
    """Wraps one agent's step methods: runs them on decoded messages and encodes what they
    send, as ``swarm.agent.process`` does, timing the agent and the wire work apart.

    After each ``finish_step``: ``core_cpu_s`` (thread CPU of the agent's calls),
    ``encode_s`` / ``decode_s`` (wall), ``wire_s`` (wall, by message: ``WIRE_KINDS``) and
    ``wire_cpu_s`` (thread CPU of all the wire work).
    """

    def __init__(self, agent: DroneAgent, codec: WireCodec, bus: WireBus,
                 config: ScenarioConfig) -> None:
        self.agent, self.codec, self.bus, self.config = agent, codec, bus, config
        self.drone = agent.setup.drone_id
        self._begin, self._round, self._finish = (agent.begin_step, agent.consensus_round,
                                                  agent.finish_step)
        agent.begin_step, agent.consensus_round, agent.finish_step = (  # type: ignore[method-assign]
            self.begin_step, self.consensus_round, self.finish_step)
        self.core_cpu_s = self.encode_s = self.decode_s = self.wire_cpu_s = 0.0
        self.wire_s = dict.fromkeys(WIRE_KINDS, 0.0)
        self._current_round = 0
        self._step = 0
        self._frame: CameraFrameWire | None = None
        self._position = np.zeros(3)
        self._flying = np.zeros(3)

    def _timed(self, kind: str, work: Callable[[], Any]) -> Any:
        # The wall interval holds the work only: the thread clock (a system call, ~0.25 us)
        # is read outside it.
        cpu = time.thread_time()
        wall = time.perf_counter()
        result = work()
        elapsed = time.perf_counter() - wall
        self.wire_cpu_s += time.thread_time() - cpu
        self.wire_s[kind] += elapsed
        if kind.startswith("encode"):
            self.encode_s += elapsed
        else:
            self.decode_s += elapsed
        return result

    def _core(self, call: Callable[..., Any], *args: Any) -> Any:
        cpu = time.thread_time()
        result = call(*args)
        self.core_cpu_s += time.thread_time() - cpu
        return result

    def _send_consensus(self, message: ConsensusMessage | None) -> None:
        if message is not None:
            payload = self._timed("encode consensus",
                                  lambda: self.codec.encode_consensus(message))
            self.bus.consensus[(message.round, self.drone)] = payload

    def begin_step(self, step: int, position: np.ndarray, detections: list[Detection],
                   communicated: np.ndarray | None = None) -> ConsensusMessage:
        self.core_cpu_s = self.encode_s = self.decode_s = self.wire_cpu_s = 0.0
        self.wire_s = dict.fromkeys(WIRE_KINDS, 0.0)
        self._step, self._position, self._current_round = step, position, 0
        dt = self.config.scenario.dt_s
        # The world's side (not timed): the camera frame of this drone.
        frame = self.codec.encode(CameraFrameWire.build(
            drone=self.drone, step=step, time_s=step * dt, vehicle_time_ms=round(step * dt * 1e3),
            detections=detections, target_velocities=communicated,
            drone_positions=self.bus.reported_positions()))

        def decode_frame() -> tuple[list[Detection], np.ndarray | None]:
            wire = self._frame = self.codec.decode_camera(frame)
            return wire.detection_list(), wire.target_velocity_array()

        detections, communicated = self._timed("decode camera", decode_frame)
        message = self._core(self._begin, step, position, detections, communicated)
        self.bus.beacons[self.drone] = self._timed("encode beacon", lambda: (
            self.codec.encode_beacon(self.drone, step, step * dt, position,
                                     velocity_m_s=self._flying, sample_age_s=0.0)))
        self._send_consensus(message)
        return message

    def consensus_round(self, inbox: dict[int, ConsensusMessage]) -> ConsensusMessage | None:
        rnd = self._current_round
        decoded = self._timed("decode consensus", lambda: {
            j: self.codec.decode_consensus(self.bus.consensus[(rnd, j)]) for j in inbox})
        message = self._core(self._round, decoded)
        self._current_round += 1
        self._send_consensus(message)
        return message

    def finish_step(self, _beacons: dict[int, list[float]]) -> StepResult:
        frame = self._frame
        assert frame is not None

        def others() -> dict[int, list[float]]:  # as LockstepExchange.beacons takes them
            rows = frame.drone_position_rows()
            assert rows is not None
            return {j: rows[j] for j in range(len(rows)) if j != self.drone}

        decoded = self._timed("drone positions", others)
        result: StepResult = self._core(self._finish, decoded)
        agent = self.agent
        self._timed("encode telemetry", lambda: self.codec.encode_telemetry(
            result.diagnostics, self._position, qp_fallbacks=agent.qp_fallbacks,
            rejected_messages=agent.rejected_inputs,
            missing_neighbour_messages=agent.missing_neighbour_messages,
            stale_neighbour_messages=0, late_steps=0, steps=self._step + 1,
            neighbour_age_ms=float("nan"), mavlink_state="armed OFFBOARD"))
        self._flying = result.velocity
        return result


class QpSwitch:
    """Swaps one agent's relaxed-QP workspace between ours and the QP rebuilt in CVXPY (a
    benchmark-only swap of the agent's private attribute)."""

    def __init__(self, agent: DroneAgent, config: ScenarioConfig) -> None:
        ctrl = config.control
        if ctrl.qp != "relaxed":
            raise ValueError("the CVXPY step is written for the relaxed QP (Case 2)")
        self.agent = agent
        self.ours = agent._qp_relaxed
        self.cvxpy = CvxpyRebuiltWorkspace(
            agent.setup.n_targets, agent.setup.n_drones - 1, slack_weight=ctrl.slack_weight,
            weight_floor=ctrl.weight_floor, u_max=ctrl.u_max_m_s)

    def use(self, backend: str) -> None:
        self.agent._qp_relaxed = (  # type: ignore[assignment]
            self.cvxpy if backend == "cvxpy" else self.ours)


def warm_up_cvxpy() -> None:
    """One throw-away solve: CVXPY's first call in a process imports and sets up far more
    than the later ones."""
    CvxpyRebuiltWorkspace(1, 1, slack_weight=1.0, weight_floor=1e-3, u_max=1.0).solve(
        (0.0, 0.0, 0.0), [0.0] * 9, [0.0, 0.0, -1.0], [1.0])


@contextlib.contextmanager
def probed_agents(config: ScenarioConfig) -> Iterator[list[StepProbe]]:
    """The agents ``run_reference`` builds, each wrapped in a ``StepProbe``."""
    probes: list[StepProbe] = []
    bus = WireBus(config.wire_codec(), config.swarm.n_drones)
    original, over_link = reference.build_agent, reference.position_over_link

    def build(*args: Any, **kwargs: Any) -> DroneAgent:
        agent = original(*args, **kwargs)
        codec = config.wire_codec()
        probes.append(StepProbe(agent, codec, bus, config))
        return agent

    def reported(position: np.ndarray, origin: np.ndarray) -> np.ndarray:
        seen = over_link(position, origin)
        bus.report(seen)
        return seen

    reference.build_agent, reference.position_over_link = build, reported
    try:
        yield probes
    finally:
        reference.build_agent, reference.position_over_link = original, over_link


def run_once(scenario: Scenario) -> dict[str, Any]:
    """One run: a sample per drone and control-active step.

    The CVXPY scenario flies our path until its switch, then alternates step by step: even
    steps with the QP rebuilt in CVXPY (the samples), odd steps with ours (``paired``), so
    that both are timed under the same load (the solutions agree to ~1e-7 m/s, so the
    trajectory is ours).
    """
    samples: dict[str, list[float]] = {
        name: [] for name in ("core", "total", "cpu", "core_cpu", "qp_solve", *SECTIONS,
                              *WIRE_KINDS)}
    paired: dict[str, list[float]] = {"core": [], "total": [], "cpu": []}
    config = scenario.config
    dt = config.scenario.dt_s
    switch = round(scenario.qp_switch_s / dt) if scenario.qp == "cvxpy" else None
    if switch is not None:
        warm_up_cvxpy()

    def backend(k: int) -> str:
        return "ours" if switch is None or k < switch or (k - switch) % 2 else "cvxpy"

    progress(f"step: {scenario.label}, {config.scenario.duration_s:g} s simulated")
    with probed_agents(config) as probes:
        switches: list[QpSwitch] = []

        def on_step(k: int, diagnostics: list) -> None:
            if switch is not None and k + 1 >= switch:
                if not switches:
                    switches.extend(QpSwitch(p.agent, config) for p in probes)
                for qp_switch in switches:
                    qp_switch.use(backend(k + 1))
            for probe, diag in zip(probes, diagnostics, strict=True):
                if not diag.control_active or (switch is not None and k < switch):
                    continue
                encode_us, decode_us = probe.encode_s * 1e6, probe.decode_s * 1e6
                total_us = diag.step_us + encode_us + decode_us
                cpu_us = (probe.core_cpu_s + probe.wire_cpu_s) * 1e6
                if switch is not None and backend(k) == "ours":
                    paired["core"].append(diag.step_us)
                    paired["total"].append(total_us)
                    paired["cpu"].append(cpu_us)
                    continue
                samples["core"].append(diag.step_us)
                samples["total"].append(total_us)
                samples["core_cpu"].append(probe.core_cpu_s * 1e6)
                samples["cpu"].append(cpu_us)
                samples["qp_solve"].append(diag.qp_solve_us)
                samples["encode"].append(encode_us)
                samples["decode"].append(decode_us)
                for kind, seconds in probe.wire_s.items():
                    samples[kind].append(seconds * 1e6)
                timing = probe.agent.section_us
                for name in CORE_SECTIONS:
                    samples[name].append(timing[name])

        # As an agent process does after its set-up (swarm.net.rate.freeze_heap): the long-lived
        # objects leave the collector's reach, so a collection does not walk them mid-step.
        gc.collect()
        gc.freeze()
        try:
            record = reference.run_reference(config, seed=0, on_step=on_step)
        finally:
            gc.unfreeze()
    result: dict[str, Any] = {
        "stats_us": {name: stats(values) for name, values in samples.items()},
        "samples": len(samples["core"]), "qp_fallbacks": int(record.qp_fallback.sum()),
        "wall_s": record.wall_time_s}
    if switch is not None:
        ours = {name: stats(values) for name, values in paired.items()}
        theirs = result["stats_us"]
        result["paired_ours_us"] = ours
        result["ratio"] = {name: _ratio(theirs[name]["median"], ours[name]["median"])
                           for name in ("total", "core", "cpu")}
    return result


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median over the repeats (and spread) of each run's median and p99 per quantity."""
    names = runs[0]["stats_us"].keys()
    return {name: {key: spread([r["stats_us"][name][key] for r in runs])
                   for key in ("median", "p99")} for name in names}


def run(profile: Profile) -> dict[str, Any]:
    clock = SectionClock()
    results = []
    for scenario in scenarios(profile):
        runs = [run_once(scenario) for _ in range(profile.step_repeats)]
        results.append({"scenario": scenario.label, "m_targets": scenario.m_targets,
                        "qp": scenario.qp, "duration_s": scenario.config.scenario.duration_s,
                        "qp_switch_s": scenario.qp_switch_s if scenario.qp == "cvxpy" else None,
                        "runs": runs, "summary": summarise(runs)})
    return {"section": "step", "profile": profile.name, "repeats": profile.step_repeats,
            "results": results, "cvxpy_step_ratio": cvxpy_ratio(results), **clock.done()}


def cvxpy_ratio(results: list[dict[str, Any]]) -> dict[str, Any] | None:
    """How many times our whole M = 2 step (everything included) is faster than the same
    step with the QP rebuilt in CVXPY, from the interleaved steps of the CVXPY scenario:
    per run the ratio of the medians, then the median (and spread) over the runs; by wall
    time (total, core) and by thread CPU time (cpu)."""
    theirs = next((r for r in results if r["qp"] == "cvxpy"), None)
    if theirs is None:
        return None
    runs = theirs["runs"]
    return {
        **{name: spread([r["ratio"][name] for r in runs]) for name in ("total", "core", "cpu")},
        "cvxpy_total_us": spread([r["stats_us"]["total"]["median"] for r in runs]),
        "ours_total_us": spread([r["paired_ours_us"]["total"]["median"] for r in runs]),
        "from_s": theirs["qp_switch_s"]}


def tables(result: dict[str, Any]) -> list[Table]:
    columns = ["scenario", "M", "total med", "total p99", "core med", "core p99", "cpu med",
               *SECTIONS, "QP solve", "samples"]
    table = new_table(
        "Per-drone step [µs] (6 drones in process; wire encode/decode as the process swarm)",
        columns,
        caption=("total = core + encode + decode (everything included); medians over "
                 f"{result['repeats']} repeats of each run's median/p99, (min–max) over the "
                 "repeats;\nsections: median of each; QP solve: DAQP update + solve; cpu: "
                 "thread CPU of core + wire"))
    for res in result["results"]:
        s = res["summary"]
        table.add_row(
            res["scenario"], str(res["m_targets"]), fmt_spread(s["total"]["median"]),
            fmt_spread(s["total"]["p99"]), fmt(s["core"]["median"]["median"]),
            fmt(s["core"]["p99"]["median"]), fmt(s["cpu"]["median"]["median"]),
            *(fmt(s[name]["median"]["median"]) for name in SECTIONS),
            fmt(s["qp_solve"]["median"]["median"]), str(res["runs"][0]["samples"]))
    wire = new_table(
        "Wire work of one drone step [µs], by message (medians; M = number of targets)",
        ["scenario", "M", *WIRE_KINDS],
        caption=("consensus: every round's message (sent once, decoded once per neighbour); "
                 "camera: the frame, its detections and every drone's position; drone "
                 "positions: the others' taken from it"))
    for res in result["results"]:
        s = res["summary"]
        wire.add_row(res["scenario"], str(res["m_targets"]),
                     *(fmt(s[kind]["median"]["median"]) for kind in WIRE_KINDS))
    ratio = result.get("cvxpy_step_ratio")
    if ratio:
        table.caption += Text(
            f"\nthe M = 2 step with the QP rebuilt in CVXPY, interleaved step by step with ours "
            f"from t = {ratio['from_s']:g} s: {ratio['cvxpy_total_us']['median']:.0f} µs "
            f"against {ratio['ours_total_us']['median']:.0f} µs, "
            f"{fmt_spread(ratio['total'], 1)}× slower everything included "
            f"({fmt_spread(ratio['core'], 1)}× core step, {fmt_spread(ratio['cpu'], 1)}× "
            f"by thread CPU time)")
    return [table, wire]


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "step.json")
    parser.add_argument("--duration", type=float, default=None, help="simulated s per run")
    parser.add_argument("--repeats", type=int, default=None, help="runs per scenario")
    args = parser.parse_args(argv)
    profile = PROFILES[args.profile]
    if args.duration is not None:
        profile = dataclasses.replace(profile, step_duration_s=args.duration)
    if args.repeats is not None:
        profile = dataclasses.replace(profile, step_repeats=args.repeats)
    return report_section(run(profile), tables, "bench_step.py", argv, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
