"""How an emulated copter flies: its state (position, velocity, armed, mode, landed state), the
autopilot's modes and their guidance, takeoff, hold, land and return, the setpoint-loss
failsafes, landing detection and auto-disarm, for either flavour (``flavours``).

No MAVLink encoding here: ``sim_world.vehicle.protocol`` decodes what arrives, calls ``Flight``
and encodes its answers; results of commands are MAV_RESULT codes, as the firmware gives
them. The behaviour and where each figure comes from: docs/vehicle_emulator.md.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from sim_world.vehicle.flavours import (
    AIR_MODE,
    ARDUCOPTER_NOT_ARMABLE,
    ARDUCOPTER_PILOT_MODES,
    FLIGHT_MODELS,
    GROUND_MODE,
    MODES,
    PARAMS,
    REAL32,
    SETPOINT_MODE,
    TIMEOUT_PARAM,
    Flavour,
    FlightModel,
    ParamSpec,
    Start,
)
from swarm.models.kinematics import VelocityResponse, clamp_velocity, step_vehicle

Array = NDArray[np.float64]
_MSG = mavlink2

_ON_GROUND = _MSG.MAV_LANDED_STATE_ON_GROUND
_IN_AIR = _MSG.MAV_LANDED_STATE_IN_AIR
_TAKING_OFF = _MSG.MAV_LANDED_STATE_TAKEOFF
_LANDING = _MSG.MAV_LANDED_STATE_LANDING

STREAM_WINDOW_S: Final = 0.5  # px4: "streaming" = at least STREAM_MIN_COUNT setpoints in this
STREAM_MIN_COUNT: Final = 2
_CLIMB_REQUEST_M_S = 0.2  # px4 on the ground in OFFBOARD: a command this fast up lifts off
_ARRIVED_M = 0.2  # a return is home this close (horizontally) [m]
_MAX_PENDING_TEXTS = 8
_ZERO3 = np.zeros(3)


@dataclass(frozen=True)
class Setpoint:
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


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _approach_speed(distance_m: float, speed_max_m_s: float, gain_1_s: float,
                    accel_m_s2: float) -> float:
    """Speed towards a target ``distance_m`` away: the position loop (gain·d) near it, the
    speed from which ``accel_m_s2`` stops in d (√(2·a·d)) further out, at most the limit."""
    return min(speed_max_m_s, gain_1_s * distance_m, math.sqrt(2.0 * accel_m_s2 * distance_m))


class Flight:
    """The flight of one PX4- or ArduCopter-like copter: state, modes, guidance, failsafes.

    Every call that depends on time takes it (``now_s``, the vehicle's clock). ``position_w``
    and ``origin_w`` are checked by the caller (finite, shape (3,)). Not thread-safe.
    """

    def __init__(self, flavour: Flavour, position_w: ArrayLike, origin_w: ArrayLike, *,
                 u_max_m_s: float, setpoint_timeout_s: float | None, start: Start,
                 response: VelocityResponse, flight_model: FlightModel | None) -> None:
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
        self._flavour: Flavour = flavour
        self._origin = origin
        self._u_max = float(u_max_m_s)
        self._response = response
        self._model = FLIGHT_MODELS[flavour] if flight_model is None else flight_model

        self._param_specs = PARAMS[flavour]
        self._params = {name: float(spec.default) for name, spec in self._param_specs.items()}
        if setpoint_timeout_s is not None:
            timeout = float(setpoint_timeout_s)
            if not (math.isfinite(timeout) and timeout > 0):
                raise ValueError(f"setpoint_timeout_s must be finite and > 0, got {timeout}")
            self._params[TIMEOUT_PARAM[flavour]] = timeout

        self._modes = MODES[flavour]
        self._velocity = np.zeros(3)
        if start == "air":
            self._position = position
            self._armed = True
            self._mode = AIR_MODE[flavour]
            self._landed = _IN_AIR
            self._on_ground = False
        else:
            position[2] = origin[2]
            self._position = position
            self._armed = False
            self._mode = GROUND_MODE[flavour]
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

        self._setpoint: Setpoint | None = None
        self._last_setpoint_s: float | None = None  # last accepted (applied-kind) setpoint
        self._arrivals: deque[float] = deque(maxlen=16)  # arrival times of valid setpoints
        self._texts: deque[tuple[int, str]] = deque(maxlen=_MAX_PENDING_TEXTS)

        self.accepted_setpoints = 0
        self.ignored_setpoints = 0
        self.failsafe_events = 0

    # ---------------------------------------------------------------- read-only state
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
        return self._model

    @property
    def setpoint_timeout_s(self) -> float:
        return self._params[TIMEOUT_PARAM[self._flavour]]

    @property
    def params(self) -> dict[str, float]:
        return dict(self._params)

    @property
    def param_specs(self) -> dict[str, ParamSpec]:
        """The parameters it knows, in the order the firmware lists them (a copy)."""
        return dict(self._param_specs)

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
        return self._mode == SETPOINT_MODE[self._flavour]

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

    def setpoints_streaming(self, now_s: float) -> bool:
        """At least STREAM_MIN_COUNT valid setpoints arrived in the last STREAM_WINDOW_S."""
        recent = [t for t in self._arrivals if now_s - STREAM_WINDOW_S <= t <= now_s]
        return len(recent) >= STREAM_MIN_COUNT

    def take_texts(self) -> list[tuple[int, str]]:
        """The STATUSTEXTs (severity, text) it has to say since the last call: ArduPilot's
        way of saying why; PX4 says nothing here."""
        texts = list(self._texts)
        self._texts.clear()
        return texts

    # ---------------------------------------------------------------- lockstep
    def commanded_velocity_w(self, now_s: float) -> Array:
        """The velocity it applies now for its last accepted setpoint (zero when not
        accepting setpoints or before any)."""
        self.update(now_s)
        setpoint = self._setpoint
        if setpoint is None or not self.accepting_setpoints:
            return np.zeros(3)
        if setpoint.velocity_w is not None:
            return setpoint.velocity_w.copy()
        return self._setpoint_command(setpoint, now_s)

    def integrate(self, dt_s: float, velocity_w: Array) -> None:
        """Move for ``dt_s`` under the command ``velocity_w`` (``step_vehicle``), then the
        ground."""
        command = np.asarray(velocity_w, dtype=np.float64).reshape(3)
        self._position, self._velocity = step_vehicle(self._position, self._velocity, command,
                                                      self._u_max, dt_s, self._response)
        self._clamp_to_ground()

    def push(self, offset_w: Array) -> None:
        """Move by ``offset_w`` [m] at once, the velocity as it was: a disturbance (a gust)
        that the guidance has to take out; then the ground."""
        offset = np.asarray(offset_w, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(offset)):
            raise ValueError(f"offset_w must be 3 finite numbers [m], got {offset_w!r}")
        self._position = self._position + offset
        self._clamp_to_ground()

    # ---------------------------------------------------------------- realtime
    def fly(self, dt_s: float, now_s: float) -> None:
        """Fly for ``dt_s`` (ending at ``now_s``) as the mode and state say."""
        self.update(now_s)
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

    # ---------------------------------------------------------------- what arrives
    def receive_setpoint(self, position_w: Array | None, velocity_w: Array | None,
                         now_s: float) -> None:
        """A valid setpoint (finite, in W; ``velocity_w`` already clamped) arrived now: a
        proof of life, applied if the vehicle may (else counted in ``ignored_setpoints``)."""
        self.update(now_s)
        self._arrivals.append(now_s)
        if self._flavour == "ardupilot" and not (self.in_setpoint_mode and self._armed
                                                 and not self._on_ground):
            # ArduPilot silently ignores these; on the ground one replaces (cancels) a
            # takeoff that is still spooling up (the vehicle stays down).
            if self.in_setpoint_mode and self._armed and self._climb is not None:
                self._climb = None
            self.ignored_setpoints += 1
            return
        self._setpoint = Setpoint(position_w, velocity_w, now_s)
        self._last_setpoint_s = now_s
        self.accepted_setpoints += 1
        if self._flavour == "ardupilot":
            self._failsafe = False
            if self._climb is not None:  # replaces the takeoff target: no more climbing
                self._climb = None
                self._landed = _IN_AIR

    def set_param(self, name: str, value: float) -> None:
        """PARAM_SET of a known parameter: integer types rounded; a value that is not finite
        or below the parameter's minimum leaves it unchanged."""
        spec = self._param_specs[name]
        value = float(value)
        if spec.mav_type != REAL32 and math.isfinite(value):
            value = float(round(value))
        if math.isfinite(value) and (value > spec.minimum if spec.positive
                                     else value >= spec.minimum):
            self._params[name] = value

    def arm_disarm(self, param1: float, now_s: float) -> int:
        """MAV_CMD_COMPONENT_ARM_DISARM (param1 1: arm, 0: disarm); its MAV_RESULT."""
        if not _finite(param1) or param1 not in (0.0, 1.0):
            return _MSG.MAV_RESULT_DENIED
        if param1 == 0.0:
            if not self._armed:
                return _MSG.MAV_RESULT_ACCEPTED
            if not self._on_ground:  # ArduCopter FAILED, PX4 TEMPORARILY_REJECTED
                return _MSG.MAV_RESULT_FAILED if self._flavour == "ardupilot" \
                    else _MSG.MAV_RESULT_TEMPORARILY_REJECTED
            self._disarm()
            return _MSG.MAV_RESULT_ACCEPTED
        if self._armed:
            return _MSG.MAV_RESULT_ACCEPTED
        if self._flavour == "ardupilot":
            if self._mode in ARDUCOPTER_NOT_ARMABLE:
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

    def set_mode(self, custom_mode: int, now_s: float) -> int:
        """A change to the mode with this custom_mode (DO_SET_MODE, SET_MODE, NAV_LAND,
        NAV_RETURN_TO_LAUNCH); its MAV_RESULT."""
        names = [name for name, value in self._modes.items() if value == custom_mode]
        if not names:  # ArduCopter: FAILED for a mode number it does not have
            return _MSG.MAV_RESULT_FAILED if self._flavour == "ardupilot" \
                else _MSG.MAV_RESULT_DENIED
        name = names[0]
        if name == self._mode and not self._failsafe:
            return _MSG.MAV_RESULT_ACCEPTED  # already in it: nothing is re-initialised
        if self._flavour == "px4":
            if name == "POSCTL":
                return _MSG.MAV_RESULT_TEMPORARILY_REJECTED  # no manual control (no RC)
            # No offboard signal yet: refused when armed, accepted while disarmed (arming
            # then waits for setpoints).
            if name == "OFFBOARD" and self._armed and not self.setpoints_streaming(now_s):
                return _MSG.MAV_RESULT_TEMPORARILY_REJECTED
        elif name == self._mode:
            return _MSG.MAV_RESULT_ACCEPTED  # GUIDED in its failsafe: the next setpoint resumes
        elif name == "AUTO" and self._armed:
            self._say("Mode change to AUTO failed: no mission", _MSG.MAV_SEVERITY_WARNING)
            return _MSG.MAV_RESULT_FAILED
        self._enter_mode(name, now_s)
        return _MSG.MAV_RESULT_ACCEPTED

    def takeoff(self, altitude_m: float, now_s: float) -> int:
        """MAV_CMD_NAV_TAKEOFF with param7 ``altitude_m``; its MAV_RESULT."""
        if self._flavour == "ardupilot":
            ground = float(self._origin[2])
            if (self._mode != "GUIDED" or not self._armed or not self._on_ground
                    or not _finite(altitude_m) or altitude_m <= 0.0):
                return _MSG.MAV_RESULT_FAILED
            target = np.array([self._position[0], self._position[1], ground + altitude_m])
            self._climb = _Climb(target, now_s + self._model.takeoff_delay_s)
            self._hold_w = self._position.copy()
            self._setpoint = None
            self._last_setpoint_s = None
            self._failsafe = False
            return _MSG.MAV_RESULT_ACCEPTED
        if not self._armed:  # AUTO.TAKEOFF, on the ground; arming lifts off
            self._enter_mode("TAKEOFF", now_s)
            self._takeoff_altitude_m = float(altitude_m)  # to param7 then, if finite
            return _MSG.MAV_RESULT_ACCEPTED
        self._failsafe = self._resume_offboard = False
        self._start_takeoff(altitude_m, now_s)
        return _MSG.MAV_RESULT_ACCEPTED

    # ================================================================ internals
    def _say(self, text: str, severity: int = _MSG.MAV_SEVERITY_INFO) -> None:
        """A STATUSTEXT to say (ArduPilot's way of saying why)."""
        if self._flavour == "ardupilot":
            self._texts.append((severity, text))

    def _param(self, name: str) -> float:
        return self._params[name]

    # --- time-driven state ---
    def update(self, now_s: float) -> None:
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
                and now_s - self._touchdown_s >= self._model.land_detect_s):
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
                self._setpoint = Setpoint(moved, None, setpoint.arrived_s)
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
        """Auto-disarm on the ground: after arming, or after landing."""
        self._ground_since_s = now_s
        if self._flavour == "ardupilot":
            if landed and self._mode in ("LAND", "RTL"):
                self._ground_disarm_s = self._model.landed_disarm_s
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
            self._mode = self._mode_before_auto  # PX4 goes back (OFFBOARD)
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
            self._liftoff_s = max(now_s, self._armed_s) + self._model.offboard_takeoff_delay_s
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
        if mode == SETPOINT_MODE[self._flavour]:
            if self._setpoint is not None:
                return self._setpoint_command(self._setpoint, now_s)
            if self._failsafe:
                return np.zeros(3)  # ardupilot GUID_TIMEOUT: velocity zero
            return self._hold_command()
        if self._flavour == "ardupilot" and mode in ARDUCOPTER_PILOT_MODES:
            command = self._hold_command()
            command[2] = -self._model.pilot_sink_m_s  # no RC: throttle stick reads low
            return command
        return self._hold_command()  # BRAKE, AUTO, Hold, POSCTL

    def _setpoint_command(self, setpoint: Setpoint, now_s: float) -> Array:
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
        model = self._model
        speed = _approach_speed(distance, speed_max_m_s, model.position_gain_1_s,
                                model.approach_accel_m_s2)
        return error * (speed / distance)

    def _hold_command(self) -> Array:
        return (self._hold_w - self._position) / self._model.stop_time_constant_s

    def _enter_hold(self) -> None:
        """Hold the stopping point p + v·τ (speed then decays as e^(−t/τ))."""
        if self._on_ground:
            self._hold_w = self._position.copy()
        else:
            self._hold_w = self._position + self._model.stop_time_constant_s * self._velocity

    def _climb_command(self, climb: _Climb) -> Array:
        command = self._hold_command()
        model = self._model
        error = float(climb.target_w[2] - self._position[2])
        command[2] = math.copysign(_approach_speed(abs(error), model.takeoff_speed_m_s,
                                                   model.position_gain_1_s,
                                                   model.approach_accel_m_s2), error)
        return command

    def _land_speed(self) -> float:
        height = float(self._position[2] - self._origin[2])
        model = self._model
        slow = (self._param("LAND_SPEED") / 100.0 if self._flavour == "ardupilot"
                else self._param("MPC_LAND_SPEED"))
        fast = (self._param("WPNAV_SPEED_DN") / 100.0 if self._flavour == "ardupilot"
                else model.land_fast_m_s)
        if height <= model.land_slow_below_m:
            return slow
        if height >= model.land_fast_above_m or model.land_fast_above_m <= \
                model.land_slow_below_m:
            return fast
        share = (height - model.land_slow_below_m) / (model.land_fast_above_m
                                                      - model.land_slow_below_m)
        return slow + share * (fast - slow)

    def _land_command(self) -> Array:
        command = self._hold_command()
        command[2] = -self._land_speed()
        return command

    def _return_command(self, now_s: float) -> Array:
        ret = self._return
        if ret is None:  # entered on the ground
            return self._hold_command()
        model = self._model
        home = np.array([self._origin[0], self._origin[1], ret.altitude_z_m])
        if ret.phase == "climb":
            command = self._hold_command()
            speed = (self._param("WPNAV_SPEED_UP") / 100.0 if self._flavour == "ardupilot"
                     else model.return_climb_m_s)
            error = ret.altitude_z_m - float(self._position[2])
            command[2] = math.copysign(_approach_speed(abs(error), speed,
                                                       model.position_gain_1_s,
                                                       model.approach_accel_m_s2), error)
            return command
        if ret.phase == "return":
            return self._towards(home, model.return_speed_m_s)
        if ret.phase == "descend":
            command = self._hold_command()
            error = ret.altitude_z_m - float(self._position[2])
            command[2] = math.copysign(_approach_speed(abs(error), model.return_descent_m_s,
                                                       model.position_gain_1_s,
                                                       model.approach_accel_m_s2), error)
            return command
        if ret.phase == "land":
            return self._land_command()
        return self._hold_command()  # wait

    def _progress(self, now_s: float) -> None:
        """Position-driven transitions after a move: a takeoff done, a return's phases."""
        climb = self._climb
        if (climb is not None and climb.liftoff_s is None and abs(
                float(climb.target_w[2] - self._position[2])) <= self._model.takeoff_done_m):
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
        """px4 AUTO.TAKEOFF: to MIS_TAKEOFF_ALT above the ground (or the current altitude in
        the air), or to ``altitude_m`` above the origin if finite."""
        model = self._model
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
            self._landed = _IN_AIR  # no TAKEOFF state for a takeoff in the air
        else:
            self._climb = _Climb(target, now_s + model.takeoff_delay_s)
            self._landed = _TAKING_OFF
