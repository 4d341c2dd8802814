"""swarm.observe.live_view: the live 3D view, watched by a WebSocket client during a real
process swarm (issue 17, points 1 and 3).

``launch-swarm --foxglove`` (here ``LaunchOptions.foxglove``) serves Foxglove's WebSocket
protocol from the launcher. A client speaking that protocol (``tests/helpers/foxglove_client``)
connects while the swarm starts, subscribes to every advertised channel, and receives, for a
short lockstep Case 1: the scene (``foxglove.SceneUpdate``, protobuf) and one plot channel per
drone (JSON), all stamped in sim time; each is checked against the run's record.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.observe.live_view import LiveView, LiveViewError, plot_topic
from swarm.observe.scene import LOG_TOPIC, SCENE_TOPIC
from swarm.scenario.config import load_config
from tests.helpers.foxglove_client import FoxgloveClient
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.scene_tools import decode_scene_bytes

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"
DURATION_S = 3.0


def test_a_websocket_client_watches_the_swarm_in_3d_and_plots(tmp_path: Path) -> None:
    config = load_config(CASE1).with_duration(DURATION_S)
    n = config.swarm.n_drones
    port = free_tcp_port()
    client = FoxgloveClient(f"ws://127.0.0.1:{port}")
    launcher = SwarmLauncher(LaunchOptions(
        config=config, config_path=str(CASE1), seed=0, log_dir=tmp_path / "logs",
        foxglove=("127.0.0.1", port)), log=lambda _line: None)
    result: dict[str, object] = {}

    def run() -> None:
        try:
            result["record"] = launcher.run()
        except BaseException as err:
            result["error"] = err

    runner = threading.Thread(target=run)
    runner.start()
    client.start()
    runner.join(timeout=120)
    client.wait_closed()  # the launcher stops its server on the way out
    assert "error" not in result, result.get("error")
    record = result["record"]

    assert client.server_info is not None and "time" in client.server_info["capabilities"]
    topics = {c["topic"]: c for c in client.channels.values()}
    assert topics[SCENE_TOPIC]["schemaName"] == "foxglove.SceneUpdate"
    assert topics[SCENE_TOPIC]["encoding"] == "protobuf"
    assert {plot_topic(i) for i in range(n)} <= set(topics)
    assert topics[LOG_TOPIC]["schemaName"] == "foxglove.Log"  # quiet run: no line in it

    dt_ns = round(config.scenario.dt_s * 1e9)
    scenes = client.messages[SCENE_TOPIC]
    steps = [t // dt_ns for t, _ in scenes]
    # Connected before the mission started: every scene step, in order, none twice.
    assert steps == list(range(0, config.n_steps, 5))
    assert client.times_ns == [t for t, _ in scenes]  # the server's clock is sim time
    for log_time, data in scenes:
        k = log_time // dt_ns
        scene = decode_scene_bytes(data)
        drones = next(e for e in scene.entities if e.id == "drones")
        assert [[s.pose.position.x, s.pose.position.y, s.pose.position.z]
                for s in drones.spheres] == record.drone_positions_m[k].tolist()
        assert drones.timestamp.seconds * 10**9 + drones.timestamp.nanos == log_time
    for i in range(n):
        plots = client.messages[plot_topic(i)]
        assert [t for t, _ in plots] == [t for t, _ in scenes]
        for log_time, data in plots:
            k = log_time // dt_ns
            values = json.loads(data)
            assert values["lambda_margin"] == record.psi0[k, i].tolist()
            assert values["weights"] == record.weights[k, i].tolist()
            assert values["speed_m_s"] == pytest.approx(
                float(np.linalg.norm(record.velocities_m_s[k, i])), rel=1e-12)


def test_a_taken_port_is_one_clear_error() -> None:
    config = load_config(CASE1)
    with LiveView(config, port=0) as first, pytest.raises(
            LiveViewError, match=f"127.0.0.1:{first.port}.*in use"):
        LiveView(config, port=first.port)
