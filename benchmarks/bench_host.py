"""The host at the hour of a run: how fast it interprets Python and what a wake-up costs.

    python benchmarks/bench_host.py [--profile quick] [--out FILE]
    (or as the ``host`` section of ``python benchmarks/run_all.py``, which also measures it
    again after its last section: ``host_after`` in the summary)

The swarm's figures follow the machine they run on, and on a shared VM they follow its hour:
the same code measured a 64 µs step one morning and 101 µs another. These figures measure
the machine alone, with nothing of the project's code in them, so that two runs can be told
apart by their host before their code is compared:

- **Python**: a fixed loop of dictionary, float and integer operations (the interpreter's
  own speed at this hour), µs per 1000 iterations, median of ``HOST_LOOP_REPEATS``.
- **Wake-up between processes**: a datagram bounced between this process and a child over
  loopback UDP (each side blocked in ``recv`` until the other sends: what every MAVLink
  setpoint and Zenoh delivery of the swarm costs at least once), the round trip's wall time
  (median and p90) and the CPU of one hop (send, wake the receiver, receive: both
  processes' CPU over the bounces, per hop). Twice: both processes pinned to one CPU (the
  receiver wakes where the sender runs) and to two (the sender wakes another CPU, idle in
  between: a virtual CPU that halted must be woken by the hypervisor). Left to
  the scheduler, a run lands in either case and stays there: on this project's 2-core VM
  300 bounces measured 6 µs a round trip and 3000 bounces 81 µs in one call, 7 µs in the
  next.
- **Timer wake-up**: a thread sleeping to a 50 Hz schedule (as a realtime agent's loop
  does), its CPU per wake-up.

Nothing is asserted: these are the host's figures, recorded next to the project's.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np
from common import PROFILES, Profile, SectionClock, fmt, new_table, report_section, section_parser
from rich.table import Table

HOST_LOOP_ITERATIONS = 20_000
HOST_LOOP_REPEATS = 7
HOST_WARMUP_ROUND_TRIPS = 200
HOST_TICK_S = 0.02  # the swarm's step: 50 Hz
_ECHO_TIMEOUT_S = 10.0

# The child: runs on the CPU given as its argument, binds a loopback UDP port, says which on
# stdout, then echoes every datagram until b"quit"; b"cpu" asks for its own CPU seconds so far.
_ECHO_CHILD = """
import os, socket, sys, time
os.sched_setaffinity(0, {int(sys.argv[1])})
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
print(s.getsockname()[1], flush=True)
while True:
    data, sender = s.recvfrom(64)
    if data == b"quit":
        break
    s.sendto(repr(time.process_time()).encode() if data == b"cpu" else data, sender)
"""


def python_loop_us(iterations: int = HOST_LOOP_ITERATIONS,
                   repeats: int = HOST_LOOP_REPEATS) -> float:
    """Median wall time of the reference loop, µs per 1000 iterations."""

    def loop() -> float:
        total, table = 0.0, {}
        for i in range(iterations):
            table[i & 63] = i * 0.5
            total += table[i & 63] ** 0.5
        return total

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        loop()
        times.append((time.perf_counter() - start) * 1e6 * 1000 / iterations)
    return float(np.median(times))


def udp_round_trips(count: int, own_cpu: int, child_cpu: int) -> dict[str, float]:
    """``count`` datagrams bounced off a child process over loopback UDP, this thread on CPU
    ``own_cpu`` and the child on ``child_cpu``: the round trip's wall time (median, p90, µs)
    and the CPU of one hop (µs, both processes)."""
    allowed = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {own_cpu})  # this thread only
    child = subprocess.Popen([sys.executable, "-c", _ECHO_CHILD, str(child_cpu)],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout is not None
        port = int(child.stdout.readline())
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(_ECHO_TIMEOUT_S)
            sock.connect(("127.0.0.1", port))

            def bounce(payload: bytes) -> bytes:
                sock.send(payload)
                return sock.recv(64)

            for _ in range(HOST_WARMUP_ROUND_TRIPS):
                bounce(b"x")
            child_cpu_before = float(bounce(b"cpu"))
            own_cpu_before = time.thread_time()
            round_trips_ns = []
            for _ in range(count):
                start = time.perf_counter_ns()
                bounce(b"x")
                round_trips_ns.append(time.perf_counter_ns() - start)
            own_cpu_s = time.thread_time() - own_cpu_before
            child_cpu_s = float(bounce(b"cpu")) - child_cpu_before
            sock.send(b"quit")
        child.wait(timeout=_ECHO_TIMEOUT_S)
    finally:
        os.sched_setaffinity(0, allowed)
        if child.poll() is None:
            child.kill()
            child.wait()
    median_ns, p90_ns = np.percentile(round_trips_ns, [50, 90])
    return {"round_trip_median_us": float(median_ns) / 1e3,
            "round_trip_p90_us": float(p90_ns) / 1e3,
            "cpu_per_hop_us": (own_cpu_s + child_cpu_s) / (2 * count) * 1e6}


def timer_wakeup_cpu_us(ticks: int, period_s: float = HOST_TICK_S) -> float:
    """CPU per wake-up [µs] of a thread sleeping to a schedule of ``period_s``."""
    measured: list[float] = []

    def sleeper() -> None:
        cpu_before = time.thread_time()
        next_tick = time.monotonic()
        for _ in range(ticks):
            next_tick += period_s
            time.sleep(max(0.0, next_tick - time.monotonic()))
        measured.append((time.thread_time() - cpu_before) / ticks * 1e6)

    thread = threading.Thread(target=sleeper, name="host-timer")
    thread.start()
    thread.join()
    return measured[0]


def measure(profile: Profile) -> dict[str, Any]:
    """The host's figures now (see the module docstring); the bounces across two CPUs only
    where this process may run on two."""
    cpus = sorted(os.sched_getaffinity(0))
    figures: dict[str, Any] = {"measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                               "python_loop_us_per_1000": python_loop_us(),
                               "one_cpu": udp_round_trips(profile.host_round_trips, cpus[0],
                                                          cpus[0]),
                               "two_cpus": None}
    if len(cpus) > 1:
        figures["two_cpus"] = udp_round_trips(profile.host_round_trips, cpus[0], cpus[1])
    figures["timer_wakeup_cpu_us"] = timer_wakeup_cpu_us(profile.host_timer_ticks)
    return figures


def run(profile: Profile) -> dict[str, Any]:
    clock = SectionClock()
    figures = measure(profile)
    return {"section": "host", "profile": profile.name,
            "round_trips": profile.host_round_trips, "timer_ticks": profile.host_timer_ticks,
            "figures": figures, **clock.done()}


def figure_rows(figures: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, value) of each host figure, for a table or a line."""
    rows = [("Python reference loop [µs per 1000 iterations]",
             fmt(figures["python_loop_us_per_1000"], 1))]
    for key, where in (("one_cpu", "on one CPU"), ("two_cpus", "across two CPUs")):
        bounces = figures[key] or {}
        rows += [
            (f"UDP round trip between two processes {where}, median [µs]",
             fmt(bounces.get("round_trip_median_us"), 1)),
            ("  p90 [µs]", fmt(bounces.get("round_trip_p90_us"), 1)),
            ("  CPU of one hop: send, wake the receiver, receive [µs]",
             fmt(bounces.get("cpu_per_hop_us"), 1)),
        ]
    rows.append(("CPU of one 50 Hz timer wake-up [µs]", fmt(figures["timer_wakeup_cpu_us"], 1)))
    return rows


def tables(result: dict[str, Any]) -> list[Table]:
    table = new_table(
        "The host at the hour of this run (nothing of the project's code)",
        ["figure", "value"],
        caption=(f"{result['round_trips']} round trips, {result['timer_ticks']} timer ticks; "
                 f"measured at {result['figures']['measured_at']}"))
    for label, value in figure_rows(result["figures"]):
        table.add_row(label, value)
    return [table]


def main(argv: list[str] | None = None) -> int:
    parser = section_parser(__doc__, "host.json")
    args = parser.parse_args(argv)
    return report_section(run(PROFILES[args.profile]), tables, "bench_host.py", argv,
                          args.out)


if __name__ == "__main__":
    raise SystemExit(main())
