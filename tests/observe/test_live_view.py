"""swarm.observe.live_view: the live 3D view, watched by a WebSocket client during a real
process swarm (issue 17, points 1 and 3).

``launch-swarm --foxglove`` (here ``LaunchOptions.foxglove``) serves Foxglove's WebSocket
protocol from the launcher. A client speaking that protocol (``tests/helpers/foxglove_client``)
connects while the swarm starts, subscribes to every advertised channel, and receives, for a
short lockstep Case 1: the scene (``foxglove.SceneUpdate``, protobuf) and one plot channel per
drone (JSON), all stamped in sim time; each is checked against the run's record.

Viewers that speak only the older subprotocol ``foxglove.websocket.v1`` (issue 41, point 4)
are refused by the SDK's server: each client host gets one line, the SDK's own log line per
connection is gone, in a view of its own and in a ``launch-swarm`` run's output. A port taken
by a real socket stops ``launch-swarm`` and the standalone watcher before anything starts.
"""

from __future__ import annotations

import json
import logging
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.observe import dashboard
from swarm.observe.foxglove_scene import LOG_TOPIC, SCENE_TOPIC
from swarm.observe.live_view import SUBPROTOCOL, LiveView, LiveViewError, plot_topic
from swarm.scenario.config import load_config
from tests.helpers.cli_tools import ROOT as CLI_ROOT
from tests.helpers.cli_tools import cli_env, launch_swarm_in_process
from tests.helpers.foxglove_client import FoxgloveClient
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.scene_tools import decode_scene_bytes
from tests.helpers.waiting import wait_until

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


# -- viewers speaking only the older subprotocol --------------------------------------------

OLD_SUBPROTOCOL = "foxglove.websocket.v1"


def refused_as_an_old_viewer(url: str, source_host: str = "127.0.0.1",
                             wait_up_s: float = 0.0) -> int:
    """Open ``url`` as a viewer offering only the older subprotocol, from ``source_host``; the
    HTTP status of the refusal (AssertionError if the server accepts). Retries a refused TCP
    connection for ``wait_up_s`` (a server still starting)."""
    deadline = time.monotonic() + wait_up_s
    while True:
        try:
            with connect(url, subprotocols=[OLD_SUBPROTOCOL], open_timeout=5.0, proxy=None,
                         source_address=(source_host, 0)):
                raise AssertionError(f"{url} accepted a {OLD_SUBPROTOCOL}-only client")
        except InvalidStatus as refusal:
            return refusal.response.status_code
        except ConnectionRefusedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_an_old_viewer_gets_one_line_per_host_and_a_current_one_still_connects(
        caplog: pytest.LogCaptureFixture) -> None:
    config = load_config(CASE1)
    lines: list[str] = []
    with caplog.at_level(logging.DEBUG, logger="foxglove"), \
            LiveView(config, port=0, log=lines.append) as view:
        # A viewer retrying, from two hosts (127.0.0.2 is loopback too on Linux).
        statuses = [refused_as_an_old_viewer(view.url) for _ in range(4)]
        statuses += [refused_as_an_old_viewer(view.url, "127.0.0.2") for _ in range(2)]
        assert statuses == [400] * 6
        # The SDK reports each refusal on a thread of its own.
        wait_until(lambda: view.refused == 6, 10.0, "six refusals counted by the live view")
        current = FoxgloveClient(view.url)
        current.start()
        wait_until(lambda: current.server_info is not None or current.error is not None, 10.0,
                   "the current viewer's serverInfo or its error")
        assert current.error is None and current.server_info is not None
    current.wait_closed()
    assert len(lines) == 2, lines
    by_host = {line.split(" refused a viewer at ")[1].split(",")[0]: line for line in lines}
    assert set(by_host) == {"127.0.0.1", "127.0.0.2"}
    for line in lines:
        assert line.startswith(f"live view {view.url}: ")
        assert SUBPROTOCOL in line and OLD_SUBPROTOCOL in line and "Lichtblick 1.22.0" in line
        assert "\n" not in line
    # The SDK's own line per connection ("Dropping client ...: handshake failed") is gone.
    assert not [r for r in caplog.records if "handshake failed" in r.getMessage()]


def test_a_launch_swarm_run_says_one_line_for_a_retrying_old_viewer() -> None:
    """``launch-swarm --foxglove`` as a user runs it, in a process of its own, with a viewer
    that keeps trying the older subprotocol during the run: one line on stderr, no flood."""
    port = free_tcp_port()
    url = f"ws://127.0.0.1:{port}"
    run = subprocess.Popen(
        [sys.executable, "-m", "swarm.launch.cli", str(CASE1), "--headless", "--duration",
         "2", "--foxglove", f"127.0.0.1:{port}"],
        cwd=CLI_ROOT, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        statuses = [refused_as_an_old_viewer(url, wait_up_s=60.0) for _ in range(5)]
        out, err = run.communicate(timeout=120)
    finally:
        if run.poll() is None:
            run.kill()
            run.communicate()
    assert statuses == [400] * 5
    assert run.returncode == 0, out + err
    assert "verdict: OK" in out
    refusals = [line for line in err.splitlines() if "refused a viewer" in line]
    assert len(refusals) == 1, err
    assert f"live view {url}: refused a viewer at 127.0.0.1," in refusals[0]
    assert "handshake failed" in refusals[0] and "Dropping client" not in err


# -- a taken port, found before anything starts -----------------------------------------------


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A port a real server listens on (as another program's would)."""
    with socket.socket() as occupant:
        occupant.bind(("127.0.0.1", 0))
        occupant.listen(1)
        yield int(occupant.getsockname()[1])


def test_launch_swarm_on_a_taken_port_exits_2_before_starting_anything(
        taken_port: int, tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    result = launch_swarm_in_process(str(CASE1), "--headless", "--log-dir", str(logs),
                                     "--foxglove", f"127.0.0.1:{taken_port}")
    assert result.returncode == 2, result
    assert result.stdout == ""
    assert result.stderr.splitlines() == [
        f"launch-swarm: --foxglove 127.0.0.1:{taken_port}: cannot serve the live view there: "
        f"the address is in use"]
    assert not logs.exists()  # the launcher, which makes it before any child, never ran


def test_launch_swarm_on_an_address_not_of_this_machine_exits_2() -> None:
    result = launch_swarm_in_process(str(CASE1), "--headless", "--foxglove", "192.0.2.1:8765")
    assert result.returncode == 2, result
    assert len(result.stderr.splitlines()) == 1
    assert result.stderr.startswith("launch-swarm: --foxglove 192.0.2.1:8765: cannot serve")
    assert "Traceback" not in result.stderr


def test_the_watcher_on_a_taken_port_exits_2_before_joining_the_router(
        taken_port: int, capsys: pytest.CaptureFixture[str]) -> None:
    router = free_tcp_port()  # nothing listens: joining it would fail with exit code 1
    code = dashboard.main([str(CASE1), "--connect", f"tcp/127.0.0.1:{router}", "--run-id",
                           "x", "--headless", "--foxglove", f"127.0.0.1:{taken_port}"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.splitlines() == [
        f"swarm-dashboard: --foxglove 127.0.0.1:{taken_port}: cannot serve the live view "
        f"there: the address is in use"]
