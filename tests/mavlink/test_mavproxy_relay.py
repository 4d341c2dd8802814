"""Real MAVLink software on an agent's link: MAVProxy relays drone 0 (issue 3, point 8).

MAVProxy (PyPI ``mavproxy``) runs headless as a separate process between vehicle 0 and its
agent, the way a companion computer or GCS relay would sit on a real link:

    sim-world vehicle 0 ──udp──▶ MAVProxy --master=udpin:127.0.0.1:<base>
                                 MAVProxy --out=udp:127.0.0.1:<proxy> ──udp──▶ agent 0 (udpin)

and back the same way (the vehicle replies to whoever talks to it; the agent to whoever sent
its last datagram). The other five drones keep their direct links. MAVProxy is started with no
modules (``--default-modules=``: no parameter/mission/fence downloads, no console, no map),
``--streamrate=-1`` (it sends no REQUEST_DATA_STREAM of its own), GCS system id 255 (distinct
from every vehicle 1..6 and from the agents' companion id 191), ``--non-interactive``, and its
state, telemetry log and HOME in a temporary directory. It still sends its own 1 Hz GCS
HEARTBEAT to the vehicle, which the vehicle ignores.

A short lockstep Case 1 (3 s: the barrier QP runs at every step from start_s = 1 s) must
complete, satisfy the SPEC invariants and equal the in-process reference bit for bit — MAVProxy
forwards the bytes unchanged, and lockstep makes the run independent of the extra hop's
latency. MAVProxy's telemetry log proves it was on the path: every step's LOCAL_POSITION_NED
from vehicle 0 and every step-stamped setpoint of agent 0 went through it.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.mavlink.link import IDLE_STAMP_MS
from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from tests.helpers.process_tools import free_udp_block, start_mavproxy

pytestmark = pytest.mark.wallclock

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
DURATION_S = 3.0
SEED = 0
RELAYED_DRONE = 0
COMPANION_COMPONENT_ID = 191  # swarm.mavlink.link: the agent speaks as the onboard computer
COMPARED = ("drone_positions_m", "velocities_m_s", "estimates", "lambda_bar", "weights",
            "target_positions_m")


def relayed_stamps(tlog: Path) -> tuple[set[int], set[int]]:
    """From MAVProxy's telemetry log: time_boot_ms of vehicle 0's LOCAL_POSITION_NED (heard on
    the master link) and of agent 0's setpoints (forwarded from the output to the master)."""
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega", robust_parsing=True)
    positions: set[int] = set()
    setpoints: set[int] = set()
    try:
        while (msg := log.recv_msg()) is not None:
            kind, source = msg.get_type(), (msg.get_srcSystem(), msg.get_srcComponent())
            if kind == "LOCAL_POSITION_NED" and source == (RELAYED_DRONE + 1, 1):
                positions.add(msg.time_boot_ms)
            elif (kind == "SET_POSITION_TARGET_LOCAL_NED"
                  and source == (RELAYED_DRONE + 1, COMPANION_COMPONENT_ID)
                  and msg.time_boot_ms != IDLE_STAMP_MS):
                setpoints.add(msg.time_boot_ms)
    finally:
        log.close()
    return positions, setpoints


def test_swarm_completes_case1_with_an_agent_behind_mavproxy(tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(DURATION_S)
    n = config.swarm.n_drones
    base = free_udp_block(n + 1)  # base..base+n-1: the vehicles' agent ports; base+n: MAVProxy out
    proxy_port = base + n
    relay = start_mavproxy(base + RELAYED_DRONE, proxy_port, tmp_path / "mavproxy")
    swarm_logs = tmp_path / "swarm"
    try:
        # Printed once the master socket is bound and the output opened.
        relay.wait_for(f"Waiting for heartbeat from 127.0.0.1:{base + RELAYED_DRONE}", 30.0)
        record = SwarmLauncher(LaunchOptions(
            config=config, config_path=str(CASE1), seed=SEED, mode="lockstep",
            mavlink_base=base, log_dir=swarm_logs,
            mavlink_urls={RELAYED_DRONE: f"udpin:127.0.0.1:{proxy_port}"}),
            log=lambda _line: None).run()
        assert relay.process.poll() is None, f"MAVProxy ended early:\n{relay.log()}"
        # MAVProxy's log writer thread trails the traffic by a few ms: wait until the last
        # step's setpoint is in the telemetry log (or give up and let the checks below fail).
        deadline = time.monotonic() + 5.0
        while (len(relayed_stamps(relay.tlog_path)[1]) < config.n_steps
               and time.monotonic() < deadline):
            time.sleep(0.05)
    finally:
        relay.stop()

    # The mission completed, within the SPEC, and exactly as the in-process reference.
    assert record.n_steps == config.n_steps
    assert record.times_s[-1] > config.control.start_s  # the QP ran (from start_s on)
    assert not record.qp_fallback.any()
    assert check_invariants(record) == []
    reference = run_reference(config, SEED)
    for name in COMPARED:
        assert np.array_equal(getattr(record, name), getattr(reference, name)), name

    # MAVProxy was on drone 0's path, in both directions, at every lockstep step.
    assert f"Detected vehicle {RELAYED_DRONE + 1}:1" in relay.log(), relay.log()
    agent_log = (swarm_logs / f"agent{RELAYED_DRONE}.log").read_text()
    assert f"udpin:127.0.0.1:{proxy_port}" in agent_log, agent_log
    assert "mission complete" in agent_log, agent_log
    positions, setpoints = relayed_stamps(relay.tlog_path)
    assert len(setpoints) == config.n_steps, (len(setpoints), config.n_steps)
    assert setpoints <= positions  # each step: position out to the agent, its setpoint back
    steps = np.diff(sorted(setpoints))
    assert np.all(steps == round(config.scenario.dt_s * 1000)), steps  # consecutive steps
