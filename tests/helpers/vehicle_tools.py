"""An agent's side of an emulated vehicle's MAVLink link, and vehicles brought to a known state
(tests/sim_world)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from sim_world.vehicle import EmulatedVehicle
from swarm.models import frames

DRONE = 2


SYS = DRONE + 1


ORIGIN = np.array([10.0, -20.0, 0.5])


START = np.array([13.0, -16.0, 4.5])


MASK = 0x0DC7  # velocity only


POSITION_MASK = 0x0DF8  # position only


POSITION_VELOCITY_MASK = 0x0DC0  # position + velocity


FULL_MASK = 0x0C00  # position + velocity + acceleration


class _Sink:
    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.packets.append(bytes(buf))


class Agent:
    """Encodes what an agent / GCS would send and decodes the vehicle's replies."""

    def __init__(self, sysid: int = SYS, compid: int = mav.MAV_COMP_ID_ONBOARD_COMPUTER,
                 target: int = SYS) -> None:
        self.target = target
        self.sink = _Sink()
        self.mav = mav.MAVLink(self.sink, srcSystem=sysid, srcComponent=compid)

    def pack(self, msg: Any) -> bytes:
        self.mav.send(msg)
        return self.sink.packets.pop()

    def setpoint(self, vel_w: Any = (0.0, 0.0, 0.0), stamp: int = 0, *, mask: int = MASK,
                 frame: int = mav.MAV_FRAME_LOCAL_NED, target: int | None = None,
                 comp: int = 1) -> bytes:
        target = self.target if target is None else target
        vn, ve, vd = frames.to_link_float(frames.enu_to_ned(vel_w))
        return self.pack(self.mav.set_position_target_local_ned_encode(
            stamp, target, comp, frame, mask, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0))

    def position_setpoint(self, position_w: Any, vel_w: Any = None, accel_w: Any = None,
                          stamp: int = 0, *, mask: int | None = None,
                          origin: Any = ORIGIN) -> bytes:
        """A setpoint with a position (W, sent in the vehicle's local NED frame), and a
        velocity and an acceleration feed-forward if given; the mask says which are used."""
        if mask is None:
            mask = POSITION_MASK if vel_w is None else (
                POSITION_VELOCITY_MASK if accel_w is None else FULL_MASK)
        x, y, z = frames.to_link_float(frames.local_ned_from_world(position_w, origin))
        vn, ve, vd = frames.to_link_float(frames.enu_to_ned([0, 0, 0] if vel_w is None
                                                            else vel_w))
        an, ae, ad = frames.to_link_float(frames.enu_to_ned([0, 0, 0] if accel_w is None
                                                            else accel_w))
        return self.pack(self.mav.set_position_target_local_ned_encode(
            stamp, self.target, 1, mav.MAV_FRAME_LOCAL_NED, mask, x, y, z, vn, ve, vd,
            an, ae, ad, 0, 0))

    def command(self, command: int, *params: float, target: int | None = None) -> bytes:
        target = self.target if target is None else target
        p = [*params, *[0.0] * (7 - len(params))]
        return self.pack(self.mav.command_long_encode(target, 1, command, 0, *p))

    def arm(self, on: bool = True) -> bytes:
        return self.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if on else 0.0)

    def set_mode(self, main: int, sub: int = 0, flags: int = 1) -> bytes:
        return self.command(mav.MAV_CMD_DO_SET_MODE, flags, main, sub)


def parse(packets: list[bytes]) -> list[Any]:
    rx = mav.MAVLink(None)
    out: list[Any] = []
    for p in packets:
        assert p[0] == 0xFD, "vehicle must speak MAVLink 2"
        out.extend(rx.parse_buffer(p) or [])
    assert all(m.get_type() != "BAD_DATA" for m in out)
    return out


def acks(packets: list[bytes]) -> list[tuple[int, int]]:
    return [(m.command, m.result) for m in parse(packets) if m.get_type() == "COMMAND_ACK"]


def of_type(packets: list[bytes], kind: str) -> list[Any]:
    return [m for m in parse(packets) if m.get_type() == kind]


def make(flavour: str, **kw: Any) -> EmulatedVehicle:
    return EmulatedVehicle(DRONE, flavour, START, ORIGIN, **kw)  # type: ignore[arg-type]


DT = 0.02


def fly(v: EmulatedVehicle, t0: float, seconds: float, dt: float = DT,
        each: Callable[[float], object] | None = None) -> float:
    """``v.fly(dt, now)`` for ``seconds`` from ``t0`` (now = t0 + k·dt, k = 1, 2, ...;
    ``each(now)`` first at every step, e.g. to send a setpoint); returns the last now."""
    now = t0
    for k in range(1, round(seconds / dt) + 1):
        now = t0 + k * dt
        if each is not None:
            each(now)
        v.fly(dt, now)
    return now


def px4_offboard_armed(agent: Agent, t: float = 10.0, **kw: Any) -> EmulatedVehicle:
    """A px4 vehicle started in the air (armed, Hold), switched to OFFBOARD by a setpoint
    stream."""
    v = make("px4", **kw)
    assert v.armed and v.mode == "LOITER" and v.landed_state == mav.MAV_LANDED_STATE_IN_AIR
    v.receive(agent.setpoint(), t - 0.2)
    v.receive(agent.setpoint(), t - 0.1)
    assert acks(v.receive(agent.set_mode(6), t)) == [(176, mav.MAV_RESULT_ACCEPTED)]
    assert acks(v.receive(agent.arm(), t)) == [(400, mav.MAV_RESULT_ACCEPTED)]  # already
    assert v.mode == "OFFBOARD" and v.accepting_setpoints
    return v


def ardupilot_flying(agent: Agent, t: float = 10.0, **kw: Any) -> EmulatedVehicle:
    """An ardupilot vehicle started in the air: GUIDED, armed, hovering, taking setpoints
    (a takeoff there is FAILED, as on the real one)."""
    v = make("ardupilot", **kw)
    assert acks(v.receive(agent.set_mode(4), t)) == [(176, mav.MAV_RESULT_ACCEPTED)]
    assert acks(v.receive(agent.arm(), t)) == [(400, mav.MAV_RESULT_ACCEPTED)]
    assert acks(v.receive(agent.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 4.0), t)) \
        == [(22, mav.MAV_RESULT_FAILED)]
    assert v.mode == "GUIDED" and v.armed and v.airborne and v.accepting_setpoints
    assert v.landed_state == mav.MAV_LANDED_STATE_IN_AIR
    return v
