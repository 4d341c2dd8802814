"""``--set key=value``: one config value changed by its dotted key, as if the file said so.

``launch-swarm --set`` and every point of a sweep (``swarm.sweep``) go through here: the
overrides are applied to the raw TOML document before it is validated
(``swarm.scenario.config.load_config``), so a value given this way is checked exactly as one
written in the file, and a bad one is the same one-line ``ConfigError``.

Keys are dotted paths into the document: ``gramian.epsilon``, ``camera.image_noise_std``,
``gramian.weight_consensus.kp``; a number indexes an array of tables (``targets.0.velocity_m_s``
is the first ``[[targets]]`` entry's velocity). A section the file leaves out is created.

``swarm.n_drones`` set to another N than the file's (and ``swarm.edges`` not set with it) also
generates what the file's swarm would not fit: the edges become a ring plus chords
(``ring_with_chords``) and the start box's x and y sides scale with √(N / N_file), keeping the
file's drones per square metre (``benchmarks/swarm_configs.py`` scaled Case 2 to N = 12, 24
and 48 the same way).

No imports from the rest of the project but ``swarm.errors``: ``config`` imports this.
"""

from __future__ import annotations

import copy
import math
import re
import tomllib
from collections.abc import Iterable, Sequence

from swarm.errors import UsageError

Override = tuple[str, object]
KEY_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.([A-Za-z_][A-Za-z0-9_]*|[0-9]+))*$")
BARE_WORD = re.compile(r"^[A-Za-z_][A-Za-z0-9_.:/-]*$")


class OverrideError(UsageError, ValueError):
    """A ``--set`` that cannot be applied; ``str()`` is one line naming the key."""


def check_key(key: str) -> str:
    """``key`` if it is a dotted path (``section.key``, ``targets.0.start_m``); else
    OverrideError."""
    if not KEY_PATTERN.match(key) or "." not in key:
        raise OverrideError(f"{key!r}: expected a dotted key such as gramian.epsilon or "
                            f"targets.0.velocity_m_s")
    return key


def parse_value(text: str) -> object:
    """A TOML value (``0.05``, ``[0.2, 0.0, 0.0]``, ``true``, ``"px4"``); a bare word that
    is not one (``arducopter``) is taken as a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        if BARE_WORD.match(text.strip()):
            return text.strip()
        raise OverrideError(f"{text!r} is not a TOML value (a number, true/false, "
                            f"\"text\" or an array such as [0.2, 0.0, 0.0])") from None


def parse_assignment(text: str) -> Override:
    """``KEY=VALUE`` of ``--set``; OverrideError (one line) when malformed."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not value.strip():
        raise OverrideError(f"expected KEY=VALUE such as gramian.epsilon=0.06, got {text!r}")
    try:
        return check_key(key), parse_value(value.strip())
    except OverrideError as err:
        raise OverrideError(f"{key}: {err}") from None


def ring_with_chords(n_drones: int) -> list[list[int]]:
    """A connected graph for any N >= 2: the ring 0-1-…-(N−1)-0 plus the chords
    (i, i + ⌊N/2⌋) for i < ⌊N/2⌋ that are not ring edges. Every drone is in at most one
    chord, so the degree is at most 3 and λ_max(L) ≤ 6 (the consensus gains of the configs
    stay stable); for even N it is the ring with every diameter (3-regular)."""
    if n_drones < 2:
        raise OverrideError(f"swarm.n_drones: must be at least 2 (got {n_drones})")
    if n_drones == 2:
        return [[0, 1]]
    edges = [[i, (i + 1) % n_drones] for i in range(n_drones)]
    ring = {frozenset(e) for e in edges}
    half = n_drones // 2
    edges += [[i, i + half] for i in range(half) if frozenset((i, i + half)) not in ring]
    return edges


def apply_overrides(data: dict[str, object], overrides: Iterable[Override]) -> dict[str, object]:
    """A copy of the TOML document ``data`` with every override applied, in order;
    OverrideError (one line) when a key cannot be placed (a scalar where a table is needed,
    an index past the end of an array). Whether the key exists and the value fits is
    ``config_from_dict``'s to say, as for a file."""
    overrides = list(overrides)
    if not overrides:
        return data
    out = copy.deepcopy(data)
    keys = {key for key, _value in overrides}
    file_swarm = out.get("swarm")
    file_n = file_swarm.get("n_drones") if isinstance(file_swarm, dict) else None
    for key, value in overrides:
        _set(out, check_key(key), copy.deepcopy(value))
    swarm = out.get("swarm")
    if "swarm.n_drones" in keys and isinstance(swarm, dict):
        _fit_swarm(swarm, file_n, keys)
    return out


def _set(data: dict[str, object], key: str, value: object) -> None:
    parts = key.split(".")
    node: object = data
    for depth, part in enumerate(parts[:-1]):
        node = _child(node, part, parts[depth + 1].isdigit(), ".".join(parts[:depth + 1]))
    last = parts[-1]
    where = ".".join(parts[:-1])
    if isinstance(node, list):
        index = _index(node, last, key)
        node[index] = value
    elif isinstance(node, dict):
        node[last] = value
    else:
        raise OverrideError(f"{key}: {where} is a value, not a table")


def _child(node: object, part: str, next_is_index: bool, where: str) -> object:
    if isinstance(node, list):
        return node[_index(node, part, where)]
    if not isinstance(node, dict):
        raise OverrideError(f"{where}: {where.rpartition('.')[0]} is a value, not a table")
    if part not in node:
        if next_is_index:
            raise OverrideError(f"{where}: the config has no such array of tables")
        node[part] = {}
    return node[part]


def _index(node: list[object], part: str, where: str) -> int:
    if not part.isdigit():
        raise OverrideError(f"{where}: an array: index it with a number (e.g. targets.0)")
    index = int(part)
    if index >= len(node):
        raise OverrideError(f"{where}: index {index} out of range (the config has "
                            f"{len(node)} entries)")
    return index


def _fit_swarm(swarm: dict[str, object], file_n: object, keys: set[str]) -> None:
    """Edges and start box for a new ``swarm.n_drones`` (module docstring)."""
    n = swarm.get("n_drones")
    if not isinstance(n, int) or isinstance(n, bool) or n == file_n:
        return  # a wrong type is config_from_dict's to report; the same N keeps the file's
    if not 2 <= n <= 256:
        return  # SwarmSection names the range
    if "swarm.edges" not in keys:
        swarm["edges"] = ring_with_chords(n)
    size = swarm.get("initial_box_size_m")
    if ("swarm.initial_box_size_m" not in keys and isinstance(file_n, int) and file_n > 0
            and isinstance(size, Sequence) and len(size) == 3
            and all(isinstance(v, int | float) for v in size)):
        scale = math.sqrt(n / file_n)
        swarm["initial_box_size_m"] = [round(float(size[0]) * scale, 1),
                                       round(float(size[1]) * scale, 1), float(size[2])]


__all__ = ["OverrideError", "apply_overrides", "parse_assignment", "parse_value",
           "ring_with_chords"]
