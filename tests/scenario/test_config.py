"""Scenario configuration: shipped configs (SPEC §11) and the invalid-config corpus.

Every ConfigError message must be ONE line naming the key. ``tests/configs_invalid/*.toml``
holds one defect each (a copy of configs/case1.toml, or case3 for out_and_back defects) and a
first line ``# expect: <substring>`` that the error message must contain.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import subprocess
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from swarm.core.params import ConsensusGains, ControlParams, GramianParams, PerceptionParams
from swarm.models.camera import CameraParams
from swarm.models.targets import (
    LinearTrajectory,
    OutAndBackTrajectory,
    SinusoidTrajectory,
    ramp,
    ramp_distance,
)
from swarm.scenario.config import (
    ConfigError,
    ScenarioConfig,
    config_from_dict,
    load_config,
    realtime_only_reason,
)
from tests.helpers.cli_tools import launch_swarm_in_process, run_cli

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
CORPUS_DIR = ROOT / "tests" / "configs_invalid"
CORPUS = sorted(CORPUS_DIR.glob("*.toml"))
CASES = ("case1", "case2", "case3")

RING_AND_CHORDS = {frozenset(e) for e in
                   [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 3), (1, 4)]}


def load_case(name: str) -> ScenarioConfig:
    return load_config(CONFIGS / f"{name}.toml")


def raw_case(name: str) -> dict:
    with (CONFIGS / f"{name}.toml").open("rb") as handle:
        return tomllib.load(handle)


def expected_substring(path: Path) -> str:
    first_line = path.read_bytes().split(b"\n", 1)[0].decode("utf-8")
    assert first_line.startswith("# expect: "), f"{path.name}: first line must be '# expect: …'"
    expect = first_line.removeprefix("# expect: ").strip()
    assert expect
    return expect


# -- the shipped configs -------------------------------------------------------------------


@pytest.mark.parametrize("name", CASES)
def test_shipped_config_carries_the_spec_values(name: str) -> None:
    cfg = load_case(name)
    assert cfg.source == str(CONFIGS / f"{name}.toml")
    assert cfg.scenario.name == name
    assert cfg.scenario.dt_s == 0.02
    assert cfg.scenario.seed == 0
    # N = 6, 4×4×2 m box centred at [0, 0, 3.5] (SPEC §11).
    assert cfg.swarm.n_drones == 6
    assert cfg.swarm.initial_box_center_m == (0.0, 0.0, 3.5)
    assert cfg.swarm.initial_box_size_m == (4.0, 4.0, 2.0)
    # Graph: ring 0-1-2-3-4-5-0 plus chords 0-3 and 1-4 (thesis 1-4 and 2-5).
    assert {frozenset(e) for e in cfg.swarm.edges} == RING_AND_CHORDS
    assert len(cfg.swarm.edges) == 8
    graph = cfg.swarm.graph
    assert [graph.degree(i) for i in range(6)] == [3, 3, 2, 3, 3, 2]
    assert graph.is_connected()
    # Table 4.1.
    assert cfg.gramian.forgetting == 0.6  # ρ
    assert cfg.gramian.epsilon == 0.05  # ε
    assert cfg.control.gamma == 0.5  # γ
    assert cfg.control.slack_weight == 1e6  # K_δ
    assert cfg.estimation.consensus_rounds == 1  # K
    assert cfg.estimation.process_noise == 0.01  # Q = 0.01 I
    assert cfg.estimation.info_gain == 1.0  # b
    assert cfg.estimation.initial_offset_m == 0.5
    assert cfg.estimation.consensus_weights == "metropolis"
    assert cfg.estimation.model == "double_integrator"
    # Table 4.2: PI consensus gains (ζ, K_p, K_i).
    assert cfg.gramian.projector_consensus == ConsensusGains(zeta=4.0, kp=5.0, ki=3.0)
    assert cfg.gramian.weight_consensus == ConsensusGains(zeta=8.0, kp=12.0, ki=6.0)
    assert cfg.gramian.smooth_min_exponent == -10.0
    # Fig. 3.1: perception and camera.
    p = cfg.perception
    assert (p.d_min_th_m, p.d_max_th_m, p.sigma_dmin_sq_m2, p.sigma_dmax_sq_m2,
            p.alpha_th_deg, p.sigma_beta_sq) == (1.0, 6.0, 0.04, 1.8, 35.0, 0.015)
    c = cfg.camera
    assert (c.range_min_m, c.range_max_m, c.half_fov_deg, c.image_noise_std) == (
        0.5, 8.0, 50.0, 0.005)
    # Control (SPEC §8-§9).
    assert cfg.control.start_s == 1.0
    assert cfg.control.u_max_m_s == 3.0
    assert cfg.control.weight_floor == 1e-3
    assert cfg.control.collision_distance_m == 0.5
    # Targets start at [±0.1, 0, 0] and ramp over 5 s.
    for target in cfg.targets:
        assert abs(target.start_m[0]) == 0.1
        assert target.start_m[1:] == (0.0, 0.0)
        assert target.ramp_s == 5.0


@pytest.mark.parametrize("name", CASES)
def test_shipped_config_sections_equal_the_code_defaults(name: str) -> None:
    """configs/*.toml spell out the defaults of the parameter classes (one source of truth)."""
    cfg = load_case(name)
    assert cfg.camera == CameraParams()
    assert cfg.perception == PerceptionParams()
    assert cfg.gramian == GramianParams()
    defaults = ControlParams()
    for field in ("start_s", "gamma", "slack_weight", "weight_floor", "u_max_m_s",
                  "collision_distance_m", "collision_radius_m", "collision_gain"):
        assert getattr(cfg.control, field) == getattr(defaults, field), field


@pytest.mark.parametrize("name, duration, qp, task, n_targets", [
    ("case1", 30.0, "hard", "zero", 1),
    ("case2", 50.0, "relaxed", "zero", 2),
    ("case3", 45.0, "relaxed", "bearing_formation", 1),
])
def test_shipped_config_case_specifics(name: str, duration: float, qp: str, task: str,
                                       n_targets: int) -> None:
    cfg = load_case(name)
    assert cfg.scenario.duration_s == duration
    assert cfg.n_steps == round(duration / 0.02)
    assert cfg.control.qp == qp
    assert cfg.control.task == task
    assert len(cfg.targets) == n_targets


def test_case1_target_is_the_ramped_line() -> None:
    (target,) = load_case("case1").targets
    trajectory = target.build()
    assert isinstance(trajectory, LinearTrajectory)
    assert trajectory == LinearTrajectory((0.1, 0.0, 0.0), (0.2, 0.3, 0.0), 5.0)
    np.testing.assert_array_equal(trajectory.velocity(10.0), [0.2, 0.3, 0.0])


def test_case2_targets_are_the_line_and_the_spec_sinusoid() -> None:
    first, second = load_case("case2").targets
    assert first.build() == LinearTrajectory((0.1, 0.0, 0.0), (0.2, 0.3, 0.0), 5.0)
    wave = second.build()
    assert isinstance(wave, SinusoidTrajectory)
    for t in np.linspace(0.0, 50.0, 101):
        expected = [-0.1 - 0.2 * ramp_distance(t, 5.0), -2.2 * math.sin(0.15 * t), 0.0]
        np.testing.assert_allclose(wave.position(t), expected, rtol=0, atol=1e-14)
        np.testing.assert_allclose(
            wave.velocity(t), [-0.2 * ramp(t, 5.0), -0.33 * math.cos(0.15 * t), 0.0],
            rtol=0, atol=1e-14)


def test_case3_target_goes_out_until_25_s_and_is_back_at_40_s() -> None:
    (target,) = load_case("case3").targets
    trajectory = target.build()
    assert isinstance(trajectory, OutAndBackTrajectory)
    assert (trajectory.turn_s, trajectory.back_s, trajectory.ramp_s) == (25.0, 40.0, 5.0)
    np.testing.assert_allclose(trajectory.position(45.0), [0.1, 0.0, 0.0], rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", CASES)
def test_config_from_dict_round_trip_and_immutability(name: str) -> None:
    cfg = load_case(name)
    again = config_from_dict(raw_case(name))
    assert again == cfg  # ``source`` is not compared
    assert again.source == "<memory>"
    with pytest.raises(AttributeError):
        cfg.scenario.duration_s = 1.0  # type: ignore[misc]


def test_with_duration_changes_only_the_duration() -> None:
    cfg = load_case("case1")
    short = cfg.with_duration(2.0)
    assert short.scenario.duration_s == 2.0
    assert short.n_steps == 100
    assert short.swarm == cfg.swarm and short.gramian == cfg.gramian
    assert cfg.scenario.duration_s == 30.0
    with pytest.raises(ConfigError, match=r"control\.start_s"):
        cfg.with_duration(0.5)  # before control.start_s


# -- every numeric leaf: NaN, ±inf, a string, a boolean ------------------------------------


def _leaves(node: object, path: str = ""):
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, f"{path}.{key}" if path else key)
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _leaves(value, f"{path}[{index}]")
    else:
        yield path, node


def _set_leaf(data: dict, path: str, value: object) -> None:
    tokens = re.findall(r"[^.\[\]]+", path)
    node: object = data
    for token in tokens[:-1]:
        node = node[int(token)] if isinstance(node, list) else node[token]  # type: ignore[index]
    last = tokens[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value  # type: ignore[index]


@pytest.mark.parametrize("name", ["case2", "case3", "case2_envelope", "case2_range"])
def test_every_leaf_with_a_bad_value_is_refused_naming_its_key(name: str) -> None:
    """78-80 leaves × 5 bad values: each gives a one-line ConfigError naming the key path.

    Vector elements are named by the vector (``swarm.initial_box_center_m``), edge ids by the
    edge list; nothing else may escape (no TypeError, no silent acceptance).
    """
    base = raw_case(name)
    checked = 0
    for path, value in _leaves(base):
        bad_values: tuple[object, ...]
        if isinstance(value, str):
            # An empty string is an option left off (e.g. no signing key file): only its
            # type can be wrong; a set string also gets an unknown value.
            bad_values = (1.0, True) + (("no-such-" + value,) if value.strip() else ())
        else:
            bad_values = (math.nan, math.inf, -math.inf, "1.0", True)
        key = re.sub(r"\[\d+\](\[\d+\])?$", "", path)
        for bad in bad_values:
            if path == "scenario.name" and isinstance(bad, str):
                continue  # any non-empty name is valid
            data = copy.deepcopy(base)
            _set_leaf(data, path, bad)
            with pytest.raises(ConfigError) as info:
                config_from_dict(data)
            message = str(info.value)
            assert "\n" not in message, (path, bad, message)
            assert key in message, (path, bad, message)
            checked += 1
    assert checked > 300


# -- the invalid-config corpus -------------------------------------------------------------


def test_corpus_is_large_and_well_formed() -> None:
    assert len(CORPUS) >= 30
    for path in CORPUS:
        expected_substring(path)


@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_corpus_file_is_refused_with_a_one_line_message_naming_the_key(path: Path) -> None:
    expect = expected_substring(path)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert len(message.splitlines()) == 1 and "\n" not in message and "\r" not in message, message
    assert message.startswith(f"{path}: "), message
    assert expect in message, message
    # ConfigError is a ValueError, so callers that only know ValueError still catch it.
    assert isinstance(info.value, ValueError)


@pytest.fixture(scope="module")
def corpus_cli_results() -> dict[Path, subprocess.CompletedProcess[str]]:
    """``launch-swarm <file> --inprocess`` for every corpus file, run by its ``main`` here (a
    process each cost 17-26 s of suite; ``test_corpus_files_fail_the_same_way_as_processes``
    shows a process answers the same)."""
    return {path: launch_swarm_in_process(str(path), "--inprocess") for path in CORPUS}


def test_corpus_files_fail_the_same_way_as_processes(
        corpus_cli_results: dict[Path, subprocess.CompletedProcess[str]]) -> None:
    """``python -m swarm.launch.cli <file> --inprocess`` as a process, for a few corpus files: the
    same exit code, the same line, nothing else (the process boundary adds nothing)."""
    sample = CORPUS[::max(1, len(CORPUS) // 3)][:3]
    with ThreadPoolExecutor(max_workers=len(sample)) as pool:
        results = dict(zip(sample, pool.map(
            lambda p: run_cli(str(p), "--inprocess", timeout=60.0), sample), strict=True))
    for path, result in results.items():
        here = corpus_cli_results[path]
        assert (result.returncode, result.stdout, result.stderr) == (
            here.returncode, here.stdout, here.stderr), path


def _unwrapped(text: str) -> str:
    """Drop every whitespace character, so the text check does not depend on line breaks."""
    return "".join(text.split())


@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_corpus_file_makes_the_cli_exit_2_without_traceback(
        path: Path, corpus_cli_results: dict[Path, subprocess.CompletedProcess[str]]) -> None:
    result = corpus_cli_results[path]
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert "Traceback" not in result.stdout + result.stderr
    assert result.stdout == ""
    stderr = _unwrapped(result.stderr)
    assert stderr.startswith(_unwrapped("launch-swarm: config error: ")), result.stderr
    assert _unwrapped(expected_substring(path)) in stderr, result.stderr


@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_corpus_file_cli_error_is_exactly_one_line(
        path: Path, corpus_cli_results: dict[Path, subprocess.CompletedProcess[str]]) -> None:
    lines = [line for line in corpus_cli_results[path].stderr.splitlines() if line.strip()]
    assert len(lines) == 1, lines


# -- loading errors outside the corpus -----------------------------------------------------


def test_missing_file_and_directory_give_one_line_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file") as info:
        load_config(tmp_path / "nope.toml")
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="is a directory") as info:
        load_config(tmp_path)
    assert "\n" not in str(info.value)


def test_unknown_key_lists_the_known_keys_of_its_table() -> None:
    data = raw_case("case1")
    data["camera"]["focal_length"] = 1.0
    with pytest.raises(ConfigError, match=r"camera\.focal_length: unknown key") as info:
        config_from_dict(data)
    assert "range_min_m" in str(info.value)


def test_optional_sections_default_to_the_spec_values() -> None:
    data = raw_case("case1")
    for section in ("camera", "perception", "estimation", "gramian", "checks"):
        del data[section]
    cfg = config_from_dict(data)
    assert cfg.camera == CameraParams()
    assert cfg.gramian == GramianParams()
    assert cfg.perception == PerceptionParams()


def test_seventeen_targets_are_refused() -> None:
    data = raw_case("case1")
    data["targets"] = data["targets"] * 17
    with pytest.raises(ConfigError, match="targets: need 1 to 16"):
        config_from_dict(data)


# -- bugs (expected failures) --------------------------------------------------------------


def test_unknown_key_with_a_newline_still_gives_one_line() -> None:
    data = raw_case("case1")
    data["bad\nkey"] = 1
    with pytest.raises(ConfigError) as info:
        config_from_dict(data)
    assert "\n" not in str(info.value)


def test_enum_error_separates_key_and_reason() -> None:
    data = raw_case("case1")
    data["control"]["qp"] = "soft"
    with pytest.raises(ConfigError, match=r"^control\.qp: "):
        config_from_dict(data)


def test_box_too_small_message_shows_plain_numbers() -> None:
    with pytest.raises(ConfigError) as info:
        load_config(CORPUS_DIR / "initial_box_too_small.toml")
    assert "[0.5, 0.5, 0.5]" in str(info.value)


def test_with_duration_below_dt_raises_config_error() -> None:
    with pytest.raises(ConfigError, match="duration_s"):
        load_case("case1").with_duration(0.01)


def test_every_accepted_box_can_hold_its_drones() -> None:
    data = raw_case("case1")
    data["swarm"].update(n_drones=2, edges=[[0, 1]], initial_box_size_m=[1.0, 0.0, 0.0])
    with pytest.raises(ConfigError, match=r"swarm\.initial_box_size_m"):
        config_from_dict(data)


def test_a_resolved_config_reads_back_equal(tmp_path: Path) -> None:
    """launch-swarm hands its children the config it resolved (e.g. SITL origin offsets) as
    JSON: it must read back into an equal config, and a broken file is one line."""
    import dataclasses

    from swarm.scenario.config import write_resolved_config

    config = load_config(ROOT / "configs" / "case2.toml")
    config = dataclasses.replace(config, vehicles=dataclasses.replace(
        config.vehicles, flavour="ardupilot", response="arducopter",
        origin_offsets_m=tuple((float(i), -0.5 * i, 0.01) for i in range(6))))
    path = write_resolved_config(config, tmp_path / "config.json")
    assert load_config(path) == config
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    for name, expect in (("bad.json", "not valid JSON"), ("list.json", "expected a JSON object"),
                         ("missing.json", "no such file")):
        with pytest.raises(ConfigError) as info:
            load_config(tmp_path / name)
        assert expect in str(info.value) and "\n" not in str(info.value)


def _case1_data() -> dict:
    return tomllib.loads((CONFIGS / "case1.toml").read_text())


def test_tracking_margins_left_out_are_fitted_to_the_vehicles() -> None:
    """[control] tracking_error_bound_m_s and command_accel_limit_m_s2 left out: 0 (the
    thesis' QP) on ideal vehicles, the fitted values for the ArduCopter/PX4 responses and for
    real autopilots of a flavour (``autopilot=``); a value given is kept; a resolved config
    (every key written) reads back equal whatever the vehicles."""
    from swarm.scenario.config import TRACKING_DEFAULTS, config_to_data

    def tracking(config: ScenarioConfig) -> tuple[float, float]:
        return (config.control.tracking_error_bound_m_s,
                config.control.command_accel_limit_m_s2)

    for case in CASES:
        assert tracking(load_config(CONFIGS / f"{case}.toml")) == (0.0, 0.0)
    for response in ("arducopter", "px4"):
        data = _case1_data()
        data["vehicles"]["response"] = response
        assert tracking(config_from_dict(data)) == TRACKING_DEFAULTS[response]
    assert TRACKING_DEFAULTS["px4"][0] > 0 and TRACKING_DEFAULTS["arducopter"][0] > 0
    for autopilot, response in (("ardupilot", "arducopter"), ("px4", "px4")):
        fitted = config_from_dict(_case1_data(), autopilot=autopilot)
        assert tracking(fitted) == TRACKING_DEFAULTS[response]
        assert config_from_dict(config_to_data(fitted)) == fitted
    data = _case1_data()
    data["control"]["tracking_error_bound_m_s"] = 0.05
    assert tracking(config_from_dict(data, autopilot="px4")) == (0.05, TRACKING_DEFAULTS["px4"][1])


@pytest.mark.parametrize(("key", "value", "reason"), [
    ("tracking_error_bound_m_s", -0.1, "must be a finite number >= 0"),
    ("tracking_error_bound_m_s", 3.0, "must be below u_max_m_s"),
    ("command_accel_limit_m_s2", math.nan, "must be a finite number >= 0"),
])
def test_bad_tracking_margins_are_one_line_errors(key: str, value: float, reason: str) -> None:
    data = _case1_data()
    data["control"][key] = value
    with pytest.raises(ConfigError) as err:
        config_from_dict(data)
    message = str(err.value)
    assert f"control.{key}" in message and reason in message and "\n" not in message


@pytest.mark.parametrize("model, size", [("double_integrator", 6), ("single_integrator", 3)])
def test_every_process_builds_its_codec_from_the_config(model: str, size: int) -> None:
    """One place says how large a target's state is and what the processes speak: the
    estimator's own size (icf.state_dimension), N drones, M targets."""
    base = load_config(CONFIGS / "case2.toml")
    config = dataclasses.replace(base, estimation=dataclasses.replace(base.estimation,
                                                                      model=model))
    assert config.state_dimension == size
    codec = config.wire_codec()
    assert (codec.n_drones, codec.n_targets, codec.n_state) == (6, 2, size)


@pytest.mark.parametrize(("flags", "says"), [
    ({"external": True}, "real or external autopilots"),
    ({"restarts_agents": True}, "--agent-restarts needs --mode realtime"),
    ({"kills_agents": True}, "--kill-agent needs --mode realtime"),
    ({"faulty_consensus": True}, "--drop-consensus and --delay-consensus need"),
])
def test_the_mode_rules_hold_outside_realtime_only(flags: dict, says: str) -> None:
    """One home for what needs realtime (launch-swarm, sim-world, swarm-agent and the
    launcher's options all ask ``realtime_only_reason``)."""
    vehicles = load_config(CONFIGS / "case1.toml").vehicles
    assert realtime_only_reason(vehicles, mode="realtime", **flags) is None
    for mode, inprocess in (("lockstep", False), ("realtime", True)):
        reason = realtime_only_reason(vehicles, mode=mode, inprocess=inprocess, **flags)
        assert reason is not None and says in reason and "\n" not in reason
    assert realtime_only_reason(vehicles, mode="lockstep") is None
    ground = dataclasses.replace(vehicles, start="ground")
    assert "vehicles.start = 'ground'" in realtime_only_reason(ground, mode="lockstep")


# -- what a config leaves out, and the resolved config -------------------------------------

REQUIRED_SECTIONS = ("scenario", "swarm", "targets")
OPTIONAL_SECTIONS = ("camera", "perception", "estimation", "gramian", "control", "checks",
                     "safety", "vehicles", "runtime", "security")


def _field_names(schema: type) -> set[str]:
    return {f.name for f in dataclasses.fields(schema) if f.init and f.name != "source"}


def _assert_every_key(data: object, schema: object, path: str = "") -> int:
    """Every field of every dataclass in ``schema`` is a key of ``data``; the keys counted."""
    import typing

    origin = typing.get_origin(schema)
    if origin is tuple and isinstance(data, list):
        args = typing.get_args(schema)
        item_schema = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        return sum(_assert_every_key(item, item_schema, f"{path}[{k}]")
                   for k, item in enumerate(data)) if item_schema is not None else 0
    if not (dataclasses.is_dataclass(schema) and isinstance(schema, type)):
        return 0
    assert isinstance(data, dict), path
    assert set(data) == _field_names(schema), (path, sorted(_field_names(schema) - set(data)))
    hints = typing.get_type_hints(schema)
    return len(data) + sum(_assert_every_key(value, hints[key], f"{path}.{key}")
                           for key, value in data.items())


def test_only_scenario_swarm_and_targets_are_required() -> None:
    """Each other section left out takes its defaults (the thesis' values: case1 differs from
    them in control.qp only); a required one left out says which ones are required."""
    from swarm.scenario.config import config_to_data

    full = load_case("case1")
    minimal = config_from_dict({name: raw_case("case1")[name] for name in REQUIRED_SECTIONS})
    assert minimal == dataclasses.replace(full, control=dataclasses.replace(full.control,
                                                                              qp="relaxed"))
    for name in OPTIONAL_SECTIONS:
        data = raw_case("case1")
        data.pop(name, None)
        assert config_to_data(config_from_dict(data))[name] == \
            config_to_data(minimal)[name], name
    for name in REQUIRED_SECTIONS:
        data = raw_case("case1")
        del data[name]
        with pytest.raises(ConfigError) as info:
            config_from_dict(data)
        message = str(info.value)
        assert message.startswith(f"Object missing required field `{name}`: a config needs "
                                  f"[scenario], [swarm] and [[targets]]"), message
        assert "\n" not in message


@pytest.mark.parametrize("keep", [REQUIRED_SECTIONS, (*REQUIRED_SECTIONS, "checks", "control")])
def test_the_resolved_config_holds_every_key_the_defaults_included(keep: tuple[str, ...]) -> None:
    """What a recording keeps (``config_to_data``) names every key of every section, also
    the keys and sections the file left out (case1 gives no checks.envelope_tolerance_m, no
    target amplitude_m; msgspec alone wrote only the keys given) and the tracking margins
    fitted to the vehicles."""
    from swarm.scenario.config import TRACKING_DEFAULTS, config_to_data

    raw = raw_case("case1")
    data = {name: raw[name] for name in keep}
    data.setdefault("vehicles", {})["response"] = "px4"
    config = config_from_dict(data)
    resolved = config_to_data(config)
    assert _assert_every_key(resolved, ScenarioConfig) > 100
    assert resolved["checks"]["envelope_tolerance_m"] == 5e-3
    assert resolved["targets"][0]["amplitude_m"] == [0.0, 0.0, 0.0]
    assert (resolved["control"]["tracking_error_bound_m_s"],
            resolved["control"]["command_accel_limit_m_s2"]) == TRACKING_DEFAULTS["px4"]
    assert config_from_dict(resolved) == config


def _shipped_configs() -> list[Path]:
    return sorted([*CONFIGS.glob("*.toml"), *CONFIGS.glob("bench/*.toml"),
                   *(ROOT / "tests" / "configs").glob("*.toml")])


@pytest.mark.parametrize("path", _shipped_configs(), ids=lambda p: p.stem)
def test_the_resolved_config_as_toml_reads_back_equal(path: Path, tmp_path: Path) -> None:
    from swarm.scenario.config import config_to_data, config_to_toml

    config = load_config(path)
    text = config_to_toml(config)
    assert text.startswith(f"# The resolved config of {path}: ")
    (tmp_path / "resolved.toml").write_text(text)
    again = load_config(tmp_path / "resolved.toml")
    assert again == config
    assert config_to_data(again) == config_to_data(config)


def test_the_toml_text_keeps_odd_strings_and_says_the_failsafe_delay() -> None:
    from swarm.scenario.config import config_to_toml

    data = _case1_data()
    data["scenario"]["name"] = 'a "case"\twith \\ ☃, \x7f and \U0001F681'
    data["vehicles"]["flavour"] = "ardupilot"
    data["safety"] = {"floor_m": 1.0, "keep_out": [{"center_m": [9.0, 9.0], "radius_m": 1.0}]}
    config = config_from_dict(data)
    text = config_to_toml(config)
    assert config_from_dict(tomllib.loads(text)) == config
    assert "# vehicles.setpoint_timeout_s = 0: the flavour's default, 3 s (ardupilot)." in text
    [unset] = [line for line in text.splitlines() if line.startswith("# Not set: ")]
    assert "safety.ceiling_m" in unset and "safety.floor_m" not in unset
    assert tomllib.loads(text)["safety"]["keep_out"] == [{"center_m": [9.0, 9.0],
                                                          "radius_m": 1.0}]


def test_print_config_shows_what_the_run_would_use(tmp_path: Path) -> None:
    """``launch-swarm --print-config``: TOML on stdout, exit 0, nothing started; the file's
    left-out sections filled in, --seed and --duration applied, and with --mavlink the
    tracking margins fitted to that autopilot flavour."""
    from swarm.scenario.config import TRACKING_DEFAULTS

    minimal = tmp_path / "minimal.toml"
    raw = raw_case("case1")
    minimal.write_text("\n".join(
        ["[scenario]", 'name = "minimal"', "duration_s = 30.0", "[swarm]", "n_drones = 6",
         f"edges = {raw['swarm']['edges']}", "[[targets]]", 'trajectory = "linear"',
         "start_m = [0.1, 0.0, 0.0]"]) + "\n")
    result = launch_swarm_in_process(str(minimal), "--print-config", "--seed", "7",
                                     "--duration", "3")
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    printed = tomllib.loads(result.stdout)
    assert printed["scenario"] == {"name": "minimal", "duration_s": 3.0, "dt_s": 0.02,
                                   "seed": 7}
    assert printed["checks"] == {"lambda_tolerance": 0.005, "collision_tolerance_m": 0.001,
                                 "envelope_tolerance_m": 0.005}
    expected = load_config(minimal).with_duration(3.0).with_seed(7)
    assert config_from_dict(printed) == expected
    urls = [arg for i in range(6) for arg in ("--mavlink", f"{i}=udpin:127.0.0.1:{14540 + i}")]
    result = launch_swarm_in_process(str(CONFIGS / "case1.toml"), "--print-config", *urls)
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
    control = tomllib.loads(result.stdout)["control"]
    assert (control["tracking_error_bound_m_s"], control["command_accel_limit_m_s2"]) == \
        TRACKING_DEFAULTS["px4"]
    assert 'mavlink_urls = ["udpin:127.0.0.1:14540", ' in result.stdout
    bad = launch_swarm_in_process(str(CORPUS_DIR / "target_above_start_box.toml"),
                                  "--print-config")
    assert (bad.returncode, bad.stdout) == (2, "") and len(bad.stderr.splitlines()) == 1


# -- geometry that cannot work -------------------------------------------------------------


@pytest.mark.parametrize(("start_m", "refused"), [
    ([0.1, 0.0, 4.5], "z = 4.5 m is not below the top of the drones' start box"),
    ([0.1, 0.0, 4.49], None),  # inside the box, below its top: drones above it can see it
    ([0.0, 0.0, 4.5 - 8.0], "8 m from the nearest point of the drones' start box, not within"
                            " camera.range_max_m = 8 m"),
    ([0.0, 0.0, 4.5 - 7.99], None),  # right below, just within range
    ([2.0 + 4.0 * math.tan(math.radians(50.0)), 0.0, 0.5], None),  # at the edge of the view
    ([2.0 + 4.0 * math.tan(math.radians(50.0)) + 1e-6, 0.0, 0.5],
     "m beside the drones' start box, outside every camera's field of view"),
    ([0.0, -2.0 - 4.0 * math.tan(math.radians(50.0)) - 1e-6, 0.5],
     "outside every camera's field of view"),
])
def test_a_target_no_drone_can_see_at_the_start_is_refused(start_m: list[float],
                                                           refused: str | None) -> None:
    """The camera looks down and sees D_m < d < D_M inside ±α_M: a target no start position
    in the box can see is refused, naming the target; the boundaries are the camera's own."""
    data = _case1_data()
    data["swarm"]["initial_box_size_m"] = [4.0, 4.0, 0.0]  # every drone starts at z = 4.5
    data["swarm"]["initial_box_center_m"] = [0.0, 0.0, 4.5]
    data["swarm"]["initial_min_separation_m"] = 0.5
    data["targets"][0]["start_m"] = start_m
    if refused is None:
        assert config_from_dict(data).targets[0].start_m == tuple(start_m)
        return
    with pytest.raises(ConfigError) as info:
        config_from_dict(data)
    message = str(info.value)
    assert message.startswith("targets[0].start_m: ") and refused in message, message
    assert "\n" not in message


def test_the_second_target_is_named_when_it_is_the_one_out_of_view() -> None:
    data = raw_case("case2")
    data["targets"][1]["start_m"] = [-0.1, 0.0, 6.0]
    with pytest.raises(ConfigError, match=r"^targets\[1\]\.start_m: z = 6 m is not below"):
        config_from_dict(data)
