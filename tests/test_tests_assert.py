"""Every test checks something: a ``test_*`` function of tests/ holds an ``assert``, a
``pytest.raises``/``warns``/``fail``, an ``assert_*`` call (``np.testing``), or a call of a
helper listed in ``ASSERTING_HELPERS``, which checks for it (a check inside a function the
test defines counts). Found by reading the source (``ast``), so a test that only runs code
cannot slip in."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

# Helpers that do a test's checking, per file (relative to tests/), as the test calls them,
# and how they check.
ASSERTING_HELPERS: dict[str, dict[str, str]] = {
    "core/test_fast_paths.py": {"_close": "np.testing.assert_allclose"},
    "core/test_kernels.py": {"_close": "np.testing.assert_allclose"},
    "models/test_kinematics.py": {"_check_layout": "asserts the box and the separation"},
    "messages/test_wire.py": {
        "decode_only_wire_error": "fails on any exception but WireError"},
    "conformance/test_conformance.py": {
        "_flier": "the dialogue raises DialogueError on any unexpected answer",
        "sitl_flights.result": "raises what the SITL dialogue raised"},
}

PYTEST_CHECKS = {"raises", "warns", "fail"}


def _called(func: ast.expr) -> str:
    """How a call names what it calls: ``f``, ``a.b``, or for ``f(x)(y)`` that of ``f(x)``."""
    if isinstance(func, ast.Call):
        return _called(func.func)
    return ast.unparse(func)


def _checks(test: ast.AST, helpers: set[str]) -> bool:
    for node in ast.walk(test):
        if isinstance(node, ast.Assert):
            return True
        if isinstance(node, ast.Call):
            name = _called(node.func)
            last = name.rsplit(".", 1)[-1]
            if (name in helpers or last.startswith("assert")
                    or (name.startswith("pytest.") and last in PYTEST_CHECKS)):
                return True
    return False


def _tests(tree: ast.Module) -> Iterator[ast.FunctionDef | ast.AsyncFunctionDef]:
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and (
                node.name.startswith("test")):  # what pytest collects
            yield node


def unchecked_tests(source: str, helpers: set[str]) -> list[str]:
    """The names of the ``test_*`` functions in ``source`` that check nothing."""
    return [test.name for test in _tests(ast.parse(source))
            if not _checks(test, helpers)]


def test_every_test_in_the_suite_checks_something() -> None:
    unchecked = []
    for path in sorted(TESTS.rglob("test_*.py")):
        where = path.relative_to(TESTS).as_posix()
        helpers = set(ASSERTING_HELPERS.get(where, {}))
        unchecked += [f"{where}::{name}"
                      for name in unchecked_tests(path.read_text(), helpers)]
    assert unchecked == [], ("tests that check nothing (give them an assertion, or list the "
                             f"helper that checks in ASSERTING_HELPERS): {unchecked}")


@pytest.mark.parametrize("where", sorted(ASSERTING_HELPERS))
def test_every_listed_helper_is_still_called_by_a_test_of_its_file(where: str) -> None:
    tree = ast.parse((TESTS / where).read_text())
    called = {_called(node.func) for test in _tests(tree) for node in ast.walk(test)
              if isinstance(node, ast.Call)}
    assert set(ASSERTING_HELPERS[where]) <= called, set(ASSERTING_HELPERS[where]) - called


def test_the_scan_finds_a_test_that_only_runs_code() -> None:
    source = '''
def test_runs() -> None:
    make_something(1)
    pytest.approx(1.0)

def test_asserts() -> None:
    assert make_something(1)

async def test_raises() -> None:
    with pytest.raises(ValueError):
        make_something(-1)

def test_numpy() -> None:
    np.testing.assert_array_equal(make_something(1), 1)

def test_helper() -> None:
    checked(make_something(1))

def test_helper_of_a_fixture(fixture) -> None:
    fixture.result(1)

def test_inside_a_nested_check() -> None:
    def check():
        assert make_something(1)
    wait(check)

class TestGrouped:
    def test_method_runs(self) -> None:
        make_something(2)
'''
    assert unchecked_tests(source, {"checked", "fixture.result"}) == [
        "test_runs", "test_method_runs"]
    assert unchecked_tests(source, set()) == [
        "test_runs", "test_helper", "test_helper_of_a_fixture", "test_method_runs"]
