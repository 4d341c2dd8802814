"""What differs between the two firmwares an emulated vehicle behaves like, ArduCopter and PX4:
their modes and how MAVLink numbers them, their parameters (defaults, types, limits), the
timings and speeds of their automatic flight, their default telemetry streams and what they
say about themselves. Tables only; ``sim_world.vehicle.flight`` and
``sim_world.vehicle.protocol`` read them. The figures come from the real firmware's SITL
(docs/vehicle_emulator.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final, Literal

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.models.kinematics import ARDUCOPTER_SITL_RESPONSE, PX4_SITL_RESPONSE, VelocityResponse

Flavour = Literal["px4", "ardupilot"]
Start = Literal["air", "ground"]
FLAVOURS: Final[tuple[Flavour, ...]] = ("px4", "ardupilot")
_MSG = mavlink2

# --- modes -----------------------------------------------------------------------------------
# PX4 custom_mode: main mode in bits 16-23, sub mode in bits 24-31 (px4_custom_mode.h).
_PX4_MAIN_POSCTL, _PX4_MAIN_AUTO, _PX4_MAIN_OFFBOARD = 3, 4, 6


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4's custom_mode of a main mode and a sub mode."""
    return (main << 16) | (sub << 24)


# Names as pymavlink's mode_string_v10 gives them.
PX4_MODES: Final[dict[str, int]] = {
    "POSCTL": px4_custom_mode(_PX4_MAIN_POSCTL),
    "OFFBOARD": px4_custom_mode(_PX4_MAIN_OFFBOARD),
    "LOITER": px4_custom_mode(_PX4_MAIN_AUTO, 3),  # AUTO.LOITER, "Hold"
    "TAKEOFF": px4_custom_mode(_PX4_MAIN_AUTO, 2),
    "LAND": px4_custom_mode(_PX4_MAIN_AUTO, 6),
    "RTL": px4_custom_mode(_PX4_MAIN_AUTO, 5),
}
ARDUCOPTER_MODES: Final[dict[str, int]] = {
    "STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9,
    "POSHOLD": 16, "BRAKE": 17,
}
MODES: Final[dict[Flavour, dict[str, int]]] = {"px4": PX4_MODES, "ardupilot": ARDUCOPTER_MODES}
ARDUCOPTER_PILOT_MODES: Final = frozenset({"STABILIZE", "ALT_HOLD", "LOITER", "POSHOLD"})
ARDUCOPTER_NOT_ARMABLE: Final = frozenset({"LAND", "RTL", "BRAKE"})
SETPOINT_MODE: Final[dict[Flavour, str]] = {"px4": "OFFBOARD", "ardupilot": "GUIDED"}
GROUND_MODE: Final[dict[Flavour, str]] = {"px4": "LOITER", "ardupilot": "STABILIZE"}
AIR_MODE: Final[dict[Flavour, str]] = {"px4": "LOITER", "ardupilot": "GUIDED"}

# --- parameters ------------------------------------------------------------------------------
# The firmware's defaults and MAVLink types (ArduCopter reports integers C-cast, as floats).
REAL32: Final = _MSG.MAV_PARAM_TYPE_REAL32
_INT32, _INT16, _INT8 = (_MSG.MAV_PARAM_TYPE_INT32, _MSG.MAV_PARAM_TYPE_INT16,
                         _MSG.MAV_PARAM_TYPE_INT8)


@dataclass(frozen=True)
class ParamSpec:
    default: float
    mav_type: int
    minimum: float  # a PARAM_SET below this (or not finite) leaves the value unchanged
    positive: bool = False  # the value must be > minimum


PARAMS: Final[dict[Flavour, dict[str, ParamSpec]]] = {
    "ardupilot": {
        "GUID_TIMEOUT": ParamSpec(3.0, REAL32, 0.0, positive=True),
        "RTL_ALT": ParamSpec(1500, _INT32, 200),  # [cm]; ArduCopter's RTL_ALT_MIN
        "RTL_LOIT_TIME": ParamSpec(5000, _INT32, 0),  # [ms]
        "RTL_CONE_SLOPE": ParamSpec(3.0, REAL32, 0.0),
        "LAND_SPEED": ParamSpec(50, _INT16, 30),  # [cm/s]
        "WPNAV_SPEED_UP": ParamSpec(250.0, REAL32, 10.0),  # [cm/s]
        "WPNAV_SPEED_DN": ParamSpec(150.0, REAL32, 10.0),  # [cm/s]
        "DISARM_DELAY": ParamSpec(10, _INT8, 0),  # [s]; 0: never
    },
    "px4": {
        "COM_OF_LOSS_T": ParamSpec(1.0, REAL32, 0.0, positive=True),
        "COM_DISARM_LAND": ParamSpec(2.0, REAL32, -1.0),  # ≤ 0: never
        "COM_DISARM_PRFLT": ParamSpec(10.0, REAL32, -1.0),  # ≤ 0: never
        "MIS_TAKEOFF_ALT": ParamSpec(2.5, REAL32, 0.0),
        "MPC_LAND_SPEED": ParamSpec(0.7, REAL32, 0.1),
        "RTL_RETURN_ALT": ParamSpec(30.0, REAL32, 0.0),
        "RTL_DESCEND_ALT": ParamSpec(10.0, REAL32, 0.0),
        "RTL_LAND_DELAY": ParamSpec(0.0, REAL32, -1.0),
    },
}
# The parameter that holds the setpoint-loss failsafe delay [s].
TIMEOUT_PARAM: Final[dict[Flavour, str]] = {"px4": "COM_OF_LOSS_T", "ardupilot": "GUID_TIMEOUT"}


# --- automatic flight ------------------------------------------------------------------------
@dataclass(frozen=True)
class FlightModel:
    """Timings and speeds of one firmware's automatic flight, as measured on its SITL build
    (the figures of ``FLIGHT_MODELS``). Speeds that the firmware takes from a parameter are
    parameters of the vehicle instead (``PARAMS``)."""

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

# --- telemetry streams -----------------------------------------------------------------------
EVERY_CALL: Final = 0.0  # stream interval meaning "on every telemetry() call"
# Default interval per stream and flavour (None = not streamed).
DEFAULT_INTERVAL_S: Final[dict[Flavour, dict[str, float | None]]] = {
    # HEARTBEAT is the caller's job (heartbeat() at 1 Hz) unless an interval is requested.
    "px4": {"HEARTBEAT": None, "LOCAL_POSITION_NED": EVERY_CALL, "ATTITUDE": 0.1,
            "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0},
    "ardupilot": {"HEARTBEAT": None, "LOCAL_POSITION_NED": None, "ATTITUDE": 1.0,
                  "SYS_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0},
}
# Interval that "0 = default rate" restores (LOCAL_POSITION_NED is then on in both flavours).
RESTORED_INTERVAL_S: Final[dict[str, float]] = {
    "HEARTBEAT": 1.0, "LOCAL_POSITION_NED": EVERY_CALL, "ATTITUDE": 0.1, "SYS_STATUS": 1.0,
    "EXTENDED_SYS_STATE": 1.0}
# ArduPilot's REQUEST_DATA_STREAM groups that are emulated (PX4 ignores the message).
DATA_STREAMS: Final[dict[int, tuple[str, ...]]] = {
    _MSG.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "EXTENDED_SYS_STATE"),
    _MSG.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED",),
    _MSG.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
}
DATA_STREAMS[_MSG.MAV_DATA_STREAM_ALL] = tuple(
    name for names in list(DATA_STREAMS.values()) for name in names)

# --- what the firmware says about itself -----------------------------------------------------
AUTOPILOT: Final[dict[Flavour, int]] = {
    "px4": _MSG.MAV_AUTOPILOT_PX4, "ardupilot": _MSG.MAV_AUTOPILOT_ARDUPILOTMEGA}
# AUTOPILOT_VERSION's flight_sw_version: major, minor, patch, release type (255: official).
FIRMWARE_VERSION: Final[dict[Flavour, int]] = {
    "px4": (1 << 24) | (15 << 16) | (4 << 8) | 255,  # 1.15.4 official
    "ardupilot": (4 << 24) | (7 << 16) | (0 << 8) | 0,  # 4.7.0-dev (the SITL build)
}
# How each encodes parameter values on the wire (an AUTOPILOT_VERSION capability).
PARAM_ENCODING: Final[dict[Flavour, int]] = {
    "px4": _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE,
    "ardupilot": _MSG.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
}
