"""One instrumented process-swarm run (``SwarmLauncher``) for the swarm benchmarks.

Besides the launcher's own record and counters, a run measures, from outside the swarm:

- the world's clock: every ``world/clock`` message the launcher receives, timestamped on
  arrival (the launcher's ``clock`` store is wrapped), gives the mission window — from the
  first "running" message (step 0 published) to "done" (every step integrated) — and the
  wall time between consecutive steps;
- the processes: a sampler thread reads ``/proc/<pid>/stat`` (utime + stime) and
  ``/proc/<pid>/status`` (VmRSS, VmHWM) of every child the launcher spawned, every
  ``SAMPLE_PERIOD_S`` (at the window's opening, ``SECOND_SAMPLE_S`` later, and at its close);
  CPU per process is its CPU time over the mission window divided by the window;
- start-up: each child's start time (``/proc/<pid>/stat`` starttime) and the arrival of each
  line in its log file (polled every ``LOG_PERIOD_S`` until the mission runs, then every
  ``SAMPLE_PERIOD_S`` / 2: the world can see a drone armed before its log says so), so an
  agent's start-up splits into process start → set up (imports, config, Zenoh session, MAVLink
  socket; its "waiting for HEARTBEAT" line) → HEARTBEAT → first setpoints → armed and
  streaming (``AGENT_PHASES``); launch → every drone streaming is the first "running" clock
  message after ``SwarmLauncher.run`` was called;
- telemetry: every agent's ``step_us``, ``counters.neighbour_age_ms`` (realtime: age of
  the freshest neighbour message when used, from the neighbour's put) and its
  running late/step counters.

A mission the launcher reports as failed keeps its figures when the failure is an agent
that ended normally (exit 0) before the launcher heard the world's "done" (``usable``).

Timestamps are CLOCK_BOOTTIME seconds, the clock of ``/proc``'s start times.
"""

from __future__ import annotations

import itertools
import os
import random
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common import SectionClock, load_average, progress, stats
from swarm_configs import load_scaled

from swarm.launch.launcher import Child, LaunchOptions, MissionError, SwarmLauncher, udp_ports_free
from swarm.messages.wire import ClockWire, TelemetryWire
from swarm.runs.checks import check_invariants, summarize_targets

CLK_TCK = os.sysconf("SC_CLK_TCK")
SAMPLE_PERIOD_S = 0.2
SECOND_SAMPLE_S = 0.05  # after the window's first sample, the next one [s]
PSS_PERIOD_S = 2.0
LOG_PERIOD_S = 0.02
# Agent log lines that mark its start-up phases (first match): set up (imports, config,
# Zenoh session, MAVLink socket) and waiting for the autopilot, HEARTBEAT received, first
# setpoints streamed (PX4), armed and streaming.
AGENT_PHASES = {"setup_done": re.compile(r"waiting for HEARTBEAT"),
                "heartbeat": re.compile(r": HEARTBEAT from"),
                "first_setpoint": re.compile(r"streaming zero setpoints"),
                "ready": re.compile(r"armed and streaming")}
LAUNCHER_STREAMING = re.compile(r"armed and streaming after ([0-9.]+) s")
AGENT_DONE_FIRST = re.compile(r"^agent\d+ \(pid \d+\) ended with exit code 0;")


def now_s() -> float:
    return time.clock_gettime(time.CLOCK_BOOTTIME)


def free_udp_block(count: int) -> int:
    """A base port p with UDP p..p+count−1 free on 127.0.0.1, drawn at random below Linux's
    ephemeral range: other swarms on the machine take the default block (14540) first, and
    one that binds it between the launcher's check and its agents' bind ends a run."""
    rng = random.SystemRandom()
    for _ in range(500):
        base = rng.randrange(20000, 32768 - count)
        if udp_ports_free(base, count):
            return base
    raise MissionError("no free block of UDP ports on 127.0.0.1")


def read_proc(pid: int) -> tuple[float, float, float] | None:
    """(CPU seconds, VmRSS MiB, VmHWM MiB) of a live process, None once it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    cpu_s = (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime, stime (fields 14, 15)
    memory = {}
    for line in status.splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            key, value = line.split(":", 1)
            memory[key] = int(value.split()[0]) / 1024.0
    if "VmRSS" not in memory:  # a zombie has no memory lines
        return None
    return cpu_s, memory["VmRSS"], memory.get("VmHWM", memory["VmRSS"])


THREAD_GROUPS = ("python", "zenoh_rx", "zenoh_other")


def read_thread_cpu(pid: int) -> tuple[float, float, float] | None:
    """CPU seconds of a live process by thread group: the Python main thread (tid = pid),
    Zenoh's receive threads (which also run our direct subscription callbacks: decoding and
    validation): "app-*", where ``session.ZENOH_RUNTIME_DEFAULT`` hands receiving over, or
    "rx-*" with zenoh's own defaults; and every other thread (Zenoh's transmit thread, Python
    callback threads; pymavlink has none). None once it is gone. Threads that ended earlier
    are not counted."""
    groups = [0.0, 0.0, 0.0]
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    for tid in tids:
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat.rsplit(")", 1)[1].split()
        cpu_s = (int(fields[11]) + int(fields[12])) / CLK_TCK
        group = 0 if tid == str(pid) else 1 if name.startswith(("rx-", "app-")) else 2
        groups[group] += cpu_s
    return groups[0], groups[1], groups[2]


def read_pss_mib(pid: int) -> float | None:
    """Proportional set size [MiB]: private pages plus a share of the shared ones (the
    libraries every agent maps), from /proc/<pid>/smaps_rollup."""
    try:
        text = Path(f"/proc/{pid}/smaps_rollup").read_text()
    except OSError:
        return None
    match = re.search(r"^Pss:\s+(\d+) kB", text, re.MULTILINE)
    return int(match.group(1)) / 1024.0 if match else None


def process_start_s(pid: int) -> float | None:
    """The process's start time on CLOCK_BOOTTIME [s] (10 ms resolution)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return int(fields[19]) / CLK_TCK  # starttime (field 22)


class ClockTap:
    """Stands in for the launcher's ``clock`` store: passes every call through and keeps
    (arrival time, step, state) of each clock message."""

    def __init__(self, inner: Any) -> None:
        self._inner = inner
        self.events: list[tuple[float, int, str]] = []
        # Set when the state changes (the mission's window opens or closes): the sampler
        # samples every child at once, before a fast swarm's processes have ended.
        self.state_changed = threading.Event()

    def put(self, source: Any, value: ClockWire, *args: Any, **kwargs: Any) -> Any:
        if not self.events or self.events[-1][2] != value.state:
            self.state_changed.set()
        self.events.append((now_s(), value.step, value.state))
        return self._inner.put(source, value, *args, **kwargs)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


@dataclass
class ChildTrace:
    """What the sampler saw of one child process."""

    name: str
    pid: int
    start_s: float | None
    cpu: list[tuple[float, float]] = field(default_factory=list)  # (t, CPU s)
    # (t, (python, zenoh_rx, zenoh_other) CPU s), see read_thread_cpu
    thread_cpu: list[tuple[float, tuple[float, float, float]]] = field(default_factory=list)
    rss_mb: list[float] = field(default_factory=list)  # [MiB]
    hwm_mb: float = 0.0  # [MiB]
    pss_mb: float | None = None  # newest [MiB]
    log_lines: list[tuple[float, str]] = field(default_factory=list)
    _log_offset: int = 0
    _log_rest: str = ""


class Sampler(threading.Thread):
    """Polls the launcher's children (CPU, memory, new log lines) until stopped."""

    def __init__(self, launcher: SwarmLauncher, mission_running: Callable[[], bool],
                 wake: threading.Event | None = None) -> None:
        super().__init__(name="swarm-probe", daemon=True)
        self.launcher = launcher
        self.mission_running = mission_running
        self.traces: dict[int, ChildTrace] = {}
        self.halt = threading.Event()
        # Set by whoever sees the mission's window open or close (``ClockTap``): sample now.
        self.wake = wake if wake is not None else threading.Event()
        self._next_pss = 0.0

    def run(self) -> None:
        next_sample = 0.0
        was_running = just_opened = False
        while not self.halt.is_set():
            t = now_s()
            children = list(self.launcher.children)
            running = self.mission_running()
            if running != was_running:  # the mission's window opens or closes: sample now
                was_running, next_sample, just_opened = running, t, running
            for child in children:  # every loop: a line's time is when it was first seen
                self._read_log(child, self._trace(child), t)
            if t >= next_sample:
                # The sample after the window's first comes soon: a window shorter than the
                # period still holds two samples of every process (the processes may be gone
                # by the sample at its close).
                next_sample = t + (SECOND_SAMPLE_S if just_opened else SAMPLE_PERIOD_S)
                just_opened = False
                with_pss = t >= self._next_pss
                if with_pss:
                    self._next_pss = t + PSS_PERIOD_S
                for child in children:
                    self._sample(self._trace(child), t, with_pss)
            self.wake.wait(LOG_PERIOD_S if not running
                           else min(SAMPLE_PERIOD_S / 2, max(0.0, next_sample - now_s())))
            self.wake.clear()

    def stop(self) -> None:
        self.halt.set()
        self.wake.set()

    def _trace(self, child: Child) -> ChildTrace:
        pid = child.process.pid
        trace = self.traces.get(pid)
        if trace is None:
            trace = self.traces[pid] = ChildTrace(child.name, pid, process_start_s(pid))
        return trace

    @staticmethod
    def _sample(trace: ChildTrace, t: float, with_pss: bool) -> None:
        reading = read_proc(trace.pid)
        if reading is None:
            return
        cpu_s, rss_mb, hwm_mb = reading
        trace.cpu.append((t, cpu_s))
        threads = read_thread_cpu(trace.pid)
        if threads is not None:
            trace.thread_cpu.append((t, threads))
        trace.rss_mb.append(rss_mb)
        trace.hwm_mb = max(trace.hwm_mb, hwm_mb)
        if with_pss:  # 0.5 ms a read: not at every sample
            trace.pss_mb = read_pss_mib(trace.pid) or trace.pss_mb

    @staticmethod
    def _read_log(child: Child, trace: ChildTrace, t: float) -> None:
        try:
            with child.log_path.open("rb") as handle:
                handle.seek(trace._log_offset)
                chunk = handle.read()
        except OSError:
            return
        if not chunk:
            return
        trace._log_offset += len(chunk)
        text = trace._log_rest + chunk.decode(errors="replace")
        *lines, trace._log_rest = text.split("\n")
        trace.log_lines += [(t, line) for line in lines if line.strip()]


def _window_samples(samples: list, start: float, end: float) -> tuple | None:
    """The first and last sample inside [start, end]; for a window shorter than the sampling
    period (a short run on a fast machine), the samples just around it instead; None
    without two distinct samples."""
    inside = [sample for sample in samples if start <= sample[0] <= end]
    if len(inside) >= 2 and inside[-1][0] > inside[0][0]:
        return inside[0], inside[-1]
    before = [sample for sample in samples if sample[0] <= start]
    after = [sample for sample in samples if sample[0] >= end]
    if before and after and after[0][0] > before[-1][0]:
        return before[-1], after[0]
    return None


def _cpu_share(trace: ChildTrace, start: float, end: float) -> float | None:
    """The process's CPU time over [start, end] / (end − start), from the samples nearest
    inside the window (``_window_samples``); None without two samples."""
    pair = _window_samples(trace.cpu, start, end)
    if pair is None:
        return None
    (t0, c0), (t1, c1) = pair
    return (c1 - c0) / (t1 - t0)


def _thread_shares(trace: ChildTrace, start: float, end: float) -> dict[str, float] | None:
    """``_cpu_share`` by thread group (cores), None without two samples."""
    pair = _window_samples(trace.thread_cpu, start, end)
    if pair is None:
        return None
    (t0, c0), (t1, c1) = pair
    return {group: (b - a) / (t1 - t0)
            for group, a, b in zip(THREAD_GROUPS, c0, c1, strict=True)}


def _phase_times(trace: ChildTrace) -> dict[str, float | None]:
    """Seconds from the child's start to each phase line of its log (None: not seen)."""
    base = trace.start_s
    out: dict[str, float | None] = dict.fromkeys(AGENT_PHASES)
    if base is None:
        return out
    for phase, marker in AGENT_PHASES.items():
        hit = next((t for t, line in trace.log_lines if marker.search(line)), None)
        out[phase] = None if hit is None else hit - base
    return out


def _cpu_until(trace: ChildTrace, t: float | None) -> float | None:
    """The process's CPU time [s] at its last sample before ``t`` (None: no sample)."""
    if t is None:
        return None
    before = [c for ts, c in trace.cpu if ts <= t]
    return before[-1] if before else None


def _late_after(telemetry: list[tuple[int, int, float, float | None, int, int]],
                skip_steps: int) -> float | None:
    """Late-step rate of the agents after each one's first ``skip_steps`` steps (the
    start-up transient), from the running counters in their telemetry."""
    first: dict[int, tuple[int, int]] = {}
    last: dict[int, tuple[int, int]] = {}
    for drone, _k, _us, _age, late, steps in telemetry:
        if steps >= skip_steps and (drone not in first or steps < first[drone][1]):
            first[drone] = (late, steps)
        if drone not in last or steps > last[drone][1]:
            last[drone] = (late, steps)
    late = sum(last[d][0] - first[d][0] for d in first)
    steps = sum(last[d][1] - first[d][1] for d in first)
    return late / steps if steps > 0 else None


def attempt_swarm(config_path: Path, config: Any, mode: str, **kwargs: Any) -> dict[str, Any]:
    """``run_swarm``, or {"error": ...} when the mission fails (a failed run is reported
    with the others, not allowed to end the benchmark)."""
    n = config.swarm.n_drones
    progress(f"{mode} swarm, N = {n}, {config.scenario.duration_s:g} s simulated")
    try:
        result = run_swarm(config_path, config, mode, **kwargs)
    except (MissionError, OSError) as err:
        result = {"n_drones": n, "mode": mode, "error": str(err), "usable": False}
    if "error" in result:
        kept = "figures kept" if result["usable"] else "no figures"
        progress(f"{mode} swarm, N = {n}: failed ({kept}): {result['error'].splitlines()[0]}")
    return result


def run_swarm(config_path: Path, config: Any, mode: str, *, seed: int = 0,
              check: bool = True) -> dict[str, Any]:
    """One mission of the process swarm with everything measured (see the module doc)."""
    launcher_lines: list[tuple[float, str]] = []
    launcher = SwarmLauncher(
        LaunchOptions(config=config, config_path=str(config_path), seed=seed, mode=mode,
                      mavlink_base=free_udp_block(config.swarm.n_drones)),
        log=lambda line: launcher_lines.append((now_s(), line)))
    tap = ClockTap(launcher.clock)
    launcher.clock = tap  # type: ignore[assignment]
    # (drone, step, step_us, neighbour age ms, late steps so far, steps so far)
    telemetry: list[tuple[int, int, float, float | None, int, int]] = []

    def on_telemetry(tel: TelemetryWire) -> None:
        c = tel.counters
        telemetry.append((tel.drone, tel.step, tel.step_us, c.neighbour_age_ms, c.late_steps,
                          c.steps))

    sampler = Sampler(launcher, lambda: any(s == "running" for _t, _k, s in tap.events[-1:]),
                      wake=tap.state_changed)
    load_before = load_average()
    launched = now_s()
    sampler.start()
    record, error = None, None
    try:
        record = launcher.run(telemetry_listeners=[on_telemetry])
    except MissionError as err:
        error = str(err)
    finally:
        sampler.stop()
        sampler.join()
    result = _summarise(config, mode, launcher, tap, sampler, telemetry, launcher_lines,
                        launched)
    result["load_before"], result["load_after"] = load_before, load_average()
    if error is not None:
        result["error"] = error
        # An agent that ended its mission normally (exit 0) before the launcher heard the
        # world's "done" makes the launcher report a failure; the figures are still whole.
        result["usable"] = AGENT_DONE_FIRST.search(error) is not None
    if check and record is not None:
        result["violations"] = [str(v) for v in check_invariants(record)]
        result["final_position_error_m"] = [t.final_position_error_m
                                            for t in summarize_targets(record)]
        # Agent steps that measured some target: how many camera frames the agents used.
        result["measured_steps"] = int(record.detected.any(axis=2).sum())
    return result


def _summarise(config: Any, mode: str, launcher: SwarmLauncher, tap: ClockTap,
               sampler: Sampler, telemetry: list[tuple[int, int, float, float | None, int, int]],
               launcher_lines: list[tuple[float, str]], launched: float) -> dict[str, Any]:
    n_steps, dt = config.n_steps, config.scenario.dt_s
    running = [(t, k) for t, k, s in tap.events if s == "running"]
    done = next((t for t, _k, s in tap.events if s == "done"), None)
    start = running[0][0] if running else None
    steps = n_steps
    if done is None and len(running) > 1:  # a run cut short: up to the last step heard
        done, steps = running[-1][0], running[-1][1] - running[0][1]
    window = (done - start) if start is not None and done is not None else None
    # Wall time per step from the clock messages (one per step in both modes).
    periods_ms = [1e3 * (b[0] - a[0]) / (b[1] - a[1]) for a, b in itertools.pairwise(running)
                  if b[1] > a[1]]
    traces = list(sampler.traces.values())
    agents = [tr for tr in traces if tr.name.startswith("agent")]
    world = next((tr for tr in traces if tr.name == "world"), None)
    cpu_agents = ([_cpu_share(tr, start, done) for tr in agents]
                  if window else [])
    reported = next((float(m.group(1)) for _t, line in launcher_lines
                     if (m := LAUNCHER_STREAMING.search(line))), None)
    phases = {tr.name: _phase_times(tr) for tr in agents}
    counters = launcher.collector.counters()
    return {
        "n_drones": config.swarm.n_drones, "mode": mode, "duration_s": config.scenario.duration_s,
        "n_steps": n_steps,
        "mission": {
            "wall_s": window,
            "steps": steps,
            "sim_steps_per_s": steps / window if window else None,
            "real_time_factor": steps * dt / window if window else None,
            "step_period_ms": stats(periods_ms),
        },
        "startup": {
            "launch_to_streaming_s": (start - launched) if start is not None else None,
            "launcher_reported_s": reported,
            "agent_spawn_after_launch_s": stats(
                [tr.start_s - launched for tr in agents if tr.start_s is not None]),
            "agent_phases_s": {phase: stats([p[phase] for p in phases.values()])
                               for phase in AGENT_PHASES},
            # From the launch to each agent's first setpoints, i.e. its spawn time included.
            "first_setpoint_after_launch_s": stats(
                [tr.start_s + phases[tr.name]["first_setpoint"] - launched for tr in agents
                 if tr.start_s is not None and phases[tr.name]["first_setpoint"] is not None]),
            # CPU an agent used until armed and streaming (start-up CPU-bound or waiting?).
            "agent_cpu_until_ready_s": stats(
                [_cpu_until(tr, tr.start_s + phases[tr.name]["ready"]) for tr in agents
                 if tr.start_s is not None and phases[tr.name]["ready"] is not None]),
            "world_cpu_until_running_s": (_cpu_until(world, start)
                                          if world is not None else None),
            "per_agent_s": phases,
        },
        "cpu": {
            "agent_cores": stats(cpu_agents),
            # Where an agent's (the world's) CPU goes, by thread group: cores, median over
            # the agents of each group.
            "agent_thread_cores": {
                group: stats([shares[group] for tr in agents
                              if (shares := _thread_shares(tr, start, done)) is not None])
                for group in THREAD_GROUPS} if window else None,
            "world_thread_cores": (_thread_shares(world, start, done)
                                   if world is not None and window else None),
            "world_cores": _cpu_share(world, start, done) if world and window else None,
            "total_cores": (sum(c for c in cpu_agents if c is not None)
                            + (_cpu_share(world, start, done) or 0.0)) if window else None,
        },
        "memory_mib": {
            "agent_hwm": stats([tr.hwm_mb for tr in agents if tr.hwm_mb]),
            "agent_rss": stats([max(tr.rss_mb) for tr in agents if tr.rss_mb]),
            "agent_pss": stats([tr.pss_mb for tr in agents if tr.pss_mb is not None]),
            "world_hwm": world.hwm_mb if world else None,
        },
        "counters": counters,
        "late_fraction": counters["late_steps"] / max(counters["agent_steps"], 1),
        "late_fraction_after_1s": _late_after(telemetry, round(1.0 / dt)),
        # Steps with the barrier QP active, as in the step benchmark.
        "step_us": stats([us for _i, k, us, _age, _l, _s in telemetry
                          if k * dt >= config.control.start_s]),
        "neighbour_age_ms": stats([age for _i, _k, _us, age, _l, _s in telemetry
                                   if age is not None]),
        "telemetry_messages": len(telemetry),
    }


def swarm_section(section: str, profile_name: str, sizes: Sequence[int], mode: str,
                  duration_s: float, repeats: int,
                  summarise: Callable[[list[dict[str, Any]]], dict[str, Any]]
                  ) -> dict[str, Any]:
    """``repeats`` process swarms of Case 2 scaled to each N in ``sizes`` (``swarm_configs``)
    in ``mode``, ``duration_s`` simulated each: every run's figures and their summary."""
    clock = SectionClock()
    results = []
    for n in sizes:
        path, config = load_scaled(n)
        config = config.with_duration(duration_s)
        runs = [attempt_swarm(path, config, mode) for _ in range(repeats)]
        results.append({"n_drones": n, "config": str(path), "runs": runs,
                        "summary": summarise(runs)})
    return {"section": section, "profile": profile_name, "duration_s": duration_s,
            "repeats": repeats, "results": results, **clock.done()}
