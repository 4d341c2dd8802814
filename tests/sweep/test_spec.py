"""Sweep files (swarm.sweep.spec, swarm.sweep.plan): a bad one is one line and exit 2 with
nothing started; a good one expands into the same points every time."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import pytest

from swarm.sweep import cli
from swarm.sweep.plan import CODE_VERSION_VARIABLE, code_version, plan_sweep
from swarm.sweep.spec import SweepError, expand, parse_spec

ROOT = Path(__file__).resolve().parents[2]
CASE1 = ROOT / "configs" / "case1.toml"


def sweep_main(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(args))
        except SystemExit as stop:
            code = stop.code if isinstance(stop.code, int) else 2
    return code, out.getvalue(), err.getvalue()


GOOD = f'base = "{CASE1}"\nseeds = [0, 1]\n[set]\n"scenario.duration_s" = 2.0\n'


@pytest.mark.parametrize(("body", "said"), [
    ("colour = 1\n" + GOOD, "colour: unknown key"),
    (GOOD + '[axes]\n"gramian.epsilon" = 0.05\n', "axes.'gramian.epsilon': must be an array"),
    (GOOD + '[axes]\n"gramian.epsilon" = []\n', "axes.'gramian.epsilon': an empty axis"),
    (GOOD + '[axes]\n"gramian.epsilon" = [0.05, nan]\n',
     "axes.'gramian.epsilon': nan is not a finite number"),
    (GOOD + '[axes]\n"targets.0.velocity_m_s" = [[0.2, inf, 0.0]]\n',
     "axes.'targets.0.velocity_m_s': inf is not a finite number"),
    (GOOD.replace("seeds = [0, 1]", 'seeds = ["0", 1]'), "seeds: must be [first, last]"),
    (GOOD.replace("seeds = [0, 1]", "seeds = [3, 1]"), "seeds: need 0 <= first <= last"),
    ('mode = "fast"\n' + GOOD, "mode: must be one of"),
    ("record = 1\n" + GOOD, "record: must be true or false"),
    (GOOD + '[axes]\n"epsilon" = [0.05]\n', "expected a dotted key"),
    (GOOD + '[samples]\ncount = 3\n[samples.ranges]\n"camera.image_noise_std" = [0.01, 0.0]\n',
     "need low < high"),
    # keys and values only the scenario config knows are wrong: the point is named
    (GOOD + '[axes]\n"gramian.epsilonn" = [0.05]\n',
     "point gramian.epsilonn=0.05 seed 0: " + str(CASE1) + ": gramian.epsilonn: unknown key"),
    (GOOD + '[axes]\n"gramian.epsilon" = [0.05, "high"]\n',
     "gramian.epsilon: Expected `float`, got `str`"),
    (GOOD + '[axes]\n"gramian.epsilon" = [0.05, -0.01]\n',
     "gramian.epsilon must be a finite number > 0 (got -0.01)"),
    ('kill_agents = ["1@1.0"]\n' + GOOD, "--kill-agent needs --mode realtime"),
])
def test_a_bad_sweep_file_is_one_line_exit_2_and_nothing_runs(tmp_path: Path, body: str,
                                                             said: str) -> None:
    sweep = tmp_path / "bad.toml"
    sweep.write_text(body)
    out = tmp_path / "out"
    code, stdout, stderr = sweep_main(str(sweep), "--out", str(out))
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"swarm-sweep: {sweep}: "), stderr
    assert said in lines[0]
    assert "Traceback" not in stderr and stdout == ""
    assert not out.exists()  # nothing started, nothing written


def test_missing_sweep_file_and_bad_arguments_are_one_line(tmp_path: Path) -> None:
    code, _, stderr = sweep_main(str(tmp_path / "none.toml"), "--out", str(tmp_path / "o"))
    assert code == 2 and stderr.strip() == f"swarm-sweep: {tmp_path / 'none.toml'}: no such file"
    code, _, stderr = sweep_main("x.toml")
    assert code == 2 and len(stderr.strip().splitlines()) == 1
    code, _, stderr = sweep_main("x.toml", "--out", "o", "--scheduler", "tcp://h:1",
                                 "--workers", "2")
    assert code == 2 and "--workers sizes the local cluster" in stderr
    code, _, stderr = sweep_main("report", str(tmp_path))
    assert code == 2 and "no such file" in stderr


def test_expansion_is_grid_then_samples_then_seeds_and_repeatable() -> None:
    data = {"base": "x.toml", "seeds": [4, 5],
            "axes": {"gramian.epsilon": [0.04, 0.05], "swarm.n_drones": [6, 8]},
            "samples": {"count": 3, "seed": 7,
                        "ranges": {"camera.image_noise_std": [0.0, 0.01],
                                   "estimation.consensus_rounds": [1, 3]}}}
    spec = parse_spec(data)
    points = expand(spec)
    assert len(points) == spec.n_points == 2 * 2 * 3 * 2
    assert [p.seed for p in points[:4]] == [4, 5, 4, 5]
    assert points[0].cell == (("gramian.epsilon", 0.04), ("swarm.n_drones", 6))
    assert points[6].cell == (("gramian.epsilon", 0.04), ("swarm.n_drones", 8))
    rounds = {dict(p.sampled)["estimation.consensus_rounds"] for p in points}
    noise = [dict(p.sampled)["camera.image_noise_std"] for p in points]
    assert rounds <= {1, 2, 3} and all(isinstance(r, int) for r in rounds)
    assert all(0.0 <= v <= 0.01 for v in noise)
    assert expand(parse_spec(data)) == points  # the same file, the same points
    with pytest.raises(SweepError, match=r"samples\.count"):
        parse_spec({**data, "samples": {"count": 0, "ranges": {"a.b": [0, 1]}}})


def test_every_point_is_a_validated_config_with_its_own_key(tmp_path: Path) -> None:
    sweep = tmp_path / "s.toml"
    sweep.write_text(GOOD + '[axes]\n"swarm.n_drones" = [4, 7]\n'
                            '"targets.0.velocity_m_s" = [[0.2, 0.0, 0.0], [0.4, 0.0, 0.0]]\n')
    plan = plan_sweep(sweep, tmp_path / "out")
    assert len(plan.tasks) == 8 and len({t.key for t in plan.tasks}) == 8
    task = plan.tasks[-1]
    assert task.params == {"swarm.n_drones": 7, "targets.0.velocity_m_s": [0.4, 0.0, 0.0]}
    assert task.seed == 1 and task.config_data["scenario"]["seed"] == 1
    assert task.config_data["swarm"]["n_drones"] == 7
    assert len(task.config_data["swarm"]["edges"]) == 7 + 3
    assert plan_sweep(sweep, tmp_path / "out").tasks == plan.tasks  # keys are stable


def test_the_code_version_is_part_of_every_key(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A commit between two runs of a sweep makes every point new (the code changed); the
    version can be pinned (VIGIL_CODE_VERSION) to resume across one that changes nothing."""
    sweep = tmp_path / "s.toml"
    sweep.write_text(GOOD)
    keys = {}
    for version in ("0.1.0 aaaa", "0.1.0 bbbb", "0.1.0 aaaa"):
        monkeypatch.setenv(CODE_VERSION_VARIABLE, version)
        code_version.cache_clear()
        plan = plan_sweep(sweep, tmp_path / "out")
        assert plan.code_version == version
        keys.setdefault(version, []).append([t.key for t in plan.tasks])
    assert keys["0.1.0 aaaa"][0] == keys["0.1.0 aaaa"][1]
    assert not set(keys["0.1.0 aaaa"][0]) & set(keys["0.1.0 bbbb"][0])
    monkeypatch.delenv(CODE_VERSION_VARIABLE)
    code_version.cache_clear()
    assert code_version().startswith("0.1.0 ")  # the package version and the checkout
    code_version.cache_clear()
