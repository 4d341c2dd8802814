"""One drone as an OS process: the core's per-drone step between Zenoh and MAVLink (SPEC §12).

Inputs: its own position from the autopilot (LOCAL_POSITION_NED, converted in
``swarm.models.frames``), its camera frames (``world/camera/<i>``), its graph neighbours'
consensus messages and every drone's beacon (collision rows), all in one message of the
world's (``world/beacons``: N messages a step through the router instead of N(N − 1)).
Outputs: velocity setpoints to the autopilot, its own consensus messages, beacon and
telemetry. It never reads ``world/truth``.

A step is the same in every mode (``AgentProcess._step``); what the mode decides (how
messages are kept, what a step sees of its neighbours, the loop) is its ``Exchange``
(``swarm.agent.exchange``): ``lockstep`` waits for everything of step k (deterministic),
``realtime`` runs a 50 Hz loop with the newest of everything; neighbour data older than
``runtime.stale_timeout_s`` is left out of the consensus sums and counted.

Realtime membership: the swarm is the own drone and every drone whose beacon was heard within
``runtime.member_timeout_s``; its size is the N of the formulas (``DroneAgent.
set_swarm_size``), so a drone that is lost (its process killed, its link gone) leaves every
survivor's consensus and a restarted one rejoins. A lost drone's vehicle holds where its last
beacon put it, so it stays in the collision rows there (moving on with its last velocity for
at most the vehicle's setpoint-loss failsafe time).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarm.agent.exchange import Mode, Peers, exchange_for
from swarm.agent.qp_failures import QpFailureLog
from swarm.core.consensus_message import ConsensusMessage
from swarm.core.drone_step import DroneAgent, StepDiagnostics
from swarm.errors import EXIT_END_MISSION, EXIT_FAILED, EXIT_OK, VigilError
from swarm.mavlink.link import AutopilotLink, LinkError, PositionSample
from swarm.mavlink.udpin import BoundSocket
from swarm.messages.rules import WireError
from swarm.messages.wire import (
    BeaconRelayWire,
    BeaconWire,
    CameraFrameWire,
    ClockWire,
)
from swarm.models.command_reference import CommandReference
from swarm.net.faults import FaultyPublisher, LinkFaults
from swarm.net.keys import Keys
from swarm.net.rate import freeze_heap
from swarm.net.security import agent_role
from swarm.net.session import (
    TransportError,
    declare_publisher,
    join_router,
    put_stamped,
)
from swarm.net.stores import LatestValues
from swarm.net.subscriptions import DrainedSubscriber, RejectionCounter, subscribe
from swarm.scenario.config import ScenarioConfig, realtime_only_reason
from swarm.scenario.setup import build_agent, initial_drone_positions
from swarm.watch.localization_watch import LocalizationWatch
from swarm.watch.vehicle_watch import VehicleWatch

ROUTER_RETRY_S = 0.05  # the world's router is not up yet: try again this soon


def _drained(subscriber: object) -> DrainedSubscriber:
    """A camera or consensus subscription, which the exchange's ``receiving`` makes a ring or a
    FIFO (``keep_latest``, ``backlog``): the ``DrainedSubscriber`` it is."""
    if not isinstance(subscriber, DrainedSubscriber):
        raise TypeError(f"expected a ring or FIFO subscription, got {subscriber!r}")
    return subscriber


class VehicleNotAsAsked(VigilError):
    """Policy "leave" or "end": the vehicle is not as the agent asked
    (swarm.watch.vehicle_watch)."""


class MissionEnded(Exception):
    """The world said the mission is done (or aborted); leave the loop."""

    def __init__(self, state: str, detail: str = "") -> None:
        super().__init__(f"{state}: {detail}" if detail else state)
        self.state = state


@dataclass(frozen=True)
class AgentOptions:
    config: ScenarioConfig
    drone_id: int
    seed: int
    run_id: str
    mavlink_url: str
    connect: tuple[str, ...]
    listen: tuple[str, ...] = ()
    mode: Mode = "lockstep"
    log: Callable[[str], None] = field(default=print)
    # Test option (realtime): lose or delay this drone's outgoing consensus messages.
    consensus_faults: LinkFaults = field(default_factory=LinkFaults)
    # Where the first failed QPs are saved (swarm.agent.qp_failures); None: only logged.
    qp_dump_dir: Path | None = None
    # mavlink_url's udpin socket, bound before the imports (swarm-agent); None: the link
    # opens its connection itself.
    mavlink_socket: BoundSocket | None = None


class AgentProcess:
    """Zenoh subscriptions, the MAVLink link and the loop around one ``DroneAgent``."""

    def __init__(self, options: AgentOptions) -> None:
        self.options = options
        cfg = options.config
        self.id = options.drone_id
        self.n = cfg.swarm.n_drones
        self.others = set(range(self.n)) - {self.id}
        self._reached = self.n  # drones this one's news reaches (``_watch_reach``)
        # Whom this drone may hear: its graph neighbours, or with radios of limited range
        # anyone (each step's neighbours are then those its radio hears: the exchange).
        self.neighbours = (set(self.others) if cfg.network.ranged
                           else set(cfg.swarm.graph.neighbours[self.id]))
        self.agent: DroneAgent = build_agent(cfg, options.seed, self.id)
        self.codec = cfg.wire_codec()
        self.keys = Keys(options.run_id)
        self.rejections = RejectionCounter()
        # Each sender's own keys (the codec bounds ids to 0..N-1): a string compare per
        # message, not a key parse.
        self._consensus_keys = [self.keys.consensus(j) for j in range(self.n)]
        self.camera_latest: LatestValues[CameraFrameWire] = LatestValues()  # start() waits on it
        self.clock: LatestValues[ClockWire] = LatestValues()
        self.qp_failures = QpFailureLog(options.log, options.qp_dump_dir)
        self.steps_run = 0
        self._telemetry_waiting: list[bytes] = []  # encoded, not sent yet (_queue_telemetry)
        self._flying = np.zeros(3)  # the velocity setpoint last sent (what the vehicle flies)
        # vehicles.setpoints = "tracked": the reference the setpoints follow, and when the
        # last one went out (monotonic s; realtime measures Δt_k, lockstep uses ΔT).
        self.reference = (CommandReference(cfg.vehicles.reference_reset_m)
                          if cfg.vehicles.setpoints == "tracked" else None)
        self.tracking_error_m: float | None = None
        self.velocity_error_m_s: float | None = None

        # The link first: it listens for a second autopilot on its port (EXCLUSIVE_LISTEN_S)
        # while the Zenoh session and subscriptions are set up.
        self.link = AutopilotLink(options.mavlink_url, self.id, cfg.vehicles.flavour,
                                  cfg.vehicles.origin_w(self.id), log=options.log,
                                  signing_key=cfg.vehicles.signing_key(),
                                  bound=options.mavlink_socket)
        self.watch = VehicleWatch(self.link.setpoint_mode)
        self.localization = LocalizationWatch(len(cfg.targets), cfg.gramian.epsilon,
                                              cfg.checks.lambda_tolerance)
        # The realtime subscriptions, drained by the loop: all of them, and by stream.
        self._rings: list[DrainedSubscriber] = []
        self._rings_of: dict[str, list[DrainedSubscriber]] = {}
        # Before the subscriptions: their callbacks store through it.
        self.exchange = exchange = exchange_for(options.mode, Peers(
            self.id, self.neighbours, self.others, cfg, self.agent, self.link,
            self.camera_latest, self._check_clock, options.log, self._drain_rings))
        try:
            self.session = self._open_session()
        except BaseException:
            self.link.close()
            raise
        # How each stream is received and kept is the exchange's (``Exchange.receiving``).
        # Our own beacon never comes back to us.
        receiving, rounds = exchange.receiving, self.agent.n_rounds
        subs = [
            subscribe(self.session, self.keys.camera(self.id), self.codec.decode_camera,
                      self._on_camera, self.rejections, "camera", **receiving("camera", 1)),
            subscribe(self.session, self.keys.clock, self.codec.decode_clock,
                      self._on_clock, self.rejections, "clock", **receiving("clock", 1)),
        ]
        relay = [subscribe(
            self.session, self.keys.beacon_relay, self.codec.decode_beacon_relay,
            self._on_beacon_relay, self.rejections, "beacon relay",
            **receiving("beacons", 1))] if exchange.relayed_beacons else []
        consensus = [subscribe(self.session, self.keys.consensus(j), self.codec.decode_consensus,
                               self._on_consensus, self.rejections, "consensus",
                               on_sent_time=exchange.consensus_sent if exchange.sent_times
                               else None, **receiving("consensus", rounds))
                     for j in sorted(self.neighbours)]
        exchange.attach(_drained(subs[0]), {j: _drained(sub) for j, sub in
                                            zip(sorted(self.neighbours), consensus, strict=True)})
        self._subscribers = subs = subs + relay + consensus

        def rings(group: list) -> list[DrainedSubscriber]:
            return [sub for sub in group if isinstance(sub, DrainedSubscriber)]

        self._rings = rings(subs)
        self._rings_of = {"consensus": rings(consensus), "beacons": rings(relay)}
        # Consensus: blocking or dropping, as the exchange says. Beacons and telemetry never
        # drop: the recorder keeps every one (in realtime, ~2-4 %
        # of the telemetry used to be dropped in zenoh's tx queues on a loaded machine), and
        # a blocked put waits only while a link's queue is full, i.e. well under a step.
        self._pub_consensus = declare_publisher(self.session, self.keys.consensus(self.id),
                                                block=exchange.block_consensus)
        faults = options.consensus_faults
        reason = realtime_only_reason(cfg.vehicles, mode=options.mode,
                                      faulty_consensus=faults.active)
        if reason is not None:
            raise LinkError(f"drone {self.id}: {reason}")
        self._faulty = (FaultyPublisher(self.session, self._pub_consensus, faults)
                        if faults.active else None)
        self._pub_beacon = declare_publisher(self.session, self.keys.beacon(self.id), block=True)
        self._pub_telemetry = declare_publisher(self.session, self.keys.telemetry(self.id),
                                                block=True)

    def _open_session(self):
        """Join the world's router, waiting for it if the world is not up yet."""
        opts = self.options
        mode = "peer" if opts.listen else "client"
        security = opts.config.security
        if security.enabled and opts.listen:
            # Links between peers would bypass the router's access control.
            raise LinkError(f"drone {self.id}: --listen (peer mode) is not available with "
                            "[security]: agents join the world's router as clients")
        try:
            return join_router(
                opts.connect, opts.config.runtime.start_timeout_s, mode=mode,
                listen=opts.listen, tls=security.identity(agent_role(self.id)),
                retry_s=ROUTER_RETRY_S,
                on_wait=lambda: opts.log(f"drone {self.id}: waiting for the world's Zenoh "
                                         f"router at {', '.join(opts.connect)}"))
        except TransportError as err:
            raise LinkError(
                f"drone {self.id}: cannot reach the world's Zenoh router at "
                f"{', '.join(opts.connect)} within {opts.config.runtime.start_timeout_s} s: "
                f"is sim-world running? ({err})") from None

    # -- subscriptions (zenoh threads) ------------------------------------------------------

    def _drain_rings(self, stream: str | None = None) -> None:
        """Take what waits in the rings: every ring, or those of ``stream`` ("consensus",
        "beacons")."""
        for ring in self._rings if stream is None else self._rings_of[stream]:
            ring.drain()

    def _on_clock(self, _key: str, clock: ClockWire, arrived_s: float | None = None) -> None:
        self.clock.put(0, clock, arrived_s=arrived_s)
        if clock.state in ("done", "aborted"):  # whatever the loop waits for is not coming
            self.exchange.close()

    def _on_camera(self, key: str, frame: CameraFrameWire,
                   arrived_s: float | None = None) -> None:
        if frame.drone != self.id:
            self.rejections.reject("camera", f"frame for drone {frame.drone} on {key}")
            return
        self.exchange.put_camera(frame)
        self.camera_latest.put(0, frame, arrived_s=arrived_s)  # every mode: start() waits

    def _on_consensus(self, key: str, msg: ConsensusMessage,
                      arrived_s: float | None = None) -> None:
        if msg.sender not in self.neighbours:
            self.rejections.reject("consensus", f"message from non-neighbour {msg.sender}")
            return
        if key != self._consensus_keys[msg.sender]:  # j's data on another drone's key
            self.rejections.reject("consensus", f"sender {msg.sender} on {key}")
            return
        self.exchange.put_consensus(msg, arrived_s)

    def _on_beacon_relay(self, _key: str, relay: BeaconRelayWire,
                         arrived_s: float | None = None) -> None:
        """Every drone's beacon as the world relays it (the world checked that each came on
        its sender's key), kept whole (realtime)."""
        self.exchange.put_relay(relay, arrived_s)

    # -- helpers ------------------------------------------------------------------------------

    def _check_clock(self) -> None:
        latest = self.clock.get(0)
        if latest is not None and latest[0].state in ("done", "aborted"):
            raise MissionEnded(latest[0].state, latest[0].detail)

    def _publish(self, publisher, message) -> None:
        """Encode (validated: peers would reject what fails) and send; count failures."""
        self._send(publisher, self.codec.encode, message)

    def _encode(self, encode: Callable[..., bytes], *args, **kwargs) -> bytes | None:
        """``encode(*args, **kwargs)`` (one of the codec's checked encoders); None, counted,
        if it refuses the message."""
        try:
            return encode(*args, **kwargs)
        except WireError as err:
            self.rejections.reject("outgoing", err.reason, err.rule)
            return None

    def _send(self, publisher, encode: Callable[..., bytes], *args, stamped: bool = False,
              **kwargs) -> None:
        """Encode with ``encode`` and send (``stamped``: with a Zenoh timestamp of now,
        ``put_stamped``); count failures."""
        payload = self._encode(encode, *args, **kwargs)
        if payload is None:
            return
        if stamped:
            put_stamped(self.session, publisher, payload)
        else:
            publisher.put(payload)

    def _publish_consensus(self, msg: ConsensusMessage | None) -> None:
        payload = None if msg is None else self._encode(self.codec.encode_consensus, msg)
        if payload is None:
            return
        if self._faulty is not None:
            self._faulty.put(payload)
        else:
            put_stamped(self.session, self._pub_consensus, payload)

    def _step(self, step: int, sample: PositionSample, frame: CameraFrameWire | None,
              sample_age_s: float = 0.0, camera_position: np.ndarray | None = None) -> None:
        """One step of the core from the vehicle's ``sample``, the same in every mode: what
        it sees of the others is the exchange's (``sample_age_s``: how old the sample is;
        ``camera_position``: the pose ``frame`` was taken at when not the sample's)."""
        agent, exchange = self.agent, self.exchange
        position, vehicle_velocity = sample.position_w, sample.velocity_w
        exchange.begin(step)
        if self._faulty is not None:
            self._faulty.advance(step)
        detections = frame.detection_list() if frame is not None else []
        communicated = frame.target_velocity_array() if frame is not None else None
        msg = agent.begin_step(step, position, detections, communicated, camera_position)
        # Consensus first: the neighbours wait for it before anything else of this step.
        self._publish_consensus(msg)
        # Realtime: stamped, so a receiver that takes it from its ring later knows when it came.
        self._send(self._pub_beacon, self.codec.encode_beacon, self.id, step,
                   step * self.options.config.scenario.dt_s, position,
                   velocity_m_s=self._flying, sample_age_s=sample_age_s,
                   vehicle_time_ms=sample.time_boot_ms, stamped=exchange.sent_times)
        for rnd in range(agent.n_rounds):
            self._publish_consensus(agent.consensus_round(exchange.inbox(step, rnd)))
        result = agent.finish_step(exchange.beacons(step, sample_age_s, self._flying,
                                                    around=position))
        self.steps_run += 1
        for failed in agent.qp_failures:
            self.qp_failures.report(failed)
        stamp = frame.vehicle_time_ms if frame is not None else 0
        self._send_command(result.velocity, position, vehicle_velocity, stamp)
        self._flying = result.velocity
        self._watch_localization(result.diagnostics)
        self._watch_reach(result.diagnostics)
        self._queue_telemetry(
            result.diagnostics, position, qp_fallbacks=agent.qp_fallbacks,
            rejected_messages=agent.rejected_inputs + self.rejections.total()
            + self.link.rejected_frames,
            missing_neighbour_messages=agent.missing_neighbour_messages,
            stale_neighbour_messages=exchange.stale_messages, late_steps=exchange.late_steps,
            steps=self.steps_run,
            neighbour_age_ms=exchange.neighbour_age_ms, swarm_size=agent.swarm_size,
            mavlink_state=f"{'armed' if self.link.armed else 'disarmed'} {self.link.mode}",
            rate_limit_releases=agent.rate_limit_releases,
            safety_conflicts=agent.safety_conflicts, link_conflicts=agent.link_conflicts,
            splits_said=agent.splits_said,
            reference_resets=self.reference.resets if self.reference is not None else 0,
            tracking_error_m=self.tracking_error_m,
            velocity_error_m_s=self.velocity_error_m_s,
            vehicle_events=self.watch.events, vehicle_status=self._vehicle_status(),
            lambda_breaches=self.localization.breaches,
            first_lambda_breach_s=self.localization.first_breach_s,
            localization_status=self.localization.status())
        self._watch_vehicle(step, sample_age_s)

    def _queue_telemetry(self, *args, **kwargs) -> None:
        """This step's telemetry (``codec.encode_telemetry``'s arguments), sent once the
        exchange's ``telemetry_steps`` of them are waiting."""
        payload = self._encode(self.codec.encode_telemetry, *args, **kwargs)
        if payload is None:
            return
        self._telemetry_waiting.append(payload)
        if len(self._telemetry_waiting) >= self.exchange.telemetry_steps:
            self._flush_telemetry()

    def _flush_telemetry(self) -> None:
        """Send the telemetry waiting: one step as its own ``TelemetryWire``, several as a
        ``TelemetryBatchWire``."""
        waiting, self._telemetry_waiting = self._telemetry_waiting, []
        if len(waiting) > 1:
            self._send(self._pub_telemetry, self.codec.encode_telemetry_batch, waiting)
        elif waiting:
            self._pub_telemetry.put(waiting[0])

    def _vehicle_status(self) -> str:
        problem = self.watch.problem
        if not problem:
            return ""
        return f"{self.options.config.vehicles.on_vehicle_event}: {problem}"[:64]

    def _watch_reach(self, diag: StepDiagnostics) -> None:
        """Say at once when this drone's news stops reaching some drones (the swarm has split,
        docs/network.md) or reaches them again: a log line at each change."""
        if not self.options.config.network.ranged or diag.reached == self._reached:
            return
        previous, self._reached = self._reached, diag.reached
        if diag.reached < self.n:
            self.options.log(f"drone {self.id}: step {diag.step}: the swarm has split: this "
                             f"drone's part has {diag.reached} of {self.n} drones (N = "
                             f"{diag.reached} in its formulas)")
        elif previous < self.n:
            self.options.log(f"drone {self.id}: step {diag.step}: the swarm is whole again "
                             f"({self.n} drones)")

    def _watch_localization(self, diag: StepDiagnostics) -> None:
        """Say at once when an own λ̄ copy goes below ε − tol, or comes back
        (swarm.watch.localization_watch): a log line now, the counters in this step's telemetry."""
        for event in self.localization.update(diag.time_s, diag.lambda_bar,
                                              control_active=diag.control_active,
                                              swarm_size=self.agent.swarm_size):
            self.options.log(event.describe(self.id))

    def _watch_vehicle(self, step: int, sample_age_s: float) -> None:
        """Compare the vehicle with what was asked (swarm.watch.vehicle_watch); log a change
        with its time and apply ``vehicles.on_vehicle_event``."""
        link = self.link
        event = self.watch.update(step * self.options.config.scenario.dt_s, armed=link.armed,
                                  mode=link.mode, position_age_s=sample_age_s)
        if event is None:
            return
        policy = self.options.config.vehicles.on_vehicle_event
        self.options.log(event.describe(self.id) + (
            f"; policy {policy}" if event.problem else ""))
        if event.problem and policy != "continue":
            raise VehicleNotAsAsked(policy)

    def _send_command(self, velocity: np.ndarray, position: np.ndarray,
                      vehicle_velocity: np.ndarray | None, stamp: int) -> None:
        """The step's command to the autopilot: velocity only, or the setpoint along the
        command reference (``vehicles.setpoints``); the tracking errors measured on the way."""
        if vehicle_velocity is not None:
            self.velocity_error_m_s = float(np.linalg.norm(vehicle_velocity - self._flying))
        if self.reference is None:
            self.link.send_velocity(velocity, stamp)
            return
        if self.watch.problem:  # the vehicle flies a mode of its own: start again from it
            self.reference.restart()
        elapsed = self.exchange.setpoint_interval_s()
        p = position.tolist()
        v = None if vehicle_velocity is None else vehicle_velocity.tolist()
        sp = self.reference.setpoint((p[0], p[1], p[2]), v, tuple(velocity.tolist()), elapsed)
        self.tracking_error_m = sp.position_error_m
        if sp.reset:
            self.options.log(f"drone {self.id}: vehicle {sp.position_error_m:.2f} m from the "
                             f"command reference: reference put back on it "
                             f"({self.reference.resets} resets)")
        self.link.send_tracked(sp.position_w, sp.velocity_w, sp.acceleration_w, stamp)

    # -- phases ------------------------------------------------------------------------------

    def start(self) -> None:
        """MAVLink handshake, then keep the setpoint stream alive until the mission starts."""
        cfg = self.options.config
        freeze_heap()  # set up: collect now, not between the handshake and the first step
        # On the ground, the vehicle climbs to the drone's start position (the world's emulated
        # vehicles start there in the air, as the thesis does; real ones may start anywhere).
        start_position = initial_drone_positions(cfg, self.options.seed)[self.id]
        self.link.handshake(timeout_s=cfg.runtime.start_timeout_s,
                            start_position_w=start_position)
        self.options.log(f"drone {self.id}: armed and streaming; waiting for the mission")
        deadline = time.monotonic() + cfg.runtime.start_timeout_s
        while self.camera_latest.get(0) is None:
            self._check_clock()
            if time.monotonic() > deadline:
                raise LinkError(f"drone {self.id}: the mission did not start within "
                                f"{cfg.runtime.start_timeout_s} s")
            self.link.keepalive(time.monotonic())
            sample = self.exchange.announce()
            if sample is not None:
                self._publish(self._pub_beacon, BeaconWire.build(
                    sender=self.id, step=0, time_s=0.0, position_m=sample.position_w,
                    vehicle_time_ms=sample.time_boot_ms))
            self.exchange.wait_first_frame(0.05)

    def run(self) -> int:
        """The mission; whatever ends it (done, an error, Ctrl-C/SIGTERM), the vehicle gets a
        zero-velocity setpoint and then the configured end action (``vehicles.end_action``)."""
        try:
            return self._run()
        finally:
            try:
                self._flush_telemetry()  # the steps still waiting: nothing run goes unsent
            except Exception as err:  # the session may be what failed: still end the mission
                self.options.log(f"drone {self.id}: last telemetry not sent: {err}")
            self.link.end_mission(self.options.config.vehicles.end_action)
            for line in self.rejections.lines():
                self.options.log(f"drone {self.id}: rejected {line}")
            for reason, count in sorted(self.link.rejections.items()):
                self.options.log(f"drone {self.id}: rejected MAVLink: {count} × {reason}")
            if self._faulty is not None:
                f = self._faulty
                self.options.log(
                    f"drone {self.id}: injected consensus faults: {f.dropped} messages lost, "
                    f"{f.delayed} delayed {f.faults.delay_steps} steps, of {f.offered}")

    def _run(self) -> int:
        log = self.options.log
        try:
            self.start()
            self.exchange.run(self._step)
        except MissionEnded as over:
            if over.state == "done":
                log(f"drone {self.id}: mission complete; {self.agent.qp_fallbacks} QP "
                    f"fallbacks ({self.qp_failures.count} QPs not solved), "
                    f"{self.exchange.late_steps} late steps, {self.exchange.unpaired_frames} "
                    f"frames measured from the newest pose (theirs not kept), "
                    f"{self.rejections.total() + self.link.rejected_frames} rejected inputs")
                return EXIT_OK
            log(f"drone {self.id}: mission aborted by the world: {over}")
            return EXIT_FAILED
        except LinkError as err:
            log(str(err) if str(err).startswith("drone ") else f"drone {self.id}: {err}")
            return EXIT_FAILED
        except VehicleNotAsAsked as policy:
            if str(policy) == "end":
                log(f"drone {self.id}: ending the mission (vehicles.on_vehicle_event = end)")
                return EXIT_END_MISSION
            log(f"drone {self.id}: leaving the swarm (vehicles.on_vehicle_event = leave)")
            return EXIT_FAILED
        return EXIT_OK

    def close(self) -> None:
        self.exchange.close()  # ends its waits, and the thread that ends them
        for sub in self._subscribers:
            sub.undeclare()
        self.link.close()
        self.session.close()
