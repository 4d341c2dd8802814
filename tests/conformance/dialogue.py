"""The conformance dialogues: one scripted MAVLink conversation per flavour, written once and
flown against any target (a real SITL or our emulated vehicle, see ``test_conformance``).

Each step sends what a companion computer sends and checks two kinds of answer:

* ``Record.answer``: the same discrete answer on every target — COMMAND_ACK results, the mode
  and armed flag of the HEARTBEAT, EXTENDED_SYS_STATE's landed state, what is said;
* ``Record.figure``: a measured figure (a rate, a delay, a speed, a height) within a stated
  band. The bands are the real firmware's figures (measured on the SITL builds by these
  dialogues, see each step) with a margin for run-to-run spread and a loaded machine; the
  emulator must land in the same band.

Heights are measured from where the vehicle stood before its first takeoff (``ground``),
horizontal positions as displacements: PX4 SIH's local origin is not where the vehicle stands
(its local position on the ground is off by up to 2 m, and drifts), so absolute coordinates
are never compared. Steps are ordered so that one boot serves a whole flavour: ground state,
takeoff, in-air answers, velocity step, setpoint loss, hold, return, land, and a second takeoff
with setpoints sent during its climb. Waits are ``Pilot.until`` with a deadline; the only fixed
waits are the commanded durations themselves (a setpoint held for N s, a rate counted over N s).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.conformance.pilot import DialogueError, Pilot, Sample, Setpoint, mav

ACCEPTED = mav.MAV_RESULT_ACCEPTED
TEMPORARILY_REJECTED = mav.MAV_RESULT_TEMPORARILY_REJECTED
FAILED = mav.MAV_RESULT_FAILED
ON_GROUND, IN_AIR = mav.MAV_LANDED_STATE_ON_GROUND, mav.MAV_LANDED_STATE_IN_AIR
TAKEOFF, LANDING = mav.MAV_LANDED_STATE_TAKEOFF, mav.MAV_LANDED_STATE_LANDING
LOCAL_POSITION_NED, EXTENDED_SYS_STATE, HEARTBEAT = 32, 245, 0
STILL_M_S = 0.2  # "at rest": horizontal speed below this [m/s]
PX4_STILL_M_S = 0.4  # PX4 SIH drifts 0.2-0.3 m/s while holding (GPS noise), measured
ARM_READY_TIMEOUT_S = 60.0  # PX4 SITL refuses to arm (TEMPORARILY_REJECTED) ~37 s after boot


@dataclass
class Record:
    """What one run of a dialogue answered and measured (checked as it goes)."""

    target: str
    answers: dict[str, Any] = field(default_factory=dict)
    figures: dict[str, tuple[float, float, float, str]] = field(default_factory=dict)
    log: Callable[[str], None] = field(default=lambda line: None)

    def answer(self, name: str, got: Any, expected: Any) -> None:
        self.answers[name] = got
        self.log(f"  {name}: {got!r}")
        if got != expected:
            raise DialogueError(f"{self.target}: {name}: got {got!r}, expected {expected!r}")

    def figure(self, name: str, value: float, low: float, high: float, unit: str) -> None:
        self.figures[name] = (float(value), low, high, unit)
        self.log(f"  {name}: {value:.3f} {unit} (band {low:g}..{high:g})")
        if not (math.isfinite(value) and low <= value <= high):
            raise DialogueError(f"{self.target}: {name} = {value:.3f} {unit}, outside "
                                f"{low:g}..{high:g} {unit}")

    def table(self) -> str:
        lines = [f"{self.target}:"]
        lines += [f"  {name:58s} {value:8.3f} {unit:5s} [{low:g}, {high:g}]"
                  for name, (value, low, high, unit) in self.figures.items()]
        return "\n".join(lines)


# ------------------------------------------------------------------------------- measurements
def _speed_xy(sample: Sample) -> float:
    return float(np.hypot(sample.velocity_ned_m_s[0], sample.velocity_ned_m_s[1]))


def _mean_ned(samples: list[Sample]) -> np.ndarray:
    if not samples:
        raise DialogueError("no LOCAL_POSITION_NED samples to average")
    return np.mean([s.ned_m for s in samples], axis=0)


def _log_where(pilot: Pilot, record: Record, ground_ned: np.ndarray, what: str) -> None:
    """The vehicle's horizontal position from home, in the log (what a figure that depends
    on the way flown so far can be checked against)."""
    north, east = (pilot.sample.ned_m - ground_ned)[:2]
    record.log(f"{pilot.now():7.2f} {what}: {north:+.2f} m north, {east:+.2f} m east of home")


def _from_home_m(pilot: Pilot, ground_ned: np.ndarray) -> float:
    """Horizontal distance from home (where the vehicle stood before its takeoff)."""
    return float(np.hypot(*(pilot.sample.ned_m - ground_ned)[:2]))


def _height(pilot: Pilot, ground_ned: np.ndarray) -> float:
    return float(ground_ned[2] - pilot.sample.ned_m[2])


def _first_time(samples: list[Sample], check: Callable[[Sample], bool]) -> float:
    for s in samples:
        if check(s):
            return s.t_s
    return math.nan


def _ground_reference(pilot: Pilot, record: Record, rate_window_s: float = 1.0) -> np.ndarray:
    """Count LOCAL_POSITION_NED for ``rate_window_s`` (its rate is a figure) and return where
    the vehicle stands (mean over that window)."""
    pilot.until(lambda: bool(pilot.samples) and pilot.landed_state is not None, 10.0,
                "LOCAL_POSITION_NED and EXTENDED_SYS_STATE after requesting them")
    start = pilot.now()
    pilot.pump(rate_window_s)
    window = pilot.since(start)
    record.figure("LOCAL_POSITION_NED rate after asking for 50 Hz",
                  len(window) / (pilot.now() - start), 42.0, 56.0, "Hz")
    return _mean_ned(window)


def _velocity_step(pilot: Pilot, record: Record, speed_m_s: float, hold_s: float,
                   still_m_s: float, end_band: tuple[float, float],
                   t63_band: tuple[float, float]) -> None:
    """From rest, velocity setpoints east at ``speed_m_s`` for ``hold_s``: the speed reached
    (mean over the last 0.5 s), the time to 63 % of it, and the height kept."""
    pilot.setpoint = Setpoint.velocity(0.0, 0.0, 0.0)
    pilot.until(lambda: _speed_xy(pilot.sample) < still_m_s, 5.0, "at rest before the step")
    start = pilot.now()
    z_start = pilot.sample.ned_m[2]
    pilot.setpoint = Setpoint.velocity(0.0, speed_m_s, 0.0)
    pilot.pump(hold_s)
    window = pilot.since(start)
    reached = float(np.mean([s.velocity_ned_m_s[1] for s in window
                             if s.t_s >= pilot.now() - 0.5]))
    # 63 % of the speed the vehicle reaches, not of the command: PX4 SIH levels off near
    # 0.6-0.65 m/s for ~0.5 s on its way to ~0.8 m/s, so a crossing of 0.63 m/s came anywhere
    # from 0.6 to 1.5 s after the step (four traces: 0.60-1.37 s; of what it reaches: 0.51-0.77).
    t63 = _first_time(window, lambda s: s.velocity_ned_m_s[1] >= 0.63 * reached) - start
    record.figure(f"velocity step {speed_m_s:g} m/s east: time to 63 % of the speed reached",
                  t63, *t63_band, "s")
    record.figure(f"velocity step {speed_m_s:g} m/s east: speed after {hold_s:g} s", reached,
                  *end_band, "m/s")
    drift = max(abs(s.ned_m[2] - z_start) for s in window)
    record.figure("velocity step: height change", drift, 0.0, 0.4, "m")


def _at_rest_after(pilot: Pilot, start_s: float, still_m_s: float,
                   timeout_s: float, what: str, window_s: float = 0.5) -> float:
    """Seconds from ``start_s`` until the horizontal speed, averaged over the last
    ``window_s`` (PX4 SIH's reported velocity is noisy: ±0.3 m/s sample to sample), is below
    ``still_m_s``; the time is that of the window's middle."""
    def still() -> bool:
        recent = pilot.since(pilot.now() - window_s)
        return len(recent) >= 5 and float(np.mean([_speed_xy(s) for s in recent])) < still_m_s
    pilot.until(still, timeout_s, what)
    return pilot.sample.t_s - 0.5 * window_s - start_s


def _slowest_mean_speed(samples: list[Sample], window_s: float) -> float:
    """The smallest horizontal speed averaged over consecutive ``window_s`` windows of the
    samples (PX4 SIH's reported velocity is noisy sample to sample) [m/s]."""
    start = samples[0].t_s
    bins: dict[int, list[float]] = {}
    for s in samples:
        bins.setdefault(int((s.t_s - start) // window_s), []).append(_speed_xy(s))
    return min(float(np.mean(speeds)) for speeds in bins.values() if len(speeds) >= 3)


def _landing(pilot: Pilot, record: Record, ground_ned: np.ndarray, rate_band: tuple[float, float],
             disarm_band: tuple[float, float]) -> None:
    """After a land command: LANDING, the descent rate (mean between 2 m and 0.6 m above the
    ground, or over the first 2 s if lower), touchdown, ON_GROUND, disarmed."""
    pilot.until(lambda: pilot.landed_state == LANDING, 2.0, "landed state LANDING")
    start = pilot.now()
    pilot.until(lambda: pilot.landed_state == ON_GROUND, 25.0, "landed state ON_GROUND")
    landed = pilot.now()
    descent = [s for s in pilot.since(start) if 0.6 <= ground_ned[2] - s.ned_m[2] <= 2.0]
    if len(descent) < 10:
        descent = [s for s in pilot.since(start) if s.t_s <= start + 2.0]
    record.figure("land: descent rate", float(np.mean([s.velocity_ned_m_s[2] for s in descent])),
                  *rate_band, "m/s")
    pilot.until(lambda: not pilot.armed, 10.0, "auto-disarm after landing")
    record.figure("land: ON_GROUND → disarmed", pilot.now() - landed, *disarm_band, "s")


def _arm_when_ready(pilot: Pilot, record: Record, where: str = "on the ground") -> None:
    """ARM once a second until ACCEPTED: the real PX4 says TEMPORARILY_REJECTED until its
    pre-arm checks pass (~37 s after boot; ``swarm.mavlink.sitl`` calls it ready a little earlier),
    and again while one of them fails for a moment (seen in CI: ``check_baro_no_data`` from SIH
    on a loaded machine, a second after it had armed); the emulator is ready at once. Any other
    answer fails."""
    deadline = pilot.now() + ARM_READY_TIMEOUT_S
    while (result := pilot.arm()) == TEMPORARILY_REJECTED and pilot.now() < deadline:
        pilot.pump(1.0)
    record.answer(f"ARM {where} (once pre-arm checks pass)", result, ACCEPTED)
    pilot.until(lambda: pilot.armed, 2.0, "armed")


# ------------------------------------------------------------------------------- ArduCopter
def ardupilot_dialogue(pilot: Pilot, record: Record) -> None:
    """ArduCopter (measured on ArduPilot 90700977c5 SITL; figures in each band's comment)."""
    # --- ground: heartbeat, streams, refusals, modes
    pilot.until(lambda: pilot.heartbeat is not None, 10.0, "first HEARTBEAT")
    assert pilot.heartbeat is not None
    record.answer("HEARTBEAT autopilot", pilot.heartbeat.autopilot,
                  mav.MAV_AUTOPILOT_ARDUPILOTMEGA)
    record.answer("HEARTBEAT type", pilot.heartbeat.vehicle_type, mav.MAV_TYPE_QUADROTOR)
    record.answer("boot mode, armed", (pilot.mode, pilot.armed), ("STABILIZE", False))
    for message_id, hz in ((LOCAL_POSITION_NED, 50.0), (EXTENDED_SYS_STATE, 10.0),
                           (HEARTBEAT, 10.0)):
        record.answer(f"SET_MESSAGE_INTERVAL {message_id} at {hz:g} Hz",
                      pilot.message_interval(message_id, hz), ACCEPTED)
    ground = _ground_reference(pilot, record)  # measured 50.0 Hz
    record.answer("landed state before takeoff", pilot.landed_state, ON_GROUND)
    record.answer("NAV_TAKEOFF in STABILIZE, disarmed", pilot.takeoff(3.0), FAILED)
    record.answer("DO_SET_MODE BRAKE on the ground", pilot.set_mode(17), ACCEPTED)
    pilot.until(lambda: pilot.mode == "BRAKE", 2.0, "mode BRAKE")
    said = len(pilot.texts)
    record.answer("ARM in BRAKE", pilot.arm(), FAILED)
    pilot.until(lambda: len(pilot.texts) > said, 2.0, "a STATUSTEXT saying why")
    record.answer("ARM in BRAKE: STATUSTEXT", pilot.texts[-1][1], "Arm: BRAKE mode not armable")
    record.answer("DO_SET_MODE GUIDED", pilot.set_mode(4), ACCEPTED)
    pilot.until(lambda: pilot.mode == "GUIDED", 2.0, "mode GUIDED")
    record.answer("NAV_TAKEOFF in GUIDED, disarmed", pilot.takeoff(3.0), FAILED)
    record.answer("ARM in GUIDED", pilot.arm(), ACCEPTED)
    pilot.until(lambda: pilot.armed, 2.0, "armed")
    record.answer("DISARM on the ground", pilot.arm(False), ACCEPTED)
    pilot.until(lambda: not pilot.armed, 2.0, "disarmed")
    record.answer("ARM again", pilot.arm(), ACCEPTED)
    pilot.until(lambda: pilot.armed, 2.0, "armed")
    record.answer("NAV_TAKEOFF to 0 m", pilot.takeoff(0.0), FAILED)

    # --- takeoff on the ground: spool-up, TAKEOFF while climbing, IN_AIR at the altitude
    commanded = pilot.now()
    record.answer("NAV_TAKEOFF to 3 m, armed on the ground", pilot.takeoff(3.0), ACCEPTED)
    pilot.pump(1.0)
    record.answer("landed state 1 s after NAV_TAKEOFF (spool-up)", pilot.landed_state, ON_GROUND)
    pilot.until(lambda: _height(pilot, ground) > 0.2, 8.0, "leaving the ground")
    record.figure("takeoff: NAV_TAKEOFF → 0.2 m up", pilot.now() - commanded, 2.5, 4.5, "s")
    pilot.until(lambda: _height(pilot, ground) > 1.0, 5.0, "1 m up")
    record.answer("landed state while climbing", pilot.landed_state, TAKEOFF)
    climb_start = pilot.now()
    pilot.until(lambda: pilot.landed_state == IN_AIR, 10.0, "landed state IN_AIR")
    record.figure("takeoff: height at IN_AIR", _height(pilot, ground), 2.8, 3.1, "m")
    peak = max(-s.velocity_ned_m_s[2] for s in pilot.since(climb_start - 1.0))
    record.figure("takeoff: peak climb rate", peak, 1.0, 1.7, "m/s")  # measured 1.31-1.37
    pilot.pump(1.0)
    record.figure("takeoff: height 1 s later", _height(pilot, ground), 2.85, 3.15, "m")

    # --- in the air
    record.answer("NAV_TAKEOFF in the air", pilot.takeoff(5.0), FAILED)
    record.answer("DISARM in the air", pilot.arm(False), FAILED)
    pilot.pump(0.3)
    record.answer("armed after DISARM in the air", pilot.armed, True)
    record.answer("ARM in the air (already armed)", pilot.arm(), ACCEPTED)

    # --- velocity following (measured: 63 % of the speed reached after 0.65-0.73 s, 0.99-1.04
    # m/s after 3-4 s)
    _velocity_step(pilot, record, 1.0, 3.0, STILL_M_S, (0.9, 1.1), (0.35, 1.1))

    # --- setpoint loss: the last velocity for GUID_TIMEOUT, then stop; still GUIDED, armed
    record.answer("PARAM_SET GUID_TIMEOUT 1.5",
                  pilot.set_param("GUID_TIMEOUT", 1.5, mav.MAV_PARAM_TYPE_REAL32), 1.5)
    lost = pilot.now()
    pilot.setpoint = None
    slowing = pilot.until(lambda: _speed_xy(pilot.sample) < 0.5, 6.0, "slowing after the loss")
    record.figure("loss: last setpoint → below 0.5 m/s", slowing, 1.5, 2.8, "s")  # measured
    kept = [_speed_xy(s) for s in pilot.since(lost) if s.t_s <= lost + 1.3]
    record.figure("loss: slowest speed during GUID_TIMEOUT", min(kept), 0.85, 1.1, "m/s")
    record.figure("loss: at rest after",
                  _at_rest_after(pilot, lost, STILL_M_S, 6.0, "at rest after the loss"),
                  1.8, 4.5, "s")
    record.answer("loss: mode, armed", (pilot.mode, pilot.armed), ("GUIDED", True))

    # --- hold = BRAKE (measured from 2 m/s: at rest ~2 s later, 2.3-2.8 m on)
    pilot.setpoint = Setpoint.velocity(0.0, 1.5, 0.0)
    pilot.pump(2.5)
    pilot.setpoint = None
    braking = pilot.sample
    record.answer("DO_SET_MODE BRAKE in the air", pilot.set_mode(17), ACCEPTED)
    pilot.until(lambda: pilot.mode == "BRAKE", 2.0, "mode BRAKE")
    record.figure("BRAKE from 1.5 m/s: at rest after",
                  _at_rest_after(pilot, braking.t_s, STILL_M_S, 8.0, "at rest in BRAKE"),
                  1.0, 5.0, "s")
    record.figure("BRAKE from 1.5 m/s: distance to rest",
                  float(np.hypot(*(pilot.sample.ned_m - braking.ned_m)[:2])), 0.8, 3.5, "m")

    # --- return = RTL (RTL_ALT 2 m: below the vehicle, so no climb): heads home
    record.answer("PARAM_SET RTL_ALT 200 cm",
                  pilot.set_param("RTL_ALT", 200, mav.MAV_PARAM_TYPE_INT32), 200.0)
    away = _from_home_m(pilot, ground)
    height = _height(pilot, ground)
    record.figure("RTL: distance from home", away, 3.0, 14.0, "m")
    record.answer("DO_SET_MODE RTL", pilot.set_mode(6), ACCEPTED)
    pilot.until(lambda: pilot.mode == "RTL", 2.0, "mode RTL")
    halved = pilot.until(lambda: _from_home_m(pilot, ground) < away / 2,
                         10.0, "half way home")
    record.figure("RTL: time to halve the distance home", halved, 1.0, 6.0, "s")
    record.figure("RTL: height change on the way", abs(_height(pilot, ground) - height),
                  0.0, 0.5, "m")
    record.answer("RTL: landed state on the way", pilot.landed_state, IN_AIR)

    # --- land = LAND (measured: 0.50 m/s, touchdown → ON_GROUND 1.7 s → disarmed 0.45 s)
    record.answer("DO_SET_MODE LAND", pilot.set_mode(9), ACCEPTED)
    pilot.until(lambda: pilot.mode == "LAND", 2.0, "mode LAND")
    _landing(pilot, record, ground, (0.4, 0.6), (0.0, 2.0))
    record.answer("mode after landing", pilot.mode, "LAND")

    # --- second takeoff; a setpoint during the climb replaces the takeoff target
    record.answer("DO_SET_MODE GUIDED on the ground", pilot.set_mode(4), ACCEPTED)
    pilot.until(lambda: pilot.mode == "GUIDED", 2.0, "mode GUIDED")
    record.answer("ARM after landing", pilot.arm(), ACCEPTED)
    pilot.until(lambda: pilot.armed, 2.0, "armed")
    ground = _mean_ned(pilot.since(pilot.now() - 0.3))
    record.answer("NAV_TAKEOFF to 5 m", pilot.takeoff(5.0), ACCEPTED)
    pilot.until(lambda: _height(pilot, ground) > 1.0, 8.0, "1 m up")
    record.answer("landed state at 1 m", pilot.landed_state, TAKEOFF)
    interrupted = _height(pilot, ground)
    pilot.setpoint = Setpoint.velocity(0.0, 0.0, 0.0)
    pilot.until(lambda: pilot.landed_state == IN_AIR, 2.0, "IN_AIR after the setpoint")
    pilot.pump(3.0)
    heights = [ground[2] - s.ned_m[2] for s in pilot.since(pilot.now() - 3.0)]
    record.figure("setpoint at 1 m into a 5 m takeoff: highest point above it",
                  max(heights) - interrupted, 0.0, 2.0, "m")  # measured 1.3: vertical decel
    record.figure("setpoint in the climb: vertical speed 3 s later",
                  abs(float(pilot.sample.velocity_ned_m_s[2])), 0.0, 0.25, "m/s")


# ------------------------------------------------------------------------------- PX4
def px4_dialogue(pilot: Pilot, record: Record) -> None:
    """PX4 v1.15.4 SIH (measured on that SITL; figures in each band's comment)."""
    pilot.poll_heartbeat_s = 0.25  # PX4 sends HEARTBEAT at 1 Hz only; ask for more
    pilot.until(lambda: pilot.heartbeat is not None, 10.0, "first HEARTBEAT")
    assert pilot.heartbeat is not None
    record.answer("HEARTBEAT autopilot", pilot.heartbeat.autopilot, mav.MAV_AUTOPILOT_PX4)
    record.answer("HEARTBEAT type", pilot.heartbeat.vehicle_type, mav.MAV_TYPE_QUADROTOR)
    record.answer("boot mode, custom_mode, armed",
                  (pilot.mode, pilot.heartbeat.custom_mode, pilot.armed),
                  ("LOITER", 0x03040000, False))
    record.answer("SET_MESSAGE_INTERVAL 32 at 50 Hz",
                  pilot.message_interval(LOCAL_POSITION_NED, 50.0), ACCEPTED)
    record.answer("SET_MESSAGE_INTERVAL 245 at 10 Hz",
                  pilot.message_interval(EXTENDED_SYS_STATE, 10.0), ACCEPTED)
    record.answer("SET_MESSAGE_INTERVAL 0 (HEARTBEAT) at 10 Hz",
                  pilot.message_interval(HEARTBEAT, 10.0), FAILED)
    ground = _ground_reference(pilot, record)  # measured 49.5 Hz
    record.answer("landed state before takeoff", pilot.landed_state, ON_GROUND)
    # 2.5 m (PX4's default): at 1.5 m SIH's Hold wandered at 0.5 m/s in one run of three.
    record.answer("PARAM_SET MIS_TAKEOFF_ALT 2.5",
                  pilot.set_param("MIS_TAKEOFF_ALT", 2.5, mav.MAV_PARAM_TYPE_REAL32), 2.5)
    record.answer("NAV_TAKEOFF disarmed", pilot.takeoff(), ACCEPTED)
    pilot.pump(1.0)
    record.answer("after NAV_TAKEOFF disarmed: mode, armed, landed state",
                  (pilot.mode, pilot.armed, pilot.landed_state), ("TAKEOFF", False, ON_GROUND))
    # Armed in AUTO.TAKEOFF it would lift off at once: back to Hold before arming.
    record.answer("DO_SET_MODE AUTO.LOITER disarmed", pilot.set_mode(4, 3), ACCEPTED)
    pilot.until(lambda: pilot.mode == "LOITER", 2.0, "mode LOITER")
    # Pre-arm checks: the real one refuses (TEMPORARILY_REJECTED) until ~37 s after boot.
    _arm_when_ready(pilot, record)
    record.answer("DISARM on the ground", pilot.arm(False), ACCEPTED)
    pilot.until(lambda: not pilot.armed, 2.0, "disarmed")
    record.answer("DO_SET_MODE OFFBOARD disarmed, no setpoints", pilot.set_mode(6), ACCEPTED)
    pilot.until(lambda: pilot.mode == "OFFBOARD", 2.0, "mode OFFBOARD")
    record.answer("ARM in OFFBOARD without setpoints", pilot.arm(), TEMPORARILY_REJECTED)
    record.answer("DO_SET_MODE AUTO.LOITER", pilot.set_mode(4, 3), ACCEPTED)
    pilot.until(lambda: pilot.mode == "LOITER", 2.0, "mode LOITER")
    _arm_when_ready(pilot, record, "in AUTO.LOITER")

    # --- takeoff on the ground: AUTO.TAKEOFF to MIS_TAKEOFF_ALT, then Hold
    ground = _mean_ned(pilot.since(pilot.now() - 0.5))
    commanded = pilot.now()
    record.answer("NAV_TAKEOFF armed on the ground", pilot.takeoff(), ACCEPTED)
    pilot.until(lambda: pilot.mode == "TAKEOFF", 2.0, "mode TAKEOFF")
    pilot.until(lambda: pilot.landed_state == TAKEOFF, 3.0, "landed state TAKEOFF")
    # Timed by the landed state: SIH's height estimate wanders by tenths of a metre while
    # armed on the ground (measured: "0.3 m up" after 2.3-4.5 s in four runs).
    pilot.until(lambda: pilot.landed_state == IN_AIR, 15.0, "landed state IN_AIR")
    record.figure("takeoff: NAV_TAKEOFF → landed state IN_AIR", pilot.now() - commanded,
                  3.5, 9.0, "s")
    pilot.until(lambda: pilot.mode == "LOITER", 5.0, "Hold after the takeoff")
    record.answer("landed state after the takeoff", pilot.landed_state, IN_AIR)
    # PX4 switches to Hold 0.5-0.7 m below the takeoff altitude and ends the climb in Hold
    # (measured: 0.8 m at the switch, 1.26 m 0.5 s later, 1.41 m after 3 s, 1.50 m after 4 s;
    # the ground estimate itself sinks ~0.2 m while armed on the ground): judge it 3 s later.
    pilot.pump(3.0)
    record.figure("takeoff: height 3 s after Hold (MIS_TAKEOFF_ALT 2.5 m)",
                  _height(pilot, ground), 2.1, 2.9, "m")

    # --- in the air: NAV_TAKEOFF climbs again; setpoints + OFFBOARD during that climb
    record.answer("DISARM in the air", pilot.arm(False), TEMPORARILY_REJECTED)
    record.answer("DO_SET_MODE OFFBOARD armed, no setpoints", pilot.set_mode(6),
                  TEMPORARILY_REJECTED)
    before = _height(pilot, ground)
    record.answer("NAV_TAKEOFF in the air", pilot.takeoff(), ACCEPTED)
    pilot.until(lambda: pilot.mode == "TAKEOFF", 2.0, "mode TAKEOFF in the air")
    record.answer("landed state during a takeoff in the air", pilot.landed_state, IN_AIR)
    pilot.until(lambda: _height(pilot, ground) > before + 0.5, 6.0, "climbing again")
    interrupted = _height(pilot, ground)
    pilot.setpoint = Setpoint.velocity(0.0, 0.0, 0.0)
    pilot.pump(0.3)
    record.answer("DO_SET_MODE OFFBOARD during the climb", pilot.set_mode(6), ACCEPTED)
    pilot.until(lambda: pilot.mode == "OFFBOARD", 2.0, "mode OFFBOARD")
    pilot.pump(1.5)
    record.figure("OFFBOARD in a takeoff climb: height above where it was asked",
                  _height(pilot, ground) - interrupted, -0.2, 1.5, "m")

    # --- velocity following (measured: 63 % of the speed reached after 0.51-0.77 s, idle or
    # beside four busy loops; 0.68-0.87 m/s after 3 s: PX4 SIH plateaus at ~0.76 of the
    # command for seconds, docs/guarantee_real_vehicles.md, "The fit")
    _log_where(pilot, record, ground, "before the velocity step")
    _velocity_step(pilot, record, 1.0, 3.0, PX4_STILL_M_S, (0.6, 1.1), (0.2, 1.2))
    _log_where(pilot, record, ground, "after the velocity step")

    # --- offboard loss: Hold after COM_OF_LOSS_T (1 s); setpoints again: OFFBOARD again
    lost = pilot.now()
    at_loss = max(float(np.mean([_speed_xy(s) for s in pilot.since(lost - 0.5)])), 0.1)
    pilot.setpoint = None
    record.figure("loss: last setpoint → Hold",
                  pilot.until(lambda: pilot.mode == "LOITER", 4.0, "Hold after the loss"),
                  0.9, 2.3, "s")
    record.answer("loss: armed", pilot.armed, True)
    # Judged by the braking, not by coming to rest: SIH's Hold brakes within ~0.4 s of the
    # switch and then drifts again with its simulated GPS noise, to 0.3-0.4 m/s 7 s after the
    # loss (a CI run: still 0.47 m/s at 6 s). This ratio measured 0.07-0.44 on SITL (4 runs;
    # the emulator 0.06); a vehicle that does not brake gives ~1; the band is the Hold's below.
    hold = pilot.now()
    pilot.pump(1.5)
    record.figure("loss: slowest 0.25 s in the first 1.5 s of Hold / speed at the loss",
                  _slowest_mean_speed(pilot.since(hold), 0.25) / at_loss, 0.0, 0.7, "")
    pilot.setpoint = Setpoint.velocity(0.0, 0.0, 0.0)
    record.figure("setpoints again → OFFBOARD again",
                  pilot.until(lambda: pilot.mode == "OFFBOARD", 3.0, "OFFBOARD again"),
                  0.0, 1.5, "s")

    # --- hold = AUTO.LOITER
    _log_where(pilot, record, ground, "before the hold leg")
    pilot.setpoint = Setpoint.velocity(0.0, 1.5, 0.0)
    pilot.pump(2.5)
    # RTL below needs a way to go. The way flown so far ends 6.7-6.8 m east of home here (two
    # runs beside the suite's CPU-bound tests), but a CI run reached RTL only 1.72 m from home
    # (without this log); so the leg flies on east, for at most 5 s, until 3.5 m from home.
    pilot.until(lambda: _from_home_m(pilot, ground) >= 3.5, 5.0, "3.5 m from home")
    holding = pilot.sample
    _log_where(pilot, record, ground, "at the switch to Hold")
    record.answer("DO_SET_MODE AUTO.LOITER (Hold) in the air", pilot.set_mode(4, 3), ACCEPTED)
    pilot.setpoint = None
    pilot.until(lambda: pilot.mode == "LOITER", 2.0, "mode LOITER")
    # Judged by the slow-down, not by coming to rest: in 3 of 6 runs SIH's Hold went on
    # drifting at ~0.5 m/s for > 6 s (the ratio below: 0.33, 0.49; the others at rest after
    # 0.93-1.03 s, 0.85-1.08 m on), which the emulator does not reproduce (0.23).
    pilot.pump(2.0)
    entry = max(_speed_xy(holding), 0.1)
    recent = pilot.since(pilot.now() - 0.5)
    record.figure("Hold from 1.2-1.5 m/s: speed 2 s later / speed at the switch",
                  float(np.mean([_speed_xy(s) for s in recent])) / entry, 0.0, 0.7, "")

    # --- return = AUTO.RTL (RTL_RETURN_ALT 1.5 m: below the vehicle, so no climb)
    for name in ("RTL_RETURN_ALT", "RTL_DESCEND_ALT"):
        record.answer(f"PARAM_SET {name} 1.5",
                      pilot.set_param(name, 1.5, mav.MAV_PARAM_TYPE_REAL32), 1.5)
    _log_where(pilot, record, ground, "before RTL")
    away = _from_home_m(pilot, ground)
    # How far the manoeuvres above took the vehicle (a precondition: RTL has a way to go; the
    # figures below scale with it). On PX4 SIH it varies with the velocity plateau (0.71-0.86
    # of the command) and with Hold's drift: a CI run measured 2.93 m, so ≥ 2.5 m.
    record.figure("RTL: distance from home", away, 2.5, 14.0, "m")
    record.answer("DO_SET_MODE AUTO.RTL", pilot.set_mode(4, 5), ACCEPTED)
    pilot.until(lambda: pilot.mode == "RTL", 2.0, "mode RTL")
    halved = pilot.until(lambda: _from_home_m(pilot, ground) < away / 2,
                         10.0, "half way home")
    record.figure("RTL: time to halve the distance home", halved, 1.0, 7.0, "s")

    # --- land = AUTO.LAND (measured ~0.7-1 m/s, ON_GROUND → disarmed 2-2.6 s)
    record.answer("DO_SET_MODE AUTO.LAND", pilot.set_mode(4, 6), ACCEPTED)
    pilot.until(lambda: pilot.mode == "LAND", 2.0, "mode LAND")
    _landing(pilot, record, ground, (0.4, 1.3), (1.0, 4.0))
    pilot.pump(1.0)
    record.answer("mode after landing and disarming", pilot.mode, "LOITER")  # before RTL

    # --- the agent's takeoff: position setpoints 2.5 m up streamed, OFFBOARD, ARM
    ground = _mean_ned(pilot.since(pilot.now() - 0.5))
    target = Setpoint.position(float(ground[0]), float(ground[1]), float(ground[2]) - 2.5)
    pilot.setpoint = target
    pilot.pump(0.5)
    record.answer("DO_SET_MODE OFFBOARD with position setpoints", pilot.set_mode(6), ACCEPTED)
    pilot.until(lambda: pilot.mode == "OFFBOARD", 2.0, "mode OFFBOARD")
    armed = pilot.now()
    record.answer("ARM in OFFBOARD with setpoints", pilot.arm(), ACCEPTED)
    # Lift-off by the landed state: after a landing PX4 SIH's height estimate on the ground
    # wanders by tenths of a metre within a second (measured), so "0.3 m up" is not a clock.
    pilot.until(lambda: pilot.landed_state != ON_GROUND, 8.0, "leaving the ground")
    record.figure("OFFBOARD takeoff: ARM → landed state not ON_GROUND", pilot.now() - armed,
                  0.6, 3.0, "s")  # measured 1.18 s
    record.answer("OFFBOARD takeoff: landed state", pilot.landed_state, IN_AIR)
    reached = pilot.until(lambda: abs(_height(pilot, ground) - 2.5) < 0.3, 12.0,
                          "within 0.3 m of the position setpoint")
    record.figure("OFFBOARD takeoff: ARM → within 0.3 m of 2.5 m", pilot.now() - armed,
                  3.0, 12.0, "s")
    del reached
