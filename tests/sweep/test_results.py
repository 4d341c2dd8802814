"""results.jsonl (swarm.sweep.results): whole rows, never a key twice, a cut line dropped."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from swarm.sweep.results import RESULTS_FILE, ResultsError, ResultsWriter, read_rows


def test_a_key_is_written_once_and_found_again(tmp_path: Path) -> None:
    with ResultsWriter(tmp_path) as writer:
        assert writer.write({"key": "a", "verdict": "OK"})
        assert not writer.write({"key": "a", "verdict": "FAILED"})
        assert writer.write({"key": "b", "verdict": "OK"})
    with ResultsWriter(tmp_path) as again:
        assert again.keys == {"a", "b"}
        assert not again.write({"key": "b", "verdict": "OK"})
    lines = (tmp_path / RESULTS_FILE).read_text().splitlines()
    assert [json.loads(line)["key"] for line in lines] == ["a", "b"]
    assert json.loads(lines[0])["verdict"] == "OK"


def test_a_row_cut_short_is_dropped_when_the_file_is_opened(tmp_path: Path) -> None:
    path = tmp_path / RESULTS_FILE
    path.write_text('{"key": "a"}\n{"key": "b", "verd')
    assert [r["key"] for r in read_rows(path)] == ["a"]
    with ResultsWriter(tmp_path) as writer:
        assert writer.keys == {"a"}
        writer.write({"key": "b"})
    assert path.read_text() == '{"key": "a"}\n{"key": "b"}\n'


def test_a_line_that_is_not_a_row_is_one_line_error(tmp_path: Path) -> None:
    path = tmp_path / RESULTS_FILE
    path.write_text('{"key": "a"}\nnot json\n')
    with pytest.raises(ResultsError) as err:
        read_rows(path)
    assert str(err.value).startswith(f"{path}:2: not a JSON object")
    path.write_text('[1, 2]\n')
    with pytest.raises(ResultsError, match="not a sweep row"):
        read_rows(path)
