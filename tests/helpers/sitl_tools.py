"""What the tests with real autopilot firmware share: finding a SITL build, running one
instance for a test, and skipping (saying why) when there is none.

A build is found from the environment variable of ``swarm.mavlink.sitl`` (``VIGIL_ARDUCOPTER``: the
arducopter binary; ``VIGIL_PX4``: a PX4 SITL build directory), else at the place the project
keeps them for its tests: ``../shared/autopilots/ardupilot/arducopter`` and
``../shared/autopilots/px4`` beside the repository. The builds are never copied into it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from swarm.mavlink.sitl import (
    ENV_VARIABLE,
    Firmware,
    Kind,
    SitlError,
    SitlInstance,
    SitlMonitor,
    SitlSpec,
    default_params,
    firmware_from_env,
    free_instances,
    free_udp_port,
)
from swarm.models.frames import GeoPoint

ROOT = Path(__file__).resolve().parents[2]
SHARED_AUTOPILOTS = ROOT.parent / "shared" / "autopilots"
DEFAULT_BUILDS: dict[Kind, Path] = {"ardupilot": SHARED_AUTOPILOTS / "ardupilot" / "arducopter",
                                    "px4": SHARED_AUTOPILOTS / "px4"}
HOME = GeoPoint(-35.363261, 149.165230, 584.0)
BOOT_TIMEOUT_S = 90.0  # PX4 can arm ~37 s after boot; ArduPilot ~4 s at 10x
DEFAULT_SETPOINT_TIMEOUT_S: dict[Kind, float] = {"ardupilot": 3.0, "px4": 1.0}  # firmware's


def find_firmware(kind: Kind) -> Firmware | None:
    """The build named by the environment variable, else the project's default one, else
    None; a variable that names something unusable fails (a user meant it)."""
    from_env = firmware_from_env(kind)
    if from_env is not None:
        return from_env
    path = DEFAULT_BUILDS[kind]
    try:
        return Firmware.at(path) if path.exists() else None
    except SitlError:
        return None


def missing_reason(kind: Kind) -> str:
    """Why ``find_firmware(kind)`` found nothing (for pytest.skip)."""
    return (f"no {kind} SITL build: set {ENV_VARIABLE[kind]} or put one at "
            f"{DEFAULT_BUILDS[kind]} (see ../shared/autopilots/README.md)")


def firmware_or_skip(kind: Kind) -> Firmware:
    firmware = find_firmware(kind)
    if firmware is None:
        pytest.skip(missing_reason(kind))
    return firmware


@dataclass(frozen=True)
class RunningSitl:
    """One autopilot for a test: its companion link goes to ``companion_port`` (listen there
    with ``udpin``: ``companion_url``), ``monitor`` watches it on its second link."""

    instance: SitlInstance
    monitor: SitlMonitor
    companion_port: int

    @property
    def companion_url(self) -> str:
        return f"udpin:127.0.0.1:{self.companion_port}"

    @property
    def kind(self) -> Kind:
        return self.instance.spec.firmware.kind


class BootingSitl:
    """One SITL instance (its own working directory, free ports, the first free instance
    number) booting while the caller goes on: ``start()`` returns at once, ``wait()`` blocks
    until it can arm (``SitlMonitor.wait_ready``; ArduPilot is then set back to 1x) or raises
    what the boot raised, ``stop()`` stops the instance and its monitor (any time, more than
    once). PX4 needs ~37 s before it can arm, which another test can use meanwhile
    (``tests/conformance/conftest.py``). ``params`` are set at boot after the firmware's
    defaults and ``swarm.mavlink.sitl.default_params`` (the swarm's setpoint timeout, PX4's
    Hold on offboard loss, no PX4 flight log)."""

    def __init__(self, firmware: Firmware, *, system_id: int = 1,
                 companion_port: int | None = None, setpoint_timeout_s: float | None = None,
                 params: Sequence[tuple[str, float]] = (), home: GeoPoint = HOME,
                 ready_timeout_s: float = BOOT_TIMEOUT_S,
                 log: Callable[[str], None] | None = None) -> None:
        kind = firmware.kind
        timeout = DEFAULT_SETPOINT_TIMEOUT_S[kind] if setpoint_timeout_s is None \
            else setpoint_timeout_s
        port = free_udp_port() if companion_port is None else companion_port
        self.spec = SitlSpec(firmware, free_instances(kind, 1)[0], system_id, home, port,
                             free_udp_port(), default_params(kind, timeout) + tuple(params))
        self.kind = kind
        self.ready_timeout_s = ready_timeout_s
        self.log = log if log is not None else (lambda _line: None)
        self._logdir = tempfile.TemporaryDirectory(prefix=f"vigil-{kind}-test-")
        self.console_log = Path(self._logdir.name) / "console.log"
        self.instance = SitlInstance(self.spec, self.console_log)
        self.monitor: SitlMonitor | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stopped = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    @property
    def running(self) -> RunningSitl:
        """The instance as it is now (ready or not)."""
        assert self.monitor is not None, "start() first"
        return RunningSitl(self.instance, self.monitor, self.spec.companion_port)

    def start(self) -> None:
        with self._lock:
            self.instance.start()
            self.monitor = SitlMonitor([self.instance], log=self.log)
        self._thread = threading.Thread(target=self._boot, name=f"boot-{self.kind}",
                                        daemon=True)
        self._thread.start()

    def _boot(self) -> None:
        monitor = self.monitor
        assert monitor is not None
        try:
            monitor.wait_ready(self.ready_timeout_s, stop=self._stopped.is_set)
        except BaseException as err:  # handed to wait()
            self._error = err
        finally:
            self._ready.set()

    def wait(self) -> RunningSitl:
        """Block until ready; what the boot raised, if it did."""
        if self._thread is None:
            raise SitlError("BootingSitl.wait() before start()")
        self._ready.wait()
        if self._error is not None:
            if isinstance(self._error, KeyboardInterrupt):
                raise SitlError(f"{self.instance.name}: stopped while booting")
            raise self._error
        return self.running

    def stop(self) -> None:
        self._stopped.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)
        with self._lock:
            if self.monitor is not None:
                self.monitor.close()
            self.instance.stop()
        self._logdir.cleanup()


@contextlib.contextmanager
def running_sitl(firmware: Firmware, *, wait_ready: bool = True,
                 **options: Any) -> Iterator[RunningSitl]:
    """One instance for a ``with`` block (``BootingSitl``'s options), always stopped on the
    way out; ``wait_ready``: enter once it can arm, else at once (ArduPilot boots at 10x and
    is set to 1x when ready, in the background: ``wait_ready`` of the monitor from the test).
    """
    booting = BootingSitl(firmware, **options)
    try:
        booting.start()
        yield booting.wait() if wait_ready else booting.running
    finally:
        booting.stop()


def sitl_processes(containing: str = "") -> list[str]:
    """Command lines of the arducopter / px4 processes running now whose command line or
    environment holds ``containing`` (e.g. a port or working directory of a test's run):
    none may outlive the run."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        with contextlib.suppress(OSError):
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            name = Path(argv[0].decode(errors="replace")).name
            if not (name in ("arducopter", "px4") or name.startswith("px4-")):
                continue
            line = " ".join(a.decode(errors="replace") for a in argv)
            environ = Path(f"/proc/{pid}/environ").read_bytes().decode(errors="replace")
            if containing in line or containing in environ:
                found.append(f"{pid}: {line}")
    return found
