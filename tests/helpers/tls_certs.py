"""Test certificates for ``[security]`` (the layout of ``swarm.net.security``), made with the
``openssl`` command-line tool: EC P-256 keys, valid for two days, in a directory of the test's.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from swarm.net.security import CA_FILE, common_name, roles

OPENSSL = shutil.which("openssl")
requires_openssl = pytest.mark.skipif(
    OPENSSL is None, reason="the openssl command-line tool makes the test certificates; "
                            "it is not on PATH")
_LEAF_EXTENSIONS = ("basicConstraints=critical,CA:FALSE\n"
                    "keyUsage=critical,digitalSignature\n"
                    "extendedKeyUsage=serverAuth,clientAuth\n"
                    "subjectAltName=IP:127.0.0.1,DNS:localhost\n")


def _openssl(*args: str | Path) -> None:
    assert OPENSSL is not None
    subprocess.run([OPENSSL, *map(str, args)], check=True, capture_output=True, timeout=60)


def make_ca(directory: Path, name: str = "vigil-test-ca") -> Path:
    """A self-signed CA: ``ca.pem`` and ``ca.key`` in ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", directory / "ca.key", "-out", directory / CA_FILE, "-days", "2",
             "-subj", f"/CN={name}", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    return directory / CA_FILE


def make_leaf(ca_dir: Path, directory: Path, stem: str, cn: str) -> None:
    """``<stem>.pem`` / ``<stem>.key`` in ``directory``: common name ``cn``, signed by the CA
    in ``ca_dir``, usable as server and client (SAN 127.0.0.1 and localhost)."""
    directory.mkdir(parents=True, exist_ok=True)
    csr, ext = directory / f"{stem}.csr", directory / f"{stem}.ext"
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", directory / f"{stem}.key", "-out", csr, "-subj", f"/CN={cn}")
    ext.write_text(_LEAF_EXTENSIONS)
    _openssl("x509", "-req", "-in", csr, "-CA", ca_dir / CA_FILE, "-CAkey", ca_dir / "ca.key",
             "-set_serial", str(abs(hash((stem, cn, str(directory)))) % (1 << 62) + 1),
             "-out", directory / f"{stem}.pem", "-days", "2", "-extfile", ext)
    csr.unlink()
    ext.unlink()


def make_tls_dir(directory: Path, n_drones: int) -> Path:
    """A complete ``[security] tls_dir`` for ``n_drones`` drones (the CA's key stays there
    too, for ``make_leaf``)."""
    make_ca(directory)
    for role in roles(n_drones):
        make_leaf(directory, directory, role, common_name(role))
    return directory
