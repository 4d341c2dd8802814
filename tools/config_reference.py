"""The config reference (docs/config_reference.md), generated from the config schema.

Every key of a scenario file comes from the frozen dataclasses that ``swarm.scenario.config``
converts a TOML document into (``ScenarioConfig`` and its sections, the core's parameter
classes among them). For each key this reads, from the code itself:

- its dotted name (as ``launch-swarm --set`` and sweeps take it), type and default: from the
  dataclass fields and their annotations;
- its meaning and unit: from the comment beside or above the field (the project writes the
  unit in the name, ``_m``, ``_s``, ``_m_s``, … or as ``[unit]`` in the comment);
- what values are valid: the choices of a ``Literal`` type, and the reason text of every
  ``require(...)`` of the section's ``__post_init__`` and of every ``raise ConfigError(...)``
  in the config module that names the key — the words of the one-line error a bad value gets.

So the page cannot drift from the schema: ``--check`` fails when the committed file differs
from what the code gives (a test runs it), and a field without a comment is an error here.

    python tools/config_reference.py --write     # regenerate docs/config_reference.md
    python tools/config_reference.py --check     # exit 1 when it is stale
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import re
import sys
import textwrap
import tokenize
import types
import typing
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from swarm.core import params as core_params
from swarm.core.graph import CommunicationGraph
from swarm.core.safety import KeepOutCylinder, SafetyParams, convex_counter_clockwise
from swarm.errors import EXIT_FAILED, EXIT_OK, VigilError, run_main
from swarm.scenario import config as config_module
from swarm.scenario.cli_common import OneLineParser
from swarm.scenario.config import (
    AUTOPILOT_RESPONSE,
    DEFAULT_SETPOINT_TIMEOUT_S,
    TRACKING_DEFAULTS,
    TRACKING_KEYS,
    KeepOutSection,
    SafetySection,
    ScenarioConfig,
    SwarmSection,
)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUTPUT = ROOT / "docs" / "config_reference.md"
COMMAND = "python tools/config_reference.py --write"

# Functions that validate a section's fields for it (the section builds what they belong to),
# and which of its fields they speak for (None: every field).
VALIDATED_BY: dict[type, tuple[tuple[Callable[..., object], tuple[str, ...] | None], ...]] = {
    SwarmSection: ((CommunicationGraph.__post_init__, ("edges",)),),
    SafetySection: ((SafetyParams.__post_init__, None), (convex_counter_clockwise, None)),
    KeepOutSection: ((KeepOutCylinder.__post_init__, None),),
}
RULE_WORDS = ("must", "needs", "need", "is")  # a reason that reads as a rule without its key
# Unit suffixes of field names, longest first (the project's naming rule).
UNIT_SUFFIXES = (("_m_s2", "m/s²"), ("_rad_s", "rad/s"), ("_m_s", "m/s"), ("_m2", "m²"),
                 ("_deg", "deg"), ("_s", "s"), ("_m", "m"))
ITEM = "<i>"  # the index of an array of tables in a dotted key (targets.0.start_m)


class ReferenceError_(VigilError):  # noqa: N801 (not the builtin ReferenceError)
    """The schema cannot be documented as it stands (e.g. a field without a comment)."""


@dataclass(frozen=True)
class Key:
    """One key of a scenario file as the reference shows it."""

    dotted: str  # e.g. "gramian.projector_consensus.kp", "targets.<i>.start_m"
    type_text: str
    unit: str  # "" when the key has none
    default: str  # "required" for keys without a default
    rules: tuple[str, ...]  # what a valid value is, in the code's words
    description: str


@dataclass(frozen=True)
class Section:
    """A table of a scenario file: ``[gramian]``, ``[gramian.projector_consensus]``,
    ``[[targets]]``."""

    dotted: str  # "gramian.projector_consensus", "targets"
    array: bool  # an array of tables ([[targets]], keep_out)
    required: bool
    description: str
    rules: tuple[str, ...]  # refusals about the section as a whole
    keys: tuple[Key, ...]


# -- what the code says about its fields ---------------------------------------------------


def field_comments(cls: type) -> dict[str, str]:
    """Each field's comment: the comment lines right above it and the one beside it, joined.

    Read from the class's source with ``tokenize`` (comments are not in the AST)."""
    source = textwrap.dedent(inspect.getsource(cls))
    tree = ast.parse(source)
    body = tree.body[0].body  # type: ignore[attr-defined]
    comments: dict[int, str] = {}
    comment_only: set[int] = set()
    lines = source.splitlines()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            row = token.start[0]
            comments[row] = token.string.lstrip("#").strip()
            if lines[row - 1].lstrip().startswith("#"):
                comment_only.add(row)
    found: dict[str, str] = {}
    previous_end = 0
    for node in body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            above: list[str] = []
            row = node.lineno - 1
            while row > previous_end and row in comment_only:
                above.insert(0, comments[row])
                row -= 1
            beside = [comments[r] for r in range(node.lineno, (node.end_lineno or node.lineno) + 1)
                      if r in comments and r not in comment_only]
            text = " ".join(part for part in (*above, *beside) if part)
            found[node.target.id] = re.sub(r"\s+", " ", text).strip()
        previous_end = node.end_lineno or node.lineno
    return found


def _constant_bindings(target: ast.expr, iterable: ast.expr) -> list[dict[str, object]] | None:
    """The names a ``for`` over a literal tuple binds to constants, one dict per turn
    (``for name in ("a", "b")``, ``for name, x in (("a", …), ("b", …))``); None otherwise."""
    if not isinstance(iterable, ast.Tuple | ast.List):
        return None
    turns: list[dict[str, object]] = []
    for element in iterable.elts:
        turn: dict[str, object] = {}
        if isinstance(target, ast.Name) and isinstance(element, ast.Constant):
            turn[target.id] = element.value
        elif isinstance(target, ast.Tuple) and isinstance(element, ast.Tuple):
            for name, value in zip(target.elts, element.elts, strict=False):
                if isinstance(name, ast.Name) and isinstance(value, ast.Constant):
                    turn[name.id] = value.value
        turns.append(turn)
    return turns


def _text(node: ast.expr, env: dict[str, object],
          strings: dict[str, ast.expr] | None = None) -> str | None:
    """A message argument as text: an f-string's values are "…" unless a loop bound them to a
    constant or they name a local string (``strings``: ``key = f"targets[{k}].start_m"``);
    None for anything that is not a string literal."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        parts = []
        for value in node.values:
            name = (value.value.id if isinstance(value, ast.FormattedValue)
                    and isinstance(value.value, ast.Name) else None)
            if isinstance(value, ast.Constant):
                parts.append(str(value.value))
            elif name is not None and name in env:
                parts.append(str(env[name]))
            elif name is not None and strings and name in strings:
                parts.append(_text(strings[name], env) or "…")
            else:
                parts.append("…")
        return "".join(parts)
    return None


def _local_strings(tree: ast.AST) -> dict[str, ast.expr]:
    """The names a function assigns a string literal or f-string to (once)."""
    found: dict[str, ast.expr] = {}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name)
                and isinstance(node.value, ast.Constant | ast.JoinedStr)):
            found[node.targets[0].id] = node.value
    return found


def _without_got(text: str) -> str:
    """A refusal without the value it quotes: "… (got …)" → "…"."""
    return re.sub(r"\s*\(got …\)$", "", text).strip()


def _helper_reasons() -> dict[str, str]:
    """The reason each one-field helper of ``swarm.core.params`` gives (``require_finite``:
    "must be a finite number"), read from its body."""
    reasons: dict[str, str] = {}
    for name, function in vars(core_params).items():
        if not (name.startswith("require_") and inspect.isfunction(function)):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
        for call in ast.walk(tree):
            if (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)
                    and call.func.id == "require" and len(call.args) >= 3):
                reason = _text(call.args[2], {})
                if reason:
                    reasons[name] = reason
    return reasons


def _calls_and_raises(statements: Sequence[ast.stmt], env: dict[str, object]
                      ) -> Iterator[tuple[ast.AST, dict[str, object]]]:
    """Every call and ``raise`` in ``statements`` with the constants that enclosing ``for``
    loops over literal tuples bind (one visit per turn of such a loop)."""
    for statement in statements:
        if isinstance(statement, ast.For):
            turns = _constant_bindings(statement.target, statement.iter) or [{}]
            for turn in turns:
                yield from _calls_and_raises(statement.body, {**env, **turn})
            continue
        blocks = [getattr(statement, name) for name in ("body", "orelse", "finalbody")
                  if isinstance(getattr(statement, name, None), list)]
        blocks += [handler.body for handler in getattr(statement, "handlers", [])]
        if blocks:
            for block in blocks:
                yield from _calls_and_raises(block, env)
            continue
        for node in ast.walk(statement):
            if isinstance(node, ast.Call | ast.Raise):
                yield node, env


def _rule(field_name: str, reason: str, colon: bool) -> str:
    """A reason as the reference shows it: as the code says it after the key when it reads as
    a rule by itself ("must be > 0", "self-loop [… , …] is not allowed" after "edges:"), else
    with the key's last name in front ("keep_in vertices must be finite")."""
    reason = _without_got(reason)
    if colon or reason.split(" ", 1)[0] in RULE_WORDS:
        return reason
    return f"{field_name} {reason}"


def function_rules(function: Callable[..., object], names: set[str],
                   helpers: dict[str, str]) -> dict[str, list[str]]:
    """What ``function`` (a ``__post_init__`` or a checker it calls) requires of each field in
    ``names``, in its own words: the reason of each ``require(cond, FIELD, REASON, value)`` and
    of each ``require_*`` helper, and each ``raise ValueError(...)`` that starts with a field's
    name."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    rules: dict[str, list[str]] = {}

    def add(field_name: object, reason: str | None, colon: bool = False) -> None:
        if not isinstance(field_name, str) or not reason:
            return
        field_name = field_name.rsplit(".", 1)[-1]  # "keep_out.radius_m" → "radius_m"
        if field_name in names:
            rules.setdefault(field_name, []).append(_rule(field_name, reason, colon))

    for node, env in _calls_and_raises(tree.body[0].body, {}):  # type: ignore[attr-defined]
        if isinstance(node, ast.Raise):
            call = node.exc
            if isinstance(call, ast.Call) and call.args:
                message = _text(call.args[0], env)
                if message and " " in message:
                    first, rest = message.split(" ", 1)
                    add(first.rstrip(":"), rest, first.endswith(":"))
            continue
        assert isinstance(node, ast.Call)
        if not isinstance(node.func, ast.Name) or not node.args:
            continue
        field_node = node.args[0] if node.func.id in helpers else (
            node.args[1] if node.func.id == "require" and len(node.args) >= 3 else None)
        if field_node is None:
            continue
        field_name = (field_node.value if isinstance(field_node, ast.Constant)
                      else env.get(field_node.id) if isinstance(field_node, ast.Name) else None)
        reason = helpers.get(node.func.id) or _text(node.args[2], env)
        add(field_name, reason)
    return rules


KEY_AT_START = re.compile(r"^([a-z_]+(?:(?:\.[a-z_]+)|(?:\.…)|(?:\[…\]))*)(:?) ")


def cross_section_rules(module: types.ModuleType) -> dict[str, list[str]]:
    """The refusals of the config module's own functions that name their key first
    (``raise ConfigError(f"estimation.laplacian_step must be < … for this graph")``), by
    dotted key; list indices become ``<i>``."""
    rules: dict[str, list[str]] = {}
    for function in vars(module).values():
        if not (inspect.isfunction(function) and function.__module__ == module.__name__):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
        strings = _local_strings(tree)
        for node, env in _calls_and_raises(tree.body[0].body, {}):  # type: ignore[attr-defined]
            if not (isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call)
                    and isinstance(node.exc.func, ast.Name)
                    and node.exc.func.id == "ConfigError" and node.exc.args):
                continue
            # The key with the loops' constants in it; the reason with "…" for every value.
            message = _text(node.exc.args[0], env, strings)
            plain = _text(node.exc.args[0], {}, strings)
            match = KEY_AT_START.match(message or "")
            plain_match = KEY_AT_START.match(plain or "")
            if not (message and plain and match and plain_match):
                continue
            key = match.group(1).replace("[…]", f".{ITEM}").removesuffix(f".{ITEM}")
            reason = _rule(key.rsplit(".", 1)[-1], plain[plain_match.end():],
                           plain_match.group(2) == ":")
            if re.search(r"[A-Za-z]", reason) and reason not in rules.get(key, []):
                rules.setdefault(key, []).append(reason)
    return rules


# -- types and values ------------------------------------------------------------------------


def _is_section(kind: object) -> bool:
    return dataclasses.is_dataclass(kind) and isinstance(kind, type)


def _array_item(kind: object) -> object | None:
    """X of ``tuple[X, ...]``, else None."""
    args = typing.get_args(kind)
    if typing.get_origin(kind) is tuple and len(args) == 2 and args[1] is Ellipsis:
        return args[0]
    return None


def type_text(kind: object) -> str:
    """How a field's annotation reads in a TOML file."""
    if kind is float:
        return "float"
    if kind is int:
        return "integer"
    if kind is str:
        return "string"
    if kind is bool:
        return "boolean"
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    if origin is Literal:
        return "string"
    if origin in (types.UnionType, typing.Union):
        present = [arg for arg in args if arg is not type(None)]
        if len(present) == 1:
            return f"{type_text(present[0])} (optional)"
    item = _array_item(kind)
    if item is not None:
        return f"array of {type_text(item)}"
    if origin is tuple:
        return "[" + ", ".join(type_text(arg) for arg in args) + "]"
    raise ReferenceError_(f"no TOML form known for the type {kind!r}")


def value_text(value: object) -> str:
    """A default as it would be written in TOML."""
    if value is None:
        return "not set"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if value == int(value) and abs(value) >= 1e4:
            return f"{value:.0e}".replace("e+0", "e").replace("e+", "e")
        return repr(value)
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, tuple | list):
        return "[" + ", ".join(value_text(item) for item in value) + "]"
    return str(value)


def _choices(kind: object) -> tuple[str, ...]:
    if typing.get_origin(kind) is Literal:
        return tuple(str(arg) for arg in typing.get_args(kind))
    return ()


def unit_and_description(name: str, kind: object, comment: str) -> tuple[str, str]:
    """The unit (from the name's suffix, else a numeric field's last ``[unit]`` in its
    comment) and the comment without that unit."""
    unit = next((u for suffix, u in UNIT_SUFFIXES if name.endswith(suffix)), "")
    if not unit and _has_float(kind):
        brackets = re.findall(r"\[([^\[\]]+)\]", comment)
        unit = brackets[-1] if brackets else ""
    description = comment
    if unit:
        description = re.sub(r"\s*\[" + re.escape(unit) + r"\]", "", description, count=1)
    return unit, description.strip().rstrip(";,").strip()


def _has_float(kind: object) -> bool:
    return kind is float or any(_has_float(arg) for arg in typing.get_args(kind))


# -- computed defaults -------------------------------------------------------------------------


def _tracking_default(index: int) -> Callable[[object], str]:
    def default(_: object) -> str:
        by_response = ", ".join(f"{response} {value_text(values[index])}"
                                for response, values in TRACKING_DEFAULTS.items())
        by_flavour = ", ".join(f"{flavour} → {response}"
                               for flavour, response in AUTOPILOT_RESPONSE.items())
        return (f"by `vehicles.response`: {by_response}; real autopilots (`--sitl`, "
                f"`--mavlink`) by flavour ({by_flavour})")
    return default


def _setpoint_timeout_default(value: object) -> str:
    by_flavour = ", ".join(f"{flavour} {value_text(seconds)}"
                           for flavour, seconds in DEFAULT_SETPOINT_TIMEOUT_S.items())
    return f"{value_text(value)} (the flavour's: {by_flavour})"


# Defaults that the loader fills in from other keys, from the tables it fills them from.
COMPUTED_DEFAULTS: dict[str, Callable[[object], str]] = {
    **{f"control.{key}": _tracking_default(i) for i, key in enumerate(TRACKING_KEYS)},
    "vehicles.setpoint_timeout_s": _setpoint_timeout_default,
}


# -- the walk ------------------------------------------------------------------------------------


def sections(root: type = ScenarioConfig, module: types.ModuleType = config_module
             ) -> list[Section]:
    """Every table of a scenario file, in the schema's order, with its keys."""
    helpers = _helper_reasons()
    cross = cross_section_rules(module)
    found: list[Section] = []
    hints = typing.get_type_hints(root)
    comments = field_comments(root)
    for f in dataclasses.fields(root):
        if not f.init or f.name == "source":
            continue
        kind = hints[f.name]
        item = _array_item(kind)
        section_class = item if item is not None and _is_section(item) else kind
        if not _is_section(section_class):
            raise ReferenceError_(f"{f.name}: a top-level key that is not a section")
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        default = None if required or item is not None else _default_of(f)
        _walk_section(f.name, section_class, item is not None, required, default,
                      comments.get(f.name, ""), helpers, cross, found)
    unused = set(cross) - {s.dotted for s in found} - {k.dotted for s in found for k in s.keys}
    if unused:
        raise ReferenceError_(f"rules name keys the schema does not have: {sorted(unused)}")
    return found


def _default_of(f: dataclasses.Field[Any]) -> object:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _walk_section(dotted: str, cls: type, array: bool, required: bool, instance: object,
                  comment: str, helpers: dict[str, str], cross: dict[str, list[str]],
                  found: list[Section]) -> None:
    hints = typing.get_type_hints(cls)
    comments = field_comments(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    rules: dict[str, list[str]] = {}
    own = getattr(cls, "__post_init__", None)
    validators = ((own, None),) if own is not None else ()
    for function, only in (*validators, *VALIDATED_BY.get(cls, ())):
        speaks_for = names if only is None else names & set(only)
        for name, reasons in function_rules(function, speaks_for, helpers).items():
            rules.setdefault(name, []).extend(reasons)
    prefix = f"{dotted}.{ITEM}" if array else dotted
    keys: list[Key] = []
    nested: list[tuple[str, type, bool, object, str]] = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        kind = hints[f.name]
        item = _array_item(kind)
        if _is_section(kind) or (item is not None and _is_section(item)):
            value = getattr(instance, f.name) if instance is not None else _default_of(f)
            sub = item if item is not None else kind
            assert isinstance(sub, type)
            nested.append((f.name, sub, item is not None,
                           None if item is not None else value, comments.get(f.name, "")))
            continue
        key = f"{prefix}.{f.name}"
        field_comment = comments.get(f.name, "")
        if not field_comment:
            raise ReferenceError_(
                f"{key}: no comment beside or above the field in {cls.__qualname__}; the "
                f"reference takes each key's meaning from there")
        unit, meaning = unit_and_description(f.name, kind, field_comment)
        if instance is not None:
            value: object = getattr(instance, f.name)
        else:
            value = _default_of(f)
        if value is dataclasses.MISSING:
            default = "required"
        elif key in COMPUTED_DEFAULTS:
            default = COMPUTED_DEFAULTS[key](value)
        else:
            default = value_text(value)
        choices = _choices(kind)
        valid = [("one of " + ", ".join(f'`"{c}"`' for c in choices))] if choices else []
        for reason in (*rules.get(f.name, ()), *cross.get(key, ())):
            if choices and reason.startswith("must be '"):
                continue  # the choices, said again
            if reason not in valid:
                valid.append(reason)
        keys.append(Key(key, type_text(kind), unit, default, tuple(valid), meaning))
    description = comment or (inspect.getdoc(cls) or "")
    if cls.__doc__ is None or (cls.__doc__ or "").startswith(f"{cls.__name__}("):
        description = comment  # a dataclass's generated signature is no description
    if not description:
        raise ReferenceError_(f"[{dotted}]: {cls.__qualname__} has no docstring and the field "
                              f"holding it no comment")
    found.append(Section(dotted, array, required, re.sub(r"\s+", " ", description).strip(),
                         tuple(cross.get(dotted, ())), tuple(keys)))
    for name, sub, sub_array, value, sub_comment in nested:
        _walk_section(f"{prefix}.{name}", sub, sub_array, False, value, sub_comment, helpers,
                      cross, found)


# -- the page ------------------------------------------------------------------------------------

INTRO = """\
# Config reference

<!-- Generated from the config schema by `{command}`; do not edit by hand.
     tests/tools/test_config_reference.py fails when it is stale. -->

A scenario is one TOML file (`configs/case1.toml` is a complete example, every key with its
unit). Required are `[scenario]` (`name`, `duration_s`), `[swarm]` (`n_drones`, `edges`) and
1 to 16 `[[targets]]` (`trajectory`, `start_m`); every other key may be left out and takes the
default below. `launch-swarm CONFIG --print-config` prints every value a run would use.

A value that breaks a rule is refused before anything starts, with one line naming the key
(exit code 2); so is an unknown key. The *valid* column quotes the code's own rules and
refusals (`…` stands for a number the message fills in). Keys are written dotted, as
`launch-swarm --set KEY=VALUE` and sweep files take them; `<i>` is the index of an entry of an
array of tables (`targets.0.start_m` is the first `[[targets]]` entry's `start_m`).

Sections: {toc}
"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _heading(section: Section) -> str:
    return f"[[{section.dotted}]]" if section.array else f"[{section.dotted}]"


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading (lower case; spaces to '-'; other punctuation dropped)."""
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def render(found: Sequence[Section] | None = None) -> str:
    """The whole page."""
    found = sections() if found is None else found
    toc = ", ".join(f"[`{_heading(s)}`](#{_anchor(s.dotted)})" for s in found
                    if s.dotted.count(".") == 0)
    out = [INTRO.format(command=COMMAND, toc=toc)]
    for section in found:
        out.append(f"## {section.dotted}\n")
        tags = ["required" if section.required else "optional"]
        if section.array:
            tags.append("an array of tables")
        out.append(f"`{_heading(section)}` ({', '.join(tags)}). {section.description}\n")
        for rule in section.rules:
            out.append(f"- Refused: {rule}")
        if section.rules:
            out.append("")
        if section.keys:
            out.append("| key | type | unit | default | valid | meaning |")
            out.append("|---|---|---|---|---|---|")
            for key in section.keys:
                out.append("| " + " | ".join((
                    f"`{key.dotted}`", key.type_text, _cell(key.unit) or "—",
                    _cell(key.default), _cell("; ".join(key.rules)) or "—",
                    _cell(key.description))) + " |")
            out.append("")
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="config_reference", description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="write the reference")
    mode.add_argument("--check", action="store_true",
                      help="exit 1 when the reference differs from what the schema gives")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"the page (default: {DEFAULT_OUTPUT.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    return run_main("config_reference", lambda: _run(args.output, write=args.write))


def _run(output: Path, *, write: bool) -> int:
    text = render()
    if write:
        output.write_text(text, encoding="utf-8")
        print(f"config_reference: wrote {output}")
        return EXIT_OK
    try:
        current = output.read_text(encoding="utf-8")
    except FileNotFoundError:
        current = None
    if current != text:
        print(f"config_reference: {output} is stale (or missing): run `{COMMAND}`",
              file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
