"""A ground station's view of one emulated vehicle: the second MAVLink link every autopilot has.

PX4 SITL sends its ground-station link to UDP 14550 beside the offboard one; ArduPilot SITL
serves one on its second serial port. ``GcsLink`` is that link for an ``EmulatedVehicle``: its
own sequence numbers, its own fixed stream rates, and a rule for what a ground station may do.

Streams (``telemetry``), at the rates of PX4's "normal" ground-station mode, rounded:
HEARTBEAT and SYS_STATUS at 1 Hz, GLOBAL_POSITION_INT and LOCAL_POSITION_NED at 5 Hz, ATTITUDE
at 10 Hz. GLOBAL_POSITION_INT places the vehicle on Earth from the world frame's geodetic
origin (``vehicles.geo_origin``; ``GeoPoint.moved``, the local tangent plane SITL homes use);
``relative_alt`` is the height above the vehicle's home (its local NED origin). The emulated
vehicle is a point mass: ATTITUDE reports it level, facing north, and GLOBAL_POSITION_INT's
heading is "unknown" (UINT16_MAX).

What comes from the ground station (``receive``):

* read requests (parameters, the mission list, TIMESYNC) are answered by the vehicle itself,
  as it answers its companion;
* its HEARTBEAT, and anything addressed to another system, is ignored;
* everything that could change the flight — COMMAND_LONG / COMMAND_INT, SET_MODE, setpoints,
  PARAM_SET, mission uploads, RC overrides — is **refused** unless the link was opened with
  ``control=True``: commands get COMMAND_ACK MAV_RESULT_DENIED (ArduPilot also says why in a
  STATUSTEXT, as it does), PARAM_SET the parameter's unchanged value, a mission upload
  MISSION_ACK MAV_MISSION_DENIED, the rest no answer. Each refusal is counted in ``refused``
  (by message, and command id) and logged the first time that kind arrives;
* with ``control=True`` every frame goes to the vehicle as if from its companion, and each
  command is logged.

With MAVLink signing on, the ground-station link only streams (it holds no key): what it
receives is counted in ``refused`` as ``signed_vehicle`` and never reaches the vehicle.

Public API: ``GcsLink(vehicle, geo_origin, *, control=False, log=None)`` with
``telemetry(time_boot_ms, now_s) -> list[bytes]``, ``receive(data, now_s) -> list[bytes]``,
``refused`` (Counter), ``rejections`` (Counter of undecodable input), ``GCS_STREAM_PERIODS_S``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sim_world.vehicle import (
    AUTOPILOT_COMPONENT_ID,
    SYS_STATUS_SENSORS,
    EmulatedVehicle,
    PacketCollector,
)
from swarm.mavlink.parse import parse_bytes
from swarm.models import frames
from swarm.models.frames import GeoPoint

__all__ = ["GCS_STREAM_PERIODS_S", "GcsLink"]

_MSG = mavlink2
GCS_STREAM_PERIODS_S: dict[str, float] = {
    "HEARTBEAT": 1.0, "SYS_STATUS": 1.0, "GLOBAL_POSITION_INT": 0.2,
    "LOCAL_POSITION_NED": 0.2, "ATTITUDE": 0.1}
_DUE_TOLERANCE_S = 0.005  # a stream is due this early (call jitter)
# Answered by the vehicle: reading changes nothing.
_READ_ONLY = frozenset({"PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "MISSION_REQUEST_LIST",
                        "TIMESYNC"})
_COMMANDS = frozenset({"COMMAND_LONG", "COMMAND_INT"})
_MISSION_UPLOADS = frozenset({"MISSION_COUNT", "MISSION_ITEM", "MISSION_ITEM_INT",
                              "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT"})
_UNKNOWN_HEADING = 0xFFFF


def _int_clamped(value: float, bound: int) -> int:
    return max(-bound, min(bound, round(value)))


class GcsLink:
    """The ground-station link of ``vehicle`` (see the module docstring)."""

    def __init__(self, vehicle: EmulatedVehicle, geo_origin: GeoPoint, *,
                 control: bool = False, log: Callable[[str], None] | None = None) -> None:
        if control and vehicle.signing:
            raise ValueError("a ground station cannot control a vehicle that signs its MAVLink "
                             "(the GCS link holds no key): drop the GCS control or the signing")
        self.vehicle, self.geo_origin, self.control = vehicle, geo_origin, control
        self._log = log or (lambda line: None)
        self._out = PacketCollector()
        self._tx = mavlink2.MAVLink(self._out, srcSystem=vehicle.system_id,
                                    srcComponent=AUTOPILOT_COMPONENT_ID)
        self._rx = mavlink2.MAVLink(None, srcSystem=vehicle.system_id,
                                    srcComponent=AUTOPILOT_COMPONENT_ID)
        self._rx.robust_parsing = True
        self._next_due_s: dict[str, float | None] = dict.fromkeys(GCS_STREAM_PERIODS_S)
        self.refused: Counter[str] = Counter()
        self.rejections: Counter[str] = Counter()

    # ------------------------------------------------------------------ outgoing
    def telemetry(self, time_boot_ms: int, now_s: float) -> list[bytes]:
        """The streams due at ``now_s`` [s] (any clock that does not go backwards)."""
        stamp = int(time_boot_ms) & 0xFFFFFFFF
        messages = [self._message(name, stamp) for name in GCS_STREAM_PERIODS_S
                    if self._due(name, now_s)]
        return self._emit(messages)

    def _due(self, name: str, now_s: float) -> bool:
        due = self._next_due_s[name]
        if due is not None and now_s < due - _DUE_TOLERANCE_S:
            return False
        period = GCS_STREAM_PERIODS_S[name]
        following = (now_s if due is None else due) + period
        self._next_due_s[name] = following if following > now_s else now_s + period
        return True

    def _message(self, name: str, stamp: int) -> Any:
        v = self.vehicle
        if name == "HEARTBEAT":
            return self._tx.heartbeat_encode(*v.heartbeat_fields())
        if name == "SYS_STATUS":
            return self._tx.sys_status_encode(*SYS_STATUS_SENSORS)
        if name == "ATTITUDE":
            return self._tx.attitude_encode(stamp, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        ned = frames.local_ned_from_world(v.position_w, v.origin_w)
        velocity_ned = frames.enu_to_ned(v.velocity_w)
        if name == "LOCAL_POSITION_NED":
            return self._tx.local_position_ned_encode(stamp, *(float(c) for c in ned),
                                                      *(float(c) for c in velocity_ned))
        east, north, up = (float(c) for c in v.position_w)
        where = self.geo_origin.moved(east, north, up)
        cm_s = [_int_clamped(100.0 * float(c), 0x7FFF) for c in velocity_ned]
        return self._tx.global_position_int_encode(
            stamp, _int_clamped(where.lat_deg * 1e7, 0x7FFFFFFF),
            _int_clamped(where.lon_deg * 1e7, 0x7FFFFFFF),
            _int_clamped(where.alt_m * 1000.0, 0x7FFFFFFF),
            _int_clamped(-float(ned[2]) * 1000.0, 0x7FFFFFFF), *cm_s, _UNKNOWN_HEADING)

    def _emit(self, messages: list[Any]) -> list[bytes]:
        for msg in messages:
            self._tx.send(msg)
        packets, self._out.packets = self._out.packets, []
        return packets

    # ------------------------------------------------------------------ incoming
    def receive(self, data: bytes, now_s: float) -> list[bytes]:
        """Handle one datagram from the ground station; the packets to send back to it."""
        replies: list[bytes] = []
        for msg in parse_bytes(self._rx, data, self.rejections, datagram=True):
            kind = msg.get_type()
            target = getattr(msg, "target_system", 0)
            if kind == "HEARTBEAT" or target not in (0, self.vehicle.system_id):
                continue  # a GCS's own heartbeat; a message for another vehicle
            if self.vehicle.signing:
                self._refuse("signed_vehicle", "the vehicle signs its MAVLink, this link has "
                             "no key")
                continue
            if self.control:
                if kind in _COMMANDS or kind == "SET_MODE":
                    self._log(f"drone {self.vehicle.drone_id}: ground station sent {_name(msg)}")
                replies += self.vehicle.receive(msg.get_msgbuf(), now_s)
            elif kind in _READ_ONLY:
                replies += self.vehicle.receive(msg.get_msgbuf(), now_s)
            else:
                replies += self._refusal(msg, kind, now_s)
        return replies

    def _refusal(self, msg: Any, kind: str, now_s: float) -> list[bytes]:
        self._refuse(_name(msg), "the ground-station link streams and answers reads only")
        if kind in _COMMANDS:
            answer = [self._tx.command_ack_encode(msg.command, _MSG.MAV_RESULT_DENIED, 0, 0,
                                                  msg.get_srcSystem(), msg.get_srcComponent())]
            if self.vehicle.flavour == "ardupilot":
                answer.append(self._tx.statustext_encode(
                    _MSG.MAV_SEVERITY_WARNING, b"GCS link is read-only"))
            return self._emit(answer)
        if kind == "PARAM_SET":  # its unchanged value, as the vehicle reports it
            read = self._tx.param_request_read_encode(self.vehicle.system_id,
                                                      AUTOPILOT_COMPONENT_ID,
                                                      msg.param_id.encode(), -1)
            read.pack(self._rx)
            return self.vehicle.receive(read.get_msgbuf(), now_s)
        if kind in _MISSION_UPLOADS:
            return self._emit([self._tx.mission_ack_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), _MSG.MAV_MISSION_DENIED,
                getattr(msg, "mission_type", 0))])
        return []

    def _refuse(self, name: str, why: str) -> None:
        if self.refused[name] == 0:
            self._log(f"drone {self.vehicle.drone_id}: refused {name} from the ground station "
                      f"({why}; later ones are counted)")
        self.refused[name] += 1


def _name(msg: Any) -> str:
    """``COMMAND_LONG 400`` for commands (their id), else the message's name."""
    kind = msg.get_type()
    return f"{kind} {msg.command}" if kind in _COMMANDS else kind
