"""MAVLink 2 message signing between an agent and its vehicle: key file and pymavlink state.

Off unless ``[vehicles] signing_key_file`` names a key file. The file holds the 32-byte
secret key as 64 hexadecimal digits (surrounding whitespace ignored), e.g. made with
``openssl rand -hex 32 > swarm.key``: text, so it survives copy-paste into a GCS or an
autopilot's key setup, and a wrong file (a passphrase, a binary blob) is refused rather
than silently hashed into some other key. Errors never show the file's content.

Signing itself is pymavlink's (``MAVLink.signing``: ``sign_packet`` on send,
``check_signature`` on receive, its per-stream timestamp rule). This module only sets that
state up for a bare ``MAVLink`` object (the emulated vehicle has no ``mavutil`` connection,
whose ``setup_signing`` does the same) and keeps the signing timestamp on the wall clock:
pymavlink advances it by one tick per packet sent, so a long-lived end would fall behind
real time and a peer that restarts (new timestamp = now) would then reject its frames as
"more than a minute old"; autopilots refresh it from their clock for the same reason.

No pymavlink import here: the config loader validates key files without loading a dialect.
"""

from __future__ import annotations

import string
import time
from pathlib import Path
from typing import Any

from swarm.errors import UsageError

__all__ = ["KEY_BYTES", "SigningKeyError", "enable_signing", "read_signing_key",
           "refresh_signing_timestamp", "signing_timestamp"]

KEY_BYTES = 32
_EPOCH_2015_S = 1420070400  # MAVLink signing timestamps count 10 µs units since 2015-01-01
_MAX_KEY_FILE_BYTES = 4096  # a key file is tiny; do not read a wrongly named big file


class SigningKeyError(UsageError, ValueError):
    """The key file cannot be used; the message is one line and never shows its content."""


def read_signing_key(path: str | Path) -> bytes:
    """The 32-byte secret from ``path`` (64 hex digits); SigningKeyError otherwise."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            raw = handle.read(_MAX_KEY_FILE_BYTES + 1)
    except FileNotFoundError:
        raise SigningKeyError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise SigningKeyError(f"{path}: is a directory, expected a key file") from None
    except PermissionError:
        raise SigningKeyError(f"{path}: permission denied") from None
    except OSError as err:
        raise SigningKeyError(f"{path}: cannot read: {err.strerror or err}") from None
    expected = (f"expected the {KEY_BYTES}-byte key as {2 * KEY_BYTES} hex digits "
                f"(e.g. openssl rand -hex {KEY_BYTES})")
    try:
        text = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise SigningKeyError(f"{path}: not a text file: {expected}") from None
    if len(raw) > _MAX_KEY_FILE_BYTES or len(text) != 2 * KEY_BYTES:
        size = f"more than {_MAX_KEY_FILE_BYTES} bytes" if len(raw) > _MAX_KEY_FILE_BYTES \
            else f"{len(text)} characters"
        raise SigningKeyError(f"{path}: {expected}, got {size}")
    if not all(c in string.hexdigits for c in text):
        raise SigningKeyError(f"{path}: {expected}, got other characters")
    return bytes.fromhex(text)


def signing_timestamp(unix_s: float) -> int:
    """MAVLink signing timestamp (10 µs units since 2015-01-01 UTC) of a Unix time."""
    return int(max(unix_s - _EPOCH_2015_S, 0.0) * 100_000)


def enable_signing(mav: Any, key: bytes, *, link_id: int, unix_s: float | None = None) -> None:
    """Sign every frame ``mav`` sends and accept only correctly signed ones: the state
    ``mavutil.mavfile.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None)``
    sets, for a bare ``MAVLink`` object."""
    if len(key) != KEY_BYTES:
        raise ValueError(f"a MAVLink signing key has {KEY_BYTES} bytes, got {len(key)}")
    if not 0 <= link_id <= 255:
        raise ValueError(f"link_id must be in 0..255, got {link_id}")
    signing = mav.signing
    signing.secret_key = bytes(key)
    signing.sign_outgoing = True
    signing.allow_unsigned_callback = None  # unsigned frames are refused, none excepted
    signing.link_id = int(link_id)
    signing.timestamp = signing_timestamp(time.time() if unix_s is None else unix_s)


def refresh_signing_timestamp(mav: Any, unix_s: float | None = None) -> None:
    """Move ``mav``'s signing timestamp up to the wall clock (never back: it must only grow)."""
    now = signing_timestamp(time.time() if unix_s is None else unix_s)
    if now > mav.signing.timestamp:
        mav.signing.timestamp = now
