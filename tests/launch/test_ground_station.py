"""A ground station watches a process swarm: MAVProxy sees every emulated vehicle (issue 17,
point 4).

``launch-swarm --gcs 127.0.0.1:<port>`` gives each of the world's vehicles a ground-station
link to that port (``sim_world.gcs_link``), as every PX4 SITL instance sends to 14550. MAVProxy
(PyPI ``mavproxy``, headless, no modules) listens there as the ground station would. A short
lockstep Case 1 must then:

* reproduce the in-process reference bit for bit and hold the SPEC invariants: the ground
  station costs the mission nothing (MAVProxy's own 1 Hz HEARTBEAT reaches every vehicle);
* show MAVProxy every vehicle (its "Detected vehicle" line per system id), with
  GLOBAL_POSITION_INT that places each drone where the run's record has it at the end (distance
  from the world's geodetic origin by the tests' haversine, tests/helpers/geo_tools.py).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.runs.checks import check_invariants
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config
from tests.helpers.geo_tools import haversine_m
from tests.helpers.process_tools import free_udp_block, start_mavproxy

pytestmark = pytest.mark.wallclock

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
DURATION_S = 3.0
SEED = 0
COMPARED = ("drone_positions_m", "velocities_m_s", "estimates", "lambda_bar", "weights")


def _last_global_positions(tlog: Path) -> dict[int, object]:
    """The last GLOBAL_POSITION_INT of each system MAVProxy heard on its master link."""
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega", robust_parsing=True)
    last: dict[int, object] = {}
    try:
        while (msg := log.recv_match(type="GLOBAL_POSITION_INT")) is not None:
            last[msg.get_srcSystem()] = msg
    finally:
        log.close()
    return last


def test_mavproxy_as_ground_station_sees_the_whole_fleet_and_the_mission_is_unchanged(
        tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(DURATION_S)
    n = config.swarm.n_drones
    base = free_udp_block(n + 2)  # vehicles' agent ports, then the GCS port, MAVProxy's out
    gcs_port = base + n
    station = start_mavproxy(gcs_port, base + n + 1, tmp_path / "mavproxy")
    try:
        station.wait_for(f"Waiting for heartbeat from 127.0.0.1:{gcs_port}", 30.0)
        record = SwarmLauncher(LaunchOptions(
            config=config, config_path=str(CASE1), seed=SEED, mode="lockstep",
            mavlink_base=base, log_dir=tmp_path / "swarm", gcs=("127.0.0.1", gcs_port)),
            log=lambda _line: None).run()
        deadline = time.monotonic() + 5.0  # MAVProxy's log writer trails the traffic
        while (len(_last_global_positions(station.tlog_path)) < n
               and time.monotonic() < deadline):
            time.sleep(0.05)
    finally:
        station.stop()

    assert check_invariants(record) == []
    reference = run_reference(config, SEED)
    for name in COMPARED:
        assert np.array_equal(getattr(record, name), getattr(reference, name)), name

    for system in range(1, n + 1):
        assert f"Detected vehicle {system}:1" in station.log(), station.log()
    last = _last_global_positions(station.tlog_path)
    assert sorted(last) == list(range(1, n + 1))
    lat0, lon0, alt0 = config.vehicles.geo_origin
    final = record.drone_positions_m[-1]
    for i in range(n):
        gpi = last[i + 1]
        horizontal = haversine_m(lat0, lon0, gpi.lat * 1e-7, gpi.lon * 1e-7)
        # The last stream may be a step or two before the record's last row (≤ 6 cm a step).
        assert abs(horizontal - float(np.hypot(final[i, 0], final[i, 1]))) < 0.2, i
        assert abs(gpi.alt / 1000.0 - (alt0 + final[i, 2])) < 0.2, i
