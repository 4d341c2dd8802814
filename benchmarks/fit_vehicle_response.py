"""Fit the emulator's velocity response (τ, a_max) to a real autopilot flown in SITL.

    python benchmarks/fit_vehicle_response.py [--autopilot ardupilot|px4] [--firmware PATH]
                                              [--out DIR] [--from-log FILE]

Our emulated vehicles and the in-process reference move a drone's velocity v towards its
velocity command u with ``swarm.models.kinematics.VelocityResponse(τ, a_max)``: per 20 ms step
Δ = (1 − e^(−ΔT/τ))·(u − v), limited to ‖Δ‖ ≤ a_max·ΔT. This script measures what the real
flight code does with the same commands, and fits τ and a_max to it:

1. Flight. One SITL (ArduCopter, or PX4 with SIH) through ``swarm.mavlink.sitl``; over its companion
   link (pymavlink, ``udpin``, system 1 component 191, as an agent) LOCAL_POSITION_NED is
   requested at 50 Hz; ArduPilot: GUIDED, ARM, NAV_TAKEOFF to 5 m; PX4: position setpoints
   5 m up streamed at 20 Hz, OFFBOARD, ARM. Then ``SEQUENCE``: velocity setpoints every 20 ms
   (SET_POSITION_TARGET_LOCAL_NED, type mask 0x0DC7, as the swarm sends them) — horizontal
   steps of 0.5-3 m/s in several directions, reversals, vertical steps, 3-D steps, each held
   3-4 s between zero-velocity rests; its last part (different steps, a reversal at 3 m/s,
   a smooth swarm-like command and a ramp) is held out of the fit. Every setpoint sent and
   every LOCAL_POSITION_NED received is logged with the wall time of sending or receipt.
2. Clock. Measured samples are placed on the autopilot's own clock (``time_boot_ms``; SITL
   may run slower than the wall clock on a busy machine), and the setpoints are mapped onto
   it: boot time ≈ a + b·wall (least squares over the samples) plus the upper envelope of the
   residuals over ±1 s (the samples that arrived fastest), so a send lands at the boot time
   the autopilot had when it was sent.
3. Fit, per axis group — horizontal (N, E), vertical (D) and all three (the one pair the 3-D
   emulator uses) — on a 50 Hz grid of the autopilot's clock: ``VelocityResponse.step`` run
   on the logged commands from the measured velocity at the start of the part, τ and a_max
   minimizing the RMS velocity error sqrt(mean ‖v_model − v_measured‖²) (a coarse grid, then
   bounded Nelder-Mead); a_max at its upper bound means no limit (reported as 0, the
   emulator's "none"). Also: the pure delay d that best aligns u(t − d) with the measured v,
   the RMS error of the ideal vehicle (v = u, at zero delay and at d), the fitted model's on
   the fit part and on the held-out part, the steady-state gain (measured over commanded
   velocity in the last second of each hold), and, as diagnostics of what the emulator
   leaves out, fits of τ and a_max behind a pure delay, and with a steady-state gain
   (the model driven by g·u).

Output: a table, and under ``--out`` (default ``benchmarks/results/vehicle_response/``)
``<autopilot>_<time>_log.json`` (the raw log; ``--from-log`` fits it again without flying)
and ``<autopilot>_<time>_fit.json`` (the figures). The firmware: ``--firmware``, else
``VIGIL_ARDUCOPTER`` / ``VIGIL_PX4``, else ``../shared/autopilots`` next to the repository.
One SITL instance at a time; it is always stopped, also on errors and Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from common import RESULTS, ROOT, console, fmt, machine_info, new_table, progress, write_json
from numpy.typing import NDArray
from rich.table import Table
from scipy.optimize import minimize

from swarm.errors import EXIT_FAILED, EXIT_OK, VigilError, run_main
from swarm.mavlink.parse import POSITION_ONLY_TYPE_MASK, VELOCITY_ONLY_TYPE_MASK
from swarm.mavlink.sitl import (
    KINDS,
    Firmware,
    Kind,
    SitlInstance,
    SitlMonitor,
    SitlSpec,
    default_params,
    firmware_from_env,
    free_instances,
    free_udp_port,
)
from swarm.models.frames import GeoPoint
from swarm.models.kinematics import VelocityResponse

Array = NDArray[np.float64]
Ned = tuple[float, float, float]

HOME = GeoPoint(-35.363261, 149.165230, 584.0)
SYSTEM_ID = 1
COMPANION_COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER, as the swarm's agents
AUTOPILOT_COMPONENT_ID = 1
SETPOINT_PERIOD_S = 0.02  # 50 Hz, the swarm's step
CLIMB_SETPOINT_PERIOD_S = 0.05  # 20 Hz, PX4's position setpoints while it climbs
POSITION_INTERVAL_US = 20_000  # LOCAL_POSITION_NED at 50 Hz
HEARTBEAT_PERIOD_S = 1.0
TAKEOFF_HEIGHT_M = 5.0
CLIMB_TOLERANCE_M = 0.3
READY_TIMEOUT_S = 90.0
ARM_TIMEOUT_S = 60.0  # PX4 refuses to arm until ~37 s after boot
CLIMB_TIMEOUT_S = 40.0
MAV_FRAME_LOCAL_NED = 1
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_SET_MESSAGE_INTERVAL = 511
LOCAL_POSITION_NED_ID = 32
MAV_RESULT_ACCEPTED, MAV_RESULT_IN_PROGRESS = 0, 5
MODE_ARGS: dict[Kind, tuple[float, float]] = {"ardupilot": (1.0, 4.0),  # custom, GUIDED
                                               "px4": (1.0, 6.0)}  # custom, OFFBOARD

# The fit: groups of NED components, the model's step, bounds and the start grid.
GROUPS: dict[str, tuple[int, ...]] = {"horizontal": (0, 1), "vertical": (2,),
                                      "3-D": (0, 1, 2)}
FIT_DT_S = SETPOINT_PERIOD_S
TAU_BOUNDS_S = (0.0, 3.0)
ACCEL_BOUNDS_M_S2 = (0.2, 30.0)  # the top means "no limit" (reported as 0)
TAU_GRID_S = (0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0, 1.5, 2.0)
ACCEL_GRID_M_S2 = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0, 20.0)
LAG_SCAN_S = np.arange(0.0, 1.5001, 0.01)
ENVELOPE_HALF_WINDOW_S = 1.0
SMOOTH_FROM = "swarm-like"  # the held-out part's smooth commands: from here to the end
STEADY_WINDOW_S = 1.0  # the last second of a hold
STEADY_MIN_HOLD_S = 2.9


class FitError(VigilError, RuntimeError):
    """The flight could not be flown or the log cannot be fitted; one line."""


# -- the command sequence --------------------------------------------------------------------


@dataclass(frozen=True)
class Phase:
    """One stretch of the sequence: ``command(t)`` [m/s, NED] for t in [0, duration_s)."""

    label: str
    duration_s: float
    part: str  # "fit" or "held-out"
    command: Callable[[float], Ned]
    hold: bool = False  # a constant non-zero command: its last second gives a steady state


def _hold(label: str, ned_m_s: Ned, duration_s: float, part: str) -> Phase:
    return Phase(label, duration_s, part, lambda _t: ned_m_s, hold=any(ned_m_s))


def _rest(part: str, duration_s: float = 3.0) -> Phase:
    return _hold("rest", (0.0, 0.0, 0.0), duration_s, part)


def _out_and_back(label: str, ned_m_s: Ned, duration_s: float, part: str) -> list[Phase]:
    """A step, a rest, the opposite step (back to where it started), a rest."""
    back = (-ned_m_s[0], -ned_m_s[1], -ned_m_s[2])
    return [_hold(f"{label} out", ned_m_s, duration_s, part), _rest(part),
            _hold(f"{label} back", back, duration_s, part), _rest(part)]


def _reversal(label: str, ned_m_s: Ned, duration_s: float, part: str) -> list[Phase]:
    """A step straight into the opposite step (no rest), then a rest."""
    back = (-ned_m_s[0], -ned_m_s[1], -ned_m_s[2])
    return [_hold(f"{label} +", ned_m_s, duration_s, part),
            _hold(f"{label} −", back, duration_s, part), _rest(part)]


def _swarm_like(t: float) -> Ned:
    """A smooth command like the QP's, 16 s, back where it started: periods 8, 16/3, 16 s."""
    return (1.5 * math.sin(2 * math.pi * t / 8.0), 1.2 * math.sin(2 * math.pi * 3 * t / 16.0),
            -0.4 * math.sin(2 * math.pi * t / 16.0))


def _ramp(t: float) -> Ned:
    """East 0 → 2 m/s in 3 s, 2 → −2 in 6 s, −2 → 0 in 3 s (back where it started)."""
    if t < 3.0:
        east = 2.0 * t / 3.0
    elif t < 9.0:
        east = 2.0 - 4.0 * (t - 3.0) / 6.0
    else:
        east = -2.0 + 2.0 * (t - 9.0) / 3.0
    return (0.0, east, 0.0)


_D3 = 3.0 / math.sqrt(2.0)  # 3 m/s diagonal
_D15 = 1.5 / math.sqrt(2.0)
SEQUENCE: tuple[Phase, ...] = (
    _rest("fit"),
    *_out_and_back("N 0.5", (0.5, 0.0, 0.0), 4.0, "fit"),
    *_out_and_back("E 1", (0.0, 1.0, 0.0), 4.0, "fit"),
    *_out_and_back("N 2", (2.0, 0.0, 0.0), 4.0, "fit"),
    *_out_and_back("NE 3", (_D3, _D3, 0.0), 4.0, "fit"),
    *_reversal("E 1 reversal", (0.0, 1.0, 0.0), 4.0, "fit"),
    *_reversal("N 2 reversal", (2.0, 0.0, 0.0), 4.0, "fit"),
    *_out_and_back("up 0.5", (0.0, 0.0, -0.5), 3.0, "fit"),
    *_out_and_back("up 1", (0.0, 0.0, -1.0), 3.0, "fit"),
    *_out_and_back("NE 1.4 up 0.5", (1.0, 1.0, -0.5), 4.0, "fit"),
    *_out_and_back("E 2", (0.0, 2.0, 0.0), 4.0, "held-out"),
    *_out_and_back("SE 1.5", (-_D15, _D15, 0.0), 4.0, "held-out"),
    *_reversal("N 3 reversal", (3.0, 0.0, 0.0), 4.0, "held-out"),
    *_out_and_back("up 0.75", (0.0, 0.0, -0.75), 3.0, "held-out"),
    Phase("swarm-like", 16.0, "held-out", _swarm_like),
    _rest("held-out"),
    Phase("ramp E ±2", 12.0, "held-out", _ramp),
    _rest("held-out"),
)


# -- flying ------------------------------------------------------------------------------------


@dataclass
class FlightLog:
    """What was sent and received (wall times: time.monotonic() of sending / receipt)."""

    autopilot: Kind
    firmware: str
    phase_start_wall_s: list[float]
    command_wall_s: list[float]
    command_ned_m_s: list[Ned]
    sample_wall_s: list[float]
    sample_boot_ms: list[int]
    sample_position_ned_m: list[Ned]
    sample_velocity_ned_m_s: list[Ned]
    late_ticks: int = 0  # setpoint ticks more than one period late (skipped)

    def to_json(self) -> dict[str, Any]:
        return {
            "autopilot": self.autopilot, "firmware": self.firmware,
            "phases": [{"label": p.label, "part": p.part, "duration_s": p.duration_s,
                        "start_wall_s": s}
                       for p, s in zip(SEQUENCE, self.phase_start_wall_s, strict=True)],
            "commands": {"wall_s": self.command_wall_s, "ned_m_s": self.command_ned_m_s},
            "samples": {"wall_s": self.sample_wall_s, "time_boot_ms": self.sample_boot_ms,
                        "position_ned_m": self.sample_position_ned_m,
                        "velocity_ned_m_s": self.sample_velocity_ned_m_s},
            "late_ticks": self.late_ticks,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> FlightLog:
        phases = data["phases"]
        if [p["label"] for p in phases] != [p.label for p in SEQUENCE]:
            raise FitError("the log's phases are not this script's SEQUENCE (an older log?)")
        return cls(data["autopilot"], data["firmware"], [p["start_wall_s"] for p in phases],
                   data["commands"]["wall_s"], [tuple(c) for c in data["commands"]["ned_m_s"]],
                   data["samples"]["wall_s"], data["samples"]["time_boot_ms"],
                   [tuple(c) for c in data["samples"]["position_ned_m"]],
                   [tuple(c) for c in data["samples"]["velocity_ned_m_s"]],
                   int(data.get("late_ticks", 0)))


class CompanionLink:
    """The companion link as an agent has it: reads the autopilot, sends setpoints and
    commands, logs every LOCAL_POSITION_NED while ``recording``."""

    def __init__(self, port: int, kind: Kind) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self.kind = kind
        self.conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=SYSTEM_ID,
            source_component=COMPANION_COMPONENT_ID, dialect="ardupilotmega")
        self.mavlink = mavutil.mavlink
        self.heard = False
        self.armed = False
        self.position_ned_m: Array | None = None
        self.velocity_ned_m_s: Array | None = None
        self.position_count = 0
        self.acks: dict[int, int] = {}
        self.said: deque[str] = deque(maxlen=5)
        self.recording = False
        self.sample_wall_s: list[float] = []
        self.sample_boot_ms: list[int] = []
        self.sample_position: list[Ned] = []
        self.sample_velocity: list[Ned] = []
        self._last_heartbeat_s = -math.inf
        self.command_wall_s: list[float] = []
        self.command_ned: list[Ned] = []

    def close(self) -> None:
        self.conn.close()

    # -- reading -------------------------------------------------------------------------------
    def wait(self, timeout_s: float) -> None:
        """Until a datagram arrives or ``timeout_s`` passes, then read everything there is."""
        if timeout_s > 0:
            select.select([self.conn.port.fileno()], [], [], timeout_s)
        for _ in range(1000):
            msg = self.conn.recv_msg()
            if msg is None:
                return
            self._handle(msg, time.monotonic())

    def _handle(self, msg: Any, now_s: float) -> None:
        if msg.get_srcSystem() != SYSTEM_ID or msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            return
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            position, velocity = (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz)
            if not all(math.isfinite(c) for c in position + velocity):
                return
            self.position_ned_m = np.array(position)
            self.velocity_ned_m_s = np.array(velocity)
            self.position_count += 1
            if self.recording:
                self.sample_wall_s.append(now_s)
                self.sample_boot_ms.append(int(msg.time_boot_ms))
                self.sample_position.append(position)
                self.sample_velocity.append(velocity)
        elif kind == "HEARTBEAT":
            self.heard = True
            self.armed = bool(msg.base_mode & 128)
        elif kind == "COMMAND_ACK":
            self.acks[int(msg.command)] = int(msg.result)
        elif kind == "STATUSTEXT":
            self.said.append(str(msg.text))
            progress(f"autopilot: {msg.text}")

    # -- sending -------------------------------------------------------------------------------
    def _heartbeat(self) -> None:
        now = time.monotonic()
        if now - self._last_heartbeat_s >= HEARTBEAT_PERIOD_S:
            self._last_heartbeat_s = now
            self.conn.mav.heartbeat_send(self.mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                         self.mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                         self.mavlink.MAV_STATE_ACTIVE)

    def send_velocity(self, ned_m_s: Ned, log: bool) -> None:
        """A velocity setpoint (type mask 0x0DC7, MAV_FRAME_LOCAL_NED), as the swarm's."""
        self._setpoint(VELOCITY_ONLY_TYPE_MASK, (0.0, 0.0, 0.0), ned_m_s)
        if log:
            self.command_wall_s.append(time.monotonic())
            self.command_ned.append(ned_m_s)

    def send_position(self, ned_m: Ned) -> None:
        self._setpoint(POSITION_ONLY_TYPE_MASK, ned_m, (0.0, 0.0, 0.0))

    def _setpoint(self, type_mask: int, position: Ned, velocity: Ned) -> None:
        self.conn.mav.set_position_target_local_ned_send(
            0, SYSTEM_ID, AUTOPILOT_COMPONENT_ID, MAV_FRAME_LOCAL_NED, type_mask,
            *position, *velocity, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._heartbeat()

    def send_command(self, command: int, *params: float) -> None:
        values = [*params, *[0.0] * (7 - len(params))]
        self.conn.mav.command_long_send(SYSTEM_ID, AUTOPILOT_COMPONENT_ID, command, 0,
                                        *values)
        self._heartbeat()

    # -- loops -----------------------------------------------------------------------------------
    def run(self, duration_s: float, stream: Callable[[], None] | None = None,
            period_s: float = SETPOINT_PERIOD_S,
            done: Callable[[], bool] | None = None) -> bool:
        """Read for up to ``duration_s``, calling ``stream`` every ``period_s``; True as soon
        as ``done()`` holds."""
        start = time.monotonic()
        next_tick = start
        while True:
            now = time.monotonic()
            if stream is not None and now >= next_tick:
                stream()
                next_tick = max(next_tick + period_s, now)
            if done is not None and done():
                return True
            if now - start >= duration_s:
                return False
            until = min(next_tick if stream is not None else math.inf, start + duration_s)
            self.wait(max(until - time.monotonic(), 0.0))

    def command(self, what: str, command: int, params: Sequence[float], timeout_s: float,
                stream: Callable[[], None] | None = None,
                period_s: float = SETPOINT_PERIOD_S) -> None:
        """COMMAND_LONG until ACCEPTED: resent after 1 s without an answer, 1 s after a
        refusal; FitError naming the last answer and what the autopilot said after
        ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        last = "no answer"
        while time.monotonic() < deadline:
            self.acks.pop(command, None)
            self.send_command(command, *params)
            answered = self.run(1.0, stream, period_s, lambda: command in self.acks)
            while answered and self.acks.get(command) == MAV_RESULT_IN_PROGRESS:
                self.acks.pop(command, None)
                answered = self.run(1.0, stream, period_s, lambda: command in self.acks)
            if not answered:
                continue
            result = self.acks[command]
            if result == MAV_RESULT_ACCEPTED:
                progress(f"{what}: accepted")
                return
            if f"result {result}" not in last:
                progress(f"{what}: refused (MAV_RESULT {result}), retrying")
            last = f"result {result}"
            self.run(1.0, stream, period_s)
        said = f"; the autopilot said {list(self.said)}" if self.said else ""
        raise FitError(f"{what} not accepted within {timeout_s:g} s ({last}){said}")

    def request_positions(self, timeout_s: float = 10.0) -> None:
        """LOCAL_POSITION_NED at 50 Hz, asked again every 2 s until ≥ 40 arrive in a second."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.send_command(MAV_CMD_SET_MESSAGE_INTERVAL, LOCAL_POSITION_NED_ID,
                              POSITION_INTERVAL_US)
            self.run(1.0)
            before = self.position_count
            self.run(1.0)
            if self.position_count - before >= 40:
                return
        raise FitError(f"LOCAL_POSITION_NED not at 50 Hz on the companion link within "
                       f"{timeout_s:g} s (got {self.position_count} in all); is the "
                       f"autopilot's EKF up?")


def default_firmware(kind: Kind) -> Firmware:
    """``VIGIL_ARDUCOPTER`` / ``VIGIL_PX4``, else ``../shared/autopilots`` beside the repo."""
    found = firmware_from_env(kind)
    if found is not None:
        return found
    base = ROOT.parent / "shared" / "autopilots"
    return Firmware.at(base / "ardupilot" / "arducopter" if kind == "ardupilot" else base / "px4")


def take_off(link: CompanionLink, kind: Kind) -> None:
    """Into the air, 5 m above where it stands, the way the swarm's agents do it."""
    assert link.position_ned_m is not None
    ground = link.position_ned_m.copy()
    target_down_m = float(ground[2]) - TAKEOFF_HEIGHT_M
    stream: Callable[[], None] | None = None
    if kind == "ardupilot":
        link.command("GUIDED", MAV_CMD_DO_SET_MODE, MODE_ARGS[kind], 10.0)
        link.command("ARM", MAV_CMD_COMPONENT_ARM_DISARM, (1.0,), ARM_TIMEOUT_S)
        link.command("NAV_TAKEOFF", MAV_CMD_NAV_TAKEOFF,
                     (0, 0, 0, 0, 0, 0, TAKEOFF_HEIGHT_M), 10.0)
    else:
        hover = (float(ground[0]), float(ground[1]), target_down_m)

        def stream() -> None:
            link.send_position(hover)

        link.run(1.0, stream, CLIMB_SETPOINT_PERIOD_S)
        link.command("OFFBOARD", MAV_CMD_DO_SET_MODE, MODE_ARGS[kind], 10.0, stream,
                     CLIMB_SETPOINT_PERIOD_S)
        link.command("ARM", MAV_CMD_COMPONENT_ARM_DISARM, (1.0,), ARM_TIMEOUT_S, stream,
                     CLIMB_SETPOINT_PERIOD_S)

    def there() -> bool:
        p, v = link.position_ned_m, link.velocity_ned_m_s
        return (p is not None and v is not None and abs(p[2] - target_down_m) < CLIMB_TOLERANCE_M
                and float(np.linalg.norm(v)) < 0.2)

    if not link.run(CLIMB_TIMEOUT_S, stream, CLIMB_SETPOINT_PERIOD_S, there):
        raise FitError(f"not {TAKEOFF_HEIGHT_M:g} m up within {CLIMB_TIMEOUT_S:g} s "
                       f"(down = {link.position_ned_m}); the autopilot said {list(link.said)}")
    progress(f"up at {TAKEOFF_HEIGHT_M:g} m")
    link.run(1.0, stream, CLIMB_SETPOINT_PERIOD_S)  # settle


def fly_sequence(link: CompanionLink) -> tuple[list[float], int]:
    """``SEQUENCE`` as velocity setpoints every 20 ms on one tick schedule (a tick more than a
    period late is skipped and counted); returns each phase's start (wall) and the skips."""
    starts = np.concatenate([[0.0], np.cumsum([p.duration_s for p in SEQUENCE])])
    total_s = float(starts[-1])
    phase_start_wall_s: list[float] = []
    late = 0
    link.recording = True
    begin = time.monotonic()
    tick = 0
    while True:
        due = begin + tick * SETPOINT_PERIOD_S
        now = time.monotonic()
        if now < due:
            link.wait(due - now)
            continue
        if now - due > SETPOINT_PERIOD_S:
            skipped = int((now - due) / SETPOINT_PERIOD_S)
            late += skipped
            tick += skipped
            due = begin + tick * SETPOINT_PERIOD_S
        t = due - begin
        if t >= total_s:
            break
        index = int(np.searchsorted(starts, t, side="right")) - 1
        while len(phase_start_wall_s) <= index:
            phase_start_wall_s.append(begin + float(starts[len(phase_start_wall_s)]))
            if SEQUENCE[len(phase_start_wall_s) - 1].label != "rest":
                progress(f"{t:6.1f} s  {SEQUENCE[len(phase_start_wall_s) - 1].label}")
        link.send_velocity(SEQUENCE[index].command(t - float(starts[index])), log=True)
        tick += 1
    link.send_velocity((0.0, 0.0, 0.0), log=True)
    link.run(1.0, lambda: link.send_velocity((0.0, 0.0, 0.0), log=True))
    link.recording = False
    return phase_start_wall_s, late


def fly(firmware: Firmware, console_log: Path) -> FlightLog:
    """One SITL, up, the sequence, down (stopped); the log of what was sent and measured."""
    kind = firmware.kind
    companion_port, monitor_port = free_udp_port(), free_udp_port()
    link = CompanionLink(companion_port, kind)
    spec = SitlSpec(firmware, instance=free_instances(kind, 1)[0], system_id=SYSTEM_ID,
                    home=HOME, companion_port=companion_port, monitor_port=monitor_port,
                    params=default_params(kind, 3.0 if kind == "ardupilot" else 0.5))
    instance = SitlInstance(spec, console_log)
    monitor: SitlMonitor | None = None
    try:
        instance.start()
        progress(f"started {firmware.name} (pid {instance.pid}, console {console_log})")
        monitor = SitlMonitor([instance], log=progress)
        monitor.wait_ready(READY_TIMEOUT_S)
        if not link.run(10.0, done=lambda: link.heard):
            raise FitError("no HEARTBEAT on the companion link within 10 s")
        link.request_positions()
        take_off(link, kind)
        starts, late = fly_sequence(link)
        if instance.poll() is not None:
            raise FitError(f"{firmware.name} exited (code {instance.poll()}) during the flight")
    finally:
        if monitor is not None:
            monitor.close()
        instance.stop()
        link.close()
    return FlightLog(kind, str(firmware.path), starts, link.command_wall_s, link.command_ned,
                     link.sample_wall_s, link.sample_boot_ms, link.sample_position,
                     link.sample_velocity, late)


# -- the autopilot's clock ----------------------------------------------------------------------


@dataclass(frozen=True)
class ClockMap:
    """Wall time of receipt → the autopilot's boot time: a + b·wall + envelope(wall)."""

    offset_s: float  # a
    rate: float  # b: autopilot seconds per wall second
    envelope_wall_s: Array  # bin centres
    envelope_s: Array  # upper envelope of the residuals there
    latency_s: Array  # per sample: envelope − residual, over b (how late it arrived) [s]

    def boot_s(self, wall_s: Array) -> Array:
        wall = np.asarray(wall_s, dtype=float)
        return (self.offset_s + self.rate * wall
                + np.interp(wall, self.envelope_wall_s, self.envelope_s))


def clock_map(sample_wall_s: Array, sample_boot_s: Array) -> ClockMap:
    """The mapping of the module docstring (2.): least squares, then the upper envelope of
    the residuals in ±1 s (a sample that arrived late lies below it)."""
    rate, offset = np.polyfit(sample_wall_s, sample_boot_s, 1)
    residual = sample_boot_s - (offset + rate * sample_wall_s)
    width = ENVELOPE_HALF_WINDOW_S
    bins = np.floor((sample_wall_s - sample_wall_s[0]) / width).astype(int)
    peak = np.full(bins.max() + 1, -np.inf)
    np.maximum.at(peak, bins, residual)
    padded = np.concatenate([[-np.inf], peak, [-np.inf]])
    envelope = np.maximum(np.maximum(padded[:-2], padded[1:-1]), padded[2:])
    centres = sample_wall_s[0] + (np.arange(peak.size) + 0.5) * width
    keep = np.isfinite(envelope)
    envelope, centres = envelope[keep], centres[keep]
    latency = (np.interp(sample_wall_s, centres, envelope) - residual) / rate
    return ClockMap(float(offset), float(rate), centres, envelope, latency)


# -- the fit ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Part:
    """One part of the sequence on a 50 Hz grid of the autopilot's clock."""

    name: str
    t_s: Array  # grid [s, boot time]
    measured_m_s: Array  # (n, 3) measured velocity at the grid times (linear interpolation)
    command_boot_s: Array  # every setpoint, at its boot time
    command_m_s: Array  # (m, 3)

    def command_at(self, delay_s: float = 0.0) -> Array:
        """(n, 3): the setpoint in force at t − delay for each grid time t (zero before the
        first)."""
        index = np.searchsorted(self.command_boot_s, self.t_s - delay_s, side="right") - 1
        out = self.command_m_s[np.clip(index, 0, None)].copy()
        out[index < 0] = 0.0
        return out


def simulate(response: VelocityResponse, command_m_s: Array, v0_m_s: Array) -> Array:
    """v_model on the grid: v[0] = v0 (measured), v[k+1] = response.step(v[k], u[k], ΔT)."""
    out = np.empty_like(command_m_s)
    velocity = np.asarray(v0_m_s, dtype=float).copy()
    out[0] = velocity
    for k in range(command_m_s.shape[0] - 1):
        velocity = response.step(velocity, command_m_s[k], FIT_DT_S)
        out[k + 1] = velocity
    return out


def rms_m_s(model_m_s: Array, measured_m_s: Array) -> float:
    """sqrt(mean over samples of ‖model − measured‖²) (the columns given are the group)."""
    error = model_m_s - measured_m_s
    return float(np.sqrt(np.mean(np.sum(error * error, axis=1))))


def model_rms(part: Part, group: tuple[int, ...], tau_s: float, accel_m_s2: float,
              delay_s: float = 0.0, gain: float = 1.0) -> float:
    """RMS error of ``VelocityResponse(τ, a_max)`` driven by gain·u(t − delay) on ``part``
    (delay 0 and gain 1: the emulator's model)."""
    cols = list(group)
    command = gain * part.command_at(delay_s)[:, cols]
    measured = part.measured_m_s[:, cols]
    model = simulate(VelocityResponse(tau_s, accel_m_s2), command, measured[0])
    return rms_m_s(model[1:], measured[1:])


# The diagnostics' third parameter (not in the emulator): name, bounds, start, simplex step.
EXTRAS: dict[str, tuple[tuple[float, float], float, float]] = {
    "delay_s": ((0.0, 1.5), 0.2, 0.05),  # a pure delay before the lag
    "gain": ((0.3, 1.5), 0.9, 0.05),  # a steady-state gain (PX4's deficit)
}


def fit_response(part: Part, group: tuple[int, ...],
                 extra: str | None = None) -> dict[str, float]:
    """τ and a_max (and the ``EXTRAS`` parameter ``extra``, if given) minimizing
    ``model_rms`` on ``part``: the best of a coarse grid, then Nelder-Mead within the
    bounds."""
    start: tuple[float, ...]
    scores = {(tau, accel): model_rms(part, group, tau, accel)
              for tau in TAU_GRID_S for accel in ACCEL_GRID_M_S2}
    start = min(scores, key=scores.__getitem__)
    bounds = [TAU_BOUNDS_S, ACCEL_BOUNDS_M_S2]
    steps = [0.05, 0.5]
    if extra is not None:
        extra_bounds, extra_start, extra_step = EXTRAS[extra]
        start, bounds, steps = (*start, extra_start), [*bounds, extra_bounds], \
            [*steps, extra_step]

    def rms(values: Sequence[float]) -> float:
        named = {} if extra is None else {extra: values[2]}
        return model_rms(part, group, values[0], values[1], **named)

    def objective(x: Array) -> float:
        values = [float(v) for v in x]
        if not all(lo <= v <= hi for v, (lo, hi) in zip(values, bounds, strict=True)):
            return 1e3
        return rms(values)

    simplex = np.vstack([start, *(np.asarray(start) + np.diag(steps))])
    found = minimize(objective, np.asarray(start), method="Nelder-Mead",
                     options={"initial_simplex": simplex, "xatol": 1e-3, "fatol": 1e-6,
                              "maxfev": 300})
    values = [float(v) for v in found.x]
    if values[1] >= 0.95 * ACCEL_BOUNDS_M_S2[1]:
        values[1] = 0.0  # at the bound: no limit, which the emulator writes as 0
    result = {"time_constant_s": values[0], "accel_limit_m_s2": values[1],
              "rms_m_s": rms(values), "evaluations": int(found.nfev)}
    if extra is not None:
        result[extra] = values[2]
    return result


def best_lag(part: Part, group: tuple[int, ...]) -> tuple[float, float]:
    """The pure delay d (0-1.5 s, 10 ms steps) minimizing the RMS of v_measured − u(t − d),
    and that RMS."""
    cols = list(group)
    measured = part.measured_m_s[:, cols]
    errors = [rms_m_s(part.command_at(float(d))[:, cols], measured) for d in LAG_SCAN_S]
    best = int(np.argmin(errors))
    return float(LAG_SCAN_S[best]), float(errors[best])


def steady_gains(log: FlightLog, clock: ClockMap, t_s: Array, measured_m_s: Array,
                 group: tuple[int, ...]) -> list[float]:
    """For each hold of a command within ``group`` only: the mean measured velocity over the
    hold's last second, projected on the command, over the command's size."""
    cols, other = list(group), [c for c in range(3) if c not in group]
    gains = []
    for phase, start_wall in zip(SEQUENCE, log.phase_start_wall_s, strict=True):
        command = np.array(phase.command(0.0))
        if not phase.hold or phase.duration_s < STEADY_MIN_HOLD_S or np.any(command[other]):
            continue
        end = float(clock.boot_s(np.array([start_wall + phase.duration_s]))[0])
        window = (t_s >= end - STEADY_WINDOW_S) & (t_s < end)
        if not np.any(window):
            continue
        u = command[cols]
        mean = measured_m_s[window][:, cols].mean(axis=0)
        gains.append(float(mean @ u / (u @ u)))
    return gains


def build_parts(log: FlightLog) -> tuple[ClockMap, dict[str, Part], Array, Array]:
    """The clock map, the fit and held-out parts, and the whole grid with its measurements."""
    wall = np.asarray(log.sample_wall_s, dtype=float)
    boot = np.asarray(log.sample_boot_ms, dtype=float) / 1000.0
    if wall.size < 100:
        raise FitError(f"only {wall.size} LOCAL_POSITION_NED samples in the log")
    order = np.argsort(boot, kind="stable")
    boot, wall = boot[order], wall[order]
    velocity = np.asarray(log.sample_velocity_ned_m_s, dtype=float)[order]
    unique = np.concatenate([[True], np.diff(boot) > 0])  # a repeated stamp: keep the first
    boot, wall, velocity = boot[unique], wall[unique], velocity[unique]
    clock = clock_map(wall, boot)
    command_boot = clock.boot_s(np.asarray(log.command_wall_s, dtype=float))
    command = np.asarray(log.command_ned_m_s, dtype=float)
    phase_boot = clock.boot_s(np.asarray(log.phase_start_wall_s, dtype=float))
    end_boot = float(command_boot[-1])
    held_index = next(i for i, p in enumerate(SEQUENCE) if p.part == "held-out")
    smooth_index = next(i for i, p in enumerate(SEQUENCE) if p.label == SMOOTH_FROM)
    bounds = {"fit": (float(phase_boot[0]), float(phase_boot[held_index])),
              "held-out": (float(phase_boot[held_index]), end_boot),
              "smooth": (float(phase_boot[smooth_index]), end_boot)}
    t_all = np.arange(phase_boot[0], end_boot, FIT_DT_S)
    measured_all = np.column_stack([np.interp(t_all, boot, velocity[:, c]) for c in range(3)])
    parts = {}
    for name, (lo, hi) in bounds.items():
        keep = (t_all >= lo) & (t_all < hi)
        parts[name] = Part(name, t_all[keep], measured_all[keep], command_boot, command)
    return clock, parts, t_all, measured_all


def analyse(log: FlightLog) -> dict[str, Any]:
    """Every figure of the module docstring (3.) from a flight log."""
    clock, parts, t_all, measured_all = build_parts(log)
    fit_part = parts["fit"]
    boot = np.asarray(log.sample_boot_ms, dtype=float) / 1000.0
    gaps = np.diff(np.sort(boot))
    groups: dict[str, Any] = {}
    fitted: dict[str, dict[str, float]] = {}
    for name, group in GROUPS.items():
        progress(f"fitting {name}")
        fitted[name] = fit_response(fit_part, group)
    for name, group in GROUPS.items():
        params = fitted[name]
        tau, accel = params["time_constant_s"], params["accel_limit_m_s2"]
        joint = fitted["3-D"]
        progress(f"diagnostic fits {name}")
        delayed = fit_response(fit_part, group, "delay_s")
        scaled = fit_response(fit_part, group, "gain")
        entry: dict[str, Any] = {"components_ned": list(group), "params": params,
                                 "with_delay": delayed, "with_gain": scaled}
        gains = steady_gains(log, clock, t_all, measured_all, group)
        entry["steady_gain"] = {"median": float(np.median(gains)) if gains else None,
                                "min": min(gains, default=None),
                                "max": max(gains, default=None), "values": gains}
        for part in parts.values():
            lag_s, lag_rms = best_lag(part, group)
            entry[part.name] = {
                "seconds": float(part.t_s[-1] - part.t_s[0]),
                "lag_s": lag_s,
                "rms_ideal_m_s": model_rms(part, group, 0.0, 0.0),
                "rms_ideal_at_lag_m_s": lag_rms,
                "rms_fitted_m_s": model_rms(part, group, tau, accel),
                "rms_joint_fit_m_s": model_rms(part, group, joint["time_constant_s"],
                                               joint["accel_limit_m_s2"]),
                "rms_with_delay_m_s": model_rms(part, group, delayed["time_constant_s"],
                                                delayed["accel_limit_m_s2"],
                                                delayed["delay_s"]),
                "rms_with_gain_m_s": model_rms(part, group, scaled["time_constant_s"],
                                               scaled["accel_limit_m_s2"],
                                               gain=scaled["gain"]),
            }
        groups[name] = entry
    latency = clock.latency_s
    return {
        "autopilot": log.autopilot, "firmware": log.firmware,
        "model": "swarm.models.kinematics.VelocityResponse, ΔT = 20 ms; RMS = sqrt(mean ‖Δv‖²)",
        "groups": groups,
        "clock": {"autopilot_s_per_wall_s": clock.rate,
                  "receipt_latency_s": {"median": float(np.median(latency)),
                                        "p99": float(np.percentile(latency, 99))}},
        "samples": {"count": len(log.sample_boot_ms),
                    "interval_s": {"median": float(np.median(gaps)),
                                   "max": float(gaps.max())},
                    "setpoints": len(log.command_wall_s), "late_ticks": log.late_ticks},
    }


# -- output -----------------------------------------------------------------------------------


PARTS = ("fit", "held-out", "smooth")


def _by_part(entry: dict[str, Any], key: str, digits: int = 3) -> str:
    """'fit/held-out/smooth' of one figure of a group."""
    return "/".join(fmt(entry[part][key], digits) for part in PARTS)


def tables(result: dict[str, Any]) -> list[Table]:
    name = {"ardupilot": "ArduCopter SITL", "px4": "PX4 SITL (SIH)"}[result["autopilot"]]
    groups = result["groups"]
    any_group = next(iter(groups.values()))
    fit_s, held_s, smooth_s = (any_group[p]["seconds"] for p in PARTS)
    seconds = (f"fit part {fit_s:.0f} s, held-out part {held_s:.0f} s, of which smooth "
               f"{smooth_s:.0f} s")
    main = new_table(
        f"{name}: velocity response fitted (VelocityResponse, 50 Hz; {seconds})",
        ["group", "τ [s]", "a_max [m/s²]", "lag [s]", "ideal RMS [m/s]", "ideal at lag",
         "fitted RMS", "3-D pair RMS", "steady gain"],
        caption="each figure on the fit / held-out / smooth (held-out's last part) parts; "
                "RMS = sqrt(mean ‖v_model − v_measured‖²) over the group's components; "
                "a_max 0 = no limit; lag = the pure delay best aligning u(t − lag) with v; "
                "steady gain = measured/commanded over a hold's last second, median "
                "(min–max)")
    for group, entry in groups.items():
        params, gain = entry["params"], entry["steady_gain"]
        main.add_row(
            group, fmt(params["time_constant_s"], 3), fmt(params["accel_limit_m_s2"], 2),
            _by_part(entry, "lag_s", 2), _by_part(entry, "rms_ideal_m_s"),
            _by_part(entry, "rms_ideal_at_lag_m_s"), _by_part(entry, "rms_fitted_m_s"),
            _by_part(entry, "rms_joint_fit_m_s"),
            f"{fmt(gain['median'], 2)} ({fmt(gain['min'], 2)}–{fmt(gain['max'], 2)})"
            if gain["median"] is not None else "—")
    extra = new_table(
        f"{name}: diagnostics — the same model behind a pure delay, or with a steady-state "
        f"gain (neither is in the emulator)",
        ["group", "delay [s]", "τ [s]", "a_max [m/s²]", "RMS [m/s]", "gain", "τ [s]",
         "a_max [m/s²]", "RMS [m/s]"],
        caption="RMS on the fit / held-out / smooth parts")
    for group, entry in groups.items():
        d, g = entry["with_delay"], entry["with_gain"]
        extra.add_row(group, fmt(d["delay_s"], 3), fmt(d["time_constant_s"], 3),
                      fmt(d["accel_limit_m_s2"], 2), _by_part(entry, "rms_with_delay_m_s"),
                      fmt(g["gain"], 3), fmt(g["time_constant_s"], 3),
                      fmt(g["accel_limit_m_s2"], 2), _by_part(entry, "rms_with_gain_m_s"))
    clock, samples = result["clock"], result["samples"]
    link = new_table(f"{name}: link and clock", ["figure", "value"])
    link.add_row("autopilot s per wall s", fmt(clock["autopilot_s_per_wall_s"], 4))
    link.add_row("receipt latency median / p99 [ms]",
                 f"{fmt(clock['receipt_latency_s']['median'] * 1e3, 1)} / "
                 f"{fmt(clock['receipt_latency_s']['p99'] * 1e3, 1)}")
    link.add_row("LOCAL_POSITION_NED samples", str(samples["count"]))
    link.add_row("sample interval median / max [ms]",
                 f"{fmt(samples['interval_s']['median'] * 1e3, 1)} / "
                 f"{fmt(samples['interval_s']['max'] * 1e3, 1)}")
    link.add_row("setpoints sent / ticks skipped (late)",
                 f"{samples['setpoints']} / {samples['late_ticks']}")
    return [main, extra, link]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--autopilot", choices=KINDS, default="ardupilot")
    parser.add_argument("--firmware", type=Path, default=None,
                        help="arducopter binary or PX4 build directory (default: "
                             "VIGIL_ARDUCOPTER / VIGIL_PX4, else ../shared/autopilots)")
    parser.add_argument("--out", type=Path, default=RESULTS / "vehicle_response",
                        help="directory for the log and the results")
    parser.add_argument("--from-log", type=Path, default=None,
                        help="fit this *_log.json again instead of flying")
    args = parser.parse_args(argv)
    return run_main("fit_vehicle_response", lambda: _run(parser, args, argv))


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace,
         argv: Sequence[str] | None) -> int:
    out = console()
    try:
        if args.from_log is not None:
            log = FlightLog.from_json(json.loads(args.from_log.read_text()))
            stem = args.from_log.name.removesuffix("_log.json")
        else:
            firmware = (Firmware.at(args.firmware) if args.firmware is not None
                        else default_firmware(args.autopilot))
            if firmware.kind != args.autopilot:
                parser.error(f"{firmware.path} is {firmware.kind} firmware ({firmware.name}), "
                             f"not --autopilot {args.autopilot}")
            stem = f"{firmware.kind}_{time.strftime('%Y%m%d-%H%M%S')}"
            args.out.mkdir(parents=True, exist_ok=True)
            log = fly(firmware, args.out / f"{stem}_sitl.log")
            write_json(args.out / f"{stem}_log.json", log.to_json())
        result = analyse(log)
    except OSError as error:  # a file or the firmware's sockets: not ours, said in one line
        print(f"fit_vehicle_response: {error}", file=sys.stderr)
        return EXIT_FAILED
    for table in tables(result):
        out.print(table)
    result["command"] = " ".join(["python", "benchmarks/fit_vehicle_response.py",
                                  *(argv if argv is not None else sys.argv[1:])])
    result["machine"] = machine_info()
    path = args.out / f"{stem}_fit.json"
    write_json(path, result)
    out.print(f"wrote {path} and {args.out / (stem + '_log.json')}")
    return EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
