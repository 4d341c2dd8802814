"""swarm.mavlink.sitl without running firmware: finding a build, placing homes, instance ports.

(Running instances are tested in test_sitl_handshake.py and test_sitl_missions.py.)"""

from __future__ import annotations

import math
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from swarm.mavlink.sitl import (
    ARDUPILOT_RC_IN_BASE_PORT,
    ENV_ARDUCOPTER,
    ENV_PX4,
    Firmware,
    SitlError,
    SitlInstance,
    SitlSpec,
    default_params,
    firmware_from_env,
    free_instances,
    free_udp_port,
)
from swarm.models.frames import GeoPoint

pytestmark = pytest.mark.wallclock

ELF = b"\x7fELF" + bytes(60)


def _binary(path: Path, content: bytes = ELF, mode: int = 0o755) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(content)
    path.chmod(mode)
    return path


def _px4_build(root: Path) -> Path:
    _binary(root / "bin" / "px4")
    (root / "etc" / "init.d-posix").mkdir(parents=True)
    return root


def test_a_binary_is_ardupilot_and_a_build_directory_is_px4(tmp_path: Path) -> None:
    arducopter = _binary(tmp_path / "ap" / "arducopter")
    assert Firmware.at(arducopter) == Firmware("ardupilot", arducopter.resolve())
    px4 = _px4_build(tmp_path / "px4")
    assert Firmware.at(px4) == Firmware("px4", px4.resolve())
    assert Firmware.at(px4 / "bin") == Firmware("px4", px4.resolve())
    assert Firmware.at(px4 / "bin" / "px4") == Firmware("px4", px4.resolve())


@pytest.mark.parametrize("make, message", [
    (lambda d: d / "nothing", "no such file or directory"),
    (lambda d: (d / "empty").mkdir() or d / "empty", "not a PX4 SITL build directory"),
    (lambda d: _binary(d / "script", b"#!/bin/sh\n"), "not an executable binary"),
    (lambda d: _binary(d / "arducopter", mode=0o644), "not executable"),
])
def test_unusable_builds_are_one_line_errors(tmp_path: Path, make, message: str) -> None:
    if message == "not executable" and os.geteuid() == 0:
        # root may execute anything with an x bit only; a file without any is still refused
        pass
    path = make(tmp_path)
    with pytest.raises(SitlError, match=message) as err:
        Firmware.at(path)
    assert "\n" not in str(err.value)


def test_environment_variables_name_the_builds(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_ARDUCOPTER, raising=False)
    assert firmware_from_env("ardupilot") is None
    px4 = _px4_build(tmp_path / "px4")
    monkeypatch.setenv(ENV_PX4, str(px4))
    assert firmware_from_env("px4") == Firmware("px4", px4.resolve())
    monkeypatch.setenv(ENV_ARDUCOPTER, str(px4))  # a PX4 build where ArduPilot was meant
    with pytest.raises(SitlError, match="is a PX4 SITL"):
        firmware_from_env("ardupilot")
    # The directory that holds the binary, where the binary was meant: said so, not "not a
    # PX4 SITL build directory".
    arducopter = _binary(tmp_path / "ap" / "arducopter")
    monkeypatch.setenv(ENV_ARDUCOPTER, str(arducopter.parent))
    with pytest.raises(SitlError, match=re.escape(
            f"is a directory: it names the arducopter SITL binary itself ({arducopter} is "
            f"there)")):
        firmware_from_env("ardupilot")
    monkeypatch.setenv(ENV_ARDUCOPTER, str(tmp_path / "px4" / "etc"))
    with pytest.raises(SitlError, match=r"is a directory: .*\(build it with \./waf copter"):
        firmware_from_env("ardupilot")
    monkeypatch.setenv(ENV_ARDUCOPTER, str(arducopter))
    assert firmware_from_env("ardupilot") == Firmware("ardupilot", arducopter.resolve())


def test_copter_defaults_beside_the_binary_or_in_its_waf_source_tree(tmp_path: Path) -> None:
    beside = _binary(tmp_path / "a" / "arducopter")
    (tmp_path / "a" / "copter.parm").write_text("FRAME_CLASS 1\n")
    assert Firmware.at(beside).copter_defaults == tmp_path / "a" / "copter.parm"
    tree = tmp_path / "ardupilot"
    built = _binary(tree / "build" / "sitl" / "bin" / "arducopter")
    parm = tree / "Tools" / "autotest" / "default_params" / "copter.parm"
    parm.parent.mkdir(parents=True)
    parm.write_text("FRAME_CLASS 1\n")
    assert Firmware.at(built).copter_defaults == parm
    lonely = _binary(tmp_path / "b" / "arducopter")
    assert Firmware.at(lonely).copter_defaults is None
    spec = SitlSpec(Firmware.at(lonely), 0, 1, GeoPoint(0, 0, 0), 20000, 20001)
    instance = SitlInstance(spec, tmp_path / "console.log", workdir_parent=tmp_path)
    with pytest.raises(SitlError, match=r"no copter\.parm"):
        instance.start()
    assert instance.poll() is None and list(tmp_path.glob("vigil-sitl-*")) == []


def test_parameters_each_autopilot_needs() -> None:
    assert dict(default_params("ardupilot", 3.0)) == {"GUID_TIMEOUT": 3.0}
    px4 = dict(default_params("px4", 0.5))
    assert px4 == {"COM_OF_LOSS_T": 0.5, "COM_OBL_RC_ACT": 5, "SDLOG_MODE": -1}


def test_ardupilot_instances_skip_a_taken_rc_port() -> None:
    first = free_instances("ardupilot", 1)[0]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("0.0.0.0", ARDUPILOT_RC_IN_BASE_PORT + 10 * first))
        chosen = free_instances("ardupilot", 2)
    assert first not in chosen and len(set(chosen)) == 2
    assert free_instances("px4", 3) == [0, 1, 2]


def _ephemeral_ports() -> range:
    low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
    return range(int(low), int(high) + 1)


def test_a_picked_udp_port_is_never_one_the_kernel_or_another_process_hands_out() -> None:
    """The kernel hands ephemeral ports to every socket that sends unbound (an autopilot's
    outgoing links), and a port picked for a SITL boot is bound only a minute later: it
    comes from outside that range, and no other process (xdist's other worker) gets it."""
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys\n"
         "from swarm.mavlink.sitl import free_udp_port\n"
         "print(*[free_udp_port() for _ in range(30)], flush=True)\n"
         "sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        theirs = {int(word) for word in child.stdout.readline().split()}
        ours = {free_udp_port() for _ in range(30)}
    finally:
        child.communicate("")
    assert len(theirs) == 30 and len(ours) == 30
    assert not theirs & ours
    ephemeral = _ephemeral_ports()
    assert not any(port in ephemeral for port in ours | theirs)


def test_a_bound_udp_port_is_passed_over_and_running_out_is_one_line(
        monkeypatch: pytest.MonkeyPatch) -> None:
    def bindable(port: int) -> bool:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind(("0.0.0.0", port))
            except OSError:
                return False
        return True

    # a 3-port range above the ephemeral one, where nothing else picks
    base = next(port for port in range(_ephemeral_ports().stop, 65500, 3)
                if all(bindable(port + i) for i in range(3)))
    monkeypatch.setattr("swarm.mavlink.sitl.PICKED_UDP_PORTS", range(base, base + 3))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", base + 1))
        assert {free_udp_port(), free_udp_port()} == {base, base + 2}
        with pytest.raises(SitlError, match=f"no free UDP port in {base}..{base + 2}$"):
            free_udp_port()


def test_spec_bounds() -> None:
    firmware = Firmware("px4", Path("/nonexistent"))
    with pytest.raises(SitlError, match="system id"):
        SitlSpec(firmware, 0, 0, GeoPoint(0, 0, 0), 1, 2)
    with pytest.raises(SitlError, match="boot speedup"):
        SitlSpec(firmware, 0, 1, GeoPoint(0, 0, 0), 1, 2, boot_speedup=math.nan)


def test_a_px4_instance_gets_its_own_links_parameters_and_command_links(tmp_path: Path
                                                                         ) -> None:
    """What the PX4 instance is started with, without starting it: the rc overrides that rcS
    finds first on PATH, and a px4-<module> link for every module of the build."""
    root = _px4_build(tmp_path / "px4")
    (root / "bin" / "px4-commander").write_text("px4")  # a build copied without its links
    shutil.copy(__file__, root / "bin" / "px4-alias.sh")
    spec = SitlSpec(Firmware.at(root), 3, 4, GeoPoint(-35.0, 149.0, 584.0), 25000, 25001,
                    (("COM_OF_LOSS_T", 0.5),))
    instance = SitlInstance(spec, tmp_path / "console.log", workdir_parent=tmp_path)
    instance.workdir = tmp_path / "work"
    instance.workdir.mkdir()
    argv, env = instance._px4_command()
    bin_dir = instance.workdir / "bin"
    assert argv[:6] == [str(bin_dir / "px4"), "-d", "-i", "3", "-w", str(instance.workdir)]
    assert env["PATH"].split(os.pathsep)[0] == str(bin_dir)
    assert (bin_dir / "px4-commander").resolve() == (root / "bin" / "px4").resolve()
    assert stat.S_ISLNK((bin_dir / "px4-commander").lstat().st_mode)
    params = (bin_dir / "px4-rc.params").read_text()
    for line in ("param set MAV_SYS_ID 4", "param set SIH_LOC_LAT0 -350000000",
                 "param set SIH_LOC_LON0 1490000000", "param set SIH_LOC_H0 584.0",
                 "param set COM_OF_LOSS_T 0.5"):
        assert line in params
    links = (bin_dir / "px4-rc.mavlink").read_text()
    assert "-m onboard -o 25000" in links and "-o 25001" in links
    assert "PX4_SIM_SPEED_FACTOR" not in env and env["PX4_RUN_DIR"] == str(instance.workdir)
    np.testing.assert_equal(len(links.splitlines()), 3)
