"""The C extensions are refused when older than their sources (an uncompiled edit), and the
layouts they export are read by name, with one-line errors."""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import pytest

from swarm.compiled import check_built_from_current_source, field_index, field_slice, in_order
from swarm.errors import VigilError
from tools.mutation import EXTENSIONS

ROOT = Path(__file__).resolve().parent.parent


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


def test_a_binary_older_than_a_header_it_includes_is_refused(tmp_path: Path) -> None:
    binary, source, header = (tmp_path / "_wire.so", tmp_path / "_wire.c",
                              tmp_path / "relay_row.h")
    for path, at in ((binary, 2_000), (source, 1_000), (header, 3_000)):
        path.write_bytes(b"")
        os.utime(path, (at, at))
    with pytest.raises(VigilError, match=r"_wire.so is older than relay_row.h"):
        check_built_from_current_source(binary, source, header)
    check_built_from_current_source(binary, source)


FIELDS = (("weight", 0, 1), ("grad", 1, 4), ("distance", 4, 5))


def test_fields_are_read_by_name() -> None:
    assert field_index(FIELDS, "distance") == 4
    assert field_slice(FIELDS, "grad") == slice(1, 4)
    assert field_slice(FIELDS, "weight") == slice(0, 1)
    with pytest.raises(VigilError, match="field 'grad' holds 3 floats, not one"):
        field_index(FIELDS, "grad")
    with pytest.raises(VigilError, match=r"no field 'lie' in the compiled layout \(it has "
                                         r"weight, grad, distance\)"):
        field_slice(FIELDS, "lie")


def test_constants_are_put_in_the_kernels_order_every_one_given() -> None:
    names = ("n_agents", "gamma", "share")
    assert in_order(names, {"share": 1.0, "n_agents": 3.0, "gamma": 0.5}) == [3.0, 0.5, 1.0]
    with pytest.raises(VigilError, match=r"constants: missing \['gamma'\], unknown \['rho'\] "
                                         r"\(the kernel takes n_agents, gamma, share\)"):
        in_order(names, {"share": 1.0, "n_agents": 3.0, "rho": 0.5})


def test_the_mutation_tool_builds_every_extension_the_project_declares() -> None:
    """``tools/mutation.py`` compiles the extensions in its copy of the tree itself: it must
    know each one that ``pyproject.toml`` declares, or the copy cannot import its module."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    declared = [source for ext in project["tool"]["setuptools"]["ext-modules"]
                for source in ext["sources"]]
    assert sorted(declared) == sorted(source for source, _ in EXTENSIONS)
