"""Start, supervise and stop a process swarm: one ``sim-world`` and N ``swarm-agent``s.

Every child runs in its own session (process group) and dies with the launcher (Linux
parent-death signal), its output goes to a log file, and on any way out — mission done,
a child dying, Ctrl-C or SIGTERM — every group gets SIGTERM, then SIGKILL after a grace
period, so no process and no port outlives the launcher. The launcher is a Zenoh client of
the world's router: it listens to telemetry and truth like any other consumer and builds
the run record from them (``swarm.observe.collector``); with ``record_dir`` it also records them,
with every beacon and camera frame, to an MCAP file as the run goes (``swarm.observe.recording``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import secrets
import select
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, ClassVar, TypedDict

import numpy as np

from swarm.children import child_environment
from swarm.errors import EXIT_END_MISSION, UsageError, VigilError
from swarm.mavlink.link import EndReport, autopilot_mode_name, end_mode_name
from swarm.mavlink.sitl import (
    DEFAULT_BOOT_SPEEDUP,
    Firmware,
    SitlError,
    SitlFleet,
    VehicleView,
    try_exclusive_lock,
)
from swarm.models import frames
from swarm.models.frames import GeoPoint
from swarm.net.session import TransportError, local_endpoint
from swarm.observe.collector import TelemetryCollector
from swarm.observe.live_view import LiveViewError
from swarm.observe.recording.schema import AutopilotState, RecordingError, RecordingMetadata
from swarm.observe.run_observer import RunObserver, TelemetryListener
from swarm.runs.record import RunRecord
from swarm.scenario.cli_common import DEFAULT_MAVLINK_BASE
from swarm.scenario.config import ScenarioConfig, realtime_only_reason, write_resolved_config
from swarm.scenario.setup import initial_drone_positions

# Listen this long for datagrams before taking a block of MAVLink ports: PX4 SITL streams its
# offboard link at tens of messages a second, ArduPilot at least a 1 Hz heartbeat (agents also
# refuse a second autopilot on their port, see swarm.mavlink.link).
TRAFFIC_LISTEN_S = 0.3
STOP_GRACE_S = 4.0  # SIGTERM → SIGKILL; the whole stop stays under 5 s
AGENT_END_GRACE_S = 1.5  # agents stop first (their end action), then the world (within the above)
CLEAN_EXIT_GRACE_S = 2.0  # a child's exit 0 waits this long for the world's "done" to arrive
SUPERVISE_PERIOD_S = 0.1
LOG_TAIL_LINES = 12
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


class MissionError(VigilError, RuntimeError):
    """The swarm could not run the mission; the message says which process and why."""

    label: ClassVar[str] = "mission failed: "


class LaunchOptionsError(UsageError, ValueError):
    """Launch options that cannot be used together (the command line's, and the config's)."""


@dataclass(frozen=True)
class LaunchOptions:
    config: ScenarioConfig
    config_path: str
    seed: int
    mode: str = "lockstep"
    run_id: str = ""  # empty: a random one
    zenoh_port: int = 0  # 0: a free port
    mavlink_base: int = 0  # 0: DEFAULT_MAVLINK_BASE if free and quiet, else the next such block
    # Each process's log goes to log_dir (kept); None: a temporary directory, removed if the run
    # succeeds: run() decides (success: it returned, no agent lost, the recording whole), or,
    # with defer_log_cleanup, the caller does (finish_log_dir; launch-swarm, which knows the
    # verdict). A failed run keeps it and says so.
    log_dir: Path | None = None
    defer_log_cleanup: bool = False
    extra_agent_args: dict[int, list[str]] = field(default_factory=dict)
    mavlink_urls: dict[int, str] = field(default_factory=dict)  # e.g. through MAVProxy
    # The world serves no vehicles (--vehicles external) and a separate ``sim-vehicles``
    # process plays the autopilots, as real ones would be flown; realtime only.
    external_vehicles: bool = False
    # Real autopilot firmware: one SITL instance of this build per drone (swarm.mavlink.sitl),
    # started, brought up, flown by the agents and stopped by the launcher; realtime only.
    sitl: Firmware | None = None
    sitl_boot_speedup: float = DEFAULT_BOOT_SPEEDUP
    sitl_params: tuple[tuple[str, float], ...] = ()  # --sitl-param: set at boot on every one
    # Every emulated vehicle also streams to a ground station at this (host, port)
    # (sim_world.gcs_link); with gcs_control the ground station may command them.
    gcs: tuple[str, int] | None = None
    gcs_control: bool = False
    # Serve the live 3D view for Foxglove at this (host, port) (swarm.observe.live_view).
    foxglove: tuple[str, int] | None = None
    # Record telemetry, beacons, detections and truth to record_dir/run.mcap
    # (swarm.observe.recording).
    record_dir: Path | None = None
    # Realtime: an agent that dies during the mission is restarted with the same id (it
    # rejoins the swarm) this many times at most, each restart this long after the loss.
    agent_restarts: int = 0
    agent_restart_delay_s: float = 2.0
    # Fault injection (realtime): (drone, t) = SIGKILL that drone's agent when the mission
    # clock reaches t [s], as if its companion computer died (``--kill-agent``).
    kill_agents: tuple[tuple[int, float], ...] = ()

    def __post_init__(self) -> None:
        if self.agent_restarts < 0 or not self.agent_restart_delay_s >= 0:
            raise LaunchOptionsError("agent_restarts and agent_restart_delay_s must be >= 0")
        reason = realtime_only_reason(
            self.config.vehicles, mode=self.mode,
            external=(self.sitl is not None or self.external_vehicles
                      or bool(self.config.vehicles.mavlink_urls)),
            restarts_agents=bool(self.agent_restarts), kills_agents=bool(self.kill_agents))
        if reason is not None:
            raise LaunchOptionsError(reason)
        for drone, time_s in self.kill_agents:
            if not 0 <= drone < self.config.swarm.n_drones:
                raise LaunchOptionsError(f"--kill-agent {drone}@{time_s:g}: no drone {drone} "
                                         f"(the swarm has 0..{self.config.swarm.n_drones - 1})")
            if not (math.isfinite(time_s) and 0 < time_s < self.config.scenario.duration_s):
                raise LaunchOptionsError(f"--kill-agent {drone}@{time_s:g}: the time must be "
                                         f"within the mission (0, "
                                         f"{self.config.scenario.duration_s:g}) s")
        if len({drone for drone, _ in self.kill_agents}) < len(self.kill_agents):
            raise LaunchOptionsError("--kill-agent: one kill per drone")
        if self.sitl is not None and self.config.vehicles.mavlink_urls:
            raise LaunchOptionsError("--sitl starts its own autopilots: leave "
                                     "vehicles.mavlink_urls empty (or drop --sitl to fly "
                                     "those)")


class _Placement(TypedDict, total=False):
    """``subprocess.Popen``'s scheduling arguments of a child (``_placement``)."""

    process_group: int
    start_new_session: bool


def _placement(drone: int | None) -> _Placement:
    """Where a child is scheduled: every child leads a process group of its own (stopped as
    one); the world and sim-vehicles also get a session of their own, agents share the
    launcher's.

    Linux (autogroup) shares the CPU between sessions first, then between the threads in
    each. On one host the world is the physics, the cameras and the mission clock: in a
    session of its own it gets a share whatever the number of agents. With a session per
    agent it got 1/(N + 1) of the CPU under load (Case 2 realtime at N = 24 on 2 cores: a
    10 s mission ran for minutes, or never ended; now 20 s take 74 s: the launcher, which
    records, shares the agents' session). Niceness is no substitute: agents at nice 10 reached
    their steps late (N = 6: 11-29 % late steps against ~1 % at equal niceness). On separate
    computers per drone, as flown, none of this applies.
    """
    return {"process_group": 0} if drone is not None else {"start_new_session": True}


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def udp_ports_free(base: int, count: int, skip: frozenset[int] = frozenset(), *,
                   listen_s: float = 0.0) -> bool:
    """Can UDP ports base..base+count−1 (but the offsets in ``skip``) be bound on loopback,
    and (``listen_s`` > 0) does nothing arrive on them for that long? An autopilot SITL sends
    to its port without binding it (PX4 to 14540 + i), so a free port may still be taken."""
    sockets = []
    try:
        for offset in range(count):
            if offset in skip:
                continue
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sockets.append(sock)
            sock.bind(("127.0.0.1", base + offset))
        if listen_s > 0 and sockets:
            readable, _, _ = select.select(sockets, [], [], listen_s)
            return not readable
        return True
    except OSError:
        return False
    finally:
        for sock in sockets:
            sock.close()


def _candidate_bases(count: int) -> range:
    return range(DEFAULT_MAVLINK_BASE, 32768 - count, 100)


def choose_mavlink_base(requested: int, count: int,
                        skip: frozenset[int] = frozenset()) -> int:
    """The requested base if its ports are free and quiet, else (none requested) the first
    free, quiet block from DEFAULT_MAVLINK_BASE on.

    ``skip``: drones whose agent listens elsewhere (e.g. behind MAVProxy, which holds base+i).
    """
    if requested:
        if not udp_ports_free(requested, count, skip):
            raise MissionError(f"UDP ports {requested}..{requested + count - 1} on 127.0.0.1 "
                               f"are in use (another swarm?); pick another --mavlink-base")
        if not udp_ports_free(requested, count, skip, listen_s=TRAFFIC_LISTEN_S):
            raise MissionError(f"UDP ports {requested}..{requested + count - 1} on 127.0.0.1 "
                               f"receive traffic from another program (an autopilot SITL "
                               f"sending there?); pick another --mavlink-base")
        return requested
    for base in _candidate_bases(count):
        if udp_ports_free(base, count, listen_s=TRAFFIC_LISTEN_S):
            return base
    raise MissionError("no free block of UDP ports for the MAVLink links")


def mavlink_lock_path(base: int) -> Path:
    """The file a launcher holds locked while it uses the MAVLink block from ``base``."""
    return Path(tempfile.gettempdir()) / f"vigil-mavlink-{base}.lock"


def reserve_mavlink_base(requested: int, count: int, skip: frozenset[int] = frozenset()
                         ) -> tuple[int, IO[bytes]]:
    """``choose_mavlink_base``, plus an exclusive lock on the block until the returned file
    is closed (the kernel drops it if this process dies).

    The world and agents bind the ports only later, so two launchers started together would
    both see the same block free: the lock (``<tmp>/vigil-mavlink-<base>.lock``) makes the
    second one take the next block, or fail at once if that base was requested. A block that
    receives datagrams (``TRAFFIC_LISTEN_S``) is passed over: something sends there.
    """
    base = requested
    candidates = [requested] if requested else _candidate_bases(count)
    for base in candidates:
        if not requested and not udp_ports_free(base, count):
            continue
        handle = try_exclusive_lock(mavlink_lock_path(base))
        if handle is None:
            if requested:
                raise MissionError(f"UDP ports {base}..{base + count - 1} are reserved by "
                                   f"another launch-swarm; pick another --mavlink-base")
            continue
        if not requested:
            if udp_ports_free(base, count, listen_s=TRAFFIC_LISTEN_S):
                return base, handle
            handle.close()
            continue
        try:
            return choose_mavlink_base(requested, count, skip), handle
        except MissionError:
            handle.close()
            raise
    raise MissionError("no free block of UDP ports for the MAVLink links")


@dataclass
class Child:
    name: str
    process: subprocess.Popen
    log_path: Path
    drone: int | None = None  # the drone an agent flies
    lost: bool = False  # an agent that died during a realtime mission, already reported

    def tail(self, lines: int = LOG_TAIL_LINES) -> list[str]:
        try:
            text = self.log_path.read_text(errors="replace")
        except OSError:
            return []
        return [line for line in text.splitlines() if line.strip()][-lines:]


@dataclass(frozen=True)
class AgentLoss:
    """An agent process that died during a realtime mission (the mission went on)."""

    drone: int
    time_s: float  # mission time when the launcher noticed
    how: str  # "signal 9", "exit code 1"
    restarted: bool = False


END_REPORT_TAIL_BYTES = 65536  # an agent's end action is among the last lines of its log


def _last_end_report(log_path: Path, drone: int) -> EndReport | None:
    """The last end-action line of drone ``drone`` in the log at ``log_path`` (its tail)."""
    try:
        with log_path.open("rb") as handle:
            handle.seek(max(log_path.stat().st_size - END_REPORT_TAIL_BYTES, 0))
            lines = handle.read().decode(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        report = EndReport.parse(line)
        if report is not None and report.drone == drone:
            return report
    return None


ProgressCallback = Callable[[int, "TelemetryCollector"], None]


class SwarmLauncher(RunObserver):
    """Runs one mission with the world and every agent as separate OS processes; observes
    it as ``RunObserver`` (collector, recording, live view, telemetry listeners)."""

    def __init__(self, options: LaunchOptions, log: Callable[[str], None] = print) -> None:
        self.options = options
        cfg = options.config
        super().__init__(cfg, options.run_id or f"run{secrets.token_hex(4)}",
                         prog="launch-swarm", log=log)
        self.n = cfg.swarm.n_drones
        self.children: list[Child] = []
        self.stop_requested = threading.Event()
        self._clean_exits: dict[str, float] = {}  # child name → when its exit 0 was first seen
        self.zenoh_port = options.zenoh_port or free_tcp_port()
        self.endpoint = local_endpoint(self.zenoh_port, tls=cfg.security.enabled)
        # SITL: agent i listens on base + i, the launcher's monitor link of autopilot i on
        # base + N + i.
        self.mavlink_base, self._port_lock = reserve_mavlink_base(
            options.mavlink_base, 2 * self.n if options.sitl is not None else self.n,
            frozenset(options.mavlink_urls))
        # After the ports: a launcher that cannot start leaves no directory behind.
        self._own_log_dir = options.log_dir is None  # a temp dir (LaunchOptions.log_dir)
        self._log_dir_finished = False
        try:
            self.log_dir = options.log_dir or Path(tempfile.mkdtemp(
                prefix=f"vigil-{self.run_id}-"))
            self.log_dir.mkdir(parents=True, exist_ok=True)
        except OSError:
            self._port_lock.close()
            raise
        # The config every child reads (``self.config``): the user's file, or the one resolved
        # here (SITL: the flavour of the firmware and the origin offsets measured on the
        # autopilots).
        self.config_path = options.config_path
        self.sitl_fleet: SitlFleet | None = None
        self._autopilot_seen: dict[int, tuple[str, bool]] = {}
        self.agent_losses: list[AgentLoss] = []
        self._restarts_due: dict[int, float] = {}  # drone → monotonic time of its restart
        self._killed: set[int] = set()  # drones killed by kill_agents
        self._restarts_done: dict[int, int] = {}
        # Every drone's end action, once its agent is gone (_report_end_actions).
        self.end_actions: dict[int, EndReport] = {}

    # -- children ---------------------------------------------------------------------------

    def _spawn(self, name: str, argv: list[str], drone: int | None = None) -> Child:
        log_path = self.log_dir / f"{name}.log"
        handle = log_path.open("wb")
        # Spawned without preexec_fn (vfork: ~0.3 ms against 6-8 ms per fork of this
        # process); the child binds its life to ours itself (swarm.children.follow_parent).
        # SIGKILL when we die, not SIGTERM: it fires only when the launcher could not stop its
        # children itself (kill -9, a crash), so nobody is left to escalate, and a child's
        # graceful exit can stall in zenoh's session close for seconds (seen after a kill -9
        # of a recording launcher: world and agents all waited in close until a second
        # signal). SCHED_BATCH for lockstep, where only throughput counts: a batch thread
        # does not preempt the one running when a message wakes it, so the eight processes of
        # a swarm on a few cores switch context a third less often and each runs longer with
        # warm caches (Case 2 on 2 cores: ~60 % of the context switches, ~5 % less CPU; the
        # swarm's messages alone, without its compute: 3.7 instead of 4.2 ms per step). Not
        # for realtime, where a wake-up must run at once.
        env = child_environment(dict(os.environ, PYTHONUNBUFFERED="1"), parent_pid=os.getpid(),
                                sched_batch=self.options.mode == "lockstep")
        # The step's matrices are 3x3..6x6: a BLAS thread pool per process only adds threads
        # that compete for the two cores. An explicit setting by the user wins.
        for variable in BLAS_THREAD_VARIABLES:
            env.setdefault(variable, "1")
        process = subprocess.Popen(
            argv, stdout=handle, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=env, **_placement(drone))
        handle.close()
        child = Child(name, process, log_path, drone)
        self.children.append(child)
        return child

    def _common_args(self) -> list[str]:
        opts = self.options
        return [self.config_path, "--run-id", self.run_id, "--mode", opts.mode,
                "--seed", str(opts.seed), "--duration", repr(opts.config.scenario.duration_s)]

    def start_world(self) -> Child:
        argv = [sys.executable, "-m", "sim_world.cli", *self._common_args(),
                "--listen", self.endpoint, "--mavlink-base", str(self.mavlink_base)]
        if self.external_autopilots:
            argv += ["--vehicles", "external"]
        if self.options.gcs is not None:
            argv += ["--gcs", "{}:{}".format(*self.options.gcs)]
            argv += ["--gcs-control"] if self.options.gcs_control else []
        return self._spawn("world", argv)

    def start_vehicles(self) -> Child:
        argv = [sys.executable, "-m", "sim_world.vehicles_cli", self.config_path,
                "--seed", str(self.options.seed), "--mavlink-base", str(self.mavlink_base)]
        return self._spawn("vehicles", argv)

    def start_agent(self, drone_id: int) -> Child:
        opts = self.options
        common = self._common_args()
        configured = self.config.vehicles.mavlink_urls
        url = opts.mavlink_urls.get(drone_id) or (
            configured[drone_id] if configured
            else f"udpin:127.0.0.1:{self.mavlink_base + drone_id}")
        argv = [sys.executable, "-m", "swarm.agent.cli", "--id", str(drone_id),
                "--config", common[0], *common[1:], "--connect", self.endpoint,
                "--mavlink", url, "--qp-dump-dir", str(self.log_dir),
                *opts.extra_agent_args.get(drone_id, [])]
        restarts = self._restarts_done.get(drone_id, 0)
        name = f"agent{drone_id}" + (f".restart{restarts}" if restarts else "")
        return self._spawn(name, argv, drone_id)

    def start_camera(self, drone_id: int) -> Child:
        """Drone ``drone_id``'s detector (camera.model = "rendered", docs/camera.md)."""
        common = self._common_args()
        argv = [sys.executable, "-m", "swarm.camera.cli", "--id", str(drone_id),
                "--config", common[0], *common[1:], "--connect", self.endpoint]
        return self._spawn(f"camera{drone_id}", argv)

    def stop_children(self) -> None:
        """SIGTERM every process group, SIGKILL what is left after the grace period. The
        agents go first (up to AGENT_END_GRACE_S): each commands its vehicle's end action on
        the way out, and an emulated vehicle needs the world still there to obey it."""
        deadline = time.monotonic() + STOP_GRACE_S
        agents = [child for child in self.children if child.drone is not None]
        for group in (agents, [child for child in self.children if child.drone is None]):
            for child in group:
                if child.process.poll() is None:
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(child.process.pid, signal.SIGTERM)
            if group is agents:
                agents_done = time.monotonic() + AGENT_END_GRACE_S
                for child in agents:
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        child.process.wait(timeout=max(agents_done - time.monotonic(), 0.01))
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

    def _report_end_actions(self) -> None:
        """Once every agent is gone: what became of each drone's end action, in a line per
        outcome. Each agent logs it as its last word on the vehicle (``EndReport``, after
        ``vehicles.end_action`` was acknowledged, refused, not answered or not sent); the log
        is read, not a message, because the end action also runs when the network is what
        failed. An agent with no such line died before it could send it (``kill -9``, a
        crash): its vehicle is left to its own setpoint-loss failsafe."""
        latest: dict[int, Child] = {}
        for child in self.children:  # started in order: a restart's replaces the lost one
            if child.drone is not None:
                latest[child.drone] = child
        if self.end_actions or not latest:
            return
        vehicles = self.config.vehicles
        mode = end_mode_name(vehicles.flavour, vehicles.end_action)
        for drone, child in sorted(latest.items()):
            report = _last_end_report(child.log_path, drone)
            if report is None:
                report = EndReport(
                    drone, vehicles.end_action, mode, "not sent",
                    f"its agent ended with {self._how(child)} before it could send it; the "
                    f"vehicle is left to its own setpoint-loss failsafe")
            self.end_actions[drone] = report
        groups: dict[tuple[str, str, str, str], list[int]] = {}
        for drone, report in self.end_actions.items():
            key = (report.action, report.mode, report.outcome, report.detail)
            groups.setdefault(key, []).append(drone)
        for (action, shown, outcome, detail), drones in groups.items():
            who = (f"drone {drones[0]}" if len(drones) == 1
                   else f"drones {', '.join(map(str, drones))}")
            self.log(f"launch-swarm: {who}: end action {action} ({shown}) {outcome}"
                     + (f": {detail}" if detail else ""))

    def _dead_child(self) -> Child | None:
        """A child that ended badly, or ended cleanly but the mission did not end with it.

        An agent exits 0 only after it has seen the world's "done" clock, which may reach it
        before it reaches us: a clean exit counts as a failure only if "done" does not follow
        within ``CLEAN_EXIT_GRACE_S``.
        """
        done = self._mission_state() == "done"
        now = time.monotonic()
        for child in self.children:
            code = child.process.poll()
            if code is None or (done and code == 0) or child.lost:
                continue
            if code == 0:
                first_seen = self._clean_exits.setdefault(child.name, now)
                if now - first_seen < CLEAN_EXIT_GRACE_S:
                    continue
            return child
        return None

    def _failure(self, child: Child) -> MissionError:
        return MissionError(self._ending(child))

    @staticmethod
    def _how(child: Child) -> str:
        code = child.process.returncode
        return f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"

    def _ending(self, child: Child) -> str:
        tail = "\n    ".join(child.tail())
        return (f"{child.name} (pid {child.process.pid}) ended with {self._how(child)}; last "
                f"lines of {child.log_path}:\n    {tail}")

    def _survivable(self, child: Child) -> bool:
        """Realtime, mission running: a lost agent leaves the swarm, which goes on without it
        (its vehicle holds, the others' membership drops it). Not in lockstep, where every
        drone waits for every other one, nor before the mission starts, nor the last one."""
        alive = [c for c in self.children
                 if c.drone is not None and c is not child and c.process.poll() is None]
        if child.process.returncode == EXIT_END_MISSION:  # vehicles.on_vehicle_event = end
            return False
        return (self.options.mode == "realtime" and child.drone is not None
                and self._mission_state() == "running" and bool(alive))

    def _lose_agent(self, child: Child) -> None:
        """Report a lost agent, and restart it later if restarts are left."""
        assert child.drone is not None
        child.lost = True
        drone = child.drone
        time_s = max(self.collector.last_truth_step, 0) * self.options.config.scenario.dt_s
        restart = self._restarts_done.get(drone, 0) < self.options.agent_restarts
        self.agent_losses.append(AgentLoss(drone, time_s, self._how(child), restart))
        command = child.process.args  # the argv list _start gave it
        then = (f"restarting it in {self.options.agent_restart_delay_s:g} s" if restart else
                "restart it by hand with: " + (shlex.join(map(str, command))
                                               if isinstance(command, list) else str(command)))
        self.log(f"launch-swarm: drone {drone} lost at t = {time_s:.2f} s: "
                 f"{self._ending(child)}\n  the mission goes on without it; {then}")
        if restart:
            self._restarts_due[drone] = time.monotonic() + self.options.agent_restart_delay_s

    def _kill_due_agents(self) -> None:
        """``kill_agents``: SIGKILL each agent whose time has come (once); the loss is then
        found and handled like any other (``_lose_agent``)."""
        time_s = max(self.collector.last_truth_step, 0) * self.options.config.scenario.dt_s
        for drone, due_s in self.options.kill_agents:
            if drone in self._killed or time_s < due_s:
                continue
            self._killed.add(drone)
            child = next((c for c in self.children if c.drone == drone
                          and c.process.poll() is None), None)
            if child is None:
                self.log(f"launch-swarm: --kill-agent {drone}@{due_s:g}: it is not running")
                continue
            self.log(f"launch-swarm: t = {time_s:.2f} s: killing drone {drone}'s agent "
                     f"(pid {child.process.pid}) as asked (--kill-agent)")
            with contextlib.suppress(ProcessLookupError):
                os.kill(child.process.pid, signal.SIGKILL)

    def _restart_due_agents(self) -> None:
        now = time.monotonic()
        for drone, due in list(self._restarts_due.items()):
            if now >= due:
                del self._restarts_due[drone]
                self._restarts_done[drone] = self._restarts_done.get(drone, 0) + 1
                child = self.start_agent(drone)
                self.log(f"launch-swarm: drone {drone} restarted (pid {child.process.pid}, "
                         f"log {child.log_path})")

    # -- autopilots ---------------------------------------------------------------------------

    @property
    def external_autopilots(self) -> bool:
        """The world serves no vehicles: SITL, configured connection strings, or sim-vehicles."""
        return (self.options.sitl is not None or self.options.external_vehicles
                or bool(self.config.vehicles.mavlink_urls))

    def _start_sitl(self) -> None:
        """One autopilot per drone, at home below its start position (W's origin on Earth is
        ``vehicles.geo_origin``, the ground is z = 0); once every one is ready, each one's
        origin offset is measured (where its estimator puts it on the ground is where it
        stands in W) and the resolved config written for the world and the agents."""
        firmware = self.options.sitl
        assert firmware is not None
        cfg = dataclasses.replace(self.config, vehicles=dataclasses.replace(
            self.config.vehicles, flavour=firmware.kind))
        if firmware.kind != self.config.vehicles.flavour:
            self.log(f"launch-swarm: vehicles.flavour = {firmware.kind!r} for {firmware.name}")
        positions = initial_drone_positions(cfg, self.options.seed)
        ground_w = [np.array([p[0], p[1], 0.0]) for p in positions]
        geo = GeoPoint(*cfg.vehicles.geo_origin)
        n, base = self.n, self.mavlink_base
        fleet = SitlFleet(firmware, [geo.moved(g[0], g[1]) for g in ground_w],
                          [base + i for i in range(n)], [base + n + i for i in range(n)],
                          self.log_dir, setpoint_timeout_s=cfg.vehicles.failsafe_timeout_s,
                          boot_speedup=self.options.sitl_boot_speedup,
                          extra_params=self.options.sitl_params, log=self.log,
                          on_state=self._on_autopilot_state)
        self.sitl_fleet = fleet
        try:
            fleet.start()
            fleet.wait_ready(cfg.runtime.start_timeout_s, stop=self.stop_requested.is_set)
            offsets = fleet.origin_offsets(ground_w)
        except SitlError as err:
            raise MissionError(str(err)) from None
        cfg = dataclasses.replace(cfg, vehicles=dataclasses.replace(
            cfg.vehicles, origin_offsets_m=tuple(
                (float(o[0]), float(o[1]), float(o[2])) for o in offsets)))
        self.config = cfg
        self.config_path = str(write_resolved_config(cfg, self.log_dir / "config.json"))
        shown = ", ".join(f"[{o[0]:.2f}, {o[1]:.2f}, {o[2]:.2f}]" for o in offsets)
        self.log(f"launch-swarm: origin offsets measured on the autopilots: {shown} m")

    def _on_autopilot_state(self, drone: int, view: VehicleView) -> None:
        """The monitor link's newest state of autopilot ``drone`` (its thread): mode and
        armed changes logged, and during the mission the state recorded."""
        seen = (view.mode, view.armed)
        if self._autopilot_seen.get(drone) != seen:
            if drone in self._autopilot_seen:
                shown = autopilot_mode_name(self.config.vehicles.flavour, view.mode)
                self.log(f"launch-swarm: drone {drone}'s autopilot now {shown}, "
                         f"{'armed' if view.armed else 'disarmed'}")
            self._autopilot_seen[drone] = seen
        recorder = self.recorder
        if (recorder is None or view.local_ned is None or view.local_velocity_ned is None
                or self._mission_state() not in ("running", "done")):
            return
        position = frames.world_from_local_ned(view.local_ned, self.config.vehicles.origin_w(
            drone))
        velocity = frames.ned_to_enu(view.local_velocity_ned)
        with contextlib.suppress(ValueError):  # a non-finite sample: nothing to record
            recorder.put(AutopilotState(
                drone=drone, time_s=max(self.collector.last_truth_step, 0)
                * self.config.scenario.dt_s,
                position_m=tuple(float(v) for v in position),  # type: ignore[arg-type]
                velocity_m_s=tuple(float(v) for v in velocity),  # type: ignore[arg-type]
                mode=view.mode, armed=view.armed, landed_state=view.landed_state or 0))

    def _await_autopilots_after_agents(self, timeout_s: float = 2.5) -> None:
        """SITL: until every autopilot has sent a HEARTBEAT (1 Hz) and a position since the
        agents left, so that the recording ends with what the end action made of it."""
        if self.sitl_fleet is None or self.sitl_fleet.monitor is None:
            return
        monitor = self.sitl_fleet.monitor
        since = time.monotonic()
        deadline = since + timeout_s
        while time.monotonic() < deadline:
            views = [monitor.view(i) for i in range(self.n)]
            if all(v.heartbeat_s is not None and v.heartbeat_s > since and v.local_s is not None
                   and v.local_s > v.heartbeat_s for v in views):
                return
            time.sleep(0.05)

    def _check_sitl(self) -> None:
        """An autopilot that dies ends the mission (its drone would fall)."""
        if self.sitl_fleet is None:
            return
        dead = self.sitl_fleet.dead()
        if dead is not None:
            tail = "\n    ".join(dead.tail())
            raise MissionError(f"{dead.name} (pid {dead.pid}) ended with exit code "
                               f"{dead.poll()}; last lines of {dead.console_log}:\n    {tail}")

    # -- zenoh --------------------------------------------------------------------------------

    def _connect(self, timeout_s: float) -> None:
        """Join the world's router as a client, retrying while the world starts up."""
        def children_alive() -> None:
            for child in self.children:
                if child.process.poll() is not None:
                    raise self._failure(child)

        try:
            self.connect([self.endpoint], timeout_s, before_each_try=children_alive,
                         pause=self.stop_requested.wait)
        except TransportError as err:
            raise MissionError(f"cannot reach the world's Zenoh router at "
                               f"{self.endpoint}: {err}") from None
        self.subscribe()

    # -- the mission -------------------------------------------------------------------------

    def run(self, on_progress: ProgressCallback | None = None,
            telemetry_listeners: Sequence[TelemetryListener] = ()) -> RunRecord:
        """Run the mission to its end; MissionError if a process dies or the world aborts.

        ``on_progress(step, collector)`` runs on this thread whenever the truth step moves;
        ``telemetry_listeners`` get every telemetry message as it arrives.
        """
        self.telemetry_listeners = tuple(telemetry_listeners)
        cfg = self.options.config
        started = time.monotonic()
        try:
            vehicles = (f", {self.options.sitl.name} autopilots" if self.options.sitl
                        else ", external autopilots" if self.external_autopilots else "")
            kept = (" (removed if the run succeeds; --log-dir keeps them)"
                    if self._own_log_dir else "")
            self.log(f"launch-swarm: run {self.run_id}: world + {self.n} agents "
                     f"({self.options.mode}{vehicles}), zenoh {self.endpoint}, MAVLink "
                     f"{self.mavlink_base}..{self.mavlink_base + self.n - 1}, logs "
                     f"{self.log_dir}{kept}")
            if self.options.sitl is not None:
                self._start_sitl()
            elif self.external_autopilots:
                # The config as resolved here (the --mavlink URLs, the tracking margins fitted
                # to the autopilots' flavour), not the user's file, for every child.
                self.config_path = str(write_resolved_config(self.config,
                                                             self.log_dir / "config.json"))
            self._open_recorder()
            self._open_live_view()
            if self.options.external_vehicles:
                self.start_vehicles()
            # The agents start with the world, not after it: their imports overlap the
            # world's start-up, and they keep trying its router until it is up.
            world_started = time.monotonic()
            self.start_world()
            for i in range(self.n):
                if self.config.camera.rendered:
                    self.start_camera(i)
                self.start_agent(i)
            self._connect(timeout_s=30.0)
            announced = False
            last_progress = -1
            while True:
                self._state_changed.wait(SUPERVISE_PERIOD_S)
                self._state_changed.clear()
                if self.stop_requested.is_set():
                    raise KeyboardInterrupt
                self._check_sitl()
                dead = self._dead_child()
                while dead is not None:
                    if not self._survivable(dead):
                        raise self._failure(dead)
                    self._lose_agent(dead)
                    dead = self._dead_child()
                if self._mission_state() == "running":
                    self._kill_due_agents()
                    self._restart_due_agents()
                state = self._mission_state()
                if state == "running" and not announced:
                    announced = True
                    self.log(f"launch-swarm: every drone armed and streaming after "
                             f"{time.monotonic() - started:.1f} s; mission running")
                if state == "aborted":
                    latest = self.clock.get(0)  # the clock that said "aborted"
                    detail = latest[0].detail if latest is not None else "no detail"
                    raise MissionError(f"the world aborted the mission: {detail}")
                if state == "waiting" and time.monotonic() - world_started > (
                        cfg.runtime.start_timeout_s + 10.0):
                    raise MissionError("the mission never started")
                step = self.collector.last_truth_step
                if on_progress is not None and step != last_progress:
                    last_progress = step
                    on_progress(step, self.collector)
                if state == "done":
                    break
            self._wait_agents_done()
            self._await_autopilots_after_agents()
            self._leave_zenoh()  # no message arrives after this: record and recording agree
            record = self.collector.record(self.options.seed, time.monotonic() - started)
            self.close()
            if not self.options.defer_log_cleanup:
                self.finish_log_dir(success=not self.agent_losses
                                    and self.recording_problem is None)
            return record
        finally:
            self.close()

    def finish_log_dir(self, success: bool) -> None:
        """The temporary log directory (``LaunchOptions.log_dir`` None): removed after a run
        that succeeded, unless an agent saved a QP it could not solve there
        (``swarm.runs.failed_qp``); otherwise kept, and said so. A directory given is always
        kept. Once; ``run`` calls it unless ``defer_log_cleanup``."""
        if not self._own_log_dir or self._log_dir_finished:
            return
        self._log_dir_finished = True
        dumps = sorted(self.log_dir.glob("qp-*.npz"))
        if dumps:
            self.log(f"launch-swarm: {len(dumps)} QPs the agents could not solve are saved in "
                     f"{self.log_dir} (kept; python -m swarm.runs.failed_qp FILE solves one "
                     f"again)")
        elif success:
            shutil.rmtree(self.log_dir, ignore_errors=True)
        else:
            self.log(f"launch-swarm: the run did not succeed: logs kept in {self.log_dir}")

    def _wait_agents_done(self) -> None:
        deadline = time.monotonic() + 5.0
        for child in (c for c in self.children if c.name.startswith("agent")):
            try:
                child.process.wait(timeout=max(deadline - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                break

    def _open_recorder(self) -> None:
        opts = self.options
        if opts.record_dir is None:
            return
        metadata = RecordingMetadata.for_run(self.config, opts.seed, opts.mode, self.run_id,
                                             opts.config_path)
        try:
            self.open_recorder(opts.record_dir, metadata, autopilots=self.sitl_fleet is not None)
        except RecordingError as err:
            raise MissionError(str(err)) from None

    def _open_live_view(self) -> None:
        if self.options.foxglove is None:
            return
        try:
            self.open_live_view(self.options.foxglove)
        except LiveViewError as err:
            raise MissionError(str(err)) from None

    def close(self) -> None:
        """Leave Zenoh, finish the recording and stop every child; safe to call more than
        once."""
        self.stop_observing()
        self.stop_children()  # the agents' end actions go out before their autopilots stop
        self._report_end_actions()
        if self.sitl_fleet is not None:
            self.sitl_fleet.stop()
        self._port_lock.close()  # the children that used the ports are gone
