"""How one agent's step meets the rest of the swarm: one protocol, one class per mode.

``AgentProcess`` owns what every mode shares (the Zenoh session, the MAVLink link, the core,
the publishers, the checks on who sent what) and runs one step the same way in every mode
(``AgentProcess.step``). What a mode decides is here, behind ``Exchange``:

* how messages are received and kept (``receiving``, ``sent_times``) and stored
  (``put_camera``, ``put_consensus``, and with ``relayed_beacons`` ``put_relay``: the world's
  relay, ``world/beacons``, which carries every drone's beacon packed in one message, kept
  whole as arrays);
* what a step sees of its neighbours (``inbox``: the consensus messages of a round) and of
  the other drones (``beacons``: positions for the collision rows and formation bearings,
  ``around`` the own position only those the step can use), and the swarm size N
  (``begin``);
* the time between two setpoints (``setpoint_interval_s``), what is sent before the mission
  starts (``announce``) and the loop that paces the steps (``run``).

``LockstepExchange``: step k waits for the camera frame of step k, the position sample
stamped with that frame's ``vehicle_time_ms`` and every neighbour's round messages (frames and
messages taken by the step's own thread from FIFOs, ``DrainedSubscriber.receive_one``); the other
drones' positions of step k come with the frame (``CameraFrameWire.drone_positions``: what
their vehicles report, as their beacons would carry them): deterministic (equal to the
in-process reference bit for bit).
``RealtimeExchange``: a loop on the wall clock with the newest of everything, each drone's
at its own phase after the world's tick (``loop_phase_s``); neighbour data older than
``runtime.stale_timeout_s`` is left out and counted; N follows the drones the world's relay
says it heard within ``runtime.member_timeout_s``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from swarm.agent.nearby import carry, nearby
from swarm.core.consensus_message import ConsensusMessage
from swarm.core.drone_step import DroneAgent
from swarm.errors import UsageError
from swarm.mavlink.link import AutopilotLink, LinkError, PositionSample
from swarm.messages.native import RELAY_HELD, RELAY_WIDTH
from swarm.messages.wire import BeaconRelayWire, CameraFrameWire
from swarm.net.rate import RateLimiter
from swarm.net.stores import LatestValues, StepMailbox
from swarm.net.subscriptions import BlockingReceives, DrainedSubscriber
from swarm.scenario.config import ScenarioConfig

Mode = Literal["lockstep", "realtime"]
# What an agent subscribes to: its camera frames, the world's clock, the world's beacon relay
# (realtime) and each neighbour's consensus messages.
Stream = Literal["camera", "clock", "beacons", "consensus"]
# ``beacons(..., around=p)`` hands the core the drones within R_ca plus this of p: the core
# applies R_ca itself (``kernels.qp_rows``), so the margin only has to cover rounding [m].
VICINITY_MARGIN_M = 0.5
WAIT_SLICE_S = 0.25  # how often a lockstep wait's deadline is looked at (BlockingReceives)
# A lockstep agent sends its telemetry this many steps at a time (``TelemetryBatchWire``):
# every message costs a put, the router's forwarding and the observer's receiving, and the
# steps come every ~3 ms of wall time. Case 2, lockstep, 20 s, side by side: telemetry
# once per step cost ~11 % of the real-time factor (6.5× against 7.2× with none);
# LOCKSTEP_TELEMETRY_STEPS = 10 keeps every step's message and holds it at most ~30 ms.
LOCKSTEP_TELEMETRY_STEPS = 10
# A lockstep agent's camera frames and each neighbour's consensus messages wait in a FIFO
# inside zenoh for the step's thread. A source is never more than a step ahead (step k + 1
# needs every setpoint of step k): its FIFO holds at most two steps of its messages. But
# anything on its key waits there until the step's next wait for it, which takes it (and
# decodes, and counts a junk payload) on the way; a full FIFO would hold up the session's
# receiving until then. So the bound is only against runaway memory (a FIFO allocates as
# samples wait): a bound of 32 stalled the fuzz test's swarm under 10 000 junk payloads per
# key, which now wait and are counted a step later.
LOCKSTEP_BACKLOG = 1 << 16
FIRST_FRAME_POLL_S = 0.01  # before the mission: how often the frame's ring or FIFO is looked at

# One step of the agent: (step, the vehicle's position sample, the camera frame or None, the
# sample's age [s], the pose the frame was taken from when not the sample's).
StepFunction = Callable[[int, PositionSample, "CameraFrameWire | None", float,
                         "np.ndarray | None"], None]


@dataclass
class Peers:
    """What an exchange needs of the process: who is who, the core, the link, the log, the
    frames every mode waits on before the start, and how to learn that the mission ended
    (``check_clock`` raises when it has)."""

    drone_id: int
    neighbours: set[int]
    others: set[int]
    config: ScenarioConfig
    agent: DroneAgent
    link: AutopilotLink
    camera_latest: LatestValues[CameraFrameWire]
    check_clock: Callable[[], None]
    log: Callable[[str], None]
    # Take what waits in the subscriptions' rings (realtime: ``DrainedSubscriber.drain``):
    # ``drain()`` every ring, ``drain("consensus")`` / ``drain("beacons")`` only the rings of
    # the neighbours' consensus messages / of the world's beacon relay.
    drain: Callable[..., None]


class Vicinity:
    """Which other drones a step can use: those within R_ca (+ ``VICINITY_MARGIN_M``) of
    the own position, for the collision rows, and the graph neighbours wherever they are,
    for the formation bearings. Everything else the core would leave out anyway, so the
    step's Python work grows with the drones around, not with N: the selection is one
    compiled pass over all N (``swarm.agent.nearby``)."""

    def __init__(self, peers: Peers) -> None:
        n = peers.config.swarm.n_drones
        self.radius_m = peers.config.control.collision_radius_m + VICINITY_MARGIN_M
        self.always = bytes(j in peers.neighbours for j in range(n))


class Exchange(Protocol):
    """The mode of an agent's exchange (module docstring)."""

    relayed_beacons: bool  # the others' positions come in the world's relay (put_relay)
    block_consensus: bool  # a consensus put waits for room (True) or drops (False)
    sent_times: bool  # read each consensus message's Zenoh timestamp (neighbour age)
    telemetry_steps: int  # steps of telemetry per message (AgentProcess sends them together)
    late_steps: int
    unpaired_frames: int
    stale_messages: int
    neighbour_age_ms: float

    def receiving(self, stream: Stream, per_step: int) -> dict[str, Any]: ...
    def attach(self, camera: DrainedSubscriber,
               consensus: Mapping[int, DrainedSubscriber]) -> None: ...
    def put_camera(self, frame: CameraFrameWire) -> None: ...
    def put_consensus(self, msg: ConsensusMessage, arrived_s: float | None = None) -> None: ...
    def consensus_sent(self, msg: ConsensusMessage, sent_unix_s: float) -> None: ...
    def put_relay(self, relay: BeaconRelayWire, arrived_s: float | None = None) -> None: ...
    def close(self) -> None: ...
    def announce(self) -> PositionSample | None: ...
    def wait_first_frame(self, timeout_s: float) -> None: ...
    def begin(self, step: int) -> None: ...
    def inbox(self, step: int, rnd: int) -> dict[int, ConsensusMessage]: ...
    def beacons(self, step: int, sample_age_s: float, flying: np.ndarray, *,
                around: np.ndarray | None = None) -> dict[int, list[float]]: ...
    def setpoint_interval_s(self) -> float: ...
    def run(self, step: StepFunction) -> None: ...


class LockstepExchange:
    """Everything keyed by (step, round), waited for (module docstring)."""

    relayed_beacons = False  # the camera frame of step k carries every drone's position
    block_consensus = True  # peers wait for every message
    sent_times = False  # lockstep reports no neighbour age: its hot path skips them
    telemetry_steps = LOCKSTEP_TELEMETRY_STEPS

    def __init__(self, peers: Peers) -> None:
        self.peers = peers
        self.vicinity = Vicinity(peers)
        self.camera_steps: StepMailbox[CameraFrameWire] = StepMailbox()
        self.consensus_steps: StepMailbox[ConsensusMessage] = StepMailbox()
        self._neighbour_order = sorted(peers.neighbours)
        self._camera_from: dict[int, DrainedSubscriber] = {}
        self._consensus_from: dict[int, DrainedSubscriber] = {}
        self._receives: BlockingReceives | None = None  # attach
        self._closed = False
        self.late_steps = self.unpaired_frames = self.stale_messages = 0
        self.neighbour_age_ms = math.nan

    def receiving(self, stream: Stream, per_step: int) -> dict[str, Any]:
        """The camera frames and each neighbour's consensus: a FIFO inside zenoh, from
        which the step's thread takes them while it waits for them (``attach``). The clock:
        a callback on zenoh's receiving thread, which must end any wait."""
        if stream in ("camera", "consensus"):
            return {"backlog": LOCKSTEP_BACKLOG}
        return {"direct": True}

    def attach(self, camera: DrainedSubscriber,
               consensus: Mapping[int, DrainedSubscriber]) -> None:
        """The FIFOs of ``receiving``: the camera's, and the consensus one of each
        neighbour."""
        if set(consensus) != self.peers.neighbours:
            raise ExchangeError(f"consensus subscriptions for {sorted(consensus)}, expected "
                                f"the neighbours {sorted(self.peers.neighbours)}")
        self._camera_from = {0: camera}
        self._consensus_from = dict(consensus)
        self._receives = BlockingReceives([camera, *consensus.values()],
                                          check_period_s=WAIT_SLICE_S)
        if self._closed:
            self._receives.close()

    def put_camera(self, frame: CameraFrameWire) -> None:
        self.camera_steps.put(frame.step, 0, 0, frame)

    def put_consensus(self, msg: ConsensusMessage, arrived_s: float | None = None) -> None:
        self.consensus_steps.put(msg.step, msg.round, msg.sender, msg)

    def consensus_sent(self, msg: ConsensusMessage, sent_unix_s: float) -> None:
        return None

    def put_relay(self, relay: BeaconRelayWire, arrived_s: float | None = None) -> None:
        raise ExchangeError("a lockstep agent takes the other drones' positions from its "
                            "camera frame, not from a relay of beacons")

    def close(self) -> None:
        """End every wait now and for good (the mission is over, or the process closes)."""
        self._closed = True
        for mailbox in (self.camera_steps, self.consensus_steps):
            mailbox.close()
        if self._receives is not None:
            self._receives.close()

    def announce(self) -> PositionSample | None:
        return None  # the world steps every vehicle of its own; nobody waits to hear us

    def wait_first_frame(self, timeout_s: float) -> None:
        """Until the first frame or ``timeout_s``: the camera's FIFO is looked at every
        ``FIRST_FRAME_POLL_S`` (before the mission only: a wait on it cannot time out)."""
        if not self._camera_from:
            raise ExchangeError("attach first: a lockstep agent takes its frames from its "
                                "camera subscription")
        poll_first_frame(self.peers, self._camera_from[0].drain, timeout_s)

    def begin(self, step: int) -> None:
        return None  # N is the configured swarm

    def inbox(self, step: int, rnd: int) -> dict[int, ConsensusMessage]:
        """Every neighbour's message of (step, round), taken from its FIFO in arrival order
        (a message of a later round or step is kept for its own inbox). With radios of limited
        range the neighbours are those the step's camera frame says this drone hears; what the
        others sent is taken from their FIFOs and left to be pruned."""
        heard = (self._frame(step).radio_neighbours() if self.peers.config.network.ranged
                 else None)
        if heard is None:
            return self._take(self.consensus_steps, step, rnd, self._consensus_from,
                              self._neighbour_order, f"round-{rnd} consensus")
        for j, fifo in self._consensus_from.items():
            if j not in heard:
                fifo.drain()
        got = self._take(self.consensus_steps, step, rnd, self._consensus_from, heard,
                         f"round-{rnd} consensus")
        return {j: got[j] for j in heard}

    def _frame(self, step: int) -> CameraFrameWire:
        return self._take(self.camera_steps, step, 0, self._camera_from, (0,),
                          "camera frame")[0]

    def _take(self, mailbox: StepMailbox, step: int, rnd: int,
              fifos: Mapping[int, DrainedSubscriber], senders: Sequence[int],
              what: str) -> dict:
        """(step, round) of every sender: what the mailbox holds, and what the senders'
        FIFOs bring, taken in arrival order on this thread until it is complete, watching
        for the mission end and the lockstep deadline."""
        mailbox.prune(step)
        got = mailbox.get(step, rnd)
        missing = [j for j in senders if j not in got]
        if not missing:
            return got
        if self._receives is None:
            raise ExchangeError(f"attach first: a lockstep agent waits for its {what} on "
                                "its subscriptions")
        timeout_s = self.peers.config.runtime.lockstep_timeout_s
        self._receives.arm(time.monotonic() + timeout_s)
        try:
            while missing:
                if not fifos[missing[0]].receive_one():
                    self.peers.check_clock()  # the mission ended: that is why
                    if self._receives.expired:
                        raise LinkError(f"drone {self.peers.drone_id}: step {step}: no "
                                        f"{what} from {missing} within {timeout_s} s")
                    raise LinkError(f"drone {self.peers.drone_id}: step {step}: the exchange "
                                    f"closed while waiting for {what} from {missing}")
                got = mailbox.get(step, rnd)
                missing = [j for j in senders if j not in got]
            return got
        finally:
            self._receives.arm(None)

    def beacons(self, step: int, sample_age_s: float, flying: np.ndarray, *,
                around: np.ndarray | None = None) -> dict[int, list[float]]:
        """The other drones' positions at step k (``around`` a position: those the step can
        use, ``Vicinity``), all of the same instant: those the camera frame of step k carries
        (its vehicle's report, as its beacon of step k would say), as lists of floats,
        bit-exact."""
        frame = self._frame(step)
        positions = frame.drone_positions
        if positions is None:
            raise LinkError(f"drone {self.peers.drone_id}: step {step}: the camera frame "
                            "carries no drone positions (a lockstep world sends them)")
        vicinity = self.vicinity
        return nearby(positions.native(), 3, None, self.peers.drone_id, None,
                      None if around is None else around.tolist(), vicinity.radius_m,
                      vicinity.always)

    def setpoint_interval_s(self) -> float:
        return self.peers.config.scenario.dt_s

    def run(self, step: StepFunction) -> None:
        timeout_s = self.peers.config.runtime.lockstep_timeout_s
        k = 0
        while True:
            frame = self._frame(k)
            sample = self.peers.link.wait_position(frame.vehicle_time_ms, timeout_s)
            step(k, sample, frame, 0.0, None)
            k += 1


class RealtimeExchange:
    """The newest of everything, on the wall clock (module docstring)."""

    # Samples wait in bounded rings inside zenoh (``receiving``: a few steps' worth of every
    # source; no Python, no GIL) and the loop takes them where it reads them (``drain``: every
    # ring at each tick, the consensus rings before each round's inbox and the relay's before
    # the beacons; an empty ring's drain costs ~10 µs of a cold loop), so receiving never
    # preempts the step. Direct callbacks preempted it (Case 2 scaled to N = 12: 21-38 % late
    # steps), a Python thread per ring less so (11-13 % that day; on another, side by side,
    # 44 % with a thread per ring against 7 % drained here). Zenoh's own unbounded queue
    # grew by ~300 kB/s per agent on an overloaded machine (Case 2 at N = 24) while the
    # agents fell ever further behind.
    relayed_beacons = True
    block_consensus = False  # the newest message is what counts: drop when the queue is full
    sent_times = True
    telemetry_steps = 1  # live: each step's as it is made

    def __init__(self, peers: Peers, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.peers = peers
        n = peers.config.swarm.n_drones
        self.vicinity = Vicinity(peers)
        self._clock = clock
        # One store per mode: a step mailbox nobody waits on is never pruned (realtime agents
        # piled up to its 65 536 entries, ~100 MB, over a long mission).
        self.consensus_latest: LatestValues[ConsensusMessage] = LatestValues(clock=clock)
        # The world's newest relay, whole: it carries every drone the world has heard, so a
        # newer one replaces it entirely (``put_relay``).
        self.relay: HeldRelay | None = None
        self._members_key = b""
        # When each neighbour's newest consensus message of each round left it (its Zenoh
        # timestamp, Unix s): the reported neighbour age includes the hop, not only the wait.
        self._consensus_sent: dict[tuple[int, int], float] = {}
        self.late_steps = self.unpaired_frames = self.stale_messages = 0
        self.neighbour_age_ms = math.nan
        self.members = frozenset(range(n))  # drones heard recently, self included
        self._first_step_s: float | None = None
        self._last_setpoint_s: float | None = None  # monotonic s

    def receiving(self, stream: Stream, per_step: int) -> dict[str, Any]:
        return {"keep_latest": 4 * per_step}  # rings of a few steps' worth, every stream

    def attach(self, camera: DrainedSubscriber,
               consensus: Mapping[int, DrainedSubscriber]) -> None:
        return None  # their rings are drained by the loop (Peers.drain)

    def put_camera(self, frame: CameraFrameWire) -> None:
        return None  # the loop reads the newest frame (``Peers.camera_latest``)

    def put_consensus(self, msg: ConsensusMessage, arrived_s: float | None = None) -> None:
        self.consensus_latest.put((msg.sender, msg.round), msg, arrived_s=arrived_s)

    def consensus_sent(self, msg: ConsensusMessage, sent_unix_s: float) -> None:
        if msg.sender in self.peers.neighbours:
            self._consensus_sent[(msg.sender, msg.round)] = sent_unix_s

    def put_relay(self, relay: BeaconRelayWire, arrived_s: float | None = None) -> None:
        """The world's relay, which arrived at ``arrived_s`` (None: now; never later than
        now), in place of the one held, unless it is older (a lower step). Our own beacon,
        which comes back with everyone's, is left out."""
        held = self.relay
        if held is not None and relay.step < held.step:
            return
        now = self._clock()
        ids = relay.sender_ids()
        self.relay = HeldRelay(relay.step, ids, ids.tolist(), relay.rows(),
                               now if arrived_s is None else min(arrived_s, now))

    def beacon_ages(self) -> dict[int, float]:
        """How old each held beacon is [s]: since its arrival at the world."""
        relay = self.relay
        if relay is None:
            return {}
        own = self.peers.drone_id
        return {j: age for j, age in zip(relay.id_list, relay.ages_s(self._clock()).tolist(),
                                         strict=True) if j != own}

    def close(self) -> None:
        return None  # nothing waits: the loop checks the clock every tick

    def announce(self) -> PositionSample | None:
        """The vehicle's position before the start: a world without simulated vehicles
        starts when it has heard every drone."""
        return self.peers.link.latest_position()

    def wait_first_frame(self, timeout_s: float) -> None:
        """Until the first frame or ``timeout_s``: the rings are looked at every
        ``FIRST_FRAME_POLL_S`` (before the mission only; nothing wakes a wait on a ring)."""
        poll_first_frame(self.peers, self.peers.drain, timeout_s)

    def begin(self, step: int) -> None:
        """N = the own drone and the drones heard within ``member_timeout_s``.

        The mission starts once every vehicle is ready, which most agents learn before their
        first beacon goes out: a drone not heard at all yet counts as present until
        ``member_timeout_s`` after our first step."""
        peers = self.peers
        if peers.config.network.ranged:
            return  # the drone's reach stamps say who is in its part (docs/network.md)
        timeout = peers.config.runtime.member_timeout_s
        now = self._clock()
        if self._first_step_s is None:
            self._first_step_s = now
        present = np.zeros(peers.config.swarm.n_drones, dtype=bool)
        relay = self.relay
        if now - self._first_step_s <= timeout:
            present[:] = True
            if relay is not None:  # heard once: present while heard recently
                present[relay.ids] = False
        if relay is not None:
            present[relay.ids[relay.ages_s(now) <= timeout]] = True
        present[peers.drone_id] = True
        key = present.tobytes()  # one comparison of N bytes, not a set of N ids, per step
        if key == self._members_key:
            return
        self._members_key = key
        members = frozenset(np.flatnonzero(present).tolist())
        if members == self.members:
            return
        left, joined = sorted(self.members - members), sorted(members - self.members)
        self.members = members
        peers.agent.set_swarm_size(len(members))
        changes = []
        if left:
            changes.append(f"drones {left} not heard for {timeout} s left")
        if joined:
            changes.append(f"drones {joined} joined")
        peers.log(f"drone {peers.drone_id}: step {step}: {'; '.join(changes)}: swarm of "
                  f"{len(members)} now")

    def inbox(self, step: int, rnd: int) -> dict[int, ConsensusMessage]:
        """Each neighbour's newest message of this round, if fresh enough (what came since the
        loop's tick is taken first: only the consensus rings, the others are read later)."""
        self.peers.drain("consensus")
        stale_after = self.peers.config.runtime.stale_timeout_s
        inbox: dict[int, ConsensusMessage] = {}
        ages = []
        now_unix = time.time()
        candidates: Collection[int] = self.peers.neighbours
        if self.peers.config.network.ranged:  # whom the newest frame says the radio hears
            newest = self.peers.camera_latest.get(0)
            heard = None if newest is None else newest[0].radio_neighbours()
            candidates = () if heard is None else heard
        for j in candidates:
            latest = self.consensus_latest.get((j, rnd))
            if latest is None:
                continue
            msg, age = latest
            if age > stale_after:
                self.stale_messages += 1
                continue
            inbox[j] = msg
            # From the neighbour's put to now (the hop included); without a timestamp, from
            # its arrival. A skewed clock never makes an age negative.
            sent = self._consensus_sent.get((j, rnd))
            ages.append(max(now_unix - sent, age) if sent is not None else age)
        self.neighbour_age_ms = 1000.0 * min(ages) if ages else math.nan
        return inbox

    def beacons(self, step: int, sample_age_s: float, flying: np.ndarray, *,
                around: np.ndarray | None = None) -> dict[int, list[float]]:
        """The other drones' latest beacons (``around`` a position: those the step can use,
        ``Vicinity``), each position carried forward to the instant of our own position
        sample (p_j + v_j·a_j − v_i·a_i, a = age of the sample; ``flying`` = v_i, the
        velocity last sent): the collision rows see the relative position as it is, not as
        it was up to a step ago.

        A beacon older than the stale timeout belongs to a drone that is late or lost; its
        vehicle flies the last setpoint until its failsafe holds it, so it is carried forward
        for at most that long and kept there: nobody flies into a hovering drone."""
        self.peers.drain("beacons")
        relay = self.relay
        if relay is None:
            return {}
        # One compiled pass over the relay: each row p + min(a_j + age_j, hold)·v − a_i·v_i
        # (age_j = the relay's age + how long the world held it), then the vicinity.
        forward = carry(max(self._clock() - relay.arrived_s, 0.0), sample_age_s,
                        flying.tolist(), self.peers.config.vehicles.failsafe_timeout_s)
        vicinity = self.vicinity
        return nearby(relay.rows, RELAY_WIDTH, relay.id_list, self.peers.drone_id, forward,
                      None if around is None else around.tolist(), vicinity.radius_m,
                      vicinity.always)

    def setpoint_interval_s(self) -> float:
        """Measured: the wall time since the last setpoint (ΔT before the first)."""
        now = time.monotonic()
        last, self._last_setpoint_s = self._last_setpoint_s, now
        return self.peers.config.scenario.dt_s if last is None else max(now - last, 1e-3)

    def run(self, step: StepFunction) -> None:
        peers = self.peers
        link = peers.link
        n_steps = peers.config.n_steps
        last_frame_step = -1
        current: PositionSample | None = None
        # Count steps from the world's step of the first frame: with both loops on the wall
        # clock (RateLimiter keeps phase), step k here is sim time k·ΔT there, so telemetry
        # lines up with truth and the filter predicts exactly as far as the targets moved.
        first = peers.camera_latest.get(0)
        k = first[0].step if first is not None else 0
        # The loop ticks at its own phase after the world's (which the first frame's stamp
        # gives), so that the agents' steps are spread over the period instead of all
        # contending for the cores at once.
        now = time.monotonic()
        first_tick_s = (now - (first[1] if first is not None else 0.0)
                        + loop_phase_s(peers.drone_id, peers.config.swarm.n_drones,
                                       peers.config.scenario.dt_s))
        if first_tick_s > now:
            time.sleep(first_tick_s - now)
        limiter = RateLimiter(peers.config.scenario.dt_s, first_tick_s=first_tick_s)
        while True:
            peers.drain()
            peers.check_clock()
            current = link.latest_position() or current
            latest = peers.camera_latest.get(0)
            frame = camera_position = None
            if latest is not None and latest[0].step != last_frame_step:
                frame = latest[0]
                last_frame_step = frame.step
                # The frame was rendered from the pose stamped vehicle_time_ms, one step or
                # more before the newest sample: measure from that pose. (Six ArduCopter
                # SITLs on two cores: the estimate error went above 0.1 m in the last 10 s
                # of 1 mission in 7, against 4 in 6 measuring from the newest pose.)
                taken_at = link.position_at(frame.vehicle_time_ms)
                if taken_at is None:
                    self.unpaired_frames += 1
                else:
                    camera_position = taken_at.position_w
            # The mission has n_steps: past its last step (the world's "done" not yet here)
            # the agent only holds its vehicle (keepalive) and waits for the end.
            if k >= n_steps:
                link.keepalive()
            elif current is not None:
                step(k, current, frame, max(time.monotonic() - current.received_s, 0.0),
                     camera_position)
                k += 1
            if limiter.sleep():
                self.late_steps += 1


@dataclass(frozen=True)
class HeldRelay:
    """The world's relay as a realtime agent holds it: the senders (as an array and a list)
    and their ``BeaconRelayWire`` rows, and when it arrived [s, the exchange's clock]."""

    step: int
    ids: NDArray[np.intp]
    id_list: list[int]
    rows: np.ndarray
    arrived_s: float

    def ages_s(self, now_s: float) -> np.ndarray:
        """Each beacon's age at ``now_s``: since it reached the world (the relay's age plus
        how long the world had held it), never negative."""
        return max(now_s - self.arrived_s, 0.0) + self.rows[:, RELAY_HELD]


def poll_first_frame(peers: Peers, drain: Callable[[], object], timeout_s: float) -> None:
    """Until the first camera frame is held or ``timeout_s`` has passed: ``drain`` (what
    takes the waiting samples) every ``FIRST_FRAME_POLL_S``. Before the mission only: rings
    and FIFOs wake nobody, and a wait on a FIFO cannot time out."""
    deadline = time.monotonic() + timeout_s
    while True:
        drain()
        remaining = deadline - time.monotonic()
        if peers.camera_latest.get(0) is not None or remaining <= 0:
            return
        time.sleep(min(FIRST_FRAME_POLL_S, remaining))


def loop_phase_s(drone_id: int, n_drones: int, period_s: float) -> float:
    """How long after the world's tick drone ``drone_id``'s realtime loop ticks [s]: the N
    loops spread evenly over the period, none at the world's own tick."""
    return period_s * (drone_id + 1) / (n_drones + 1)


EXCHANGES: dict[Mode, type[LockstepExchange] | type[RealtimeExchange]] = {
    "lockstep": LockstepExchange, "realtime": RealtimeExchange}


class ExchangeError(UsageError, ValueError):
    """An exchange asked for what it does not do: a mode that does not exist, a relay of
    beacons in lockstep."""


def exchange_for(mode: str, peers: Peers) -> Exchange:
    """The exchange of ``mode`` ("lockstep", "realtime")."""
    kind = EXCHANGES.get(mode)  # type: ignore[call-overload]
    if kind is None:
        raise ExchangeError(f"unknown mode {mode!r} (expected one of {', '.join(EXCHANGES)})")
    return kind(peers)
