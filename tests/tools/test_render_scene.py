"""tools/render_scene.py draws a recording's scene (the README's picture of the 3D view)."""

from __future__ import annotations

from pathlib import Path

from matplotlib.collections import PathCollection
from mpl_toolkits.mplot3d.art3d import Line3DCollection

from swarm.observe.recording.writer import record_reference
from swarm.scenario.config import load_config
from tools.render_scene import draw_scene, main, read_scenes

ROOT = Path(__file__).resolve().parents[2]


def test_it_draws_every_primitive_of_the_last_scene_and_writes_the_png(tmp_path: Path) -> None:
    config = load_config(ROOT / "configs" / "case2.toml").with_duration(1.5)
    record_reference(config, 0, tmp_path / "rec")
    *_, (_, _, _, scene) = read_scenes(tmp_path / "rec")
    ax = draw_scene(scene).axes[0]
    n, m = config.swarm.n_drones, len(config.targets)
    solid = [c for c in ax.collections if isinstance(c, PathCollection)]
    assert len(solid) == n + m + n * m  # drones, targets, estimates (rings are lines)
    assert len([c for c in ax.collections if isinstance(c, Line3DCollection)]) == 2  # fov, graph
    assert len(ax.texts) == n + m
    assert len(ax.lines) == n + n * m  # equators: collision spheres, uncertainty ellipsoids
    out = tmp_path / "scene.png"
    assert main([str(tmp_path / "rec"), str(out), "--time", "0.5"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
