"""Zenoh TLS with mutual authentication, and the access control the world's router enforces.

Off by default. ``[security] tls_dir = "certs"`` (relative to the config file) turns it on; the
directory holds PEM files made by one certificate authority:

- ``ca.pem``: the CA certificate every process trusts (and nothing else);
- ``world.pem`` / ``world.key``: the router (``sim-world``); common name ``vigil-world``, with
  the router's address (``IP:127.0.0.1``) as a subject alternative name, since every client
  checks the name it connected to;
- ``agent-<i>.pem`` / ``agent-<i>.key`` for drone i = 0..N-1: common name ``vigil-agent-<i>``;
- ``observer.pem`` / ``observer.key``: ``launch-swarm`` (its collector and recorder) and the
  dashboard; common name ``vigil-observer``.

Every endpoint is then ``tls/<host>:<port>`` and every link needs a certificate signed by the
CA (mutual TLS): a session without one cannot connect at all. The router also maps each
client's certificate common name to a role (zenoh ``access_control``, default deny):

- drone i may publish only its own ``agent/i/{consensus,beacon,telemetry}`` and subscribe to
  its camera ``world/camera/i``, ``world/clock``, every beacon (each drone's, and the world's
  relay ``world/beacons``) and its graph neighbours' consensus, and is sent nothing
  else: never ``world/truth``;
- the observer may subscribe to everything of the run and publishes nothing;
- anyone else (a certificate of the CA with another common name) may do nothing.

Each rule names the run's keys (``vigil/<run_id>/...``), so a certificate also gets nothing
of another run behind the same router.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from swarm.errors import UsageError

CA_FILE: Final = "ca.pem"
WORLD_ROLE: Final = "world"
OBSERVER_ROLE: Final = "observer"
CN_PREFIX: Final = "vigil-"
_PEM_CERTIFICATE: Final = b"-----BEGIN CERTIFICATE-----"
_PEM_KEY_END: Final = b"PRIVATE KEY-----"


class SecurityError(UsageError, ValueError):
    """An unusable TLS directory (one line: which file and why)."""


def agent_role(drone_id: int) -> str:
    """The role (file stem) of drone ``drone_id``: ``agent-<i>``."""
    if isinstance(drone_id, bool) or not isinstance(drone_id, int) or drone_id < 0:
        raise ValueError(f"drone id must be an integer >= 0, got {drone_id!r}")
    return f"agent-{drone_id}"


def common_name(role: str) -> str:
    """The certificate common name a role must carry: ``vigil-<role>``."""
    return CN_PREFIX + role


def roles(n_drones: int) -> list[str]:
    return [WORLD_ROLE, OBSERVER_ROLE, *(agent_role(i) for i in range(n_drones))]


@dataclass(frozen=True)
class TlsIdentity:
    """The CA certificate, and one role's certificate and private key (absolute paths)."""

    ca: Path
    certificate: Path
    private_key: Path

    @classmethod
    def of(cls, tls_dir: str | Path, role: str) -> TlsIdentity:
        base = Path(tls_dir).absolute()
        return cls(base / CA_FILE, base / f"{role}.pem", base / f"{role}.key")

    def zenoh_settings(self) -> dict[str, Any]:
        """``transport/link/tls/*`` settings (zenoh 1.x) for both directions of a session:
        mutual TLS, the server's name checked against the endpoint's host."""
        prefix = "transport/link/tls/"
        return {
            prefix + "root_ca_certificate": str(self.ca),
            prefix + "enable_mtls": True,
            prefix + "verify_name_on_connect": True,
            prefix + "listen_certificate": str(self.certificate),
            prefix + "listen_private_key": str(self.private_key),
            prefix + "connect_certificate": str(self.certificate),
            prefix + "connect_private_key": str(self.private_key),
            "transport/link/protocols": ["tls"],  # no plain link in or out
        }


def _check_file(path: Path, marker: bytes, what: str) -> None:
    try:
        with path.open("rb") as handle:
            head = handle.read(1 << 16)  # a PEM marker is near the start; never a huge file
    except FileNotFoundError:
        raise SecurityError(f"{path}: no such file ({what})") from None
    except IsADirectoryError:
        raise SecurityError(f"{path}: is a directory, expected {what}") from None
    except PermissionError:
        raise SecurityError(f"{path}: permission denied ({what})") from None
    except OSError as err:
        raise SecurityError(f"{path}: cannot read {what}: {err.strerror}") from None
    if marker not in head:
        raise SecurityError(f"{path}: not {what}")


def check_tls_dir(tls_dir: str | Path, n_drones: int) -> None:
    """Every file of the layout is there and looks like PEM; else ``SecurityError``.

    The certificates themselves (signature, common name, expiry) are checked by zenoh when a
    link opens; a key file's content never appears in a message.
    """
    base = Path(tls_dir)
    if not base.is_dir():
        raise SecurityError(f"{base}: no such directory")
    _check_file(base / CA_FILE, _PEM_CERTIFICATE, "a PEM CA certificate")
    for role in roles(n_drones):
        identity = TlsIdentity.of(base, role)
        _check_file(identity.certificate, _PEM_CERTIFICATE, f"a PEM certificate of {role}")
        _check_file(identity.private_key, _PEM_KEY_END, f"a PEM private key of {role}")


def router_access_control(prefix: str, neighbours: Sequence[Iterable[int]]) -> dict[str, Any]:
    """The router's zenoh ``access_control`` block for the run under ``prefix``
    (``vigil/<run_id>``); ``neighbours[i]``: the drones whose consensus drone i reads.

    Rules are seen from the router: ``ingress`` is what a client sends it (publications,
    subscriptions), ``egress`` what it forwards to that client. A client's publisher only
    sends once the router has told it that someone subscribes, so each role is allowed to
    *hear of* every subscription of the run (egress ``declare_subscriber``); what it may
    publish or receive is restricted separately.
    """
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def allow(rule_id: str, messages: list[str], flow: str, keys: list[str]) -> str:
        rules.append({"id": rule_id, "permission": "allow", "messages": messages,
                      "flows": [flow], "key_exprs": keys})
        return rule_id

    def policy(role: str, rule_ids: list[str]) -> None:
        subjects.append({"id": role, "cert_common_names": [common_name(role)]})
        policies.append({"id": role, "rules": rule_ids, "subjects": [role]})

    hear_subscriptions = allow("hear-subscriptions", ["declare_subscriber"], "egress",
                               [f"{prefix}/**"])
    for i, adjacent in enumerate(neighbours):
        role = agent_role(i)
        own = [f"{prefix}/agent/{i}/{kind}" for kind in ("consensus", "beacon", "telemetry")]
        # A rendered camera's detector runs on the drone under its identity: it reads the
        # drone's images and publishes its camera frames (docs/camera.md).
        own.append(f"{prefix}/world/camera/{i}")
        # Every other drone's beacon comes in the world's relay (world/beacons), which the
        # world builds from what it took on each sender's own key: an agent reads no
        # other agent's beacon key.
        reads = [f"{prefix}/world/camera/{i}", f"{prefix}/world/image/{i}",
                 f"{prefix}/world/clock",
                 f"{prefix}/world/beacons",
                 *(f"{prefix}/agent/{j}/consensus" for j in sorted(set(adjacent)))]
        policy(role, [allow(f"{role}-publish", ["put"], "ingress", own),
                      allow(f"{role}-subscribe", ["declare_subscriber"], "ingress", reads),
                      allow(f"{role}-receive", ["put"], "egress", reads),
                      hear_subscriptions])
    everything = [f"{prefix}/**"]
    policy(OBSERVER_ROLE, [
        allow("observer-subscribe", ["declare_subscriber"], "ingress", everything),
        allow("observer-receive", ["put"], "egress", everything)])
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}
