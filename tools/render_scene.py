"""Draw a recording's 3D scene with matplotlib, primitive by primitive, as a 3D panel would.

    python tools/render_scene.py runs/case2 docs/case2_scene.png [--time S]

It reads the ``scene`` channel of ``DIR/run.mcap`` (``foxglove.SceneUpdate``, protobuf) with
the MCAP reader and the MCAP project's protobuf decoder, takes the scene at ``--time`` (default:
the last one) and draws exactly its primitives: spheres as discs of their colour (translucent
ones — the collision spheres of radius Δ, the uncertainty ellipsoids — as their equator: the
ellipse of their first two axes, posed as the primitive says), cylinders as their rims,
LINE_LIST lines as segments, texts at their positions. The README's picture of the live view
comes from here: no Foxglove or Lichtblick app runs headless on this project's machines
(npm has only Lichtblick's extension API, not its app), so this draws what they would be
sent.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from mpl_toolkits.mplot3d.art3d import Line3DCollection
from scipy.spatial.transform import Rotation

from swarm.errors import EXIT_OK, run_main
from swarm.observe.foxglove_scene import SCENE_TOPIC
from swarm.observe.recording.reader import locate
from swarm.observe.recording.schema import RecordingFileError
from swarm.scenario.cli_common import OneLineParser

RING_POINTS = 48


def read_scenes(recording: Path) -> list[tuple[int, str, str, Any]]:
    """(log_time ns, schema name, channel encoding, decoded SceneUpdate) of every scene."""
    with locate(recording).open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        return [(message.log_time, schema.name, channel.message_encoding, decoded)
                for schema, channel, message, decoded
                in reader.iter_decoded_messages(topics=[SCENE_TOPIC])]


def _xyz(p: Any) -> list[float]:
    return [p.x, p.y, p.z]


def _rgba(c: Any) -> tuple[float, float, float, float]:
    return (c.r, c.g, c.b, c.a)


def _equator(sphere: Any) -> np.ndarray:
    """(RING_POINTS, 3) points of a sphere primitive's equator: the ellipse of its size's x
    and y axes, turned by its pose's orientation and placed at its position."""
    angle = np.linspace(0.0, 2 * np.pi, RING_POINTS)
    local = np.stack([sphere.size.x / 2 * np.cos(angle), sphere.size.y / 2 * np.sin(angle),
                      np.zeros(RING_POINTS)], axis=1)
    q = sphere.pose.orientation
    rotation = Rotation.from_quat([q.x, q.y, q.z, q.w]) if (q.x, q.y, q.z, q.w) != (0, 0, 0, 0) \
        else Rotation.identity()  # an unset quaternion means no rotation, as in Foxglove
    return rotation.apply(local) + np.array(_xyz(sphere.pose.position))


def draw_scene(scene: Any, title: str = "") -> Figure:
    """One decoded SceneUpdate, drawn (equal scale on x and y)."""
    figure = Figure(figsize=(9.0, 6.6), dpi=110, layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot(projection="3d")
    ax.computed_zorder = False
    points: list[list[float]] = []
    for entity in scene.entities:
        for line in entity.lines:
            ends = np.array([_xyz(p) for p in line.points]).reshape(-1, 2, 3)
            ax.add_collection3d(Line3DCollection(ends, colors=[_rgba(line.color)],
                                                 linewidths=line.thickness * 0.8))
            points += ends.reshape(-1, 3).tolist()
        for sphere in entity.spheres:
            centre, colour = _xyz(sphere.pose.position), _rgba(sphere.color)
            if colour[3] < 0.5:  # translucent: its equator
                ax.plot(*_equator(sphere).T, color=colour[:3], alpha=0.6, lw=0.8)
            else:
                ax.scatter(*centre, color=[colour], s=900 * sphere.size.x ** 2,
                           depthshade=False, edgecolors="k", linewidths=0.4)
            points.append(centre)
        for cylinder in entity.cylinders:  # its top and bottom rims
            centre, colour = np.array(_xyz(cylinder.pose.position)), _rgba(cylinder.color)
            angle = np.linspace(0.0, 2 * np.pi, RING_POINTS)
            for dz in (-cylinder.size.z / 2, cylinder.size.z / 2):
                ax.plot(centre[0] + cylinder.size.x / 2 * np.cos(angle),
                        centre[1] + cylinder.size.y / 2 * np.sin(angle),
                        np.full(RING_POINTS, centre[2] + dz), color=colour[:3], lw=1.0)
            points.append(centre.tolist())
        for text in entity.texts:
            ax.text(*_xyz(text.pose.position), text.text, color=_rgba(text.color), fontsize=8)
    cloud = np.array(points) if points else np.zeros((1, 3))
    low, high = cloud.min(axis=0), cloud.max(axis=0)
    centre, span = (low + high) / 2, np.maximum(high - low, 1.0) * 1.05
    for setter, c, s in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, span, strict=True):
        setter(c - s / 2, c + s / 2)
    ax.set_box_aspect(tuple(span), zoom=1.2)
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_zlabel("z up [m]")
    ax.view_init(elev=24, azim=-62)
    ax.set_title(title)
    return figure


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="render_scene", description=(__doc__ or "").splitlines()[0])
    parser.add_argument("recording", type=Path, help="a --record directory or its run.mcap")
    parser.add_argument("out", type=Path, help="the PNG to write")
    parser.add_argument("--time", type=float, default=None, metavar="S",
                        help="sim time of the scene (default: the last one)")
    args = parser.parse_args(argv)
    return run_main("render_scene", lambda: _run(args.recording, args.out, args.time))


def _run(recording: Path, out: Path, time_s: float | None) -> int:
    scenes = read_scenes(recording)
    if not scenes:
        raise RecordingFileError(f"{recording}: no scene channel")
    if time_s is None:
        log_time, _, _, scene = scenes[-1]
    else:
        log_time, _, _, scene = min(scenes, key=lambda s: abs(s[0] - time_s * 1e9))
    figure = draw_scene(scene, f"recorded scene at t = {log_time / 1e9:.1f} s "
                               f"(foxglove.SceneUpdate, drawn primitive by primitive)")
    figure.savefig(out)
    print(f"render_scene: wrote {out}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
