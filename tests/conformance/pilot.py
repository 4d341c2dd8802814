"""The conformance dialogue's side of the link: a companion computer talking MAVLink 2 to one
vehicle (real SITL or emulated, the same code for both) and recording what it answers.

``Pilot(url, system_id)`` opens a pymavlink connection (``udpin:127.0.0.1:<port>``: the vehicle
sends its companion link there) as system 200, component 191 (MAV_COMP_ID_ONBOARD_COMPUTER),
and keeps, as messages arrive: the newest HEARTBEAT (mode name, custom mode, armed), the
landed state (EXTENDED_SYS_STATE), every LOCAL_POSITION_NED with its arrival time, every
COMMAND_ACK, STATUSTEXT and PARAM_VALUE. ``pump(seconds)`` reads for that long and meanwhile
streams the current setpoint (``setpoint``) at ``SETPOINT_RATE_HZ``, sends a companion
HEARTBEAT at 1 Hz and, when ``poll_heartbeat_s`` is set, asks for a HEARTBEAT (REQUEST_MESSAGE)
that often (PX4 sends its own at 1 Hz only and refuses a faster interval). ``until(check,
timeout_s, what)`` pumps until ``check()`` is true and raises ``DialogueError`` (with the
vehicle's state) when it is not by then. Times are ``time.monotonic()`` minus the pilot's
start.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # after MAVLINK20: MAVLink 2 framing

from swarm.mavlink import px4_events

Array = NDArray[np.float64]
mav = mavutil.mavlink

SETPOINT_RATE_HZ = 20.0  # as MAVSDK streams offboard setpoints; well above PX4's 2 Hz minimum
COMMAND_ACK_TIMEOUT_S = 1.5  # UDP on loopback: a lost ACK is resent once this is over
VELOCITY_MASK = 0x0DC7  # velocity only, as the swarm's agents send
POSITION_MASK = 0x0DF8  # position only


class DialogueError(AssertionError):
    """A step of the dialogue did not get the answer or behaviour it expects."""


@dataclass(frozen=True)
class Sample:
    """One LOCAL_POSITION_NED: arrival time [s], position and velocity in local NED."""

    t_s: float
    ned_m: Array
    velocity_ned_m_s: Array


@dataclass
class Setpoint:
    """What ``pump`` streams: type_mask, local NED position [m] and velocity [m/s]."""

    type_mask: int
    position_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def velocity(cls, north: float, east: float, down: float) -> Setpoint:
        return cls(VELOCITY_MASK, velocity_ned_m_s=(north, east, down))

    @classmethod
    def position(cls, north: float, east: float, down: float) -> Setpoint:
        return cls(POSITION_MASK, position_ned_m=(north, east, down))


@dataclass
class Heartbeat:
    mode: str
    custom_mode: int
    armed: bool
    autopilot: int
    vehicle_type: int


@dataclass
class Pilot:
    """See the module docstring."""

    url: str
    system_id: int = 1
    poll_heartbeat_s: float | None = None
    log: Callable[[str], None] = field(default=lambda line: None)

    def __post_init__(self) -> None:
        self.link = mavutil.mavlink_connection(self.url, source_system=200,
                                               source_component=mav.MAV_COMP_ID_ONBOARD_COMPUTER,
                                               dialect="ardupilotmega")
        self.t0 = time.monotonic()
        self.heartbeat: Heartbeat | None = None
        self.landed_state: int | None = None
        self.samples: list[Sample] = []
        self.acks: list[tuple[float, int, int]] = []
        self.texts: list[tuple[float, str]] = []
        self.params: dict[str, float] = {}
        self.modes: list[tuple[float, str, bool]] = []  # (t, mode, armed) at each change
        self.landed_states: list[tuple[float, int]] = []  # (t, state) at each change
        self.setpoint: Setpoint | None = None
        self._last_setpoint = -math.inf
        self._last_companion_heartbeat = -math.inf
        self._last_poll = -math.inf

    # ---------------------------------------------------------------- time and state
    def now(self) -> float:
        return time.monotonic() - self.t0

    @property
    def sample(self) -> Sample:
        if not self.samples:
            raise DialogueError(f"no LOCAL_POSITION_NED from {self.url} yet")
        return self.samples[-1]

    @property
    def mode(self) -> str:
        return "NONE" if self.heartbeat is None else self.heartbeat.mode

    @property
    def armed(self) -> bool:
        return self.heartbeat is not None and self.heartbeat.armed

    def since(self, t_s: float) -> list[Sample]:
        return [s for s in self.samples if s.t_s >= t_s]

    def state(self) -> str:
        where = "no position"
        if self.samples:
            s = self.samples[-1]
            where = (f"NED ({s.ned_m[0]:.2f}, {s.ned_m[1]:.2f}, {s.ned_m[2]:.2f}) m, velocity "
                     f"({s.velocity_ned_m_s[0]:.2f}, {s.velocity_ned_m_s[1]:.2f}, "
                     f"{s.velocity_ned_m_s[2]:.2f}) m/s")
        said = f", last said {self.texts[-1][1]!r}" if self.texts else ""
        return (f"t={self.now():.2f} s mode {self.mode} {'armed' if self.armed else 'disarmed'}"
                f" landed_state {self.landed_state} {where}{said}")

    # ---------------------------------------------------------------- the link
    def pump(self, seconds: float) -> None:
        """Read for ``seconds`` (streaming the setpoint, heartbeats and polls meanwhile)."""
        end = time.monotonic() + seconds
        while True:
            self._send_periodic()
            remaining = end - time.monotonic()
            if remaining <= 0:
                return
            msg = self.link.recv_match(blocking=True, timeout=min(remaining, 0.01))
            while msg is not None:
                self._on(msg)
                msg = self.link.recv_match(blocking=False)

    def until(self, check: Callable[[], bool], timeout_s: float, what: str) -> float:
        """Pump until ``check()``; the time it took [s]. DialogueError after ``timeout_s``."""
        start = time.monotonic()
        while not check():
            if time.monotonic() - start > timeout_s:
                raise DialogueError(f"{what}: not within {timeout_s:g} s; vehicle: "
                                    f"{self.state()}")
            self.pump(0.01)
        return time.monotonic() - start

    def _send_periodic(self) -> None:
        now = time.monotonic()
        if self.setpoint is not None and now - self._last_setpoint >= 1.0 / SETPOINT_RATE_HZ:
            self._last_setpoint = now
            sp = self.setpoint
            self.link.mav.set_position_target_local_ned_send(
                int(self.now() * 1000) & 0xFFFFFFFF, self.system_id, 1, mav.MAV_FRAME_LOCAL_NED,
                sp.type_mask, *sp.position_ned_m, *sp.velocity_ned_m_s, 0, 0, 0, 0, 0)
        if now - self._last_companion_heartbeat >= 1.0:
            self._last_companion_heartbeat = now
            self.link.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER,
                                         mav.MAV_AUTOPILOT_INVALID, 0, 0, mav.MAV_STATE_ACTIVE)
        if self.poll_heartbeat_s is not None and now - self._last_poll >= self.poll_heartbeat_s:
            self._last_poll = now
            self.link.mav.command_long_send(self.system_id, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                            mav.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0)

    def _on(self, msg: Any) -> None:
        if px4_events.message_source(msg) != (self.system_id, 1):
            return
        kind = msg.get_type()
        t = self.now()
        event = px4_events.event_from_message(msg)
        if event is not None:  # PX4 says why (a refusal, a failsafe) in EVENTs, not STATUSTEXT
            self.texts.append((t, px4_events.describe(event)))
            self.log(f"{t:7.2f} said {px4_events.describe(event)}")
        if kind == "LOCAL_POSITION_NED":
            self.samples.append(Sample(t, np.array([msg.x, msg.y, msg.z]),
                                       np.array([msg.vx, msg.vy, msg.vz])))
        elif kind == "HEARTBEAT":
            hb = Heartbeat(mavutil.mode_string_v10(msg), int(msg.custom_mode),
                           bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED),
                           int(msg.autopilot), int(msg.type))
            if self.heartbeat is None or (hb.mode, hb.armed) != (self.heartbeat.mode,
                                                                  self.heartbeat.armed):
                self.modes.append((t, hb.mode, hb.armed))
                raw = f" (custom_mode 0x{hb.custom_mode:08x})" if hb.mode == "UNKNOWN" else ""
                self.log(f"{t:7.2f} mode {hb.mode}{raw} "
                         f"{'armed' if hb.armed else 'disarmed'}")
            self.heartbeat = hb
        elif kind == "EXTENDED_SYS_STATE":
            if msg.landed_state != self.landed_state:
                self.landed_states.append((t, int(msg.landed_state)))
                self.log(f"{t:7.2f} landed_state {msg.landed_state}")
            self.landed_state = int(msg.landed_state)
        elif kind == "COMMAND_ACK":
            if msg.command != mav.MAV_CMD_REQUEST_MESSAGE:
                self.log(f"{t:7.2f} ACK {msg.command} {msg.result}")
            self.acks.append((t, int(msg.command), int(msg.result)))
        elif kind == "STATUSTEXT":
            self.texts.append((t, str(msg.text)))
            self.log(f"{t:7.2f} said {msg.text!r}")
        elif kind == "PARAM_VALUE":
            self.params[str(msg.param_id)] = float(msg.param_value)

    # ---------------------------------------------------------------- commands
    def command(self, command: int, *params: float, timeout_s: float = 5.0) -> int:
        """COMMAND_LONG until its COMMAND_ACK arrives (resent every COMMAND_ACK_TIMEOUT_S);
        the result."""
        values = [*params, *[0.0] * (7 - len(params))]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            count = len(self.acks)
            self.link.mav.command_long_send(self.system_id, 1, command, 0, *values)
            resend = time.monotonic() + COMMAND_ACK_TIMEOUT_S
            while time.monotonic() < min(resend, deadline):
                for _, acked, result in self.acks[count:]:
                    if acked == command:
                        return result
                self.pump(0.01)
        raise DialogueError(f"no COMMAND_ACK for command {command} within {timeout_s:g} s; "
                            f"vehicle: {self.state()}")

    def set_mode(self, main: int, sub: int = 0) -> int:
        """DO_SET_MODE with CUSTOM_MODE_ENABLED: ArduCopter's mode number in ``main``; PX4's
        main and sub mode."""
        return self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                            main, sub)

    def arm(self, on: bool = True) -> int:
        return self.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if on else 0.0)

    def takeoff(self, altitude_m: float = math.nan) -> int:
        return self.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan,
                            altitude_m)

    def message_interval(self, message_id: int, rate_hz: float) -> int:
        return self.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, 1e6 / rate_hz)

    def set_param(self, name: str, value: float, mav_type: int,
                  timeout_s: float = 5.0) -> float:
        """PARAM_SET until the vehicle echoes a PARAM_VALUE of it; the value echoed."""
        deadline = time.monotonic() + timeout_s
        self.params.pop(name, None)
        while time.monotonic() < deadline:
            self.link.mav.param_set_send(self.system_id, 1, name.encode(), float(value),
                                         mav_type)
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                if name in self.params:
                    return self.params[name]
                self.pump(0.01)
        raise DialogueError(f"no PARAM_VALUE {name} within {timeout_s:g} s")

    def close(self) -> None:
        self.link.close()
