"""An emulated vehicle flying itself (sim_world.vehicle.flight through EmulatedVehicle):
takeoff, hold, land, return, failsafes, the ground, the velocity response, position setpoints
(the behaviour docs/vehicle_emulator.md describes).

Every test drives the vehicle with explicit times: ``fly(dt, now)`` at dt = 0.02 s, commands
and setpoints through ``receive`` as an agent would send them (pymavlink encoder). The
vehicles' default response is ideal (v = u), so speeds are checked exactly where the
guidance gives them exactly.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.vehicle import FLIGHT_MODELS, MEASURED_RESPONSE, EmulatedVehicle
from swarm.models import frames
from swarm.models.kinematics import VelocityResponse, clamp_velocity, step_vehicle
from tests.helpers.vehicle_tools import (
    DRONE,
    DT,
    FULL_MASK,
    ORIGIN,
    POSITION_VELOCITY_MASK,
    START,
    SYS,
    Agent,
    acks,
    ardupilot_flying,
    fly,
    make,
    of_type,
    px4_offboard_armed,
)

GROUND = float(ORIGIN[2])
HOME_XY = ORIGIN[:2]
ON_GROUND = mav.MAV_LANDED_STATE_ON_GROUND
IN_AIR = mav.MAV_LANDED_STATE_IN_AIR
TAKING_OFF = mav.MAV_LANDED_STATE_TAKEOFF
LANDING = mav.MAV_LANDED_STATE_LANDING
ACCEPTED = mav.MAV_RESULT_ACCEPTED
EPS = 1e-9


@dataclass(frozen=True)
class Sample:
    """The vehicle's state right after ``fly(dt, t)``."""

    t: float
    p: np.ndarray
    v: np.ndarray
    landed: int
    mode: str
    armed: bool
    airborne: bool

    @property
    def speed(self) -> float:
        return float(np.linalg.norm(self.v))


def record(v: EmulatedVehicle, t0: float, seconds: float,
           each: Callable[[float], object] | None = None) -> list[Sample]:
    """Fly ``seconds`` from ``t0`` as ``fly`` does, and keep every step's state."""
    samples: list[Sample] = []
    for k in range(1, round(seconds / DT) + 1):
        now = t0 + k * DT
        if each is not None:
            each(now)
        v.fly(DT, now)
        samples.append(Sample(now, v.position_w, v.velocity_w, v.landed_state, v.mode, v.armed,
                              v.airborne))
    return samples


def first(samples: list[Sample], condition: Callable[[Sample], bool]) -> Sample:
    return next(s for s in samples if condition(s))


def horizontal_distance(p: np.ndarray, xy: np.ndarray) -> float:
    return math.hypot(float(p[0] - xy[0]), float(p[1] - xy[1]))


def takeoff(a: Agent, altitude_m: float = math.nan) -> bytes:
    return a.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)


def ardupilot_on_the_ground_armed(a: Agent, t: float = 1.0) -> EmulatedVehicle:
    """start="ground" → GUIDED → armed: ready for a takeoff."""
    v = make("ardupilot", start="ground")
    assert acks(v.receive(a.set_mode(4), t)) == [(176, ACCEPTED)]
    assert acks(v.receive(a.arm(), t)) == [(400, ACCEPTED)]
    assert v.armed and v.mode == "GUIDED" and not v.airborne and v.landed_state == ON_GROUND
    assert not v.accepting_setpoints  # ArduPilot: not before it is in the air
    return v


# ---------------------------------------------------------------- takeoff
def test_ardupilot_takeoff_spools_up_climbs_and_reports_in_air() -> None:
    a = Agent()
    v = ardupilot_on_the_ground_armed(a, 1.0)
    model = FLIGHT_MODELS["ardupilot"]
    target = GROUND + 4.0
    assert acks(v.receive(takeoff(a, 4.0), 1.0)) == [(22, ACCEPTED)]
    assert v.mode == "GUIDED" and v.landed_state == ON_GROUND  # spooling up
    trace = record(v, 1.0, 20.0)
    liftoff = 1.0 + model.takeoff_delay_s
    spool_up = [s for s in trace if s.t < liftoff - EPS]
    assert spool_up and all(s.p[2] == GROUND and s.landed == ON_GROUND and not s.airborne
                            and s.armed for s in spool_up)
    up = first(trace, lambda s: s.p[2] > GROUND)
    assert up.t == pytest.approx(liftoff, abs=EPS) and up.airborne
    climbing = [s for s in trace if s.t >= up.t and s.landed == TAKING_OFF]
    assert climbing and climbing[0] is up
    assert max(s.v[2] for s in trace) == pytest.approx(model.takeoff_speed_m_s)  # peak rate
    assert all(s.v[2] <= model.takeoff_speed_m_s + EPS for s in trace)
    done = first(trace, lambda s: s.landed == IN_AIR)
    assert abs(done.p[2] - target) <= model.takeoff_done_m
    assert all(s.landed == IN_AIR for s in trace if s.t >= done.t)
    assert all(s.mode == "GUIDED" and s.armed for s in trace)
    final = trace[-1]
    assert final.p[2] == pytest.approx(target, abs=1e-3) and final.speed < 1e-3  # holds there
    np.testing.assert_array_equal(final.p[:2], START[:2])  # straight up
    assert v.accepting_setpoints
    (es,) = of_type(v.telemetry(0, final.t), "EXTENDED_SYS_STATE")
    assert es.landed_state == IN_AIR


@pytest.mark.parametrize("altitude", [math.nan, 0.0, -3.0])
def test_ardupilot_takeoff_needs_an_altitude_above_the_ground(altitude: float) -> None:
    a = Agent()
    v = ardupilot_on_the_ground_armed(a)
    assert acks(v.receive(takeoff(a, altitude), 1.0)) == [(22, mav.MAV_RESULT_FAILED)]
    trace = record(v, 1.0, 6.0)
    assert all(s.p[2] == GROUND and s.landed == ON_GROUND for s in trace)


def test_ardupilot_takeoff_in_the_air_failed() -> None:
    a = Agent()
    v = make("ardupilot")
    assert acks(v.receive(takeoff(a, 10.0), 1.0)) == [(22, mav.MAV_RESULT_FAILED)]
    trace = record(v, 1.0, 8.0)
    assert all(np.array_equal(s.p, START) and s.landed == IN_AIR and s.mode == "GUIDED"
               for s in trace)  # GUIDED without a setpoint holds where it is
    # after a takeoff from the ground too: the next one, in the air, is FAILED
    v = ardupilot_on_the_ground_armed(a)
    v.receive(takeoff(a, 3.0), 1.0)
    fly(v, 1.0, 15.0)
    assert v.landed_state == IN_AIR
    assert acks(v.receive(takeoff(a, 6.0), 16.0)) == [(22, mav.MAV_RESULT_FAILED)]


def test_px4_takeoff_in_the_air_climbs_again_and_holds() -> None:
    """Measured: AUTO.TAKEOFF in the air climbs MIS_TAKEOFF_ALT above where it is."""
    a = Agent()
    v = make("px4")
    assert acks(v.receive(takeoff(a), 1.0)) == [(22, ACCEPTED)]
    assert v.mode == "TAKEOFF" and v.landed_state == IN_AIR
    trace = record(v, 1.0, 15.0)
    target = START[2] + v.params["MIS_TAKEOFF_ALT"]
    hold = first(trace, lambda s: s.mode == "LOITER")
    assert abs(hold.p[2] - target) <= v.flight_model.takeoff_done_m
    assert all(s.landed == IN_AIR for s in trace)
    assert trace[-1].p[2] == pytest.approx(target, abs=1e-3)


def test_px4_takeoff_command_while_disarmed_then_arming_takes_off() -> None:
    """Measured: NAV_TAKEOFF disarmed → AUTO.TAKEOFF on the ground; arming takes off to
    MIS_TAKEOFF_ALT, after the spool-up; within takeoff_done_m: IN_AIR and Hold."""
    a = Agent()
    v = make("px4", start="ground")
    model = FLIGHT_MODELS["px4"]
    assert acks(v.receive(takeoff(a), 1.0)) == [(22, ACCEPTED)]
    assert v.mode == "TAKEOFF" and not v.armed and v.landed_state == ON_GROUND
    assert acks(v.receive(a.arm(), 1.0)) == [(400, ACCEPTED)]
    assert v.landed_state == TAKING_OFF and not v.airborne
    trace = record(v, 1.0, 15.0)
    liftoff = 1.0 + model.takeoff_delay_s
    assert all(s.p[2] == GROUND and s.landed == TAKING_OFF for s in trace
               if s.t < liftoff - EPS)
    assert first(trace, lambda s: s.p[2] > GROUND).t == pytest.approx(liftoff, abs=EPS)
    target = GROUND + v.params["MIS_TAKEOFF_ALT"]
    hold = first(trace, lambda s: s.mode == "LOITER")
    climb = [s for s in trace if s.t < hold.t]
    assert all(s.mode == "TAKEOFF" and s.v[2] <= model.takeoff_speed_m_s + EPS for s in climb)
    assert max(s.v[2] for s in climb) == pytest.approx(model.takeoff_speed_m_s)
    assert hold.landed == IN_AIR and abs(hold.p[2] - target) <= model.takeoff_done_m
    assert trace[-1].p[2] == pytest.approx(target, abs=1e-3) and trace[-1].armed


@pytest.mark.parametrize("armed_first", [True, False])
def test_px4_takeoff_to_param7(armed_first: bool) -> None:
    """A finite param7 is the takeoff altitude (metres above the origin here), also when
    the command came while disarmed and arming takes off."""
    a = Agent()
    v = make("px4", start="ground")
    if armed_first:
        v.receive(a.arm(), 1.0)
    assert acks(v.receive(takeoff(a, 6.0), 1.0)) == [(22, ACCEPTED)]
    if not armed_first:
        v.receive(a.arm(), 1.0)
    assert v.mode == "TAKEOFF" and v.landed_state == TAKING_OFF
    fly(v, 1.0, 20.0)
    assert v.mode == "LOITER" and v.landed_state == IN_AIR
    assert v.position_w[2] == pytest.approx(GROUND + 6.0, abs=1e-3)
    # AUTO.TAKEOFF by mode (no altitude) after a disarmed NAV_TAKEOFF: MIS_TAKEOFF_ALT
    v = make("px4", start="ground")
    v.receive(takeoff(a, 6.0), 1.0)
    v.receive(a.set_mode(4, 3), 1.0)
    v.receive(a.set_mode(4, 2), 1.0)
    v.receive(a.arm(), 1.0)
    fly(v, 1.0, 20.0)
    assert v.position_w[2] == pytest.approx(GROUND + v.params["MIS_TAKEOFF_ALT"], abs=1e-3)


# ---------------------------------------------------------------- arming, disarming
@pytest.mark.parametrize(("flavour", "result"), [("ardupilot", mav.MAV_RESULT_FAILED),
                                                 ("px4", mav.MAV_RESULT_TEMPORARILY_REJECTED)])
def test_disarm_in_the_air_refused_on_the_ground_accepted(flavour: str, result: int) -> None:
    a = Agent()
    v = make(flavour)
    replies = v.receive(a.arm(False), 1.0)
    assert acks(replies) == [(400, result)] and v.armed
    assert of_type(replies, "HEARTBEAT") == []  # nothing changed
    v.receive(a.command(mav.MAV_CMD_NAV_LAND), 1.0)
    t = 1.0
    while v.landed_state != ON_GROUND:  # descending, touched down, not yet detected: refused
        assert acks(v.receive(a.arm(False), t)) == [(400, result)] and v.armed
        t = fly(v, t, DT)
        assert t < 30.0
    assert v.armed  # landed just now: the auto-disarm has not come yet
    replies = v.receive(a.arm(False), t)
    assert acks(replies) == [(400, ACCEPTED)] and not v.armed
    assert len(of_type(replies, "HEARTBEAT")) == 1


@pytest.mark.parametrize(("flavour", "param"), [("ardupilot", "DISARM_DELAY"),
                                                ("px4", "COM_DISARM_PRFLT")])
def test_auto_disarm_on_the_ground_after_arming(flavour: str, param: str) -> None:
    a = Agent()
    v = make(flavour, start="ground")
    v.receive(a.arm(), 1.0)
    trace = record(v, 1.0, 12.0)
    off = first(trace, lambda s: not s.armed)
    assert off.t == pytest.approx(1.0 + v.params[param], abs=DT + EPS)  # 10 s
    texts = [m.text for m in of_type(v.telemetry(0, off.t), "STATUSTEXT")]
    assert texts == (["Disarming motors"] if flavour == "ardupilot" else [])
    # 0 means never
    v = make(flavour, start="ground")
    mav_type = mav.MAV_PARAM_TYPE_INT8 if flavour == "ardupilot" else mav.MAV_PARAM_TYPE_REAL32
    (pv,) = of_type(v.receive(a.pack(a.mav.param_set_encode(SYS, 1, param.encode(), 0.0,
                                                            mav_type)), 1.0), "PARAM_VALUE")
    assert pv.param_value == 0.0 and pv.param_type == mav_type
    v.receive(a.arm(), 1.0)
    fly(v, 1.0, 30.0)
    assert v.armed


# ---------------------------------------------------------------- ardupilot takeoff and setpoints
def test_ardupilot_setpoint_during_the_spool_up_cancels_the_takeoff() -> None:
    a = Agent()
    v = ardupilot_on_the_ground_armed(a, 1.0)
    v.receive(takeoff(a, 4.0), 1.0)
    t = fly(v, 1.0, 1.0)
    assert not v.airborne
    v.receive(a.setpoint([0.0, 0.0, 1.0]), t)
    assert v.ignored_setpoints == 1 and v.accepted_setpoints == 0
    trace = record(v, t, 7.0)  # well past the end of the spool-up (t = 4)
    assert all(s.p[2] == GROUND and not s.airborne and s.landed == ON_GROUND and s.armed
               and s.mode == "GUIDED" for s in trace)
    # still on the ground, armed: the auto-disarm DISARM_DELAY after arming
    off = first(record(v, trace[-1].t, 4.0), lambda s: not s.armed)
    assert off.t == pytest.approx(1.0 + v.params["DISARM_DELAY"], abs=DT + EPS)


def test_ardupilot_disarm_during_the_spool_up_accepted() -> None:
    a = Agent()
    v = ardupilot_on_the_ground_armed(a, 1.0)
    v.receive(takeoff(a, 4.0), 1.0)
    t = fly(v, 1.0, 2.0)
    assert acks(v.receive(a.arm(False), t)) == [(400, ACCEPTED)]
    assert all(s.p[2] == GROUND and not s.armed for s in record(v, t, 5.0))


def test_ardupilot_setpoint_during_the_climb_stops_the_climb() -> None:
    a = Agent()
    v = ardupilot_on_the_ground_armed(a, 1.0)
    v.receive(takeoff(a, 10.0), 1.0)
    t = fly(v, 1.0, 5.0)  # 3 s spool-up, 2 s of climb
    assert v.airborne and v.landed_state == TAKING_OFF
    assert v.position_w[2] > GROUND + 1.0
    p0 = v.position_w
    u = np.array([0.5, 0.0, 0.0])
    trace = record(v, t, 3.0, each=lambda now: v.receive(a.setpoint(u), now))
    assert v.landed_state == IN_AIR and v.accepted_setpoints == len(trace)
    assert all(s.p[2] == p0[2] and np.array_equal(s.v, u) for s in trace)  # no more climbing
    assert trace[-1].p[0] == pytest.approx(p0[0] + 1.5)


def test_ardupilot_guid_timeout_stops_the_vehicle_in_guided_armed() -> None:
    a = Agent()
    v = ardupilot_flying(a, 10.0)
    timeout = v.setpoint_timeout_s
    assert timeout == 3.0
    v.receive(a.setpoint([1.0, 0.0, 0.0]), 10.0)
    trace = record(v, 10.0, 8.0)
    moving = [s for s in trace if s.t <= 10.0 + timeout + EPS]
    stopped = [s for s in trace if s.t > 10.0 + timeout + EPS]
    assert all(np.array_equal(s.v, [1.0, 0.0, 0.0]) for s in moving)
    assert all(np.array_equal(s.v, [0.0, 0.0, 0.0]) for s in stopped)
    assert all(np.array_equal(s.p, stopped[0].p) for s in stopped)
    assert stopped[0].p[0] == pytest.approx(START[0] + timeout, abs=DT + EPS)
    assert all(s.mode == "GUIDED" and s.armed and s.landed == IN_AIR for s in trace)
    assert v.failsafe_active and v.failsafe_events == 1 and not v.accepting_setpoints
    # the next setpoint resumes
    v.receive(a.setpoint([0.0, 1.0, 0.0]), 18.1)
    v.fly(DT, 18.1)
    np.testing.assert_array_equal(v.velocity_w, [0.0, 1.0, 0.0])
    assert not v.failsafe_active and v.accepting_setpoints


def test_ardupilot_guid_timeout_with_a_lagging_response_the_vehicle_comes_to_rest() -> None:
    a = Agent()
    v = ardupilot_flying(a, 10.0, response=MEASURED_RESPONSE["ardupilot"])
    fly(v, 10.0, 2.0, each=lambda now: v.receive(a.setpoint([2.0, 0.0, 0.0]), now))
    assert v.velocity_w[0] > 1.5
    trace = record(v, 12.0, 10.0)  # silence: the timeout at 15.0
    assert trace[-1].speed < 1e-3 and v.failsafe_active and v.mode == "GUIDED" and v.armed
    assert np.linalg.norm(trace[-1].p - trace[-51].p) < 1e-3  # at rest


def test_ardupilot_guid_timeout_freezes_a_position_velocity_target() -> None:
    """ArduPilot moves a position + velocity target on with its velocity; at GUID_TIMEOUT
    the target stays where it had got to and the vehicle goes there and stays."""
    a = Agent()
    v = ardupilot_flying(a, 10.0)
    v.receive(a.position_setpoint(START, [1.0, 0.0, 0.0]), 10.0)
    trace = record(v, 10.0, 25.0)
    assert v.failsafe_active and v.mode == "GUIDED"
    np.testing.assert_allclose(trace[-1].p, START + np.array([v.setpoint_timeout_s, 0.0, 0.0]),
                               atol=1e-3)
    assert trace[-1].speed < 1e-3


# ---------------------------------------------------------------- hold
@pytest.mark.parametrize(("flavour", "mode_args", "mode"), [("ardupilot", (17,), "BRAKE"),
                                                            ("px4", (4, 3), "LOITER")])
def test_hold_speed_decays_and_the_vehicle_stops(flavour: str, mode_args: tuple[int, ...],
                                                 mode: str) -> None:
    a = Agent()
    v = ardupilot_flying(a, 10.0) if flavour == "ardupilot" else px4_offboard_armed(a, 10.0)
    u = np.array([2.0, 0.0, 0.0])
    t = fly(v, 10.0, 2.0, each=lambda now: v.receive(a.setpoint(u), now))
    p0, v0 = v.position_w, v.velocity_w
    np.testing.assert_array_equal(v0, u)
    assert acks(v.receive(a.set_mode(*mode_args), t)) == [(176, ACCEPTED)] and v.mode == mode
    tau = v.flight_model.stop_time_constant_s  # measured: BRAKE 1.3 s, Hold 0.45 s
    trace = record(v, t, 12.0 * tau)
    speeds = [s.speed for s in trace]
    assert speeds[0] == pytest.approx(2.0, rel=0.05)  # no jolt
    assert all(later <= earlier + EPS for earlier, later in itertools.pairwise(speeds))
    at_tau = min(trace, key=lambda s: abs(s.t - (t + tau)))
    assert at_tau.speed == pytest.approx(2.0 * math.exp(-1.0), rel=0.05)  # e^(−t/τ)
    np.testing.assert_allclose(trace[-1].p, p0 + tau * v0, atol=1e-3)  # the stopping point
    assert trace[-1].speed < 1e-3
    assert all(s.p[2] == p0[2] and s.mode == mode and s.armed for s in trace)
    assert not v.failsafe_active
    # and it stays there
    rest = record(v, trace[-1].t, 5.0)
    np.testing.assert_allclose(rest[-1].p, p0 + tau * v0, atol=1e-4)


# ---------------------------------------------------------------- land
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
@pytest.mark.parametrize("how", ["mode", "command"])
def test_land_descends_at_the_land_speed_lands_and_disarms(flavour: str, how: str) -> None:
    a = Agent()
    v = make(flavour)
    model = v.flight_model
    speed = 0.5 if flavour == "ardupilot" else 0.7  # LAND_SPEED 50 cm/s; MPC_LAND_SPEED
    if how == "command":
        message, command = a.command(mav.MAV_CMD_NAV_LAND), 21
    else:
        message, command = (a.set_mode(9) if flavour == "ardupilot" else a.set_mode(4, 6)), 176
    assert acks(v.receive(message, 1.0)) == [(command, ACCEPTED)]
    assert v.mode == "LAND" and v.landed_state == LANDING
    trace = record(v, 1.0, 20.0)
    descending = [s for s in trace if s.p[2] > GROUND]
    assert all(s.v[2] == -speed and s.landed == LANDING and s.armed for s in descending)
    assert all(np.array_equal(s.p[:2], START[:2]) for s in trace)  # straight down
    touchdown = first(trace, lambda s: s.p[2] == GROUND)
    assert touchdown.t == pytest.approx(1.0 + (START[2] - GROUND) / speed, abs=DT + EPS)
    landed = first(trace, lambda s: s.landed == ON_GROUND)
    assert landed.t - touchdown.t == pytest.approx(model.land_detect_s, abs=DT + EPS)
    off = first(trace, lambda s: not s.armed)
    disarm_s = model.landed_disarm_s if flavour == "ardupilot" else v.params["COM_DISARM_LAND"]
    assert off.t - landed.t == pytest.approx(disarm_s, abs=DT + EPS)
    assert all(s.p[2] == GROUND for s in trace if s.t >= touchdown.t)
    final = trace[-1]
    assert not final.armed and final.landed == ON_GROUND and not final.airborne
    # px4 goes back to the mode it was in before AUTO.LAND (air start: Hold)
    assert final.mode == ("LAND" if flavour == "ardupilot" else "LOITER")


def test_px4_land_from_offboard_goes_back_to_offboard_when_disarmed() -> None:
    a = Agent()
    v = px4_offboard_armed(a, 10.0)
    assert acks(v.receive(a.command(mav.MAV_CMD_NAV_LAND), 10.0)) == [(21, ACCEPTED)]
    trace = record(v, 10.0, 15.0)
    assert all(s.mode == "LAND" for s in trace if s.armed)
    assert not v.armed and v.mode == "OFFBOARD" and v.landed_state == ON_GROUND  # measured


@pytest.mark.parametrize(("flavour", "height", "speed"), [
    ("ardupilot", 4.0, 0.5), ("ardupilot", 25.0, 1.5),  # LAND_SPEED below 10 m, WPNAV_SPEED_DN
    ("px4", 3.0, 0.7), ("px4", 7.5, 1.1), ("px4", 25.0, 1.5),  # 0.7 below 5 m, linear, 1.5
])
def test_land_speed_depends_on_the_height(flavour: str, height: float, speed: float) -> None:
    a = Agent()
    v = EmulatedVehicle(DRONE, flavour, [START[0], START[1], GROUND + height],  # type: ignore[arg-type]
                        ORIGIN)
    v.receive(a.command(mav.MAV_CMD_NAV_LAND), 1.0)
    v.fly(DT, 1.0 + DT)
    assert v.velocity_w[2] == pytest.approx(-speed)


@pytest.mark.parametrize(("flavour", "param", "value", "speed"), [
    ("ardupilot", "LAND_SPEED", 80.0, 0.8), ("px4", "MPC_LAND_SPEED", 1.0, 1.0)])
def test_land_speed_parameter(flavour: str, param: str, value: float, speed: float) -> None:
    a = Agent()
    v = make(flavour)
    mav_type = mav.MAV_PARAM_TYPE_INT16 if flavour == "ardupilot" else mav.MAV_PARAM_TYPE_REAL32
    v.receive(a.pack(a.mav.param_set_encode(SYS, 1, param.encode(), value, mav_type)), 1.0)
    assert v.params[param] == value
    v.receive(a.command(mav.MAV_CMD_NAV_LAND), 1.0)
    trace = record(v, 1.0, 2.0)
    assert all(s.v[2] == pytest.approx(-speed) for s in trace)


def test_parameter_set_keeps_the_value_when_out_of_range() -> None:
    a = Agent()
    v = make("ardupilot")

    def set_param(name: str, value: float, mav_type: int) -> float:
        (pv,) = of_type(v.receive(a.pack(a.mav.param_set_encode(SYS, 1, name.encode(), value,
                                                                mav_type)), 1.0), "PARAM_VALUE")
        assert pv.param_id == name and pv.param_type == mav_type
        assert pv.param_value == v.params[name]
        return v.params[name]

    assert set_param("LAND_SPEED", 20.0, mav.MAV_PARAM_TYPE_INT16) == 50.0  # below 30 cm/s
    assert set_param("LAND_SPEED", 80.4, mav.MAV_PARAM_TYPE_INT16) == 80.0  # an integer
    assert set_param("GUID_TIMEOUT", 0.0, mav.MAV_PARAM_TYPE_REAL32) == 3.0  # must be > 0
    assert set_param("GUID_TIMEOUT", math.nan, mav.MAV_PARAM_TYPE_REAL32) == 3.0
    assert set_param("RTL_ALT", 2500.0, mav.MAV_PARAM_TYPE_INT32) == 2500.0


# ---------------------------------------------------------------- pilot modes without RC
@pytest.mark.parametrize(("number", "mode"), [(0, "STABILIZE"), (2, "ALT_HOLD"), (5, "LOITER"),
                                              (16, "POSHOLD")])
def test_ardupilot_pilot_mode_without_rc_sinks_and_lands(number: int, mode: str) -> None:
    a = Agent()
    v = make("ardupilot")
    model = v.flight_model
    assert acks(v.receive(a.set_mode(number), 1.0)) == [(176, ACCEPTED)] and v.mode == mode
    trace = record(v, 1.0, 16.0)
    assert all(s.v[2] == -model.pilot_sink_m_s for s in trace if s.p[2] > GROUND)  # 2.5 m/s
    assert all(np.array_equal(s.p[:2], START[:2]) for s in trace)
    touchdown = first(trace, lambda s: s.p[2] == GROUND)
    assert touchdown.t == pytest.approx(1.0 + (START[2] - GROUND) / model.pilot_sink_m_s,
                                        abs=DT + EPS)
    landed = first(trace, lambda s: s.landed == ON_GROUND)
    assert landed.t - touchdown.t == pytest.approx(model.land_detect_s, abs=DT + EPS)
    off = first(trace, lambda s: not s.armed)  # DISARM_DELAY after landing
    assert off.t - landed.t == pytest.approx(v.params["DISARM_DELAY"], abs=DT + EPS)
    assert v.mode == mode


# ---------------------------------------------------------------- return
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_rtl_climbs_returns_home_and_lands(flavour: str) -> None:
    a = Agent()
    v = make(flavour)
    assert acks(v.receive(a.command(mav.MAV_CMD_NAV_RETURN_TO_LAUNCH), 1.0)) \
        == [(20, ACCEPTED)]
    assert v.mode == "RTL" and v.landed_state == IN_AIR
    trace = record(v, 1.0, 90.0)
    # ArduCopter: RTL_ALT 15 m (the cone allows it 5 m from home); PX4: RTL_RETURN_ALT 30 m
    altitude = GROUND + (15.0 if flavour == "ardupilot" else 30.0)
    top = max(trace, key=lambda s: s.p[2])
    assert top.p[2] == pytest.approx(altitude, abs=0.1)
    climb_speed = 2.5 if flavour == "ardupilot" else 3.0  # WPNAV_SPEED_UP; MPC_Z_V_AUTO_UP
    assert max(s.v[2] for s in trace) == pytest.approx(climb_speed)
    home = first(trace, lambda s: horizontal_distance(s.p, HOME_XY) <= 0.2)
    assert home.t > top.t - 1.0 and home.p[2] == pytest.approx(altitude, abs=0.1)
    landing = [s for s in trace if s.landed == LANDING]
    assert landing and landing[0].t >= home.t
    assert all(s.landed == IN_AIR for s in trace if s.t < landing[0].t)
    assert all(horizontal_distance(s.p, HOME_XY) <= 0.2 for s in trace if s.t >= home.t)
    if flavour == "ardupilot":  # RTL_LOIT_TIME 5 s at home before it lands
        assert landing[0].t - home.t == pytest.approx(5.0, abs=2 * DT)
        assert landing[0].p[2] == pytest.approx(altitude, abs=0.1)
    else:  # descends to RTL_DESCEND_ALT at 1.5 m/s, then lands (RTL_LAND_DELAY 0)
        assert landing[0].p[2] == pytest.approx(GROUND + 10.0, abs=0.15)
        assert min(s.v[2] for s in trace) == pytest.approx(-1.5)
    final = trace[-1]
    assert final.p[2] == GROUND and final.landed == ON_GROUND and not final.armed
    assert horizontal_distance(final.p, HOME_XY) <= 0.2
    assert final.mode == ("RTL" if flavour == "ardupilot" else "LOITER")


def test_px4_rtl_with_a_negative_land_delay_descends_and_hovers_for_ever() -> None:
    """RTL_LAND_DELAY < 0: after the descent to RTL_DESCEND_ALT the vehicle never lands."""
    a = Agent()
    v = make("px4")
    v.receive(a.pack(a.mav.param_set_encode(SYS, 1, b"RTL_LAND_DELAY", -1.0,
                                            mav.MAV_PARAM_TYPE_REAL32)), 1.0)
    assert v.params["RTL_LAND_DELAY"] == -1.0
    assert acks(v.receive(a.command(mav.MAV_CMD_NAV_RETURN_TO_LAUNCH), 1.0)) \
        == [(20, ACCEPTED)]
    trace = record(v, 1.0, 120.0)
    assert max(s.p[2] for s in trace) == pytest.approx(GROUND + 30.0, abs=0.1)
    final = trace[-1]
    assert final.p[2] == pytest.approx(GROUND + v.params["RTL_DESCEND_ALT"], abs=0.15)
    assert horizontal_distance(final.p, HOME_XY) <= 0.2 and final.speed < 1e-3
    assert all(s.landed == IN_AIR and s.armed and s.mode == "RTL" for s in trace)


# ---------------------------------------------------------------- px4 offboard
def test_px4_offboard_on_the_ground_lifts_off_after_the_delay_and_climbs() -> None:
    a = Agent()
    v = make("px4", start="ground")
    model = FLIGHT_MODELS["px4"]
    target = v.position_w + np.array([0.0, 0.0, 3.0])

    def send(now: float) -> None:
        v.receive(a.position_setpoint(target), now)

    send(0.9)
    send(0.95)
    assert acks(v.receive(a.set_mode(6), 1.0)) == [(176, ACCEPTED)]
    assert acks(v.receive(a.arm(), 1.0)) == [(400, ACCEPTED)]
    trace = record(v, 1.0, 14.0, each=send)
    liftoff = 1.0 + model.offboard_takeoff_delay_s  # after arming (the request came before)
    before = [s for s in trace if s.t < liftoff - EPS]
    assert before and all(s.p[2] == GROUND and not s.airborne and s.landed == ON_GROUND
                          for s in before)
    up = first(trace, lambda s: s.p[2] > GROUND)
    assert up.t == pytest.approx(liftoff, abs=DT + EPS)  # the vehicle sees it when it flies
    assert all(s.landed == IN_AIR and s.airborne for s in trace if s.t >= up.t)
    np.testing.assert_allclose(trace[-1].p, target, atol=1e-2)
    assert all(s.mode == "OFFBOARD" and s.armed for s in trace)  # no auto-disarm once up


def test_px4_offboard_liftoff_counts_from_the_request_when_later_than_arming() -> None:
    a = Agent()
    v = make("px4", start="ground")
    target = [v.position_w]  # first at ground level: no climb asked

    def send(now: float) -> None:
        v.receive(a.position_setpoint(target[0]), now)

    send(0.9)
    send(0.95)
    v.receive(a.set_mode(6), 1.0)
    v.receive(a.arm(), 1.0)
    trace = record(v, 1.0, 4.0, each=send)
    assert all(s.p[2] == GROUND and s.landed == ON_GROUND for s in trace)
    target[0] = v.position_w + np.array([0.0, 0.0, 3.0])
    trace = record(v, 5.0, 4.0, each=send)
    up = first(trace, lambda s: s.p[2] > GROUND)
    assert up.t == pytest.approx(5.0 + DT + v.flight_model.offboard_takeoff_delay_s, abs=EPS)


def test_px4_offboard_loss_holds_and_setpoints_bring_offboard_back() -> None:
    a = Agent()
    v = px4_offboard_armed(a, 10.0)
    u = np.array([1.0, 0.0, 0.0])

    def send(now: float) -> None:
        v.receive(a.setpoint(u), now)

    t = fly(v, 10.0, 2.0, each=send)
    silence = record(v, t, 4.0)
    loss = first(silence, lambda s: s.mode == "LOITER")
    assert loss.t == pytest.approx(t + v.setpoint_timeout_s, abs=DT + EPS)  # COM_OF_LOSS_T
    assert all(np.array_equal(s.v, u) and s.mode == "OFFBOARD" for s in silence
               if s.t < loss.t)
    assert silence[-1].speed < 5e-3 and v.failsafe_active and v.failsafe_events == 1
    assert v.armed and v.landed_state == IN_AIR
    again = record(v, silence[-1].t, 1.0, each=send)
    back = first(again, lambda s: s.mode == "OFFBOARD")
    assert back.t - silence[-1].t <= 2 * DT + EPS  # two setpoints are a stream
    assert not v.failsafe_active and v.mode == "OFFBOARD"
    np.testing.assert_array_equal(again[-1].v, u)


# ---------------------------------------------------------------- position setpoints
@pytest.mark.parametrize("mask", [0x0DF8, 0x09F8, 0x05F8, 0x01F8])
@pytest.mark.parametrize(("distance", "speed"), [
    (0.5, 0.5), (1.0, 1.0), (1.5, 1.5),  # the position loop, gain 1/s
    (2.5, math.sqrt(5.0)),  # decelerating at 1 m/s² further out: √(2·a·d)
    (5.0, 3.0),  # at most u_max
])
def test_position_only_setpoint_commands_the_position_loop(mask: int, distance: float,
                                                           speed: float) -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    v.receive(a.position_setpoint(START + np.array([distance, 0.0, 0.0]), mask=mask), 10.01)
    assert v.rejected_frames == 0
    np.testing.assert_allclose(v.commanded_velocity_w(10.01), [speed, 0.0, 0.0], rtol=1e-12)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_position_setpoint_is_flown_to_and_held(flavour: str) -> None:
    a = Agent()
    v = ardupilot_flying(a, 10.0) if flavour == "ardupilot" else px4_offboard_armed(a, 10.0)
    target = START + np.array([4.0, -3.0, 2.0])
    trace = record(v, 10.0, 15.0, each=lambda now: v.receive(a.position_setpoint(target), now))
    np.testing.assert_allclose(trace[-1].p, target, atol=1e-3)
    assert trace[-1].speed < 1e-3 and max(np.max(np.abs(s.v)) for s in trace) <= 3.0
    assert not v.failsafe_active


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, 3, elements=st.floats(-20, 20)),
       st.sampled_from([POSITION_VELOCITY_MASK, 0x09C0, FULL_MASK, 0x0800]),
       st.sampled_from(["px4", "ardupilot"]))
def test_position_velocity_setpoint_lockstep_applies_the_feed_forward(
        u: np.ndarray, mask: int, flavour: str) -> None:
    """Lockstep integrates what the agent integrated: the velocity, bit for bit clamped."""
    a = Agent()
    v = px4_offboard_armed(a) if flavour == "px4" else ardupilot_flying(a)
    v.begin_step(40)
    v.receive(a.position_setpoint(START + np.array([3.0, 1.0, -1.0]), u, [0.5, 0.5, 0.5], stamp=40,
                                  mask=mask), 10.01)
    assert v.rejected_frames == 0
    expected = clamp_velocity(frames.velocity_over_link(u), 3.0)
    for got in (v.commanded_velocity_w(10.02), v.setpoint_stamped()):
        assert got is not None
        np.testing.assert_array_equal(got.view(np.uint64), expected.view(np.uint64))


def test_position_velocity_target_moves_on_ardupilot_not_px4() -> None:
    """ArduPilot moves the target on with the setpoint's velocity until the next one; PX4
    flies to the fixed position with the velocity fed forward (it settles 1 m ahead)."""
    a = Agent()
    moved: dict[str, float] = {}
    for flavour in ("ardupilot", "px4"):
        v = ardupilot_flying(a, 10.0) if flavour == "ardupilot" else px4_offboard_armed(a, 10.0)
        v.receive(a.position_setpoint(START, [1.0, 0.0, 0.0]), 10.0)
        fly(v, 10.0, 0.9)
        moved[flavour] = float(v.position_w[0] - START[0])
    assert moved["ardupilot"] == pytest.approx(0.9, abs=0.05)
    assert moved["px4"] == pytest.approx(1.0 - math.exp(-0.9), abs=0.05)


@pytest.mark.parametrize(("kw", "accepted"), [
    ({"position_w": [np.nan, 0.0, 0.0]}, False),  # used position
    ({"vel_w": [0.0, np.inf, 0.0]}, False),  # used velocity
    ({"vel_w": [0.0, 0.0, 0.0], "accel_w": [0.0, 0.0, np.nan]}, False),  # used acceleration
    ({"vel_w": [0.0, 0.0, 0.0], "accel_w": [0.0, 0.0, np.nan],
      "mask": POSITION_VELOCITY_MASK}, True),  # the acceleration is not used
    ({"vel_w": [np.nan, 0.0, 0.0], "mask": 0x0DF8}, True),  # the velocity is not used
])
def test_non_finite_fields_reject_a_setpoint_only_when_used(kw: dict[str, Any],
                                                            accepted: bool) -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    position = kw.pop("position_w", START + np.array([1.0, 0.0, 0.0]))
    before = v.accepted_setpoints
    v.receive(a.position_setpoint(position, **kw), 10.01)
    assert (v.accepted_setpoints == before + 1) is accepted
    assert v.rejections == ({} if accepted else {"nonfinite_setpoint": 1})
    assert v.nonfinite_setpoints == (0 if accepted else 1)


# ---------------------------------------------------------------- velocity response
responses = st.builds(VelocityResponse, st.floats(0.01, 2.0),
                      st.one_of(st.just(0.0), st.floats(0.1, 10.0)))
commands = arrays(np.float64, 3, elements=st.floats(-5, 5))


@settings(max_examples=80, deadline=None)
@given(commands, responses, st.sampled_from(["px4", "ardupilot"]))
def test_fly_lags_as_step_vehicle_of_the_same_inputs(u: np.ndarray, response: VelocityResponse,
                                                     flavour: str) -> None:
    a = Agent()
    v = px4_offboard_armed(a, response=response) if flavour == "px4" \
        else ardupilot_flying(a, response=response)
    assert v.response is response
    v.receive(a.setpoint(u), 10.0)
    applied = v.commanded_velocity_w(10.0)
    p, vel = v.position_w, v.velocity_w
    np.testing.assert_array_equal(vel, 0.0)
    for k in range(1, 20):
        p, vel = step_vehicle(p, vel, applied, 3.0, DT, response)
        v.fly(DT, 10.0 + k * DT)
        np.testing.assert_array_equal(v.velocity_w.view(np.uint64), vel.view(np.uint64))
        np.testing.assert_array_equal(v.position_w.view(np.uint64), p.view(np.uint64))
        if k == 1 and np.any(applied != 0.0):  # it lags: one step does not reach u
            assert np.linalg.norm(v.velocity_w) < np.linalg.norm(applied)


@settings(max_examples=100, deadline=None)
@given(arrays(np.float64, 3, elements=st.floats(-100, 100)),
       st.lists(arrays(np.float64, 3, elements=st.floats(-3, 3)), min_size=1, max_size=20),
       st.floats(1e-3, 0.1), st.sampled_from(["px4", "ardupilot"]))
def test_integrate_with_the_ideal_response_is_p_plus_dt_v_bit_for_bit(
        p0: np.ndarray, velocities: list[np.ndarray], dt: float, flavour: str) -> None:
    origin = np.array([0.0, 0.0, -1000.0])  # far below: the ground plays no part
    v = EmulatedVehicle(DRONE, flavour, p0, origin)  # type: ignore[arg-type]
    p = p0.copy()
    for velocity in velocities:
        v.integrate(dt, velocity)
        p = p + dt * velocity
        np.testing.assert_array_equal(v.position_w.view(np.uint64), p.view(np.uint64))
        np.testing.assert_array_equal(v.velocity_w, velocity)


@settings(max_examples=50, deadline=None)
@given(commands, responses)
def test_integrate_with_a_response_is_step_vehicle(u: np.ndarray,
                                                   response: VelocityResponse) -> None:
    v = make("ardupilot", response=response)
    p, vel = START.copy(), np.zeros(3)
    for _ in range(10):
        v.integrate(DT, u)
        p, vel = step_vehicle(p, vel, u, 3.0, DT, response)
        np.testing.assert_array_equal(v.position_w.view(np.uint64), p.view(np.uint64))
        np.testing.assert_array_equal(v.velocity_w.view(np.uint64), vel.view(np.uint64))


def test_integrate_stops_at_the_ground() -> None:
    v = make("px4")
    for _ in range(100):
        v.integrate(DT, [1.0, 0.0, -3.0])
    assert v.position_w[2] == GROUND and v.velocity_w[2] == 0.0
    assert v.position_w[0] == pytest.approx(START[0] + 2.0)


# ---------------------------------------------------------------- the ground
_MODES = {"px4": [(6, 0), (4, 3), (4, 2), (4, 6), (4, 5), (3, 0)],
          "ardupilot": [(n, 0) for n in (0, 2, 3, 4, 5, 6, 9, 16, 17)]}
vectors = arrays(np.float64, 3, elements=st.floats(-40, 40))
actions = st.one_of(
    st.tuples(st.just("velocity"), vectors),
    st.tuples(st.just("position"), vectors),
    st.tuples(st.just("position_velocity"), vectors, vectors),
    st.tuples(st.just("mode"), st.integers(0, 99)),
    st.tuples(st.just("arm"), st.booleans()),
    st.tuples(st.just("takeoff"), st.floats(-5, 30)),
    st.tuples(st.just("land")),
    st.tuples(st.just("rtl")),
    st.tuples(st.just("wait")),
)


@settings(max_examples=120, deadline=None)
@given(st.sampled_from(["px4", "ardupilot"]), st.sampled_from(["air", "ground", "takeoff"]),
       st.booleans(),
       st.lists(st.tuples(actions, st.integers(0, 150), st.booleans()), max_size=12))
def test_the_ground_is_never_crossed(flavour: str, start: str, measured: bool,
                                     script: list[tuple[Any, int, bool]]) -> None:
    """Whatever is commanded, the vehicle stays at or above the ground (z = origin_w[2]),
    and a vehicle that is not airborne (in particular any disarmed one) rests on it."""
    a = Agent()
    response = MEASURED_RESPONSE[flavour] if measured else VelocityResponse()  # type: ignore[index]
    v = make(flavour, start="air" if start == "air" else "ground", response=response)
    t = 1.0
    if start == "takeoff":  # a scripted takeoff first, for flights that start on the ground
        if flavour == "ardupilot":
            v.receive(a.set_mode(4), t)
        v.receive(a.arm(), t)
        v.receive(takeoff(a, 3.0), t)

    def check() -> None:
        p = v.position_w
        assert np.all(np.isfinite(p)) and np.all(np.isfinite(v.velocity_w))
        assert p[2] >= GROUND
        if not v.airborne or not v.armed or v.landed_state == ON_GROUND:
            assert p[2] == GROUND and v.landed_state in (ON_GROUND, TAKING_OFF)
        if not v.airborne:
            np.testing.assert_array_equal(v.velocity_w, 0.0)

    check()
    for action, steps, stream in script:
        kind = action[0]
        message: bytes | None
        if kind == "velocity":
            message = a.setpoint(action[1])
        elif kind == "position":
            message = a.position_setpoint(START + action[1])
        elif kind == "position_velocity":
            message = a.position_setpoint(START + action[1], action[2])
        elif kind == "mode":
            modes = _MODES[flavour]
            message = a.set_mode(*modes[action[1] % len(modes)])
        elif kind == "arm":
            message = a.arm(action[1])
        elif kind == "takeoff":
            message = takeoff(a, action[1])
        elif kind == "land":
            message = a.command(mav.MAV_CMD_NAV_LAND)
        elif kind == "rtl":
            message = a.command(mav.MAV_CMD_NAV_RETURN_TO_LAUNCH)
        else:
            message = None
        if message is not None:
            v.receive(message, t)
        check()
        for _ in range(steps):
            t += DT
            if stream and message is not None and kind in ("velocity", "position",
                                                           "position_velocity"):
                v.receive(message, t)
            v.fly(DT, t)
            check()
    assert not any(k.startswith(("handler_error", "parser_error")) for k in v.rejections)
