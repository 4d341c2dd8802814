"""``swarm.observe.plots``: every figure is written as a valid PNG, the bearing error only with a
formation task; missing samples do not break a figure; the FoV pyramid's geometry."""

from __future__ import annotations

import dataclasses
import math
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from swarm.models.camera import fov_segments
from swarm.observe.plots import figures_for, plot_envelope, write_plots
from swarm.runs.record import RunRecord
from swarm.runs.reference import run_reference
from swarm.scenario.config import load_config

ROOT = Path(__file__).resolve().parents[2]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
COMMON = {"position_error.png", "psi.png", "weights.png", "speed.png", "view3d.png"}


def short_record(case: str, duration_s: float) -> RunRecord:
    return run_reference(load_config(ROOT / "configs" / f"{case}.toml").with_duration(duration_s))


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from the IHDR chunk; fails unless the file is a PNG."""
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, path
    assert data[12:16] == b"IHDR", path
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def assert_sensible_pngs(paths: list[Path]) -> None:
    for path in paths:
        width, height = png_size(path)
        assert 600 <= width <= 2500 and 300 <= height <= 2500, (path.name, width, height)
        assert path.stat().st_size > 20_000, path.name  # not a blank canvas


@pytest.fixture(scope="module")
def case2() -> RunRecord:
    return short_record("case2", 2.0)


def test_figures_without_a_formation_task(case2: RunRecord, tmp_path: Path) -> None:
    written = write_plots(case2, tmp_path / "out")
    assert {p.name for p in written} == COMMON
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(COMMON)
    assert_sensible_pngs(written)
    # One panel per target: the two-target figures are taller than the one-panel speed plot.
    assert png_size(tmp_path / "out" / "weights.png")[1] > png_size(
        tmp_path / "out" / "speed.png")[1]


def test_bearing_error_only_with_a_formation_task(tmp_path: Path) -> None:
    record = short_record("case3", 1.2)
    assert record.config.control.task == "bearing_formation"
    written = write_plots(record, tmp_path)
    assert {p.name for p in written} == COMMON | {"bearing_error.png"}
    assert_sensible_pngs(written)


def test_missing_samples_leave_gaps_not_errors(case2: RunRecord, tmp_path: Path) -> None:
    arrays = {}
    for name in ("drone_positions_m", "velocities_m_s", "estimates", "lambda_bar", "psi0",
                 "psi1", "weights"):
        values = getattr(case2, name).copy()
        values[40:50, 1] = np.nan
        values[-1, 0] = np.nan  # the final instant of the 3D view misses drone 0
        arrays[name] = values
    holed = dataclasses.replace(case2, **arrays)
    assert_sensible_pngs(write_plots(holed, tmp_path))


def test_every_figure_maker_returns_a_figure_quickly(case2: RunRecord) -> None:
    started = time.perf_counter()
    for make in figures_for(case2).values():
        figure = make(case2)
        assert figure.axes
    assert time.perf_counter() - started < 20.0


def test_fov_pyramid_reaches_the_ground_or_stops_at_range() -> None:
    apex = np.array([1.0, 2.0, 3.0])
    half = math.tan(math.radians(50.0))
    segments = fov_segments(apex, 50.0, 8.0, ground_z=0.0)
    assert len(segments) == 8
    corners = np.array([s[1] for s in segments[:4]])
    assert np.allclose(segments[0][0], apex)
    assert np.allclose(corners[:, 2], 0.0)  # to the ground: edge 3 m·1.96 < 8 m
    assert np.allclose(np.abs(corners[:, :2] - apex[:2]), 3.0 * half)
    # High up, the edges stop at D_M.
    far = fov_segments(np.array([0.0, 0.0, 10.0]), 50.0, 8.0, ground_z=0.0)
    lengths = [np.linalg.norm(s[1] - s[0]) for s in far[:4]]
    assert np.allclose(lengths, 8.0)
    assert fov_segments(np.array([0.0, 0.0, -1.0]), 50.0, 8.0, ground_z=0.0) == []


def test_the_envelope_figure_only_with_an_envelope_and_one_panel_per_kind(
        tmp_path: Path) -> None:
    """configs/case2_envelope.toml for 30 s (the ceiling reached from 24 s): envelope.png is
    written, with a panel per kind of boundary (floor, ceiling, fence, obstacle), each drone's
    distance drawn, and the conflict steps marked."""
    record = short_record("case2_envelope", 30.0)
    written = write_plots(record, tmp_path / "out")
    assert {p.name for p in written} == COMMON | {"envelope.png"}
    assert_sensible_pngs(written)
    figure = plot_envelope(record)
    axes = figure.axes
    assert [ax.get_ylabel().split("\n")[0] for ax in axes] == ["floor", "ceiling", "fence",
                                                               "obstacle"]
    n = record.config.swarm.n_drones
    assert all(len(ax.lines) >= n for ax in axes)
    marked = sum(len(c.get_offsets()) for ax in axes for c in ax.collections)
    assert record.safety_conflict is not None
    assert marked == int(record.safety_conflict.sum()) > 0
