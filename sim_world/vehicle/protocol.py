"""The MAVLink 2 side of an emulated vehicle: ``EmulatedVehicle`` parses what arrives (bytes in,
replies out), answers commands and parameter requests, streams telemetry and stamps the
setpoints of lockstep steps, around the vehicle's ``Flight`` (``sim_world.vehicle.flight``).

No sockets and no clock of its own: every call that depends on time takes it (``now_s``).
Encoding and parsing use pymavlink's generated MAVLink 2 module; the per-step
LOCAL_POSITION_NED out and setpoints in go through ``swarm.mavlink.parse.FastFrame``
(byte-identical frames, without pymavlink's per-byte parser). Not thread-safe. The public
API and the behaviour of both flavours: docs/vehicle_emulator.md.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sim_world.vehicle.flavours import (
    AUTOPILOT,
    DATA_STREAMS,
    DEFAULT_INTERVAL_S,
    EVERY_CALL,
    FIRMWARE_VERSION,
    FLAVOURS,
    MODES,
    PARAM_ENCODING,
    RESTORED_INTERVAL_S,
    Flavour,
    FlightModel,
    Start,
    px4_custom_mode,
)
from sim_world.vehicle.flight import Flight
from swarm.mavlink.parse import LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED, parse_bytes
from swarm.mavlink.signing import enable_signing, refresh_signing_timestamp
from swarm.models import frames
from swarm.models.kinematics import VelocityResponse, clamp_velocity

Array = NDArray[np.float64]

AUTOPILOT_COMPONENT_ID = 1
_SIGNING_LINK_ID = 0  # the autopilot's MAVLink channel 0
_MSG = mavlink2

# --- setpoints -------------------------------------------------------------------------------
_IGNORE_POSITION = 0x007  # bits 0-2: x, y, z
_IGNORE_VELOCITY = 0x038  # bits 3-5: vx, vy, vz
_IGNORE_ACCEL = 0x1C0  # bits 6-8: afx, afy, afz
_YAW_BITS = 0xC00  # bits 10-11: yaw, yaw rate (free)
# type_mask without the yaw bits → what the setpoint carries (the force bit 0x200 and bits
# above 11 never match).
_SETPOINT_KINDS: dict[int, tuple[bool, bool, bool]] = {  # (position, velocity, acceleration)
    _IGNORE_POSITION | _IGNORE_ACCEL: (False, True, False),
    _IGNORE_VELOCITY | _IGNORE_ACCEL: (True, False, False),
    _IGNORE_ACCEL: (True, True, False),
    0: (True, True, True),
}

# --- telemetry streams ------------------------------------------------------------------------
_STREAM_IDS = {
    _MSG.MAVLINK_MSG_ID_HEARTBEAT: "HEARTBEAT",
    _MSG.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
    _MSG.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    _MSG.MAVLINK_MSG_ID_SYS_STATUS: "SYS_STATUS",
    _MSG.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "EXTENDED_SYS_STATE",
}
# A periodic stream is due this early (absorbs float round-off and call jitter without
# shortening the period noticeably).
_DUE_TOLERANCE_S = 0.005

_SENSORS = (_MSG.MAV_SYS_STATUS_SENSOR_3D_GYRO | _MSG.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | _MSG.MAV_SYS_STATUS_SENSOR_3D_MAG | _MSG.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | _MSG.MAV_SYS_STATUS_SENSOR_GPS | _MSG.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
# SYS_STATUS's fields (every link): sensors present, enabled and healthy; load 10 %; 16.2 V,
# current unknown, 100 % battery; no errors.
SYS_STATUS_SENSORS = (_SENSORS, _SENSORS, _SENSORS, 100, 16200, -1, 100, 0, 0, 0, 0, 0, 0)
_MAX_STAMPED = 256


@dataclass
class _Stream:
    interval_s: float | None  # None: off; EVERY_CALL: every call; > 0: period
    explicit: bool = False  # set by SET_MESSAGE_INTERVAL (wins over REQUEST_DATA_STREAM)
    next_due_s: float | None = None
    last_sent_s: float | None = None


class PacketCollector:
    """File-like sink for pymavlink's MAVLink.send(): keeps the packed packets."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, buf: bytes | bytearray) -> None:
        self.packets.append(bytes(buf))


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


class EmulatedVehicle:
    """MAVLink 2 protocol state machine of one PX4- or ArduCopter-like copter
    (docs/vehicle_emulator.md)."""

    def __init__(
        self,
        drone_id: int,
        flavour: Flavour,
        position_w: ArrayLike,
        origin_w: ArrayLike,
        *,
        u_max_m_s: float = 3.0,
        setpoint_timeout_s: float | None = None,
        start: Start = "air",
        response: VelocityResponse = VelocityResponse(),  # noqa: B008 (frozen, immutable)
        flight_model: FlightModel | None = None,
        datagram_framing: bool = True,
        signing_key: bytes | None = None,
        signing_clock: Callable[[], float] = time.time,
    ) -> None:
        if flavour not in FLAVOURS:
            raise ValueError(f"flavour must be 'px4' or 'ardupilot', got {flavour!r}")
        if not 0 <= drone_id <= 253:
            raise ValueError(f"drone_id must be in 0..253 (system id = drone_id + 1), "
                             f"got {drone_id}")
        self._flight = Flight(flavour, position_w, origin_w, u_max_m_s=u_max_m_s,
                              setpoint_timeout_s=setpoint_timeout_s, start=start,
                              response=response, flight_model=flight_model)
        self._drone_id = int(drone_id)
        self._sysid = self._drone_id + 1
        self._flavour: Flavour = flavour
        self._origin_xyz = frames.as_xyz(self._flight.origin_w, "origin_w")
        self._u_max = self._flight.u_max_m_s
        self._datagram_framing = bool(datagram_framing)
        self._modes = MODES[flavour]

        self._stamped: dict[int, Array] = {}
        self._awaited_stamp: int | None = None
        self._last_time_boot_ms = 0
        self._streams = {name: _Stream(DEFAULT_INTERVAL_S[flavour][name])
                         for name in _STREAM_IDS.values()}

        self._rx = mavlink2.MAVLink(None, srcSystem=self._sysid,
                                    srcComponent=AUTOPILOT_COMPONENT_ID)
        self._rx.robust_parsing = True
        self._out = PacketCollector()
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
        self.nonfinite_setpoints = 0
        self.accepted_frames = 0
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
        return self._flight.position_w

    @property
    def reported_position_w(self) -> Array:
        """The W-position an agent reads from this vehicle's LOCAL_POSITION_NED now: its
        position as the float32 local NED the stream carries (``_local_position_fields``),
        converted back (``frames.position_over_link``)."""
        return frames.position_over_link(self._flight.position_w, self._flight.origin_w)

    @property
    def origin_w(self) -> Array:
        return self._flight.origin_w

    @property
    def ground_z_m(self) -> float:
        """The ground: the plane z = origin_w[2] of W."""
        return self._flight.ground_z_m

    @property
    def velocity_w(self) -> Array:
        return self._flight.velocity_w

    @property
    def u_max_m_s(self) -> float:
        return self._u_max

    @property
    def response(self) -> VelocityResponse:
        return self._flight.response

    @property
    def flight_model(self) -> FlightModel:
        return self._flight.flight_model

    @property
    def setpoint_timeout_s(self) -> float:
        return self._flight.setpoint_timeout_s

    @property
    def params(self) -> dict[str, float]:
        return self._flight.params

    @property
    def armed(self) -> bool:
        return self._flight.armed

    @property
    def mode(self) -> str:
        return self._flight.mode

    @property
    def custom_mode(self) -> int:
        return self._flight.custom_mode

    @property
    def landed_state(self) -> int:
        """MAV_LANDED_STATE_*: ON_GROUND, TAKEOFF, IN_AIR or LANDING (EXTENDED_SYS_STATE)."""
        return self._flight.landed_state

    @property
    def in_setpoint_mode(self) -> bool:
        return self._flight.in_setpoint_mode

    @property
    def airborne(self) -> bool:
        """Off the ground: climbing after a takeoff, flying or landing (not spooling up)."""
        return self._flight.airborne

    @property
    def failsafe_active(self) -> bool:
        return self._flight.failsafe_active

    @property
    def accepting_setpoints(self) -> bool:
        """A setpoint arriving now would be applied: armed, in the setpoint mode, not in
        failsafe, and (ardupilot) in the air. "Ready for the mission" is this and
        ``setpoints_streaming(now_s)``."""
        return self._flight.accepting_setpoints

    @property
    def accepted_setpoints(self) -> int:
        return self._flight.accepted_setpoints

    @property
    def ignored_setpoints(self) -> int:
        return self._flight.ignored_setpoints

    @property
    def failsafe_events(self) -> int:
        return self._flight.failsafe_events

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
        """At least ``flight.STREAM_MIN_COUNT`` valid setpoints arrived in the last
        ``flight.STREAM_WINDOW_S``."""
        return self._flight.setpoints_streaming(now_s)

    # ---------------------------------------------------------------- lockstep
    def commanded_velocity_w(self, now_s: float) -> Array:
        return self._flight.commanded_velocity_w(now_s)

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
        self._flight.integrate(dt_s, np.asarray(velocity_w, dtype=np.float64))

    def push(self, offset_w: ArrayLike) -> None:
        """Move the vehicle by ``offset_w`` [m] at once (a gust; ``Flight.push``)."""
        self._flight.push(np.asarray(offset_w, dtype=np.float64))

    # ---------------------------------------------------------------- realtime
    def fly(self, dt_s: float, now_s: float) -> None:
        """Fly for ``dt_s`` (ending at ``now_s``) as the mode and state say."""
        self._flight.fly(dt_s, now_s)

    # ---------------------------------------------------------------- outgoing
    def heartbeat(self) -> bytes:
        if self._signing:  # once a second, as autopilots refresh it from their clock
            refresh_signing_timestamp(self._tx, self._signing_clock())
        (packet,) = self._emit([self._heartbeat_msg()])
        return packet

    def telemetry(self, time_boot_ms: int, now_s: float) -> list[bytes]:
        self._flight.update(now_s)
        self._last_time_boot_ms = int(time_boot_ms) & 0xFFFFFFFF
        packets: list[bytes] = []
        texts = self._flight.take_texts()
        if texts:
            packets += self._emit([self._statustext_msg(severity, text)
                                   for severity, text in texts])
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
        mask = int(msg.type_mask)
        kind = _SETPOINT_KINDS.get(mask & ~_YAW_BITS) if not mask & ~0x0FFF else None
        if kind is None:
            self._reject("setpoint_type_mask")
            return []
        has_position, has_velocity, has_accel = kind
        used = ((msg.x, msg.y, msg.z) if has_position else ()) \
            + ((msg.vx, msg.vy, msg.vz) if has_velocity else ()) \
            + ((msg.afx, msg.afy, msg.afz) if has_accel else ())
        if not _finite(*used):
            # Dropped at the boundary like any malformed frame: not applied, not stamped, no
            # proof of life; the vehicle keeps flying what it flew (or fails safe on silence).
            self.nonfinite_setpoints += 1
            self._reject("nonfinite_setpoint")
            return []
        position = np.array(frames.world_from_local_ned_xyz(
            (msg.x, msg.y, msg.z), self._origin_xyz), dtype=np.float64) \
            if has_position else None
        velocity = clamp_velocity(np.array(frames.ned_to_enu_xyz(msg.vx, msg.vy, msg.vz),
                                           dtype=np.float64), self._u_max) \
            if has_velocity else None
        self._flight.receive_setpoint(position, velocity, now_s)
        stamp = int(msg.time_boot_ms)
        if stamp in self._stamped or len(self._stamped) < _MAX_STAMPED:
            self._stamped[stamp] = self._flight.commanded_velocity_w(now_s)
        return []

    def _on_command(self, msg: Any, now_s: float) -> list[Any]:
        if msg.get_type() == "COMMAND_INT":
            params = (msg.param1, msg.param2, msg.param3, msg.param4,
                      float(msg.x), float(msg.y), msg.z)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4,
                      msg.param5, msg.param6, msg.param7)
        flight = self._flight
        flight.update(now_s)
        state = (flight.mode, flight.armed)
        result, extra = self._command(msg.command, params, now_s)
        out = [self._ack(msg, msg.command, result), *extra]
        # why (ArduPilot's STATUSTEXT), right behind the answer
        out += [self._statustext_msg(severity, text) for severity, text in flight.take_texts()]
        if (flight.mode, flight.armed) != state:
            out.append(self._heartbeat_msg())
        return out

    def _ack(self, msg: Any, command: int, result: int) -> Any:
        return self._tx.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                           msg.get_srcComponent())

    def _command(self, command: int, p: tuple[float, ...], now_s: float) -> tuple[int, list[Any]]:
        flight = self._flight
        if command == _MSG.MAV_CMD_COMPONENT_ARM_DISARM:
            return flight.arm_disarm(p[0], now_s), []
        if command == _MSG.MAV_CMD_DO_SET_MODE:
            if not _finite(p[0], p[1], p[2]):
                return _MSG.MAV_RESULT_DENIED, []
            if not int(p[0]) & _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return _MSG.MAV_RESULT_DENIED, []
            if self._flavour == "px4":
                custom = px4_custom_mode(int(p[1]) & 0xFF, int(p[2]) & 0xFF)
            else:
                custom = int(p[1])
            return flight.set_mode(custom, now_s), []
        if command == _MSG.MAV_CMD_NAV_TAKEOFF:
            return flight.takeoff(p[6], now_s), []
        if command in (_MSG.MAV_CMD_NAV_LAND, _MSG.MAV_CMD_NAV_RETURN_TO_LAUNCH):
            name = "LAND" if command == _MSG.MAV_CMD_NAV_LAND else "RTL"
            return flight.set_mode(self._modes[name], now_s), []
        if command == _MSG.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(p[0], p[1]), []
        if command == _MSG.MAV_CMD_GET_MESSAGE_INTERVAL:
            stream = _STREAM_IDS.get(int(p[0])) if _finite(p[0]) else None
            if stream is None:
                return _MSG.MAV_RESULT_DENIED, []
            interval = self._streams[stream].interval_s
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

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not _finite(msg_id, interval_us):
            return _MSG.MAV_RESULT_DENIED
        name = _STREAM_IDS.get(int(msg_id))
        if name is None or (interval_us < 0 and interval_us != -1):
            return _MSG.MAV_RESULT_DENIED
        if name == "HEARTBEAT" and self._flavour == "px4":
            return _MSG.MAV_RESULT_FAILED  # PX4 keeps its 1 Hz heartbeat
        stream = self._streams[name]
        if interval_us == -1:
            stream.interval_s = None
        elif interval_us == 0:
            stream.interval_s = RESTORED_INTERVAL_S[name]
        else:
            stream.interval_s = interval_us * 1e-6
        stream.explicit = True
        stream.next_due_s = None
        return _MSG.MAV_RESULT_ACCEPTED

    def _on_set_mode(self, msg: Any, now_s: float) -> list[Any]:
        flight = self._flight
        flight.update(now_s)
        state = (flight.mode, flight.armed)
        if not msg.base_mode & _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            result = _MSG.MAV_RESULT_DENIED
        else:
            result = flight.set_mode(int(msg.custom_mode), now_s)
        out = [self._ack(msg, _MSG.MAVLINK_MSG_ID_SET_MODE, result)]
        if (flight.mode, flight.armed) != state:
            out.append(self._heartbeat_msg())
        return out

    def _on_request_data_stream(self, msg: Any, now_s: float) -> list[Any]:
        if self._flavour != "ardupilot":
            self.ignored_messages += 1  # PX4 does not implement REQUEST_DATA_STREAM
            return []
        names = DATA_STREAMS.get(msg.req_stream_id, ())
        for name in names:
            stream = self._streams[name]
            if stream.explicit:
                continue
            on = msg.start_stop != 0 and msg.req_message_rate > 0
            stream.interval_s = 1.0 / msg.req_message_rate if on else None
            stream.next_due_s = None
        return []

    def _param_msg(self, name: str) -> Any:
        specs = self._flight.param_specs
        index = list(specs).index(name)
        return self._tx.param_value_encode(name.encode(), self._flight.params[name],
                                           specs[name].mav_type, len(specs), index)

    def _on_param_request_list(self, msg: Any, now_s: float) -> list[Any]:
        return [self._param_msg(name) for name in self._flight.param_specs]

    def _on_param_request_read(self, msg: Any, now_s: float) -> list[Any]:
        specs = self._flight.param_specs
        names = list(specs)
        if msg.param_index == -1 and msg.param_id in specs:
            return [self._param_msg(msg.param_id)]
        if 0 <= msg.param_index < len(names):
            return [self._param_msg(names[msg.param_index])]
        self.ignored_messages += 1  # unknown parameter: no answer, as autopilots do
        return []

    def _on_param_set(self, msg: Any, now_s: float) -> list[Any]:
        if msg.param_id not in self._flight.param_specs:
            self.ignored_messages += 1
            return []
        self._flight.set_param(msg.param_id, float(msg.param_value))
        return [self._param_msg(msg.param_id)]  # the (possibly unchanged) value, as they do

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

    def heartbeat_fields(self) -> tuple[int, int, int, int, int, int]:
        """HEARTBEAT's fields now (type, autopilot, base_mode, custom_mode, system_status,
        mavlink_version), for every link of the vehicle."""
        armed = self._flight.armed
        base_mode = _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if armed:
            base_mode |= _MSG.MAV_MODE_FLAG_SAFETY_ARMED
        status = _MSG.MAV_STATE_ACTIVE if armed else _MSG.MAV_STATE_STANDBY
        return (_MSG.MAV_TYPE_QUADROTOR, AUTOPILOT[self._flavour], base_mode,
                self._flight.custom_mode, status, 3)

    def _heartbeat_msg(self) -> Any:
        return self._tx.heartbeat_encode(*self.heartbeat_fields())

    def _statustext_msg(self, severity: int, text: str) -> Any:
        return self._tx.statustext_encode(severity, text.encode()[:50])

    def _local_position_fields(self) -> tuple[float, ...]:
        flight = self._flight
        x, y, z = frames.local_ned_from_world_xyz(tuple(flight.position_w.tolist()),
                                                  self._origin_xyz)
        return (x, y, z, *frames.enu_to_ned_xyz(*flight.velocity_w.tolist()))

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
            return self._tx.sys_status_encode(*SYS_STATUS_SENSORS)
        return self._tx.extended_sys_state_encode(_MSG.MAV_VTOL_STATE_UNDEFINED,
                                                  self._flight.landed_state)

    def _autopilot_version_msg(self) -> Any:
        caps = (_MSG.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | _MSG.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | _MSG.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | PARAM_ENCODING[self._flavour])
        return self._tx.autopilot_version_encode(caps, FIRMWARE_VERSION[self._flavour], 0, 0, 0,
                                                 [0] * 8, [0] * 8, [0] * 8, 0, 0, self._sysid)


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
