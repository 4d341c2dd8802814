"""The emulated vehicle's MAVLink side (sim_world.vehicle.protocol.EmulatedVehicle: pure
protocol, explicit times) and its UDP endpoint.

The "agent" side of these tests is a real pymavlink MAVLink 2 encoder/parser; no byte is
packed by hand except deliberate corruption.
"""

from __future__ import annotations

import select
import socket

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.mavlink_endpoint import VehicleEndpoint
from sim_world.vehicle import EmulatedVehicle
from sim_world.vehicle import VehicleEndpoint as ReExported
from swarm.models import frames
from swarm.models.kinematics import clamp_velocity
from tests.helpers.vehicle_tools import (
    ORIGIN,
    START,
    SYS,
    Agent,
    acks,
    ardupilot_flying,
    fly,
    make,
    of_type,
    parse,
    px4_offboard_armed,
)


# ---------------------------------------------------------------- heartbeat
@pytest.mark.parametrize(("flavour", "autopilot", "mode", "custom"), [
    ("px4", mav.MAV_AUTOPILOT_PX4, "LOITER", (4 << 16) | (3 << 24)),
    ("ardupilot", mav.MAV_AUTOPILOT_ARDUPILOTMEGA, "STABILIZE", 0),
])
def test_heartbeat_contents(flavour: str, autopilot: int, mode: str, custom: int) -> None:
    v = make(flavour, start="ground")
    (hb,) = parse([v.heartbeat()])
    assert hb.get_type() == "HEARTBEAT"
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (SYS, 1)
    assert hb.type == mav.MAV_TYPE_QUADROTOR and hb.autopilot == autopilot
    assert hb.base_mode == mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.custom_mode == custom and hb.system_status == mav.MAV_STATE_STANDBY
    assert mavutil.mode_string_v10(hb) == v.mode == mode
    v.receive(Agent().arm(), 1.0)
    (hb,) = parse([v.heartbeat()])
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.system_status == mav.MAV_STATE_ACTIVE
    assert mavutil.mode_string_v10(hb) == mode  # arming changes no mode


@pytest.mark.parametrize(("flavour", "mode", "custom"), [
    ("px4", "LOITER", (4 << 16) | (3 << 24)), ("ardupilot", "GUIDED", 4)])
def test_air_start_is_armed_and_hovering(flavour: str, mode: str, custom: int) -> None:
    v = make(flavour)
    (hb,) = parse([v.heartbeat()])
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == mav.MAV_STATE_ACTIVE and hb.custom_mode == custom
    assert mavutil.mode_string_v10(hb) == v.mode == mode
    assert v.armed and v.airborne and v.landed_state == mav.MAV_LANDED_STATE_IN_AIR
    np.testing.assert_array_equal(v.position_w, START)
    (es,) = of_type(v.telemetry(0, 0.0), "EXTENDED_SYS_STATE")
    assert es.landed_state == mav.MAV_LANDED_STATE_IN_AIR


@pytest.mark.parametrize(("flavour", "mode"), [("px4", "LOITER"), ("ardupilot", "STABILIZE")])
def test_ground_start_is_disarmed_on_the_ground_below_the_start(flavour: str,
                                                                 mode: str) -> None:
    v = make(flavour, start="ground")
    assert not v.armed and not v.airborne and v.mode == mode
    assert v.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    np.testing.assert_array_equal(v.position_w, [START[0], START[1], ORIGIN[2]])
    assert v.ground_z_m == ORIGIN[2]
    (lp,) = of_type(v.receive(Agent().command(512, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
                              1.0), "LOCAL_POSITION_NED")
    assert (lp.x, lp.y, lp.z) == (4.0, 3.0, 0.0)  # at home height: the NED origin's


def test_heartbeat_reports_offboard_and_guided() -> None:
    a = Agent()
    (hb,) = parse([px4_offboard_armed(a).heartbeat()])
    assert (hb.custom_mode >> 16) & 0xFF == 6 and mavutil.mode_string_v10(hb) == "OFFBOARD"
    (hb,) = parse([ardupilot_flying(a).heartbeat()])
    assert hb.custom_mode == 4 and mavutil.mode_string_v10(hb) == "GUIDED"


# ---------------------------------------------------------------- commands
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_arm_disarm_acks_and_immediate_heartbeat(flavour: str) -> None:
    v, a = make(flavour, start="ground"), Agent()
    replies = v.receive(a.arm(), 1.0)
    (ack,) = of_type(replies, "COMMAND_ACK")
    assert (ack.command, ack.result) == (400, mav.MAV_RESULT_ACCEPTED)
    assert (ack.target_system, ack.target_component) == (SYS, mav.MAV_COMP_ID_ONBOARD_COMPUTER)
    (hb,) = of_type(replies, "HEARTBEAT")
    assert hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and v.armed
    assert acks(v.receive(a.arm(), 1.1)) == [(400, mav.MAV_RESULT_ACCEPTED)]  # idempotent
    assert of_type(v.receive(a.arm(), 1.2), "HEARTBEAT") == []  # no change, no extra HB
    replies = v.receive(a.arm(False), 1.3)  # on the ground: accepted
    assert acks(replies) == [(400, mav.MAV_RESULT_ACCEPTED)]
    (hb,) = of_type(replies, "HEARTBEAT")
    assert not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED and not v.armed
    assert acks(v.receive(a.command(400, 7.0), 1.4)) == [(400, mav.MAV_RESULT_DENIED)]
    assert not v.armed


@pytest.mark.parametrize("start", ["air", "ground"])
@pytest.mark.parametrize(("flavour", "params", "mode"), [
    ("px4", (1, 4, 3), "LOITER"), ("px4", (1, 4, 6), "LAND"), ("px4", (1, 4, 5), "RTL"),
    ("px4", (1, 4, 2), "TAKEOFF"),
    ("ardupilot", (1, 4), "GUIDED"), ("ardupilot", (1, 5), "LOITER"),
    ("ardupilot", (1 | 128, 17), "BRAKE"), ("ardupilot", (1, 9), "LAND"),
    ("ardupilot", (1, 6), "RTL"), ("ardupilot", (1, 0), "STABILIZE"),
])
def test_set_mode_accepted(flavour: str, params: tuple[int, ...], mode: str,
                           start: str) -> None:
    v = make(flavour, start=start)
    armed = v.armed
    assert acks(v.receive(Agent().command(176, *params), 1.0)) == [(176, 0)]
    assert v.mode == mode and v.armed == armed  # a mode change never arms nor disarms
    (hb,) = parse([v.heartbeat()])
    assert mavutil.mode_string_v10(hb) == mode


@pytest.mark.parametrize("start", ["air", "ground"])
def test_px4_posctl_rejected_without_manual_control(start: str) -> None:
    v = make("px4", start=start)
    assert acks(v.receive(Agent().set_mode(3), 1.0)) \
        == [(176, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    assert v.mode == "LOITER"


@pytest.mark.parametrize("start", ["air", "ground"])
@pytest.mark.parametrize(("flavour", "params", "result"), [
    ("px4", (1, 9, 0), mav.MAV_RESULT_DENIED),  # unknown main mode
    ("px4", (0, 3, 0), mav.MAV_RESULT_DENIED),  # no CUSTOM_MODE_ENABLED
    ("px4", (1, 4, 7), mav.MAV_RESULT_DENIED),  # unknown AUTO sub mode
    ("px4", (1, float("nan"), 0), mav.MAV_RESULT_DENIED),
    ("ardupilot", (0, 4), mav.MAV_RESULT_DENIED),
    ("ardupilot", (1, float("nan")), mav.MAV_RESULT_DENIED),
    ("ardupilot", (1, 99), mav.MAV_RESULT_FAILED),  # no such mode number (measured)
])
def test_set_mode_refused(flavour: str, params: tuple[float, ...], result: int,
                          start: str) -> None:
    v = make(flavour, start=start)
    mode, armed = v.mode, v.armed
    assert acks(v.receive(Agent().command(176, *params), 1.0)) == [(176, result)]
    assert (v.mode, v.armed) == (mode, armed)


def test_ardupilot_auto_without_a_mission() -> None:
    """AUTO (no mission) is FAILED armed, accepted disarmed, and then not armable."""
    a = Agent()
    v = make("ardupilot")
    replies = v.receive(a.set_mode(3), 1.0)
    assert acks(replies) == [(176, mav.MAV_RESULT_FAILED)] and v.mode == "GUIDED"
    assert [m.text for m in of_type(replies, "STATUSTEXT")] \
        == ["Mode change to AUTO failed: no mission"]
    v = make("ardupilot", start="ground")
    assert acks(v.receive(a.set_mode(3), 1.0)) == [(176, mav.MAV_RESULT_ACCEPTED)]
    assert v.mode == "AUTO"
    replies = v.receive(a.arm(), 1.1)
    assert acks(replies) == [(400, mav.MAV_RESULT_FAILED)] and not v.armed
    assert [m.text for m in of_type(replies, "STATUSTEXT")] == ["Arm: Mode requires mission"]


@pytest.mark.parametrize(("mode", "number"), [("LAND", 9), ("RTL", 6), ("BRAKE", 17)])
def test_ardupilot_refuses_to_arm_in_a_mode_that_is_not_armable(mode: str,
                                                                 number: int) -> None:
    a = Agent()
    v = make("ardupilot", start="ground")
    assert acks(v.receive(a.set_mode(number), 1.0)) == [(176, 0)] and v.mode == mode
    replies = v.receive(a.arm(), 1.1)
    assert acks(replies) == [(400, mav.MAV_RESULT_FAILED)] and not v.armed
    assert [m.text for m in of_type(replies, "STATUSTEXT")] == [f"Arm: {mode} mode not armable"]
    assert of_type(replies, "HEARTBEAT") == []  # nothing changed


def test_legacy_set_mode_message_is_acked_with_its_message_id() -> None:
    v, a = make("ardupilot", start="ground"), Agent()
    replies = v.receive(a.pack(a.mav.set_mode_encode(SYS, 1, 4)), 1.0)
    assert acks(replies) == [(mav.MAVLINK_MSG_ID_SET_MODE, 0)] and v.mode == "GUIDED"
    assert len(of_type(replies, "HEARTBEAT")) == 1  # the mode changed
    v = make("px4")
    replies = v.receive(a.pack(a.mav.set_mode_encode(SYS, 1, (4 << 16) | (6 << 24))), 1.0)
    assert acks(replies) == [(11, 0)] and v.mode == "LAND"
    replies = v.receive(a.pack(a.mav.set_mode_encode(SYS, 1, 3 << 16)), 1.1)
    assert acks(replies) == [(11, mav.MAV_RESULT_TEMPORARILY_REJECTED)] and v.mode == "LAND"
    replies = v.receive(a.pack(a.mav.set_mode_encode(SYS, 0, 4 << 16)), 1.2)  # no custom flag
    assert acks(replies) == [(11, mav.MAV_RESULT_DENIED)] and v.mode == "LAND"


def test_command_int_is_handled_like_command_long() -> None:
    v, a = make("px4"), Agent()
    msg = a.mav.command_int_encode(SYS, 1, 0, 400, 0, 0, 1, 0, 0, 0, 0, 0, 0)
    assert acks(v.receive(a.pack(msg), 1.0)) == [(400, 0)] and v.armed


def test_unknown_command_is_unsupported() -> None:
    v = make("px4")
    assert acks(v.receive(Agent().command(mav.MAV_CMD_DO_SET_SERVO, 1, 1500), 1.0)) \
        == [(mav.MAV_CMD_DO_SET_SERVO, mav.MAV_RESULT_UNSUPPORTED)]


def test_request_message_autopilot_version_params_mission_timesync() -> None:
    for flavour, param, value in (("px4", "COM_OF_LOSS_T", 1.0),
                                  ("ardupilot", "GUID_TIMEOUT", 3.0)):
        v, a = make(flavour), Agent()
        replies = v.receive(a.command(512, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION), 1.0)
        assert acks(replies) == [(512, 0)]
        (ver,) = of_type(replies, "AUTOPILOT_VERSION")
        assert ver.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert ver.capabilities & mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        assert acks(v.receive(a.command(512, 12345), 1.0)) == [(512, mav.MAV_RESULT_DENIED)]
        assert of_type(v.receive(a.command(520), 1.0), "AUTOPILOT_VERSION")

        values = of_type(v.receive(a.pack(a.mav.param_request_list_encode(SYS, 1)), 1.0),
                         "PARAM_VALUE")
        pv = values[0]  # the setpoint timeout first
        assert (pv.param_id, pv.param_value, pv.param_count, pv.param_index) == (param, value,
                                                                                8, 0)
        assert [m.param_id for m in values] == list(v.params)
        assert [(m.param_count, m.param_index) for m in values] == [(8, i) for i in range(8)]
        assert [m.param_value for m in values] \
            == [float(np.float32(x)) for x in v.params.values()]  # a float field on the link
        set_msg = a.mav.param_set_encode(SYS, 1, param.encode(), 1.5, mav.MAV_PARAM_TYPE_REAL32)
        (pv,) = of_type(v.receive(a.pack(set_msg), 1.0), "PARAM_VALUE")
        assert pv.param_value == 1.5 and v.setpoint_timeout_s == 1.5
        read = a.mav.param_request_read_encode(SYS, 1, param.encode(), -1)
        assert of_type(v.receive(a.pack(read), 1.0), "PARAM_VALUE")[0].param_value == 1.5
        unknown = a.mav.param_request_read_encode(SYS, 1, b"NOPE", -1)
        assert v.receive(a.pack(unknown), 1.0) == []

        (mc,) = of_type(v.receive(a.pack(a.mav.mission_request_list_encode(SYS, 1)), 1.0),
                        "MISSION_COUNT")
        assert mc.count == 0 and mc.target_system == SYS
        (ts,) = of_type(v.receive(a.pack(a.mav.timesync_encode(0, 777)), 2.5), "TIMESYNC")
        assert (ts.tc1, ts.ts1) == (2_500_000_000, 777)
        assert v.rejected_frames == 0


# ---------------------------------------------------------------- PX4 offboard rules
def test_px4_offboard_denied_without_streaming_setpoints() -> None:
    v, a = make("px4"), Agent()
    assert acks(v.receive(a.set_mode(6), 1.0)) == [(176, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    v.receive(a.setpoint(), 1.0)  # a single setpoint is not a stream
    assert acks(v.receive(a.set_mode(6), 1.05)) == [(176, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    v.receive(a.setpoint(), 1.1)
    assert not v.setpoints_streaming(1.7)  # both older than 0.5 s by then
    assert acks(v.receive(a.set_mode(6), 1.7)) == [(176, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    assert v.mode == "LOITER"


def test_px4_offboard_accepted_when_streaming_and_setpoint_applied_when_armed() -> None:
    v, a = make("px4", start="ground"), Agent()
    u = np.array([1.0, -2.0, 0.5])
    v.receive(a.setpoint(u), 1.0)
    v.receive(a.setpoint(u), 1.1)
    assert v.setpoints_streaming(1.2)
    assert acks(v.receive(a.set_mode(6), 1.2)) == [(176, 0)] and v.in_setpoint_mode
    np.testing.assert_array_equal(v.commanded_velocity_w(1.2), 0.0)  # disarmed
    assert not v.accepting_setpoints
    assert acks(v.receive(a.arm(), 1.25)) == [(400, 0)]
    assert v.accepting_setpoints  # px4 takes setpoints on the ground too
    np.testing.assert_array_equal(v.commanded_velocity_w(1.3), frames.velocity_over_link(u))


def test_px4_offboard_while_disarmed_without_setpoints_then_arming_waits_for_them() -> None:
    """Measured: DO_SET_MODE OFFBOARD without a setpoint stream is ACCEPTED while disarmed;
    arming is then TEMPORARILY_REJECTED until setpoints stream."""
    v, a = make("px4", start="ground"), Agent()
    assert acks(v.receive(a.set_mode(6), 1.0)) == [(176, mav.MAV_RESULT_ACCEPTED)]
    assert v.mode == "OFFBOARD"
    assert acks(v.receive(a.arm(), 1.1)) == [(400, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    v.receive(a.setpoint(), 1.2)
    assert acks(v.receive(a.arm(), 1.25)) == [(400, mav.MAV_RESULT_TEMPORARILY_REJECTED)]
    v.receive(a.setpoint(), 1.3)
    assert acks(v.receive(a.arm(), 1.35)) == [(400, mav.MAV_RESULT_ACCEPTED)] and v.armed
    assert v.mode == "OFFBOARD" and not v.failsafe_active


def test_px4_setpoint_loss_failsafe_holds_and_setpoints_bring_offboard_back() -> None:
    a = Agent()
    v = px4_offboard_armed(a, t=10.0)
    assert v.setpoint_timeout_s == 1.0  # COM_OF_LOSS_T
    u = np.array([2.0, 1.0, -0.5])
    v.receive(a.setpoint(u), 10.0)
    np.testing.assert_array_equal(v.commanded_velocity_w(11.0), frames.velocity_over_link(u))
    assert not v.failsafe_active and v.mode == "OFFBOARD"
    np.testing.assert_array_equal(v.commanded_velocity_w(11.0001), 0.0)
    assert v.failsafe_active and v.mode == "LOITER" and v.failsafe_events == 1
    assert not v.accepting_setpoints and v.armed
    (hb,) = parse([v.heartbeat()])
    assert mavutil.mode_string_v10(hb) == "LOITER" and hb.custom_mode >> 16 & 0xFF == 4
    # one setpoint is no stream yet; a stream brings OFFBOARD back by itself (measured)
    v.receive(a.setpoint(u), 12.0)
    np.testing.assert_array_equal(v.commanded_velocity_w(12.0), 0.0)
    assert v.mode == "LOITER"
    v.receive(a.setpoint(u), 12.05)
    assert v.mode == "OFFBOARD" and not v.failsafe_active and v.accepting_setpoints
    np.testing.assert_array_equal(v.commanded_velocity_w(12.05), frames.velocity_over_link(u))
    (hb,) = parse([v.heartbeat()])
    assert mavutil.mode_string_v10(hb) == "OFFBOARD"
    # lost again; a mode commanded meanwhile wins: the stream no longer brings OFFBOARD back
    np.testing.assert_array_equal(v.commanded_velocity_w(13.1), 0.0)
    assert v.failsafe_active and v.mode == "LOITER" and v.failsafe_events == 2
    assert acks(v.receive(a.set_mode(4, 3), 13.2)) == [(176, 0)]
    assert not v.failsafe_active
    v.receive(a.setpoint(u), 13.3)
    v.receive(a.setpoint(u), 13.35)
    np.testing.assert_array_equal(v.commanded_velocity_w(13.4), 0.0)
    assert v.mode == "LOITER"
    assert acks(v.receive(a.set_mode(6), 13.4)) == [(176, 0)]  # streaming: accepted
    np.testing.assert_array_equal(v.commanded_velocity_w(13.4), frames.velocity_over_link(u))


def test_ardupilot_setpoint_loss_failsafe_stops_but_stays_guided() -> None:
    a = Agent()
    v = ardupilot_flying(a, t=10.0)
    u = np.array([-1.0, 0.5, 0.25])
    v.receive(a.setpoint(u), 10.0)
    np.testing.assert_array_equal(v.commanded_velocity_w(13.0), frames.velocity_over_link(u))
    np.testing.assert_array_equal(v.commanded_velocity_w(13.0001), 0.0)
    assert v.failsafe_active and v.mode == "GUIDED" and v.failsafe_events == 1
    assert not v.accepting_setpoints and v.armed
    v.receive(a.setpoint(u), 14.0)  # the next setpoint resumes
    assert not v.failsafe_active
    np.testing.assert_array_equal(v.commanded_velocity_w(14.0), frames.velocity_over_link(u))


def test_ardupilot_position_only_setpoints_never_time_out() -> None:
    a = Agent()
    v = ardupilot_flying(a, t=10.0)
    v.receive(a.position_setpoint(START + np.array([5.0, 0.0, 0.0])), 10.0)
    assert v.commanded_velocity_w(10.0)[0] > 0.0
    assert v.commanded_velocity_w(100.0)[0] > 0.0  # the vehicle has not moved: still going
    assert not v.failsafe_active and v.failsafe_events == 0


@pytest.mark.parametrize(("flavour", "param"), [("ardupilot", "GUID_TIMEOUT"),
                                                ("px4", "COM_OF_LOSS_T")])
def test_setpoint_timeout_is_configurable(flavour: str, param: str) -> None:
    v = EmulatedVehicle(0, flavour, START, ORIGIN, setpoint_timeout_s=0.2)  # type: ignore[arg-type]
    assert v.system_id == 1 and v.params[param] == 0.2
    b = Agent(sysid=1, target=1)
    if flavour == "px4":
        v.receive(b.setpoint(), 0.9)
        v.receive(b.setpoint(), 0.95)
        assert acks(v.receive(b.set_mode(6), 1.0)) == [(176, 0)]
    assert acks(v.receive(b.arm(), 1.0)) == [(400, 0)]
    v.receive(b.setpoint([1, 0, 0]), 1.0)
    assert v.commanded_velocity_w(1.2)[0] == 1.0
    assert v.commanded_velocity_w(1.2001)[0] == 0.0 and v.failsafe_active


def test_ardupilot_ignores_setpoints_before_guided_armed_takeoff() -> None:
    v, a = make("ardupilot", start="ground"), Agent()
    u = np.array([1.0, 1.0, 0.0])

    def applied(t: float) -> np.ndarray:
        v.receive(a.setpoint(u), t)
        return v.commanded_velocity_w(t)

    np.testing.assert_array_equal(applied(1.0), 0.0)  # STABILIZE, disarmed
    assert acks(v.receive(a.command(22, 0, 0, 0, 0, 0, 0, 4.0), 1.0)) == [(22, 4)]  # FAILED
    v.receive(a.set_mode(4), 1.1)
    np.testing.assert_array_equal(applied(1.2), 0.0)  # GUIDED, disarmed
    assert acks(v.receive(a.command(22, 0, 0, 0, 0, 0, 0, 4.0), 1.2)) == [(22, 4)]
    v.receive(a.arm(), 1.3)
    np.testing.assert_array_equal(applied(1.4), 0.0)  # GUIDED, armed, on the ground
    assert v.ignored_setpoints == 3 and v.accepted_setpoints == 0
    assert not v.accepting_setpoints
    assert acks(v.receive(a.command(22, 0, 0, 0, 0, 0, 0, 0.0), 1.5)) == [(22, 4)]  # 0 m
    assert acks(v.receive(a.command(22, 0, 0, 0, 0, 0, 0, 4.0), 1.5)) == [(22, 0)]
    t = fly(v, 1.5, 4.0)  # the spool-up, the start of the climb: no setpoint meanwhile
    assert v.airborne and v.accepting_setpoints
    np.testing.assert_array_equal(v.commanded_velocity_w(t), 0.0)  # old ones were dropped
    np.testing.assert_array_equal(applied(t + 0.1), frames.velocity_over_link(u))
    assert v.landed_state == mav.MAV_LANDED_STATE_IN_AIR  # the setpoint ended the takeoff
    v.receive(a.set_mode(5), t + 0.2)  # LOITER: not the setpoint mode
    np.testing.assert_array_equal(applied(t + 0.3), 0.0)
    v.receive(a.set_mode(4), t + 0.4)
    np.testing.assert_array_equal(applied(t + 0.5), frames.velocity_over_link(u))
    # landed (and disarmed): a new takeoff is needed
    assert acks(v.receive(a.set_mode(9), t + 0.6)) == [(176, 0)]
    t = fly(v, t + 0.6, 30.0)
    assert not v.armed and not v.airborne
    v.receive(a.set_mode(4), t)
    v.receive(a.arm(), t)
    assert v.armed
    np.testing.assert_array_equal(applied(t + 0.1), 0.0)
    assert v.rejected_frames == 0


speeds = arrays(np.float64, 3, elements=st.floats(-20, 20, allow_nan=False))


@settings(max_examples=150, deadline=None)
@given(speeds, st.sampled_from(["px4", "ardupilot"]))
def test_applied_velocity_is_bit_exact_clamped_velocity_over_link(u: np.ndarray,
                                                                  flavour: str) -> None:
    a = Agent()
    v = px4_offboard_armed(a) if flavour == "px4" else ardupilot_flying(a)
    v.receive(a.setpoint(u, stamp=40), 10.01)
    expected = clamp_velocity(frames.velocity_over_link(u), 3.0)
    got = v.commanded_velocity_w(10.02)
    np.testing.assert_array_equal(got.view(np.uint64), expected.view(np.uint64))
    assert np.all(np.abs(got) <= 3.0)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_non_finite_setpoint_is_rejected_and_counted(bad: float, axis: int) -> None:
    """Dropped at the boundary: not applied, not stamped (lockstep would integrate it), no
    proof of life; the vehicle flies on with the last valid setpoint."""
    a = Agent()
    v = px4_offboard_armed(a)
    v.begin_step(77)
    v.receive(a.setpoint([1.0, 0.0, 0.0], stamp=76), 10.01)
    accepted, arrivals = v.accepted_setpoints, v.accepted_frames
    velocity = [0.5, -0.5, 0.25]
    velocity[axis] = bad
    assert v.receive(a.setpoint(velocity, stamp=77), 10.02) == []
    np.testing.assert_array_equal(v.commanded_velocity_w(10.03), [1.0, 0.0, 0.0])
    assert v.setpoint_stamped() is None
    assert v.rejections["nonfinite_setpoint"] == 1 and v.rejected_frames == 1
    assert v.nonfinite_setpoints == 1 and not v.failsafe_active
    assert (v.accepted_setpoints, v.accepted_frames) == (accepted, arrivals)


def test_empty_datagram_is_counted() -> None:
    v = make("px4")
    assert v.receive(b"", 1.0) == []
    assert v.rejections["empty_datagram"] == 1 and v.accepted_frames == 0
    v.receive(Agent().arm(), 1.0)
    assert v.accepted_frames == 1 and v.rejected_frames == 1
    gcs = Agent(sysid=255, compid=190)  # a valid frame the vehicle has no use for
    v.receive(gcs.pack(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0)), 1.0)
    assert v.accepted_frames == 1 and v.ignored_messages == 1


# ---------------------------------------------------------------- setpoint validation
@pytest.mark.parametrize("mask", [0x0DC7, 0x09C7, 0x05C7, 0x01C7])
def test_velocity_only_masks_accepted(mask: int) -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    v.receive(a.setpoint([1, 2, 3], mask=mask), 10.01)
    assert v.rejected_frames == 0
    np.testing.assert_array_equal(v.commanded_velocity_w(10.01), [1, 2, 3])


@pytest.mark.parametrize(("kw", "reason"), [
    ({"mask": 0x0C07}, "setpoint_type_mask"),  # velocity and acceleration
    ({"mask": 0x0C3F}, "setpoint_type_mask"),  # acceleration only
    ({"mask": 0x0C38}, "setpoint_type_mask"),  # position and acceleration
    ({"mask": 0x0DFF}, "setpoint_type_mask"),  # nothing
    ({"mask": 0x0DF9}, "setpoint_type_mask"),  # x ignored, y and z used
    ({"mask": 0x0FF8}, "setpoint_type_mask"),  # position only with the force bit
    ({"mask": 0x0FC7}, "setpoint_type_mask"),  # force bit
    ({"mask": 0x0DCF}, "setpoint_type_mask"),  # vx ignored
    ({"mask": 0x1DC7}, "setpoint_type_mask"),  # undefined bit
    ({"frame": mav.MAV_FRAME_BODY_NED}, "setpoint_frame"),
    ({"frame": mav.MAV_FRAME_LOCAL_OFFSET_NED}, "setpoint_frame"),
    ({"target": SYS + 1}, "wrong_target_system"),
])
def test_bad_setpoints_rejected_and_ignored(kw: dict[str, int], reason: str) -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    v.receive(a.setpoint([1, 0, 0]), 10.01)
    assert v.receive(a.setpoint([0, 3, 0], **kw), 10.02) == []
    assert v.rejections == {reason: 1}
    np.testing.assert_array_equal(v.commanded_velocity_w(10.03), [1, 0, 0])


def test_broadcast_target_accepted_other_component_ignored() -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    v.receive(a.setpoint([1, 0, 0], target=0, comp=0), 10.01)
    np.testing.assert_array_equal(v.commanded_velocity_w(10.01), [1, 0, 0])
    v.receive(a.setpoint([0, 1, 0], comp=mav.MAV_COMP_ID_CAMERA), 10.02)
    np.testing.assert_array_equal(v.commanded_velocity_w(10.02), [1, 0, 0])
    assert v.rejected_frames == 0 and v.ignored_messages == 1


def test_command_for_another_system_rejected() -> None:
    v = make("px4")
    assert v.receive(Agent().arm(), 1.0) != []
    assert v.receive(Agent().command(400, 0.0, target=SYS + 5), 1.1) == []
    assert v.armed and v.rejections == {"wrong_target_system": 1}


# ---------------------------------------------------------------- garbage
def test_garbage_truncated_and_corrupted_frames_counted_and_dropped() -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    good = a.setpoint([1.0, 0.0, 0.0])
    v.receive(good, 10.01)
    rng = np.random.default_rng(3)
    assert v.receive(rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), 10.02) == []
    assert v.receive(a.setpoint([0.0, 2.0, 0.0])[:20], 10.03) == []  # truncated
    bad_crc = bytearray(a.setpoint([0.0, 2.0, 0.0]))
    bad_crc[-1] ^= 0xFF
    assert v.receive(bytes(bad_crc), 10.04) == []
    flipped = bytearray(a.set_mode(4, 3))  # LOITER, if it were taken
    flipped[12] ^= 0x01  # payload bit flip: CRC no longer matches
    assert v.receive(bytes(flipped), 10.05) == []
    assert v.receive(b"", 10.06) == []
    unknown = bytearray(a.setpoint())
    unknown[7:10] = (0x12, 0x34, 0x00)  # message id 0x3412: not in the dialect
    v.receive(bytes(unknown), 10.07)
    assert v.armed and v.mode == "OFFBOARD"
    np.testing.assert_array_equal(v.commanded_velocity_w(10.08), [1.0, 0.0, 0.0])
    assert v.rejections["truncated"] >= 1 and v.rejections["bad_data"] >= 2
    assert v.rejections["unknown_message"] == 1
    assert not any(k.startswith(("handler_error", "parser_error")) for k in v.rejections)
    # the vehicle still works, and valid packets after junk in one datagram are applied
    replies = v.receive(b"\x00\x01junk" + a.setpoint([0.0, 0.0, 1.0]) + a.set_mode(4, 3),
                        10.1)
    assert acks(replies) == [(176, 0)] and v.mode == "LOITER" and v.accepted_setpoints == 4


def test_stream_framing_completes_packets_across_calls() -> None:
    a = Agent()
    packet = a.arm()
    datagram = make("px4", start="ground")
    assert datagram.receive(packet[:9], 1.0) == [] and datagram.rejections == {"truncated": 1}
    assert datagram.receive(packet[9:], 1.0) == [] and not datagram.armed
    stream = make("px4", start="ground", datagram_framing=False)
    assert stream.receive(packet[:9], 1.0) == []
    assert acks(stream.receive(packet[9:], 1.0)) == [(400, 0)] and stream.armed
    assert stream.rejected_frames == 0


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400), st.sampled_from(["px4", "ardupilot"]))
def test_arbitrary_bytes_never_raise(data: bytes, flavour: str) -> None:
    v = make(flavour, start="ground")
    v.receive(data, 1.0)
    v.receive(data + Agent().arm() + data, 1.1)
    assert acks(v.receive(Agent().arm(False), 1.2)) == [(400, 0)]
    assert not any(k.startswith(("handler_error", "parser_error")) for k in v.rejections)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 60), st.integers(0, 255))
def test_any_single_byte_corruption_is_harmless(index: int, value: int) -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    v.receive(a.setpoint([1.0, 0.0, 0.0]), 10.01)
    packet = bytearray(a.setpoint([0.0, -3.0, 0.0]))
    index %= len(packet)
    changed = packet[index] != value
    packet[index] = value
    v.receive(bytes(packet), 10.02)
    got = v.commanded_velocity_w(10.02)
    # the CRC covers every byte after the start marker: a changed packet is never applied
    expected = [1.0, 0.0, 0.0] if changed else [0.0, -3.0, 0.0]
    np.testing.assert_array_equal(got, expected)
    assert not any(k.startswith(("handler_error", "parser_error")) for k in v.rejections)
    if changed:
        assert v.rejected_frames + v.ignored_messages >= 1


# ---------------------------------------------------------------- telemetry
def test_local_position_ned_in_the_vehicle_frame() -> None:
    v, a = make("px4"), Agent()
    del a
    (lp,) = of_type(v.telemetry(1234, 1.0), "LOCAL_POSITION_NED")
    assert lp.time_boot_ms == 1234
    # START - ORIGIN = (3 east, 4 north, 4 up)
    assert (lp.x, lp.y, lp.z) == (4.0, 3.0, -4.0)
    v.integrate(0.5, [1.0, -2.0, 0.5])
    np.testing.assert_array_equal(v.position_w, START + 0.5 * np.array([1.0, -2.0, 0.5]))
    (lp,) = of_type(v.telemetry(1734, 1.5), "LOCAL_POSITION_NED")
    expected = frames.to_link_float(frames.local_ned_from_world(v.position_w, ORIGIN))
    np.testing.assert_array_equal([lp.x, lp.y, lp.z], expected)
    assert (lp.vx, lp.vy, lp.vz) == (-2.0, 1.0, -0.5)  # north, east, down
    np.testing.assert_array_equal(
        frames.world_from_local_ned([lp.x, lp.y, lp.z], ORIGIN),
        frames.position_over_link(v.position_w, ORIGIN))


def _count(v: EmulatedVehicle, kind: str, seconds: float, hz: float = 50.0,
           t0: float = 100.0) -> int:
    n = 0
    for k in range(round(seconds * hz)):
        t = t0 + k / hz
        n += len(of_type(v.telemetry(round(t * 1000), t), kind))
    return n


def test_default_stream_rates_per_flavour() -> None:
    px4, apm = make("px4"), make("ardupilot")
    assert _count(px4, "LOCAL_POSITION_NED", 2.0) == 100  # every call
    assert _count(apm, "LOCAL_POSITION_NED", 2.0) == 0  # ArduPilot: only when requested
    assert _count(make("px4"), "HEARTBEAT", 3.0) == 0  # the caller sends heartbeat() itself
    assert _count(make("ardupilot"), "HEARTBEAT", 3.0) == 0
    assert _count(make("px4"), "ATTITUDE", 2.0) == 20
    for kind in ("SYS_STATUS", "EXTENDED_SYS_STATE"):
        assert _count(make("px4"), kind, 3.0) == 3


def test_set_message_interval() -> None:
    v, a = make("ardupilot"), Agent()
    lpn = mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED
    assert acks(v.receive(a.command(511, lpn, 20_000), 1.0)) == [(511, 0)]  # 50 Hz
    assert _count(v, "LOCAL_POSITION_NED", 2.0) == 100
    assert acks(v.receive(a.command(511, lpn, 100_000), 1.0)) == [(511, 0)]  # 10 Hz
    assert _count(v, "LOCAL_POSITION_NED", 2.0, t0=200.0) == 20
    (mi,) = of_type(v.receive(a.command(510, lpn), 1.0), "MESSAGE_INTERVAL")
    assert (mi.message_id, mi.interval_us) == (lpn, 100_000)
    assert acks(v.receive(a.command(511, lpn, -1), 1.0)) == [(511, 0)]
    assert _count(v, "LOCAL_POSITION_NED", 1.0, t0=300.0) == 0
    assert acks(v.receive(a.command(511, lpn, 0), 1.0)) == [(511, 0)]  # default: every call
    assert _count(v, "LOCAL_POSITION_NED", 1.0, t0=400.0) == 50
    assert acks(v.receive(a.command(511, 9999, 1000), 1.0)) == [(511, mav.MAV_RESULT_DENIED)]
    assert acks(v.receive(a.command(511, lpn, -7), 1.0)) == [(511, mav.MAV_RESULT_DENIED)]
    hb = mav.MAVLINK_MSG_ID_HEARTBEAT
    assert acks(v.receive(a.command(511, hb, 500_000), 1.0)) == [(511, 0)]
    assert _count(v, "HEARTBEAT", 2.0, t0=500.0) == 4
    (one,) = of_type(v.receive(a.command(512, lpn), 1.0), "LOCAL_POSITION_NED")
    assert (one.x, one.y, one.z) == (4.0, 3.0, -4.0)


def test_request_data_stream_ardupilot_only_and_explicit_interval_wins() -> None:
    a = Agent()
    v = make("ardupilot")
    v.receive(a.pack(a.mav.request_data_stream_encode(SYS, 1, mav.MAV_DATA_STREAM_POSITION,
                                                      5, 1)), 1.0)
    assert _count(v, "LOCAL_POSITION_NED", 2.0) == 10
    v.receive(a.command(511, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000), 1.0)
    v.receive(a.pack(a.mav.request_data_stream_encode(SYS, 1, mav.MAV_DATA_STREAM_ALL, 2, 1)),
              1.0)
    assert _count(v, "LOCAL_POSITION_NED", 2.0, t0=200.0) == 100
    p = make("px4")
    p.receive(a.pack(a.mav.request_data_stream_encode(SYS, 1, mav.MAV_DATA_STREAM_ALL, 0, 0)),
              1.0)
    assert _count(p, "LOCAL_POSITION_NED", 1.0) == 50  # PX4 ignores REQUEST_DATA_STREAM


def test_extended_sys_state_and_sys_status() -> None:
    a = Agent()
    v = make("ardupilot", start="ground")
    (es,) = of_type(v.telemetry(0, 0.0), "EXTENDED_SYS_STATE")
    assert es.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    v = ardupilot_flying(a)
    packets = v.telemetry(0, 20.0)
    (es,) = of_type(packets, "EXTENDED_SYS_STATE")
    assert es.landed_state == mav.MAV_LANDED_STATE_IN_AIR
    (ss,) = of_type(packets, "SYS_STATUS")
    assert ss.onboard_control_sensors_health == ss.onboard_control_sensors_present != 0


def test_telemetry_survives_a_clock_that_jumps_back() -> None:
    v = make("px4")
    assert _count(v, "SYS_STATUS", 1.0, t0=500.0) == 1
    assert _count(v, "SYS_STATUS", 1.0, t0=0.0) == 1


# ---------------------------------------------------------------- lockstep
def test_setpoint_stamped_and_begin_step() -> None:
    a = Agent()
    v = px4_offboard_armed(a)
    assert v.awaited_stamp is None and v.setpoint_stamped() is None
    v.begin_step(20)
    assert v.awaited_stamp == 20
    assert v.setpoint_stamped(20) is None
    v.receive(a.setpoint([1.0, 2.0, 9.0], stamp=20), 10.02)
    v.receive(a.setpoint([5.0, 5.0, 5.0], stamp=0xFFFFFFFF), 10.03)  # keepalive stamp
    np.testing.assert_array_equal(v.setpoint_stamped(20), [1.0, 2.0, 3.0])  # clamped
    np.testing.assert_array_equal(v.setpoint_stamped(), [1.0, 2.0, 3.0])
    assert v.setpoint_stamped(40) is None
    v.begin_step(40)
    assert v.setpoint_stamped(20) is None
    v.receive(a.setpoint([0.0, 0.1, 0.0], stamp=40), 10.04)
    np.testing.assert_array_equal(v.setpoint_stamped(40), frames.velocity_over_link([0, 0.1, 0]))
    # a setpoint the vehicle may not apply still "arrives", with the velocity it applies: 0
    w = make("px4")
    w.begin_step(60)
    w.receive(a.setpoint([1.0, 0.0, 0.0], stamp=60), 1.0)
    np.testing.assert_array_equal(w.setpoint_stamped(60), 0.0)


def test_integrate_is_plain_forward_euler() -> None:
    v = make("px4")
    u = np.array([0.3, -0.7, 0.11])
    for _ in range(50):
        v.integrate(0.02, u)
    p = START.copy()
    for _ in range(50):
        p = p + 0.02 * u
    np.testing.assert_array_equal(v.position_w, p)
    np.testing.assert_array_equal(v.velocity_w, u)


def test_constructor_validation() -> None:
    with pytest.raises(ValueError, match="flavour"):
        EmulatedVehicle(0, "inav", START, ORIGIN)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="drone_id"):
        EmulatedVehicle(254, "px4", START, ORIGIN)
    with pytest.raises(ValueError, match="setpoint_timeout_s"):
        EmulatedVehicle(0, "px4", START, ORIGIN, setpoint_timeout_s=0.0)
    with pytest.raises(ValueError, match="u_max_m_s"):
        EmulatedVehicle(0, "px4", START, ORIGIN, u_max_m_s=float("inf"))
    with pytest.raises(ValueError, match="start"):
        EmulatedVehicle(0, "px4", START, ORIGIN, start="hover")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="ground"):  # in the air, but not above the ground
        EmulatedVehicle(0, "ardupilot", [START[0], START[1], ORIGIN[2]], ORIGIN)
    with pytest.raises(ValueError, match="response"):
        EmulatedVehicle(0, "px4", START, ORIGIN, response=0.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        EmulatedVehicle(0, "px4", [0.0, float("nan"), 3.0], ORIGIN)
    # the firmware's defaults: COM_OF_LOSS_T, GUID_TIMEOUT
    assert make("px4").setpoint_timeout_s == 1.0 and make("ardupilot").setpoint_timeout_s == 3.0
    # "ground" takes the x, y of any position: z is the ground's
    v = EmulatedVehicle(0, "px4", [1.0, 2.0, -7.0], ORIGIN, start="ground")
    np.testing.assert_array_equal(v.position_w, [1.0, 2.0, ORIGIN[2]])


# ---------------------------------------------------------------- UDP endpoint
def _readable(sock: socket.socket, timeout: float = 2.0) -> bool:
    return bool(select.select([sock], [], [], timeout)[0])


def _poll_until(ep: VehicleEndpoint, count: int, timeout: float = 2.0) -> list[bytes]:
    got: list[bytes] = []
    while len(got) < count and select.select([ep], [], [], timeout)[0]:
        got.extend(ep.poll())
    return got


def test_endpoint_sends_to_agent_port_and_follows_mavlink_senders() -> None:
    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    relay = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    relay.bind(("127.0.0.1", 0))
    junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    v = make("px4")
    with VehicleEndpoint(agent.getsockname()) as ep, agent, relay, junk:
        assert ep.local_address[0] == "127.0.0.1" and ep.local_address[1] > 0
        assert ep.poll() == []  # non-blocking
        assert ep.send([v.heartbeat(), b"", v.heartbeat()]) == 2
        assert _readable(agent) and agent.recv(65535)[0] == 0xFD
        # junk from a stray sender is delivered but does not take the link over
        junk.sendto(b"hello", ep.local_address)
        assert _poll_until(ep, 1) == [b"hello"] and ep.peer_address == agent.getsockname()
        # a MAVLink sender (e.g. MAVProxy relaying) becomes the peer, like PX4 SITL
        relay.sendto(Agent().arm(), ep.local_address)
        (data,) = _poll_until(ep, 1)
        assert ep.peer_address == relay.getsockname() and ep.peer_changes == 1
        ep.send(v.receive(data, 1.0), coalesce=True)
        assert _readable(relay)
        assert acks([relay.recv(65535)]) == [(400, 0)]
        assert ep.datagrams_received == 2
    ep.close()  # idempotent


def test_endpoint_is_re_exported_by_the_vehicle_module() -> None:
    assert ReExported is VehicleEndpoint


def test_endpoint_fixed_peer_when_not_following() -> None:
    agent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    agent.bind(("127.0.0.1", 0))
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with VehicleEndpoint(agent.getsockname(), follow_sender=False) as ep, agent, other:
        other.sendto(Agent().arm(), ep.local_address)
        assert len(_poll_until(ep, 1)) == 1
        assert ep.peer_address == agent.getsockname()


@settings(max_examples=50, deadline=None)
@given(speeds)
@example(np.array([0.3, -0.2, 0.1]))  # float32 rounding shows in every axis
@example(np.full(3, 2.24609375))  # ends on float32 values: the report is the truth
def test_reported_position_is_what_an_agent_reads_from_local_position_ned(u: np.ndarray) -> None:
    """``reported_position_w`` (what a lockstep world puts in every camera frame for this
    drone) is, bit for bit, the position the agent's link makes of the LOCAL_POSITION_NED
    the vehicle sends at that moment (float32 local NED, back to W), not the float64 truth."""
    a = Agent()
    v = px4_offboard_armed(a)
    t = fly(v, 10.0, 0.3, each=lambda now: v.receive(a.setpoint(u, stamp=40), now))
    report = of_type(v.telemetry(1234, t), "LOCAL_POSITION_NED")[-1]
    read = frames.world_from_local_ned((report.x, report.y, report.z), v.origin_w)
    np.testing.assert_array_equal(v.reported_position_w.view(np.uint64), read.view(np.uint64))
    local = frames.local_ned_from_world(v.position_w, v.origin_w)
    if not np.array_equal(frames.to_link_float(local), local):  # float32 rounding shows
        assert not np.array_equal(v.reported_position_w, v.position_w)
