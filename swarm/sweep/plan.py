"""A sweep file read and every point validated: the tasks, before anything runs.

Each point's config is built as ``launch-swarm --set`` builds one (``load_config`` with the
point's overrides, the SITL flavour's fitted tracking margins for a SITL mode), so any bad key
or value is the one-line ``ConfigError`` a file gives, naming the point.
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from swarm.mavlink.sitl import ENV_VARIABLE, firmware_from_env
from swarm.observe.recording.schema import git_commit, package_version
from swarm.scenario.config import (
    ConfigError,
    config_to_data,
    load_config,
    read_toml_file,
    realtime_only_reason,
)
from swarm.sweep.rows import MissionTask, mission_key
from swarm.sweep.spec import KILL_AXIS, KILL_DRONE, SweepError, SweepSpec, expand, parse_spec

RECORDINGS = "recordings"
CODE_VERSION_VARIABLE = "VIGIL_CODE_VERSION"


@dataclass(frozen=True)
class SweepPlan:
    spec: SweepSpec
    path: Path  # the sweep file
    base: Path  # the scenario file, resolved
    tasks: tuple[MissionTask, ...]
    code_version: str


@cache
def code_version() -> str:
    """The package version and the checkout it runs from (``git describe --always
    --dirty``: the commit, marked when the tree has changes), e.g. "0.1.0 1892c80-dirty";
    or ``$VIGIL_CODE_VERSION`` when set (a sweep resumed after a commit that changes no
    mission, e.g. a README edit, or tests in a tree others commit to)."""
    pinned = os.environ.get(CODE_VERSION_VARIABLE, "").strip()
    if pinned:
        return pinned
    version = package_version()
    root = Path(__file__).resolve().parents[2]
    try:
        described = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True, text=True, timeout=10, check=False)
        if described.returncode == 0 and described.stdout.strip():
            return f"{version} {described.stdout.strip()}"
    except (OSError, subprocess.SubprocessError):
        pass
    commit = git_commit()
    return version if commit == "unknown" else f"{version} {commit[:12]}"


def read_spec(path: Path) -> SweepSpec:
    return parse_spec(read_toml_file(path, SweepError, "a sweep .toml file"), str(path))


def plan_sweep(path: Path, out: Path, *, stop_event: str | None = None,
               check_firmware: bool = True) -> SweepPlan:
    """Read the sweep file and validate every point; SweepError or ConfigError, one line.
    ``check_firmware``: a SITL mode needs its firmware's environment variable here (a local
    cluster; a remote worker says so in its rows)."""
    spec = read_spec(path)
    base = (path.parent / spec.base).resolve()
    if not base.is_file():
        raise SweepError(f"{path}: base: {base} is not a scenario file")
    kills_agents = bool(spec.kill_agents) or any(
        any(values) for key, values in spec.axes if key == KILL_AXIS)
    reason = realtime_only_reason(
        load_config(base).vehicles, mode="realtime" if spec.sitl else spec.mode,
        inprocess=spec.mode == "inprocess", external=spec.sitl is not None,
        kills_agents=kills_agents)
    if reason is not None:
        raise SweepError(f"{path}: mode = {spec.mode!r}: {reason}")
    if spec.sitl is not None and check_firmware and firmware_from_env(spec.sitl) is None:
        raise SweepError(f"{path}: mode = {spec.mode!r}: ${ENV_VARIABLE[spec.sitl]} is not "
                         f"set (the SITL build each worker starts)")
    version = code_version()
    tasks = []
    seen: set[str] = set()
    for point in expand(spec):
        try:
            config = load_config(base, autopilot=spec.sitl, overrides=point.overrides)
            config = config.with_seed(point.seed)
            vehicles = config.vehicles
            mode_problem = realtime_only_reason(
                vehicles, mode="realtime" if spec.sitl else spec.mode,
                inprocess=spec.mode == "inprocess", external=spec.sitl is not None,
                kills_agents=bool(spec.kill_agents) or point.kill_at_s is not None)
            if mode_problem is not None:
                raise ConfigError(mode_problem)
            for drone, _time_s in spec.kill_agents:
                if drone >= config.swarm.n_drones:
                    raise ConfigError(f"kill_agents: drone {drone} out of range "
                                      f"0..{config.swarm.n_drones - 1}")
            if point.kill_at_s is not None and point.kill_at_s >= config.scenario.duration_s:
                raise ConfigError(f"{KILL_AXIS} = {point.kill_at_s:g}: not before the "
                                  f"mission's end ({config.scenario.duration_s:g} s)")
        except ConfigError as err:
            raise SweepError(f"{path}: point {point.describe()}: {err}") from None
        data = config_to_data(config)
        losses: list[tuple[tuple[int, float], ...] | None] = [None]
        if point.kill_at_s is not None:
            losses = [((drone, point.kill_at_s),) for drone in range(config.swarm.n_drones)]
        elif any(key == KILL_AXIS for key in spec.axis_keys):
            losses = [()]  # the cell without a loss
        for loss in losses:
            kills = spec.kill_agents if loss is None else loss
            params = point.params if loss is None else point.params | {
                KILL_DRONE: loss[0][0] if loss else None}
            key = mission_key(data, point.seed, spec.mode, kills, version)
            if key in seen:
                raise SweepError(f"{path}: point {point.describe()}: the same mission as an "
                                 f"earlier point (an axis value that changes nothing?)")
            seen.add(key)
            tasks.append(MissionTask(
                key=key, params=params, axes=spec.axis_keys, seed=point.seed,
                mode=spec.mode, config_data=data, source=str(base), code_version=version,
                kill_agents=kills,
                record_dir=str((out / RECORDINGS / key).resolve()) if spec.record else None,
                timeout_s=spec.timeout_s, stop_event=stop_event, keep=spec.keep))
    return SweepPlan(spec=spec, path=path, base=base, tasks=tuple(tasks), code_version=version)


def local_workers(spec: SweepSpec) -> int:
    """The local cluster's size: one worker per CPU this process may use; one for wall-clock
    missions (realtime, SITL), whose timing two at once on one machine would disturb."""
    if spec.mode in ("inprocess", "lockstep"):
        return max(1, len(os.sched_getaffinity(0)))
    return 1
