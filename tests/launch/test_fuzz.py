"""Bad input never crashes anything, and every rejection is counted where it can be seen.

The swarm test runs Case 1 in lockstep as real processes (world, six agents, real Zenoh, real
MAVLink/UDP) and, while the mission runs, a separate Zenoh session and separate UDP sockets
flood every input the processes have:

- 10 000 payloads on every Zenoh key an agent subscribes to: ``world/camera/<i>`` for each
  drone (frames with and without every drone's position, as lockstep sends them),
  ``world/clock`` and ``agent/<j>/consensus`` of each drone; and 10 000 on each key that
  nobody in a lockstep swarm listens to, which must change nothing: the world's beacon
  relay ``world/beacons`` (realtime only) and the drones' beacons (``agent/*/beacon``,
  spread over every drone's key and one of no drone; a lockstep world takes none);
- 10 000 datagrams at every UDP endpoint: each emulated vehicle's socket in the world and
  each agent's ``udpin`` port.

Each payload's fate is decided beforehand by the receiving code itself
(``tests.helpers.fuzz_tools``):
Zenoh payloads are kept only if the agents' codec refuses them, vehicle datagrams only if an
``EmulatedVehicle`` rejects all of them (with their exact count of rejections), and every
datagram at an agent's port comes from an address that is not its vehicle's. Nothing may be
lost on the way (Zenoh publishes with congestion control BLOCK over TCP; the UDP flood never
lets a socket queue overflow, and the kernel's drop counters are checked), so the counts are
exact: each agent's telemetry ``counters.rejected_messages`` rises by exactly its share and
the world's clock ``rejected_inputs`` by exactly the vehicles' share and the beacons'. Every
process stays up, the mission completes, and its result equals the in-process reference to
1e-9 — so no rejected value (NaN/inf included) reached any computation.

The boundary test checks each numerical input on its own: NaN/±inf in a position sample, a
detection's image point, a consensus message, a beacon and a setpoint at the vehicle is
rejected and counted where it enters, and the QP (``LocalQpWorkspace.solve``, wrapped to
assert finite inputs) never sees one — not even when the value is handed to the core
directly, past the wire checks.
"""

from __future__ import annotations

import dataclasses
import math
import random
import re
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle
from swarm.core.drone_step import ConsensusMessage, Detection
from swarm.core.qp import LocalQpWorkspace
from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.mavlink.link import AutopilotLink, LinkError
from swarm.mavlink.parse import LOCAL_POSITION_NED
from swarm.messages.wire import (
    BeaconRelayWire,
    BeaconWire,
    CameraFrameWire,
    ClockWire,
    TelemetryWire,
    WireCodec,
)
from swarm.net.keys import Keys
from swarm.net.session import declare_publisher, open_session, zenoh_config
from swarm.net.subscriptions import RejectionCounter, subscribe
from swarm.runs.checks import check_invariants
from swarm.scenario.config import load_config
from swarm.scenario.setup import build_agent, initial_drone_positions
from tests.helpers.fuzz_tools import (
    UdpFlood,
    VehicleModel,
    mavlink_datagrams,
    socket_inodes,
    udp_sockets,
    zenoh_payloads,
)
from tests.helpers.reference_tools import assert_matches_reference

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
PER_KEY = 10_000
PER_ENDPOINT = 10_000
DURATION_S = 30.0  # long enough for the whole flood to arrive while the mission runs
WRONG_DRONE_FRAMES = 100  # valid camera frames for another drone, on each camera key


# -- valid messages to mutate ------------------------------------------------------------------


def _camera_bases(codec: WireCodec, drone: int, n: int) -> list[bytes]:
    positions = np.column_stack([np.arange(n) - 2.5, np.full(n, -1.0), np.full(n, 3.5)])
    return [codec.encode(CameraFrameWire.build(
        drone, step, 0.02 * step, 1000 + 20 * step,
        [Detection(0, np.array([0.1 * step - 0.3, 0.05]))] if step % 2 else [],
        drone_positions=positions + 0.1 * step if step < 2 else None))
        for step in range(4)]


def _beacon_bases(codec: WireCodec, n: int) -> list[bytes]:
    return [codec.encode(BeaconWire.build(j, 7 + j, 0.14 + 0.02 * j, (j, -1.0, 3.5),
                                          velocity_m_s=(0.1, 0.2, -0.1), sample_age_s=0.01))
            for j in range(n)]


def _relay_bases(codec: WireCodec, n: int) -> list[bytes]:
    beacons = [BeaconWire.build(j, 9, 0.18, (j, -1.0, 3.5), velocity_m_s=(0.1, 0.2, -0.1),
                                sample_age_s=0.01) for j in range(n)]
    return [codec.encode(BeaconRelayWire.build(9, (
        (b, 0.001 * j) for j, b in enumerate(beacons[:count])))) for count in (1, n)]


def _clock_bases(codec: WireCodec) -> list[bytes]:
    return [codec.encode(ClockWire(step=s, time_s=0.02 * s, state=state, mode="lockstep",
                                   detail=detail, rejected_inputs=s))
            for s, state, detail in ((0, "waiting", "waiting for drones [3]"),
                                     (40, "running", ""), (1500, "done", ""))]


def _consensus_bases(codec: WireCodec, sender: int, m: int, n_state: int) -> list[bytes]:
    rng = np.random.default_rng(sender)
    out = []
    for rnd in (0, 1):
        states = {} if rnd else dict(
            projector_mean=rng.normal(size=(m, 3, 3)), weight_mean=rng.random(m),
            projector_integral=rng.normal(size=(m, 3, 3)), weight_integral=rng.random(m),
            gramian=rng.normal(size=(m, 3, 3)))
        out.append(codec.encode(ConsensusMessage.of_arrays(
            sender, 12, rnd, rng.normal(size=(m, n_state, n_state)),
            rng.normal(size=(m, n_state)), **states)))
    return out


class Plan:
    """What goes where, and how many rejections each process must count."""

    def __init__(self, config: Any, keys: Keys, seed: int = 2026) -> None:
        rng = random.Random(seed)
        n, m, n_state = config.swarm.n_drones, len(config.targets), config.state_dimension
        neighbours = config.swarm.graph.neighbours
        codec = config.wire_codec()  # exactly the agents' codec
        self.zenoh: dict[str, list[bytes]] = {}
        self.reach: dict[str, tuple[int, ...]] = {}  # the agents that receive each key
        self.agent_expected = [0] * n
        for i in range(n):
            payloads = zenoh_payloads(rng, _camera_bases(codec, i, n), codec.decode_camera,
                                      PER_KEY - WRONG_DRONE_FRAMES, n_drones=n)
            other = (i + 1) % n  # valid frames, but for another drone: the agent refuses
            payloads += [codec.encode(CameraFrameWire.build(other, s, 0.02 * s, 5 * s, []))
                         for s in range(WRONG_DRONE_FRAMES)]
            rng.shuffle(payloads)
            self.zenoh[keys.camera(i)] = payloads
            self.reach[keys.camera(i)] = (i,)
            self.agent_expected[i] += PER_KEY
        beacons = zenoh_payloads(rng, _beacon_bases(codec, n), codec.decode_beacon, PER_KEY,
                                 n_drones=n)
        beacon_keys = [keys.beacon(j) for j in (*range(n), 999)]
        for k, key in enumerate(beacon_keys):  # agent/*/beacon: nobody takes them here
            self.zenoh[key] = beacons[k::len(beacon_keys)]
            self.reach[key] = ()
        # Lockstep: the world takes no beacon (the frames carry every drone's position) and
        # relays none, so no agent listens to world/beacons: neither flood may count.
        self.world_zenoh_expected = 0
        self.zenoh[keys.beacon_relay] = zenoh_payloads(
            rng, _relay_bases(codec, n), codec.decode_beacon_relay, PER_KEY, n_drones=n)
        self.reach[keys.beacon_relay] = ()
        self.zenoh[keys.clock] = zenoh_payloads(rng, _clock_bases(codec), codec.decode_clock,
                                                PER_KEY, n_drones=n)
        self.reach[keys.clock] = tuple(range(n))
        self.agent_expected = [e + PER_KEY for e in self.agent_expected]
        for j in range(n):  # agent/<j>/consensus reaches j's graph neighbours
            self.zenoh[keys.consensus(j)] = zenoh_payloads(
                rng, _consensus_bases(codec, j, m, n_state), codec.decode_consensus, PER_KEY,
                n_drones=n)
            self.reach[keys.consensus(j)] = tuple(neighbours[j])
            for i in neighbours[j]:
                self.agent_expected[i] += PER_KEY
        sysids = range(1, n + 1)
        model = VehicleModel(config.vehicles.flavour)
        self.vehicle_datagrams = mavlink_datagrams(rng, PER_ENDPOINT, sysids, keep=model.keep)
        self.vehicle_expected_each = sum(model.expected[d] for d in self.vehicle_datagrams)
        # At an agent's port, every datagram comes from an address other than its vehicle's.
        self.agent_datagrams = mavlink_datagrams(rng, PER_ENDPOINT, sysids)
        self.agent_expected = [e + PER_ENDPOINT for e in self.agent_expected]


# -- the swarm test ------------------------------------------------------------------------------


def _wait(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)  # polling a condition with a deadline


def _flood_zenoh(session: Any, plan: Plan, consumed: Callable[[int], int],
                 stop: Callable[[], bool], *, window: int = 2000, batch: int = 50) -> int:
    """Put every payload of the plan, keys interleaved, keeping at most ``window`` payloads
    per agent that its telemetry has not counted yet: a lockstep swarm must keep stepping
    (a step held up for ``lockstep_timeout_s`` by a backlog of junk aborts the mission)."""
    publishers = {key: declare_publisher(session, key, block=True) for key in plan.zenoh}
    n = len(plan.agent_expected)
    sent_to = [0] * n
    sent = 0
    longest = max(map(len, plan.zenoh.values()))
    for k in range(longest):
        if k % batch == 0:
            deadline = time.monotonic() + 60
            while max(sent_to[i] - consumed(i) for i in range(n)) > window:
                assert not stop(), "the mission ended during the flood"
                assert time.monotonic() < deadline, "the agents stopped counting"
                time.sleep(0.002)  # polling the agents' telemetry (bounded by the deadline)
        for key, payloads in plan.zenoh.items():
            if k < len(payloads):
                publishers[key].put(payloads[k])
                sent += 1
                for i in plan.reach[key]:
                    sent_to[i] += 1
    for publisher in publishers.values():
        publisher.undeclare()
    return sent


@pytest.mark.slow
def test_a_flood_of_bad_input_changes_nothing_and_every_rejection_is_counted(
        tmp_path: Path) -> None:
    started = time.monotonic()
    config = load_config(CASE1).with_duration(DURATION_S)
    n = config.swarm.n_drones
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(CASE1), seed=0,
                                           log_dir=tmp_path), log=lambda _line: None)
    plan = Plan(config, launcher.keys)
    generated = time.monotonic()

    telemetry: dict[int, TelemetryWire] = {}
    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["record"] = launcher.run(telemetry_listeners=[
                lambda tel: telemetry.__setitem__(tel.drone, tel)])
        except BaseException as err:  # reported below
            outcome["error"] = err

    mission = threading.Thread(target=run)
    mission.start()
    session = None
    clocks: list[ClockWire] = []
    flood: UdpFlood | None = None
    try:
        _wait(lambda: launcher._mission_state() == "running" or not mission.is_alive(), 90,
              "the mission to start")
        assert mission.is_alive(), outcome
        before = {i: t.counters.rejected_messages for i, t in telemetry.items()}
        assert set(before.values()) <= {0}, before  # a clean swarm rejects nothing

        session = open_session(zenoh_config(mode="client", connect=[launcher.endpoint]))
        codec = config.wire_codec()
        subscribe(session, launcher.keys.clock, codec.decode_clock,
                  lambda _key, clock: clocks.append(clock), RejectionCounter(), "clock",
                  remote_only=True)
        world = next(c for c in launcher.children if c.name == "world")
        inodes = socket_inodes(world.process.pid)
        vehicle_ports = sorted(s.port for s in udp_sockets() if s.inode in inodes)
        assert len(vehicle_ports) == n, vehicle_ports
        agent_ports = [launcher.mavlink_base + i for i in range(n)]
        udp_plan = {port: plan.vehicle_datagrams for port in vehicle_ports}
        udp_plan.update({port: plan.agent_datagrams for port in agent_ports})
        flood = UdpFlood(udp_plan)
        udp_error: list[BaseException] = []

        def udp() -> None:
            try:
                flood.run(time.monotonic() + 120, stop=lambda: not mission.is_alive())
            except BaseException as err:
                udp_error.append(err)

        udp_thread = threading.Thread(target=udp)
        flood_started = time.monotonic()
        udp_thread.start()

        def consumed(i: int) -> int:
            """Payloads agent i has counted, less the datagrams sent to its port."""
            tel = telemetry.get(i)
            counted = 0 if tel is None else tel.counters.rejected_messages - before.get(i, 0)
            return counted - flood.sent[agent_ports[i]]

        try:
            zenoh_sent = _flood_zenoh(session, plan, consumed, lambda: not mission.is_alive())
        except AssertionError as err:
            raise AssertionError(f"{err} after {time.monotonic() - flood_started:.1f} s; "
                                 f"mission: {outcome}, state {launcher._mission_state()}, "
                                 f"last steps { {i: t.step for i, t in telemetry.items()} }"
                                 ) from None
        udp_thread.join(150)
        flood_s = time.monotonic() - flood_started
        drops_after = flood.drops()  # drops happen as datagrams arrive: all have arrived
        assert not udp_error, (udp_error, outcome)
        state = launcher._mission_state()
        assert state == "running", f"the flood ({flood_s:.1f} s) outlasted the mission: {state}"
        assert all(c.process.poll() is None for c in launcher.children)  # everyone still up

        mission.join(240)
        assert not mission.is_alive()
        assert "error" not in outcome, outcome.get("error")
        record = outcome["record"]
    finally:
        if mission.is_alive():
            launcher.stop_requested.set()
            mission.join(30)
        if session is not None:
            session.close()
        if flood is not None:
            flood.close()

    # The mission: complete, and exactly the reference (nothing rejected reached anything).
    assert record.n_steps == config.n_steps
    assert_matches_reference(config, record, seed=0)
    assert check_invariants(record) == []
    # Every input was delivered (no kernel drops, Zenoh never drops with BLOCK)...
    assert zenoh_sent == sum(map(len, plan.zenoh.values())) == 15 * PER_KEY
    assert all(flood.sent[p] == PER_ENDPOINT for p in udp_plan)
    assert drops_after == flood.drops_before, (flood.drops_before, drops_after)
    # ...and every one counted where it can be seen: agents in their telemetry,
    got = [telemetry[i].counters.rejected_messages for i in range(n)]
    assert all(telemetry[i].step == config.n_steps - 1 for i in range(n))
    assert got == plan.agent_expected, (got, plan.agent_expected)
    # the world on its clock (its last one, the mission's "done"),
    done = [c for c in clocks if c.state == "done"]
    assert done, [c.state for c in clocks[-3:]]
    assert done[0].rejected_inputs == n * plan.vehicle_expected_each + plan.world_zenoh_expected
    # and the launcher (a subscriber of world/clock too) in its own counter.
    assert launcher.rejections.snapshot()["clock"]["rejected"] == PER_KEY
    # Each agent's log says, per kind, how many, by rule, and the last reason with its key.
    for i in range(n):
        log = (tmp_path / f"agent{i}.log").read_text()
        camera = re.escape(launcher.keys.camera(i))
        assert re.search(rf"drone {i}: rejected camera: [1-9][0-9]* rejected, 0 unexpected "
                         rf"\((?:[a-z]+ [0-9]+, )*[a-z]+ [0-9]+; last: .+ on {camera}\)", log), \
            log[-2000:]
    print(f"\n[fuzz] {zenoh_sent} Zenoh payloads on {len(plan.zenoh)} keys, "
          f"{sum(flood.sent.values())} datagrams at {len(udp_plan)} UDP endpoints in "
          f"{flood_s:.1f} s; counted: agents {got}, world {done[0].rejected_inputs} "
          f"(vehicles {plan.vehicle_expected_each} each, beacons "
          f"{plan.world_zenoh_expected}); generation "
          f"{generated - started:.1f} s, total {time.monotonic() - started:.1f} s")


# -- NaN/inf at each numerical boundary ----------------------------------------------------------

NONFINITE = (math.nan, math.inf, -math.inf)


@pytest.fixture
def guarded_qp(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """``LocalQpWorkspace.solve`` asserting that every number it is given is finite; the
    list holds the number of inputs of each call."""
    calls: list[int] = []
    real = LocalQpWorkspace.solve

    def solve(self: LocalQpWorkspace, nominal: Any, u_columns: Any, lower: Any,
              weights: Any, u_box: Any = None) -> Any:
        values = [*nominal, *u_columns, *lower, *weights]
        if u_box is not None:
            values += [*u_box[0], *u_box[1]]
        assert all(math.isfinite(v) for v in values), f"non-finite QP input: {values}"
        calls.append(len(values))
        return real(self, nominal, u_columns, lower, weights, u_box)

    monkeypatch.setattr(LocalQpWorkspace, "solve", solve)
    return calls


def _poisoned(codec: WireCodec, payload: bytes, path: tuple[int, ...], bad: float) -> bytes:
    """``payload`` with the float at ``path`` (or one float64 of the packed array there)
    replaced by ``bad``."""
    tree = msgspec.msgpack.decode(payload)
    node = tree
    for k in path[:-1]:
        node = node[k]
    old = node[path[-1]]
    node[path[-1]] = (struct.pack("<d", bad) + old[8:]) if isinstance(old, bytes) else bad
    return msgspec.msgpack.encode(tree)


def _zenoh_boundaries(config: Any, bad: float) -> None:
    """Camera frames, beacons and consensus messages go through ``subscribe`` with the
    agents' decoders, as in ``AgentProcess``: the poisoned ones are counted, never handed on."""
    n, m = config.swarm.n_drones, len(config.targets)
    codec = config.wire_codec()
    keys = Keys("nanfuzz")
    camera = codec.encode(CameraFrameWire.build(0, 3, 0.06, 1060,
                                                [Detection(0, np.array([0.1, -0.2]))]))
    beacon = _beacon_bases(codec, n)[1]
    consensus = _consensus_bases(codec, 1, m, 6)[0]
    cases = {  # kind: (key, decoder, valid payload, poisoned payloads)
        "camera": (keys.camera(0), codec.decode_camera, camera,
                   [_poisoned(codec, camera, (6, 0, 1), bad),
                    _poisoned(codec, camera, (6, 0, 2), bad),
                    _poisoned(codec, camera, (4,), bad)]),
        "beacon": (keys.beacon(1), codec.decode_beacon, beacon,
                   [_poisoned(codec, beacon, (5, k), bad) for k in range(3)]
                   + [_poisoned(codec, beacon, (6, 0), bad), _poisoned(codec, beacon, (7,), bad)]),
        "consensus": (keys.consensus(1), codec.decode_consensus, consensus,
                      [_poisoned(codec, consensus, (7,), bad)]),
    }
    session = open_session(zenoh_config(mode="peer"))
    rejections = RejectionCounter()
    delivered: dict[str, list[Any]] = {kind: [] for kind in cases}
    try:
        subscribers = [subscribe(session, key, decode,
                                 lambda _key, value, kind=kind: delivered[kind].append(value),
                                 rejections, kind)
                       for kind, (key, decode, _, _) in cases.items()]
        for key, _, valid, poisoned in cases.values():
            for payload in [*poisoned, valid]:
                session.put(key, payload)
        expected = sum(len(p) for *_, p in cases.values())
        _wait(lambda: rejections.total() + sum(map(len, delivered.values()))
              >= expected + len(cases), 10, "the deliveries")
        for sub in subscribers:
            sub.undeclare()
    finally:
        session.close()
    assert rejections.total() == expected
    for kind, (*_, poisoned) in cases.items():
        counts = rejections.snapshot()[kind]
        assert (counts["rejected"], counts["unexpected"]) == (len(poisoned), 0), counts
        assert "finite" in counts["last_reason"], counts["last_reason"]
        assert counts["rules"] == {"finite": len(poisoned)}, counts  # counted by the rule broken
        assert len(delivered[kind]) == 1  # only the valid one got through


def _mavlink_boundaries(bad: float) -> None:
    """A position sample at the agent's link and a setpoint at the vehicle."""
    link = AutopilotLink("udpin:127.0.0.1:0", 2, "px4", np.zeros(3), log=lambda _line: None)
    vehicle = EmulatedVehicle(2, "px4", (1.0, 2.0, 3.0), np.zeros(3))
    assert link.local_address is not None
    endpoint = VehicleEndpoint(("127.0.0.1", link.local_address[1]))
    try:
        endpoint.send(vehicle.telemetry(20, 0.02))
        assert link.wait_position(20, 2.0).time_boot_ms == 20
        for k in range(6):  # x, y, z, vx, vy, vz
            fields = [1.0, 2.0, -3.0, 0.1, 0.2, 0.3]
            fields[k] = bad
            endpoint.send([LOCAL_POSITION_NED.pack(vehicle._tx, 40 + k, *fields)])
        endpoint.send(vehicle.telemetry(60, 0.06))
        assert link.wait_position(60, 2.0).time_boot_ms == 60
        assert link.rejections["nonfinite_position"] == 6 == link.rejected_frames
        for k in range(6):
            with pytest.raises(LinkError):
                link.wait_position(40 + k, 0.0)
        assert np.all(np.isfinite(link.latest_position().position_w))
    finally:
        endpoint.close()
        link.close()
    agent = mav.MAVLink(None, srcSystem=3, srcComponent=mav.MAV_COMP_ID_ONBOARD_COMPUTER)
    for k in range(3):
        velocity = [0.5, 0.5, 0.5]
        velocity[k] = bad
        frame = agent.set_position_target_local_ned_encode(
            77, 3, 1, mav.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, *velocity, 0, 0, 0, 0, 0)
        vehicle.begin_step(77)
        assert vehicle.receive(frame.pack(agent), 1.0) == []
        assert vehicle.setpoint_stamped() is None
    assert vehicle.rejections["nonfinite_setpoint"] == 3 == vehicle.rejected_frames


def _core_boundaries(config: Any, bad: float, guarded_qp: list[int]) -> None:
    """Past the wire checks, the core itself drops a non-finite detection, consensus message
    or beacon (counted in ``rejected_inputs``) and the QP never sees one."""
    n = config.swarm.n_drones
    graph = config.swarm.graph
    agents = [build_agent(config, 0, i) for i in range(n)]
    positions = initial_drone_positions(config, 0)
    neighbour = graph.neighbours[0][0]
    steps = 5
    for k in range(steps):
        detections = [[Detection(0, np.array([0.01 * i, -0.02]))] for i in range(n)]
        detections[0].append(Detection(0, np.array([bad, 0.0])))  # the same target, poisoned
        messages = [agents[i].begin_step(k, positions[i], detections[i]) for i in range(n)]
        for _ in range(agents[0].n_rounds):
            inboxes = [{j: messages[j] for j in graph.neighbours[i]} for i in range(n)]
            good = inboxes[0][neighbour]
            data = good.data.copy()
            data[3] = bad  # V[0, 0, 3] of the packed block (swarm.core.consensus_message)
            inboxes[0][neighbour] = dataclasses.replace(good, data=data)
            messages = [agents[i].consensus_round(inboxes[i]) for i in range(n)]
        beacons = dict(enumerate(positions))
        poisoned = dict(beacons)
        poisoned[n - 1] = np.array([1.0, bad, 3.0])
        results = [agents[i].finish_step(poisoned if i == 0 else beacons) for i in range(n)]
        positions = positions + config.scenario.dt_s * np.array([r.velocity for r in results])
    assert agents[0].rejected_inputs == steps * (2 + agents[0].n_rounds)
    assert all(a.rejected_inputs == 0 for a in agents[1:])
    assert len(guarded_qp) >= steps * n  # the QP ran every step, on finite inputs only


@pytest.mark.parametrize("bad", NONFINITE, ids=("nan", "inf", "-inf"))
def test_a_non_finite_number_at_any_boundary_is_counted_and_never_reaches_the_qp(
        bad: float, guarded_qp: list[int], tmp_path: Path) -> None:
    source = CASE1.read_text()
    assert "start_s = 1.0" in source
    path = tmp_path / "qp_from_the_start.toml"
    path.write_text(source.replace("start_s = 1.0", "start_s = 0.0"))  # the QP at every step
    config = load_config(path)
    _zenoh_boundaries(config, bad)
    _mavlink_boundaries(bad)
    _core_boundaries(config, bad, guarded_qp)
