"""One real Zenoh session in its own OS process, for the tests of swarm.net
(``tests.helpers.zenoh_tools.Child`` starts and drives it).

Driven by JSON lines on stdin, reports JSON lines on stdout:

- events: ``ready`` (session open, subscribers declared), ``value`` (a decoded beacon or
  consensus message of its run, with the rejection counts at that moment), ``stats``, ``bye``.
- commands: ``beacon`` / ``consensus`` (publish a valid message of its run), ``raw`` (publish
  arbitrary hex bytes on a key), ``stats``, ``quit``. End of stdin also quits, so a child
  never outlives a parent that died.

It subscribes to its run's beacons and consensus messages through
``swarm.net.subscriptions.subscribe`` and, separately, to ``vigil/**`` to record every run id
whose traffic reaches it at all.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading

import numpy as np

from swarm.core.drone_step import ConsensusMessage
from swarm.messages.wire import BeaconWire, WireCodec
from swarm.net.keys import Keys
from swarm.net.session import open_session, zenoh_config
from swarm.net.subscriptions import RejectionCounter, subscribe

N_DRONES, N_TARGETS, N_STATE = 6, 2, 6

_out_lock = threading.Lock()


def emit(**event) -> None:
    line = json.dumps(event)
    with _out_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def consensus(sender: int, step: int, round_: int) -> ConsensusMessage:
    """A deterministic message whose values encode (sender, step, round)."""
    base = float(1000 * sender + step) + round_ / 10
    extras = {}
    if round_ == 0:
        extras = dict(projector_mean=np.full((N_TARGETS, 3, 3), base),
                      projector_integral=np.full((N_TARGETS, 3, 3), -base),
                      weight_mean=np.full(N_TARGETS, base), weight_integral=np.zeros(N_TARGETS),
                      gramian=np.full((N_TARGETS, 3, 3), base))
    return ConsensusMessage.of_arrays(
        sender, step, round_, np.full((N_TARGETS, N_STATE, N_STATE), base),
        np.full((N_TARGETS, N_STATE), base), **extras)


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--mode", default="peer")
    parser.add_argument("--listen", action="append", default=[])
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--run-id", required=True)
    args = parser.parse_args()

    keys = Keys(args.run_id)
    codec = WireCodec(N_DRONES, N_TARGETS, N_STATE)
    rejections = RejectionCounter()
    runs_seen: dict[str, int] = {}
    runs_lock = threading.Lock()
    received = {"n": 0}

    session = open_session(zenoh_config(mode=args.mode, listen=args.listen,
                                        connect=args.connect, connect_timeout_s=10.0))

    def count() -> None:
        with runs_lock:
            received["n"] += 1

    def on_beacon(key: str, beacon) -> None:
        count()
        emit(event="value", kind="beacon", key=key, sender=beacon.sender, step=beacon.step,
             position=list(beacon.position_m), rejections=rejections.snapshot())

    def on_consensus(key: str, message: ConsensusMessage) -> None:
        count()
        emit(event="value", kind="consensus", key=key, sender=message.sender,
             step=message.step, round=message.round,
             first=float(message.information.flat[0]), rejections=rejections.snapshot())

    def on_any(sample) -> None:
        run = str(sample.key_expr).split("/")[1]
        with runs_lock:
            runs_seen[run] = runs_seen.get(run, 0) + 1

    subscribe(session, keys.all_beacons, codec.decode_beacon, on_beacon, rejections, "beacon")
    subscribe(session, keys.all_consensus, codec.decode_consensus, on_consensus, rejections,
              "consensus")
    session.declare_subscriber("vigil/**", on_any)
    emit(event="ready", pid=os.getpid(), run_id=args.run_id)

    try:
        for line in sys.stdin:
            cmd = json.loads(line)
            op = cmd["cmd"]
            if op == "beacon":
                message = BeaconWire.build(cmd["sender"], cmd["step"], 0.02 * cmd["step"],
                                      cmd.get("position", [1.0, 2.0, 3.0]))
                session.put(keys.beacon(cmd["sender"]), codec.encode(message))
            elif op == "consensus":
                message = consensus(cmd["sender"], cmd["step"], cmd["round"])
                session.put(keys.consensus(cmd["sender"]), codec.encode(message))
            elif op == "raw":
                session.put(cmd["key"], bytes.fromhex(cmd["hex"]))
            elif op == "stats":
                with runs_lock:
                    seen, n = dict(runs_seen), received["n"]
                emit(event="stats", rejections=rejections.snapshot(), runs_seen=seen, received=n)
            elif op == "quit":
                break
    finally:
        session.close()
        emit(event="bye")
    return 0


if __name__ == "__main__":
    sys.exit(main())
