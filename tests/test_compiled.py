"""The C extensions are refused when older than their sources (an uncompiled edit)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from swarm.compiled import check_built_from_current_source
from swarm.errors import VigilError


def test_a_binary_older_than_its_source_is_refused(tmp_path: Path) -> None:
    """An edit of a C source not yet compiled stops the import with what to run."""
    binary, source = tmp_path / "_kernels.so", tmp_path / "_kernels.c"
    binary.write_bytes(b"")
    source.write_text("")
    os.utime(binary, (1_000, 1_000))
    os.utime(source, (2_000, 2_000))
    with pytest.raises(VigilError, match=r"_kernels.so is older than _kernels.c: rebuild it "
                                         r"with `pip install -e .`"):
        check_built_from_current_source(binary, source)
    os.utime(binary, (3_000, 3_000))
    check_built_from_current_source(binary, source)  # up to date: nothing said
    source.unlink()
    check_built_from_current_source(binary, source)  # an installed wheel: no source

