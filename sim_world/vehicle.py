"""One emulated MAVLink 2 vehicle (PX4 or ArduCopter flavour) as a pure protocol state machine.

SPEC §12. No sockets and no clock of its own: every call that depends on time takes it
(``now_s``, seconds on any monotonic clock the caller chooses — sim time in lockstep, wall
time in realtime; it should not go backwards — a jump back only restarts the telemetry
schedule — so in lockstep keep one clock per vehicle that also advances before the mission
starts, e.g. wall time until then and that instant plus sim time after). Bytes in, bytes
out, so the same
object is driven by ``sim-world`` in both time modes and by tests without any network.
Encoding and parsing use pymavlink's generated MAVLink 2 module
(``pymavlink.dialects.v20.ardupilotmega``); the per-step LOCAL_POSITION_NED out and velocity
setpoints in go through ``swarm.mavlink_parse.FastFrame`` (pymavlink's formats and checksum,
byte-identical frames, without its per-byte parser). Not thread-safe.

Vehicle ``drone_id`` is MAVLink system ``drone_id + 1``, component 1 (MAV_COMP_ID_AUTOPILOT1).

Public API
----------
``Flavour = Literal["px4", "ardupilot"]``; ``VehicleEndpoint`` (the UDP socket, defined in
``sim_world.mavlink_endpoint``) is re-exported here.

``EmulatedVehicle(drone_id, flavour, position_w, origin_w, *, u_max_m_s=3.0,
setpoint_timeout_s=None, takeoff_required=None, datagram_framing=True, signing_key=None,
signing_clock=time.time)``
    ``setpoint_timeout_s``: setpoint-loss failsafe delay, default 0.5 s for px4
    (``COM_OF_LOSS_T``) and 3.0 s for ardupilot (``GUID_TIMEOUT``); also readable and
    settable over MAVLink as that parameter. ``takeoff_required``: whether setpoints need a
    prior ``MAV_CMD_NAV_TAKEOFF``; default True for ardupilot, False for px4. The world spawns
    vehicles at altitude, so a takeoff is accepted at once and does not move the vehicle.
    ``datagram_framing``: each ``receive()`` call is one UDP datagram, so bytes of an
    incomplete packet left at its end are counted as a truncated frame and dropped (they can
    never complete a packet); with False the input is a byte stream (serial/TCP) and a packet
    may span calls.
    ``signing_key``: the 32-byte MAVLink 2 signing secret (``swarm.mavlink_signing``; None:
    off). With it, every frame the vehicle sends is signed (pymavlink's ``sign_packet``,
    link id 0) and only correctly signed frames are accepted (pymavlink's
    ``check_signature``: right key, signing timestamp newer than the last of that stream);
    the rest are dropped unanswered and counted in ``rejections`` as ``unsigned``,
    ``bad_signature`` or ``stale_signature`` (a replay). ``signing_clock``: seconds since
    the Unix epoch, read only for the signing timestamp, which MAVLink keeps on the wall
    clock whatever ``now_s`` is (refreshed by ``heartbeat()``). Both setpoint fast paths
    are off while signing.

``receive(data, now_s) -> list[bytes]``
    Parse any bytes (garbage, truncated, several packets), apply what they command and return
    the reply packets (COMMAND_ACK, PARAM_VALUE, AUTOPILOT_VERSION, ...; plus an immediate
    HEARTBEAT after a change of mode or arming). Never raises on bad input: each dropped frame
    (and an empty datagram) is counted in ``rejected_frames`` (reasons in ``rejections``);
    each frame a handler took (not rejected, not ignored) is counted in ``accepted_frames``
    (``sim_world.fleet`` follows a new sender only when this grows: neither junk nor a stray
    valid frame the vehicle has no use for, e.g. a GCS heartbeat, redirects its stream).
``commanded_velocity_w(now_s) -> ndarray``
    Velocity the vehicle applies now, in W: ``clamp_velocity(frames.velocity_over_link(u),
    u_max)`` of the last accepted setpoint ``u`` (bit-exact), or zero when disarmed, outside
    the setpoint mode (px4 OFFBOARD, ardupilot GUIDED), on the ground (ardupilot before
    takeoff), before any setpoint, or in failsafe.
``begin_step(time_boot_ms)`` / ``setpoint_stamped(time_boot_ms=None) -> ndarray | None``
    Lockstep: ``begin_step`` forgets earlier stamped setpoints and records the awaited stamp
    (``awaited_stamp``); ``setpoint_stamped`` returns the applied velocity
    (``commanded_velocity_w`` evaluated when it arrived) of the setpoint whose
    ``time_boot_ms`` equals the stamp (default: the awaited one) and that arrived since
    ``begin_step``, else None. A setpoint the vehicle may not apply (disarmed, wrong mode,
    failsafe) still arrives, with velocity zero.
``integrate(dt_s, velocity_w)``
    ``position_w += dt_s * velocity_w`` (float64); ``velocity_w`` is also what
    LOCAL_POSITION_NED reports as the vehicle's velocity.
``heartbeat() -> bytes``
    One HEARTBEAT now; the caller sends one per second (SPEC: 1 Hz). telemetry() adds
    HEARTBEATs only if a client sets an interval for them.
``telemetry(time_boot_ms, now_s) -> list[bytes]``
    The streams that are due: LOCAL_POSITION_NED (px4: on every call by default; ardupilot:
    only once requested), ATTITUDE (px4 10 Hz, ardupilot 1 Hz), SYS_STATUS and
    EXTENDED_SYS_STATE (1 Hz).
    Rates follow MAV_CMD_SET_MESSAGE_INTERVAL (interval -1 disables, 0 restores the default —
    "every call" for LOCAL_POSITION_NED in both flavours —, > 0 sets the period; a period no
    longer than the call period means every call) and, ardupilot only, REQUEST_DATA_STREAM
    for messages without an explicit interval.
Read-only state: ``drone_id``, ``system_id``, ``flavour``, ``position_w`` (float64 truth,
a copy), ``origin_w``, ``velocity_w`` (last integrated), ``armed``, ``mode`` (pymavlink's
name of the current mode, e.g. "OFFBOARD", "LOITER", "POSCTL", "GUIDED", "BRAKE"),
``custom_mode``, ``in_setpoint_mode``, ``airborne``, ``failsafe_active``,
``accepting_setpoints``, ``awaited_stamp``,
``setpoints_streaming(now_s)``, ``setpoint_timeout_s``, ``u_max_m_s``; counters
``rejected_frames``, ``rejections`` (reason → count), ``accepted_setpoints``,
``ignored_setpoints``, ``nonfinite_setpoints``, ``failsafe_events``, ``ignored_messages``;
``signing`` (bool) and ``authenticated_frames`` (frames accepted with a good signature: the
caller follows a new peer address only when this grows, see ``sim_world.fleet``).

Behaviour (SPEC §12, PX4 / ArduCopter conventions)
--------------------------------------------------
* Initial state: disarmed, px4 in AUTO.LOITER ("LOITER", PX4's Hold), ardupilot in
  STABILIZE (ArduCopter's boot mode), at ``position_w`` (already at altitude).
* HEARTBEAT: MAV_TYPE_QUADROTOR, autopilot MAV_AUTOPILOT_PX4 / MAV_AUTOPILOT_ARDUPILOTMEGA,
  base_mode = CUSTOM_MODE_ENABLED | SAFETY_ARMED when armed, custom_mode = current mode
  (px4: main mode in bits 16-23, sub mode in bits 24-31: POSCTL 3, OFFBOARD 6, AUTO 4 /
  LOITER 3 = hold; ArduCopter: the mode number, GUIDED 4, LOITER 5, BRAKE 17, ...).
* Setpoints: SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_LOCAL_NED, position and acceleration
  ignored, velocity used, no force bit: type_mask 0x0DC7 (also 0x01C7, 0x05C7, 0x09C7 — the
  yaw / yaw-rate bits are free since attitude is not modelled; MAVSDK sends 0x09C7). Any
  other frame or mask is rejected, and so is a setpoint with a non-finite velocity (counted
  as ``nonfinite_setpoint``: never applied, never a proof of life). target_system must be
  this vehicle or 0, target_component 1 or 0. px4 stores every valid setpoint (they are the
  offboard "proof of life") and applies it while armed in OFFBOARD; ardupilot ignores
  (counts in ``ignored_setpoints``) setpoints unless GUIDED, armed and airborne.
* px4: DO_SET_MODE/SET_MODE to OFFBOARD is TEMPORARILY_REJECTED unless setpoints are
  streaming (≥ 2 received in the last 0.5 s). No setpoint for ``setpoint_timeout_s`` while in
  OFFBOARD → failsafe: mode becomes AUTO.LOITER (hold) and is reported so; leaving it takes a
  new mode command.
* ardupilot: no accepted setpoint for ``setpoint_timeout_s`` in GUIDED → failsafe: stop and
  hold, mode stays GUIDED; the next accepted setpoint resumes. Takeoff needs GUIDED and armed
  (else FAILED); disarming lands (a new takeoff is needed). px4: NAV_TAKEOFF while armed is
  accepted and, as PX4 does after AUTO.TAKEOFF, ends in AUTO.LOITER (TEMPORARILY_REJECTED
  while disarmed).
* Commands (COMMAND_LONG or COMMAND_INT): ARM_DISARM (400), DO_SET_MODE (176; param1 must
  have CUSTOM_MODE_ENABLED), NAV_TAKEOFF (22), SET/GET_MESSAGE_INTERVAL (511/510),
  REQUEST_MESSAGE (512: AUTOPILOT_VERSION, HEARTBEAT, LOCAL_POSITION_NED, ATTITUDE,
  SYS_STATUS, EXTENDED_SYS_STATE), REQUEST_AUTOPILOT_CAPABILITIES (520); anything else gets
  MAV_RESULT_UNSUPPORTED. The legacy SET_MODE message is acknowledged with command = 11.
  Unknown modes are DENIED.
* Also: PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET for the timeout parameter
  (REAL32), MISSION_REQUEST_LIST → MISSION_COUNT 0, TIMESYNC answered (tc1 = now in ns).
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sim_world.kinematics import clamp_velocity
from sim_world.mavlink_endpoint import VehicleEndpoint
from swarm import frames
from swarm.mavlink_parse import LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED, parse_bytes
from swarm.mavlink_signing import enable_signing, refresh_signing_timestamp

Array = NDArray[np.float64]
Flavour = Literal["px4", "ardupilot"]

__all__ = ["AUTOPILOT_COMPONENT_ID", "EmulatedVehicle", "Flavour", "VehicleEndpoint"]

AUTOPILOT_COMPONENT_ID = 1
_SIGNING_LINK_ID = 0  # the autopilot's MAVLink channel 0

# --- modes -----------------------------------------------------------------------------------
# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h).
_PX4_MAIN_POSCTL, _PX4_MAIN_AUTO, _PX4_MAIN_OFFBOARD = 3, 4, 6
_PX4_SUB_AUTO_LOITER = 3


def _px4_custom_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


_PX4_MODES: dict[str, int] = {
    "POSCTL": _px4_custom_mode(_PX4_MAIN_POSCTL),
    "OFFBOARD": _px4_custom_mode(_PX4_MAIN_OFFBOARD),
    "LOITER": _px4_custom_mode(_PX4_MAIN_AUTO, _PX4_SUB_AUTO_LOITER),  # "Hold"
}
# ArduCopter mode numbers (the subset that makes sense for an airborne velocity-driven copter).
_ACM_MODES: dict[str, int] = {
    "STABILIZE": 0, "ALT_HOLD": 2, "GUIDED": 4, "LOITER": 5, "POSHOLD": 16, "BRAKE": 17,
}
_SETPOINT_MODE = {"px4": "OFFBOARD", "ardupilot": "GUIDED"}
_INITIAL_MODE = {"px4": "LOITER", "ardupilot": "STABILIZE"}
_TIMEOUT_PARAM = {"px4": "COM_OF_LOSS_T", "ardupilot": "GUID_TIMEOUT"}
_DEFAULT_TIMEOUT_S = {"px4": 0.5, "ardupilot": 3.0}

# --- setpoints -------------------------------------------------------------------------------
_IGNORE_POSITION = 0x007  # bits 0-2: x, y, z
_IGNORE_VELOCITY = 0x038  # bits 3-5: vx, vy, vz
_IGNORE_ACCEL = 0x1C0  # bits 6-8: afx, afy, afz
_FORCE_SET = 0x200  # bit 9: afx..afz are forces
_IGNORE_YAW_BITS = 0xC00  # bits 10-11: yaw, yaw rate
VELOCITY_ONLY_TYPE_MASK = _IGNORE_POSITION | _IGNORE_ACCEL | _IGNORE_YAW_BITS  # 0x0DC7

STREAM_WINDOW_S = 0.5  # px4: "streaming" = at least STREAM_MIN_COUNT setpoints in this window
STREAM_MIN_COUNT = 2

# --- telemetry streams ------------------------------------------------------------------------
_MSG = mavlink2
_STREAM_IDS = {
    _MSG.MAVLINK_MSG_ID_HEARTBEAT: "HEARTBEAT",
    _MSG.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
    _MSG.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    _MSG.MAVLINK_MSG_ID_SYS_STATUS: "SYS_STATUS",
    _MSG.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "EXTENDED_SYS_STATE",
}
EVERY_CALL = 0.0  # stream interval meaning "on every telemetry() call"
# Default interval per stream and flavour (None = not streamed).
_DEFAULT_INTERVAL_S: dict[str, dict[str, float | None]] = {
    # HEARTBEAT is the caller's job (heartbeat() at 1 Hz) unless an interval is requested.
    "px4": {"HEARTBEAT": None, "LOCAL_POSITION_NED": EVERY_CALL, "ATTITUDE": 0.1,
            "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0},
    "ardupilot": {"HEARTBEAT": None, "LOCAL_POSITION_NED": None, "ATTITUDE": 1.0,
                  "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0},
}
# Interval that "0 = default rate" restores (LOCAL_POSITION_NED is then on in both flavours).
_RESTORED_INTERVAL_S = {"HEARTBEAT": 1.0, "LOCAL_POSITION_NED": EVERY_CALL, "ATTITUDE": 0.1,
                        "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0}
# ArduPilot REQUEST_DATA_STREAM groups we emulate.
_DATA_STREAMS = {
    _MSG.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "EXTENDED_SYS_STATE"),
    _MSG.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED",),
    _MSG.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
}
_DATA_STREAMS[_MSG.MAV_DATA_STREAM_ALL] = tuple(
    name for names in list(_DATA_STREAMS.values()) for name in names)
# A periodic stream is due this early (absorbs float round-off and call jitter without
# shortening the period noticeably).
_DUE_TOLERANCE_S = 0.005

_SENSORS = (_MSG.MAV_SYS_STATUS_SENSOR_3D_GYRO | _MSG.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | _MSG.MAV_SYS_STATUS_SENSOR_3D_MAG | _MSG.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | _MSG.MAV_SYS_STATUS_SENSOR_GPS | _MSG.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
_MAX_STAMPED = 256


@dataclass
class _Stream:
    interval_s: float | None  # None: off; EVERY_CALL: every call; > 0: period
    explicit: bool = False  # set by SET_MESSAGE_INTERVAL (wins over REQUEST_DATA_STREAM)
    next_due_s: float | None = None
    last_sent_s: float | None = None


class _Collector:
    """File-like sink for pymavlink's MAVLink.send(): keeps the packed packets."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, buf: bytes | bytearray) -> None:
        self.packets.append(bytes(buf))


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class EmulatedVehicle:
    """MAVLink 2 protocol state machine of one PX4- or ArduCopter-like copter (see module doc)."""

    def __init__(
        self,
        drone_id: int,
        flavour: Flavour,
        position_w: ArrayLike,
        origin_w: ArrayLike,
        *,
        u_max_m_s: float = 3.0,
        setpoint_timeout_s: float | None = None,
        takeoff_required: bool | None = None,
        datagram_framing: bool = True,
        signing_key: bytes | None = None,
        signing_clock: Callable[[], float] = time.time,
    ) -> None:
        if flavour not in ("px4", "ardupilot"):
            raise ValueError(f"flavour must be 'px4' or 'ardupilot', got {flavour!r}")
        if not 0 <= drone_id <= 253:
            raise ValueError(f"drone_id must be in 0..253 (system id = drone_id + 1), "
                             f"got {drone_id}")
        if not (math.isfinite(u_max_m_s) and u_max_m_s > 0):
            raise ValueError(f"u_max_m_s must be finite and > 0, got {u_max_m_s}")
        timeout = _DEFAULT_TIMEOUT_S[flavour] if setpoint_timeout_s is None \
            else float(setpoint_timeout_s)
        if not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f"setpoint_timeout_s must be finite and > 0, got {timeout}")
        self._drone_id = int(drone_id)
        self._sysid = self._drone_id + 1
        self._flavour: Flavour = flavour
        self._position = np.array(position_w, dtype=np.float64).reshape(3).copy()
        self._origin = np.array(origin_w, dtype=np.float64).reshape(3).copy()
        self._velocity = np.zeros(3)
        self._u_max = float(u_max_m_s)
        self._timeout_s = timeout
        self._takeoff_required = (flavour == "ardupilot") if takeoff_required is None \
            else bool(takeoff_required)
        self._datagram_framing = bool(datagram_framing)

        self._modes = _PX4_MODES if flavour == "px4" else _ACM_MODES
        self._mode = _INITIAL_MODE[flavour]
        self._armed = False
        self._landed = self._takeoff_required  # ardupilot: "on the ground" until takeoff
        self._failsafe = False

        self._setpoint_ned: Array | None = None  # as decoded (float32 values), NED
        self._last_setpoint_s: float | None = None  # last accepted (applied-kind) setpoint
        self._arrivals: deque[float] = deque(maxlen=16)  # arrival times of valid setpoints
        self._stamped: dict[int, Array] = {}
        self._awaited_stamp: int | None = None
        self._last_time_boot_ms = 0

        self._streams = {name: _Stream(_DEFAULT_INTERVAL_S[flavour][name])
                         for name in _STREAM_IDS.values()}

        self._rx = mavlink2.MAVLink(None, srcSystem=self._sysid,
                                    srcComponent=AUTOPILOT_COMPONENT_ID)
        self._rx.robust_parsing = True
        self._out = _Collector()
        self._tx = mavlink2.MAVLink(self._out, srcSystem=self._sysid,
                                    srcComponent=AUTOPILOT_COMPONENT_ID)
        self._signing_clock = signing_clock
        self._signing = signing_key is not None
        if signing_key is not None:
            # One signing state for both directions, as one pymavlink MAVLink object has: a
            # received timestamp also moves the one we send with (check_signature does so).
            self._rx.signing = self._tx.signing
            enable_signing(self._tx, signing_key, link_id=_SIGNING_LINK_ID,
                           unix_s=signing_clock())

        self.rejections: Counter[str] = Counter()
        self.accepted_setpoints = 0
        self.ignored_setpoints = 0
        self.nonfinite_setpoints = 0
        self.accepted_frames = 0
        self.failsafe_events = 0
        self.ignored_messages = 0

    # ---------------------------------------------------------------- read-only state
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
    def position_w(self) -> Array:
        return self._position.copy()

    @property
    def origin_w(self) -> Array:
        return self._origin.copy()

    @property
    def velocity_w(self) -> Array:
        return self._velocity.copy()

    @property
    def u_max_m_s(self) -> float:
        return self._u_max

    @property
    def setpoint_timeout_s(self) -> float:
        return self._timeout_s

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def custom_mode(self) -> int:
        return self._modes[self._mode]

    @property
    def in_setpoint_mode(self) -> bool:
        return self._mode == _SETPOINT_MODE[self._flavour]

    @property
    def airborne(self) -> bool:
        """px4: armed; ardupilot (takeoff_required): armed and a takeoff was accepted."""
        return self._armed and not self._landed

    @property
    def failsafe_active(self) -> bool:
        return self._failsafe

    @property
    def accepting_setpoints(self) -> bool:
        """A setpoint arriving now would be applied: armed, in the setpoint mode, airborne
        (ardupilot: after takeoff) and not in failsafe. "Ready for the mission" is this and
        ``setpoints_streaming(now_s)``."""
        return (self._armed and self.in_setpoint_mode and not self._landed
                and not self._failsafe)

    @property
    def rejected_frames(self) -> int:
        return sum(self.rejections.values())

    @property
    def signing(self) -> bool:
        return self._signing

    @property
    def authenticated_frames(self) -> int:
        return int(self._rx.signing.goodsig_count)

    def setpoints_streaming(self, now_s: float) -> bool:
        """At least STREAM_MIN_COUNT valid setpoints arrived in the last STREAM_WINDOW_S."""
        recent = [t for t in self._arrivals if now_s - STREAM_WINDOW_S <= t <= now_s]
        return len(recent) >= STREAM_MIN_COUNT

    # ---------------------------------------------------------------- dynamics / lockstep
    def commanded_velocity_w(self, now_s: float) -> Array:
        self._update(now_s)
        if (self._setpoint_ned is None or not self._armed or not self.in_setpoint_mode
                or self._landed or self._failsafe):
            return np.zeros(3)
        return clamp_velocity(frames.ned_to_enu(self._setpoint_ned), self._u_max)

    def begin_step(self, time_boot_ms: int) -> None:
        self._stamped.clear()
        self._awaited_stamp = int(time_boot_ms)

    @property
    def awaited_stamp(self) -> int | None:
        """The stamp given to the last begin_step() (None before the first)."""
        return self._awaited_stamp

    def setpoint_stamped(self, time_boot_ms: int | None = None) -> Array | None:
        stamp = self._awaited_stamp if time_boot_ms is None else int(time_boot_ms)
        velocity = None if stamp is None else self._stamped.get(stamp)
        return None if velocity is None else velocity.copy()

    def integrate(self, dt_s: float, velocity_w: ArrayLike) -> None:
        velocity = np.asarray(velocity_w, dtype=np.float64).reshape(3)
        self._position = self._position + dt_s * velocity
        self._velocity = velocity.copy()

    # ---------------------------------------------------------------- outgoing
    def heartbeat(self) -> bytes:
        if self._signing:  # once a second, as autopilots refresh it from their clock
            refresh_signing_timestamp(self._tx, self._signing_clock())
        (packet,) = self._emit([self._heartbeat_msg()])
        return packet

    def telemetry(self, time_boot_ms: int, now_s: float) -> list[bytes]:
        self._update(now_s)
        self._last_time_boot_ms = int(time_boot_ms) & 0xFFFFFFFF
        packets: list[bytes] = []
        for name, stream in self._streams.items():
            if not self._due(stream, now_s):
                continue
            packet = self._local_position_packet() if name == "LOCAL_POSITION_NED" else None
            packets += [packet] if packet is not None else self._emit(
                [self._stream_msg(name, self._last_time_boot_ms)])
        return packets

    # ---------------------------------------------------------------- incoming
    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        replies: list[Any] = []
        if not data and self._datagram_framing:
            self._reject("empty_datagram")  # holds no frame at all: still a rejected input
            return []
        setpoint = SET_POSITION_TARGET_LOCAL_NED.message(data) \
            if self._datagram_framing and not self._signing else None  # unsigned frames only
        messages = [setpoint] if setpoint is not None else parse_bytes(
            self._rx, data, self.rejections, datagram=self._datagram_framing)
        for msg in messages:
            rejected, ignored = self.rejected_frames, self.ignored_messages
            try:
                replies.extend(self._handle(msg, now_s))
            except Exception as exc:  # a malformed field value must never escape
                self._reject(f"handler_error:{type(exc).__name__}")
            if (self.rejected_frames, self.ignored_messages) == (rejected, ignored):
                self.accepted_frames += 1
        return self._emit(replies)

    # ================================================================ internals
    def _reject(self, reason: str) -> None:
        self.rejections[reason] += 1

    def _emit(self, msgs: list[Any]) -> list[bytes]:
        for msg in msgs:
            self._tx.send(msg)
        packets, self._out.packets = self._out.packets, []
        return packets

    def _update(self, now_s: float) -> None:
        """Setpoint-loss failsafe."""
        if not self.in_setpoint_mode or self._failsafe:
            return
        stale = self._last_setpoint_s is None or now_s - self._last_setpoint_s > self._timeout_s
        if self._flavour == "px4":
            if stale:
                self._mode = "LOITER"
                self._failsafe = True
                self.failsafe_events += 1
        elif self._armed and not self._landed and self._last_setpoint_s is not None and stale:
            self._failsafe = True  # GUIDED: stop and hold, mode unchanged
            self._setpoint_ned = None
            self.failsafe_events += 1

    # --- dispatch ---
    def _handle(self, msg: Any, now_s: float) -> list[Any]:
        target_system = getattr(msg, "target_system", None)
        if target_system is not None and target_system not in (0, self._sysid):
            self._reject("wrong_target_system")
            return []
        target_component = getattr(msg, "target_component", None)
        if target_component is not None and target_component not in (0, AUTOPILOT_COMPONENT_ID):
            self.ignored_messages += 1  # addressed to another component of this system
            return []
        handler = _HANDLERS.get(msg.get_type())
        if handler is None:
            self.ignored_messages += 1
            return []
        return handler(self, msg, now_s)

    def _on_setpoint(self, msg: Any, now_s: float) -> list[Any]:
        if msg.coordinate_frame != _MSG.MAV_FRAME_LOCAL_NED:
            self._reject("setpoint_frame")
            return []
        mask = msg.type_mask
        if (mask & ~0x0FFF or mask & _IGNORE_POSITION != _IGNORE_POSITION
                or mask & _IGNORE_ACCEL != _IGNORE_ACCEL or mask & _IGNORE_VELOCITY
                or mask & _FORCE_SET):
            self._reject("setpoint_type_mask")
            return []
        if not _finite(msg.vx, msg.vy, msg.vz):
            # Dropped at the boundary like any malformed frame: not applied, not stamped, no
            # proof of life; the vehicle keeps flying what it flew (or fails safe on silence).
            self.nonfinite_setpoints += 1
            self._reject("nonfinite_setpoint")
            return []
        self._update(now_s)
        self._arrivals.append(now_s)
        if self._flavour == "ardupilot" and not (self.in_setpoint_mode and self._armed
                                                 and not self._landed):
            self.ignored_setpoints += 1  # ArduPilot silently ignores these
        else:
            self._setpoint_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
            self._last_setpoint_s = now_s
            self.accepted_setpoints += 1
            if self._flavour == "ardupilot":
                self._failsafe = False
        stamp = int(msg.time_boot_ms)
        if stamp in self._stamped or len(self._stamped) < _MAX_STAMPED:
            self._stamped[stamp] = self.commanded_velocity_w(now_s)
        return []

    def _on_command(self, msg: Any, now_s: float) -> list[Any]:
        if msg.get_type() == "COMMAND_INT":
            params = (msg.param1, msg.param2, msg.param3, msg.param4,
                      float(msg.x), float(msg.y), msg.z)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4,
                      msg.param5, msg.param6, msg.param7)
        self._update(now_s)
        state = (self._mode, self._armed)
        result, extra = self._command(msg.command, params, now_s)
        out = [self._ack(msg, msg.command, result), *extra]
        if (self._mode, self._armed) != state:
            out.append(self._heartbeat_msg())
        return out

    def _ack(self, msg: Any, command: int, result: int) -> Any:
        return self._tx.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                           msg.get_srcComponent())

    def _command(self, command: int, p: tuple[float, ...], now_s: float) -> tuple[int, list[Any]]:
        if command == _MSG.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(p[0]), []
        if command == _MSG.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0], p[1], p[2]):
                return _MSG.MAV_RESULT_DENIED, []
            if not int(p[0]) & _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return _MSG.MAV_RESULT_DENIED, []
            if self._flavour == "px4":
                custom = _px4_custom_mode(int(p[1]) & 0xFF, int(p[2]) & 0xFF)
            else:
                custom = int(p[1])
            return self._set_mode(custom, now_s), []
        if command == _MSG.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(), []
        if command == _MSG.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(p[0], p[1]), []
        if command == _MSG.MAV_CMD_GET_MESSAGE_INTERVAL:
            name = _STREAM_IDS.get(int(p[0])) if _finite(p[0]) else None
            if name is None:
                return _MSG.MAV_RESULT_DENIED, []
            interval = self._streams[name].interval_s
            interval_us = -1 if interval is None else round(interval * 1e6)
            return _MSG.MAV_RESULT_ACCEPTED, [
                self._tx.message_interval_encode(int(p[0]), interval_us)]
        if command in (_MSG.MAV_CMD_REQUEST_MESSAGE,
                       _MSG.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = _MSG.MAVLINK_MSG_ID_AUTOPILOT_VERSION \
                if command == _MSG.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES \
                else (int(p[0]) if _finite(p[0]) else -1)
            if msg_id == _MSG.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
                return _MSG.MAV_RESULT_ACCEPTED, [self._autopilot_version_msg()]
            if msg_id in _STREAM_IDS:
                return _MSG.MAV_RESULT_ACCEPTED, [
                    self._stream_msg(_STREAM_IDS[msg_id], self._last_time_boot_ms)]
            return _MSG.MAV_RESULT_DENIED, []
        return _MSG.MAV_RESULT_UNSUPPORTED, []

    def _arm_disarm(self, param1: float) -> int:
        if not _finite(param1) or param1 not in (0.0, 1.0):
            return _MSG.MAV_RESULT_DENIED
        if param1 == 1.0:
            self._armed = True
        else:
            self._armed = False
            self._landed = self._takeoff_required
            if self._flavour == "ardupilot":  # landed: a new takeoff and setpoints are needed
                self._setpoint_ned = None
                self._last_setpoint_s = None
                self._failsafe = False
        return _MSG.MAV_RESULT_ACCEPTED

    def _set_mode(self, custom_mode: int, now_s: float) -> int:
        names = [name for name, value in self._modes.items() if value == custom_mode]
        if not names:
            return _MSG.MAV_RESULT_DENIED
        name = names[0]
        if (self._flavour == "px4" and name == "OFFBOARD" and self._mode != "OFFBOARD"
                and not self.setpoints_streaming(now_s)):
            return _MSG.MAV_RESULT_TEMPORARILY_REJECTED  # PX4: no offboard signal yet
        if name != self._mode or self._failsafe:
            self._failsafe = False
            if self._flavour == "ardupilot":
                self._setpoint_ned = None  # GUIDED starts from "hold"
                self._last_setpoint_s = None
        self._mode = name
        return _MSG.MAV_RESULT_ACCEPTED

    def _takeoff(self) -> int:
        if self._flavour == "ardupilot":
            if self._mode != "GUIDED" or not self._armed:
                return _MSG.MAV_RESULT_FAILED
            self._landed = False  # already at altitude: airborne at once, no motion
            return _MSG.MAV_RESULT_ACCEPTED
        if not self._armed:
            return _MSG.MAV_RESULT_TEMPORARILY_REJECTED
        self._landed = False
        self._mode = "LOITER"  # AUTO.TAKEOFF completes at once and PX4 then holds
        self._failsafe = False
        return _MSG.MAV_RESULT_ACCEPTED

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not _finite(msg_id, interval_us):
            return _MSG.MAV_RESULT_DENIED
        name = _STREAM_IDS.get(int(msg_id))
        if name is None or (interval_us < 0 and interval_us != -1):
            return _MSG.MAV_RESULT_DENIED
        stream = self._streams[name]
        if interval_us == -1:
            stream.interval_s = None
        elif interval_us == 0:
            stream.interval_s = _RESTORED_INTERVAL_S[name]
        else:
            stream.interval_s = interval_us * 1e-6
        stream.explicit = True
        stream.next_due_s = None
        return _MSG.MAV_RESULT_ACCEPTED

    def _on_set_mode(self, msg: Any, now_s: float) -> list[Any]:
        self._update(now_s)
        state = (self._mode, self._armed)
        if not msg.base_mode & _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            result = _MSG.MAV_RESULT_DENIED
        else:
            result = self._set_mode(int(msg.custom_mode), now_s)
        out = [self._ack(msg, _MSG.MAVLINK_MSG_ID_SET_MODE, result)]
        if (self._mode, self._armed) != state:
            out.append(self._heartbeat_msg())
        return out

    def _on_request_data_stream(self, msg: Any, now_s: float) -> list[Any]:
        if self._flavour != "ardupilot":
            self.ignored_messages += 1  # PX4 does not implement REQUEST_DATA_STREAM
            return []
        names = _DATA_STREAMS.get(msg.req_stream_id, ())
        for name in names:
            stream = self._streams[name]
            if stream.explicit:
                continue
            on = msg.start_stop != 0 and msg.req_message_rate > 0
            stream.interval_s = 1.0 / msg.req_message_rate if on else None
            stream.next_due_s = None
        return []

    def _param_msg(self, index: int) -> Any:
        name = _TIMEOUT_PARAM[self._flavour]
        return self._tx.param_value_encode(name.encode(), self._timeout_s,
                                           _MSG.MAV_PARAM_TYPE_REAL32, 1, index)

    def _on_param_request_list(self, msg: Any, now_s: float) -> list[Any]:
        return [self._param_msg(0)]

    def _on_param_request_read(self, msg: Any, now_s: float) -> list[Any]:
        if msg.param_index == 0 or (msg.param_index == -1
                                    and msg.param_id == _TIMEOUT_PARAM[self._flavour]):
            return [self._param_msg(0)]
        self.ignored_messages += 1  # unknown parameter: no answer, as autopilots do
        return []

    def _on_param_set(self, msg: Any, now_s: float) -> list[Any]:
        if msg.param_id != _TIMEOUT_PARAM[self._flavour]:
            self.ignored_messages += 1
            return []
        if math.isfinite(msg.param_value) and msg.param_value > 0:
            self._timeout_s = float(msg.param_value)
        return [self._param_msg(0)]  # the (possibly unchanged) value, as autopilots reply

    def _on_mission_request_list(self, msg: Any, now_s: float) -> list[Any]:
        return [self._tx.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                              msg.mission_type)]

    def _on_timesync(self, msg: Any, now_s: float) -> list[Any]:
        if msg.tc1 != 0:
            return []
        return [self._tx.timesync_encode(max(0, int(now_s * 1e9)), msg.ts1)]

    # --- outgoing messages ---
    def _due(self, stream: _Stream, now_s: float) -> bool:
        interval = stream.interval_s
        if interval is None:
            return False
        if stream.last_sent_s is not None and now_s < stream.last_sent_s:
            stream.next_due_s = None  # the caller's clock went backwards: restart schedule
        if interval != EVERY_CALL and stream.next_due_s is not None \
                and now_s < stream.next_due_s - min(_DUE_TOLERANCE_S, 0.25 * interval):
            return False
        if interval != EVERY_CALL:
            base = now_s if stream.next_due_s is None else stream.next_due_s
            stream.next_due_s = base + interval
            if stream.next_due_s <= now_s:  # fell behind by more than a period
                stream.next_due_s = now_s + interval
        stream.last_sent_s = now_s
        return True

    def _heartbeat_msg(self) -> Any:
        base_mode = _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base_mode |= _MSG.MAV_MODE_FLAG_SAFETY_ARMED
        autopilot = _MSG.MAV_AUTOPILOT_PX4 if self._flavour == "px4" \
            else _MSG.MAV_AUTOPILOT_ARDUPILOTMEGA
        status = _MSG.MAV_STATE_ACTIVE if self._armed else _MSG.MAV_STATE_STANDBY
        return self._tx.heartbeat_encode(_MSG.MAV_TYPE_QUADROTOR, autopilot, base_mode,
                                         self.custom_mode, status, 3)

    def _local_position_fields(self) -> tuple[float, ...]:
        x, y, z = (float(c) for c in frames.local_ned_from_world(self._position, self._origin))
        vx, vy, vz = (float(c) for c in frames.enu_to_ned(self._velocity))
        return x, y, z, vx, vy, vz

    def _local_position_packet(self) -> bytes | None:
        """LOCAL_POSITION_NED packed on the fast path (None: pymavlink must pack it)."""
        return LOCAL_POSITION_NED.pack(self._tx, self._last_time_boot_ms,
                                       *self._local_position_fields())

    def _stream_msg(self, name: str, time_boot_ms: int) -> Any:
        if name == "HEARTBEAT":
            return self._heartbeat_msg()
        if name == "LOCAL_POSITION_NED":
            return self._tx.local_position_ned_encode(time_boot_ms,
                                                      *self._local_position_fields())
        if name == "ATTITUDE":
            return self._tx.attitude_encode(time_boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if name == "SYS_STATUS":
            return self._tx.sys_status_encode(_SENSORS, _SENSORS, _SENSORS, 100, 16200, -1, 100,
                                              0, 0, 0, 0, 0, 0)
        landed = _MSG.MAV_LANDED_STATE_IN_AIR if self.airborne \
            else _MSG.MAV_LANDED_STATE_ON_GROUND
        return self._tx.extended_sys_state_encode(_MSG.MAV_VTOL_STATE_UNDEFINED, landed)

    def _autopilot_version_msg(self) -> Any:
        caps = (_MSG.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | _MSG.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | _MSG.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT)
        if self._flavour == "px4":
            caps |= _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            version = (1 << 24) | (14 << 16) | (0 << 8) | 255  # 1.14.0 official
        else:
            caps |= _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
            version = (4 << 24) | (5 << 16) | (0 << 8) | 255  # 4.5.0 official
        return self._tx.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8,
                                                 [0] * 8, 0, 0, self._sysid)


_HANDLERS = {
    "SET_POSITION_TARGET_LOCAL_NED": EmulatedVehicle._on_setpoint,
    "COMMAND_LONG": EmulatedVehicle._on_command,
    "COMMAND_INT": EmulatedVehicle._on_command,
    "SET_MODE": EmulatedVehicle._on_set_mode,
    "REQUEST_DATA_STREAM": EmulatedVehicle._on_request_data_stream,
    "PARAM_REQUEST_LIST": EmulatedVehicle._on_param_request_list,
    "PARAM_REQUEST_READ": EmulatedVehicle._on_param_request_read,
    "PARAM_SET": EmulatedVehicle._on_param_set,
    "MISSION_REQUEST_LIST": EmulatedVehicle._on_mission_request_list,
    "TIMESYNC": EmulatedVehicle._on_timesync,
}
