"""swarm.observe.layout: the Foxglove layout in docs/ is the generator's, and every topic and
field it plots is in a recording (issue 17, point 2)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from mcap.reader import make_reader

from swarm.observe.camera_view import annotations_topic, calibration_topic, image_topic
from swarm.observe.foxglove_scene import LOG_TOPIC, SCENE_TOPIC
from swarm.observe.layout import layout_json, lichtblick_layout, main
from swarm.observe.recording.writer import record_reference
from swarm.scenario.config import load_config

ROOT = Path(__file__).resolve().parents[2]
CASE2 = ROOT / "configs" / "case2.toml"
PATH = re.compile(r'^"(?P<topic>[^"]+)"\.(?P<field>\w+)(?:\[(?P<index>\d+)\])?$')


def _panels(content: dict) -> list[dict]:
    if content["type"] == "panel":
        return [content]
    return [p for item in content["items"] for p in _panels(item["content"])]


def test_the_docs_layout_is_the_generators_for_case2(tmp_path: Path) -> None:
    assert (ROOT / "docs" / "foxglove_layout.json").read_text() == \
        layout_json(load_config(CASE2))
    out = tmp_path / "layout.json"
    assert main([str(CASE2), str(out)]) == 0
    assert out.read_text() == layout_json(load_config(CASE2))
    assert main([str(tmp_path / "missing.toml"), str(out)]) == 2


def test_every_plotted_path_and_the_3d_topic_are_in_a_recording(tmp_path: Path) -> None:
    config = load_config(CASE2).with_duration(1.5)
    record_reference(config, 0, tmp_path)
    panels = _panels(json.loads(layout_json(config))["content"])
    (three_d,) = [p for p in panels if p["panelType"] == "ThreeDee"]
    assert list(three_d["config"]["topics"]) == [SCENE_TOPIC]
    with (tmp_path / "run.mcap").open("rb") as handle:
        reader = make_reader(handle)
        first: dict[str, dict] = {}
        for _, channel, message in reader.iter_messages():
            if channel.message_encoding == "json" and channel.topic not in first:
                first[channel.topic] = json.loads(message.data)
        topics = {c.topic for c in reader.get_summary().channels.values()}
    assert SCENE_TOPIC in topics
    (log,) = [p for p in panels if p["panelType"] == "Log"]
    assert log["config"]["topicToRender"] == LOG_TOPIC and LOG_TOPIC in topics
    paths = [s["value"] for p in panels if p["panelType"] == "Plot"
             for s in p["config"]["paths"]]
    assert len(paths) == 2 * 6 * 2 + 6  # margins and weights per drone and target, speeds
    for path in paths:
        parsed = PATH.match(path)
        assert parsed is not None, path
        values = first[parsed["topic"]][parsed["field"]]
        if parsed["index"] is not None:
            assert int(parsed["index"]) < len(values), path
        else:
            assert isinstance(values, float), path


# Lichtblick's panel registry (packages/suite-base/src/panels/index.ts, 2026-11): the types
# a layout's panel ids may name.
LICHTBLICK_TYPES = {"3D", "DiagnosticStatusPanel", "DiagnosticSummary", "Image", "Indicator",
                    "Gauge", "Teleop", "map", "Parameters", "Plot", "PieChart", "Publish",
                    "CallService", "RawMessages", "RosOut", "StateTransitions", "Table",
                    "TopicGraph", "SourceInfo", "GlobalVariableSliderPanel", "NodePlayground",
                    "Tab"}


def _leaves(node) -> list[str]:
    return [node] if isinstance(node, str) else _leaves(node["first"]) + _leaves(node["second"])


def test_the_lichtblick_layout_passes_lichtblicks_import_rules_and_holds_the_same_panels(
        tmp_path: Path) -> None:
    """docs/lichtblick_layout.json is the generator's, and is what Lichtblick's layout import
    (``validateLayoutData``) accepts: objects ``configById`` and ``globalVariables``, a numeric
    ``playbackConfig.speed``, an object ``userNodes``, a ``layout`` tree whose leaves are
    exactly the configured panels, each id ``<registered type>!<n>``; and it holds the SDK
    layout's panels, topics, series and titles, split as the SDK layout splits."""
    config = load_config(CASE2)
    assert (ROOT / "docs" / "lichtblick_layout.json").read_text() == \
        layout_json(config, lichtblick=True)
    out = tmp_path / "lichtblick.json"
    assert main([str(CASE2), str(out), "--lichtblick"]) == 0
    data = json.loads(out.read_text())
    assert isinstance(data["configById"], dict) and isinstance(data["globalVariables"], dict)
    assert isinstance(data["playbackConfig"]["speed"], float)
    assert isinstance(data["userNodes"], dict)
    leaves = _leaves(data["layout"])
    assert sorted(leaves) == sorted(data["configById"])
    assert all(leaf.split("!")[0] in LICHTBLICK_TYPES for leaf in leaves)

    sdk = _panels(json.loads(layout_json(config))["content"])
    assert [leaf.split("!")[0] for leaf in leaves] == [
        "3D", "Image", "Plot", "Plot", "Plot", "RosOut"]
    assert [p["panelType"] for p in sdk] == ["ThreeDee", "Image", "Plot", "Plot", "Plot", "Log"]
    for leaf, panel in zip(leaves, sdk, strict=True):
        converted = data["configById"][leaf]
        assert converted["lichtblickPanelTitle"] == panel["title"]
        for key, value in panel["config"].items():
            if key != "paths":
                assert converted[key] == value, (leaf, key)
        if "paths" in panel["config"]:
            assert [{k: v for k, v in path.items() if k != "timestampMethod"}
                    for path in converted["paths"]] == panel["config"]["paths"]
            assert {path["timestampMethod"] for path in converted["paths"]} == {"receiveTime"}
    assert data["configById"][leaves[-1]]["topicToRender"] == LOG_TOPIC
    assert data["configById"][leaves[0]]["topics"] == {SCENE_TOPIC: {"visible": True}}
    assert data["configById"][leaves[1]]["imageMode"] == {
        "imageTopic": image_topic(0), "calibrationTopic": calibration_topic(0),
        "annotations": {annotations_topic(0): {"visible": True}}}
    # 3 : 2 between the column of the 3D and Image panels (2 : 1) and that of four equal panels
    layout = data["layout"]
    assert (layout["direction"], layout["splitPercentage"]) == ("row", 60.0)
    assert (layout["first"]["direction"], layout["first"]["splitPercentage"]) == (
        "column", 66.667)
    column = layout["second"]
    assert [column["splitPercentage"], column["second"]["splitPercentage"],
            column["second"]["second"]["splitPercentage"]] == [25.0, 33.333, 50.0]
    assert lichtblick_layout(config) == data
