"""Real autopilot firmware in the loop: start, watch and stop ArduCopter and PX4 (SIH) SITL.

An instance is the autopilot's own flight code compiled for the host ("software in the loop")
with a simulated airframe inside: ArduPilot's ``arducopter`` binary with its built-in
multicopter model, or PX4's ``px4`` with SIH, PX4's built-in physics. Nothing of either is
part of this package: the user points at a build (docs/real_autopilots.md has the build
commands) with ``--sitl PATH`` on ``launch-swarm`` or the environment variables
``VIGIL_ARDUCOPTER`` (the ``arducopter`` binary) and ``VIGIL_PX4`` (a PX4 SITL build
directory holding ``bin/px4`` and ``etc/``).

Each instance runs in a temporary working directory of its own (its eeprom, parameters,
logs), leads a process group of its own (stopped as one: SIGTERM, then SIGKILL) and dies with
the process that started it (Linux parent-death signal), so no autopilot outlives a run.

Links: the autopilot sends two MAVLink 2 streams over UDP to 127.0.0.1, both as a client
(the autopilot picks its own source port, the receiver listens):

- the *companion* link to ``companion_port``, where the drone's agent listens
  (``udpin:127.0.0.1:<port>``) — ArduPilot's SERIAL0, PX4's "onboard" (offboard API) link;
- the *monitor* link to ``monitor_port`` — ArduPilot's SERIAL1, PX4's normal (GCS) link — on
  which ``SitlMonitor`` waits for the autopilot to be ready and then watches it.

Ports: ArduPilot binds UDP 5501 + 10·I (its RC input) for ``--instance I``; ``free_instances``
picks instances whose port is free. PX4's links bind the local ports this module picks
(PX4's own ``px4-rc.mavlink`` would send to 14540 + I and 14550, where other PX4 instances of
the machine send too; ours is first on PATH, which rcS searches for it).

Parameters are set at boot: for ArduPilot a defaults file after the firmware's own
(``--defaults copter.parm,ours.parm``), for PX4 our ``px4-rc.params``, which rcS sources from
PATH before the simulator starts.

Clock: ArduPilot boots at ``boot_speedup``× (its EKF and simulated GPS settle in ~4 s of wall
time instead of ~40) and is set back to 1× (``SIM_SPEEDUP``) once ready, before any agent
flies it: the swarm runs on the wall clock. PX4's SIH speed factor is fixed at start, so PX4
runs at 1× throughout, and can arm ~37 s after boot: its EKF2 aligns its tilt only after ~33 s
of SIH's noisy accelerometer. The stock boot is kept: a smaller initial tilt uncertainty
(EKF2_ANGERR_INIT) makes it ready in seconds but changes how the vehicle flies, outside the
bands of the conformance dialogues.
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np
from numpy.typing import NDArray

from swarm.children import die_with_parent
from swarm.errors import UsageError, VigilError
from swarm.models.frames import GeoPoint

Kind = Literal["ardupilot", "px4"]
KINDS: tuple[Kind, ...] = ("ardupilot", "px4")
ENV_ARDUCOPTER = "VIGIL_ARDUCOPTER"
ENV_PX4 = "VIGIL_PX4"
ENV_VARIABLE: dict[Kind, str] = {"ardupilot": ENV_ARDUCOPTER, "px4": ENV_PX4}

ARDUPILOT_RC_IN_BASE_PORT = 5501  # UDP, + 10·instance: the only port ArduPilot SITL binds here
PX4_AIRFRAME = "10040"  # sihsim_quadx
STOP_GRACE_S = 3.0
DEFAULT_BOOT_SPEEDUP = 10.0

Array = NDArray[np.float64]


class SitlError(VigilError, RuntimeError):
    """An autopilot SITL instance could not be found, started or brought up; one line."""


class FirmwareError(SitlError, UsageError):
    """A path or variable that names no usable SITL build (input, not a failed run)."""


# -- finding the firmware ----------------------------------------------------------------------


@dataclass(frozen=True)
class Firmware:
    """A SITL build: ``path`` is the ``arducopter`` binary or the PX4 build directory."""

    kind: Kind
    path: Path

    @property
    def name(self) -> str:
        return "ArduCopter SITL" if self.kind == "ardupilot" else "PX4 SITL (SIH)"

    @property
    def executable(self) -> Path:
        return self.path if self.kind == "ardupilot" else self.path / "bin" / "px4"

    @property
    def copter_defaults(self) -> Path | None:
        """ArduPilot's ``copter.parm`` (the defaults its autotest gives the SITL copter: frame,
        RC calibration, sensor offsets): beside the binary, or in the source tree of a waf
        build (``build/sitl/bin/arducopter`` → ``Tools/autotest/default_params/``)."""
        if self.kind != "ardupilot":
            return None
        for candidate in (self.path.parent / "copter.parm",
                          self.path.parents[3] / "Tools" / "autotest" / "default_params"
                          / "copter.parm" if len(self.path.parents) > 3 else None):
            if candidate is not None and candidate.is_file():
                return candidate
        return None

    @classmethod
    def at(cls, path: str | Path) -> Firmware:
        """The build at ``path`` (kind told from what is there); SitlError (one line) when it
        is neither an ArduCopter binary nor a PX4 build directory."""
        path = Path(path).expanduser()
        if path.is_dir():
            root = path.parent if path.name == "bin" else path
            if (root / "bin" / "px4").is_file() and (root / "etc").is_dir():
                firmware = cls("px4", root.resolve())
                firmware.check()
                return firmware
            raise FirmwareError(f"{path}: not a PX4 SITL build directory (no bin/px4 and etc/ "
                            f"in it); give the arducopter binary or the PX4 build directory")
        if path.is_file():
            if path.name == "px4" and (path.parent.parent / "etc").is_dir():
                return cls.at(path.parent.parent)
            firmware = cls("ardupilot", path.resolve())
            firmware.check()
            return firmware
        raise FirmwareError(f"{path}: no such file or directory (expected the arducopter SITL "
                        f"binary or a PX4 SITL build directory)")

    def check(self) -> None:
        executable = self.executable
        if not executable.is_file():
            raise FirmwareError(f"{executable}: no such file")
        if not os.access(executable, os.X_OK):
            raise FirmwareError(f"{executable}: not executable (chmod +x?)")
        with executable.open("rb") as handle:
            if handle.read(4) != b"\x7fELF":
                raise FirmwareError(f"{executable}: not an executable binary (ELF)")


def firmware_from_env(kind: Kind) -> Firmware | None:
    """The build named by ``VIGIL_ARDUCOPTER`` / ``VIGIL_PX4`` (None when unset); SitlError
    when the variable names something unusable."""
    value = os.environ.get(ENV_VARIABLE[kind], "")
    if not value:
        return None
    path = Path(value).expanduser()
    if kind == "ardupilot" and path.is_dir() and not (path / "bin" / "px4").is_file():
        inside = path / "arducopter"
        hint = (f" ({inside} is there)" if inside.is_file()
                else " (build it with ./waf copter: build/sitl/bin/arducopter)")
        raise FirmwareError(f"{ENV_VARIABLE[kind]}={value} is a directory: it names the "
                            f"arducopter SITL binary itself{hint}")
    firmware = Firmware.at(value)
    if firmware.kind != kind:
        raise FirmwareError(f"{ENV_VARIABLE[kind]}={value} is a {firmware.name}, not {kind}")
    return firmware


# -- one instance --------------------------------------------------------------------------------


@dataclass(frozen=True)
class SitlSpec:
    """What one autopilot instance is to be."""

    firmware: Firmware
    instance: int  # ArduPilot: --instance (port block); PX4: -i
    system_id: int  # MAVLink system id (drone id + 1)
    home: GeoPoint
    companion_port: int  # UDP port on 127.0.0.1 the companion (agent) link is sent to
    monitor_port: int  # UDP port on 127.0.0.1 the monitor link is sent to
    params: tuple[tuple[str, float], ...] = ()  # set at boot, after the firmware's defaults
    boot_speedup: float = DEFAULT_BOOT_SPEEDUP  # ArduPilot only

    def __post_init__(self) -> None:
        if not 1 <= self.system_id <= 250:
            raise SitlError(f"system id {self.system_id} out of range 1..250")
        if not 0 <= self.instance <= 200:
            raise SitlError(f"instance {self.instance} out of range 0..200")
        if not (math.isfinite(self.boot_speedup) and 1.0 <= self.boot_speedup <= 100.0):
            raise SitlError(f"boot speedup {self.boot_speedup} out of range 1..100")


# Ports handed out by ``free_udp_port``: below Linux's ephemeral range (32768-60999 by
# default), where the kernel never picks a port for a socket that binds none, and below the
# launcher's MAVLink blocks (from 24540).
PICKED_UDP_PORTS = range(20000, 24500)
_held_port_locks: list[IO[bytes]] = []  # this process's claims, released when it exits


def udp_port_lock_path(port: int) -> Path:
    return Path(tempfile.gettempdir()) / f"vigil-udp-{port}.lock"


def try_exclusive_lock(path: Path) -> IO[bytes] | None:
    """The file at ``path``, opened and exclusively locked (``flock``) until the returned handle
    is closed or this process exits (the kernel then drops the lock); None if another handle,
    in this process or another, holds it."""
    handle = open(path, "ab")  # noqa: SIM115 - held by the caller
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        return None
    return handle


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nobody has bound now and nobody else will be handed.

    The port is only bound later, often much later (a SITL boot takes up to a minute), so it
    must stay free meanwhile. A port of the kernel's choice did not: the kernel hands the
    same ephemeral range to every socket that sends before binding (each autopilot's and
    MAVProxy's outgoing links), and one took a dialogue's port during a boot ("Address
    already in use" in CI). So it comes from ``PICKED_UDP_PORTS``, outside that range, and
    the process holds a lock on it (``<tmp>/vigil-udp-<port>.lock``) until it exits, so no
    other caller, in this process or another, is handed it.
    """
    first = (os.getpid() * 97) % len(PICKED_UDP_PORTS)  # processes start apart
    for step in range(len(PICKED_UDP_PORTS)):
        port = PICKED_UDP_PORTS[(first + step) % len(PICKED_UDP_PORTS)]
        handle = try_exclusive_lock(udp_port_lock_path(port))
        if handle is None:
            continue
        if _udp_port_free(port):
            _held_port_locks.append(handle)
            return port
        handle.close()
    raise SitlError(f"no free UDP port in {PICKED_UDP_PORTS.start}..{PICKED_UDP_PORTS.stop - 1}")


def _udp_port_free(port: int, host: str = "0.0.0.0") -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def free_instances(kind: Kind, count: int, start: int = 0) -> list[int]:
    """``count`` instance numbers whose fixed ports are free now (ArduPilot: UDP 5501 + 10·I;
    PX4 binds no port of its own here, so any numbers do)."""
    if kind == "px4":
        return list(range(start, start + count))
    found = [i for i in range(start, 200)
             if _udp_port_free(ARDUPILOT_RC_IN_BASE_PORT + 10 * i)][:count]
    if len(found) < count:
        raise SitlError(f"no {count} free ArduPilot SITL instances (UDP 5501 + 10·I in use)")
    return found


class SitlInstance:
    """One running autopilot (see the module docstring)."""

    def __init__(self, spec: SitlSpec, console_log: Path, workdir_parent: Path | None = None
                 ) -> None:
        self.spec = spec
        self.console_log = console_log
        self.workdir_parent = workdir_parent  # None: the system's temporary directory
        self.workdir: Path | None = None
        self.process: subprocess.Popen | None = None

    @property
    def name(self) -> str:
        return f"{self.spec.firmware.kind} SITL system {self.spec.system_id}"

    def start(self) -> None:
        spec = self.spec
        self.workdir = Path(tempfile.mkdtemp(prefix=f"vigil-sitl-{spec.system_id}-",
                                             dir=self.workdir_parent))
        try:
            if spec.firmware.kind == "ardupilot":
                argv, env = self._ardupilot_command()
            else:
                argv, env = self._px4_command()
        except BaseException:
            self._remove_workdir()
            raise
        with self.console_log.open("wb") as log:
            try:
                self.process = subprocess.Popen(
                    argv, cwd=self.workdir, env=env, stdin=subprocess.DEVNULL, stdout=log,
                    stderr=subprocess.STDOUT, start_new_session=True,
                    preexec_fn=die_with_parent)
            except OSError as err:
                self._remove_workdir()
                raise SitlError(f"cannot start {spec.firmware.executable}: {err}") from None

    def _ardupilot_command(self) -> tuple[list[str], dict[str, str]]:
        spec, workdir = self.spec, self.workdir
        assert workdir is not None
        params = workdir / "vigil.parm"
        params.write_text("".join(f"{name} {_param_text(value)}\n" for name, value in spec.params))
        shipped = spec.firmware.copter_defaults  # ArduPilot's own defaults for its SITL copter
        if shipped is None:
            raise SitlError(f"no copter.parm beside {spec.firmware.path} nor in its source tree: "
                            f"copy ArduPilot's Tools/autotest/default_params/copter.parm next "
                            f"to the binary (without it the SITL copter has no frame set)")
        defaults = [str(shipped), str(params)]
        home = spec.home
        argv = [str(spec.firmware.executable), "--model", "+",
                "--speedup", f"{spec.boot_speedup:g}", "--instance", str(spec.instance),
                "--wipe", "--defaults", ",".join(defaults),
                "--home", f"{home.lat_deg:.9f},{home.lon_deg:.9f},{home.alt_m:.3f},0",
                "--sysid", str(spec.system_id),
                "--serial0", f"udpclient:127.0.0.1:{spec.companion_port}",
                "--serial1", f"udpclient:127.0.0.1:{spec.monitor_port}",
                "--serial2", "none"]
        return argv, dict(os.environ)

    def _px4_command(self) -> tuple[list[str], dict[str, str]]:
        spec, workdir = self.spec, self.workdir
        assert workdir is not None
        root = spec.firmware.path
        bin_dir = workdir / "bin"
        bin_dir.mkdir()
        # PX4's commands are links named px4-<module> to the one binary; a build copied without
        # links (plain files) cannot run them, so they are made here for every module.
        for entry in (root / "bin").iterdir():
            name = entry.name
            if (name.startswith("px4-") and name != "px4-alias.sh") or name == "px4":
                (bin_dir / name).symlink_to(spec.firmware.executable)
        (bin_dir / "px4-alias.sh").symlink_to(root / "bin" / "px4-alias.sh")
        home = spec.home
        params = [("MAV_SYS_ID", spec.system_id),
                  ("SIH_LOC_LAT0", round(home.lat_deg * 1e7)),
                  ("SIH_LOC_LON0", round(home.lon_deg * 1e7)),
                  ("SIH_LOC_H0", home.alt_m),
                  *spec.params]
        (bin_dir / "px4-rc.params").write_text(
            "#!/bin/sh\n" + "".join(f"param set {name} {_param_text(value)}\n"
                                     for name, value in params))
        companion_local, monitor_local = free_udp_port(), free_udp_port()
        (bin_dir / "px4-rc.mavlink").write_text(
            "#!/bin/sh\n"
            f"mavlink start -u {companion_local} -r 4000000 -m onboard "
            f"-o {spec.companion_port}\n"
            f"mavlink start -u {monitor_local} -r 400000 -o {spec.monitor_port}\n")
        env = dict(os.environ, PX4_RUN_DIR=str(workdir), PX4_SYS_AUTOSTART=PX4_AIRFRAME,
                   PX4_SIMULATOR="sihsim", PX4_SIM_MODEL="sihsim_quadx",
                   PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
        for variable in ("PX4_HOME_LAT", "PX4_HOME_LON", "PX4_HOME_ALT",
                         "PX4_SIM_SPEED_FACTOR"):
            env.pop(variable, None)  # ours are the parameters above, at 1x
        argv = [str(bin_dir / "px4"), "-d", "-i", str(spec.instance), "-w", str(workdir),
                str(root / "etc")]
        return argv, env

    @property
    def pid(self) -> int | None:
        return None if self.process is None else self.process.pid

    def poll(self) -> int | None:
        """The exit code once the autopilot process has ended, else None."""
        return None if self.process is None else self.process.poll()

    def tail(self, lines: int = 12) -> list[str]:
        try:
            text = self.console_log.read_text(errors="replace")
        except OSError:
            return []
        return [line for line in text.splitlines() if line.strip()][-lines:]

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """Stop the whole process group (SIGTERM, SIGKILL after ``grace_s``) and remove the
        working directory; safe to call more than once."""
        process = self.process
        if process is not None:
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(process.pid, signal.SIGTERM)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    process.wait(timeout=grace_s)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(process.pid, signal.SIGKILL)  # anything left in its group
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(timeout=grace_s)
        self._remove_workdir()

    def _remove_workdir(self) -> None:
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
            self.workdir = None


def _param_text(value: float) -> str:
    """A parameter value as the autopilots parse it: integers in full (PX4 reads an int32
    parameter with strtol, so "-3.5e+08" would be -3), floats exactly."""
    if isinstance(value, int) or (float(value).is_integer() and abs(value) >= 2**24):
        return str(int(value))
    return repr(float(value))


def default_params(kind: Kind, setpoint_timeout_s: float) -> tuple[tuple[str, float], ...]:
    """What the swarm needs set on each autopilot (docs/real_autopilots.md,
    "What each autopilot needs set").

    ArduPilot: ``GUID_TIMEOUT`` = the setpoint-loss timeout. PX4: ``COM_OF_LOSS_T`` = the same,
    ``COM_OBL_RC_ACT`` = 5 (Hold on offboard loss: the default, Position mode, sinks without a
    pilot's sticks), ``SDLOG_MODE`` = -1 (no flight log: a full log is ~200 kB/s of disk per
    vehicle here).
    """
    if kind == "ardupilot":
        return (("GUID_TIMEOUT", setpoint_timeout_s),)
    return (("COM_OF_LOSS_T", setpoint_timeout_s), ("COM_OBL_RC_ACT", 5), ("SDLOG_MODE", -1))


# -- watching instances ----------------------------------------------------------------------------


@dataclass
class VehicleView:
    """What the monitor link last said about one autopilot (times: time.monotonic())."""

    system_id: int
    heartbeat_s: float | None = None
    autopilot: int | None = None
    mode: str = "UNKNOWN"
    armed: bool = False
    landed_state: int | None = None
    prearm_ok: bool = False  # SYS_STATUS: pre-arm checks reported present and healthy
    global_position: bool = False  # a GLOBAL_POSITION_INT arrived (PX4: global fix in use)
    local_ned: Array | None = None
    local_velocity_ned: Array | None = None
    local_s: float | None = None
    statustexts: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    params: dict[str, float] = field(default_factory=dict)
    recent_local: deque[tuple[float, Array]] = field(default_factory=lambda: deque(maxlen=200))


class SitlMonitor:
    """The launcher's own MAVLink link to each autopilot (the monitor links): waits until each
    is ready to fly, sets the clock back to 1×, and keeps the newest state of each.

    One pymavlink ``udpin`` per vehicle on its monitor port, drained by a thread of its own;
    ``on_state(index, view)`` (optional) runs on that thread after each LOCAL_POSITION_NED.
    """

    def __init__(self, instances: Sequence[SitlInstance], *,
                 log: Callable[[str], None] = print,
                 on_state: Callable[[int, VehicleView], None] | None = None) -> None:
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink import mavutil  # the launcher imports this module without it

        self._mavutil = mavutil
        self.instances = list(instances)
        self.log = log
        self.on_state = on_state
        self.views = [VehicleView(inst.spec.system_id) for inst in self.instances]
        # Datagrams pymavlink could not parse, per vehicle (the first is logged).
        self.malformed = [0] * len(self.instances)
        self._lock = threading.Lock()
        self._links: list[Any] = []
        try:
            for inst in self.instances:
                self._links.append(mavutil.mavlink_connection(
                    f"udpin:127.0.0.1:{inst.spec.monitor_port}", source_system=255,
                    source_component=mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER,
                    dialect="ardupilotmega"))
        except Exception:
            self.close()
            raise
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sitl-monitor", daemon=True)
        self._thread.start()

    # -- reading ----------------------------------------------------------------------------------
    def _run(self) -> None:
        import select

        fds = {link.port.fileno(): i for i, link in enumerate(self._links)}
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(list(fds), [], [], 0.1)
            except (OSError, ValueError):
                return
            for fd in ready:
                i = fds[fd]
                link = self._links[i]
                for _ in range(1000):
                    try:
                        msg = link.recv_msg()
                    except Exception as exc:  # pymavlink's parse errors have no common base
                        self.malformed[i] += 1
                        if self.malformed[i] == 1:
                            self.log(f"monitor link {i}: malformed datagram skipped "
                                     f"({type(exc).__name__}: {exc})")
                        continue
                    if msg is None:
                        break
                    self._handle(i, msg)

    def _handle(self, i: int, msg: Any) -> None:
        view = self.views[i]
        if msg.get_srcSystem() != view.system_id or msg.get_srcComponent() != 1:
            return
        kind = msg.get_type()
        now = time.monotonic()
        with self._lock:
            if kind == "HEARTBEAT":
                view.heartbeat_s = now
                view.autopilot = int(msg.autopilot)
                view.mode = self._mavutil.mode_string_v10(msg)
                view.armed = bool(msg.base_mode & 128)
            elif kind == "SYS_STATUS":
                bit = 0x10000000  # MAV_SYS_STATUS_PREARM_CHECK
                view.prearm_ok = bool(msg.onboard_control_sensors_present & bit
                                      and msg.onboard_control_sensors_health & bit)
            elif kind == "EXTENDED_SYS_STATE":
                view.landed_state = int(msg.landed_state)
            elif kind == "GLOBAL_POSITION_INT":
                view.global_position = True
            elif kind == "LOCAL_POSITION_NED":
                ned = np.array([msg.x, msg.y, msg.z], dtype=float)
                if np.all(np.isfinite(ned)):
                    view.local_ned = ned
                    view.local_velocity_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
                    view.local_s = now
                    view.recent_local.append((now, ned))
            elif kind == "STATUSTEXT":
                view.statustexts.append(str(msg.text))
            elif kind == "PARAM_VALUE":
                view.params[str(msg.param_id)] = float(msg.param_value)
            else:
                return
        if kind == "LOCAL_POSITION_NED" and self.on_state is not None:
            self.on_state(i, view)

    def view(self, i: int) -> VehicleView:
        with self._lock:
            return self.views[i]

    # -- commanding -------------------------------------------------------------------------------
    def _send_interval(self, i: int, message_id: int, interval_us: int) -> None:
        self._links[i].mav.command_long_send(self.views[i].system_id, 1, 511, 0, message_id,
                                             interval_us, 0, 0, 0, 0, 0)

    def request_streams(self, i: int) -> None:
        """What readiness and watching need: position at 10 Hz, status at 2 Hz."""
        mavlink = self._mavutil.mavlink
        for message_id, interval_us in ((mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100_000),
                                        (mavlink.MAVLINK_MSG_ID_SYS_STATUS, 500_000),
                                        (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 500_000),
                                        (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 500_000)):
            self._send_interval(i, message_id, interval_us)

    def set_param(self, i: int, name: str, value: float, timeout_s: float = 5.0) -> None:
        """PARAM_SET until the autopilot echoes the value (SitlError otherwise)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._links[i].mav.param_set_send(self.views[i].system_id, 1, name.encode(),
                                              float(value), 9)  # MAV_PARAM_TYPE_REAL32
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                with self._lock:
                    got = self.views[i].params.get(name)
                if got is not None and math.isclose(got, value, rel_tol=1e-6, abs_tol=1e-9):
                    return
                time.sleep(0.02)
        raise SitlError(f"{self.instances[i].name}: parameter {name} not confirmed = {value:g} "
                        f"within {timeout_s:g} s")

    # -- readiness --------------------------------------------------------------------------------
    def _ready(self, i: int) -> bool:
        view, kind = self.views[i], self.instances[i].spec.firmware.kind
        with self._lock:
            if view.heartbeat_s is None or view.local_ned is None:
                return False
            if kind == "ardupilot":
                return view.prearm_ok
            return view.global_position

    def wait_ready(self, timeout_s: float, stop: Callable[[], bool] = lambda: False) -> None:
        """Until every autopilot is ready to arm (ArduPilot: pre-arm checks pass and the EKF
        gives a position; PX4: a position and a global fix), then ArduPilot's clock back to
        1×; SitlError naming what is missing, or the console's last lines if one died."""
        started = time.monotonic()
        deadline = started + timeout_s
        requested: set[int] = set()
        pending = set(range(len(self.instances)))
        last_request = -math.inf
        while pending:
            if stop():
                raise KeyboardInterrupt
            for i in list(pending):
                inst = self.instances[i]
                code = inst.poll()
                if code is not None:
                    tail = "\n    ".join(inst.tail())
                    raise SitlError(f"{inst.name} exited with code {code} while booting; "
                                    f"last lines of {inst.console_log}:\n    {tail}")
                heard = self.views[i].heartbeat_s is not None
                if heard and (i not in requested or time.monotonic() - last_request > 2.0):
                    self.request_streams(i)  # again every 2 s until ready: UDP may lose it
                    requested.add(i)
                if self._ready(i):
                    pending.discard(i)
                    if inst.spec.firmware.kind == "ardupilot" and inst.spec.boot_speedup != 1:
                        self.set_param(i, "SIM_SPEEDUP", 1.0)
                    self.log(f"launch-swarm: {inst.name} ready after "
                             f"{time.monotonic() - started:.1f} s")
            if requested and time.monotonic() - last_request > 2.0:
                last_request = time.monotonic()
            if time.monotonic() > deadline:
                raise SitlError(self._not_ready_message(sorted(pending), timeout_s))
            time.sleep(0.05)

    def _not_ready_message(self, pending: list[int], timeout_s: float) -> str:
        parts = []
        for i in pending:
            view, inst = self.views[i], self.instances[i]
            if view.heartbeat_s is None:
                what = "no HEARTBEAT on its monitor link"
            elif view.local_ned is None:
                what = "no position estimate yet (LOCAL_POSITION_NED)"
            elif inst.spec.firmware.kind == "ardupilot":
                what = "pre-arm checks failing"
            else:
                what = "no global position fix yet"
            said = f" (last said: {view.statustexts[-1]!r})" if view.statustexts else ""
            parts.append(f"{inst.name}: {what}{said}")
        return f"autopilots not ready within {timeout_s:g} s: " + "; ".join(parts)

    def ground_local_ned(self, i: int, window_s: float = 0.5, timeout_s: float = 3.0) -> Array:
        """Mean LOCAL_POSITION_NED of autopilot i over the next ``window_s`` (on the ground:
        where its estimator puts the home it stands on)."""
        start = time.monotonic()
        while time.monotonic() < start + max(window_s, 0.0) + 0.05:
            time.sleep(0.05)
        with self._lock:
            samples = [ned for t, ned in self.views[i].recent_local if t >= start]
            newest = self.views[i].local_ned
        if not samples:
            if newest is None or time.monotonic() - start > timeout_s:
                raise SitlError(f"{self.instances[i].name}: no LOCAL_POSITION_NED on its "
                                f"monitor link")
            samples = [newest]
        return np.mean(np.array(samples), axis=0)

    def close(self) -> None:
        if getattr(self, "_stop", None) is not None:
            self._stop.set()
            self._thread.join(timeout=1.0)
        for link in self._links:
            with contextlib.suppress(Exception):
                link.close()
        self._links = []


# -- a swarm's autopilots ----------------------------------------------------------------------


class SitlFleet:
    """One autopilot instance per drone, started together, watched, stopped together.

    Drone i's autopilot is system i + 1, sends its companion link to ``companion_ports[i]``
    (where agent i listens) and its monitor link to ``monitor_ports[i]`` (this fleet's
    ``SitlMonitor``); its home is ``homes[i]``; its console goes to ``log_dir/sitl<i>.log``
    and its working directory is a temporary one inside ``log_dir``.
    """

    def __init__(self, firmware: Firmware, homes: Sequence[GeoPoint],
                 companion_ports: Sequence[int], monitor_ports: Sequence[int], log_dir: Path, *,
                 setpoint_timeout_s: float, boot_speedup: float = DEFAULT_BOOT_SPEEDUP,
                 extra_params: Sequence[tuple[str, float]] = (),
                 log: Callable[[str], None] = print,
                 on_state: Callable[[int, VehicleView], None] | None = None) -> None:
        """``extra_params``: (name, value) set at boot on every instance after the swarm's own
        (``default_params``), e.g. a failsafe to try."""
        n = len(homes)
        if not len(companion_ports) == len(monitor_ports) == n:
            raise ValueError("one home, companion port and monitor port per drone")
        self.firmware = firmware
        self.log = log
        self._on_state = on_state
        params = (*default_params(firmware.kind, setpoint_timeout_s), *extra_params)
        instances = free_instances(firmware.kind, n)
        self.instances = [
            SitlInstance(SitlSpec(firmware, instances[i], i + 1, homes[i], companion_ports[i],
                                  monitor_ports[i], params, boot_speedup),
                         log_dir / f"sitl{i}.log", log_dir)
            for i in range(n)]
        self.monitor: SitlMonitor | None = None

    def start(self) -> None:
        """Start every instance and the monitor links (SitlError, everything stopped, when
        one cannot start)."""
        try:
            for inst in self.instances:
                inst.start()
            self.monitor = SitlMonitor(self.instances, log=self.log, on_state=self._on_state)
        except BaseException:
            self.stop()
            raise
        pids = ", ".join(str(inst.pid) for inst in self.instances)
        self.log(f"launch-swarm: started {len(self.instances)} {self.firmware.name} instances "
                 f"({self.firmware.path}; pids {pids})")

    def wait_ready(self, timeout_s: float, stop: Callable[[], bool] = lambda: False) -> None:
        assert self.monitor is not None
        self.monitor.wait_ready(timeout_s, stop)

    def origin_offsets(self, ground_w: Sequence[Array]) -> list[Array]:
        """Each vehicle's local NED origin in W such that where its estimator puts it now (on
        the ground) is ``ground_w[i]``: o_i = g_i − ENU(ned_i), so that
        ``frames.world_from_local_ned(ned_i, o_i) = g_i``."""
        from swarm.models import frames

        assert self.monitor is not None
        return [np.asarray(ground_w[i], dtype=float)
                - frames.ned_to_enu(self.monitor.ground_local_ned(i))
                for i in range(len(self.instances))]

    def dead(self) -> SitlInstance | None:
        """An instance whose process has ended, if any."""
        return next((inst for inst in self.instances if inst.poll() is not None), None)

    def stop(self) -> None:
        """Stop the monitor and every instance (each by its process group); safe to repeat."""
        if self.monitor is not None:
            self.monitor.close()
            self.monitor = None
        for inst in self.instances:
            inst.stop()
