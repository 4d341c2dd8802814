"""swarm.mavlink.udpin: the socket swarm-agent binds before its imports, and when it does not."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from swarm.mavlink.sitl import free_udp_port
from swarm.mavlink.udpin import bind_early, bind_udpin, udpin_address


def test_bind_early_binds_the_agents_udpin_port_from_its_command_line() -> None:
    port = free_udp_port()
    url = f"udpin:127.0.0.1:{port}"
    bound = bind_early(["--id", "3", "--config", "x.toml", "--mavlink", url, "--seed", "1"])
    assert bound is not None
    try:
        assert bound.url == url
        assert bound.sock.getsockname() == ("127.0.0.1", port)
        assert bound.sock.getblocking() is False
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other, \
                pytest.raises(OSError):  # nobody else can have the port now
            other.bind(("127.0.0.1", port))
    finally:
        bound.close()
        bound.close()  # twice is harmless (the link may have closed it already)


@pytest.mark.parametrize("argv", [
    [],  # no --id: the full parser says what is missing
    ["--id", "x"],
    ["--id", "-1"],
    ["--id", "254"],
    ["--id", "0", "--mavlink", "tcp:127.0.0.1:5760"],  # not udpin: the link connects itself
    ["--id", "0", "--mavlink", "udpin:127.0.0.1:0"],
    ["--id", "0", "--mavlink", "udpin:127.0.0.1:port"],
    ["--id", "0", "--mavlink"],
])
def test_bind_early_leaves_what_it_cannot_use_to_the_full_parser(argv: list[str]) -> None:
    assert bind_early(argv) is None


def test_a_taken_port_is_left_for_the_link_to_report() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        assert bind_early(["--id", "0", "--mavlink", f"udpin:127.0.0.1:{port}"]) is None
        with pytest.raises(OSError):
            bind_udpin(f"udpin:127.0.0.1:{port}")


def test_default_url_and_address_parsing() -> None:
    assert udpin_address("udpin:127.0.0.1:24541") == ("127.0.0.1", 24541)
    assert udpin_address("udpin:0.0.0.0:14550") == ("0.0.0.0", 14550)
    assert udpin_address("udpout:127.0.0.1:24541") is None
    assert udpin_address("udpin:127.0.0.1:x") is None
    with pytest.raises(ValueError, match="not a udpin URL"):
        bind_udpin("tcp:127.0.0.1:5760")


def test_swarm_agent_binds_before_it_imports_numpy_or_zenoh() -> None:
    """What the agent has loaded when it binds: the standard library and this module."""
    probe = (
        "import sys; import swarm.agent.cli as cli; "
        "heavy = sorted(m for m in ('numpy', 'zenoh', 'pymavlink', 'msgspec', 'swarm.core')"
        " if m in sys.modules); print(heavy)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
