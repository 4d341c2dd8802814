"""One exception tree: every error class of swarm and sim_world derives from VigilError."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import sim_world
import swarm
from swarm.errors import VigilError

# Control flow, not errors: the world said the mission is over (the agent's loop ends).
NOT_ERRORS = {"swarm.agent.process.MissionEnded"}


def _project_modules() -> list[str]:
    names = []
    for package in (swarm, sim_world):
        for info in pkgutil.walk_packages(package.__path__, f"{package.__name__}."):
            names.append(info.name)
    return names


def test_every_exception_class_of_the_project_derives_from_the_root() -> None:
    found = {}
    for name in _project_modules():
        module = importlib.import_module(name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if issubclass(cls, BaseException) and cls.__module__ == name:
                found[f"{name}.{cls.__name__}"] = cls
    assert len(found) >= 13, sorted(found)  # the classes there are today, at least
    strays = sorted(qualified for qualified, cls in found.items()
                    if not issubclass(cls, VigilError) and qualified not in NOT_ERRORS)
    assert strays == [], strays
