"""``[security]``: Zenoh mutual TLS and the router's access control (``swarm.net.security``).

Real zenoh sessions over TLS on loopback, with certificates made here
(``tests/helpers/tls_certs.py``,
the openssl tool). The router is configured exactly as ``sim_world.World`` configures its own.
Every negative check runs next to a positive control in the same window (the same router,
the same publications), so it cannot pass because nothing was flowing at all.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from swarm.launch.launcher import LaunchOptions, SwarmLauncher
from swarm.net.keys import Keys
from swarm.net.security import (
    OBSERVER_ROLE,
    WORLD_ROLE,
    TlsIdentity,
    agent_role,
    common_name,
    router_access_control,
)
from swarm.net.session import (
    TransportError,
    declare_publisher,
    local_endpoint,
    open_session,
    zenoh_config,
)
from swarm.scenario.config import ConfigError, load_config
from tests.helpers.process_tools import free_tcp_port
from tests.helpers.tls_certs import OPENSSL, make_ca, make_leaf, make_tls_dir, requires_openssl

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"


def with_tls_dir(tls_dir: object) -> str:
    """Case 1's config text with ``[security] tls_dir`` set."""
    text = CASE1.read_text()
    assert 'tls_dir = ""' in text
    return text.replace('tls_dir = ""', f'tls_dir = "{tls_dir}"', 1)
N = 3
NEIGHBOURS = ((1,), (0, 2), (1,))  # a path 0 - 1 - 2
N_CERTIFIED = 6  # the test CA certifies 6 drones: enough for Case 1
RUN = "sec"
KEYS = Keys(RUN)
DEADLINE_S = 10.0
SETTLE_S = 0.3  # after the positive control: what was going to arrive has arrived




class Heard:
    """A thread-safe record of (key, payload) deliveries to one subscriber callback."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.samples: Counter[tuple[str, bytes]] = Counter()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.samples[(str(sample.key_expr), sample.payload.to_bytes())] += 1
            self._cond.notify_all()

    def count(self, key: str | None = None, payload: bytes | None = None) -> int:
        with self._cond:
            return sum(n for (k, p), n in self.samples.items()
                       if (key is None or k == key) and (payload is None or p == payload))

    def keys(self) -> set[str]:
        with self._cond:
            return {k for k, _ in self.samples}


def publish_until(publish: Callable[[], None], done: Callable[[], bool]) -> None:
    """Publish again until ``done`` (routes appear asynchronously), then a last round and a
    settle time, so that a forbidden delivery would have arrived by then."""
    deadline = time.monotonic() + DEADLINE_S
    while not done():
        assert time.monotonic() < deadline, "the positive control never completed"
        publish()
        time.sleep(0.05)
    publish()
    time.sleep(SETTLE_S)  # the scenario: an absence cannot be polled for, only given time


# -- certificates and sessions -------------------------------------------------------------------


@pytest.fixture(scope="module")
def tls_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if OPENSSL is None:
        pytest.skip("the openssl command-line tool makes the test certificates; not on PATH")
    base = tmp_path_factory.mktemp("tls")
    make_tls_dir(base, N_CERTIFIED)
    # A certificate of the swarm's CA for a role the router does not know.
    make_leaf(base, base / "intruder", "intruder", "vigil-intruder")
    # A certificate with a legitimate common name, signed by another CA.
    make_ca(base / "rogue-ca", "rogue-ca")
    make_leaf(base / "rogue-ca", base / "rogue", "observer", common_name(OBSERVER_ROLE))
    return base


def identity(tls_dir: Path, role: str) -> TlsIdentity:
    return TlsIdentity.of(tls_dir, role)


@contextlib.contextmanager
def opened(config: zenoh.Config) -> Iterator[zenoh.Session]:
    session = open_session(config)
    try:
        yield session
    finally:
        session.close()


@pytest.fixture
def router(tls_dir: Path) -> Iterator[tuple[zenoh.Session, str]]:
    """The world's router as ``World`` opens it: TLS and the run's access control."""
    endpoint = local_endpoint(free_tcp_port(), tls=True)
    config = zenoh_config(mode="router", listen=[endpoint], tls=identity(tls_dir, WORLD_ROLE),
                          access_control=router_access_control(KEYS.prefix, NEIGHBOURS))
    with opened(config) as session:
        yield session, endpoint


def client(endpoint: str, tls: TlsIdentity) -> contextlib.AbstractContextManager[zenoh.Session]:
    return opened(zenoh_config(mode="client", connect=[endpoint], tls=tls))


def listen(session: zenoh.Session, key: str) -> tuple[Heard, zenoh.Subscriber]:
    heard = Heard()
    return heard, session.declare_subscriber(key, heard)


# -- configuration -------------------------------------------------------------------------------


def test_security_is_off_by_default_and_tls_endpoints_need_it() -> None:
    config = load_config(CASE1)
    assert not config.security.enabled and config.security.identity() is None
    assert local_endpoint(7447) == "tcp/127.0.0.1:7447"
    assert json.loads(zenoh_config().get_json("access_control"))["enabled"] is False
    with pytest.raises(ValueError, match="tls needs certificates"):
        zenoh_config(mode="client", connect=["tls/127.0.0.1:7447"])


def test_tls_config_is_mutual_tls_only(tmp_path: Path) -> None:
    tls = TlsIdentity.of(tmp_path, agent_role(2))
    config = zenoh_config(mode="client", connect=[local_endpoint(7447, tls=True)], tls=tls)
    settings = json.loads(config.get_json("transport/link/tls"))
    assert settings["enable_mtls"] is True and settings["verify_name_on_connect"] is True
    assert settings["root_ca_certificate"] == str(tmp_path / "ca.pem")
    assert settings["connect_certificate"] == str(tmp_path / "agent-2.pem")
    assert settings["connect_private_key"] == str(tmp_path / "agent-2.key")
    assert json.loads(config.get_json("transport/link/protocols")) == ["tls"]
    with pytest.raises(ValueError, match="plain, but"):
        zenoh_config(mode="client", connect=["tcp/127.0.0.1:7447"], tls=tls)


def test_access_control_gives_agents_no_rule_on_truth_and_everyone_else_nothing() -> None:
    acl = router_access_control(KEYS.prefix, NEIGHBOURS)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    rules = {rule["id"]: rule for rule in acl["rules"]}
    for rule in rules.values():
        assert rule["permission"] == "allow"
        assert all(key.startswith(f"{KEYS.prefix}/") for key in rule["key_exprs"])
    names = {cn for subject in acl["subjects"] for cn in subject["cert_common_names"]}
    assert names == {"vigil-observer", "vigil-agent-0", "vigil-agent-1", "vigil-agent-2"}
    for policy in acl["policies"]:
        if policy["subjects"] == [OBSERVER_ROLE]:
            continue
        granted = [key for rule_id in policy["rules"] for key in rules[rule_id]["key_exprs"]
                   if rules[rule_id]["messages"] != ["declare_subscriber"]
                   or rules[rule_id]["flows"] != ["egress"]]
        assert KEYS.truth not in granted and f"{KEYS.prefix}/**" not in granted
        assert not any("truth" in key for key in granted)


def test_a_missing_certificate_is_one_config_line_without_key_material(tmp_path: Path) -> None:
    (tmp_path / "certs").mkdir()
    (tmp_path / "certs" / "ca.pem").write_text("-----BEGIN CERTIFICATE-----\nx\n")
    path = tmp_path / "scenario.toml"
    path.write_text(with_tls_dir("certs"))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "\n" not in message
    assert f"security.tls_dir: {tmp_path / 'certs' / 'world.pem'}: no such file" in message
    (tmp_path / "certs" / "world.pem").write_text("-----BEGIN CERTIFICATE-----\nx\n")
    (tmp_path / "certs" / "world.key").write_text("SECRET-MATERIAL, not PEM\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "world.key: not a PEM private key" in str(info.value)
    assert "SECRET" not in str(info.value)


@requires_openssl
def test_a_complete_tls_dir_loads_relative_to_the_config_file(tls_dir: Path,
                                                              tmp_path: Path) -> None:
    certs = tmp_path / "certs"
    shutil.copytree(tls_dir, certs)
    path = tmp_path / "scenario.toml"
    path.write_text(with_tls_dir("certs"))
    config = load_config(path)
    assert config.security.enabled
    assert config.security.identity(agent_role(4)) == TlsIdentity(
        certs / "ca.pem", certs / "agent-4.pem", certs / "agent-4.key")
    (certs / "agent-5.key").unlink()
    with pytest.raises(ConfigError, match=r"agent-5\.key: no such file"):
        load_config(path)


@requires_openssl
@pytest.mark.parametrize(("argv", "expected"), [
    (["sim_world.cli", "{config}", "--listen", "tcp/127.0.0.1:7447"],
     "sim-world: zenoh endpoint 'tcp/127.0.0.1:7447': plain, but [security] is on: use "
     "tls/<host>:<port>"),
    (["swarm.agent.cli", "--id", "0", "--config", "{config}", "--connect", "tcp/127.0.0.1:7447"],
     "swarm-agent: zenoh endpoint 'tcp/127.0.0.1:7447': plain, but [security] is on: use "
     "tls/<host>:<port>"),
    (["swarm.agent.cli", "--id", "0", "--config", "{config}", "--listen", "tls/127.0.0.1:7448"],
     "swarm-agent: --listen (peer mode) is not available with [security]: agents join the "
     "world's router as clients"),
], ids=["world-plain-listen", "agent-plain-connect", "agent-peer"])
def test_process_command_lines_refuse_plain_endpoints_and_peer_agents(
        tls_dir: Path, tmp_path: Path, argv: list[str], expected: str) -> None:
    path = tmp_path / "scenario.toml"
    path.write_text(with_tls_dir(tls_dir))
    result = subprocess.run(
        [sys.executable, "-m", *(arg.format(config=path) for arg in argv)], cwd=ROOT,
        capture_output=True, text=True, timeout=60, check=False)
    assert (result.returncode, result.stderr.splitlines()) == (2, [expected]), result.stderr


# -- real sessions ------------------------------------------------------------------------------


@requires_openssl
def test_an_agent_never_receives_truth_while_the_observer_does(tls_dir: Path, router) -> None:
    world, endpoint = router
    truth = declare_publisher(world, KEYS.truth)
    clock = declare_publisher(world, KEYS.clock)
    relay = declare_publisher(world, KEYS.beacon_relay)
    cameras = [declare_publisher(world, KEYS.camera(i)) for i in range(N)]
    with client(endpoint, identity(tls_dir, agent_role(0))) as agent, \
            client(endpoint, identity(tls_dir, OBSERVER_ROLE)) as observer:
        agent_truth, s1 = listen(agent, KEYS.truth)
        agent_run, s2 = listen(agent, KEYS.everything)
        agent_any, s3 = listen(agent, "**")
        agent_clock, s4 = listen(agent, KEYS.clock)
        agent_camera, s5 = listen(agent, KEYS.camera(0))
        other_camera, s6 = listen(agent, KEYS.camera(1))
        observer_truth, s7 = listen(observer, KEYS.truth)
        agent_relay, s8 = listen(agent, KEYS.beacon_relay)  # realtime beacons

        def publish() -> None:
            truth.put(b"truth")
            clock.put(b"clock")
            relay.put(b"relay")
            for i, camera in enumerate(cameras):
                camera.put(f"camera {i}".encode())

        publish_until(publish, lambda: observer_truth.count() >= 5
                      and agent_clock.count() >= 5 and agent_camera.count() >= 5
                      and agent_relay.count() >= 5)
        assert agent_truth.count() == 0
        assert other_camera.count() == 0
        for heard in (agent_run, agent_any):
            assert heard.keys() <= {KEYS.clock, KEYS.camera(0), KEYS.beacon_relay}, heard.keys()
        del s1, s2, s3, s4, s5, s6, s7, s8


@requires_openssl
@pytest.mark.parametrize("who", ["no certificate", "certificate of another CA", "plain tcp"])
def test_a_session_without_a_valid_certificate_cannot_connect(tls_dir: Path, router,
                                                              who: str) -> None:
    _world, endpoint = router
    with client(endpoint, identity(tls_dir, OBSERVER_ROLE)):
        pass  # positive control: the router is up and takes a valid certificate
    config = zenoh.Config()
    settings: dict[str, object] = {"mode": "client", "scouting/multicast/enabled": False,
                                   "connect/endpoints": [endpoint]}
    if who == "no certificate":  # trusts the router, shows nothing of its own
        settings["transport/link/tls/root_ca_certificate"] = str(tls_dir / "ca.pem")
    elif who == "certificate of another CA":
        rogue = TlsIdentity(tls_dir / "ca.pem", tls_dir / "rogue" / "observer.pem",
                            tls_dir / "rogue" / "observer.key")
        settings.update(rogue.zenoh_settings())
    else:
        settings["connect/endpoints"] = [endpoint.replace("tls/", "tcp/")]
    for key, value in settings.items():
        config.insert_json5(key, json.dumps(value))
    with pytest.raises(TransportError), opened(config):
        pass


@requires_openssl
def test_a_certificate_of_an_unknown_role_can_neither_publish_nor_subscribe(
        tls_dir: Path, router) -> None:
    world, endpoint = router
    truth = declare_publisher(world, KEYS.truth)
    intruder_tls = TlsIdentity(tls_dir / "ca.pem", tls_dir / "intruder" / "intruder.pem",
                               tls_dir / "intruder" / "intruder.key")
    with client(endpoint, identity(tls_dir, agent_role(0))) as agent, \
            client(endpoint, identity(tls_dir, OBSERVER_ROLE)) as observer, \
            client(endpoint, intruder_tls) as intruder:
        observer_run, s1 = listen(observer, KEYS.everything)
        agent_beacons, s2 = listen(agent, KEYS.all_beacons)
        intruder_run, s3 = listen(intruder, KEYS.everything)
        intruder_truth, s4 = listen(intruder, KEYS.truth)
        beacon = declare_publisher(agent, KEYS.beacon(0))
        forged = [declare_publisher(intruder, key) for key in
                  (KEYS.beacon(0), KEYS.beacon(1), KEYS.consensus(0), KEYS.truth, KEYS.clock)]

        def publish() -> None:
            truth.put(b"truth")
            beacon.put(b"beacon 0")
            for publisher in forged:
                publisher.put(b"forged")

        publish_until(publish, lambda: observer_run.count(KEYS.truth) >= 5
                      and observer_run.count(KEYS.beacon(0), b"beacon 0") >= 5)
        assert observer_run.count(payload=b"forged") == 0
        assert agent_beacons.count(payload=b"forged") == 0
        assert world_hears_nothing_forged(world, forged)
        # What the intruder "heard" is only what it published itself (local delivery).
        assert intruder_truth.count(payload=b"truth") == 0
        assert intruder_run.count(payload=b"beacon 0") == 0
        assert {p for (_k, p) in intruder_run.samples} <= {b"forged"}
        del s1, s2, s3, s4


def world_hears_nothing_forged(world: zenoh.Session, forged: list[zenoh.Publisher]) -> bool:
    """A subscriber in the router itself gets no publication of the intruder either."""
    heard, sub = listen(world, KEYS.everything)
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:
        for publisher in forged:
            publisher.put(b"forged")
        time.sleep(0.05)
    sub.undeclare()
    return heard.count(payload=b"forged") == 0


@requires_openssl
def test_agents_exchange_consensus_and_beacons_only_under_their_own_keys(
        tls_dir: Path, router) -> None:
    _world, endpoint = router
    with client(endpoint, identity(tls_dir, agent_role(0))) as a0, \
            client(endpoint, identity(tls_dir, agent_role(1))) as a1, \
            client(endpoint, identity(tls_dir, agent_role(2))) as a2, \
            client(endpoint, identity(tls_dir, OBSERVER_ROLE)) as observer:
        # Drone 1 reads its neighbours 0 and 2; drone 2 is no neighbour of drone 0.
        a1_consensus0, s1 = listen(a1, KEYS.consensus(0))
        a1_consensus2, s2 = listen(a1, KEYS.consensus(2))
        a1_beacons, s3 = listen(a1, KEYS.all_beacons)  # beacons reach agents in the relay
        observer_beacons, s7 = listen(observer, KEYS.all_beacons)
        a2_consensus0, s4 = listen(a2, KEYS.consensus(0))
        a1_telemetry, s5 = listen(a1, KEYS.all_telemetry)
        observer_telemetry, s6 = listen(observer, KEYS.all_telemetry)
        p0 = [declare_publisher(a0, key) for key in
              (KEYS.consensus(0), KEYS.beacon(0), KEYS.telemetry(0))]
        p2 = [declare_publisher(a2, key) for key in (KEYS.consensus(2), KEYS.beacon(2))]
        spoof = [declare_publisher(a2, key) for key in
                 (KEYS.consensus(0), KEYS.beacon(0), KEYS.telemetry(0))]

        def publish() -> None:
            for publisher in (*p0, *p2):
                publisher.put(b"own")
            for publisher in spoof:
                publisher.put(b"spoof")

        publish_until(publish, lambda: a1_consensus0.count(payload=b"own") >= 5
                      and a1_consensus2.count(payload=b"own") >= 5
                      and observer_beacons.count(KEYS.beacon(0), b"own") >= 5
                      and observer_beacons.count(KEYS.beacon(2), b"own") >= 5
                      and observer_telemetry.count(payload=b"own") >= 5)
        assert a1_consensus0.count(payload=b"spoof") == 0
        assert observer_beacons.count(payload=b"spoof") == 0
        assert a1_beacons.count() == 0  # no agent reads another's beacon key
        assert observer_telemetry.count(payload=b"spoof") == 0
        assert a2_consensus0.count(payload=b"own") == 0  # not drone 0's neighbour
        assert a1_telemetry.count() == 0  # telemetry is for the observer
        del s1, s2, s3, s4, s5, s6, s7


# -- the process swarm ---------------------------------------------------------------------------


@requires_openssl
@pytest.mark.slow
def test_case1_lockstep_swarm_runs_over_tls_and_an_agent_certificate_gets_no_truth(
        tls_dir: Path, tmp_path: Path) -> None:
    path = tmp_path / "case1_tls.toml"
    path.write_text(with_tls_dir(tls_dir))
    config = load_config(path).with_duration(1.5)  # control starts at 1 s
    launcher = SwarmLauncher(LaunchOptions(config=config, config_path=str(path), seed=0,
                                           run_id="tlsrun"), log=lambda _line: None)
    assert launcher.endpoint.startswith("tls/127.0.0.1:")
    keys = Keys("tlsrun")
    spy_truth, spy_frames = Heard(), Heard()
    spy: list[zenoh.Session] = []
    spy_subscribers: list[zenoh.Subscriber] = []
    stop = threading.Event()

    def join_as_an_agent() -> None:  # the world is not up yet: keep trying
        while not stop.is_set():
            try:
                session = open_session(zenoh_config(
                    mode="client", connect=[launcher.endpoint],
                    tls=identity(tls_dir, agent_role(5))))
            except TransportError:
                time.sleep(0.1)
                continue
            spy_subscribers.extend([session.declare_subscriber(keys.truth, spy_truth),
                                    session.declare_subscriber(keys.camera(5), spy_frames)])
            spy.append(session)
            return

    thread = threading.Thread(target=join_as_an_agent, daemon=True)
    thread.start()
    try:
        record = launcher.run()
    finally:
        stop.set()
        thread.join(5.0)
    try:
        assert record.n_steps == config.n_steps == 75
        assert spy, "the spy never joined"
        assert spy_frames.count() > 0  # the spy was connected while the swarm flew
        assert spy_truth.count() == 0
    finally:
        if spy:
            spy[0].close()
