"""tools/config_reference.py: docs/config_reference.md is what the config schema gives, and it
documents every key a resolved config has, with the code's own defaults and rules."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from swarm.scenario.config import config_to_data, load_config
from tools import config_reference
from tools.config_reference import ITEM, ReferenceError_, main, render, sections

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "config_reference.md"


def _leaf_keys(data: object, path: str = "") -> set[str]:
    """The dotted keys of a resolved config's plain data; array-of-table indices as <i>."""
    if isinstance(data, dict):
        keys: set[str] = set()
        for key, value in data.items():
            keys |= _leaf_keys(value, f"{path}.{key}" if path else key)
        return keys
    if isinstance(data, list) and data and all(isinstance(item, dict) for item in data):
        return set().union(*(_leaf_keys(item, f"{path}.{ITEM}") for item in data))
    return {path}


def _keys_by_name() -> dict[str, config_reference.Key]:
    return {key.dotted: key for section in sections() for key in section.keys}


def test_the_committed_reference_is_the_generated_one() -> None:
    assert PAGE.read_text(encoding="utf-8") == render(), (
        "docs/config_reference.md is stale: run `python tools/config_reference.py --write`")


def test_every_key_of_a_resolved_config_is_documented_and_no_other() -> None:
    # case2_envelope has a [safety] with keep_out entries, so every array of tables is filled.
    data = config_to_data(load_config(ROOT / "configs" / "case2_envelope.toml"))
    assert _leaf_keys(data) == set(_keys_by_name())


def test_each_key_has_a_meaning_and_defaults_are_the_codes() -> None:
    keys = _keys_by_name()
    assert all(key.description for key in keys.values())
    assert keys["gramian.epsilon"].default == "0.05"
    assert keys["gramian.projector_consensus.kp"].default == "5.0"  # from the parent's default
    assert keys["control.slack_weight"].default == "1e6"
    assert keys["scenario.name"].default == "required"
    assert keys["safety.floor_m"].default == "not set"
    assert "arducopter 0.1" in keys["control.tracking_error_bound_m_s"].default
    assert "ardupilot 3.0" in keys["vehicles.setpoint_timeout_s"].default


def test_units_come_from_the_names_and_the_comments() -> None:
    keys = _keys_by_name()
    assert keys["control.u_max_m_s"].unit == "m/s"
    assert keys["vehicles.response_accel_limit_m_s2"].unit == "m/s²"
    assert keys["gramian.forgetting"].unit == "1/s"  # "ρ [1/s]"
    assert keys["gramian.forgetting"].description == "ρ"
    assert keys["swarm.n_drones"].unit == ""
    assert keys["swarm.edges"].unit == ""  # "[i, j]" in an integer key's comment is no unit


def test_valid_values_are_the_codes_rules_and_refusals() -> None:
    keys = _keys_by_name()
    assert keys["scenario.dt_s"].rules == (
        "must lie in (0, 0.1] s",
        "must be a whole number of milliseconds (MAVLink time_boot_ms stamps the steps)")
    assert keys["control.qp_solver"].rules == ('one of `"daqp"`, `"piqp"`',)
    assert "must be an integer in [2, 256]" in keys["swarm.n_drones"].rules
    # a rule of another class the section builds (SafetyParams, convex_counter_clockwise)
    assert "must be below ceiling_m = …" in keys["safety.floor_m"].rules
    assert "needs at least 3 vertices [x, y]" in keys["safety.keep_in"].rules
    # a rule of a loop over field names, and a cross-section refusal with its key bound
    assert keys["vehicles.response_time_constant_s"].rules == (
        "must be a finite number >= 0", "is used only with response = 'custom'")
    assert any(rule.startswith("K_p·λ_max(L)·ΔT = … must be < 2")
               for rule in keys["gramian.weight_consensus.kp"].rules)
    assert any("not below the top of the drones' start box" in rule
               for rule in keys[f"targets.{ITEM}.start_m"].rules)
    by_section = {section.dotted: section for section in sections()}
    assert by_section["targets"].rules == ("need 1 to 16 [[targets]] entries",)
    assert by_section["safety.keep_out"].array


@dataclasses.dataclass(frozen=True)
class _Uncommented:
    """A section one of whose fields says nothing of itself."""

    speed_m_s: float = 1.0


@dataclasses.dataclass(frozen=True)
class _Root:
    section: _Uncommented = dataclasses.field(default_factory=_Uncommented)


def test_a_field_without_a_comment_cannot_be_documented() -> None:
    with pytest.raises(ReferenceError_, match=r"section\.speed_m_s: no comment"):
        sections(_Root)


def test_check_fails_on_a_stale_page_and_write_makes_it_current(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    page = tmp_path / "config_reference.md"
    assert main(["--check", "--output", str(page)]) == 1  # missing
    capsys.readouterr()
    stale = render().replace("| 0.05 |", "| 0.06 |", 1)
    assert stale != render()
    page.write_text(stale, encoding="utf-8")
    assert main(["--check", "--output", str(page)]) == 1
    error = capsys.readouterr().err.strip()
    assert re.fullmatch(r"config_reference: .* is stale \(or missing\): run `python "
                        r"tools/config_reference\.py --write`", error), error
    assert main(["--write", "--output", str(page)]) == 0
    assert main(["--check", "--output", str(page)]) == 0
