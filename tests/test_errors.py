"""One exception tree: every error class of swarm and sim_world derives from VigilError, and
what ends an executable maps to its exit code in one table (``swarm.errors.exit_code``)."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import subprocess
import sys
from collections.abc import Callable
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
         "swarm.observe.live_view.LiveViewAddressError", "swarm.net.session.EndpointError",
         "swarm.launch.launcher.LaunchOptionsError", "sim_world.fleet.MavlinkHostsError",
         "swarm.observe.recording.schema.RecordingFileError", "swarm.sweep.driver.SchedulerError"}
# Every command line (the [project.scripts], the python -m mains, the tools) and the process
# runners behind them.
ENTRY_POINTS = ("swarm.launch.cli", "swarm.agent.cli", "sim_world.cli", "sim_world.vehicles_cli",
                "swarm.observe.report_cli", "swarm.observe.dashboard", "swarm.runs.failed_qp",
                "swarm.observe.observe_cli", "swarm.sweep.cli", "swarm.observe.layout",
                "tools.config_reference", "tools.px4_event_names", "tools.render_scene",
                "tools.mutation")
EXECUTABLES = (*ENTRY_POINTS, "swarm.agent.process", "sim_world.world")
ROOT = Path(__file__).resolve().parents[1]


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
    # The codes live on the two roots only: a class of ours does not pick its own.
    assert {name for name, cls in classes.items() if "exit_status" in vars(cls)} == {
        "swarm.errors.VigilError", "swarm.errors.UsageError"}
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


def test_every_command_line_ends_through_the_one_root() -> None:
    """Each ``main`` hands its body to ``run_main`` (which catches ``VigilError``), and no
    command line names one of our error classes in an ``except`` of its own: a class of ours
    cannot be left out of a list. The launcher's run names the root itself (it keeps the log
    directory of a failed run, after saying why)."""
    ours = {cls.__name__ for cls in _exception_classes().values()} - {"VigilError"}
    for module in ENTRY_POINTS:
        tree = ast.parse(Path(importlib.import_module(module).__file__).read_text())
        calls = {node.func.id for node in ast.walk(tree)
                 if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
        named = sorted({name.id for handler in ast.walk(tree)
                        if isinstance(handler, ast.ExceptHandler) and handler.type is not None
                        for name in ast.walk(handler.type)
                        if isinstance(name, ast.Name) and name.id in ours})
        assert "run_main" in calls or module == "swarm.observe.dashboard", module
        assert named == [], f"{module} catches {named}"


# -- bad input to each command line: one line on stderr, exit 2 ---------------------------------

CASE1 = str(ROOT / "configs" / "case1.toml")


def _bad_inputs(tmp: Path) -> dict[str, tuple[str, list[str], str]]:
    """Per entry point: (prog, a command line it cannot use, a fragment of the line it says)."""
    (tmp / "empty").mkdir()
    return {
        "swarm.launch.cli": ("launch-swarm", [CASE1, "--mode", "realtime", "--kill-agent",
                                              "9@1"], "--kill-agent 9@1: no drone 9"),
        "swarm.agent.cli": ("swarm-agent", ["--id", "0", "--config", CASE1, "--connect",
                                            "tls/127.0.0.1:7447"], "tls needs certificates"),
        "sim_world.cli": ("sim-world", [CASE1, "--mavlink-host", "a,b"],
                          "--mavlink-host 'a,b': give one address"),
        "sim_world.vehicles_cli": ("sim-vehicles", [CASE1, "--gcs-control"],
                                   "--gcs-control needs --gcs"),
        "swarm.observe.report_cli": ("swarm-report", [str(tmp / "none")],
                                     "none: no such file or directory"),
        "swarm.observe.dashboard": ("swarm-dashboard", [CASE1, "--connect", "tcp/nohost"],
                                    "zenoh connect endpoint 'tcp/nohost': expected"),
        "swarm.runs.failed_qp": ("failed_qp", [str(tmp / "none.npz")], "none.npz"),
        "swarm.observe.observe_cli": ("swarm-observe", [CASE1, "--connect",
                                                        "tls/127.0.0.1:7447"],
                                      "tls needs certificates"),
        "swarm.sweep.cli": ("swarm-sweep", ["report", str(tmp / "empty")],
                            "report: " + str(tmp / "empty" / "results.jsonl")),
        "swarm.observe.layout": ("layout", [str(tmp / "none.toml"), str(tmp / "out.json")],
                                 "config error: "),
        "tools.config_reference": ("config_reference", ["--write", "--check"],
                                   "not allowed with argument"),
        "tools.px4_event_names": ("px4_event_names", [str(tmp / "empty")],
                                  "not a PX4-Autopilot checkout"),
        "tools.render_scene": ("render_scene", [str(tmp / "empty"), str(tmp / "out.png")],
                               "no run.mcap in this directory"),
        "tools.mutation": ("mutation", ["--groups", "nope"], "--groups takes"),
    }


def _in_process(module: str, argv: list[str]) -> int:
    main: Callable[[list[str]], int] = importlib.import_module(module).main
    try:
        return main(argv)
    except SystemExit as exit_:  # argparse's refusal
        return int(exit_.code or 0)


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_bad_input_to_each_command_line_is_one_line_and_the_usage_code(
        module: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    prog, argv, said = _bad_inputs(tmp_path)[module]
    if module == "swarm.agent.cli":  # it sets pymavlink's environment at import: not in here
        done = subprocess.run([sys.executable, "-m", module, *argv], capture_output=True,
                              text=True, timeout=60, cwd=ROOT, check=False)
        code, out, err = done.returncode, done.stdout, done.stderr
    else:
        code = _in_process(module, argv)
        out, err = capsys.readouterr()
    assert code == EXIT_USAGE, err
    assert len(err.splitlines()) == 1 and err.startswith(f"{prog}: ") and said in err, err
    assert "Traceback" not in out + err
