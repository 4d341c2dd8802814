"""MAVLink 2 signing between AutopilotLink and the emulated vehicles (issue 6, point 5b).

Real pymavlink at both ends over UDP on 127.0.0.1: the agent's ``AutopilotLink`` and a
one-vehicle ``VehicleFleet`` (the world's own serving code, endpoint included) stepped at
50 Hz by a background thread. Intruders are plain pymavlink ``udpout`` connections that
speak as the agent (same system and component id), unsigned or signed with another key.
"""

from __future__ import annotations

import os
import select
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.fleet import VehicleFleet
from sim_world.vehicle import EmulatedVehicle
from swarm.mavlink.link import AutopilotLink, LinkError
from swarm.mavlink.signing import (
    SigningKeyError,
    enable_signing,
    read_signing_key,
    signing_timestamp,
)
from swarm.models import frames
from swarm.scenario.config import ConfigError, load_config

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(32))
WRONG_KEY = bytes(range(100, 132))
DT = 0.02
DRONE = 0  # VehicleFleet numbers its vehicles from 0
SYS = DRONE + 1
COMPANION = mav.MAV_COMP_ID_ONBOARD_COMPUTER
ORIGIN = np.array([100.0, -50.0, 0.0])
START = np.array([103.0, -46.0, 4.0])
U = np.array([1.0, -0.5, 0.25])

os.environ.setdefault("MAVLINK20", "1")  # pymavlink reads it when a connection is made


class ServedFleet:
    """A one-vehicle VehicleFleet sending to ``agent_port``, stepped at 50 Hz (as
    ``fleet.serve_forever``, plus a record of the velocity flown at each step)."""

    def __init__(self, agent_port: int, flavour: str, signing_key: bytes | None,
                 start: str = "air") -> None:
        started = time.monotonic()
        self.fleet = VehicleFleet(np.array([START]), [ORIGIN], flavour,  # type: ignore[arg-type]
                                  host="127.0.0.1", base_port=agent_port, u_max_m_s=3.0,
                                  setpoint_timeout_s=0.5 if flavour == "px4" else 3.0,
                                  clock=lambda: time.monotonic() - started,
                                  signing_key=signing_key, start=start)  # type: ignore[arg-type]
        self.vehicle: EmulatedVehicle = self.fleet.vehicles[DRONE]
        self.address = self.fleet.endpoints[DRONE].local_address
        self.lock = threading.Lock()
        self.applied: list[np.ndarray] = []  # velocity vehicle DRONE flew at each step
        self.errors: list[BaseException] = []
        self._started = started
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        fds = [e.fileno() for e in self.fleet.endpoints]
        try:
            next_step = time.monotonic()
            while not self._stop.is_set():
                with self.lock:
                    self.fleet.service(0.0)
                    if time.monotonic() >= next_step:
                        self.fleet.send_telemetry(round((time.monotonic() - self._started)
                                                        * 1000))
                        self.fleet.fly(DT)
                        self.applied.append(self.vehicle.velocity_w)
                        next_step = max(next_step + DT, time.monotonic() - DT)
                select.select(fds, [], [], max(0.0, next_step - time.monotonic()))
        except BaseException as exc:  # surfaced by stop()
            self.errors.append(exc)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.fleet.close()
        assert not self._thread.is_alive()
        assert not self.errors, self.errors


@pytest.fixture
def served() -> Iterator[Callable[..., tuple[AutopilotLink, ServedFleet]]]:
    made: list[tuple[AutopilotLink, ServedFleet]] = []

    def factory(*, link_key: bytes | None = KEY, vehicle_key: bytes | None = KEY,
                flavour: str = "px4", start: str = "air") -> tuple[AutopilotLink, ServedFleet]:
        link = AutopilotLink("udpin:127.0.0.1:0", DRONE, flavour, ORIGIN,  # type: ignore[arg-type]
                             log=lambda _: None, signing_key=link_key)
        assert link.local_address is not None
        server = ServedFleet(link.local_address[1], flavour, vehicle_key, start)
        made.append((link, server))
        return link, server

    yield factory
    for link, server in made:
        server.stop()
        link.close()


def pump(link: AutopilotLink, seconds: float, velocity: np.ndarray | None = None,
         until: Callable[[], bool] | None = None) -> bool:
    """Drain the link and keep its setpoints going (``velocity`` every 20 ms, else the idle
    keepalive) for ``seconds`` or until ``until()``."""
    deadline = time.monotonic() + seconds
    last = 0.0
    while time.monotonic() < deadline:
        link.poll()
        if until is not None and until():
            return True
        if velocity is not None and time.monotonic() - last >= DT:
            link.send_velocity(velocity, 7)
            last = time.monotonic()
        elif velocity is None:
            link.keepalive()
        link.wait_readable(0.01)
    return until is None


def intruder(server: ServedFleet, key: bytes | None = None, **signing: Any) -> Any:
    """A pymavlink connection to the vehicle that speaks as the agent."""
    conn = mavutil.mavlink_connection(f"udpout:{server.address[0]}:{server.address[1]}",
                                      source_system=SYS, source_component=COMPANION,
                                      dialect="ardupilotmega")
    assert conn.mavlink20()
    if key is not None:
        conn.setup_signing(key, sign_outgoing=True, **signing)
    return conn


def send_setpoints(conn: Any, velocity_w: np.ndarray, count: int, stamp: int = 4242) -> None:
    vn, ve, vd = (float(c) for c in frames.enu_to_ned(velocity_w))
    for _ in range(count):
        conn.mav.set_position_target_local_ned_send(
            stamp, SYS, 1, mav.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0)
        time.sleep(0.005)  # the pace of a sender, not a wait for anything


def nothing_received(conn: Any, seconds: float = 0.3) -> bool:
    return not select.select([conn.port], [], [], seconds)[0]


def assert_flies(link: AutopilotLink, server: ServedFleet, velocity: np.ndarray) -> None:
    """Positive control: the signed agent's own setpoint is applied, bit-exact."""
    with server.lock:
        n = len(server.applied)
    target = frames.velocity_over_link(velocity)
    assert pump(link, 2.0, velocity, until=lambda: any(
        np.array_equal(v, target) for v in server.applied[n:]))
    link.send_velocity(np.zeros(3), 8)
    assert pump(link, 2.0, until=lambda: np.array_equal(server.applied[-1], np.zeros(3)))


# ---------------------------------------------------------------- (1) signed end to end
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_signed_agent_and_signed_vehicle_fly_a_setpoint(served: Any, flavour: str) -> None:
    link, server = served(flavour=flavour, start="ground")  # the whole handshake, signed
    assert link.signing and server.vehicle.signing
    link.handshake(timeout_s=20.0, start_position_w=START)
    assert link.armed and server.vehicle.accepting_setpoints
    assert_flies(link, server, U)
    sample = link.latest_position()
    assert sample is not None
    assert link.rejected_frames == 0, link.rejections
    with server.lock:
        assert server.vehicle.rejected_frames == 0, server.vehicle.rejections
        signing = server.vehicle._rx.signing
        # every frame either way was signed, and pymavlink checked its signature
        assert server.vehicle.authenticated_frames == signing.sig_count > 5
        assert server.vehicle.authenticated_frames > server.vehicle.accepted_setpoints > 0
        assert server.fleet.endpoints[DRONE].peer_changes == 0
    assert link._conn.mav.signing.goodsig_count == link._conn.mav.signing.sig_count > 10


# ---------------------------------------------------------------- (2), (3) intruders
@pytest.mark.parametrize(("key", "reason"), [(None, "unsigned"), (WRONG_KEY, "bad_signature")],
                         ids=["unsigned", "wrong_key"])
def test_setpoints_and_commands_without_the_key_are_ignored(served: Any, key: bytes | None,
                                                           reason: str) -> None:
    link, server = served()
    link.handshake(timeout_s=10.0)
    assert pump(link, 0.1)
    with server.lock:
        n = len(server.applied)
        rejected = server.vehicle.rejections[reason]
    conn = intruder(server, key)
    try:
        send_setpoints(conn, U, 20)
        conn.mav.command_long_send(SYS, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                   0, 21196, 0, 0, 0, 0, 0)  # forced disarm
        # the agent keeps its idle setpoints going meanwhile
        assert pump(link, 5.0, until=lambda: server.vehicle.rejections[reason] - rejected >= 21)
        assert nothing_received(conn)  # no ACK, and the telemetry was not redirected
    finally:
        conn.close()
    with server.lock:
        vehicle = server.vehicle
        assert vehicle.rejections[reason] - rejected == 21, vehicle.rejections
        assert vehicle.armed and vehicle.accepting_setpoints
        assert all(np.array_equal(v, np.zeros(3)) for v in server.applied[n:])
        assert server.fleet.endpoints[DRONE].peer_changes == 0
    assert_flies(link, server, U)  # still the agent's vehicle


def test_a_forged_far_future_timestamp_does_not_lock_the_agent_out(served: Any) -> None:
    """pymavlink stores a frame's timestamp before checking its signature; a forged frame on
    the agent's own stream (link id 1) dated a day ahead must not make the agent's genuine
    frames look replayed."""
    link, server = served()
    link.handshake(timeout_s=10.0)
    day_ahead = signing_timestamp(time.time() + 86400.0)
    conn = intruder(server, WRONG_KEY, link_id=1, initial_timestamp=day_ahead)
    try:
        send_setpoints(conn, U, 1)
        assert pump(link, 5.0, until=lambda: server.vehicle.rejections["bad_signature"] >= 1)
    finally:
        conn.close()
    with server.lock:
        assert server.vehicle.rejections["bad_signature"] == 1
        assert server.vehicle.rejections["stale_signature"] == 0
    assert_flies(link, server, -U)
    with server.lock:
        assert server.vehicle.rejections["stale_signature"] == 0


# ---------------------------------------------------------------- (4) replay
def test_a_replayed_signed_setpoint_is_rejected(served: Any) -> None:
    link, server = served()
    link.handshake(timeout_s=10.0)
    # A genuine frame signed with the key (its own stream, link id 9), captured as bytes.
    recorder = mav.MAVLink(None, srcSystem=SYS, srcComponent=COMPANION)
    enable_signing(recorder, KEY, link_id=9)
    vn, ve, vd = (float(c) for c in frames.enu_to_ned(U))
    frame = recorder.set_position_target_local_ned_encode(
        4242, SYS, 1, mav.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0
    ).pack(recorder)
    assert frame[2] & mav.MAVLINK_IFLAG_SIGNED
    conn = intruder(server)  # only used as a UDP sender of raw bytes
    try:
        conn.write(frame)
        assert pump(link, 2.0, until=lambda: server.vehicle.setpoint_stamped(4242) is not None)
        with server.lock:
            assert np.array_equal(server.vehicle.setpoint_stamped(4242),
                                  frames.velocity_over_link(U))  # applied once
            server.vehicle.begin_step(0)  # forget it, to see whether it comes back
            stale = server.vehicle.rejections["stale_signature"]
        for _ in range(3):
            conn.write(frame)
        assert pump(link, 2.0, until=lambda:
                    server.vehicle.rejections["stale_signature"] - stale == 3)
    finally:
        conn.close()
    with server.lock:
        assert server.vehicle.setpoint_stamped(4242) is None  # never applied again
        assert server.vehicle.rejections["bad_signature"] == 0


# ---------------------------------------------------------------- agent side
@pytest.mark.parametrize(("vehicle_key", "reason"),
                         [(None, "unsigned"), (WRONG_KEY, "bad_signature")],
                         ids=["unsigned", "wrong_key"])
def test_the_signing_agent_drops_frames_of_a_vehicle_without_the_key(
        served: Any, vehicle_key: bytes | None, reason: str) -> None:
    link, _ = served(vehicle_key=vehicle_key)
    with pytest.raises(LinkError) as err:
        link.wait_heartbeat(1.2)
    message = str(err.value)
    assert "\n" not in message and "dropped by MAVLink signing" in message, message
    assert f"{reason.replace('_', ' ')}" in message and "signing_key_file" in message
    assert link.rejections[reason] > 10  # heartbeats and 50 Hz LOCAL_POSITION_NED
    assert link.latest_position() is None  # the fast path is off: nothing unsigned gets in
    assert set(link.rejections) == {reason}


def test_the_vehicle_answers_only_signed_commands_and_signs_its_answers() -> None:
    vehicle = EmulatedVehicle(DRONE, "px4", START, ORIGIN, signing_key=KEY, start="ground")
    unsigned = mav.MAVLink(None, srcSystem=SYS, srcComponent=COMPANION)
    arm = unsigned.command_long_encode(SYS, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                       1, 0, 0, 0, 0, 0, 0)
    assert vehicle.receive(arm.pack(unsigned), 1.0) == []
    assert not vehicle.armed and vehicle.rejections == {"unsigned": 1}
    signer = mav.MAVLink(None, srcSystem=SYS, srcComponent=COMPANION)
    enable_signing(signer, KEY, link_id=1)
    replies = vehicle.receive(arm.pack(signer), 1.1)
    assert vehicle.armed and replies
    checker = mav.MAVLink(None)
    enable_signing(checker, KEY, link_id=3)
    for packet in [*replies, vehicle.heartbeat(), *vehicle.telemetry(20, 1.2)]:
        assert packet[2] & mav.MAVLINK_IFLAG_SIGNED
        (msg,) = checker.parse_buffer(packet) or [None]
        assert msg is not None and msg.get_type() != "BAD_DATA"
    assert {m.get_type() for m in (checker.parse_buffer(vehicle.telemetry(40, 1.3)[0]) or [])} \
        == {"LOCAL_POSITION_NED"}


def test_signing_is_off_by_default() -> None:
    vehicle = EmulatedVehicle(DRONE, "px4", START, ORIGIN)
    assert not vehicle.signing and vehicle._rx.signing.secret_key is None
    (packet,) = [p for p in vehicle.telemetry(20, 0.02) if p[7] == 32]  # LOCAL_POSITION_NED
    assert packet[2] == 0  # unsigned (packed by the fast path)
    with AutopilotLink("udpin:127.0.0.1:0", DRONE, "px4", ORIGIN, log=lambda _: None) as link:
        assert not link.signing and link._conn.mav.signing.secret_key is None


# ---------------------------------------------------------------- (5) key files
def write(tmp_path: Path, name: str, content: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(content)
    return path


def test_key_file_of_64_hex_digits_is_read(tmp_path: Path) -> None:
    assert read_signing_key(write(tmp_path, "k", (KEY.hex() + "\n").encode())) == KEY
    assert read_signing_key(write(tmp_path, "K", f"  {KEY.hex().upper()}\r\n".encode())) == KEY


@pytest.mark.parametrize(("content", "reason"), [
    (b"", "got 0 characters"),
    (b"00" * 31, "got 62 characters"),
    (b"0" * 65, "got 65 characters"),
    (b"zz" * 32, "got other characters"),
    (bytes(range(200, 232)), "not a text file"),  # the raw 32 bytes: refused, not guessed
    (b"correct horse battery staple", "got 28 characters"),
    (b"0" * 5000, "more than 4096 bytes"),
])
def test_bad_key_file_is_one_line_without_its_content(tmp_path: Path, content: bytes,
                                                      reason: str) -> None:
    path = write(tmp_path, "bad.key", content)
    with pytest.raises(SigningKeyError) as err:
        read_signing_key(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: ") and reason in message
    assert "64 hex digits" in message or "not a text file" in message
    assert "horse" not in message and "zz" not in message


def test_missing_key_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(SigningKeyError, match="no such file"):
        read_signing_key(tmp_path / "none.key")
    with pytest.raises(SigningKeyError, match="is a directory"):
        read_signing_key(tmp_path)


def _config_with_key(tmp_path: Path, key_line: str) -> Path:
    text = (ROOT / "configs" / "case1.toml").read_text()
    text = text.replace('signing_key_file = ""', key_line, 1)
    assert key_line in text
    path = tmp_path / "cfg" / "signed.toml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)
    return path


def test_config_key_file_is_relative_to_the_config_file(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    config_path = _config_with_key(tmp_path, 'signing_key_file = "swarm.key"')
    write(config_path.parent, "swarm.key", KEY.hex().encode())
    monkeypatch.chdir(tmp_path)  # not the config's directory
    config = load_config(config_path)
    assert config.vehicles.signing_key_file == str(config_path.parent / "swarm.key")
    assert config.vehicles.signing_key() == KEY
    assert KEY.hex() not in repr(config)  # the config (and so recordings) holds the path only
    assert load_config(ROOT / "configs" / "case1.toml").vehicles.signing_key() is None


def test_bad_key_file_in_config_is_one_config_error(tmp_path: Path) -> None:
    config_path = _config_with_key(tmp_path, 'signing_key_file = "short.key"')
    write(config_path.parent, "short.key", b"abcd")
    with pytest.raises(ConfigError) as err:
        load_config(config_path)
    assert str(err.value) == (
        f"{config_path}: vehicles.signing_key_file: {config_path.parent / 'short.key'}: "
        f"expected the 32-byte key as 64 hex digits (e.g. openssl rand -hex 32), "
        f"got 4 characters")


@pytest.mark.parametrize("module", ["sim_world.vehicles_cli", "swarm.agent.cli"])
def test_bad_key_file_makes_the_entry_points_exit_2_with_one_line(tmp_path: Path,
                                                                  module: str) -> None:
    config_path = _config_with_key(tmp_path, 'signing_key_file = "missing.key"')
    args = [str(config_path)] if module == "sim_world.vehicles_cli" \
        else ["--id", "0", "--config", str(config_path)]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    result = subprocess.run([sys.executable, "-m", module, *args], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2, result
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert "vehicles.signing_key_file" in lines[0] and "no such file" in lines[0]

