"""One exception tree: every error class of swarm and sim_world derives from VigilError, and
what ends an executable maps to its exit code in one table (``swarm.errors.exit_code``)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from pathlib import Path

import pytest

import sim_world
import swarm
from swarm.errors import (
    EXIT_END_MISSION,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_USAGE,
    UsageError,
    VigilError,
    exit_code,
)

# Control flow, not errors: the world said the mission is over (the agent's loop ends).
NOT_ERRORS = {"swarm.agent.process.MissionEnded"}


def _project_modules() -> list[str]:
    names = []
    for package in (swarm, sim_world):
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            names.append(info.name)
    return names


def _exception_classes() -> dict[str, type[BaseException]]:
    """Every exception class defined in swarm and sim_world, by qualified name."""
    found = {}
    for name in _project_modules():
        for _, cls in inspect.getmembers(importlib.import_module(name), inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == name:
                found[f"{name}.{cls.__name__}"] = cls
    return found


def test_every_exception_class_of_the_project_derives_from_the_root() -> None:
    found = _exception_classes()
    assert len(found) >= 13, sorted(found)  # the classes there are today, at least
    strays = sorted(qualified for qualified, cls in found.items()
                    if not issubclass(cls, VigilError) and qualified not in NOT_ERRORS)
    assert strays == [], strays


# -- exit codes: one table ---------------------------------------------------------------------

USAGE = {"swarm.scenario.config.ConfigError", "swarm.models.kinematics.InitialPlacementError",
         "swarm.mavlink.signing.SigningKeyError", "swarm.net.security.SecurityError",
         "swarm.mavlink.sitl.FirmwareError", "swarm.runs.failed_qp.FailedQpFileError",
         "swarm.agent.exchange.ExchangeError", "swarm.scenario.overrides.OverrideError",
         "swarm.sweep.spec.SweepError", "swarm.sweep.results.ResultsError",
         "swarm.observe.live_view.LiveViewAddressError"}
EXECUTABLES = ("swarm.launch.cli", "swarm.agent.cli", "sim_world.cli", "sim_world.vehicles_cli",
               "swarm.observe.report_cli", "swarm.observe.dashboard", "swarm.agent.process",
               "sim_world.world", "swarm.runs.failed_qp", "swarm.observe.observe_cli",
               "swarm.sweep.cli")


def test_exit_codes_come_from_one_table() -> None:
    """Input that cannot be used exits 2 (the UsageError branch of the tree), every other
    error of ours 1, an interrupt 130, anything else (a bug) 1."""
    classes = {name: cls for name, cls in _exception_classes().items()
               if issubclass(cls, VigilError)}
    usage = {name for name, cls in classes.items() if issubclass(cls, UsageError)}
    assert usage - {"swarm.errors.UsageError"} == USAGE
    for name, cls in classes.items():
        error = cls.__new__(cls)
        assert exit_code(error) == (EXIT_USAGE if name in usage else EXIT_FAILED), name
    assert exit_code(KeyboardInterrupt()) == EXIT_INTERRUPTED == 130
    assert exit_code(RuntimeError("a bug")) == EXIT_FAILED == 1
    assert (EXIT_OK, EXIT_USAGE, EXIT_END_MISSION) == (0, 2, 3)


@pytest.mark.parametrize("module", EXECUTABLES)
def test_no_executable_writes_an_exit_code_as_a_number(module: str) -> None:
    """The mains and the process runners return the named codes of ``swarm.errors``: no
    ``return 1`` and no ``fail(prog, message, 1)``, so the table above is the only one."""
    tree = ast.parse(Path(importlib.import_module(module).__file__).read_text())
    numbers = [node.lineno for node in ast.walk(tree)
               if (isinstance(node, ast.Return) and isinstance(node.value, ast.Constant)
                   and type(node.value.value) is int)
               or (isinstance(node, ast.Call) and getattr(node.func, "id", "") == "fail"
                   and len(node.args) == 3 and isinstance(node.args[2], ast.Constant))]
    assert numbers == [], f"{module}: exit codes written as numbers at lines {numbers}"
