"""A Foxglove layout for a run: the 3D scene beside plots of what the guarantee is about.

``foxglove_layout(config)`` builds it with Foxglove's own SDK (``foxglove.layouts``): the 3D
panel on the ``scene`` topic, following the ``world`` frame, and three Plot panels over every
drone's ``drone/<i>/plot`` channel — λ̄ − ε per target (the localization margin: the barrier
keeps it at or above 0), the sensing weights and ‖u‖ — above the Log panel of ``log``. The
same topics are served live (``--foxglove``) and written in every recording, so one layout
fits both.

    python -m swarm.observe.layout configs/case2.toml docs/foxglove_layout.json

writes it (Foxglove: *Layouts → Import from file*).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from foxglove.layouts import (
    BaseRendererSceneUpdateTopicSettings,
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

from swarm.observe.scene import FRAME, LOG_TOPIC, SCENE_TOPIC, plot_topic
from swarm.scenario.config import ConfigError, ScenarioConfig, load_config


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
    return Layout(content=SplitContainer(direction="row", items=[
        SplitItem(proportion=3, content=scene), SplitItem(proportion=2, content=plots)]))


def layout_json(config: ScenarioConfig) -> str:
    """The layout as a file holds it (indented, for people and diffs)."""
    return json.dumps(json.loads(foxglove_layout(config).to_json()), indent=2,
                      ensure_ascii=False) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m swarm.observe.layout",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("config", help="scenario file (its drones and targets)")
    parser.add_argument("out", type=Path, help="the layout JSON to write")
    args = parser.parse_args(argv)
    try:
        config = load_config(args.config)
    except ConfigError as err:
        print(f"layout: config error: {err}", file=sys.stderr)
        return 2
    args.out.write_text(layout_json(config))
    print(f"layout: wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
