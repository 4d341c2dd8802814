"""Write ``swarm/mavlink/px4_event_names.py``: PX4's event names by event id, from a PX4 checkout.

PX4 sends events (MAVLink EVENT) by id only; the id is a hash of the event's name, computed
at compile time from ``events::ID("name")`` in its source. This script finds every such name
under the checkout's ``src/`` (commander with its arming and health checks and its failsafe
code, navigator, ekf2, drivers, ...), computes the ids with
``swarm.mavlink.px4_events.px4_event_id``
and writes the table. Names only: nothing else of PX4's source (no message texts) is kept.

    python tools/px4_event_names.py PX4_CHECKOUT [--px4-commit SHA] [--px4-version TAG]

The commit and version default to what ``git`` says of the checkout (give them for a plain
copy of the tree, e.g. from ``git archive``). Exit 0: written; 1: nothing usable found or two
names hash to one id; 2: bad command line.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

from swarm.errors import EXIT_OK, UsageError, VigilError, run_main
from swarm.mavlink.px4_events import px4_event_id
from swarm.scenario.cli_common import OneLineParser

DEFAULT_OUTPUT = Path(__file__).resolve().parent.parent / "swarm" / "px4_event_names.py"
SOURCE_SUFFIXES = (".c", ".cpp", ".h", ".hpp")
_EVENT_NAME = re.compile(r'events::ID\(\s*"([A-Za-z0-9_]+)"\s*\)')


class EventNamesError(VigilError, RuntimeError):
    """The checkout gave no usable table; one line (exit 1)."""


def names_in_text(text: str) -> set[str]:
    """The ``events::ID("...")`` names in C/C++ source, outside ``//`` and ``/* */`` comment
    lines (a commented-out event is never sent)."""
    names: set[str] = set()
    for line in text.splitlines():
        stripped = line.lstrip()
        if stripped.startswith(("//", "/*", "*")):
            continue
        names.update(_EVENT_NAME.findall(line.split("//", 1)[0]))
    return names


def names_in_tree(root: Path) -> set[str]:
    """Every event name in the C/C++ files under ``root``."""
    names: set[str] = set()
    for path in sorted(root.rglob("*")):
        if path.suffix in SOURCE_SUFFIXES and path.is_file():
            names |= names_in_text(path.read_text(encoding="utf-8", errors="replace"))
    return names


def id_table(names: Iterable[str]) -> dict[int, str]:
    """event id → name; EventNamesError if two names share an id (the table would lie)."""
    table: dict[int, str] = {}
    for name in sorted(names):
        event_id = px4_event_id(name)
        if event_id in table:
            raise EventNamesError(f"events {table[event_id]!r} and {name!r} share id "
                                  f"0x{event_id:08x}; a table by id cannot tell them apart")
        table[event_id] = name
    return table


def render(table: Mapping[int, str], *, px4_version: str, px4_commit: str) -> str:
    """The generated module's text (sorted by name, so a regeneration diffs cleanly)."""
    lines = [
        '"""PX4 event names by event id. GENERATED: do not edit.',
        "",
        f"From PX4-Autopilot {px4_version} (commit {px4_commit}): every",
        '``events::ID("name")`` under its ``src/``,',
        'id = ``swarm.mavlink.px4_events.px4_event_id(name)``.',
        "Names only. Regenerate from a PX4 checkout with",
        "",
        "    python tools/px4_event_names.py PX4_CHECKOUT",
        "",
        "(for a tree without git, e.g. from ``git archive``, add ``--px4-commit`` and",
        "``--px4-version``).",
        '"""',
        "",
        f'PX4_VERSION = "{px4_version}"',
        f'PX4_COMMIT = "{px4_commit}"',
        "",
        "EVENT_NAMES: dict[int, str] = {",
        *(f'    0x{event_id:08x}: "{name}",'  # names are [A-Za-z0-9_]: no escaping
          for event_id, name in sorted(table.items(), key=lambda item: item[1])),
        "}",
        "",
    ]
    return "\n".join(lines)


def _git(checkout: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(checkout), *args], capture_output=True,
                              text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None if done.returncode == 0 else None


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="px4_event_names", description=__doc__.split("\n\n")[0])
    parser.add_argument("checkout", type=Path, help="PX4-Autopilot source tree")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--px4-commit", help="the checkout's commit (default: git rev-parse)")
    parser.add_argument("--px4-version", help="its release tag (default: git describe)")
    args = parser.parse_args(argv)
    return run_main("px4_event_names", lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    src = args.checkout / "src"
    if not (src / "modules" / "commander").is_dir():
        raise UsageError(f"{args.checkout}: not a PX4-Autopilot checkout (no "
                         f"src/modules/commander)")
    commit = args.px4_commit or _git(args.checkout, "rev-parse", "HEAD")
    version = args.px4_version or _git(args.checkout, "describe", "--tags", "--always")
    if commit is None or version is None:
        raise UsageError(f"{args.checkout}: not a git checkout; give --px4-commit and "
                         f"--px4-version")
    names = names_in_tree(src)
    if not names:
        raise EventNamesError(f"no events::ID(\"...\") names under {src}")
    table = id_table(names)
    args.output.write_text(render(table, px4_version=version, px4_commit=commit))
    print(f"{args.output}: {len(table)} event names from PX4 {version} ({commit[:10]})")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
