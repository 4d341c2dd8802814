"""Agent side of the MAVLink 2 link to one autopilot (PX4 or ArduPilot; real or emulated).

SPEC §12. The agent talks to its vehicle only through ``AutopilotLink``: a pymavlink
connection as a companion computer that reads positions into the world frame, sends
setpoints, brings the vehicle to "armed, in the setpoint mode, in the air" (``handshake``),
refuses a second autopilot, and ends the mission with the configured action. How it does
each, and its public API: docs/mavlink_link.md.
"""

from __future__ import annotations

import contextlib
import errno
import math
import re
import select
import socket
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.mavlink import px4_events
from swarm.mavlink.connection import LinkError, open_connection
from swarm.mavlink.connection import one_line as _one_line
from swarm.mavlink.parse import (
    LOCAL_POSITION_NED,
    POSITION_ONLY_TYPE_MASK,
    SET_POSITION_TARGET_LOCAL_NED,
    TRACKED_TYPE_MASK,
    VELOCITY_ONLY_TYPE_MASK,
    console_text,
    parse_bytes,
)
from swarm.mavlink.signing import KEY_BYTES, refresh_signing_timestamp
from swarm.mavlink.udpin import BoundSocket, udpin_address
from swarm.models import frames

Array = NDArray[np.float64]
Flavour = Literal["px4", "ardupilot"]
EndAction = Literal["hold", "land", "rtl"]
END_ACTIONS: Final[tuple[EndAction, ...]] = ("hold", "land", "rtl")

__all__ = ["END_ACTIONS", "IDLE_STAMP_MS", "AutopilotLink", "EndAction", "EndOutcome",
           "EndReport", "Flavour", "LinkError", "PositionSample", "autopilot_mode_name",
           "end_mode_name"]

IDLE_STAMP_MS = 0xFFFFFFFF
AUTOPILOT_COMPONENT_ID = 1
# ArduCopter mode numbers; PX4 (main mode, sub mode) of px4_custom_mode.h.
_ACM_MODE: Final = {"guided": 4, "hold": 17, "land": 9, "rtl": 6}  # hold = BRAKE
_PX4_MODE: Final = {"offboard": (6, 0), "hold": (4, 3), "land": (4, 6), "rtl": (4, 5)}
# pymavlink's name of each mode, as ``mode`` shows it once the HEARTBEAT has it in effect
# (GUIDED, BRAKE, LAND, RTL; PX4: OFFBOARD, LOITER, LAND, RTL).
_MODE_NAME: Final = {
    **{("ardupilot", mode): mavutil.mode_mapping_acm[number]
       for mode, number in _ACM_MODE.items()},
    **{("px4", mode): mavutil.interpret_px4_mode(0, main << 16 | sub << 24)
       for mode, (main, sub) in _PX4_MODE.items()}}
# PX4's own names of its modes (its documentation, QGroundControl), for pymavlink's names of
# them; ArduPilot's own names are pymavlink's. A mode missing here keeps pymavlink's name.
_PX4_MODE_NAME: Final = {
    "MANUAL": "Manual", "STABILIZED": "Stabilized", "ACRO": "Acro", "RATTITUDE": "Rattitude",
    "ALTCTL": "Altitude", "POSCTL": "Position", "OFFBOARD": "Offboard", "MISSION": "Mission",
    "TAKEOFF": "Takeoff", "LOITER": "Hold", "FOLLOWME": "Follow Me", "RTL": "Return",
    "LAND": "Land"}
_SETPOINT_PERIOD_S = 0.05  # idle setpoints during the handshake: 20 Hz
_KEEPALIVE_PERIOD_S = 0.1
_ZERO: frames.Xyz = (0.0, 0.0, 0.0)  # a setpoint's unused position, velocity or acceleration
_COMPANION_HEARTBEAT_PERIOD_S = 1.0
# PX4 takes OFFBOARD once setpoints arrive (a 2 Hz "proof of life" within COM_OF_LOSS_T).
_PRE_STREAM_S = 0.2
_CONFIRM_TIMEOUT_S = 2.5
_RETRY_PAUSE_S = 0.3
_REFUSED_RETRY_PAUSE_S = 1.0  # "not now" (pre-arm checks): ask again this often
_STREAM_REQUEST_PERIOD_S = 2.0
_LANDED_STATE_WAIT_S = 2.0  # an autopilot that has not sent EXTENDED_SYS_STATE by then: guess
_AIRBORNE_GUESS_M = 0.5  # armed and this far above the local origin: in the air
_POSITION_PROGRESS_PERIOD_S = 10.0
CLIMB_TOLERANCE_M = 0.25  # a climb is done within this of its target (and in the air)
_CLIMB_SPEED_DONE_M_S = 0.3
# Longer than one heartbeat period (1 Hz): every autopilot sending on the port when the link
# opened has been heard before a command that arms or moves the vehicle goes out.
EXCLUSIVE_LISTEN_S = 1.3
# Ask for a HEARTBEAT (MAV_CMD_REQUEST_MESSAGE) at most this often once the vehicle is heard,
# instead of waiting up to a second for its 1 Hz one; autopilots that refuse just NACK.
_HEARTBEAT_REQUEST_PERIOD_S = 0.25
_MAV_CMD_REQUEST_MESSAGE = 512
_END_ACK_TIMEOUT_S = 1.0
_MAX_STAMPED_SAMPLES = 512
_MAX_MESSAGES_PER_DRAIN = 100_000
_MAX_DATAGRAM = 65535
_MAX_HEARTBEAT_DATAGRAM = 400  # a datagram from elsewhere larger than this is not parsed
_SIGNING_LINK_ID = 1  # any constant: the receiver's stream key also holds our system id
_SIGNATURE_REJECTIONS = ("unsigned", "bad_signature", "stale_signature")
# ArduPilot's console text on its MAVLink port (swarm.mavlink.parse): logged a line at a time,
# this many lines at most, each cut to this many characters.
_CONSOLE_LINES_LOGGED = 20
_CONSOLE_LINE_CHARS = 200
_AUTOPILOT_NAMES = {mavlink2.MAV_AUTOPILOT_PX4: "PX4",
                    mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot"}
_EXPECTED_AUTOPILOT = {"px4": mavlink2.MAV_AUTOPILOT_PX4,
                       "ardupilot": mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA}
# HEARTBEATs of these are not vehicles (ground stations, companions, payloads).
_NOT_VEHICLES = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                           mavlink2.MAV_TYPE_GIMBAL, mavlink2.MAV_TYPE_CAMERA,
                           mavlink2.MAV_TYPE_ADSB, mavlink2.MAV_TYPE_ANTENNA_TRACKER})
_IN_AIR_STATES = frozenset({mavlink2.MAV_LANDED_STATE_IN_AIR, mavlink2.MAV_LANDED_STATE_TAKEOFF,
                            mavlink2.MAV_LANDED_STATE_LANDING})
_LANDED_STATE_NAMES = {0: "undefined", 1: "on the ground", 2: "in the air", 3: "taking off",
                       4: "landing"}
_NOT_NOW = frozenset({mavlink2.MAV_RESULT_TEMPORARILY_REJECTED, mavlink2.MAV_RESULT_FAILED})
_SAID_KEPT = 12
_WARNING_LEVEL = 4  # PX4 events at this log level or more severe are quoted
# What the autopilot said this shortly before a refusal is quoted: PX4 reports the failing
# pre-arm checks when they change, not with every refusal.
_SAID_RECENT_S = 10.0


@dataclass(frozen=True)
class PositionSample:
    """One LOCAL_POSITION_NED report in W; ``received_s`` on the link's clock."""

    time_boot_ms: int
    position_w: Array
    velocity_w: Array
    received_s: float


def _result_name(result: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else "UNKNOWN"


def autopilot_mode_name(flavour: Flavour, mode: str) -> str:
    """``mode`` (pymavlink's name, as ``AutopilotLink.mode`` gives it) as the autopilot names it:
    PX4's "Hold" for AUTO.LOITER ("LOITER"), "Return", "Land", "Offboard", ...; ArduPilot's
    own names are pymavlink's (BRAKE, LAND, RTL, GUIDED)."""
    return _PX4_MODE_NAME.get(mode, mode) if flavour == "px4" else mode


def end_mode_name(flavour: Flavour, action: EndAction) -> str:
    """The mode the end action ``action`` asks for, as the autopilot names it."""
    return autopilot_mode_name(flavour, _MODE_NAME[(flavour, action)])


EndOutcome = Literal["accepted", "refused", "got no answer", "not sent"]
_END_OUTCOMES: Final[tuple[EndOutcome, ...]] = ("accepted", "refused", "got no answer",
                                                "not sent")
_END_LINE = re.compile(r"drone (\d+): end action (hold|land|rtl) \((.+?)\) "
                       r"(accepted|refused|got no answer|not sent)(?:: (.+))?")


@dataclass(frozen=True)
class EndReport:
    """What became of one drone's end action: the autopilot accepted the mode, refused it,
    did not answer, or it was not sent (``detail`` says why, and what the vehicle does then).
    The agent logs it as one line (``line``); the launcher reads it back (``parse``)."""

    drone: int
    action: EndAction
    mode: str  # as the autopilot names it (end_mode_name): BRAKE, Hold, Land, Return, ...
    outcome: EndOutcome
    detail: str = ""

    def __post_init__(self) -> None:
        if self.action not in END_ACTIONS or self.outcome not in _END_OUTCOMES:
            raise ValueError(f"not an end action and its outcome: {self.action!r}, "
                             f"{self.outcome!r}")

    @property
    def accepted(self) -> bool:
        return self.outcome == "accepted"

    def line(self) -> str:
        detail = f": {_one_line(self.detail)}" if self.detail else ""
        return (f"drone {self.drone}: end action {self.action} ({self.mode}) {self.outcome}"
                f"{detail}")

    @classmethod
    def parse(cls, line: str) -> EndReport | None:
        """The report ``line`` holds (as ``line()`` wrote it), or None."""
        match = _END_LINE.fullmatch(line.strip())
        if match is None:
            return None
        drone, action, mode, outcome, detail = match.groups()
        return cls(int(drone), action, mode, outcome, detail or "")  # type: ignore[arg-type]


def _is_vehicle_heartbeat(msg: Any) -> bool:
    return (msg.get_type() == "HEARTBEAT" and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID
            and msg.type not in _NOT_VEHICLES)


@dataclass
class _Stage:
    """One command of the handshake: what it is and how to tell it worked."""

    name: str
    command: int
    params: Callable[[], tuple[float, ...]]
    done: Callable[[], bool] | None  # the effect the autopilot shows (None: the ACK is it)
    pending: str  # what "done" waits for, in words
    hint: str  # what the operator can do when it fails
    skip_if_done: bool = True


class AutopilotLink:
    """MAVLink 2 link from one agent to its autopilot (docs/mavlink_link.md)."""

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
        bound: BoundSocket | None = None,
    ) -> None:
        if flavour not in ("px4", "ardupilot"):
            raise ValueError(f"flavour must be 'px4' or 'ardupilot', got {flavour!r}")
        if not 0 <= drone_id <= 253:
            raise ValueError(f"drone_id must be in 0..253, got {drone_id}")
        self._url = url
        self._drone_id = int(drone_id)
        self._me = f"drone {self._drone_id}"
        self._sysid = self._drone_id + 1
        self._flavour: Flavour = flavour
        self._origin = np.array(origin_w, dtype=np.float64).reshape(3).copy()
        self._origin_xyz = frames.as_xyz(self._origin, "origin_w")
        self._log_fn = log
        self._clock = clock
        self._source_system = self._sysid if source_system is None else int(source_system)

        if bound is not None and clock is not time.monotonic:
            raise ValueError(f"{self._me}: a bound socket's listening time is on "
                             "time.monotonic, not on this link's clock")
        self._conn: Any = open_connection(url, self._source_system, who=self._me, bound=bound)
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
        # The listening window (EXCLUSIVE_LISTEN_S) counts from when the socket was bound.
        self._opened_s = bound.bound_s if bound is not None else self._clock()

        self._heartbeat: Any = None
        self._mode_name: str | None = None  # mode_string_v10 of _heartbeat, computed once
        self._last_heartbeat_s: float | None = None
        self._landed_state: int | None = None
        self._vehicle_heard = False  # any valid frame from the autopilot (its address known)
        self._autopilot_frames = 0  # valid frames from the autopilot taken so far
        self._peer: tuple[str, int] | None = None  # udpin: the vehicle's pinned address
        self._second_autopilot: str | None = None  # another autopilot heard: never fly then
        self._commanded = False  # a command that moves or arms the vehicle went out
        self._end_report: EndReport | None = None
        self._foreign_parser = mavlink2.MAVLink(None)
        self._foreign_parser.robust_parsing = True
        self._last_heartbeat_request_s: float | None = None
        self._other_systems: set[int] = set()
        self._acks: dict[int, int] = {}
        self._said: deque[tuple[float, str]] = deque(maxlen=_SAID_KEPT)
        self._latest: PositionSample | None = None
        self._by_stamp: OrderedDict[int, PositionSample] = OrderedDict()
        self._samples_received = 0
        self._hold_position_w: Array | None = None  # keepalive holds this (PX4 after a climb)
        self._last_setpoint_sent_s: float | None = None
        self._last_companion_hb_s: float | None = None
        self.rejections: Counter[str] = Counter()
        self.foreign_frames = 0
        # ArduPilot's console text between frames: not MAVLink, not a rejected frame.
        self.console_text_bytes = 0
        self._console_in = bytearray()  # what parse_bytes found in the datagram at hand
        self._console_line = bytearray()  # the console line not yet logged
        self._console_lines_logged = 0

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
    def file_descriptor(self) -> int | None:
        """The descriptor the link reads from (a UDP or TCP socket), None if it has none."""
        fd = getattr(self._conn, "fd", None)
        return fd if isinstance(fd, int) else None

    @property
    def peer(self) -> tuple[str, int] | None:
        return self._peer

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
    def setpoint_mode(self) -> str:
        """The name of the mode the agent flies its vehicle in (GUIDED, OFFBOARD), as
        ``mode`` shows it."""
        return _MODE_NAME[(self._flavour, "guided" if self._flavour == "ardupilot"
                           else "offboard")]

    @property
    def custom_mode(self) -> int | None:
        return None if self._heartbeat is None else int(self._heartbeat.custom_mode)

    @property
    def autopilot(self) -> int | None:
        return None if self._heartbeat is None else int(self._heartbeat.autopilot)

    @property
    def landed_state(self) -> int | None:
        """MAV_LANDED_STATE of the newest EXTENDED_SYS_STATE (None before one)."""
        return self._landed_state

    @property
    def last_heartbeat_s(self) -> float | None:
        return self._last_heartbeat_s

    @property
    def rejected_frames(self) -> int:
        return sum(self.rejections.values())

    @property
    def signing(self) -> bool:
        return self._signing

    @property
    def autopilot_said(self) -> list[str]:
        """The autopilot's last few STATUSTEXTs / PX4 events, oldest first."""
        return [text for _, text in self._said]

    # ---------------------------------------------------------------- reading
    def poll(self) -> None:
        """Drain every datagram waiting now and update state (heartbeat, samples, ACKs)."""
        self._drain()

    def latest_position(self) -> PositionSample | None:
        self._drain()
        return self._latest

    def position_at(self, time_boot_ms: int) -> PositionSample | None:
        """The sample stamped ``time_boot_ms`` if it is among the last ones kept, else None
        (no wait: a realtime agent pairs a camera frame with the pose it was taken at). The
        link is read again only when the stamp is not yet there: the agent has just drained
        it for its newest sample, but the frame may have come after that sample."""
        stamp = int(time_boot_ms)
        sample = self._by_stamp.get(stamp)
        if sample is None:
            self._drain()
            sample = self._by_stamp.get(stamp)
        return sample

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
                    f"{self._me}: no LOCAL_POSITION_NED stamped {stamp} ms from "
                    f"system {self._sysid} on {self._url} within {timeout_s:g} s "
                    f"(newest seen: {newest})")
            self.wait_readable(min(remaining, 0.05))

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
                f"{self._me}: system {self._sysid} on {self._url} reports autopilot "
                f"{name} but flavour {self._flavour!r} is configured")

    # ---------------------------------------------------------------- sending
    def send_velocity(self, velocity_w: ArrayLike, time_boot_ms: int) -> None:
        """One velocity setpoint (W, m/s) stamped ``time_boot_ms`` (uint32). Values beyond
        the float32 range go out as ±inf, which a vehicle drops as non-finite. The link
        stops holding a position (``keepalive`` sends zero velocity from now on)."""
        stamp = _stamp(time_boot_ms)
        self._hold_position_w = None
        self._commanded = True
        self._send_setpoint(VELOCITY_ONLY_TYPE_MASK, _ZERO,
                            frames.link_float_xyz(*frames.enu_to_ned_xyz(
                                *frames.as_xyz(velocity_w, "velocity_w"))), stamp)

    def send_tracked(self, position_w: ArrayLike, velocity_w: ArrayLike,
                     acceleration_w: ArrayLike, time_boot_ms: int) -> None:
        """One setpoint along the command reference (``swarm.models.command_reference``): position,
        velocity and acceleration feed-forward in W, type mask ``TRACKED_TYPE_MASK`` of the
        flavour (ArduPilot: the acceleration is sent but marked ignored); like
        ``send_velocity`` otherwise (``keepalive`` then sends zero velocity)."""
        stamp = _stamp(time_boot_ms)
        self._hold_position_w = None
        self._commanded = True
        as_xyz, link_float, to_ned = frames.as_xyz, frames.link_float_xyz, frames.enu_to_ned_xyz
        self._send_setpoint(
            TRACKED_TYPE_MASK[self._flavour],
            link_float(*frames.local_ned_from_world_xyz(as_xyz(position_w, "position_w"),
                                                        self._origin_xyz)),
            link_float(*to_ned(*as_xyz(velocity_w, "velocity_w"))), stamp,
            link_float(*to_ned(*as_xyz(acceleration_w, "acceleration_w"))))

    def send_position(self, position_w: ArrayLike, time_boot_ms: int) -> None:
        """One position setpoint (W, m; the vehicle's local NED over the link)."""
        local = frames.link_float_xyz(*frames.local_ned_from_world_xyz(
            frames.as_xyz(position_w, "position_w"), self._origin_xyz))
        self._send_setpoint(POSITION_ONLY_TYPE_MASK, local, _ZERO, _stamp(time_boot_ms))

    def keepalive(self, now_s: float | None = None) -> None:
        """Drain, and send an idle setpoint (stamped IDLE_STAMP_MS) if none was sent in the
        last 0.1 s: zero velocity, or the position the handshake climbed to (PX4 from the
        ground) until the first velocity setpoint; ``now_s`` is on the link's clock."""
        self._drain()
        now = self._clock() if now_s is None else now_s
        if self._last_setpoint_sent_s is None \
                or now - self._last_setpoint_sent_s >= _KEEPALIVE_PERIOD_S:
            self._send_idle()

    # ---------------------------------------------------------------- handshake
    def handshake(
        self,
        timeout_s: float = 20.0,
        *,
        start_position_w: ArrayLike | None = None,
        retries: int = 5,
        ack_timeout_s: float = 1.0,
    ) -> None:
        """Bring the vehicle to "armed, in the setpoint mode, in the air"
        (docs/mavlink_link.md, Handshake).
        ``start_position_w``: where to climb to from the ground (W); None: the vehicle must
        already be in the air (LinkError if it is on the ground)."""
        if retries < 1:
            raise ValueError(f"retries must be >= 1, got {retries}")
        deadline = self._clock() + timeout_s
        me = self._me
        if self._signing:
            self._log(f"{me}: MAVLink 2 signing on: unsigned or wrongly signed frames from "
                      f"the vehicle are dropped")
        self._log(f"{me}: waiting for HEARTBEAT from system {self._sysid} on {self._url}")
        self.wait_heartbeat(max(0.0, deadline - self._clock()))
        self._log(f"{me}: HEARTBEAT from system {self._sysid} "
                  f"({_AUTOPILOT_NAMES[self._heartbeat.autopilot]}, mode {self.mode}, "
                  f"{'armed' if self.armed else 'disarmed'}"
                  + (f", at {self._peer[0]}:{self._peer[1]}" if self._peer else "") + ")")
        run = dict(deadline=deadline, retries=retries, ack_timeout_s=ack_timeout_s,
                   timeout_s=timeout_s)
        self._await_streams(deadline, timeout_s)
        self._await_exclusive(deadline)
        airborne = self._airborne()
        assert self._latest is not None
        height = float(self._latest.position_w[2] - self._origin[2])
        self._log(f"{me}: vehicle {'in the air' if airborne else 'on the ground'} "
                  f"({height:.2f} m above its local origin, "
                  f"{_LANDED_STATE_NAMES.get(self._landed_state or 0, 'landed state unknown')})")
        target = None if start_position_w is None \
            else np.array(start_position_w, dtype=np.float64).reshape(3)
        if not airborne and target is None:
            raise LinkError(f"{me}: vehicle on the ground and no start position to climb to "
                            f"on {self._url}: fly it up first")
        if self._flavour == "px4":
            self._handshake_px4(airborne, target, run)
        else:
            self._handshake_ardupilot(airborne, target, run)

    def _handshake_ardupilot(self, airborne: bool, target: Array | None,
                             run: dict[str, Any]) -> None:
        me = self._me
        self._command_stage(self._mode_stage("guided"), stream=airborne, **run)
        if airborne:
            if not self.armed:
                raise LinkError(f"{me}: vehicle reports being in the air but disarmed on "
                                f"{self._url}: check its EXTENDED_SYS_STATE")
            self._log(f"{me}: already in the air: no takeoff")
            self._log(f"{me}: ready (GUIDED, armed, airborne)")
            return
        assert target is not None
        self._command_stage(self._arm_stage(), stream=False, **run)
        altitude = float(target[2] - self._origin[2])
        if altitude < _AIRBORNE_GUESS_M:
            raise LinkError(f"{me}: start height {altitude:.2f} m above the vehicle's local "
                            f"origin is too low for a takeoff: check vehicles.origin_offsets_m")
        # Not a single setpoint until the climb is done: in GUIDED each one replaces the
        # takeoff target, and the vehicle stops climbing.
        self._command_stage(_Stage(
            f"TAKEOFF to {altitude:.2f} m", mavlink2.MAV_CMD_NAV_TAKEOFF,
            lambda: (0, 0, 0, math.nan, 0, 0, altitude), done=None, pending="",
            hint="the vehicle must be armed in GUIDED on the ground", skip_if_done=False),
            stream=False, **run)
        self._await_climb(target, run["deadline"], run["timeout_s"], stream=False)
        if self.mode != "GUIDED" or not self.armed:
            raise LinkError(f"{me}: vehicle is {self.mode}, "
                            f"{'armed' if self.armed else 'disarmed'} after takeoff on "
                            f"{self._url}: is something else commanding it?")
        self._log(f"{me}: ready (GUIDED, armed, airborne)")

    def _handshake_px4(self, airborne: bool, target: Array | None, run: dict[str, Any]) -> None:
        me = self._me
        if not airborne:
            assert target is not None
            self._hold_position_w = target  # the idle setpoint: climb to and hold the start
            self._log(f"{me}: streaming position setpoints at the start position "
                      f"({target[0]:.2f}, {target[1]:.2f}, {target[2]:.2f}) m")
        else:
            self._log(f"{me}: streaming zero setpoints for {_PRE_STREAM_S:g} s")
        self._pump(lambda: False, min(run["deadline"], self._clock() + _PRE_STREAM_S),
                   stream=True)
        self._command_stage(self._mode_stage("offboard"), stream=True, **run)
        self._command_stage(self._arm_stage(), stream=True, **run)
        if not airborne:
            assert target is not None
            self._await_climb(target, run["deadline"], run["timeout_s"], stream=True)
        if self.mode != "OFFBOARD":
            raise LinkError(f"{me}: vehicle left OFFBOARD (now {self.mode}) while arming "
                            f"on {self._url}: is something else commanding it?")
        self._log(f"{me}: ready (OFFBOARD, armed{'' if airborne else ', at the start'})")

    def _mode_stage(self, mode: str) -> _Stage:
        name = _MODE_NAME[(self._flavour, mode)]
        hint = ("it needs a position estimate (GPS/EKF)" if self._flavour == "ardupilot" else
                "it needs a setpoint stream (COM_OF_LOSS_T) and a position estimate")
        return _Stage(name, mavlink2.MAV_CMD_DO_SET_MODE, lambda: self._mode_params(mode),
                      done=lambda: self.mode == name, pending=f"heartbeat shows {name}",
                      hint=hint)

    def _arm_stage(self) -> _Stage:
        return _Stage("ARM", mavlink2.MAV_CMD_COMPONENT_ARM_DISARM,
                      lambda: (1, 0, 0, 0, 0, 0, 0), done=lambda: self.armed,
                      pending="heartbeat shows armed",
                      hint=("pre-arm checks fail: see what the autopilot says, or give it "
                            "more time (runtime.start_timeout_s)"))

    def _mode_params(self, mode: str) -> tuple[float, ...]:
        flags = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            flags |= mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        if self._flavour == "px4":
            main, sub = _PX4_MODE[mode]
            return (flags, main, sub, 0, 0, 0, 0)
        return (flags, _ACM_MODE[mode], 0, 0, 0, 0, 0)

    def _airborne(self) -> bool:
        if not self.armed:
            return False
        if self._landed_state is not None and self._landed_state != 0:
            return self._landed_state in _IN_AIR_STATES
        assert self._latest is not None
        return float(self._latest.position_w[2] - self._origin[2]) > _AIRBORNE_GUESS_M

    def _await_streams(self, deadline: float, timeout_s: float) -> None:
        """Request LOCAL_POSITION_NED (50 Hz) and EXTENDED_SYS_STATE (2 Hz) until a position
        sample arrives (up to the deadline) and, for up to 2 s more, a landed state."""
        me = self._me
        self._log(f"{me}: requesting LOCAL_POSITION_NED at 50 Hz and EXTENDED_SYS_STATE")
        started = self._clock()
        last_request = -math.inf
        last_progress = started

        def requested() -> bool:
            nonlocal last_request, last_progress
            now = self._clock()
            if now - last_request >= _STREAM_REQUEST_PERIOD_S:
                last_request = now
                self._send_interval(mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000)
                self._send_interval(mavlink2.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 500_000)
            if self._latest is not None:
                return True
            if now - last_progress >= _POSITION_PROGRESS_PERIOD_S:
                last_progress = now
                said = self._recent_said(now - _POSITION_PROGRESS_PERIOD_S)
                self._log(f"{me}: no position estimate yet after {now - started:.0f} s"
                          + (f" (autopilot says: {said})" if said else ""))
            return False

        if not self._pump(requested, deadline, stream=False):
            said = self._recent_said(-math.inf)
            raise LinkError(
                f"{me}: handshake did not complete within {timeout_s:g} s on {self._url}: "
                f"no LOCAL_POSITION_NED from the autopilot"
                + (f" (it says: {said})" if said else "")
                + ": its estimator has no position yet (GPS fix, EKF origin); give it more "
                  "time (runtime.start_timeout_s)")
        self._log(f"{me}: position stream up after {self._clock() - started:.1f} s")
        self._pump(lambda: self._landed_state is not None,
                   min(deadline, self._clock() + _LANDED_STATE_WAIT_S), stream=False)

    def _await_climb(self, target: Array, deadline: float, timeout_s: float, *,
                     stream: bool) -> None:
        """Until the vehicle is within CLIMB_TOLERANCE_M of ``target``'s height (and, PX4, of
        the point), in the air and nearly still; LinkError at the deadline."""
        me = self._me
        started = self._clock()
        self._log(f"{me}: climbing to z = {target[2]:.2f} m ({target[2] - self._origin[2]:.2f} m "
                  f"above the vehicle's local origin)")

        def arrived() -> bool:
            sample = self._latest
            if sample is None:
                return False
            error = sample.position_w - target
            if self._flavour == "ardupilot":
                error = error[2:]  # a takeoff climbs straight up from where it stands
            in_air = self._landed_state is None or self._landed_state == \
                mavlink2.MAV_LANDED_STATE_IN_AIR
            return (float(np.max(np.abs(error))) <= CLIMB_TOLERANCE_M and in_air
                    and float(np.linalg.norm(sample.velocity_w)) <= _CLIMB_SPEED_DONE_M_S)

        if not self._pump(arrived, deadline, stream=stream):
            now_z = "unknown" if self._latest is None \
                else f"{self._latest.position_w[2] - self._origin[2]:.2f} m"
            raise LinkError(
                f"{me}: handshake did not complete within {timeout_s:g} s on {self._url}: "
                f"the climb to {target[2] - self._origin[2]:.2f} m did not arrive (now at "
                f"{now_z}, mode {self.mode}, {'armed' if self.armed else 'disarmed'})")
        self._log(f"{me}: climb done after {self._clock() - started:.1f} s")

    # ---------------------------------------------------------------- end of mission
    def end_mission(self, action: EndAction) -> bool:
        """Zero velocity now, then the end action's mode (docs/mavlink_link.md); True when the
        autopilot confirmed it. What became of it is logged as one ``EndReport`` line and kept
        in ``end_report``. Never raises: this runs on every way out."""
        if action not in END_ACTIONS:
            raise ValueError(f"end action must be one of {END_ACTIONS}, got {action!r}")
        report = self._end(action)
        self._end_report = report
        self._log(report.line())
        return report.accepted

    @property
    def end_report(self) -> EndReport | None:
        """What became of the end action (None before ``end_mission``)."""
        return self._end_report

    def _end(self, action: EndAction) -> EndReport:
        name = end_mode_name(self._flavour, action)

        def report(outcome: EndOutcome, detail: str = "") -> EndReport:
            return EndReport(self._drone_id, action, name, outcome, detail)

        if self._closed:
            return report("not sent", "the link to the vehicle was already closed")
        if not self._commanded:  # never flown (or two autopilots heard first): leave it
            return report("not sent", "the agent never commanded the vehicle (it left before "
                                      "arming or moving it): the vehicle is as it was")
        try:
            self._hold_position_w = None
            self._send_idle()
            self._log(f"{self._me}: mission over: zero velocity sent; end action {action} "
                      f"({name})")
            for attempt in (1, 2):
                self._acks.pop(mavlink2.MAV_CMD_DO_SET_MODE, None)
                self._conn.mav.command_long_send(self._sysid, AUTOPILOT_COMPONENT_ID,
                                                 mavlink2.MAV_CMD_DO_SET_MODE, attempt - 1,
                                                 *self._mode_params(action))
                if self._pump(lambda: mavlink2.MAV_CMD_DO_SET_MODE in self._acks,
                              self._clock() + _END_ACK_TIMEOUT_S, stream=False, check=False):
                    result = self._acks.pop(mavlink2.MAV_CMD_DO_SET_MODE)
                    if result == mavlink2.MAV_RESULT_ACCEPTED:
                        return report("accepted")
                    return report("refused", f"result {result} {_result_name(result)}; the "
                                             f"vehicle keeps its own failsafe")
            return report("got no answer", f"none within {_END_ACK_TIMEOUT_S:g} s, twice; the "
                                           f"vehicle keeps its own setpoint-loss failsafe")
        except Exception as exc:  # a closed socket on the way out: say so, never raise
            return report("not sent", f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._conn.close()
            if self._console_line:
                self._log_console_line(bytes(self._console_line))
                self._console_line.clear()

    def __enter__(self) -> AutopilotLink:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # ================================================================ internals
    def _log(self, line: str) -> None:
        self._log_fn(line)

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
        address = udpin_address(self._url)
        port = None if address is None else address[1]
        if port is not None and port > 0:
            return (f"{text}: is the vehicle (sim-world --mavlink-base {port - self._drone_id}, "
                    f"or an autopilot) sending to port {port}?")
        return f"{text}: is the autopilot running and sending to this address?"

    def _recent_said(self, since_s: float) -> str:
        texts = [text for t, text in self._said if t >= since_s]
        return "; ".join(f"'{text}'" for text in dict.fromkeys(texts))

    def _await_exclusive(self, deadline: float) -> None:
        """Listen until EXCLUSIVE_LISTEN_S after the link opened (a second autopilot on the
        port is heard by then and raises), before the first command that moves the vehicle."""
        until = self._opened_s + EXCLUSIVE_LISTEN_S
        if self._clock() < until:
            self._pump(lambda: False, min(until, deadline), stream=False)

    def _command_stage(self, stage: _Stage, *, stream: bool, deadline: float, retries: int,
                       ack_timeout_s: float, timeout_s: float) -> None:
        me = self._me
        if stage.skip_if_done and stage.done is not None and stage.done():
            self._log(f"{me}: {stage.name} already in effect")
            return
        self._await_exclusive(deadline)
        last = "not attempted"
        counted = 0  # attempts that count against ``retries`` (no ACK, DENIED)
        reasons_logged: set[str] = set()
        attempt = 0
        while self._clock() < deadline:
            attempt += 1
            self._acks.pop(stage.command, None)
            self._commanded = True
            sent_s = self._clock()
            self._conn.mav.command_long_send(self._sysid, AUTOPILOT_COMPONENT_ID, stage.command,
                                             min(attempt - 1, 255), *stage.params())
            last, result = self._await_result(stage, stream, deadline, ack_timeout_s)
            if last == "accepted":
                self._log(f"{me}: {stage.name} accepted")
                return
            said = self._recent_said(sent_s - _SAID_RECENT_S)
            if said:
                last = f"{last}; autopilot says: {said}"
            if result == mavlink2.MAV_RESULT_UNSUPPORTED:
                raise LinkError(f"{me}: {stage.name} refused on {self._url}: {last}: "
                                f"{stage.hint}")
            if result in _NOT_NOW:
                if last not in reasons_logged:
                    reasons_logged.add(last)
                    self._log(f"{me}: {stage.name} {last}; asking again every "
                              f"{_REFUSED_RETRY_PAUSE_S:g} s")
                pause = _REFUSED_RETRY_PAUSE_S
            else:
                counted += 1
                if counted >= retries:
                    raise LinkError(f"{me}: {stage.name} failed after {counted} attempts on "
                                    f"{self._url}: {last}: {stage.hint}")
                self._log(f"{me}: {stage.name} {last}, retry {counted + 1}/{retries}")
                pause = _RETRY_PAUSE_S
            self._pump(lambda: False, min(deadline, self._clock() + pause), stream=stream)
        raise LinkError(f"{me}: handshake did not complete within {timeout_s:g} s on "
                        f"{self._url}: {stage.name} {last}: {stage.hint}")

    def _await_result(self, stage: _Stage, stream: bool, deadline: float,
                      ack_timeout_s: float) -> tuple[str, int | None]:
        command = stage.command
        ack_deadline = min(deadline, self._clock() + ack_timeout_s)
        while True:
            if not self._pump(lambda: command in self._acks, ack_deadline, stream=stream):
                return f"got no ACK within {ack_timeout_s:g} s", None
            result = self._acks.pop(command)
            if result == mavlink2.MAV_RESULT_IN_PROGRESS:
                ack_deadline = min(deadline, self._clock() + ack_timeout_s)
                continue
            if result != mavlink2.MAV_RESULT_ACCEPTED:
                return f"denied (result {result} {_result_name(result)})", result
            if stage.done is None or self._pump(
                    stage.done, min(deadline, self._clock() + _CONFIRM_TIMEOUT_S), stream=stream):
                return "accepted", result
            return (f"accepted but not confirmed ({stage.pending}) within "
                    f"{_CONFIRM_TIMEOUT_S:g} s"), None

    def _pump(self, until: Callable[[], bool], deadline: float, *, stream: bool,
              check: bool = True) -> bool:
        """Drain (and stream idle setpoints) until ``until()`` or the deadline. ``check``:
        raise LinkError once a second autopilot has been heard."""
        while True:
            self._drain()
            if check:
                self._check_exclusive()
            if until():
                return True
            now = self._clock()
            if now >= deadline:
                return False
            wait = deadline - now
            if stream:
                if self._last_setpoint_sent_s is None \
                        or now - self._last_setpoint_sent_s >= _SETPOINT_PERIOD_S:
                    self._send_idle()
                wait = min(wait, _SETPOINT_PERIOD_S)
            self.wait_readable(min(wait, 0.05))

    def _check_exclusive(self) -> None:
        if self._second_autopilot is not None:
            raise LinkError(self._second_autopilot)

    def _send_interval(self, message_id: int, interval_us: int) -> None:
        self._conn.mav.command_long_send(self._sysid, AUTOPILOT_COMPONENT_ID,
                                         mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, message_id,
                                         interval_us, 0, 0, 0, 0, 0)

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

    def _send_idle(self) -> None:
        if self._hold_position_w is not None:
            self.send_position(self._hold_position_w, IDLE_STAMP_MS)
        else:
            self._send_setpoint(VELOCITY_ONLY_TYPE_MASK, _ZERO, _ZERO, IDLE_STAMP_MS)

    def _send_setpoint(self, type_mask: int, position_ned: frames.Xyz,
                       velocity_ned: frames.Xyz, stamp: int,
                       acceleration_ned: frames.Xyz = _ZERO) -> None:
        """Values already as the link carries them (``frames.link_float_xyz``)."""
        if self._second_autopilot is not None and not self._commanded:
            return  # which vehicle is ours was in doubt before we flew one: command none
        x, y, z = position_ned
        vn, ve, vd = velocity_ned
        an, ae, ad = acceleration_ned
        mav = self._conn.mav
        # Fields in wire order (SET_POSITION_TARGET_LOCAL_NED.fields); pymavlink's own send
        # when the fast path does not apply (signing, a send callback).
        frame = SET_POSITION_TARGET_LOCAL_NED.pack(
            mav, stamp, x, y, z, vn, ve, vd, an, ae, ad, 0.0, 0.0,
            type_mask, self._sysid, AUTOPILOT_COMPONENT_ID, mavlink2.MAV_FRAME_LOCAL_NED)
        if frame is not None:
            mav.file.write(frame)
        else:
            mav.set_position_target_local_ned_send(
                stamp, self._sysid, AUTOPILOT_COMPONENT_ID, mavlink2.MAV_FRAME_LOCAL_NED,
                type_mask, x, y, z, vn, ve, vd, an, ae, ad, 0.0, 0.0)
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

    def wait_readable(self, timeout_s: float) -> None:
        """Block until the link has something to read or ``timeout_s`` has passed (what a
        caller that drives the link with ``poll`` does between two polls)."""
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
            kind = msg.get_type()
            if kind.startswith("UNKNOWN") and int(kind[len("UNKNOWN_"):]) \
                    in px4_events.UNDECODED_MESSAGES:
                self._handle(msg, None)
            elif kind.startswith("UNKNOWN"):
                self.rejections["unknown_message"] += 1
            else:
                self._handle(msg, None)

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
            self._datagram(data, None)

    def _drain_udpin(self) -> None:
        """``udpin``: pymavlink would send to every address that ever sent a datagram here
        (for 5 s), so one forged datagram would get a copy of every setpoint. Instead the
        vehicle's address is pinned at its first valid frame (the only address sent to) for
        good; a datagram from anywhere else is counted as ``foreign_address`` and dropped —
        read only far enough to notice a second autopilot (docs/mavlink_link.md)."""
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
                self._look_for_autopilot(data, sender)
                continue
            if not data:
                self.rejections["empty_datagram"] += 1
                continue
            taken = self._autopilot_frames
            self._datagram(data, sender)
            if peer is None and self._autopilot_frames > taken:
                self._pin(sender)

    def _look_for_autopilot(self, data: bytes, sender: tuple[str, int]) -> None:
        """A datagram from another address: a second autopilot if it is clean (every byte a
        valid frame) and holds a vehicle's HEARTBEAT. Cheap for junk: only small datagrams
        that start like MAVLink 2 with message id 0 somewhere are parsed."""
        if (self._second_autopilot is not None or len(data) > _MAX_HEARTBEAT_DATAGRAM
                or not data.startswith(b"\xfd") or b"\x00\x00\x00" not in data[7:]):
            return
        scratch: Counter[str] = Counter()
        messages = parse_bytes(self._foreign_parser, data, scratch, datagram=True)
        if scratch:
            return  # junk or a corrupted frame inside: not an autopilot talking
        for msg in messages:
            if _is_vehicle_heartbeat(msg):
                self._note_second_autopilot(msg, sender)
                return

    def _note_second_autopilot(self, msg: Any, sender: tuple[str, int] | None) -> None:
        if self._second_autopilot is not None:
            return
        name = _AUTOPILOT_NAMES.get(msg.autopilot, f"autopilot type {msg.autopilot}")
        other = (f"system {msg.get_srcSystem()} ({name})"
                 + (f" at {sender[0]}:{sender[1]}" if sender is not None else ""))
        if self._heartbeat is None:
            self._second_autopilot = (
                f"{self._me}: autopilot {other} on {self._url} is not ours (system "
                f"{self._sysid}): refusing to fly it; check --id and the port")
        else:
            ours = f"system {self._sysid}" + (f" at {self._peer[0]}:{self._peer[1]}"
                                              if self._peer is not None else "")
            self._second_autopilot = (
                f"{self._me}: a second autopilot on {self._url}: {other} besides ours, "
                f"{ours}: refusing to fly either; give each autopilot its own port (is "
                f"another SITL or swarm sending here?)")
        self._log(self._second_autopilot)

    def _pin(self, sender: tuple[str, int]) -> None:
        """Send to ``sender`` (and nobody else) from now on."""
        self._peer = sender
        self._conn.clients = {sender}
        self._conn.clients_last_alive = {sender: time.time()}

    def _datagram(self, data: bytes, sender: tuple[str, int] | None) -> None:
        """Everything in one datagram (from the pinned vehicle, or the first one heard)."""
        fast = None if self._signing else LOCAL_POSITION_NED.unpack(data)  # unsigned only
        if fast is not None and fast[0] == self._sysid and fast[1] == AUTOPILOT_COMPONENT_ID:
            self._vehicle_heard = True
            self._on_local_position(*fast[2])  # the 50 Hz sample: no message object
            return
        before = self.rejected_frames
        messages = parse_bytes(self._conn.mav, data, self.rejections, datagram=True,
                               known_undecoded=px4_events.UNDECODED_MESSAGES,
                               console=self._console_in if self._flavour == "ardupilot"
                               else None)
        clean = self.rejected_frames == before  # console text is not a rejection
        if self._console_in:
            self._on_console_text(bytes(self._console_in))
            self._console_in.clear()
        for msg in messages:
            self._handle(msg, sender if clean else False)

    def _handle(self, msg: Any, sender: tuple[str, int] | Literal[False] | None) -> None:
        """``sender``: where a clean datagram came from (None: a stream link), False: the
        datagram was not clean (it cannot reveal a second autopilot)."""
        try:
            if not msg.get_type().startswith("UNKNOWN"):
                self._conn.post_message(msg)  # pymavlink's own bookkeeping (messages, params)
            self._process(msg, sender)
        except Exception as exc:  # malformed field values must never escape
            self.rejections[f"handler_error:{type(exc).__name__}"] += 1

    def _process(self, msg: Any, sender: tuple[str, int] | Literal[False] | None) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":  # from a stream link (parse_bytes takes a datagram's)
            text = console_text(msg) if self._flavour == "ardupilot" else None
            if text is not None:
                self._on_console_text(text)
            else:
                self.rejections["bad_data"] += 1  # junk, bad CRC, bad length
            return
        system, component = px4_events.message_source(msg)  # UNKNOWN_<id>: from its header
        if system != self._sysid:
            self.foreign_frames += 1
            if kind == "HEARTBEAT" and msg.type not in _NOT_VEHICLES:
                self._other_systems.add(system)
                if sender is not False and _is_vehicle_heartbeat(msg):
                    self._note_second_autopilot(msg, sender if sender else None)
            return
        if component != AUTOPILOT_COMPONENT_ID:
            self.foreign_frames += 1
            return
        if kind.startswith("UNKNOWN"):  # one of px4_events.UNDECODED_MESSAGES
            event = px4_events.event_from_message(msg)
            if event is None:
                if int(kind[len("UNKNOWN_"):]) == px4_events.EVENT_MSG_ID:
                    self.rejections["bad_data"] += 1  # an EVENT with a wrong checksum
                return  # known, carries nothing the agent needs (CURRENT_MODE, ...)
            if px4_events.log_level_number(event.log_level_external) <= _WARNING_LEVEL:
                self._said.append((self._clock(), px4_events.describe(event)))
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
        elif kind == "EXTENDED_SYS_STATE":
            self._landed_state = int(msg.landed_state)
        elif kind == "STATUSTEXT" and msg.severity <= mavlink2.MAV_SEVERITY_WARNING:
            self._said.append((self._clock(), _one_line(msg.text)))

    def _on_console_text(self, text: bytes) -> None:
        """Count ArduPilot's console text and log it a whole line at a time."""
        self.console_text_bytes += len(text)
        self._console_line += text
        *lines, rest = self._console_line.split(b"\n")
        if len(rest) > _CONSOLE_LINE_CHARS:  # no newline coming: log what there is
            lines.append(rest)
            rest = bytearray()
        self._console_line = bytearray(rest)
        for line in lines:
            self._log_console_line(bytes(line))

    def _log_console_line(self, line: bytes) -> None:
        text = _one_line(line.decode("ascii"))[:_CONSOLE_LINE_CHARS]
        if not text or self._console_lines_logged > _CONSOLE_LINES_LOGGED:
            return
        self._console_lines_logged += 1
        if self._console_lines_logged > _CONSOLE_LINES_LOGGED:
            self._log(f"{self._me}: more autopilot console text, not logged (counted in "
                      f"console_text_bytes)")
            return
        self._log(f"{self._me}: autopilot console (text on its MAVLink port, not MAVLink; "
                  f"not a rejected frame): {text}")

    def _on_local_position(self, time_boot_ms: int, x: float, y: float, z: float,
                           vx: float, vy: float, vz: float) -> None:
        if not all(map(math.isfinite, (x, y, z, vx, vy, vz))):
            self.rejections["nonfinite_position"] += 1
            return
        self._autopilot_frames += 1
        sample = PositionSample(int(time_boot_ms), np.array(frames.world_from_local_ned_xyz(
            (x, y, z), self._origin_xyz), dtype=np.float64),
            np.array(frames.ned_to_enu_xyz(vx, vy, vz), dtype=np.float64), self._clock())
        self._latest = sample
        self._samples_received += 1
        self._by_stamp[sample.time_boot_ms] = sample
        self._by_stamp.move_to_end(sample.time_boot_ms)
        while len(self._by_stamp) > _MAX_STAMPED_SAMPLES:
            self._by_stamp.popitem(last=False)


def _stamp(time_boot_ms: int) -> int:
    stamp = int(time_boot_ms)
    if not 0 <= stamp <= 0xFFFFFFFF:
        raise ValueError(f"time_boot_ms must fit in uint32, got {time_boot_ms}")
    return stamp


