"""What a wire message must satisfy, declared once on its fields (SPEC §12).

Every rule of a message lives in the annotation of its field in the msgspec ``Struct``:

- **what msgspec checks in C while it decodes:** types, ``int >= 0`` (``NonNegativeInt``),
  finite floats (``Finite``, ``NonNegativeFinite``: bounds of ±DBL_MAX, which NaN and ±inf
  fail), bounded strings and lists (``max_length``), literal values;
- **what depends on the swarm**, as ``msgspec.Meta(extra=...)`` markers that msgspec ignores
  and ``SwarmRules`` compiles for one swarm's sizes (``"drones"``, ``"targets"``, ``"state"``,
  ``"rounds"``; a size of None is unbounded):

  ``{"below": size}``     an id or a round: ``value < size``;
  ``{"equals": size}``    a size the sender states: ``value == size``;
  ``{"shape": dims}``     an ``F64Array``'s shape, each dim a size name or an int; every
                          ``F64Array`` field must declare one, and its floats must be finite;
  ``{"length": size}``    a list of exactly ``size`` items;
  ``{"max_items": size}`` a list of at most ``size`` items;
  ``{"distinct": attr}``  list items whose ``attr`` differ;
  ``{"packed": name}``    bytes packed by a layout the codec knows by ``name`` (a consensus
                          message's block: its sizes depend on other fields).

``explain`` turns msgspec's report of a failed constraint (``Expected `float` >= 0.0 - at
`$[4]```) into the field's name and the rule in words, from the same declarations. Nothing
here states a rule a second time.
"""

from __future__ import annotations

import functools
import math
import operator
import re
import sys
from collections.abc import Callable, Mapping
from typing import Annotated, Any, Final

import msgspec
import numpy as np

from swarm.errors import VigilError
from swarm.messages.native import native_finite

_MAX_REASON_CHARS: Final = 300
_LE_F64: Final = np.dtype("<f8")
_FLOAT_MAX: Final = sys.float_info.max

NonNegativeInt = Annotated[int, msgspec.Meta(ge=0)]
# Finite floats: NaN fails every comparison and ±inf the bounds, in msgspec's C decoder.
Finite = Annotated[float, msgspec.Meta(ge=-_FLOAT_MAX, le=_FLOAT_MAX)]
NonNegativeFinite = Annotated[float, msgspec.Meta(ge=0.0, le=_FLOAT_MAX)]

SIZES: Final = ("drones", "targets", "state", "rounds", "reach")

Check = Callable[[Any], None]


class WireError(VigilError, ValueError):
    """A payload (or an outgoing message) that is not a valid wire message.

    ``reason`` (also ``str(error)``) is a single line; ``rule`` is the kind of rule the
    payload broke, one of ``RULES`` (what rejections are counted by).
    """

    def __init__(self, reason: str, *, rule: str = "malformed") -> None:
        reason = " ".join(str(reason).split())
        if len(reason) > _MAX_REASON_CHARS:
            reason = reason[:_MAX_REASON_CHARS - 1] + "…"
        super().__init__(reason)
        self.reason = reason
        self.rule = rule if rule in RULES else "malformed"


# What a rejected payload broke: "size" (over the byte limit), "malformed" (not msgpack, or
# not this message's layout), "kind", "version", "type" (a field of the wrong type), "range"
# (a number below its minimum or an id beyond the swarm), "finite", "shape" (array shapes,
# list lengths and sizes that must be the swarm's), "length" (a string or list too long),
# "duplicate", "value" (not one of the allowed values).
RULES: Final = ("size", "malformed", "kind", "version", "type", "range", "finite", "shape",
                "length", "duplicate", "value")


def fail(reason: str, rule: str) -> None:
    raise WireError(reason, rule=rule)


def all_finite(raw: bytes | bytearray) -> bool:
    """Every float64 in the little-endian bytes ``raw`` (a multiple of 8 long) is finite."""
    values = np.frombuffer(raw, dtype=_LE_F64)
    return bool(np.count_nonzero(np.isfinite(values)) == values.size)  # faster than .all()


def finite_floats(named: list[tuple[str, bytes]], native: bool) -> None:
    """Raise naming the first of ``(name, little-endian float64 bytes)`` that holds a
    non-finite value. ``native``: the machine is little-endian, so a plain sum may say yes."""
    if native and native_finite(*(data for _, data in named)):
        return
    if not native and all_finite(b"".join(data for _, data in named)):
        return
    for name, data in named:
        if not all_finite(data):
            fail(f"{name} contains a non-finite value", "finite")


# -- declarations, read back -------------------------------------------------------------------


def _unwrap(t: Any) -> tuple[Any, dict[str, Any], bool]:
    """(type, swarm markers, optional) of a field's ``msgspec.inspect`` type."""
    extra: dict[str, Any] = {}
    optional = False
    if isinstance(t, msgspec.inspect.UnionType):
        members = [m for m in t.types if not isinstance(m, msgspec.inspect.NoneType)]
        if len(members) == 1 < len(t.types):
            t, optional = members[0], True
    if isinstance(t, msgspec.inspect.Metadata):
        extra = dict(t.extra or {})
        t = t.type
    unknown = set(extra) - {"below", "equals", "shape", "length", "max_items", "distinct",
                            "packed"}
    if unknown:
        raise TypeError(f"unknown wire rule markers {sorted(unknown)}")
    return t, extra, optional


@functools.cache
def _type_info(cls: type) -> Any:
    """``msgspec.inspect.type_info(cls)``, once per class: it evaluates every annotation
    (~0.3 ms for a beacon, 1.4 ms for telemetry), and a flood of refused payloads asks for
    it once each."""
    return msgspec.inspect.type_info(cls)


@functools.cache
def declared_fields(cls: type) -> tuple[tuple[str, Any, dict[str, Any], bool], ...]:
    """(name, msgspec.inspect type, swarm markers, optional) of each field of ``cls``."""
    return tuple((f.name, *_unwrap(f.type)) for f in _type_info(cls).fields)


# -- the swarm's rules, compiled ---------------------------------------------------------------


class SwarmRules:
    """The rules of every message kind that depend on one swarm's sizes, compiled once.

    ``checks[cls](message)`` raises ``WireError`` naming the field, or returns None. ``sizes``
    maps each name of ``SIZES`` to a count (None: unbounded); ``packings`` maps a ``"packed"``
    marker's name to a factory ``(sizes) -> check`` of the whole message.

    Each check is generated as the source of one straight-line Python function from the
    declarations (as ``dataclasses`` generates ``__init__``; ``sources[cls]`` shows it): an
    agent decodes a dozen messages every 20 ms step, and a chain of small closures cost twice
    the time of the hand-written checks this replaced.
    """

    def __init__(self, sizes: Mapping[str, int | None], kinds: tuple[type, ...], *,
                 array_type: type, packings: Mapping[str, Callable[[Mapping[str, int | None]],
                                                                  Check]]) -> None:
        self._sizes = dict(sizes)
        unknown = set(self._sizes) - set(SIZES)
        if unknown:
            raise TypeError(f"unknown swarm sizes {sorted(unknown)}")
        self._array_type = array_type
        self._packings = packings
        self.checks: dict[type, Check] = {}
        self.sources: dict[type, str] = {}
        for cls in kinds:
            self.checks[cls], self.sources[cls] = _Generator(self).compile(cls)

    def size(self, name: str) -> int | None:
        if name not in SIZES:
            raise TypeError(f"wire rule names an unknown swarm size {name!r}")
        return self._sizes.get(name)


class _Generator:
    """Writes the check of one message kind as Python source (see ``SwarmRules``)."""

    def __init__(self, rules: SwarmRules) -> None:
        self._rules = rules
        self._lines: list[str] = []
        self._depth = 1
        self._count = 0
        self._arrays: list[tuple[str, str]] = []  # (label expression, variable)
        self._optional: set[str] = set()  # variables that may be None
        self.env: dict[str, Any] = {
            "_out_of_range": _out_of_range, "_mismatch": _mismatch, "_bad_length": _bad_length,
            "_too_many": _too_many, "_twice": _twice, "_bad_array": _bad_array,
            "_arrays_finite": _arrays_finite, "_native": sys.byteorder == "little",
            "_finite": native_finite}

    def compile(self, cls: type) -> tuple[Check, str]:
        self._struct(cls, "m", "")
        if self._arrays:  # all floats finite: one compiled pass says yes, else numpy names one
            datas = [f"{var}.data" if var not in self._optional else
                     f"({var}.data if {var} is not None else b'')" for _, var in self._arrays]
            pairs = ", ".join(f"({label}, {var})" for label, var in self._arrays)
            self._emit(f"if not (_native and _finite({', '.join(datas)})):")
            self._emit(f"    _arrays_finite(({pairs},))")
        name = f"check_{cls.__name__}"
        source = f"def {name}(m):\n" + "\n".join(self._lines or ["    pass"]) + "\n"
        namespace = dict(self.env)
        exec(compile(source, f"<wire rules of {cls.__name__}>", "exec"), namespace)
        return namespace[name], source

    def _emit(self, line: str) -> None:
        self._lines.append("    " * self._depth + line)

    def _new(self, value: Any = None, prefix: str = "v") -> str:
        self._count += 1
        name = f"{prefix}{self._count}"
        if value is not None:
            self.env[name] = value
        return name

    def _struct(self, cls: type, expr: str, prefix: str) -> None:
        for name, t, extra, optional in declared_fields(cls):
            label = _label(prefix + name)
            var = self._new()
            header = len(self._lines)
            self._emit(f"{var} = {expr}.{name}")
            if optional:
                self._emit(f"if {var} is not None:")
                self._depth += 1
                self._optional.add(var)
            body = len(self._lines)
            self._field(label, var, t, extra, prefix + name)
            if optional:
                self._depth -= 1
            if len(self._lines) == body:  # no rule of this swarm's on this field
                del self._lines[header:]

    def _field(self, label: str, var: str, t: Any, extra: dict[str, Any], path: str) -> None:
        size = self._rules.size
        if isinstance(t, msgspec.inspect.StructType) and t.cls is self._rules._array_type:
            if "shape" not in extra:
                raise TypeError(f"{path}: an array field must declare its shape")
            sized = [d if isinstance(d, int) else size(d) for d in extra["shape"]]
            dims = tuple(d for d in sized if d is not None)
            if len(dims) != len(sized):
                raise TypeError(f"{path}: shape {extra['shape']} names an unbounded size")
            nbytes = 8 * math.prod(dims)
            self._emit(f"if {var}.shape != {dims!r} or len({var}.data) != {nbytes}:")
            self._emit(f"    _bad_array({label}, {var}, {dims!r})")
            self._arrays.append((label, var))
            return
        if "below" in extra and (bound := size(extra["below"])) is not None:
            self._emit(f"if {var} >= {bound}: _out_of_range({label}, {var}, {bound}, "
                       f"{extra['below']!r})")
        if "equals" in extra:
            expected = size(extra["equals"])
            self._emit(f"if {var} != {expected!r}: _mismatch({label}, {var}, {expected!r}, "
                       f"{extra['equals']!r})")
        if "length" in extra:
            expected = size(extra["length"])
            self._emit(f"if len({var}) != {expected!r}: _bad_length({label}, {var}, "
                       f"{expected!r}, {extra['length']!r})")
        if "max_items" in extra and (bound := size(extra["max_items"])) is not None:
            self._emit(f"if len({var}) > {bound}: _too_many({label}, {var}, {bound}, "
                       f"{extra['max_items']!r})")
        if "distinct" in extra:
            key = self._new(operator.attrgetter(extra["distinct"]), "key")
            self._emit(f"if len({var}) > 1 and len(set(map({key}, {var}))) != len({var}):")
            self._emit(f"    _twice({label}, {var}, {key}, {extra['distinct']!r})")
        if "packed" in extra:
            packing = self._new(self._rules._packings[extra["packed"]](self._rules._sizes),
                                "packing")
            self._emit(f"{packing}(m)")
        if isinstance(t, msgspec.inspect.StructType):  # a nested part of the message
            self._struct(t.cls, var, path + ".")
        elif (isinstance(t, msgspec.inspect.VarTupleType | msgspec.inspect.ListType)
              and isinstance(t.item_type, msgspec.inspect.StructType)
              and self._has_rules(t.item_type.cls)):
            index, item = self._new(prefix="k"), self._new(prefix="item")
            self._emit(f"for {index}, {item} in enumerate({var}):")
            self._depth += 1
            self._struct(t.item_type.cls, item, f"{path}[{{{index}}}].")
            self._depth -= 1

    def _has_rules(self, cls: type) -> bool:
        """Whether items of ``cls`` have any swarm rule (else a loop over them is waste)."""
        for _, t, extra, _ in declared_fields(cls):
            if extra or isinstance(t, msgspec.inspect.StructType):
                return True
        return False


def _label(path: str) -> str:
    """The source of an expression giving the field's name (an f-string inside a list)."""
    return f"f{path!r}" if "{" in path else repr(path)


# What the generated checks call on a failure: one place for each reason's words.


def _out_of_range(name: str, value: int, bound: int, size: str) -> None:
    fail(f"{name} {value} out of range (this swarm has {bound} {size})", "range")


def _mismatch(name: str, value: int, expected: int, size: str) -> None:
    fail(f"{name} {value} does not match this swarm's shape ({size} = {expected})", "shape")


def _bad_length(name: str, items: Any, expected: int, size: str) -> None:
    fail(f"{name} holds {len(items)} items, this swarm has {expected} {size}", "shape")


def _too_many(name: str, items: Any, bound: int, size: str) -> None:
    fail(f"{name} holds {len(items)} items, more than this swarm's {bound} {size}", "length")


def _twice(name: str, items: Any, key: Callable[[Any], Any], attr: str) -> None:
    values = list(map(key, items))
    twice = next(v for v in values if values.count(v) > 1)
    fail(f"{attr} {twice} appears twice in {name}", "duplicate")


def _bad_array(name: str, array: Any, shape: tuple[int, ...]) -> None:
    if tuple(array.shape) != shape:
        fail(f"{name} has shape {tuple(array.shape)!s:.60}, expected {shape}", "shape")
    fail(f"{name} carries {len(array.data)} bytes, expected {8 * math.prod(shape)} for shape "
         f"{shape}", "shape")


def _arrays_finite(pairs: tuple[tuple[str, Any], ...]) -> None:
    """Name the first array with a non-finite value (numpy: the sum could not say)."""
    finite_floats([(name, array.data) for name, array in pairs if array is not None],
                  native=False)


# -- msgspec's reports, in the fields' words ---------------------------------------------------

_AT: Final = re.compile(r"^(?P<what>.*) - at `\$(?P<path>(?:\[\d+\])*)`$")
_INDEX: Final = re.compile(r"\[(\d+)\]")


def explain(cls: type, payload: bytes, error: msgspec.ValidationError, kind: str
            ) -> WireError:
    """The error for a payload msgspec refused as a ``cls``: the field by name and, for a
    failed constraint, the rule in words (``time_s is not finite (nan)``)."""
    match = _AT.match(str(error))
    if match is None or not match.group("path"):
        return WireError(f"malformed {kind} message: {error}", rule="malformed")
    indices = [int(k) for k in _INDEX.findall(match.group("path"))]
    try:
        value: Any = msgspec.msgpack.decode(payload)
    except (msgspec.DecodeError, UnicodeDecodeError, RecursionError):
        value = None
    name, t, found = _walk(cls, indices, value, tagged=True)
    if name is None:
        return WireError(f"malformed {kind} message: {error}", rule="malformed")
    if found:
        broken = _broken_rule(name, t, _value_at(value, indices))
        if broken is not None:
            return WireError(broken[0], rule=broken[1])
    return WireError(f"{name}: {match.group('what')}", rule="type")


def _value_at(value: Any, indices: list[int]) -> Any:
    for k in indices:
        value = value[k]
    return value


def _walk(cls: type, indices: list[int], value: Any, *, tagged: bool
          ) -> tuple[str | None, Any, bool]:
    """The dotted name and declared type of the element at ``indices`` of an array-like
    struct (``tagged``: element 0 is its tag), and whether ``value`` has it."""
    name = ""
    t: Any = _type_info(cls)
    found = True
    cursor = value
    for depth, k in enumerate(indices):
        try:
            cursor = cursor[k]
        except (TypeError, IndexError, KeyError):
            found = False
        if isinstance(t, msgspec.inspect.StructType):
            fields = t.fields
            at = k - 1 if (tagged and depth == 0) else k
            if not 0 <= at < len(fields):
                return None, None, False
            field = fields[at]
            name = f"{name}.{field.name}" if name else field.name
            t = _unwrap(field.type)[0]
        elif isinstance(t, msgspec.inspect.VarTupleType | msgspec.inspect.ListType):
            name, t = f"{name}[{k}]", t.item_type
        elif isinstance(t, msgspec.inspect.TupleType):
            if not 0 <= k < len(t.item_types):
                return None, None, False
            name, t = f"{name}[{k}]", t.item_types[k]
        else:
            return None, None, False
        t = _unwrap(t)[0]
    return name or None, t, found


def _broken_rule(name: str, t: Any, value: Any) -> tuple[str, str] | None:
    """(the declared constraint ``value`` breaks in words, its rule); None: a wrong type."""
    is_number = isinstance(value, int | float) and not isinstance(value, bool)
    if isinstance(t, msgspec.inspect.IntType) and type(value) is int \
            and t.ge is not None and value < t.ge:
        return f"{name} must be an integer >= {t.ge}, got {value}", "range"
    if isinstance(t, msgspec.inspect.FloatType) and is_number:
        if isinstance(value, float) and not math.isfinite(value):
            return f"{name} is not finite ({value!r})", "finite"
        if t.ge is not None and value < t.ge:
            return f"{name} must be >= {t.ge!r}, got {value!r}", "range"
    if isinstance(t, msgspec.inspect.StrType) and isinstance(value, str) \
            and t.max_length is not None and len(value) > t.max_length:
        return (f"{name} has length {len(value)}, longer than {t.max_length} characters",
                "length")
    if isinstance(t, msgspec.inspect.VarTupleType | msgspec.inspect.ListType) \
            and isinstance(value, list) and t.max_length is not None \
            and len(value) > t.max_length:
        return f"{name} has length {len(value)}, more than {t.max_length} items", "length"
    if isinstance(t, msgspec.inspect.LiteralType):
        return f"{name} must be one of {t.values}, got {value!r:.40}", "value"
    return None
