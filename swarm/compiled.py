"""The C extensions of the project (``swarm.core._kernels``, ``swarm.messages._wire``,
``swarm.agent._exchange``, ``swarm.mavlink._frame``), as an editable install keeps them: built
by ``pip install -e .`` beside their sources.

``check_built_from_current_source``: an extension older than one of its sources (its ``.c``
and the headers it includes) is refused, or an edit not yet compiled would run the old binary
without a word.

The layouts a kernel writes or reads and the order of the constants it takes are exported by
its module (``swarm/compiled.h``: ``add_fields``, ``add_names``) and read here, so that Python
never writes an offset or a position of its own: ``field_index``/``field_slice`` of a row's
fields, ``in_order`` of named constants.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from swarm.errors import VigilError

# A field of an exported row: (name, start, stop), in floats.
Field = tuple[str, int, int]


def check_built_from_current_source(binary: Path, *sources: Path) -> None:
    """Raise ``VigilError`` if one of ``sources`` exists (a source tree, not an installed
    wheel) and is newer than ``binary``."""
    built_s = binary.stat().st_mtime
    for source in sources:
        if source.exists() and source.stat().st_mtime > built_s:
            raise VigilError(f"{binary.name} is older than {source.name}: rebuild it with "
                             "`pip install -e .`")


def not_built(module: str, source: str) -> VigilError:
    """The error of an extension that cannot be imported: the tree was never installed."""
    return VigilError(f"{module} is not built: install the project with `pip install -e .` "
                      f"(it compiles {source})")


def _field(fields: tuple[Field, ...], name: str) -> Field:
    for field in fields:
        if field[0] == name:
            return field
    raise VigilError(f"no field {name!r} in the compiled layout (it has "
                     f"{', '.join(f[0] for f in fields)})")


def field_index(fields: tuple[Field, ...], name: str) -> int:
    """The index of the one-float field ``name`` of an exported row."""
    _, start, stop = _field(fields, name)
    if stop - start != 1:
        raise VigilError(f"field {name!r} holds {stop - start} floats, not one")
    return start


def field_slice(fields: tuple[Field, ...], name: str) -> slice:
    """The floats of field ``name`` of an exported row."""
    _, start, stop = _field(fields, name)
    return slice(start, stop)


def in_order(names: tuple[str, ...], values: Mapping[str, float]) -> list[float]:
    """``values`` in the order a kernel takes them (``names``, exported by its module);
    every name given, none other."""
    if values.keys() != set(names):
        missing, extra = set(names) - values.keys(), values.keys() - set(names)
        raise VigilError(f"constants: missing {sorted(missing)}, unknown {sorted(extra)} "
                         f"(the kernel takes {', '.join(names)})")
    return [values[name] for name in names]
