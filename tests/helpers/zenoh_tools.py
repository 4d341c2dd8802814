"""Real Zenoh sessions for the tests of swarm.net: a peer in a child process
(``zenoh_peer_helper.py``, driven by ``Child``), the sockets a process holds, and bounded
waits for asynchronous route establishment."""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import zenoh

from swarm.messages.wire import WireCodec
from swarm.net.session import open_session

ROOT = Path(__file__).resolve().parents[2]
HELPER = ROOT / "tests" / "helpers" / "zenoh_peer_helper.py"
CODEC = WireCodec(6, 2, 6)
DEADLINE_S = 10.0


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def _hex_ip(text: str) -> str:
    raw = bytes.fromhex(text)
    if len(raw) == 4:
        return str(ipaddress.IPv4Address(raw[::-1]))
    words = [raw[i:i + 4][::-1] for i in range(0, 16, 4)]  # four little-endian 32-bit words
    return str(ipaddress.IPv6Address(b"".join(words)))


def inet_sockets(pid: int) -> list[tuple[str, str, int]]:
    """(protocol, local address, local port) of every TCP/UDP socket the process holds."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    found = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/{pid}/net/{proto}") as table:
            next(table)
            for row in table:
                fields = row.split()
                if fields[9] in inodes:
                    address, port = fields[1].split(":")
                    found.append((proto, _hex_ip(address), int(port, 16)))
    return found


def assert_loopback_only(pid: int) -> None:
    sockets = inet_sockets(pid)
    assert sockets, "expected the process to hold zenoh sockets"
    for proto, address, _ in sockets:
        ip = ipaddress.ip_address(address)
        mapped = getattr(ip, "ipv4_mapped", None)
        assert ip.is_loopback or (mapped is not None and mapped.is_loopback), (proto, address)
        assert proto.startswith("tcp"), f"unexpected {proto} socket on {address}"


class Child:
    """A zenoh_peer_helper process: commands in on stdin, JSON events out on stdout."""

    def __init__(self, *args: str) -> None:
        # A file, not a pipe: a chatty child never blocks. Closed in stop().
        self.stderr = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, str(HELPER), *args], cwd=ROOT, stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self.stderr, text=True, start_new_session=True)
        self.events: queue.Queue[dict] = queue.Queue()
        self.seen: list[dict] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.ready = self.expect(lambda e: e["event"] == "ready", "ready")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with contextlib.suppress(json.JSONDecodeError):
                self.events.put(json.loads(line))
        self.events.put({"event": "eof"})

    def send(self, **cmd) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()

    def next_event(self, predicate: Callable[[dict], bool], timeout_s: float) -> dict | None:
        """The first event (seen before or arriving within ``timeout_s``) matching it."""
        for event in self.seen:
            if predicate(event):
                return event
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                event = self.events.get(timeout=remaining)
            except queue.Empty:
                break
            if event["event"] == "eof":
                self.events.put(event)
                raise AssertionError(f"child exited with {self.proc.wait()}: "
                                     f"{self.stderr_tail()}")
            self.seen.append(event)
            if predicate(event):
                return event
        return None

    def stderr_tail(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-2000:]

    def expect(self, predicate: Callable[[dict], bool], what: str,
               timeout_s: float = DEADLINE_S) -> dict:
        event = self.next_event(predicate, timeout_s)
        assert event is not None, f"no {what} from child within {timeout_s} s"
        return event

    def stats(self) -> dict:
        self.seen = [e for e in self.seen if e["event"] != "stats"]
        self.send(cmd="stats")
        return self.expect(lambda e: e["event"] == "stats", "stats")

    def stop(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.send(cmd="quit")
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=3.0)
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=5.0)
        for stream in (self.proc.stdin, self.proc.stdout, self.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.close()


def repeat_until(action: Callable[[], None], done: Callable[[float], object],
                 deadline_s: float = DEADLINE_S, every_s: float = 0.05):
    """Do ``action`` until ``done(wait_s)`` (which waits up to wait_s) returns something truthy.

    Zenoh propagates subscriber declarations asynchronously, so the first put after a session
    opens can legitimately find no route yet; repeating with a deadline is the bounded wait.
    """
    deadline = time.monotonic() + deadline_s
    while time.monotonic() < deadline:
        action()
        result = done(every_s)
        if result:
            return result
    raise AssertionError(f"not done within {deadline_s} s")


@contextlib.contextmanager
def session(config: zenoh.Config) -> Iterator[zenoh.Session]:
    s = open_session(config)
    try:
        yield s
    finally:
        s.close()


def iter_queue(events: queue.Queue, wait_s: float) -> list:
    """What arrives on ``events`` within ``wait_s`` (at least one get, then no waiting)."""
    try:
        out = [events.get(timeout=wait_s)]
    except queue.Empty:
        return []
    while not events.empty():
        out.append(events.get_nowait())
    return out
