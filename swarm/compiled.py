"""The C extensions of the project (``swarm.core._kernels``, ``swarm.mavlink._frame``), as an
editable install keeps them: built by ``pip install -e .`` beside their sources.

``check_built_from_current_source``: an extension older than its source is refused, or an edit
of the C source not yet compiled would run the old binary without a word.
"""

from __future__ import annotations

from pathlib import Path

from swarm.errors import VigilError


def check_built_from_current_source(binary: Path, source: Path) -> None:
    """Raise ``VigilError`` if ``source`` exists (a source tree, not an installed wheel) and is
    newer than ``binary``."""
    if source.exists() and source.stat().st_mtime > binary.stat().st_mtime:
        raise VigilError(f"{binary.name} is older than {source.name}: rebuild it with "
                         "`pip install -e .`")


def not_built(module: str, source: str) -> VigilError:
    """The error of an extension that cannot be imported: the tree was never installed."""
    return VigilError(f"{module} is not built: install the project with `pip install -e .` "
                      f"(it compiles {source})")
