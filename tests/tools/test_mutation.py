"""The mutation tool's own parts (tools/mutation.py): mutmut's names to functions, diffs to
changed lines, the exit codes it recorded (a signal is a crash: the mutant is killed), and the
equivalents file, so that the table and ``--check`` say what mutmut found."""

from __future__ import annotations

import json
from pathlib import Path

from tools.mutation import (
    EQUIVALENTS,
    KILLED,
    ModuleResult,
    changed_lines,
    exit_code,
    function_of,
    load_equivalents,
)


def test_function_of_names_functions_and_methods() -> None:
    assert function_of("swarm.runs.checks.x__crossing__mutmut_19") == (
        "swarm.runs.checks", "_crossing")
    assert function_of("swarm.core.qp.xǁLocalQpWorkspaceǁsolve__mutmut_97") == (
        "swarm.core.qp", "LocalQpWorkspace.solve")


def test_changed_lines_are_the_removed_and_added_lines_stripped() -> None:
    diff = ("--- a.py\n+++ b.py\n@@ -1,3 +1,3 @@\n def f(x):\n-    return x < 1\n"
            "+    return x <= 1\n")
    assert changed_lines(diff) == ("return x < 1", "return x <= 1")


def test_a_mutant_whose_tests_died_of_a_signal_is_a_crash_and_killed(tmp_path: Path) -> None:
    meta = tmp_path / "mutants" / "swarm" / "core" / "qp_daqp.py.meta"
    meta.parent.mkdir(parents=True)
    meta.write_text(json.dumps({"exit_code_by_key": {"m_abort": -6, "m_failed": 1,
                                                     "m_none": None}}))
    assert exit_code(tmp_path, "swarm.core.qp_daqp", "m_abort") == -6
    assert exit_code(tmp_path, "swarm.core.qp_daqp", "m_failed") == 1
    assert exit_code(tmp_path, "swarm.core.qp_daqp", "m_none") is None
    assert exit_code(tmp_path, "swarm.core.qp_daqp", "unknown") is None
    assert exit_code(tmp_path, "swarm.core.safety", "m_abort") is None  # no meta file
    assert "crashed" in KILLED and "suspicious" not in KILLED
    result = ModuleResult("swarm.core.qp_daqp")
    result.statuses.update(["killed", "crashed", "suspicious", "survived"])
    assert (result.mutants, result.killed) == (4, 2)


def test_every_equivalent_names_its_mutant_and_says_why() -> None:
    entries = load_equivalents(EQUIVALENTS)
    assert entries, "tools/mutation_equivalents.toml has no entry"
    for e in entries:
        assert e.module.startswith("swarm.") and e.function and e.why.strip()
        assert e.original != e.mutant, e
    keys = [(e.module, e.function, e.original, e.mutant) for e in entries]
    assert len(keys) == len(set(keys)), "an equivalent is listed twice"
