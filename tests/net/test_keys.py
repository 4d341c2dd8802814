"""The key space of a run (swarm.net.keys): names, validation, and runs that never see each
other on a shared router.

No sleeps hide races: cross-process checks wait for the child's report with a deadline, and a
publish is repeated until it is seen (route establishment is asynchronous in Zenoh).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
import zenoh

from swarm.net.keys import Keys
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.zenoh_tools import Child, endpoint, repeat_until


def test_keys_are_namespaced_and_validated() -> None:
    keys = Keys("run-1_a")
    assert keys.consensus(3) == "vigil/run-1_a/agent/3/consensus"
    assert keys.beacon(0) == "vigil/run-1_a/agent/0/beacon"
    assert keys.telemetry(5) == "vigil/run-1_a/agent/5/telemetry"
    assert keys.camera(2) == "vigil/run-1_a/world/camera/2"
    assert keys.truth == "vigil/run-1_a/world/truth"
    assert keys.clock == "vigil/run-1_a/world/clock"
    assert keys.all_telemetry == "vigil/run-1_a/agent/*/telemetry"
    assert keys.all_beacons == "vigil/run-1_a/agent/*/beacon"
    assert keys.source_id(keys.beacon(4)) == 4 and keys.source_id(keys.camera(1)) == 1
    assert keys.source_id(keys.truth) is None
    assert keys.source_id(Keys("other").beacon(4)) is None
    for bad in ["", "a/b", "a*", "x" * 65, "é", "a b", None]:
        with pytest.raises(ValueError, match="run_id"):
            Keys(bad)  # type: ignore[arg-type]
    for bad_id in [-1, 1.0, True, "1"]:
        with pytest.raises(ValueError, match="drone id"):
            keys.beacon(bad_id)  # type: ignore[arg-type]
    # Zenoh's own matching: a run's wildcards never reach another run, even a prefix of it.
    mine, prefix_of_mine = zenoh.KeyExpr(Keys("run").everything), Keys("run2")
    assert not mine.intersects(zenoh.KeyExpr(prefix_of_mine.beacon(1)))
    assert zenoh.KeyExpr(keys.all_beacons).intersects(zenoh.KeyExpr(keys.beacon(3)))
    assert not zenoh.KeyExpr(keys.all_beacons).intersects(zenoh.KeyExpr(keys.telemetry(3)))


def test_run_ids_isolate_swarms_sharing_one_router(spawn) -> None:
    """Even on one shared router, a run's subscribers only ever receive their own run."""
    port = free_tcp_port()
    alpha = spawn("--mode", "router", "--listen", endpoint(port), "--run-id", "alpha")
    beta = spawn("--mode", "client", "--connect", endpoint(port), "--run-id", "beta")
    alpha2 = spawn("--mode", "client", "--connect", endpoint(port), "--run-id", "alpha")

    def seen_by(child: Child, drone: int, step: int) -> Callable[[float], object]:
        return lambda wait_s: child.next_event(
            lambda e: e["event"] == "value" and e["sender"] == drone and e["step"] == step,
            wait_s)

    # beta publishes the same drone ids and steps as alpha, on its own keys.
    repeat_until(lambda: beta.send(cmd="beacon", sender=1, step=0), seen_by(beta, 1, 0))
    repeat_until(lambda: alpha2.send(cmd="beacon", sender=1, step=0), seen_by(alpha, 1, 0))
    repeat_until(lambda: (beta.send(cmd="beacon", sender=2, step=1),
                          alpha.send(cmd="beacon", sender=2, step=1)), seen_by(alpha2, 2, 1))
    # alpha's raw vigil/** subscriber proves beta's traffic really reaches the shared router...
    repeat_until(lambda: beta.send(cmd="beacon", sender=3, step=2),
                 lambda wait_s: "beta" in alpha.stats()["runs_seen"])
    # ...while its typed subscribers (vigil/alpha/agent/*/beacon) never delivered any of it.
    for child, run in ((alpha, "alpha"), (alpha2, "alpha"), (beta, "beta")):
        values = [e for e in child.seen if e["event"] == "value"]
        assert values and all(e["key"].startswith(f"vigil/{run}/") for e in values), values
        assert child.stats()["rejections"] == {}
