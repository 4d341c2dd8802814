"""``DIR/results.jsonl``: one JSON object per line and mission, appended as each ends.

The sweep command is the only writer (on the Dask client): a row is one ``write`` of a whole
line, flushed and synced before the next, and a key already in the file is never written
again. A line cut short (the machine lost power mid-write) is dropped when the file is opened
again, so the file always holds whole rows.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

from swarm.errors import UsageError

RESULTS_FILE = "results.jsonl"


class ResultsError(UsageError, ValueError):
    """A results file that cannot be read or written; one line."""


def read_rows(path: Path) -> list[dict[str, Any]]:
    """Every whole row of ``path`` (a missing file: none). A last line without its newline
    is a row cut short and left out; any other line that is not a JSON object is an error."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    except OSError as err:
        raise ResultsError(f"{path}: cannot read: {err.strerror or err}") from None
    except UnicodeDecodeError:
        raise ResultsError(f"{path}: not a UTF-8 text file") from None
    lines = text.split("\n")
    rows = []
    for number, line in enumerate(lines[:-1], start=1):  # the part after the last \n: cut
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as err:
            raise ResultsError(f"{path}:{number}: not a JSON object: {err.msg}") from None
        if not isinstance(row, dict) or not isinstance(row.get("key"), str):
            raise ResultsError(f"{path}:{number}: not a sweep row (no key)")
        rows.append(row)
    return rows


class ResultsWriter:
    """Appends rows to ``DIR/results.jsonl``; ``keys`` are the rows already there."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / RESULTS_FILE
        try:
            directory.mkdir(parents=True, exist_ok=True)
            self._drop_cut_line()
            rows = read_rows(self.path)
            self._handle: IO[str] = self.path.open("a", encoding="utf-8")
        except OSError as err:
            raise ResultsError(f"{self.path}: cannot write: {err.strerror or err}") from None
        self.keys: set[str] = {row["key"] for row in rows}
        self.rows = rows

    def _drop_cut_line(self) -> None:
        """Truncate the file after its last newline (a row cut short by a crash)."""
        try:
            with self.path.open("rb+") as handle:
                data = handle.read()
                end = data.rfind(b"\n") + 1
                if end != len(data):
                    handle.truncate(end)
        except FileNotFoundError:
            pass

    def write(self, row: Mapping[str, Any]) -> bool:
        """Append ``row`` unless its key is there already; whether it was written."""
        key = row["key"]
        if key in self.keys:
            return False
        line = json.dumps(row, allow_nan=False, separators=(", ", ": ")) + "\n"
        self._handle.write(line)
        self._handle.flush()
        os.fsync(self._handle.fileno())
        self.keys.add(key)
        self.rows.append(dict(row))
        return True

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> ResultsWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
