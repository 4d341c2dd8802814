"""Reading recordings back (swarm.observe.recording.reader): a file cut anywhere reads up to the
cut; bad inputs give one-line RecordingErrors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from swarm.observe.recording.reader import read_recording
from swarm.observe.recording.schema import RECORDING_FILE, RecordingError
from swarm.runs.record import RunRecord


def test_a_file_cut_anywhere_reads_up_to_the_cut(
        inprocess_recording: tuple[RunRecord, Path], tmp_path: Path) -> None:
    _, directory = inprocess_recording
    data = (directory / RECORDING_FILE).read_bytes()
    full = read_recording(directory)
    # Cut inside the data section: a cut in the summary after it loses no message (and is
    # not reported as truncated). The footer (29 bytes before the 8-byte closing magic)
    # holds summary_start; the 13-byte DataEnd record sits just before it.
    summary_start = int.from_bytes(data[-8 - 29 + 9:-8 - 29 + 17], "little")
    data_end = summary_start - 13
    assert data[data_end] == 0x0F  # DataEnd opcode
    totals = []
    for fraction in (0.3, 0.55, 0.8, 0.97):
        cut = tmp_path / f"cut{fraction}.mcap"
        cut.write_bytes(data[:int(data_end * fraction)])
        part = read_recording(cut)
        assert part.truncated
        totals.append(sum(part.message_counts.values()))
        steps = part.record.n_steps
        for name in ("drone_positions_m", "target_positions_m", "true_lambda_min"):
            assert np.array_equal(getattr(part.record, name), getattr(full.record, name)[:steps])
    assert totals == sorted(totals) and totals[0] < totals[-1] <= sum(full.message_counts.values())
    # Cut in the summary: every message is there, and the data section ended cleanly.
    summary_cut = tmp_path / "summary_cut.mcap"
    summary_cut.write_bytes(data[:summary_start + (len(data) - summary_start) // 2])
    whole = read_recording(summary_cut)
    assert not whole.truncated and whole.message_counts == full.message_counts


def test_bad_inputs_give_one_line_recording_errors(tmp_path: Path) -> None:
    (tmp_path / "empty_dir").mkdir()
    (tmp_path / "garbage.mcap").write_bytes(b"this is not an mcap file at all" * 10)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with (tmp_path / "foreign.mcap").open("wb") as handle:  # valid MCAP, not ours
        writer = Writer(handle)
        writer.start()
        writer.add_metadata("other", {"a": "b"})
        writer.finish()
    cases = {
        tmp_path / "missing": "no such file or directory",
        tmp_path / "empty_dir": "no run.mcap in this directory",
        tmp_path / "garbage.mcap": "not an MCAP file",
        tmp_path / "empty.mcap": "empty",
        tmp_path / "foreign.mcap": "no Vigil metadata",
    }
    for path, message in cases.items():
        with pytest.raises(RecordingError) as caught:
            read_recording(path)
        text = str(caught.value)
        assert message in text and str(path) in text and "\n" not in text
