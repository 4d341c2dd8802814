"""Agent side of the MAVLink 2 link to one autopilot (PX4 or ArduPilot; real or emulated).

SPEC §12. The agent talks to its vehicle only through this class. It opens a pymavlink
connection (any pymavlink URL; for the emulated world and PX4 SITL ``udpin:127.0.0.1:<port>``)
as a companion computer: system id = the vehicle's (``drone_id + 1``) unless overridden,
component MAV_COMP_ID_ONBOARD_COMPUTER (191), MAVLink 2 framing, ardupilotmega dialect. It
sends a companion HEARTBEAT at 1 Hz whenever it sends anything else.

Positions come from LOCAL_POSITION_NED and are brought into the world frame W with
``frames.world_from_local_ned(ned, origin_w)`` (``origin_w``: the configured per-drone origin
offset, i.e. the vehicle's local NED origin in W); velocities with ``frames.ned_to_enu``.
Setpoints are SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_LOCAL_NED, type_mask 0x0DC7 (velocity
only), velocity ``frames.to_link_float(frames.enu_to_ned(velocity_w))``.

Reading drains the socket completely and keeps only the newest sample (a queue of stale
samples is the classic bug). Bad bytes never raise: BAD_DATA (garbage, bad CRC, bad length)
and unknown message ids are counted in ``rejected_frames`` (reasons in ``rejections``);
frames from other systems (another vehicle, a GCS, MAVProxy's own heartbeat) are ignored and
counted in ``foreign_frames``. Over ``udpin`` the vehicle's address is pinned at its first
valid frame and replies go there only; datagrams from any other address are dropped unread
and counted as ``foreign_address``: a stray or forged sender can neither redirect nor copy
the setpoints (a vehicle that comes back from another address needs a new link; PX4 SITL
and the emulated vehicles keep theirs). NaN/inf positions are dropped as
``nonfinite_position``.
The per-step messages (LOCAL_POSITION_NED in, the velocity setpoint out) take
``swarm.mavlink_parse``'s fast path over UDP: same bytes, no pymavlink message objects (so
pymavlink's own bookkeeping, e.g. ``messages`` and packet-loss counts, does not see those
samples).

Public API
----------
``Flavour = Literal["px4", "ardupilot"]``; ``IDLE_STAMP_MS = 0xFFFFFFFF`` (time_boot_ms of
the zero setpoints sent by ``handshake`` and ``keepalive``, so they never match a lockstep
step stamp).

``PositionSample(time_boot_ms, position_w, velocity_w, received_s)`` (frozen dataclass).

``LinkError(RuntimeError)``: one-line message saying what failed and what to check.

``AutopilotLink(url, drone_id, flavour, origin_w, *, log=print, source_system=None,
clock=time.monotonic, signing_key=None)``
    ``wait_heartbeat(timeout_s)``; ``handshake(timeout_s=20.0, retries=5,
    takeoff_altitude_m=None, *, ack_timeout_s=1.0)``; ``keepalive(now_s=None)``;
    ``latest_position() -> PositionSample | None``; ``wait_position(time_boot_ms, timeout_s)
    -> PositionSample``; ``send_velocity(velocity_w, time_boot_ms)``; ``poll()`` (drain
    only); ``close()`` (also a context manager). Properties: ``url``, ``drone_id``,
    ``system_id``, ``flavour``, ``origin_w``, ``local_address`` ((host, port) for UDP URLs,
    else None), ``armed``, ``mode`` (pymavlink's mode name from the newest vehicle HEARTBEAT,
    e.g. "OFFBOARD", "GUIDED"; "UNKNOWN" before one), ``custom_mode``, ``autopilot``,
    ``last_heartbeat_s``, ``rejected_frames``, ``rejections``, ``foreign_frames``.
    Times (``now_s``, ``received_s``, ``last_heartbeat_s``) are on ``clock``.

MAVLink 2 signing (``signing_key``: the 32-byte secret, see ``swarm.mavlink_signing``; None:
off): pymavlink's own ``setup_signing`` on the connection, link id 1. Everything sent is
signed (setpoints and heartbeats leave the fast path); frames from the vehicle that are
unsigned or wrongly signed, or whose signing timestamp is not newer than the last (replay),
are dropped and counted in ``rejected_frames`` (over UDP as ``unsigned``, ``bad_signature``
or ``stale_signature``; stream links count them as ``bad_data``). The signing timestamp
follows the wall clock (refreshed with the 1 Hz companion heartbeat). ``signing``
(property) says whether it is on; the key is never logged.

``wait_heartbeat`` asks the vehicle for a HEARTBEAT (MAV_CMD_REQUEST_MESSAGE, every 0.25 s)
as soon as any frame of it arrives, rather than waiting up to a second for the 1 Hz one.

Handshake (each stage logged as ``drone <id>: ...``; a stage already in effect is skipped):
PX4: stream zero setpoints at 20 Hz for 0.2 s; DO_SET_MODE OFFBOARD (custom main mode 6)
until ACCEPTED and the heartbeat shows OFFBOARD; ARM until ACCEPTED and the heartbeat shows
armed. ArduPilot: MAV_CMD_SET_MESSAGE_INTERVAL LOCAL_POSITION_NED at 50 Hz until ACCEPTED and
a sample arrives; DO_SET_MODE GUIDED (4); ARM; MAV_CMD_NAV_TAKEOFF to ``takeoff_altitude_m``
(default: the current altitude above the local origin). Zero setpoints keep streaming
throughout (PX4 leaves OFFBOARD without them). Each command is retried up to ``retries``
times (no ACK within ``ack_timeout_s``, a non-ACCEPTED result, or an ACCEPTED result that the
heartbeat does not confirm within 2.5 s); LinkError when a stage exhausts its retries or the
whole handshake exceeds ``timeout_s``.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import select
import socket
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm import frames
from swarm.mavlink_parse import LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED, parse_bytes
from swarm.mavlink_signing import KEY_BYTES, refresh_signing_timestamp

Array = NDArray[np.float64]
Flavour = Literal["px4", "ardupilot"]

__all__ = ["IDLE_STAMP_MS", "AutopilotLink", "Flavour", "LinkError", "PositionSample"]

IDLE_STAMP_MS = 0xFFFFFFFF
VELOCITY_ONLY_TYPE_MASK = 0x0DC7  # ignore x, y, z, afx, afy, afz, yaw, yaw rate
AUTOPILOT_COMPONENT_ID = 1
_PX4_MAIN_MODE_OFFBOARD = 6
_ACM_MODE_GUIDED = 4
_SETPOINT_PERIOD_S = 0.05  # zero setpoints during the handshake: 20 Hz
_KEEPALIVE_PERIOD_S = 0.1
_COMPANION_HEARTBEAT_PERIOD_S = 1.0
# PX4 takes OFFBOARD once setpoints arrive (a 2 Hz "proof of life" within COM_OF_LOSS_T);
# a few at 20 Hz are plenty, and this wait is on every agent's path to the mission.
_PRE_STREAM_S = 0.2
_CONFIRM_TIMEOUT_S = 2.5
_RETRY_PAUSE_S = 0.3
# Ask for a HEARTBEAT (MAV_CMD_REQUEST_MESSAGE) at most this often once the vehicle is heard,
# instead of waiting up to a second for its 1 Hz one; autopilots that refuse just NACK.
_HEARTBEAT_REQUEST_PERIOD_S = 0.25
_MAV_CMD_REQUEST_MESSAGE = 512
_MAX_STAMPED_SAMPLES = 512
_MAX_MESSAGES_PER_DRAIN = 100_000
_MAX_DATAGRAM = 65535
_SIGNING_LINK_ID = 1  # any constant: the receiver's stream key also holds our system id
_SIGNATURE_REJECTIONS = ("unsigned", "bad_signature", "stale_signature")
_AUTOPILOT_NAMES = {mavlink2.MAV_AUTOPILOT_PX4: "PX4",
                    mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot"}
_EXPECTED_AUTOPILOT = {"px4": mavlink2.MAV_AUTOPILOT_PX4,
                       "ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA}


@dataclass(frozen=True)
class PositionSample:
    """One LOCAL_POSITION_NED report in W; ``received_s`` on the link's clock."""

    time_boot_ms: int
    position_w: Array
    velocity_w: Array
    received_s: float


class LinkError(RuntimeError):
    """The autopilot link failed; the message is one line saying what to check."""


def _result_name(result: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else "UNKNOWN"


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class AutopilotLink:
    """MAVLink 2 link from one agent to its autopilot (see module docstring)."""

    def __init__(
        self,
        url: str,
        drone_id: int,
        flavour: Flavour,
        origin_w: ArrayLike,
        *,
        log: Callable[[str], None] = print,
        source_system: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        signing_key: bytes | None = None,
    ) -> None:
        if flavour not in ("px4", "ardupilot"):
            raise ValueError(f"flavour must be 'px4' or 'ardupilot', got {flavour!r}")
        if not 0 <= drone_id <= 253:
            raise ValueError(f"drone_id must be in 0..253, got {drone_id}")
        self._url = url
        self._drone_id = int(drone_id)
        self._sysid = self._drone_id + 1
        self._flavour: Flavour = flavour
        self._origin = np.array(origin_w, dtype=np.float64).reshape(3).copy()
        self._log_fn = log
        self._clock = clock
        self._source_system = self._sysid if source_system is None else int(source_system)

        _check_udpin_port_free(url)
        # pymavlink picks MAVLink 1 or 2 from this variable when the connection sets its
        # dialect (it is read at connection time, and inherited by child processes).
        os.environ.setdefault("MAVLINK20", "1")
        try:
            self._conn: Any = mavutil.mavlink_connection(
                url, source_system=self._source_system,
                source_component=mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
                dialect="ardupilotmega", udp_timeout=5.0)
        except Exception as exc:
            raise LinkError(_one_line(
                f"drone {self._drone_id}: cannot open MAVLink connection {url!r}: {exc}")) from exc
        if not self._conn.mavlink20():
            self._conn.close()
            raise LinkError(f"drone {self._drone_id}: pymavlink did not select MAVLink 2 for "
                            f"{url} (MAVLINK20={os.environ.get('MAVLINK20')!r})")
        self._signing = signing_key is not None
        if signing_key is not None:
            if len(signing_key) != KEY_BYTES:
                self._conn.close()
                raise ValueError(f"signing_key must have {KEY_BYTES} bytes, "
                                 f"got {len(signing_key)}")
            # pymavlink's own signing: every frame sent is signed, no unsigned one accepted.
            self._conn.setup_signing(bytes(signing_key), sign_outgoing=True,
                                     allow_unsigned_callback=None, link_id=_SIGNING_LINK_ID)
        self._closed = False

        self._heartbeat: Any = None
        self._mode_name: str | None = None  # mode_string_v10 of _heartbeat, computed once
        self._last_heartbeat_s: float | None = None
        self._vehicle_heard = False  # any valid frame from the autopilot (its address known)
        self._autopilot_frames = 0  # valid frames from the autopilot taken so far
        self._peer: tuple[str, int] | None = None  # udpin: the vehicle's pinned address
        self._last_heartbeat_request_s: float | None = None
        self._other_systems: set[int] = set()
        self._acks: dict[int, int] = {}
        self._latest: PositionSample | None = None
        self._by_stamp: OrderedDict[int, PositionSample] = OrderedDict()
        self._samples_received = 0
        self._last_setpoint_sent_s: float | None = None
        self._last_companion_hb_s: float | None = None
        self.rejections: Counter[str] = Counter()
        self.foreign_frames = 0

    # ---------------------------------------------------------------- properties
    @property
    def url(self) -> str:
        return self._url

    @property
    def drone_id(self) -> int:
        return self._drone_id

    @property
    def system_id(self) -> int:
        return self._sysid

    @property
    def flavour(self) -> Flavour:
        return self._flavour

    @property
    def origin_w(self) -> Array:
        return self._origin.copy()

    @property
    def local_address(self) -> tuple[str, int] | None:
        port = getattr(self._conn, "port", None)
        if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
            host, number = port.getsockname()[:2]
            return str(host), int(number)
        return None

    @property
    def armed(self) -> bool:
        hb = self._heartbeat
        return hb is not None and bool(hb.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode(self) -> str:
        if self._heartbeat is None:
            return "UNKNOWN"
        if self._mode_name is None:  # read every step (telemetry); the heartbeat comes at 1 Hz
            self._mode_name = mavutil.mode_string_v10(self._heartbeat)
        return self._mode_name

    @property
    def custom_mode(self) -> int | None:
        return None if self._heartbeat is None else int(self._heartbeat.custom_mode)

    @property
    def autopilot(self) -> int | None:
        return None if self._heartbeat is None else int(self._heartbeat.autopilot)

    @property
    def last_heartbeat_s(self) -> float | None:
        return self._last_heartbeat_s

    @property
    def rejected_frames(self) -> int:
        return sum(self.rejections.values())

    @property
    def signing(self) -> bool:
        return self._signing

    # ---------------------------------------------------------------- reading
    def poll(self) -> None:
        """Drain every datagram waiting now and update state (heartbeat, samples, ACKs)."""
        self._drain()

    def latest_position(self) -> PositionSample | None:
        self._drain()
        return self._latest

    def wait_position(self, time_boot_ms: int, timeout_s: float) -> PositionSample:
        stamp = int(time_boot_ms)
        deadline = self._clock() + timeout_s
        while True:
            self._drain()
            sample = self._by_stamp.get(stamp)
            if sample is not None:
                return sample
            remaining = deadline - self._clock()
            if remaining <= 0:
                newest = "none" if self._latest is None else f"{self._latest.time_boot_ms} ms"
                raise LinkError(
                    f"drone {self._drone_id}: no LOCAL_POSITION_NED stamped {stamp} ms from "
                    f"system {self._sysid} on {self._url} within {timeout_s:g} s "
                    f"(newest seen: {newest})")
            self._wait_readable(min(remaining, 0.05))

    def wait_heartbeat(self, timeout_s: float) -> None:
        """Wait for a HEARTBEAT of the vehicle's autopilot (one seen in the last 1.5 s counts)
        and check it is the configured flavour; LinkError otherwise."""
        start = self._clock()

        def fresh() -> bool:
            if self._last_heartbeat_s is not None and self._last_heartbeat_s >= start - 1.5:
                return True
            self._request_heartbeat()
            return False

        if not self._pump(fresh, start + timeout_s, stream=False):
            raise LinkError(self._no_heartbeat_message(timeout_s))
        expected = _EXPECTED_AUTOPILOT[self._flavour]
        if self._heartbeat.autopilot != expected:
            name = _AUTOPILOT_NAMES.get(self._heartbeat.autopilot,
                                        f"autopilot type {self._heartbeat.autopilot}")
            raise LinkError(
                f"drone {self._drone_id}: system {self._sysid} on {self._url} reports autopilot "
                f"{name} but flavour {self._flavour!r} is configured")

    # ---------------------------------------------------------------- sending
    def send_velocity(self, velocity_w: ArrayLike, time_boot_ms: int) -> None:
        """One velocity setpoint (W, m/s) stamped ``time_boot_ms`` (uint32). Values beyond
        the float32 range go out as ±inf, which a vehicle drops as non-finite."""
        stamp = int(time_boot_ms)
        if not 0 <= stamp <= 0xFFFFFFFF:
            raise ValueError(f"time_boot_ms must fit in uint32, got {time_boot_ms}")
        self._send_setpoint(frames.to_link_float(frames.enu_to_ned(velocity_w)), stamp)

    def keepalive(self, now_s: float | None = None) -> None:
        """Drain, and send a zero setpoint (stamped IDLE_STAMP_MS) if none was sent in the
        last 0.1 s; ``now_s`` is on the link's clock (default: read it)."""
        self._drain()
        now = self._clock() if now_s is None else now_s
        if self._last_setpoint_sent_s is None \
                or now - self._last_setpoint_sent_s >= _KEEPALIVE_PERIOD_S:
            self._send_setpoint(np.zeros(3), IDLE_STAMP_MS)

    def handshake(
        self,
        timeout_s: float = 20.0,
        retries: int = 5,
        takeoff_altitude_m: float | None = None,
        *,
        ack_timeout_s: float = 1.0,
    ) -> None:
        if retries < 1:
            raise ValueError(f"retries must be >= 1, got {retries}")
        deadline = self._clock() + timeout_s
        me = f"drone {self._drone_id}"
        if self._signing:
            self._log(f"{me}: MAVLink 2 signing on: unsigned or wrongly signed frames from "
                      f"the vehicle are dropped")
        self._log(f"{me}: waiting for HEARTBEAT from system {self._sysid} on {self._url}")
        self.wait_heartbeat(max(0.0, deadline - self._clock()))
        self._log(f"{me}: HEARTBEAT from system {self._sysid} "
                  f"({_AUTOPILOT_NAMES[self._heartbeat.autopilot]}, mode {self.mode}, "
                  f"{'armed' if self.armed else 'disarmed'})")
        run = dict(deadline=deadline, retries=retries, ack_timeout_s=ack_timeout_s,
                   timeout_s=timeout_s)
        if self._flavour == "px4":
            self._log(f"{me}: streaming zero setpoints for {_PRE_STREAM_S:g} s")
            self._pump(lambda: False, min(deadline, self._clock() + _PRE_STREAM_S), stream=True)
            self._command_stage(
                "OFFBOARD", mavlink2.MAV_CMD_DO_SET_MODE,
                lambda: (self._mode_flags(), _PX4_MAIN_MODE_OFFBOARD, 0, 0, 0, 0, 0),
                done=lambda: self.mode == "OFFBOARD", pending="heartbeat shows OFFBOARD", **run)
            self._command_stage(
                "ARM", mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, lambda: (1, 0, 0, 0, 0, 0, 0),
                done=lambda: self.armed, pending="heartbeat shows armed", **run)
            if self.mode != "OFFBOARD":
                raise LinkError(f"{me}: vehicle left OFFBOARD (now {self.mode}) while arming "
                                f"on {self._url}: is something else commanding it?")
            self._log(f"{me}: ready (OFFBOARD, armed)")
            return
        count = self._samples_received
        self._command_stage(
            "LOCAL_POSITION_NED stream", mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
            lambda: (mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000, 0, 0, 0, 0, 0),
            done=lambda: self._samples_received > count, pending="a LOCAL_POSITION_NED arrives",
            skip_if_done=False, **run)
        self._command_stage(
            "GUIDED", mavlink2.MAV_CMD_DO_SET_MODE,
            lambda: (self._mode_flags(), _ACM_MODE_GUIDED, 0, 0, 0, 0, 0),
            done=lambda: self.mode == "GUIDED", pending="heartbeat shows GUIDED", **run)
        self._command_stage(
            "ARM", mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, lambda: (1, 0, 0, 0, 0, 0, 0),
            done=lambda: self.armed, pending="heartbeat shows armed", **run)
        if takeoff_altitude_m is None:
            assert self._latest is not None  # the stream stage waited for a sample
            takeoff_altitude_m = float(self._latest.position_w[2] - self._origin[2])
        altitude = float(takeoff_altitude_m)
        self._command_stage(
            f"TAKEOFF to {altitude:.2f} m", mavlink2.MAV_CMD_NAV_TAKEOFF,
            lambda: (0, 0, 0, math.nan, 0, 0, altitude), done=None, pending="",
            skip_if_done=False, **run)
        if self.mode != "GUIDED" or not self.armed:
            raise LinkError(f"{me}: vehicle is {self.mode}, "
                            f"{'armed' if self.armed else 'disarmed'} after takeoff on "
                            f"{self._url}: is something else commanding it?")
        self._log(f"{me}: ready (GUIDED, armed, airborne)")

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._conn.close()

    def __enter__(self) -> AutopilotLink:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # ================================================================ internals
    def _log(self, line: str) -> None:
        self._log_fn(line)

    def _mode_flags(self) -> int:
        flags = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            flags |= mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        return flags

    def _no_heartbeat_message(self, timeout_s: float) -> str:
        text = f"no HEARTBEAT from system {self._sysid} on {self._url} within {timeout_s:g} s"
        refused = sum(self.rejections[reason] for reason in _SIGNATURE_REJECTIONS)
        if refused:
            how = ", ".join(f"{self.rejections[r]} {r.replace('_', ' ')}"
                            for r in _SIGNATURE_REJECTIONS if self.rejections[r])
            return (f"{text}: {refused} frame(s) dropped by MAVLink signing ({how}): does the "
                    f"vehicle sign with the same key (vehicles.signing_key_file)?")
        if self._other_systems:
            heard = ", ".join(str(s) for s in sorted(self._other_systems))
            return f"{text}: heard system(s) {heard} instead: check --id and the port"
        port = _udpin_port(self._url)
        if port is not None and port > 0:
            return (f"{text}: is sim-world running with --mavlink-base "
                    f"{port - self._drone_id}?")
        return f"{text}: is the autopilot running and sending to this address?"

    def _command_stage(
        self,
        name: str,
        command: int,
        params: Callable[[], tuple[float, ...]],
        *,
        done: Callable[[], bool] | None,
        pending: str,
        deadline: float,
        retries: int,
        ack_timeout_s: float,
        timeout_s: float,
        skip_if_done: bool = True,
    ) -> None:
        me = f"drone {self._drone_id}"
        if skip_if_done and done is not None and done():
            self._log(f"{me}: {name} already in effect")
            return
        last = "not attempted"
        for attempt in range(1, retries + 1):
            if self._clock() >= deadline:
                break
            self._acks.pop(command, None)
            self._conn.mav.command_long_send(self._sysid, AUTOPILOT_COMPONENT_ID, command,
                                             attempt - 1, *params())
            last = self._await_result(command, done, pending, deadline, ack_timeout_s)
            if last == "accepted":
                self._log(f"{me}: {name} accepted")
                return
            if attempt < retries:
                self._log(f"{me}: {name} {last}, retry {attempt + 1}/{retries}")
                self._pump(lambda: False, min(deadline, self._clock() + _RETRY_PAUSE_S),
                           stream=True)
        if self._clock() >= deadline:
            raise LinkError(f"{me}: handshake did not complete within {timeout_s:g} s on "
                            f"{self._url}: {name} {last}")
        raise LinkError(f"{me}: {name} failed after {retries} attempts on {self._url}: {last}")

    def _await_result(self, command: int, done: Callable[[], bool] | None, pending: str,
                      deadline: float, ack_timeout_s: float) -> str:
        ack_deadline = min(deadline, self._clock() + ack_timeout_s)
        while True:
            if not self._pump(lambda: command in self._acks, ack_deadline, stream=True):
                return f"got no ACK within {ack_timeout_s:g} s"
            result = self._acks.pop(command)
            if result == mavlink2.MAV_RESULT_IN_PROGRESS:
                ack_deadline = min(deadline, self._clock() + ack_timeout_s)
                continue
            if result != mavlink2.MAV_RESULT_ACCEPTED:
                return f"denied (result {result} {_result_name(result)})"
            if done is None or self._pump(
                    done, min(deadline, self._clock() + _CONFIRM_TIMEOUT_S), stream=True):
                return "accepted"
            return f"accepted but not confirmed ({pending}) within {_CONFIRM_TIMEOUT_S:g} s"

    def _pump(self, until: Callable[[], bool], deadline: float, *, stream: bool) -> bool:
        """Drain (and stream zero setpoints) until ``until()`` or the deadline."""
        while True:
            self._drain()
            if until():
                return True
            now = self._clock()
            if now >= deadline:
                return False
            wait = deadline - now
            if stream:
                if self._last_setpoint_sent_s is None \
                        or now - self._last_setpoint_sent_s >= _SETPOINT_PERIOD_S:
                    self._send_setpoint(np.zeros(3), IDLE_STAMP_MS)
                wait = min(wait, _SETPOINT_PERIOD_S)
            self._wait_readable(min(wait, 0.05))

    def _request_heartbeat(self) -> None:
        """Ask the autopilot for a HEARTBEAT now, once it is heard (udpin: before that its
        address is unknown) and at most every _HEARTBEAT_REQUEST_PERIOD_S."""
        if not self._vehicle_heard:
            return
        now = self._clock()
        if self._last_heartbeat_request_s is not None \
                and now - self._last_heartbeat_request_s < _HEARTBEAT_REQUEST_PERIOD_S:
            return
        self._last_heartbeat_request_s = now
        self._conn.mav.command_long_send(self._sysid, AUTOPILOT_COMPONENT_ID,
                                         _MAV_CMD_REQUEST_MESSAGE, 0,
                                         mavlink2.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0)

    def _send_setpoint(self, ned: Array, stamp: int) -> None:
        vn, ve, vd = (float(c) for c in ned)
        mav = self._conn.mav
        # Fields in wire order (SET_POSITION_TARGET_LOCAL_NED.fields); pymavlink's own send
        # when the fast path does not apply (signing, a send callback).
        frame = SET_POSITION_TARGET_LOCAL_NED.pack(
            mav, stamp, 0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0,
            VELOCITY_ONLY_TYPE_MASK, self._sysid, AUTOPILOT_COMPONENT_ID,
            mavlink2.MAV_FRAME_LOCAL_NED)
        if frame is not None:
            mav.file.write(frame)
        else:
            mav.set_position_target_local_ned_send(
                stamp, self._sysid, AUTOPILOT_COMPONENT_ID, mavlink2.MAV_FRAME_LOCAL_NED,
                VELOCITY_ONLY_TYPE_MASK, 0.0, 0.0, 0.0, vn, ve, vd, 0.0, 0.0, 0.0, 0.0, 0.0)
        now = self._clock()
        self._last_setpoint_sent_s = now
        if self._last_companion_hb_s is None \
                or now - self._last_companion_hb_s >= _COMPANION_HEARTBEAT_PERIOD_S:
            self._last_companion_hb_s = now
            if self._signing:
                refresh_signing_timestamp(mav)
            self._conn.mav.heartbeat_send(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                                          mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                                          mavlink2.MAV_STATE_ACTIVE)

    def _wait_readable(self, timeout_s: float) -> None:
        fd = getattr(self._conn, "fd", None)
        if fd is None:
            self._conn.select(max(0.0, timeout_s))
            return
        with contextlib.suppress(OSError, ValueError):
            select.select([fd], [], [], max(0.0, timeout_s))

    def _readable_now(self) -> bool:
        fd = getattr(self._conn, "fd", None)
        if fd is None:
            return False
        try:
            return bool(select.select([fd], [], [], 0)[0])
        except (OSError, ValueError):
            return False

    def _drain(self) -> None:
        if isinstance(self._conn, mavutil.mavudp):
            self._drain_datagrams()
            return
        for _ in range(_MAX_MESSAGES_PER_DRAIN):  # stream links (serial, TCP): pymavlink's loop
            try:
                msg = self._conn.recv_msg()
            except Exception as exc:  # pymavlink with robust parsing should not raise
                self.rejections[f"receive_error:{type(exc).__name__}"] += 1
                return
            if msg is None:
                if self._readable_now():
                    continue  # those bytes held no complete frame; more are waiting
                return
            self._handle(msg)

    def _drain_datagrams(self) -> None:
        """UDP, one datagram at a time (pymavlink's own recv_msg would keep a truncated
        frame as the start of a stream; ``parse_bytes`` counts and drops it)."""
        if getattr(self._conn, "udp_server", False):
            self._drain_udpin()
            return
        for _ in range(_MAX_MESSAGES_PER_DRAIN):
            try:
                data = self._conn.recv()  # one datagram, "" when none is waiting
            except Exception as exc:
                self.rejections[f"receive_error:{type(exc).__name__}"] += 1
                return
            if not data:
                return
            self._datagram(data)

    def _drain_udpin(self) -> None:
        """``udpin``: pymavlink would send to every address that ever sent a datagram here
        (for 5 s), so one forged datagram would get a copy of every setpoint, and a flood
        from many ports a flood of copies. Instead the vehicle's address is pinned at its
        first valid frame (the only address sent to) for good; a datagram from anywhere else
        is counted as ``foreign_address`` and dropped unread. The pin never moves: a lockstep
        world may be silent for seconds on a loaded machine, and junk with one valid frame
        inside must not take the link over then."""
        conn = self._conn
        for _ in range(_MAX_MESSAGES_PER_DRAIN):
            try:
                data, sender = conn.port.recvfrom(_MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno != errno.ECONNREFUSED:  # the ICMP of an earlier send: harmless
                    self.rejections[f"receive_error:{type(exc).__name__}"] += 1
                return
            sender = (str(sender[0]), int(sender[1]))
            peer = self._peer
            if peer is not None and sender != peer:
                self.rejections["foreign_address"] += 1
                continue
            if not data:
                self.rejections["empty_datagram"] += 1
                continue
            taken = self._autopilot_frames
            self._datagram(data)
            if peer is None and self._autopilot_frames > taken:
                self._pin(sender)

    def _pin(self, sender: tuple[str, int]) -> None:
        """Send to ``sender`` (and nobody else) from now on."""
        self._peer = sender
        self._conn.clients = {sender}
        self._conn.clients_last_alive = {sender: time.time()}

    def _datagram(self, data: bytes) -> None:
        """Everything in one datagram."""
        fast = None if self._signing else LOCAL_POSITION_NED.unpack(data)  # unsigned only
        if fast is not None and fast[0] == self._sysid and fast[1] == AUTOPILOT_COMPONENT_ID:
            self._vehicle_heard = True
            self._on_local_position(*fast[2])  # the 50 Hz sample: no message object
            return
        for msg in parse_bytes(self._conn.mav, data, self.rejections, datagram=True):
            self._handle(msg)

    def _handle(self, msg: Any) -> None:
        try:
            self._conn.post_message(msg)  # pymavlink's own bookkeeping (messages, params)
            self._process(msg)
        except Exception as exc:  # malformed field values must never escape
            self.rejections[f"handler_error:{type(exc).__name__}"] += 1

    def _process(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.rejections["bad_data"] += 1  # junk, bad CRC, bad length
            return
        if kind.startswith("UNKNOWN"):
            self.rejections["unknown_message"] += 1
            return
        if msg.get_srcSystem() != self._sysid:
            self.foreign_frames += 1
            if kind == "HEARTBEAT" and msg.type not in (mavlink2.MAV_TYPE_GCS,
                                                        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER):
                self._other_systems.add(msg.get_srcSystem())
            return
        if msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            self.foreign_frames += 1
            return
        self._vehicle_heard = True
        if kind != "LOCAL_POSITION_NED":  # a sample counts once it is finite
            self._autopilot_frames += 1
        if kind == "HEARTBEAT":
            self._heartbeat = msg
            self._mode_name = None
            self._last_heartbeat_s = self._clock()
        elif kind == "LOCAL_POSITION_NED":
            self._on_local_position(msg.time_boot_ms, msg.x, msg.y, msg.z, msg.vx, msg.vy,
                                    msg.vz)
        elif kind == "COMMAND_ACK" and msg.target_system in (0, self._source_system):
            self._acks[int(msg.command)] = int(msg.result)

    def _on_local_position(self, time_boot_ms: int, x: float, y: float, z: float,
                           vx: float, vy: float, vz: float) -> None:
        if not all(map(math.isfinite, (x, y, z, vx, vy, vz))):
            self.rejections["nonfinite_position"] += 1
            return
        self._autopilot_frames += 1
        sample = PositionSample(int(time_boot_ms),
                                frames.world_from_local_ned((x, y, z), self._origin),
                                frames.ned_to_enu((vx, vy, vz)), self._clock())
        self._latest = sample
        self._samples_received += 1
        self._by_stamp[sample.time_boot_ms] = sample
        self._by_stamp.move_to_end(sample.time_boot_ms)
        while len(self._by_stamp) > _MAX_STAMPED_SAMPLES:
            self._by_stamp.popitem(last=False)


def _udpin_port(url: str) -> int | None:
    if not url.startswith("udpin:"):
        return None
    try:
        return int(url.rsplit(":", 1)[1])
    except ValueError:
        return None


def _check_udpin_port_free(url: str) -> None:
    """pymavlink binds udpin sockets with SO_REUSEADDR, so on Linux a second process can bind
    the same port silently and steal datagrams. Probe with a plain bind first."""
    port = _udpin_port(url)
    if port is None or port == 0:
        return
    host = url[len("udpin:"):].rsplit(":", 1)[0]
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.bind((host, port))
    except OSError as exc:
        raise LinkError(_one_line(
            f"cannot listen on {url}: {exc.strerror or exc}: is another agent (same --id and "
            f"--mavlink-base) or a ground station already using that port?")) from exc
    finally:
        probe.close()
