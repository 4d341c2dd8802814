"""Start, supervise and stop a process swarm: one ``sim-world`` and N ``swarm-agent``s.

Every child runs in its own session (process group) and dies with the launcher (Linux
parent-death signal), its output goes to a log file, and on any way out — mission done,
a child dying, Ctrl-C or SIGTERM — every group gets SIGTERM, then SIGKILL after a grace
period, so no process and no port outlives the launcher. The launcher is a Zenoh client of
the world's router: it listens to telemetry and truth like any other consumer and builds
the run record from them.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from swarm.config import ScenarioConfig
from swarm.ground_truth import ReferenceGramians
from swarm.reference import RunRecord
from swarm.transport import (
    Keys,
    LatestValues,
    RejectionCounter,
    TransportError,
    open_session,
    subscribe,
    zenoh_config,
)
from swarm.wire import ClockWire, TelemetryWire, TruthWire, WireCodec

STOP_GRACE_S = 4.0  # SIGTERM → SIGKILL; the whole stop stays under 5 s
SUPERVISE_PERIOD_S = 0.1
LOG_TAIL_LINES = 12
PR_SET_PDEATHSIG = 1
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


class MissionError(RuntimeError):
    """The swarm could not run the mission; the message says which process and why."""


@dataclass(frozen=True)
class LaunchOptions:
    config: ScenarioConfig
    config_path: str
    seed: int
    mode: str = "lockstep"
    run_id: str = ""  # empty: a random one
    zenoh_port: int = 0  # 0: a free port
    mavlink_base: int = 0  # 0: 14540 if free, else the next free block
    log_dir: Path | None = None
    extra_agent_args: dict[int, list[str]] = field(default_factory=dict)
    mavlink_urls: dict[int, str] = field(default_factory=dict)  # e.g. through MAVProxy
    # The world serves no vehicles (--vehicles external) and a separate ``sim-vehicles``
    # process plays the autopilots, as real ones would be flown; realtime only.
    external_vehicles: bool = False


def _die_with_parent() -> None:
    """Runs in the child before exec: SIGTERM it when the launcher dies, however it dies."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def udp_ports_free(base: int, count: int, skip: frozenset[int] = frozenset()) -> bool:
    """Can UDP ports base..base+count−1 (but the offsets in ``skip``) be bound on loopback?"""
    sockets = []
    try:
        for offset in range(count):
            if offset in skip:
                continue
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sockets.append(sock)
            sock.bind(("127.0.0.1", base + offset))
        return True
    except OSError:
        return False
    finally:
        for sock in sockets:
            sock.close()


def choose_mavlink_base(requested: int, count: int,
                        skip: frozenset[int] = frozenset()) -> int:
    """The requested base if its ports are free, else (none requested) the first free block.

    ``skip``: drones whose agent listens elsewhere (e.g. behind MAVProxy, which holds base+i).
    """
    if requested:
        if not udp_ports_free(requested, count, skip):
            raise MissionError(f"UDP ports {requested}..{requested + count - 1} on 127.0.0.1 "
                                f"are in use (another swarm?); pick another --mavlink-base")
        return requested
    for base in range(14540, 60000, 100):
        if udp_ports_free(base, count):
            return base
    raise MissionError("no free block of UDP ports for the MAVLink links")


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path

    def tail(self, lines: int = LOG_TAIL_LINES) -> list[str]:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return []
        return [line for line in text.splitlines() if line.strip()][-lines:]


class TelemetryCollector:
    """Fills the run arrays from telemetry and truth messages (zenoh callback threads)."""

    def __init__(self, config: ScenarioConfig, n_state: int) -> None:
        n, m, k = config.swarm.n_drones, len(config.targets), config.n_steps
        self.config = config
        self.lock = threading.Lock()
        self.positions = np.full((k, n, 3), np.nan)
        self.targets = np.full((k, m, 3), np.nan)
        self.target_vel = np.full((k, m, 3), np.nan)
        self.velocities = np.full((k, n, 3), np.nan)
        self.estimates = np.full((k, n, m, n_state), np.nan)
        self.lambda_bar = np.full((k, n, m), np.nan)
        self.psi0 = np.full((k, n, m), np.nan)
        self.psi1 = np.full((k, n, m), np.nan)
        self.weights = np.full((k, n, m), np.nan)
        self.slacks = np.full((k, n, m), np.nan)
        self.weight_slacks = np.full((k, n, m), np.nan)
        self.detected = np.zeros((k, n, m), dtype=bool)
        self.bearing = np.full((k, n), np.nan)
        self.fallback = np.zeros((k, n), dtype=bool)
        self.step_us = np.full((k, n), np.nan)
        self.latest: dict[int, TelemetryWire] = {}
        self.telemetry_received = np.zeros(n, dtype=int)
        self.last_truth_step = -1
        self.missing_samples = 0  # truth or telemetry steps that never arrived (realtime)

    def on_telemetry(self, _key: str, tel: TelemetryWire) -> None:
        with self.lock:
            self.latest[tel.drone] = tel
            self.telemetry_received[tel.drone] += 1
            k, i = tel.step, tel.drone
            if not 0 <= k < self.velocities.shape[0]:
                return
            diag = tel.to_diagnostics()
            self.velocities[k, i] = diag.velocity
            self.estimates[k, i] = diag.estimates
            self.lambda_bar[k, i] = diag.lambda_bar
            self.psi0[k, i], self.psi1[k, i] = diag.psi0, diag.psi1
            self.weights[k, i] = diag.weights
            self.slacks[k, i], self.weight_slacks[k, i] = diag.slacks, diag.weight_slacks
            self.detected[k, i] = diag.detected
            self.fallback[k, i] = diag.qp_fallback
            self.step_us[k, i] = diag.step_us
            if diag.bearing_error is not None:
                self.bearing[k, i] = diag.bearing_error

    def on_truth(self, _key: str, truth: TruthWire) -> None:
        with self.lock:
            k = truth.step
            if not 0 <= k < self.positions.shape[0]:
                return
            arrays = truth.arrays()
            self.positions[k] = arrays["drone_positions"]
            self.targets[k] = arrays["target_positions"]
            self.target_vel[k] = arrays["target_velocities"]
            self.last_truth_step = max(self.last_truth_step, k)

    def record(self, seed: int, wall_time_s: float) -> RunRecord:
        """The run as a RunRecord.

        In realtime, publishers drop rather than queue, so a step can be missing: gaps are
        filled with the previous value (the first step with the next one); ``missing_samples``
        says how many were filled.
        """
        with self.lock:
            arrays = {name: getattr(self, name).copy() for name in (
                "positions", "targets", "target_vel", "velocities", "estimates", "lambda_bar",
                "psi0", "psi1", "weights", "slacks", "weight_slacks", "bearing", "step_us")}
            detected, fallback = self.detected.copy(), self.fallback.copy()
        steps = max(self.last_truth_step + 1, 0)
        self.missing_samples = 0
        for name, values in arrays.items():
            values = values[:steps]
            self.missing_samples += int(np.isnan(values).any(axis=tuple(range(1, values.ndim)))
                                        .sum()) if name in ("positions", "velocities") else 0
            for k in range(1, steps):
                gap = np.isnan(values[k])
                values[k][gap] = values[k - 1][gap]
            for k in range(steps - 2, -1, -1):
                gap = np.isnan(values[k])
                values[k][gap] = values[k + 1][gap]
            arrays[name] = values
        cfg = self.config
        dt = cfg.scenario.dt_s
        truth = ReferenceGramians(len(cfg.targets), cfg.gramian, cfg.perception,
                                  cfg.estimation.info_gain, dt)
        true_min = np.zeros((steps, len(cfg.targets)))
        measured_min = np.zeros_like(true_min)
        for k in range(steps):
            true_min[k], measured_min[k] = truth.lambda_min()
            truth.advance(arrays["positions"][k], arrays["targets"][k], detected[k])
        return RunRecord(
            config=cfg, seed=seed, times_s=np.arange(steps) * dt,
            drone_positions_m=arrays["positions"], velocities_m_s=arrays["velocities"],
            target_positions_m=arrays["targets"], target_velocities_m_s=arrays["target_vel"],
            estimates=arrays["estimates"], lambda_bar=arrays["lambda_bar"],
            psi0=arrays["psi0"], psi1=arrays["psi1"], weights=arrays["weights"],
            slacks=arrays["slacks"], weight_slacks=arrays["weight_slacks"],
            detected=detected[:steps], true_lambda_min=true_min,
            measured_lambda_min=measured_min, bearing_errors=arrays["bearing"],
            qp_fallback=fallback[:steps], step_us=arrays["step_us"], wall_time_s=wall_time_s)

    def counters(self) -> dict[str, int]:
        with self.lock:
            latest = [t.counters for t in self.latest.values()]
            received = int(self.telemetry_received.sum())
        return {
            "agent_steps": sum(c.steps for c in latest),  # as counted by the agents
            "telemetry_received": received,  # realtime telemetry may be dropped under load
            "late_steps": sum(c.late_steps for c in latest),
            "rejected_messages": sum(c.rejected_messages for c in latest),
            "stale_neighbour_messages": sum(c.stale_neighbour_messages for c in latest),
            "missing_neighbour_messages": sum(c.missing_neighbour_messages for c in latest),
            "qp_fallbacks": sum(c.qp_fallbacks for c in latest),
        }


ProgressCallback = Callable[[int, "TelemetryCollector"], None]


class SwarmLauncher:
    """Runs one mission with the world and every agent as separate OS processes."""

    def __init__(self, options: LaunchOptions, log: Callable[[str], None] = print) -> None:
        self.options = options
        self.log = log
        cfg = options.config
        self.n = cfg.swarm.n_drones
        self.run_id = options.run_id or f"run{secrets.token_hex(4)}"
        self.keys = Keys(self.run_id)
        self.children: list[Child] = []
        self.stop_requested = threading.Event()
        self.clock: LatestValues[ClockWire] = LatestValues()
        n_state = 6 if cfg.estimation.model == "double_integrator" else 3
        self.codec = WireCodec(self.n, len(cfg.targets), n_state)
        self.collector = TelemetryCollector(cfg, n_state)
        self.rejections = RejectionCounter()
        self._own_log_dir = options.log_dir is None  # a temp dir, removed after a clean run
        self.log_dir = options.log_dir or Path(tempfile.mkdtemp(prefix=f"vigil-{self.run_id}-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.zenoh_port = options.zenoh_port or free_tcp_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zenoh_port}"
        self.mavlink_base = choose_mavlink_base(options.mavlink_base, self.n,
                                                frozenset(options.mavlink_urls))
        self.session: zenoh.Session | None = None
        self._subscribers: list = []

    # -- children ---------------------------------------------------------------------------

    def _spawn(self, name: str, argv: list[str]) -> Child:
        log_path = self.log_dir / f"{name}.log"
        handle = log_path.open("wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # The step's matrices are 3x3..6x6: a BLAS thread pool per process only adds threads
        # that compete for the two cores. An explicit setting by the user wins.
        for variable in BLAS_THREAD_VARIABLES:
            env.setdefault(variable, "1")
        process = subprocess.Popen(
            argv, stdout=handle, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, preexec_fn=_die_with_parent, env=env)
        handle.close()
        child = Child(name, process, log_path)
        self.children.append(child)
        return child

    def _common_args(self) -> list[str]:
        opts = self.options
        return [opts.config_path, "--run-id", self.run_id, "--mode", opts.mode,
                "--seed", str(opts.seed), "--duration", repr(opts.config.scenario.duration_s)]

    def start_world(self) -> Child:
        argv = [sys.executable, "-m", "sim_world.cli", *self._common_args(),
                "--listen", self.endpoint, "--mavlink-base", str(self.mavlink_base)]
        if self.options.external_vehicles:
            argv += ["--vehicles", "external"]
        return self._spawn("world", argv)

    def start_vehicles(self) -> Child:
        argv = [sys.executable, "-m", "sim_world.vehicles_cli", self.options.config_path,
                "--seed", str(self.options.seed), "--mavlink-base", str(self.mavlink_base)]
        return self._spawn("vehicles", argv)

    def start_agent(self, drone_id: int) -> Child:
        opts = self.options
        common = self._common_args()
        url = opts.mavlink_urls.get(drone_id, f"udpin:127.0.0.1:{self.mavlink_base + drone_id}")
        argv = [sys.executable, "-m", "swarm.agent_cli", "--id", str(drone_id),
                "--config", common[0], *common[1:], "--connect", self.endpoint,
                "--mavlink", url, *opts.extra_agent_args.get(drone_id, [])]
        return self._spawn(f"agent{drone_id}", argv)

    def stop_children(self) -> None:
        """SIGTERM every process group, SIGKILL what is left after the grace period."""
        for child in self.children:
            if child.process.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(child.process.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for child in self.children:
            remaining = deadline - time.monotonic()
            try:
                child.process.wait(timeout=max(remaining, 0.01))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(child.process.pid, signal.SIGKILL)
                child.process.wait()
        # Grandchildren (if a child spawned any) share its group: sweep the groups once more.
        for child in self.children:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(child.process.pid, signal.SIGKILL)

    def _dead_child(self) -> Child | None:
        """A child that ended before the mission did, or ended badly after it."""
        done = self._mission_state() == "done"
        for child in self.children:
            code = child.process.poll()
            if code is not None and not (done and code == 0):
                return child
        return None

    def _failure(self, child: Child) -> MissionError:
        code = child.process.returncode
        how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        tail = "\n    ".join(child.tail())
        return MissionError(f"{child.name} (pid {child.process.pid}) ended with {how}; last "
                             f"lines of {child.log_path}:\n    {tail}")

    # -- zenoh --------------------------------------------------------------------------------

    def _connect(self, timeout_s: float) -> None:
        """Join the world's router as a client, retrying while the world starts up."""
        deadline = time.monotonic() + timeout_s
        while True:
            for child in self.children:
                if child.process.poll() is not None:
                    raise self._failure(child)
            try:
                self.session = open_session(zenoh_config(mode="client", connect=[self.endpoint]))
                break
            except TransportError as err:
                if time.monotonic() > deadline:
                    raise MissionError(f"cannot reach the world's Zenoh router at "
                                        f"{self.endpoint}: {err}") from None
                self.stop_requested.wait(0.1)
        session = self.session
        keys = self.keys
        self._subscribers = [
            subscribe(session, keys.all_telemetry, self.codec.decode_telemetry,
                      self.collector.on_telemetry, self.rejections, "telemetry"),
            subscribe(session, keys.truth, self.codec.decode_truth, self.collector.on_truth,
                      self.rejections, "truth"),
            subscribe(session, keys.clock, self.codec.decode_clock,
                      lambda _k, c: self.clock.put(0, c), self.rejections, "clock"),
        ]

    def _mission_state(self) -> str:
        latest = self.clock.get(0)
        return "starting" if latest is None else latest[0].state

    # -- the mission -------------------------------------------------------------------------

    def run(self, on_progress: ProgressCallback | None = None) -> RunRecord:
        """Run the mission to its end; MissionError if a process dies or the world aborts."""
        cfg = self.options.config
        started = time.monotonic()
        try:
            self.log(f"launch-swarm: run {self.run_id}: world + {self.n} agents "
                     f"({self.options.mode}), zenoh {self.endpoint}, MAVLink "
                     f"{self.mavlink_base}..{self.mavlink_base + self.n - 1}, logs {self.log_dir}")
            if self.options.external_vehicles:
                if self.options.mode != "realtime":
                    raise MissionError("external vehicles need --mode realtime")
                self.start_vehicles()
            self.start_world()
            self._connect(timeout_s=30.0)
            for i in range(self.n):
                self.start_agent(i)
            announced = False
            last_progress = -1
            while True:
                if self.stop_requested.wait(SUPERVISE_PERIOD_S):
                    raise KeyboardInterrupt
                dead = self._dead_child()
                if dead is not None:
                    raise self._failure(dead)
                state = self._mission_state()
                if state == "running" and not announced:
                    announced = True
                    self.log(f"launch-swarm: every drone armed and streaming after "
                             f"{time.monotonic() - started:.1f} s; mission running")
                if state == "aborted":
                    latest = self.clock.get(0)
                    raise MissionError(f"the world aborted the mission: {latest[0].detail}")
                if state == "waiting" and time.monotonic() - started > (
                        cfg.runtime.start_timeout_s + 10.0):
                    raise MissionError("the mission never started")
                step = self.collector.last_truth_step
                if on_progress is not None and step != last_progress:
                    last_progress = step
                    on_progress(step, self.collector)
                if state == "done":
                    break
            self._wait_agents_done()
            record = self.collector.record(self.options.seed, time.monotonic() - started)
            self.close()
            if self._own_log_dir:
                shutil.rmtree(self.log_dir, ignore_errors=True)
            return record
        finally:
            self.close()

    def _wait_agents_done(self) -> None:
        deadline = time.monotonic() + 5.0
        for child in (c for c in self.children if c.name.startswith("agent")):
            try:
                child.process.wait(timeout=max(deadline - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                break

    def close(self) -> None:
        """Leave Zenoh and stop every child; safe to call more than once."""
        for sub in self._subscribers:
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subscribers = []
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None
        self.stop_children()
