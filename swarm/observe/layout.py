"""A Foxglove layout for a run: the 3D scene beside plots of what the guarantee is about.

``foxglove_layout(config)`` builds it with Foxglove's own SDK (``foxglove.layouts``): the 3D
panel on the ``scene`` topic, following the ``world`` frame, and three Plot panels over every
drone's ``drone/<i>/plot`` channel — λ̄ − ε per target (the localization margin: the barrier
keeps it at or above 0), the sensing weights and ‖u‖ — above the Log panel of ``log``, and an
Image panel of drone 0's rendered camera (its image, calibration and detections,
``swarm.observe.camera_view``; empty with the bearing camera, which has no pixels). The same
topics are served live (``--foxglove``) and written in every recording, so one layout fits
both.

    python -m swarm.observe.layout configs/case2.toml docs/foxglove_layout.json

writes it (Foxglove: *Layouts → Import from file*). Lichtblick, the open-source fork of
Foxglove Studio, imports the older layout data instead (``configById``, ``globalVariables``,
``playbackConfig`` and a ``layout`` tree of splits, with its own panel type names): with
``--lichtblick`` the same layout is written in that form (``lichtblick_layout``), as
``docs/lichtblick_layout.json`` is.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

from foxglove.layouts import (
    BaseRendererSceneUpdateTopicSettings,
    ImageAnnotationSettings,
    ImageConfig,
    ImageModeConfig,
    ImagePanel,
    Layout,
    LogConfig,
    LogPanel,
    PlotConfig,
    PlotPanel,
    PlotSeries,
    SplitContainer,
    SplitItem,
    ThreeDeeConfig,
    ThreeDeePanel,
)

from swarm.errors import EXIT_OK, run_main
from swarm.observe.camera_view import annotations_topic, calibration_topic, image_topic
from swarm.observe.foxglove_scene import FRAME, LOG_TOPIC, SCENE_TOPIC, plot_topic
from swarm.scenario.cli_common import OneLineParser
from swarm.scenario.config import ScenarioConfig, load_config


def plot_path(drone: int, field: str) -> str:
    """A message path into ``drone/<i>/plot`` (the topic quoted: it has no leading slash)."""
    return f'"{plot_topic(drone)}".{field}'


def _plot(title: str, series: list[tuple[str, str]]) -> PlotPanel:
    return PlotPanel(title=title, config=PlotConfig(
        paths=[PlotSeries(value=path, label=label, enabled=True) for path, label in series],
        show_legend=True, legend_display="floating", x_axis_val="timestamp"))


def foxglove_layout(config: ScenarioConfig) -> Layout:
    n, m = config.swarm.n_drones, len(config.targets)
    scene = ThreeDeePanel(title="swarm", config=ThreeDeeConfig(
        follow_tf=FRAME, topics={SCENE_TOPIC: BaseRendererSceneUpdateTopicSettings(
            visible=True)}))
    margins = _plot("λ̄ − ε per drone and target (≥ 0: localized)", [
        (plot_path(i, f"lambda_margin[{r}]"), f"drone {i} T{r}")
        for i in range(n) for r in range(m)])
    weights = _plot("sensing weights", [(plot_path(i, f"weights[{r}]"), f"drone {i} T{r}")
                                        for i in range(n) for r in range(m)])
    speeds = _plot("‖u‖ [m/s]", [(plot_path(i, "speed_m_s"), f"drone {i}") for i in range(n)])
    log = LogPanel(title="drones' warnings", config=LogConfig(topic_to_render=LOG_TOPIC))
    plots = SplitContainer(direction="column", items=[
        SplitItem(content=margins), SplitItem(content=weights), SplitItem(content=speeds),
        SplitItem(content=log)])
    camera = ImagePanel(title='drone 0\'s camera (camera.model = "rendered")',
                        config=ImageConfig(image_mode=ImageModeConfig(
                            image_topic=image_topic(0), calibration_topic=calibration_topic(0),
                            annotations={annotations_topic(0):
                                         ImageAnnotationSettings(visible=True)})))
    left = SplitContainer(direction="column", items=[
        SplitItem(proportion=2, content=scene), SplitItem(proportion=1, content=camera)])
    return Layout(content=SplitContainer(direction="row", items=[
        SplitItem(proportion=3, content=left), SplitItem(proportion=2, content=plots)]))


# Lichtblick's name of each panel type of the SDK (its panel registry), and what its panels
# expect in their config beside the SDK's fields.
LICHTBLICK_PANEL_TYPES: Final = {"ThreeDee": "3D", "Plot": "Plot", "Log": "RosOut",
                                  "Image": "Image"}
LICHTBLICK_TITLE_KEY: Final = "lichtblickPanelTitle"
_LICHTBLICK_DEFAULTS: Final[dict[str, dict[str, Any]]] = {
    "RosOut": {"searchTerms": [], "minLogLevel": 1}}


def lichtblick_layout(config: ScenarioConfig) -> dict[str, Any]:
    """``foxglove_layout(config)`` as Lichtblick's layout data: each panel under an id
    ``<Lichtblick type>!<n>`` in ``configById`` (its title under ``lichtblickPanelTitle``, each
    plotted series stamped by receive time, which is sim time here), and every split container
    as nested binary splits (``first``, ``second``, ``splitPercentage``)."""
    configs: dict[str, dict[str, Any]] = {}

    def convert(node: dict[str, Any]) -> Any:
        if node["type"] == "panel":
            kind = LICHTBLICK_PANEL_TYPES[node["panelType"]]
            panel_id = f"{kind}!{len(configs) + 1}"
            panel = {**_LICHTBLICK_DEFAULTS.get(kind, {}), **node.get("config", {})}
            if kind == "Plot":
                panel["paths"] = [{**path, "timestampMethod": "receiveTime"}
                                  for path in panel["paths"]]
            if "title" in node:
                panel[LICHTBLICK_TITLE_KEY] = node["title"]
            configs[panel_id] = panel
            return panel_id
        return split(node["direction"], node["items"])

    def split(direction: str, items: list[dict[str, Any]]) -> Any:
        if len(items) == 1:
            return convert(items[0]["content"])
        weights = [float(item.get("proportion", 1.0)) for item in items]
        return {"direction": direction, "first": convert(items[0]["content"]),
                "second": split(direction, items[1:]),
                "splitPercentage": round(100.0 * weights[0] / sum(weights), 3)}

    tree = convert(json.loads(foxglove_layout(config).to_json())["content"])
    return {"configById": configs, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1.0}, "layout": tree}


def layout_json(config: ScenarioConfig, lichtblick: bool = False) -> str:
    """The layout as a file holds it (indented, for people and diffs); ``lichtblick``: in
    Lichtblick's form."""
    data = (lichtblick_layout(config) if lichtblick
            else json.loads(foxglove_layout(config).to_json()))
    return json.dumps(data, indent=2, ensure_ascii=False) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m swarm.observe.layout",
                           description=(__doc__ or "").splitlines()[0])
    parser.add_argument("config", help="scenario file (its drones and targets)")
    parser.add_argument("out", type=Path, help="the layout JSON to write")
    parser.add_argument("--lichtblick", action="store_true",
                        help="write it as Lichtblick imports layouts (the older layout data)")
    args = parser.parse_args(argv)
    return run_main("layout", lambda: _write(load_config(args.config), args.out,
                                             lichtblick=args.lichtblick))


def _write(config: ScenarioConfig, out: Path, *, lichtblick: bool) -> int:
    out.write_text(layout_json(config, lichtblick=lichtblick))
    print(f"layout: wrote {out}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
