"""The world process: targets, cameras and one emulated MAVLink vehicle per drone (SPEC §12).

It hosts the swarm's Zenoh router (agents and the launcher connect to it), serves each
vehicle over UDP the way PX4 SITL does, and publishes camera frames, ground truth and the
clock. Two time modes:

- ``lockstep``: step k is published (LOCAL_POSITION_NED stamped t_k, camera frames, truth),
  then the world waits until every vehicle has received a setpoint stamped t_k and integrates
  with exactly those; deterministic, reproduces the in-process reference.
- ``realtime``: a 50 Hz wall-clock loop integrates each vehicle with its latest setpoint under
  the flavour's failsafe rules; nothing waits.

What an agent knows of the other drones' positions (collision rows, formation bearings) comes
from the world in one message per agent and step, not from each other drone:

- lockstep: in the camera frame of step k (``CameraFrameWire.drone_positions``), every drone's
  position as its vehicle reports it at step k (LOCAL_POSITION_NED, float32 local NED, as its
  agent reads it: ``frames.position_over_link``) — exactly what the drones' beacons of step k
  carry, known here before any of them is sent, so no relay waits for N beacons and the
  world takes no beacon at all (the in-process reference does the same);
- realtime: at each tick, every drone's newest beacon with how long the world has held it
  (``world/beacons``, ``BeaconRelayWire``): N messages a tick instead of N(N − 1).

With ``vehicles = "external"`` it serves no vehicles: each drone's position is taken from its
beacon, so the agents can fly real autopilots against virtual targets.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sim_world.fleet import VehicleFleet
from swarm.errors import EXIT_FAILED, EXIT_OK, VigilError
from swarm.messages.wire import (
    BeaconRelayWire,
    BeaconWire,
    CameraFrameWire,
    CameraImageWire,
    ClockState,
    ClockWire,
    F64Array,
    TruthWire,
)
from swarm.models.frames import GeoPoint
from swarm.net.keys import Keys
from swarm.net.rate import RateLimiter, freeze_heap
from swarm.net.security import WORLD_ROLE, router_access_control
from swarm.net.session import declare_publisher, open_session, put_stamped, zenoh_config
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import DrainedSubscriber, RejectionCounter, subscribe
from swarm.scenario.cli_common import DEFAULT_MAVLINK_BASE
from swarm.scenario.config import ScenarioConfig, realtime_only_reason
from swarm.scenario.setup import initial_drone_positions
from swarm.scenario.world_step import Scene

Mode = Literal["lockstep", "realtime"]
VehicleSource = Literal["sim", "external"]
Array = NDArray[np.float64]
PRE_MISSION_PERIOD_S = 0.02  # telemetry and vehicle motion before the mission starts
# "running" on world/clock is repeated this often (wall), not every step: readers only act on
# state changes (start, done, aborted), and a message per step cost every agent a wake-up.
CLOCK_PERIOD_S = 0.25
# The beacon ring holds this many periods of every drone's beacons (drained at each tick).
BEACON_RING_PERIODS = 4
MISSION_TIME_OFFSET_MS = 1000  # mission stamps start this far past every pre-mission stamp
DONE_LINGER_S = 10.0  # the world stays up this long after the mission unless stopped
# How the world declares each of its publishers: ``declare(session, key, block=...)`` returns
# something with ``put(payload, timestamp=None)``. ``declare_publisher`` in a run; a test
# passes one whose publishers keep what is put.
DeclarePublisher = Callable[..., Any]


class WorldAbortError(VigilError, RuntimeError):
    """The mission cannot go on (a vehicle never armed, an agent went silent in lockstep)."""


@dataclass(frozen=True)
class WorldOptions:
    config: ScenarioConfig
    seed: int
    run_id: str
    mode: Mode = "lockstep"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    mavlink_host: str = "127.0.0.1"
    mavlink_base: int = DEFAULT_MAVLINK_BASE
    vehicles: VehicleSource = "sim"
    # Every vehicle's ground-station link sends here (``sim_world.gcs_link``); None: none.
    gcs: tuple[str, int] | None = None
    gcs_control: bool = False  # may the ground station command the vehicles?
    log: Callable[[str], None] = field(default=print)


class World:
    """State of the simulated world; ``run()`` drives it to the end of the mission."""

    def __init__(self, options: WorldOptions, *,
                 declare: DeclarePublisher = declare_publisher) -> None:
        self.options = options
        cfg = options.config
        reason = realtime_only_reason(cfg.vehicles, mode=options.mode,
                                      external=options.vehicles == "external")
        if reason is not None:
            raise ValueError(reason)
        self.n, self.m = cfg.swarm.n_drones, len(cfg.targets)
        self.dt_s = cfg.scenario.dt_s
        self.dt_ms = round(cfg.scenario.dt_s * 1000)
        self.scene = Scene(cfg, options.seed)
        self.keys = Keys(options.run_id)
        self.codec = cfg.wire_codec()
        self.rejections = RejectionCounter()
        self.started = time.monotonic()
        self._sim_now: float | None = None
        self._last_clock_s = -np.inf  # wall time of the last world/clock message
        self.positions = initial_drone_positions(cfg, options.seed)
        # External vehicles: the time_boot_ms of the sample behind each drone's position (its
        # beacon's), stamped on the frames rendered from it.
        self.pose_stamps_ms = [0] * self.n
        self.beacons: LatestValues[BeaconWire] = LatestValues()
        self.fleet: VehicleFleet | None = None
        self._failsafes_reported = [0] * self.n
        self._subscribers: list = []
        self._beacon_ring: DrainedSubscriber | None = None
        security = cfg.security
        self.session = open_session(zenoh_config(
            mode="router", listen=options.listen, connect=options.connect,
            tls=security.identity(WORLD_ROLE),
            access_control=router_access_control(
                self.keys.prefix, cfg.swarm.graph.neighbours) if security.enabled else None))
        try:
            if options.vehicles == "sim":
                self.fleet = VehicleFleet(
                    self.positions, [cfg.vehicles.origin_w(i) for i in range(self.n)],
                    cfg.vehicles.flavour, host=options.mavlink_host,
                    base_port=options.mavlink_base, u_max_m_s=cfg.control.u_max_m_s,
                    setpoint_timeout_s=cfg.vehicles.failsafe_timeout_s, clock=self.now_s,
                    signing_key=cfg.vehicles.signing_key(), start=cfg.vehicles.start,
                    response=cfg.vehicles.velocity_response, gcs=options.gcs,
                    gcs_control=options.gcs_control,
                    geo_origin=GeoPoint(*cfg.vehicles.geo_origin), log=options.log)
            if options.mode == "realtime":
                # Every drone's beacon, to relay (and, with external vehicles, where the drones
                # are). A ring taken at each tick: no Python thread, and the router's threads
                # (this process hosts the router) never wait for the GIL. External vehicles
                # are realtime only (realtime_only_reason). Lockstep takes no beacon: the
                # camera frames carry the positions (module docstring).
                ring = subscribe(self.session, self.keys.all_beacons, self.codec.decode_beacon,
                                 self._on_beacon, self.rejections, "beacon",
                                 keep_latest=BEACON_RING_PERIODS * self.n)
                assert isinstance(ring, DrainedSubscriber)
                self._beacon_ring = ring
                self._subscribers.append(ring)
        except Exception:
            self.session.close()
            raise
        # Nothing the world publishes is dropped: lockstep peers wait for every message, and a
        # recording keeps every detection and truth sample. zenoh_config gives each link room
        # for a whole step's burst, so a put waits only if a link is stuck.
        # A rendered camera's frames go to the drone's detector as images (world/image/<i>);
        # the detector publishes the camera frames (swarm-camera, docs/camera.md).
        self.rendered = cfg.camera.rendered
        self._pub_camera = [declare(self.session, self.keys.image(i) if self.rendered
                                    else self.keys.camera(i), block=True)
                            for i in range(self.n)]
        self._pub_truth = declare(self.session, self.keys.truth, block=True)
        self._pub_clock = declare(self.session, self.keys.clock, block=True)
        # Realtime only; it drops rather than waits: the next tick brings the newest beacons.
        self._pub_relay = (declare(self.session, self.keys.beacon_relay, block=False)
                           if self._beacon_ring is not None else None)

    @property
    def takes_beacons(self) -> bool:
        """Whether the world subscribes to the drones' beacons: in realtime (to relay them,
        and with external vehicles to place the drones); a lockstep world takes none."""
        return self._beacon_ring is not None

    # -- plumbing ---------------------------------------------------------------------------

    def now_s(self) -> float:
        """Wall time since start; in a lockstep mission, the mission's sim time instead, so
        that the vehicles' failsafe timers count simulated seconds, not waiting time."""
        if self._sim_now is not None:
            return self._sim_now
        return time.monotonic() - self.started

    def boot_ms(self) -> int:
        return int(self.now_s() * 1000)

    def _wait(self, timeout_s: float) -> None:
        if self.fleet is not None:
            self.fleet.service(timeout_s)
        elif timeout_s > 0:
            time.sleep(timeout_s)

    def publish_clock(self, step: int, state: ClockState, detail: str = "") -> None:
        self._last_clock_s = time.monotonic()
        self._pub_clock.put(self.codec.encode(ClockWire(
            step=step, time_s=step * self.dt_s, state=state, mode=self.options.mode,
            detail=detail, rejected_inputs=self.rejected_total())))

    def publish_running(self, step: int) -> None:
        """``running`` at step 0 (the mission starts), then every CLOCK_PERIOD_S."""
        if step == 0 or time.monotonic() - self._last_clock_s >= CLOCK_PERIOD_S:
            self.publish_clock(step, "running")

    def publish_step(self, step: int, vehicle_times_ms: Sequence[int],
                     drone_positions: Array | None = None) -> None:
        """Camera frames for every drone and the ground truth of step k; drone i's frame is
        stamped ``vehicle_times_ms[i]``, the time_boot_ms of the vehicle sample its camera
        was placed at (how an agent pairs the frame with that pose). ``drone_positions``
        (lockstep): every drone's reported position (N, 3), carried by every frame."""
        view = self.scene.at(step, self.positions, detect_markers=False)
        positions = None if drone_positions is None else F64Array.from_array(drone_positions)
        for i in range(self.n):
            wire = CameraFrameWire.build(
                drone=i, step=step, time_s=view.time_s, vehicle_time_ms=vehicle_times_ms[i],
                detections=view.detections[i],
                target_velocities=view.communicated_velocities_m_s,
                drone_positions=positions,
                radio_links=None if view.links is None else view.links[i])
            frame = self.codec.encode(wire if not self.rendered else CameraImageWire.of_frame(
                wire, b"" if view.images is None else view.images[i]))
            # Stamped: a realtime agent sets the phase of its loop from when frames leave.
            put_stamped(self.session, self._pub_camera[i], frame)
        self._pub_truth.put(self.codec.encode(TruthWire.build(
            step=step, time_s=view.time_s, drone_positions=self.positions,
            target_positions=view.target_positions_m,
            target_velocities=view.target_velocities_m_s, radio_links=view.links)))

    def _from_its_drone(self, key: str, beacon: BeaconWire) -> bool:
        """Whether ``beacon`` came on its sender's key; drone j's position on another's key is
        refused and counted."""
        if key == self.keys.beacon(beacon.sender):
            return True
        self.rejections.reject("beacon", f"sender {beacon.sender} on {key}")
        return False

    def _on_beacon(self, key: str, beacon: BeaconWire, arrived_s: float | None = None) -> None:
        if self._from_its_drone(key, beacon):
            self.beacons.put(beacon.sender, beacon, arrived_s=arrived_s)

    def take_beacons(self) -> None:
        """Store the beacons that arrived since the last call (realtime)."""
        if self._beacon_ring is not None:
            self._beacon_ring.drain()

    def relay_beacons(self, step: int) -> None:
        """Realtime: every drone's newest beacon to the agents in one message, each with how
        long the world has held it, so that an agent dates it from its arrival here."""
        if self._pub_relay is None:  # lockstep: the frames carry the positions
            return
        held = self.beacons.fresh_with_ages(math.inf)  # by drone id (the codec checked it)
        put_stamped(self.session, self._pub_relay, self.codec.encode(
            BeaconRelayWire.build(step, (held[i] for i in range(self.n) if i in held))))

    def _not_ready(self) -> list[int]:
        if self.fleet is None:
            return [i for i in range(self.n) if self.beacons.get(i) is None]
        now = self.now_s()
        return [i for i, v in enumerate(self.fleet.vehicles)
                if not (v.accepting_setpoints and v.setpoints_streaming(now))]

    def place_external_drones(self) -> None:
        """External vehicles: each drone where its newest beacon says, with that beacon's
        autopilot stamp for the frames rendered from there (a drone not heard stays put)."""
        for i in range(self.n):
            latest = self.beacons.get(i)
            if latest is not None:
                self.positions[i] = latest[0].position()
                self.pose_stamps_ms[i] = latest[0].vehicle_time_ms

    # -- phases -----------------------------------------------------------------------------

    def wait_for_mission_start(self) -> None:
        """Serve the vehicles until every drone is armed and streaming setpoints (external
        vehicles: until every drone's beacon has been heard): commands are answered as they
        arrive, the vehicles move and report every PRE_MISSION_PERIOD_S."""
        deadline = self.now_s() + self.options.config.runtime.start_timeout_s
        last_report = -np.inf
        last_move = next_tick = self.now_s()
        while True:
            # Drain what arrived first: after a stall (a loaded machine) the queued setpoints
            # must count before any failsafe timer is evaluated.
            self._wait(0.0)
            self.take_beacons()
            pending = self._not_ready()
            if not pending:
                return
            now = self.now_s()
            if now > deadline:
                what = ("armed and streaming setpoints" if self.fleet is not None
                        else "heard (no beacon)")
                raise WorldAbortError(f"drones {pending} not {what} within "
                                      f"{self.options.config.runtime.start_timeout_s} s")
            if now - last_report >= 0.5:
                last_report = now
                self.publish_clock(0, "waiting", f"waiting for drones {pending}")
            if now >= next_tick:
                next_tick += PRE_MISSION_PERIOD_S
                if next_tick <= now:  # fell behind (a stall): no burst of catch-up ticks
                    next_tick = now + PRE_MISSION_PERIOD_S
                if self.fleet is not None:
                    # Armed vehicles fly what they are told even before the mission (any
                    # MAVLink client can fly one); the agents' idle setpoints are exactly zero.
                    self.fleet.fly(now - last_move)
                    self.positions[:] = self.fleet.positions_w
                    self.fleet.send_telemetry(self.boot_ms())
                last_move = now
            self._wait(max(next_tick - self.now_s(), 0.0))

    def run_lockstep(self) -> None:
        fleet = self.fleet
        assert fleet is not None
        start_ms = self.boot_ms() + MISSION_TIME_OFFSET_MS
        # The vehicles' clock continues from wall time, one step on: a stream the agent asked
        # for at the step's rate (LOCAL_POSITION_NED at 50 Hz) is then due at step 0 whenever
        # its last pre-mission sample went out, and at every step after it.
        start_s = self.now_s() + self.dt_s
        fleet.arrival_times = False  # sim time from here: waiting for a setpoint is not time
        timeout = self.options.config.runtime.lockstep_timeout_s
        for k in range(self.options.config.n_steps):
            stamp = start_ms + k * self.dt_ms
            self._sim_now = start_s + k * self.dt_s
            for vehicle in fleet.vehicles:
                vehicle.begin_step(stamp)
            fleet.send_telemetry(stamp)
            self.publish_step(k, [stamp] * self.n, fleet.reported_positions_w())
            self.publish_running(k)
            deadline = time.monotonic() + timeout
            velocities: list[np.ndarray | None] = [None] * self.n
            missing = set(range(self.n))
            # A vehicle's stamped setpoint can only come with a datagram: after the first
            # look at every vehicle, look only at those that had one (not O(N) per wake-up).
            served: Iterable[int] = range(self.n)
            while True:
                for i in served:
                    if i in missing:
                        velocities[i] = fleet.vehicles[i].setpoint_stamped(stamp)
                        if velocities[i] is not None:
                            missing.discard(i)
                if not missing:
                    break
                if time.monotonic() > deadline:
                    raise WorldAbortError(f"step {k}: no setpoint from drones {sorted(missing)} "
                                          f"within {timeout} s")
                served = fleet.service(0.05)
            for vehicle, velocity in zip(fleet.vehicles, velocities, strict=True):
                assert velocity is not None  # the loop above ends with none missing
                vehicle.integrate(self.dt_s, velocity)
            self.positions[:] = fleet.positions_w
        self._sim_now = None

    def run_realtime(self) -> None:
        limiter = RateLimiter(self.dt_s)
        for k in range(self.options.config.n_steps):
            self.take_beacons()
            if self.fleet is None:
                self.place_external_drones()
                stamps = self.pose_stamps_ms
            else:
                self._wait(0.0)  # telemetry reports the failsafe state: setpoints count first
                stamp = self.boot_ms()
                self.fleet.send_telemetry(stamp)
                stamps = [stamp] * self.n
            # Before the frames: an agent's step k, which starts on frame k, has the relay.
            self.relay_beacons(k)
            self.publish_step(k, stamps)
            self.publish_running(k)
            # Until the next tick: answer MAVLink as it comes, then move every vehicle with
            # what it applies at that moment (its latest setpoint, or a failsafe hold).
            while (remaining := limiter.remaining()) > 0:
                self._wait(remaining)
            limiter.sleep()
            if self.fleet is not None:
                self.move_vehicles(k)

    def move_vehicles(self, step: int) -> None:
        """Realtime tick: move every vehicle for ΔT with what it applies now. Drain first:
        after a stall of this loop (a loaded machine), setpoints that came meanwhile must
        count before any failsafe timer is evaluated."""
        assert self.fleet is not None
        self._wait(0.0)
        self.fleet.fly(self.dt_s)
        self.positions[:] = self.fleet.positions_w
        self._report_failsafes(step)

    def _report_failsafes(self, step: int) -> None:
        """Log each vehicle that has just failed safe (setpoint loss: it holds)."""
        assert self.fleet is not None
        for i, vehicle in enumerate(self.fleet.vehicles):
            if vehicle.failsafe_events > self._failsafes_reported[i]:
                self._failsafes_reported[i] = vehicle.failsafe_events
                self.options.log(
                    f"world: step {step}: drone {i}'s vehicle failed safe (no setpoint for "
                    f"{vehicle.setpoint_timeout_s:g} s): holding, mode {vehicle.mode}")

    def run(self) -> int:
        opts = self.options
        log = opts.log
        try:
            log(f"world: run {opts.run_id}, {self.n} drones, {self.m} targets, mode {opts.mode}, "
                f"vehicles {opts.vehicles} ({opts.config.vehicles.flavour}), zenoh "
                f"{', '.join(opts.listen)}"
                + (f", MAVLink to {opts.mavlink_host}:{opts.mavlink_base}.."
                   f"{opts.mavlink_base + self.n - 1}" if opts.vehicles == "sim" else "")
                + (", MAVLink 2 signing on" if self.fleet is not None
                   and opts.config.vehicles.signing_key_file else ""))
            freeze_heap()  # set up: collect now, not between "every drone ready" and step 0
            self.wait_for_mission_start()
            log("world: every drone ready; mission starts")
            if opts.mode == "lockstep":
                self.run_lockstep()
            else:
                self.run_realtime()
            self.publish_clock(opts.config.n_steps, "done")
            log(f"world: mission complete ({opts.config.n_steps} steps); rejected "
                f"{self.rejected_total()} malformed inputs")
            for line in self.rejections.lines():
                log(f"world: rejected {line}")
            self.linger()
            return EXIT_OK
        except WorldAbortError as err:
            self.publish_clock(0, "aborted", str(err))
            log(f"world: mission aborted: {err}")
            return EXIT_FAILED

    def linger(self) -> None:
        """Keep the router and the vehicles up for a while after the mission, so that the
        agents and the launcher hear "done" before the world goes away (SIGTERM ends it)."""
        deadline = self.now_s() + DONE_LINGER_S
        while self.now_s() < deadline:
            self.publish_clock(self.options.config.n_steps, "done")
            self._wait(0.1)

    def rejected_total(self) -> int:
        fleet_rejections = self.fleet.rejected_frames() if self.fleet is not None else 0
        return self.rejections.total() + fleet_rejections

    def close(self) -> None:
        if self.fleet is not None:
            self.fleet.close()
        for sub in self._subscribers:
            sub.undeclare()
        self.session.close()
