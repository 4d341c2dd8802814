"""swarm.observe.layout: the Foxglove layout in docs/ is the generator's, and every topic and
field it plots is in a recording (issue 17, point 2)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from mcap.reader import make_reader

from swarm.observe.layout import layout_json, main
from swarm.observe.recording import record_reference
from swarm.observe.scene import LOG_TOPIC, SCENE_TOPIC
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
