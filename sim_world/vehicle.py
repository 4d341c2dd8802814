"""One emulated MAVLink 2 vehicle (PX4 or ArduCopter flavour) as a pure protocol state machine.

SPEC §12. No sockets and no clock of its own: every call that depends on time takes it
(``now_s``, seconds on any monotonic clock the caller chooses — sim time in lockstep, wall
time in realtime; it should not go backwards — a jump back only restarts the telemetry
schedule — so in lockstep keep one clock per vehicle that also advances before the mission
starts, e.g. wall time until then and that instant plus sim time after). Bytes in, bytes
out, so the same object is driven by ``sim-world`` in both time modes and by tests without
any network. Encoding and parsing use pymavlink's generated MAVLink 2 module
(``pymavlink.dialects.v20.ardupilotmega``); the per-step LOCAL_POSITION_NED out and setpoints
in go through ``swarm.mavlink.parse.FastFrame`` (pymavlink's formats and checksum,
byte-identical frames, without its per-byte parser). Not thread-safe.

Where the behaviour comes from: the real firmware, flown over its companion link by hand and
by ``tests/conformance`` (ArduCopter SITL at ArduPilot 90700977c5, PX4 v1.15.4 SIH, both in
``../shared/autopilots``). ``tests/conformance`` runs one scripted dialogue per flavour against
the real SITL and against this emulator and asserts the same answers; figures below marked
"measured" come from those flights. What is simplified is said where it is.

Vehicle ``drone_id`` is MAVLink system ``drone_id + 1``, component 1 (MAV_COMP_ID_AUTOPILOT1).

Public API
----------
``Flavour = Literal["px4", "ardupilot"]``, ``Start = Literal["air", "ground"]``;
``VehicleEndpoint`` (the UDP socket, defined in ``sim_world.mavlink_endpoint``) is re-exported.
``FlightModel`` (frozen dataclass: the measured timings and speeds of one flavour) with
``FLIGHT_MODELS[flavour]``; ``MEASURED_RESPONSE[flavour]``: the velocity response
(``swarm.models.kinematics.VelocityResponse``) fitted to each SITL's velocity steps.

``EmulatedVehicle(drone_id, flavour, position_w, origin_w, *, u_max_m_s=3.0,
setpoint_timeout_s=None, start="air", response=VelocityResponse(), flight_model=None,
datagram_framing=True, signing_key=None, signing_clock=time.time)``
    ``start``: "air" — armed and hovering at ``position_w`` (ardupilot GUIDED, px4 AUTO.LOITER
    "Hold", landed state IN_AIR): a vehicle already flown to its start position, no takeoff
    needed (a NAV_TAKEOFF there is FAILED on ardupilot, as on the real one); ``position_w``
    must be above the ground. "ground" — disarmed on the ground below ``position_w`` (its x, y
    at z = the ground), ardupilot in STABILIZE, px4 in AUTO.LOITER, landed state ON_GROUND.
    The ground is the plane z = ``origin_w[2]`` (the vehicle's local NED origin is its home on
    the ground): the vehicle never goes below it, and lands on it.
    ``response``: how the vehicle's velocity follows what its guidance commands, in both time
    modes (``VelocityResponse()``, the default, is ideal: v = u; ``MEASURED_RESPONSE`` holds
    the real firmware's). ``flight_model``: default ``FLIGHT_MODELS[flavour]``.
    ``setpoint_timeout_s``: setpoint-loss failsafe delay, default the firmware's: 1.0 s for px4
    (``COM_OF_LOSS_T``), 3.0 s for ardupilot (``GUID_TIMEOUT``); also readable and settable
    over MAVLink as that parameter.
    ``datagram_framing``: each ``receive()`` call is one UDP datagram, so bytes of an
    incomplete packet left at its end are counted as a truncated frame and dropped (they can
    never complete a packet); with False the input is a byte stream (serial/TCP) and a packet
    may span calls.
    ``signing_key``: the 32-byte MAVLink 2 signing secret (``swarm.mavlink.signing``; None:
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
    the reply packets (COMMAND_ACK, PARAM_VALUE, AUTOPILOT_VERSION, STATUSTEXT, ...; plus an
    immediate HEARTBEAT after a change of mode or arming). Never raises on bad input: each
    dropped frame (and an empty datagram) is counted in ``rejected_frames`` (reasons in
    ``rejections``); each frame a handler took (not rejected, not ignored) is counted in
    ``accepted_frames`` (``sim_world.fleet`` follows a new sender only when this grows:
    neither junk nor a stray valid frame the vehicle has no use for, e.g. a GCS heartbeat,
    redirects its stream).
``fly(dt_s, now_s)``
    Realtime: the vehicle flies itself for ``dt_s`` ending at ``now_s``: the guidance of its
    mode and state (setpoints, takeoff climb, hold, land, return, spool-up) gives a velocity
    command u, then ``swarm.models.kinematics.step_vehicle`` (u clamped to ±``u_max_m_s`` per
    axis, then ``response``), then the ground; then landing detection and auto-disarm.
``commanded_velocity_w(now_s) -> ndarray``
    Lockstep: the velocity the vehicle applies now for its last accepted setpoint, in W:
    ``clamp_velocity(frames.velocity_over_link(u), u_max)`` of a velocity setpoint ``u``
    (bit-exact), the velocity feed-forward of a position + velocity setpoint (lockstep
    integrates what the agent integrated; the position feedback is the realtime autopilot
    loop's business), the position loop's command for a position-only setpoint; zero when
    not ``accepting_setpoints`` or before any setpoint.
``begin_step(time_boot_ms)`` / ``setpoint_stamped(time_boot_ms=None) -> ndarray | None``
    Lockstep: ``begin_step`` forgets earlier stamped setpoints and records the awaited stamp
    (``awaited_stamp``); ``setpoint_stamped`` returns the applied velocity
    (``commanded_velocity_w`` evaluated when it arrived) of the setpoint whose
    ``time_boot_ms`` equals the stamp (default: the awaited one) and that arrived since
    ``begin_step``, else None. A setpoint the vehicle may not apply (disarmed, wrong mode,
    failsafe) still arrives, with velocity zero.
``integrate(dt_s, velocity_w)``
    Lockstep: ``(p, v) = step_vehicle(p, v, velocity_w, u_max, dt_s, response)`` (float64;
    with the ideal response exactly ``p + dt_s·velocity_w``, bit for bit the in-process
    reference), then the ground (z never below it). ``v`` is what LOCAL_POSITION_NED reports.
``heartbeat() -> bytes``
    One HEARTBEAT now; the caller sends one per second (SPEC: 1 Hz). telemetry() adds
    HEARTBEATs only if a client sets an interval for them (ardupilot; px4 refuses: FAILED).
    ``heartbeat_fields()``: its fields, and ``SYS_STATUS_SENSORS`` SYS_STATUS's, for the
    vehicle's other link (``sim_world.gcs_link``).
``telemetry(time_boot_ms, now_s) -> list[bytes]``
    The streams that are due: LOCAL_POSITION_NED (px4: on every call by default; ardupilot:
    only once requested), ATTITUDE (px4 10 Hz, ardupilot 1 Hz), SYS_STATUS and
    EXTENDED_SYS_STATE (1 Hz), and any STATUSTEXT the vehicle has to say (an auto-disarm).
    Rates follow MAV_CMD_SET_MESSAGE_INTERVAL (interval -1 disables, 0 restores the default —
    "every call" for LOCAL_POSITION_NED in both flavours —, > 0 sets the period; a period no
    longer than the call period means every call) and, ardupilot only, REQUEST_DATA_STREAM
    for messages without an explicit interval.
Read-only state: ``drone_id``, ``system_id``, ``flavour``, ``position_w`` (float64 truth,
a copy), ``reported_position_w`` (what LOCAL_POSITION_NED tells the agent, in W),
``origin_w``, ``ground_z_m``, ``velocity_w`` (last integrated), ``armed``, ``mode``
(pymavlink's name of the current mode, e.g. "OFFBOARD", "LOITER", "TAKEOFF", "LAND", "RTL",
"GUIDED", "BRAKE"), ``custom_mode``, ``landed_state`` (MAV_LANDED_STATE_*), ``in_setpoint_mode``,
``airborne``, ``failsafe_active``, ``accepting_setpoints``, ``awaited_stamp``, ``response``,
``flight_model``, ``setpoints_streaming(now_s)``, ``setpoint_timeout_s``, ``u_max_m_s``,
``params`` (name → value of the parameters it knows); counters ``rejected_frames``,
``rejections`` (reason → count), ``accepted_setpoints``, ``ignored_setpoints``,
``nonfinite_setpoints``, ``failsafe_events``, ``ignored_messages``; ``signing`` (bool) and
``authenticated_frames`` (frames accepted with a good signature: the caller follows a new
peer address only when this grows, see ``sim_world.fleet``).

Behaviour (PX4 / ArduCopter conventions, measured on the SITL builds)
---------------------------------------------------------------------
* HEARTBEAT: MAV_TYPE_QUADROTOR, autopilot MAV_AUTOPILOT_PX4 / MAV_AUTOPILOT_ARDUPILOTMEGA,
  base_mode = CUSTOM_MODE_ENABLED | SAFETY_ARMED when armed, system status ACTIVE when armed
  else STANDBY, custom_mode = current mode (px4: main mode in bits 16-23, sub mode in bits
  24-31: POSCTL 3, OFFBOARD 6, AUTO 4 with LOITER 3 = Hold, TAKEOFF 2, LAND 6, RTL 5;
  ArduCopter: the mode number: STABILIZE 0, ALT_HOLD 2, AUTO 3, GUIDED 4, LOITER 5, RTL 6,
  LAND 9, POSHOLD 16, BRAKE 17).
* Setpoints: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED, no force bit, the yaw and
  yaw-rate bits free (attitude is not modelled), one of: velocity only (type_mask 0x0DC7;
  also 0x01C7, 0x05C7, 0x09C7 — MAVSDK sends 0x09C7), position only (0x0DF8 and yaw
  variants), position + velocity (0x0DC0 ...), position + velocity + acceleration (0x0C00 ...;
  the acceleration feed-forward is accepted and not modelled). Any other frame or mask is
  rejected, and so is a setpoint with a non-finite used field (counted as
  ``nonfinite_setpoint``: never applied, never a proof of life). target_system must be this
  vehicle or 0, target_component 1 or 0. Guidance: velocity — that velocity; position —
  a position loop (gain ``FlightModel.position_gain_1_s``, decelerating at
  ``approach_accel_m_s2``); position + velocity — the velocity plus the position loop.
  ArduPilot moves the target of a position + velocity setpoint on with its velocity until
  the next one (measured: it keeps going for GUID_TIMEOUT), PX4 does not.
* px4 OFFBOARD: every valid setpoint is a proof of life; applied while armed in OFFBOARD.
  DO_SET_MODE OFFBOARD without a setpoint stream (≥ 2 in the last 0.5 s) is
  TEMPORARILY_REJECTED when armed and ACCEPTED when disarmed (measured; arming there is then
  TEMPORARILY_REJECTED until setpoints stream). No setpoint for ``COM_OF_LOSS_T`` while armed
  in OFFBOARD → failsafe: Hold (AUTO.LOITER, reported so; the swarm sets COM_OBL_RC_ACT = 5,
  the emulator always holds); when setpoints stream again the vehicle goes back to OFFBOARD
  by itself (measured: < 1 s), unless a mode was commanded meanwhile.
  Armed in OFFBOARD on the ground, a setpoint that asks to climb lifts off
  ``offboard_takeoff_delay_s`` after arming or after the request, whichever is later
  (measured: 1.2 s, then climbs to the target; landed state IN_AIR).
* ardupilot GUIDED: setpoints are ignored (``ignored_setpoints``) unless armed and in the air
  (taking off or flying); on the ground during a takeoff's spool-up one cancels the takeoff
  (measured: the vehicle never leaves the ground), during the climb it replaces the takeoff
  target (the vehicle stops climbing, IN_AIR). No setpoint with a velocity for
  ``GUID_TIMEOUT`` → failsafe: velocity zero (the vehicle stops; a position + velocity target
  is frozen where it had got to), mode stays GUIDED, armed; the next setpoint resumes.
  Position-only setpoints never time out. GUIDED without a setpoint holds the stopping point.
* Takeoff (MAV_CMD_NAV_TAKEOFF). ardupilot: param7 = altitude above home [m]; ACCEPTED only in
  GUIDED, armed, on the ground, with an altitude above it; else FAILED (in the air too).
  ``takeoff_delay_s`` of spool-up on the ground (landed state ON_GROUND), then a climb at
  ``takeoff_speed_m_s`` (TAKEOFF), IN_AIR within ``takeoff_done_m``, then hold (measured:
  3 s, 1.3 m/s peak, 0.05 m). px4: ACCEPTED (disarmed: mode AUTO.TAKEOFF on the ground, and
  arming then takes off, measured); mode AUTO.TAKEOFF to ``MIS_TAKEOFF_ALT`` above the ground — or
  above the current altitude in the air (measured: it climbs again) — or to param7 if finite
  (PX4 reads AMSL; the emulator has no geodetic frame and reads metres above its origin);
  from the ground ``takeoff_delay_s`` then a climb at ``takeoff_speed_m_s`` (landed state
  TAKEOFF from the command); within ``takeoff_done_m`` of the target: IN_AIR and Hold.
* Arming: ardupilot refuses (FAILED, with STATUSTEXT "Arm: <MODE> mode not armable" /
  "Arm: Mode requires mission") in LAND, RTL, BRAKE and AUTO; px4 refuses (TEMPORARILY_REJECTED)
  in OFFBOARD without a setpoint stream. Pre-arm checks are not modelled: the emulator is
  ready at once (the real ones: ArduCopter ~4 s at 10× boot speed, PX4 ~37 s).
  Disarming in the air: FAILED (ardupilot) / TEMPORARILY_REJECTED (px4), measured; on the
  ground ACCEPTED. Auto-disarm on the ground: ardupilot ``DISARM_DELAY`` (10 s) after arming
  or landing, ``landed_disarm_s`` after landing in LAND/RTL (measured 0.45 s); px4
  ``COM_DISARM_PRFLT`` (10 s) after arming without a takeoff, ``COM_DISARM_LAND`` (2 s) after
  landing — and px4 then goes back to the mode it was in before AUTO.LAND / AUTO.RTL
  (measured: OFFBOARD).
* Hold: ardupilot BRAKE (and GUIDED without a setpoint), px4 AUTO.LOITER: the vehicle heads
  for its stopping point p + v·τ (τ = ``stop_time_constant_s``) with gain 1/τ: its speed
  decays like e^(−t/τ) and it stays there (measured τ: BRAKE 1.3 s, Hold 0.45 s).
  ardupilot LOITER, POSHOLD, ALT_HOLD, STABILIZE in the air: no RC transmitter, so the
  throttle stick reads low: it sinks at ``pilot_sink_m_s`` (measured 2.5 m/s) and lands.
  px4 POSCTL: TEMPORARILY_REJECTED (no manual control, measured).
* Land (ardupilot LAND, px4 AUTO.LAND; also MAV_CMD_NAV_LAND): landed state LANDING, holds
  its stopping point horizontally and descends (ardupilot ``LAND_SPEED`` 0.5 m/s below 10 m,
  ``WPNAV_SPEED_DN`` above; px4 ``MPC_LAND_SPEED`` 0.7 m/s below 5 m, 1.5 m/s above 10 m,
  linear between), touches down, ON_GROUND ``land_detect_s`` later, then auto-disarm.
* Return (ardupilot RTL, px4 AUTO.RTL; also MAV_CMD_NAV_RETURN_TO_LAUNCH): climb to the return
  altitude (ardupilot: max(RTL_ALT, current) reduced near home by RTL_CONE_SLOPE, at
  WPNAV_SPEED_UP; px4: RTL_RETURN_ALT above home if lower, at 3 m/s), fly home (the origin's
  x, y), wait (ardupilot RTL_LOIT_TIME; px4 RTL_LAND_DELAY, < 0 forever; px4 first descends
  to RTL_DESCEND_ALT at 1.5 m/s), then land as above (landed state LANDING only then).
* Commands (COMMAND_LONG or COMMAND_INT): ARM_DISARM (400), DO_SET_MODE (176; param1 must
  have CUSTOM_MODE_ENABLED), NAV_TAKEOFF (22), NAV_LAND (21), NAV_RETURN_TO_LAUNCH (20),
  SET/GET_MESSAGE_INTERVAL (511/510), REQUEST_MESSAGE (512: AUTOPILOT_VERSION, HEARTBEAT,
  LOCAL_POSITION_NED, ATTITUDE, SYS_STATUS, EXTENDED_SYS_STATE), REQUEST_AUTOPILOT_CAPABILITIES
  (520); anything else gets MAV_RESULT_UNSUPPORTED. The legacy SET_MODE message is
  acknowledged with command = 11. Unknown modes: DENIED (px4), FAILED (ardupilot, measured);
  ardupilot AUTO (no mission) is accepted only while disarmed.
* Parameters (PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET, the firmware's defaults
  and types; the setpoint timeout first): ardupilot GUID_TIMEOUT, RTL_ALT [cm], RTL_LOIT_TIME
  [ms], RTL_CONE_SLOPE, LAND_SPEED [cm/s], WPNAV_SPEED_UP, WPNAV_SPEED_DN [cm/s],
  DISARM_DELAY [s]; px4 COM_OF_LOSS_T, COM_DISARM_LAND, COM_DISARM_PRFLT, MIS_TAKEOFF_ALT,
  MPC_LAND_SPEED, RTL_RETURN_ALT, RTL_DESCEND_ALT, RTL_LAND_DELAY. Also MISSION_REQUEST_LIST
  → MISSION_COUNT 0, TIMESYNC answered (tc1 = now in ns).
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sim_world.mavlink_endpoint import VehicleEndpoint
from swarm.mavlink.parse import LOCAL_POSITION_NED, SET_POSITION_TARGET_LOCAL_NED, parse_bytes
from swarm.mavlink.signing import enable_signing, refresh_signing_timestamp
from swarm.models import frames
from swarm.models.kinematics import (
    ARDUCOPTER_SITL_RESPONSE,
    PX4_SITL_RESPONSE,
    VelocityResponse,
    clamp_velocity,
    step_vehicle,
)

Array = NDArray[np.float64]
Flavour = Literal["px4", "ardupilot"]
Start = Literal["air", "ground"]

__all__ = [
    "AUTOPILOT_COMPONENT_ID",
    "FLIGHT_MODELS",
    "MEASURED_RESPONSE",
    "SYS_STATUS_SENSORS",
    "EmulatedVehicle",
    "Flavour",
    "FlightModel",
    "PacketCollector",
    "Start",
    "VehicleEndpoint",
]

AUTOPILOT_COMPONENT_ID = 1
_SIGNING_LINK_ID = 0  # the autopilot's MAVLink channel 0
_MSG = mavlink2

# --- modes -----------------------------------------------------------------------------------
# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h).
_PX4_MAIN_POSCTL, _PX4_MAIN_AUTO, _PX4_MAIN_OFFBOARD = 3, 4, 6


def _px4_custom_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


# Names as pymavlink's mode_string_v10 gives them.
_PX4_MODES: dict[str, int] = {
    "POSCTL": _px4_custom_mode(_PX4_MAIN_POSCTL),
    "OFFBOARD": _px4_custom_mode(_PX4_MAIN_OFFBOARD),
    "LOITER": _px4_custom_mode(_PX4_MAIN_AUTO, 3),  # AUTO.LOITER, "Hold"
    "TAKEOFF": _px4_custom_mode(_PX4_MAIN_AUTO, 2),
    "LAND": _px4_custom_mode(_PX4_MAIN_AUTO, 6),
    "RTL": _px4_custom_mode(_PX4_MAIN_AUTO, 5),
}
_ACM_MODES: dict[str, int] = {
    "STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9,
    "POSHOLD": 16, "BRAKE": 17,
}
_ACM_PILOT_MODES = frozenset({"STABILIZE", "ALT_HOLD", "LOITER", "POSHOLD"})
_ACM_NOT_ARMABLE = frozenset({"LAND", "RTL", "BRAKE"})
_SETPOINT_MODE = {"px4": "OFFBOARD", "ardupilot": "GUIDED"}
_GROUND_MODE = {"px4": "LOITER", "ardupilot": "STABILIZE"}
_AIR_MODE = {"px4": "LOITER", "ardupilot": "GUIDED"}
_TIMEOUT_PARAM = {"px4": "COM_OF_LOSS_T", "ardupilot": "GUID_TIMEOUT"}

_ON_GROUND = _MSG.MAV_LANDED_STATE_ON_GROUND
_IN_AIR = _MSG.MAV_LANDED_STATE_IN_AIR
_TAKING_OFF = _MSG.MAV_LANDED_STATE_TAKEOFF
_LANDING = _MSG.MAV_LANDED_STATE_LANDING

# --- parameters ------------------------------------------------------------------------------
# The firmware's defaults and MAVLink types (ArduCopter reports integers C-cast, as floats).
_REAL32, _INT32, _INT16, _INT8 = (_MSG.MAV_PARAM_TYPE_REAL32, _MSG.MAV_PARAM_TYPE_INT32,
                                  _MSG.MAV_PARAM_TYPE_INT16, _MSG.MAV_PARAM_TYPE_INT8)


@dataclass(frozen=True)
class _ParamSpec:
    default: float
    mav_type: int
    minimum: float  # a PARAM_SET below this (or not finite) leaves the value unchanged
    positive: bool = False  # the value must be > minimum


_PARAMS: dict[str, dict[str, _ParamSpec]] = {
    "ardupilot": {
        "GUID_TIMEOUT": _ParamSpec(3.0, _REAL32, 0.0, positive=True),
        "RTL_ALT": _ParamSpec(1500, _INT32, 200),  # [cm]; ArduCopter's RTL_ALT_MIN
        "RTL_LOIT_TIME": _ParamSpec(5000, _INT32, 0),  # [ms]
        "RTL_CONE_SLOPE": _ParamSpec(3.0, _REAL32, 0.0),
        "LAND_SPEED": _ParamSpec(50, _INT16, 30),  # [cm/s]
        "WPNAV_SPEED_UP": _ParamSpec(250.0, _REAL32, 10.0),  # [cm/s]
        "WPNAV_SPEED_DN": _ParamSpec(150.0, _REAL32, 10.0),  # [cm/s]
        "DISARM_DELAY": _ParamSpec(10, _INT8, 0),  # [s]; 0: never
    },
    "px4": {
        "COM_OF_LOSS_T": _ParamSpec(1.0, _REAL32, 0.0, positive=True),
        "COM_DISARM_LAND": _ParamSpec(2.0, _REAL32, -1.0),  # ≤ 0: never
        "COM_DISARM_PRFLT": _ParamSpec(10.0, _REAL32, -1.0),  # ≤ 0: never
        "MIS_TAKEOFF_ALT": _ParamSpec(2.5, _REAL32, 0.0),
        "MPC_LAND_SPEED": _ParamSpec(0.7, _REAL32, 0.1),
        "RTL_RETURN_ALT": _ParamSpec(30.0, _REAL32, 0.0),
        "RTL_DESCEND_ALT": _ParamSpec(10.0, _REAL32, 0.0),
        "RTL_LAND_DELAY": _ParamSpec(0.0, _REAL32, -1.0),
    },
}


# --- flight ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class FlightModel:
    """Timings and speeds of one firmware's automatic flight, as measured on its SITL build
    (the figures of ``FLIGHT_MODELS``; see the module docstring). Speeds that the firmware
    takes from a parameter are parameters of the vehicle instead (``params``)."""

    takeoff_delay_s: float  # takeoff accepted on the ground → leaves it (spool-up) [s]
    offboard_takeoff_delay_s: float  # px4: armed in OFFBOARD, asked to climb → leaves [s]
    takeoff_speed_m_s: float  # climb rate of a takeoff [m/s]
    takeoff_done_m: float  # a takeoff is over this close to its altitude [m]
    position_gain_1_s: float  # position loop of position setpoints and returns [1/s]
    approach_accel_m_s2: float  # deceleration towards a position target [m/s²]
    stop_time_constant_s: float  # τ of a hold/brake: speed decays as e^(−t/τ) [s]
    land_detect_s: float  # touchdown → landed state ON_GROUND [s]
    landed_disarm_s: float  # ardupilot: ON_GROUND after LAND/RTL → disarmed [s]
    pilot_sink_m_s: float  # ardupilot pilot modes without RC: sink rate [m/s]
    land_fast_m_s: float  # descent of a landing above land_slow_below_m [m/s]
    land_slow_below_m: float  # below this height a landing descends at the land speed [m]
    land_fast_above_m: float  # above this height at land_fast_m_s (px4: linear between) [m]
    return_climb_m_s: float  # px4 RTL climb (ardupilot: WPNAV_SPEED_UP) [m/s]
    return_descent_m_s: float  # px4 RTL descent to RTL_DESCEND_ALT [m/s]
    return_speed_m_s: float  # horizontal speed limit of a return [m/s]

    def __post_init__(self) -> None:
        for name, value in vars(self).items():
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"FlightModel.{name} must be a finite number >= 0, "
                                 f"got {value}")
        for name in ("position_gain_1_s", "approach_accel_m_s2", "stop_time_constant_s",
                     "takeoff_speed_m_s", "takeoff_done_m"):
            if getattr(self, name) <= 0.0:
                raise ValueError(f"FlightModel.{name} must be > 0, got {getattr(self, name)}")


FLIGHT_MODELS: Final[dict[Flavour, FlightModel]] = {
    # ArduCopter SITL (tests/conformance, ../shared/autopilots/ardupilot): takeoff ACK → climb
    # 2.97-3.1 s, climb peaking 1.31-1.37 m/s, IN_AIR 0.05 m below the target; BRAKE from
    # 2 m/s: speed ×0.83 per 0.25 s (τ ≈ 1.3 s), at rest 2.3-2.8 m further; touchdown →
    # ON_GROUND 1.65-1.7 s → disarmed 0.43-0.48 s (LAND, RTL); LOITER without RC sinks at
    # PILOT_SPEED_UP 2.5 m/s; RTL returns at ≤ 2.4 m/s over 8 m; LAND_ALT_LOW 10 m.
    "ardupilot": FlightModel(
        takeoff_delay_s=3.0, offboard_takeoff_delay_s=0.0, takeoff_speed_m_s=1.3,
        takeoff_done_m=0.1, position_gain_1_s=1.0, approach_accel_m_s2=1.0,
        stop_time_constant_s=1.3, land_detect_s=1.7, landed_disarm_s=0.45,
        pilot_sink_m_s=2.5, land_fast_m_s=1.5, land_slow_below_m=10.0, land_fast_above_m=10.0,
        return_climb_m_s=2.5, return_descent_m_s=1.5, return_speed_m_s=10.0),
    # PX4 v1.15.4 SIH: AUTO.TAKEOFF command → climb 3.5-4 s at ≤ 1.0 m/s, Hold 0.5 m below the
    # target; armed in OFFBOARD with a position 2.5 m up → IN_AIR 1.2 s after arming; Hold from
    # 1.5 m/s at rest within ~1 s (τ ≈ 0.45 s); landed → ON_GROUND 1.7 s (RTL); land speed
    # MPC_LAND_SPEED below MPC_LAND_ALT2 = 5 m, MPC_Z_V_AUTO_DN 1.5 m/s above MPC_LAND_ALT1
    # = 10 m; RTL climbs at MPC_Z_V_AUTO_UP 3 m/s, returns at ≤ 3 m/s.
    "px4": FlightModel(
        takeoff_delay_s=3.5, offboard_takeoff_delay_s=1.2, takeoff_speed_m_s=1.0,
        takeoff_done_m=0.5, position_gain_1_s=1.0, approach_accel_m_s2=1.0,
        stop_time_constant_s=0.45, land_detect_s=2.0, landed_disarm_s=0.0,
        pilot_sink_m_s=0.0, land_fast_m_s=1.5, land_slow_below_m=5.0, land_fast_above_m=10.0,
        return_climb_m_s=3.0, return_descent_m_s=1.5, return_speed_m_s=5.0),
}

# τ and a_max of ``swarm.models.kinematics.VelocityResponse`` fitted (all three axes together) to
# each SITL's velocity steps by benchmarks/fit_vehicle_response.py.
MEASURED_RESPONSE: Final[dict[Flavour, VelocityResponse]] = {
    "ardupilot": ARDUCOPTER_SITL_RESPONSE, "px4": PX4_SITL_RESPONSE}

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

STREAM_WINDOW_S = 0.5  # px4: "streaming" = at least STREAM_MIN_COUNT setpoints in this window
STREAM_MIN_COUNT = 2
_CLIMB_REQUEST_M_S = 0.2  # px4 on the ground in OFFBOARD: a command this fast up lifts off
_ARRIVED_M = 0.2  # a return is home this close (horizontally) [m]

# --- telemetry streams ------------------------------------------------------------------------
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
_MAX_PENDING_TEXTS = 8

_SENSORS = (_MSG.MAV_SYS_STATUS_SENSOR_3D_GYRO | _MSG.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | _MSG.MAV_SYS_STATUS_SENSOR_3D_MAG | _MSG.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | _MSG.MAV_SYS_STATUS_SENSOR_GPS | _MSG.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
# SYS_STATUS's fields (every link): sensors present, enabled and healthy; load 10 %; 16.2 V,
# current unknown, 100 % battery; no errors.
SYS_STATUS_SENSORS = (_SENSORS, _SENSORS, _SENSORS, 100, 16200, -1, 100, 0, 0, 0, 0, 0, 0)
_MAX_STAMPED = 256
_ZERO3 = np.zeros(3)


@dataclass
class _Stream:
    interval_s: float | None  # None: off; EVERY_CALL: every call; > 0: period
    explicit: bool = False  # set by SET_MESSAGE_INTERVAL (wins over REQUEST_DATA_STREAM)
    next_due_s: float | None = None
    last_sent_s: float | None = None


@dataclass(frozen=True)
class _Setpoint:
    """One accepted SET_POSITION_TARGET_LOCAL_NED, in W (values as decoded: float32)."""

    position_w: Array | None
    velocity_w: Array | None  # clamp_velocity(ned_to_enu(v)) of the decoded velocity
    arrived_s: float


@dataclass
class _Climb:
    """A takeoff: climb to ``target_w`` (x, y: where it started) once ``liftoff_s`` passed."""

    target_w: Array
    liftoff_s: float | None  # None: already off the ground


@dataclass
class _Return:
    phase: Literal["climb", "return", "wait", "descend", "land"]
    altitude_z_m: float  # return altitude (W z)
    since_s: float  # start of the phase


class PacketCollector:
    """File-like sink for pymavlink's MAVLink.send(): keeps the packed packets."""

    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, buf: bytes | bytearray) -> None:
        self.packets.append(bytes(buf))


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _approach_speed(distance_m: float, speed_max_m_s: float, gain_1_s: float,
                    accel_m_s2: float) -> float:
    """Speed towards a target ``distance_m`` away: the position loop (gain·d) near it, the
    speed from which ``accel_m_s2`` stops in d (√(2·a·d)) further out, at most the limit."""
    return min(speed_max_m_s, gain_1_s * distance_m, math.sqrt(2.0 * accel_m_s2 * distance_m))


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
        start: Start = "air",
        response: VelocityResponse = VelocityResponse(),  # noqa: B008 (frozen, immutable)
        flight_model: FlightModel | None = None,
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
        if start not in ("air", "ground"):
            raise ValueError(f"start must be 'air' or 'ground', got {start!r}")
        if not isinstance(response, VelocityResponse):
            raise ValueError(f"response must be a VelocityResponse, got {response!r}")
        position = np.array(position_w, dtype=np.float64).reshape(3).copy()
        origin = np.array(origin_w, dtype=np.float64).reshape(3).copy()
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(origin))):
            raise ValueError("position_w and origin_w must be finite")
        if start == "air" and not position[2] > origin[2]:
            raise ValueError(f"start='air' needs position_w above the ground z = origin_w[2] = "
                             f"{origin[2]:g} m, got z = {position[2]:g} m; use start='ground'")
        self._drone_id = int(drone_id)
        self._sysid = self._drone_id + 1
        self._flavour: Flavour = flavour
        self._origin = origin
        self._origin_xyz = frames.as_xyz(origin, "origin_w")
        self._u_max = float(u_max_m_s)
        self._response = response
        self._flight = FLIGHT_MODELS[flavour] if flight_model is None else flight_model
        self._datagram_framing = bool(datagram_framing)

        self._param_specs = _PARAMS[flavour]
        self._params = {name: float(spec.default) for name, spec in self._param_specs.items()}
        if setpoint_timeout_s is not None:
            timeout = float(setpoint_timeout_s)
            if not (math.isfinite(timeout) and timeout > 0):
                raise ValueError(f"setpoint_timeout_s must be finite and > 0, got {timeout}")
            self._params[_TIMEOUT_PARAM[flavour]] = timeout

        self._modes = _PX4_MODES if flavour == "px4" else _ACM_MODES
        self._velocity = np.zeros(3)
        if start == "air":
            self._position = position
            self._armed = True
            self._mode = _AIR_MODE[flavour]
            self._landed = _IN_AIR
            self._on_ground = False
        else:
            position[2] = origin[2]
            self._position = position
            self._armed = False
            self._mode = _GROUND_MODE[flavour]
            self._landed = _ON_GROUND
            self._on_ground = True  # resting on it (px4 reports TAKEOFF while spooling up)
        self._hold_w = self._position.copy()  # where a hold holds
        self._failsafe = False
        self._resume_offboard = False  # px4: failsafe hold that ends when setpoints return
        self._mode_before_auto: str | None = None  # px4: mode before AUTO.LAND / AUTO.RTL
        self._takeoff_altitude_m = math.nan  # px4: param7 of a NAV_TAKEOFF while disarmed
        self._climb: _Climb | None = None
        self._return: _Return | None = None
        self._liftoff_s: float | None = None  # px4 OFFBOARD on the ground: leaves it then
        self._armed_s = -math.inf  # when it was last armed
        self._touchdown_s: float | None = None  # on the ground, not yet detected as landed
        self._ground_since_s: float | None = None  # armed on the ground (auto-disarm timer)
        self._ground_disarm_s = math.inf  # ... disarms after this long

        self._setpoint: _Setpoint | None = None
        self._last_setpoint_s: float | None = None  # last accepted (applied-kind) setpoint
        self._arrivals: deque[float] = deque(maxlen=16)  # arrival times of valid setpoints
        self._stamped: dict[int, Array] = {}
        self._awaited_stamp: int | None = None
        self._last_time_boot_ms = 0
        self._texts: deque[tuple[int, str]] = deque(maxlen=_MAX_PENDING_TEXTS)

        self._streams = {name: _Stream(_DEFAULT_INTERVAL_S[flavour][name])
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
    def reported_position_w(self) -> Array:
        """The W-position an agent reads from this vehicle's LOCAL_POSITION_NED now: its
        position as the float32 local NED the stream carries (``_local_position_fields``),
        converted back (``frames.position_over_link``)."""
        return frames.position_over_link(self._position, self._origin)

    @property
    def origin_w(self) -> Array:
        return self._origin.copy()

    @property
    def ground_z_m(self) -> float:
        """The ground: the plane z = origin_w[2] of W."""
        return float(self._origin[2])

    @property
    def velocity_w(self) -> Array:
        return self._velocity.copy()

    @property
    def u_max_m_s(self) -> float:
        return self._u_max

    @property
    def response(self) -> VelocityResponse:
        return self._response

    @property
    def flight_model(self) -> FlightModel:
        return self._flight

    @property
    def setpoint_timeout_s(self) -> float:
        return self._params[_TIMEOUT_PARAM[self._flavour]]

    @property
    def params(self) -> dict[str, float]:
        return dict(self._params)

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
    def landed_state(self) -> int:
        """MAV_LANDED_STATE_*: ON_GROUND, TAKEOFF, IN_AIR or LANDING (EXTENDED_SYS_STATE)."""
        return self._landed

    @property
    def in_setpoint_mode(self) -> bool:
        return self._mode == _SETPOINT_MODE[self._flavour]

    @property
    def airborne(self) -> bool:
        """Off the ground: climbing after a takeoff, flying or landing (not spooling up)."""
        return not self._on_ground

    @property
    def failsafe_active(self) -> bool:
        return self._failsafe

    @property
    def accepting_setpoints(self) -> bool:
        """A setpoint arriving now would be applied: armed, in the setpoint mode, not in
        failsafe, and (ardupilot) in the air. "Ready for the mission" is this and
        ``setpoints_streaming(now_s)``."""
        if not (self._armed and self.in_setpoint_mode and not self._failsafe):
            return False
        return self._flavour == "px4" or not self._on_ground

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

    # ---------------------------------------------------------------- lockstep
    def commanded_velocity_w(self, now_s: float) -> Array:
        self._update(now_s)
        setpoint = self._setpoint
        if setpoint is None or not self.accepting_setpoints:
            return np.zeros(3)
        if setpoint.velocity_w is not None:
            return setpoint.velocity_w.copy()
        return self._setpoint_command(setpoint, now_s)

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
        command = np.asarray(velocity_w, dtype=np.float64).reshape(3)
        self._position, self._velocity = step_vehicle(self._position, self._velocity, command,
                                                      self._u_max, dt_s, self._response)
        self._clamp_to_ground()

    # ---------------------------------------------------------------- realtime
    def fly(self, dt_s: float, now_s: float) -> None:
        """Fly for ``dt_s`` (ending at ``now_s``) as the mode and state say (module doc)."""
        self._update(now_s)
        if self._on_ground:
            self._velocity = np.zeros(3)
            if not self._leaves_ground(now_s):
                return
        command = self._guidance(now_s)
        self._position, self._velocity = step_vehicle(self._position, self._velocity, command,
                                                      self._u_max, dt_s, self._response)
        on_ground = self._clamp_to_ground()
        if on_ground and command[2] < 0.0:
            if self._touchdown_s is None:
                self._touchdown_s = now_s
        elif not on_ground:
            self._touchdown_s = None
        self._progress(now_s)

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
        if self._texts:
            packets += self._emit([self._statustext_msg(severity, text)
                                   for severity, text in self._texts])
            self._texts.clear()
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

    def _say(self, text: str, severity: int = _MSG.MAV_SEVERITY_INFO) -> None:
        """A STATUSTEXT for the next telemetry() (ArduPilot's way of saying why)."""
        if self._flavour == "ardupilot":
            self._texts.append((severity, text))

    def _param(self, name: str) -> float:
        return self._params[name]

    # --- time-driven state ---
    def _update(self, now_s: float) -> None:
        """Everything that happens with time alone: setpoint-loss failsafes (and px4's way
        back), spool-up, landing detection, auto-disarm."""
        self._update_failsafe(now_s)
        climb = self._climb
        if (climb is not None and climb.liftoff_s is not None and now_s >= climb.liftoff_s
                and self._on_ground and self._armed):
            climb.liftoff_s = None
            self._on_ground = False
            self._landed = _TAKING_OFF
            self._ground_since_s = None
        if (self._touchdown_s is not None and not self._on_ground
                and now_s - self._touchdown_s >= self._flight.land_detect_s):
            self._land_detected(now_s)
        if (self._armed and self._on_ground and self._ground_since_s is not None
                and now_s - self._ground_since_s >= self._ground_disarm_s):
            self._disarm()

    def _update_failsafe(self, now_s: float) -> None:
        if self._flavour == "px4":
            if self._failsafe and self._resume_offboard and self.setpoints_streaming(now_s):
                self._failsafe = self._resume_offboard = False  # offboard signal is back
                self._mode = "OFFBOARD"
                return
            if not self.in_setpoint_mode or self._failsafe or not self._armed:
                return
            last = self._last_setpoint_s
            if last is None or now_s - last > self.setpoint_timeout_s:
                self._failsafe = self._resume_offboard = True
                self._enter_hold()
                self._mode = "LOITER"
                self.failsafe_events += 1
            return
        setpoint = self._setpoint
        if (self.in_setpoint_mode and not self._failsafe and self._armed
                and not self._on_ground and setpoint is not None
                and setpoint.velocity_w is not None
                and now_s - setpoint.arrived_s > self.setpoint_timeout_s):
            # GUIDED: velocity zero, mode unchanged; a position + velocity target stays where
            # it had moved to by the timeout.
            self._failsafe = True
            if setpoint.position_w is not None:
                moved = setpoint.position_w + self.setpoint_timeout_s * setpoint.velocity_w
                self._setpoint = _Setpoint(moved, None, setpoint.arrived_s)
            else:
                self._setpoint = None
            self.failsafe_events += 1

    def _land_detected(self, now_s: float) -> None:
        self._landed = _ON_GROUND
        self._on_ground = True
        self._touchdown_s = None
        self._velocity = np.zeros(3)
        self._position[2] = self._origin[2]
        self._climb = self._return = None
        self._liftoff_s = None
        self._failsafe = False
        if self._flavour == "ardupilot":
            self._setpoint = None  # a new takeoff (and setpoints after it) is needed
        self._hold_w = self._position.copy()
        if self._armed:
            self._start_ground_timer(now_s, landed=True)

    def _start_ground_timer(self, now_s: float, *, landed: bool) -> None:
        """Auto-disarm on the ground: after arming, or after landing (module doc)."""
        self._ground_since_s = now_s
        if self._flavour == "ardupilot":
            if landed and self._mode in ("LAND", "RTL"):
                self._ground_disarm_s = self._flight.landed_disarm_s
                return
            delay = self._param("DISARM_DELAY")
        else:
            delay = self._param("COM_DISARM_LAND" if landed else "COM_DISARM_PRFLT")
        self._ground_disarm_s = delay if delay > 0.0 else math.inf  # 0 (px4: < 0): never

    def _disarm(self) -> None:
        self._armed = False
        if self._on_ground:
            self._landed = _ON_GROUND  # px4: no longer "taking off" while spooling up
        self._ground_since_s = None
        self._climb = self._return = None
        self._liftoff_s = None
        self._failsafe = self._resume_offboard = False
        if self._flavour == "ardupilot":
            self._setpoint = None
            self._last_setpoint_s = None
            self._say("Disarming motors")
        elif self._mode in ("LAND", "RTL") and self._mode_before_auto is not None:
            self._mode = self._mode_before_auto  # measured: PX4 goes back (OFFBOARD)
        self._mode_before_auto = None

    def _clamp_to_ground(self) -> bool:
        """Keep z ≥ the ground; True when on it."""
        ground = self._origin[2]
        if self._position[2] > ground:
            return False
        if self._position[2] < ground:
            self._position[2] = ground
            if self._velocity[2] < 0.0:
                self._velocity[2] = 0.0
        return True

    # --- guidance ---
    def _leaves_ground(self, now_s: float) -> bool:
        """On the ground: whether it lifts off now (takeoff climb after its spool-up, or px4
        asked to climb in OFFBOARD)."""
        if not self._armed:
            return False
        if self._climb is not None:
            return self._climb.liftoff_s is None
        if not (self._flavour == "px4" and self.in_setpoint_mode and not self._failsafe
                and self._setpoint is not None):
            self._liftoff_s = None
            return False
        if self._setpoint_command(self._setpoint, now_s)[2] <= _CLIMB_REQUEST_M_S:
            self._liftoff_s = None
            return False
        if self._liftoff_s is None:
            self._liftoff_s = max(now_s, self._armed_s) + self._flight.offboard_takeoff_delay_s
        if now_s < self._liftoff_s:
            return False
        self._liftoff_s = None
        self._on_ground = False
        self._landed = _IN_AIR
        self._ground_since_s = None
        return True

    def _guidance(self, now_s: float) -> Array:
        """Velocity command in W of the current mode and state (off the ground)."""
        mode = self._mode
        if self._climb is not None:
            return self._climb_command(self._climb)
        if mode == "LAND":
            return self._land_command()
        if mode == "RTL":
            return self._return_command(now_s)
        if mode == _SETPOINT_MODE[self._flavour]:
            if self._setpoint is not None:
                return self._setpoint_command(self._setpoint, now_s)
            if self._failsafe:
                return np.zeros(3)  # ardupilot GUID_TIMEOUT: velocity zero
            return self._hold_command()
        if self._flavour == "ardupilot" and mode in _ACM_PILOT_MODES:
            command = self._hold_command()
            command[2] = -self._flight.pilot_sink_m_s  # no RC: throttle stick reads low
            return command
        return self._hold_command()  # BRAKE, AUTO, Hold, POSCTL

    def _setpoint_command(self, setpoint: _Setpoint, now_s: float) -> Array:
        if setpoint.position_w is None:
            assert setpoint.velocity_w is not None
            return setpoint.velocity_w  # bit-exact: what arrived, clamped
        target = setpoint.position_w
        feed_forward = _ZERO3 if setpoint.velocity_w is None else setpoint.velocity_w
        if self._flavour == "ardupilot" and setpoint.velocity_w is not None:
            target = target + max(0.0, now_s - setpoint.arrived_s) * setpoint.velocity_w
        return clamp_velocity(feed_forward + self._towards(target, self._u_max), self._u_max)

    def _towards(self, target_w: Array, speed_max_m_s: float) -> Array:
        """Position loop towards ``target_w`` (``_approach_speed`` along the error)."""
        error = target_w - self._position
        distance = math.sqrt(float(error @ error))
        if distance == 0.0:
            return np.zeros(3)
        flight = self._flight
        speed = _approach_speed(distance, speed_max_m_s, flight.position_gain_1_s,
                                flight.approach_accel_m_s2)
        return error * (speed / distance)

    def _hold_command(self) -> Array:
        return (self._hold_w - self._position) / self._flight.stop_time_constant_s

    def _enter_hold(self) -> None:
        """Hold the stopping point p + v·τ (speed then decays as e^(−t/τ))."""
        if self._on_ground:
            self._hold_w = self._position.copy()
        else:
            self._hold_w = self._position + self._flight.stop_time_constant_s * self._velocity

    def _climb_command(self, climb: _Climb) -> Array:
        command = self._hold_command()
        flight = self._flight
        error = float(climb.target_w[2] - self._position[2])
        command[2] = math.copysign(_approach_speed(abs(error), flight.takeoff_speed_m_s,
                                                   flight.position_gain_1_s,
                                                   flight.approach_accel_m_s2), error)
        return command

    def _land_speed(self) -> float:
        height = float(self._position[2] - self._origin[2])
        flight = self._flight
        slow = (self._param("LAND_SPEED") / 100.0 if self._flavour == "ardupilot"
                else self._param("MPC_LAND_SPEED"))
        fast = (self._param("WPNAV_SPEED_DN") / 100.0 if self._flavour == "ardupilot"
                else flight.land_fast_m_s)
        if height <= flight.land_slow_below_m:
            return slow
        if height >= flight.land_fast_above_m or flight.land_fast_above_m <= \
                flight.land_slow_below_m:
            return fast
        share = (height - flight.land_slow_below_m) / (flight.land_fast_above_m
                                                       - flight.land_slow_below_m)
        return slow + share * (fast - slow)

    def _land_command(self) -> Array:
        command = self._hold_command()
        command[2] = -self._land_speed()
        return command

    def _return_command(self, now_s: float) -> Array:
        ret = self._return
        if ret is None:  # entered on the ground
            return self._hold_command()
        flight = self._flight
        home = np.array([self._origin[0], self._origin[1], ret.altitude_z_m])
        if ret.phase == "climb":
            command = self._hold_command()
            speed = (self._param("WPNAV_SPEED_UP") / 100.0 if self._flavour == "ardupilot"
                     else flight.return_climb_m_s)
            error = ret.altitude_z_m - float(self._position[2])
            command[2] = math.copysign(_approach_speed(abs(error), speed,
                                                       flight.position_gain_1_s,
                                                       flight.approach_accel_m_s2), error)
            return command
        if ret.phase == "return":
            return self._towards(home, flight.return_speed_m_s)
        if ret.phase == "descend":
            command = self._hold_command()
            error = ret.altitude_z_m - float(self._position[2])
            command[2] = math.copysign(_approach_speed(abs(error), flight.return_descent_m_s,
                                                       flight.position_gain_1_s,
                                                       flight.approach_accel_m_s2), error)
            return command
        if ret.phase == "land":
            return self._land_command()
        return self._hold_command()  # wait

    def _progress(self, now_s: float) -> None:
        """Position-driven transitions after a move: a takeoff done, a return's phases."""
        climb = self._climb
        if (climb is not None and climb.liftoff_s is None and abs(
                float(climb.target_w[2] - self._position[2])) <= self._flight.takeoff_done_m):
            self._climb = None
            self._landed = _IN_AIR
            self._hold_w = climb.target_w.copy()
            if self._flavour == "px4" and self._mode == "TAKEOFF":
                self._mode = "LOITER"  # PX4 holds after AUTO.TAKEOFF
        ret = self._return
        if ret is None or self._mode != "RTL":
            return
        if ret.phase == "climb" and self._position[2] >= ret.altitude_z_m - 0.1:
            self._next_phase(ret, "return", now_s)
        elif ret.phase == "return":
            offset = self._position[:2] - self._origin[:2]
            if math.hypot(float(offset[0]), float(offset[1])) <= _ARRIVED_M:
                self._next_phase(ret, "wait", now_s)
        elif ret.phase == "wait":
            if self._flavour == "ardupilot":
                wait_s = self._param("RTL_LOIT_TIME") / 1000.0
            else:
                wait_s = self._param("RTL_LAND_DELAY")
                descend_z = self._origin[2] + self._param("RTL_DESCEND_ALT")
                if self._position[2] > descend_z + 0.1:
                    ret.altitude_z_m = float(descend_z)
                    self._next_phase(ret, "descend", now_s)
                    return
                if wait_s < 0.0:
                    return  # RTL_LAND_DELAY < 0: hover at RTL_DESCEND_ALT for ever
            if now_s - ret.since_s >= wait_s:
                self._next_phase(ret, "land", now_s)
        elif ret.phase == "descend" and self._position[2] <= ret.altitude_z_m + 0.1:
            self._next_phase(ret, "wait", now_s)

    def _next_phase(self, ret: _Return, phase: Literal["climb", "return", "wait", "descend",
                                                      "land"], now_s: float) -> None:
        ret.phase = phase
        ret.since_s = now_s
        self._hold_w = self._position.copy()
        if phase == "land":
            self._landed = _LANDING

    def _return_altitude_z(self) -> float:
        """W z of the return: ArduCopter's max(RTL_ALT, current) with the cone near home
        (mode_rtl.cpp: at most RTL_CONE_SLOPE × distance, at least 2.5 m of climb); PX4's
        RTL_RETURN_ALT above home, or the current altitude when higher."""
        ground = float(self._origin[2])
        height = float(self._position[2]) - ground
        if self._flavour == "px4":
            return ground + max(height, self._param("RTL_RETURN_ALT"))
        target = max(self._param("RTL_ALT") / 100.0, height)
        slope = self._param("RTL_CONE_SLOPE")
        if slope >= 0.5:  # RTL_MIN_CONE_SLOPE
            offset = self._position[:2] - self._origin[:2]
            distance = math.hypot(float(offset[0]), float(offset[1]))
            target = max(height, min(target, max(distance * slope, height + 2.5)))
        return ground + target

    # --- modes ---
    def _enter_mode(self, name: str, now_s: float) -> None:
        """Switch to ``name`` (already allowed) with what entering it does."""
        previous = self._mode
        self._failsafe = self._resume_offboard = False
        self._return = None
        self._takeoff_altitude_m = math.nan
        if self._flavour == "px4" and name in ("LAND", "RTL") and previous not in ("LAND", "RTL"):
            self._mode_before_auto = previous
        self._mode = name
        if name != "TAKEOFF" and self._climb is not None:
            self._climb = None  # a takeoff ends with any other mode
            if self._landed == _TAKING_OFF:
                self._landed = _ON_GROUND if self._on_ground else _IN_AIR
        if self._flavour == "ardupilot":
            self._setpoint = None  # GUIDED starts from "hold"
            self._last_setpoint_s = None
        airborne = not self._on_ground
        if airborne and self._landed == _LANDING and name not in ("LAND", "RTL"):
            self._landed = _IN_AIR
        self._enter_hold()
        if name == "LAND":
            if airborne:
                self._landed = _LANDING
            elif self._armed:
                self._start_ground_timer(now_s, landed=True)
        elif name == "RTL":
            if airborne:
                altitude = self._return_altitude_z()
                phase: Literal["climb", "return"] = \
                    "climb" if self._position[2] < altitude - 0.1 else "return"
                self._return = _Return(phase, altitude, now_s)
                self._landed = _IN_AIR
            elif self._armed:
                self._start_ground_timer(now_s, landed=True)
        elif name == "TAKEOFF" and previous != "TAKEOFF" and self._armed:
            self._start_takeoff(math.nan, now_s)

    def _start_takeoff(self, altitude_m: float, now_s: float) -> None:
        """px4 AUTO.TAKEOFF (module doc)."""
        flight = self._flight
        airborne = not self._on_ground
        base = float(self._position[2]) if airborne else float(self._origin[2])
        if math.isfinite(altitude_m):
            target_z = max(float(self._origin[2]) + altitude_m, base)  # not descending
        else:
            target_z = base + self._param("MIS_TAKEOFF_ALT")
        target = np.array([self._position[0], self._position[1], target_z])
        self._mode = "TAKEOFF"
        self._return = None
        self._hold_w = target.copy()
        if airborne:
            self._climb = _Climb(target, None)
            self._landed = _IN_AIR  # measured: no TAKEOFF state for a takeoff in the air
        else:
            self._climb = _Climb(target, now_s + flight.takeoff_delay_s)
            self._landed = _TAKING_OFF

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
        self._update(now_s)
        self._arrivals.append(now_s)
        if self._flavour == "ardupilot" and not (self.in_setpoint_mode and self._armed
                                                 and not self._on_ground):
            # ArduPilot silently ignores these; on the ground one replaces (cancels) a
            # takeoff that is still spooling up (measured: the vehicle stays down).
            if self.in_setpoint_mode and self._armed and self._climb is not None:
                self._climb = None
            self.ignored_setpoints += 1
        else:
            position = np.array(frames.world_from_local_ned_xyz(
                (msg.x, msg.y, msg.z), self._origin_xyz), dtype=np.float64) \
                if has_position else None
            velocity = clamp_velocity(np.array(frames.ned_to_enu_xyz(msg.vx, msg.vy, msg.vz),
                                               dtype=np.float64), self._u_max) \
                if has_velocity else None
            self._setpoint = _Setpoint(position, velocity, now_s)
            self._last_setpoint_s = now_s
            self.accepted_setpoints += 1
            if self._flavour == "ardupilot":
                self._failsafe = False
                if self._climb is not None:  # replaces the takeoff target: no more climbing
                    self._climb = None
                    self._landed = _IN_AIR
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
        if self._texts:  # why (ArduPilot's STATUSTEXT), right behind the answer
            out += [self._statustext_msg(severity, text) for severity, text in self._texts]
            self._texts.clear()
        if (self._mode, self._armed) != state:
            out.append(self._heartbeat_msg())
        return out

    def _ack(self, msg: Any, command: int, result: int) -> Any:
        return self._tx.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                           msg.get_srcComponent())

    def _command(self, command: int, p: tuple[float, ...], now_s: float) -> tuple[int, list[Any]]:
        if command == _MSG.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_disarm(p[0], now_s), []
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
            return self._takeoff(p[6], now_s), []
        if command in (_MSG.MAV_CMD_NAV_LAND, _MSG.MAV_CMD_NAV_RETURN_TO_LAUNCH):
            name = "LAND" if command == _MSG.MAV_CMD_NAV_LAND else "RTL"
            return self._set_mode(self._modes[name], now_s), []
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

    def _arm_disarm(self, param1: float, now_s: float) -> int:
        if not _finite(param1) or param1 not in (0.0, 1.0):
            return _MSG.MAV_RESULT_DENIED
        if param1 == 0.0:
            if not self._armed:
                return _MSG.MAV_RESULT_ACCEPTED
            if not self._on_ground:  # measured: ArduCopter FAILED, PX4 TEMPORARILY_REJECTED
                return _MSG.MAV_RESULT_FAILED if self._flavour == "ardupilot" \
                    else _MSG.MAV_RESULT_TEMPORARILY_REJECTED
            self._disarm()
            return _MSG.MAV_RESULT_ACCEPTED
        if self._armed:
            return _MSG.MAV_RESULT_ACCEPTED
        if self._flavour == "ardupilot":
            if self._mode in _ACM_NOT_ARMABLE:
                self._say(f"Arm: {self._mode} mode not armable", _MSG.MAV_SEVERITY_CRITICAL)
                return _MSG.MAV_RESULT_FAILED
            if self._mode == "AUTO":
                self._say("Arm: Mode requires mission", _MSG.MAV_SEVERITY_CRITICAL)
                return _MSG.MAV_RESULT_FAILED
        elif self.in_setpoint_mode and not self.setpoints_streaming(now_s):
            return _MSG.MAV_RESULT_TEMPORARILY_REJECTED  # PX4: no offboard signal
        self._armed = True
        self._armed_s = now_s
        self._say("Arming motors")
        self._hold_w = self._position.copy()
        if self._on_ground:
            self._start_ground_timer(now_s, landed=False)
            if self._flavour == "px4" and self._mode == "TAKEOFF":
                self._start_takeoff(self._takeoff_altitude_m, now_s)
        return _MSG.MAV_RESULT_ACCEPTED

    def _set_mode(self, custom_mode: int, now_s: float) -> int:
        names = [name for name, value in self._modes.items() if value == custom_mode]
        if not names:  # measured: ArduCopter FAILED for a mode number it does not have
            return _MSG.MAV_RESULT_FAILED if self._flavour == "ardupilot" \
                else _MSG.MAV_RESULT_DENIED
        name = names[0]
        if name == self._mode and not self._failsafe:
            return _MSG.MAV_RESULT_ACCEPTED  # already in it: nothing is re-initialised
        if self._flavour == "px4":
            if name == "POSCTL":
                return _MSG.MAV_RESULT_TEMPORARILY_REJECTED  # no manual control (no RC)
            # No offboard signal yet: refused when armed; measured: accepted while disarmed
            # (arming then waits for setpoints).
            if name == "OFFBOARD" and self._armed and not self.setpoints_streaming(now_s):
                return _MSG.MAV_RESULT_TEMPORARILY_REJECTED
        elif name == self._mode:
            return _MSG.MAV_RESULT_ACCEPTED  # GUIDED in its failsafe: the next setpoint resumes
        elif name == "AUTO" and self._armed:
            self._say("Mode change to AUTO failed: no mission", _MSG.MAV_SEVERITY_WARNING)
            return _MSG.MAV_RESULT_FAILED
        self._enter_mode(name, now_s)
        return _MSG.MAV_RESULT_ACCEPTED

    def _takeoff(self, altitude_m: float, now_s: float) -> int:
        if self._flavour == "ardupilot":
            ground = float(self._origin[2])
            if (self._mode != "GUIDED" or not self._armed or not self._on_ground
                    or not _finite(altitude_m) or altitude_m <= 0.0):
                return _MSG.MAV_RESULT_FAILED
            target = np.array([self._position[0], self._position[1], ground + altitude_m])
            self._climb = _Climb(target, now_s + self._flight.takeoff_delay_s)
            self._hold_w = self._position.copy()
            self._setpoint = None
            self._last_setpoint_s = None
            self._failsafe = False
            return _MSG.MAV_RESULT_ACCEPTED
        if not self._armed:  # measured: AUTO.TAKEOFF, on the ground; arming lifts off
            self._enter_mode("TAKEOFF", now_s)
            self._takeoff_altitude_m = float(altitude_m)  # to param7 then, if finite
            return _MSG.MAV_RESULT_ACCEPTED
        self._failsafe = self._resume_offboard = False
        self._start_takeoff(altitude_m, now_s)
        return _MSG.MAV_RESULT_ACCEPTED

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not _finite(msg_id, interval_us):
            return _MSG.MAV_RESULT_DENIED
        name = _STREAM_IDS.get(int(msg_id))
        if name is None or (interval_us < 0 and interval_us != -1):
            return _MSG.MAV_RESULT_DENIED
        if name == "HEARTBEAT" and self._flavour == "px4":
            return _MSG.MAV_RESULT_FAILED  # measured: PX4 keeps its 1 Hz heartbeat
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

    def _param_msg(self, name: str) -> Any:
        index = list(self._param_specs).index(name)
        return self._tx.param_value_encode(name.encode(), self._params[name],
                                           self._param_specs[name].mav_type,
                                           len(self._param_specs), index)

    def _on_param_request_list(self, msg: Any, now_s: float) -> list[Any]:
        return [self._param_msg(name) for name in self._param_specs]

    def _on_param_request_read(self, msg: Any, now_s: float) -> list[Any]:
        names = list(self._param_specs)
        if msg.param_index == -1 and msg.param_id in self._param_specs:
            return [self._param_msg(msg.param_id)]
        if 0 <= msg.param_index < len(names):
            return [self._param_msg(names[msg.param_index])]
        self.ignored_messages += 1  # unknown parameter: no answer, as autopilots do
        return []

    def _on_param_set(self, msg: Any, now_s: float) -> list[Any]:
        spec = self._param_specs.get(msg.param_id)
        if spec is None:
            self.ignored_messages += 1
            return []
        value = float(msg.param_value)
        if spec.mav_type != _REAL32 and math.isfinite(value):
            value = float(round(value))
        if math.isfinite(value) and (value > spec.minimum if spec.positive
                                     else value >= spec.minimum):
            self._params[msg.param_id] = value
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
        base_mode = _MSG.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self._armed:
            base_mode |= _MSG.MAV_MODE_FLAG_SAFETY_ARMED
        autopilot = _MSG.MAV_AUTOPILOT_PX4 if self._flavour == "px4" \
            else _MSG.MAV_AUTOPILOT_ARDUPILOTMEGA
        status = _MSG.MAV_STATE_ACTIVE if self._armed else _MSG.MAV_STATE_STANDBY
        return (_MSG.MAV_TYPE_QUADROTOR, autopilot, base_mode, self.custom_mode, status, 3)

    def _heartbeat_msg(self) -> Any:
        return self._tx.heartbeat_encode(*self.heartbeat_fields())

    def _statustext_msg(self, severity: int, text: str) -> Any:
        return self._tx.statustext_encode(severity, text.encode()[:50])

    def _local_position_fields(self) -> tuple[float, ...]:
        x, y, z = frames.local_ned_from_world_xyz(tuple(self._position.tolist()),
                                                  self._origin_xyz)
        return (x, y, z, *frames.enu_to_ned_xyz(*self._velocity.tolist()))

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
        return self._tx.extended_sys_state_encode(_MSG.MAV_VTOL_STATE_UNDEFINED, self._landed)

    def _autopilot_version_msg(self) -> Any:
        caps = (_MSG.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | _MSG.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | _MSG.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                | _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT)
        if self._flavour == "px4":
            caps |= _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            version = (1 << 24) | (15 << 16) | (4 << 8) | 255  # 1.15.4 official
        else:
            caps |= _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
            version = (4 << 24) | (7 << 16) | (0 << 8) | 0  # 4.7.0-dev (the SITL build)
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
