"""Typed, versioned, validated wire messages (SPEC §12), encoded as msgpack by msgspec.

Every message is a frozen, array-like msgspec ``Struct`` whose first two elements are its kind
(the msgspec tag) and ``version`` (== ``WIRE_VERSION``). numpy float64 arrays travel as raw
little-endian bytes — ``F64Array`` = [shape, bytes], or for a consensus message one packed block
of every array (``ConsensusWire.data``) — so every value, including -0.0, subnormals and the last
bit of every mantissa, arrives exactly as it was sent; scalar floats are msgpack float64, which
is exact too. A lockstep multi-process run therefore sees bit-identical inputs.

``WireCodec(n_drones, n_targets, n_state)`` knows the sizes of one swarm. ``encode`` checks a
message before it leaves (so a process cannot emit what its peers would reject) and the
``decode_*`` methods check what arrives: message kind, version, ids in range, steps ≥ 0, exact
array shapes and byte lengths, every float finite, bounded strings and lists. Any problem — and
any byte string at all that is not a valid message — raises ``WireError`` with a one-line
reason; nothing else escapes a decoder, and what it allocates is proportional to the payload
(msgspec checks every length prefix against the bytes actually present; payloads over
``max_payload_bytes`` are refused before decoding).

Speed (an agent process encodes and decodes a dozen messages in every 20 ms step, right after
the core's step has left the caches cold, where every numpy entry point costs several µs):
msgspec checks the types, the bounded lengths and ``≥ 0`` of the integers in C while it decodes;
a decoder then takes the short way — a quick check of the rest (ranges that depend on the swarm,
sizes, finiteness as one plain-Python sum over all the floats of a message: a sum of finite
floats is finite unless it overflows) — and only if that fails the long way: decoding again
and the full field-by-field ``validate``, which names the problem or accepts (an overflowing
sum of finite values). ``decode_consensus`` copies the packed block once and hands out views
of it. ``encode_consensus``, ``encode_beacon`` and ``encode_telemetry`` (the agent's own
messages, from the core's types) check the same short way what is not true by construction,
give exactly the bytes of ``encode`` of the ``consensus_to_wire`` / ``BeaconWire.build`` /
``telemetry_from_diagnostics`` message, and take that long way on any doubt.

Conversions to and from the core types: ``consensus_to_wire`` / ``consensus_from_wire`` /
``decode_consensus`` (``ConsensusMessage``), ``CameraFrameWire.build`` / ``.detection_list``
(``Detection``), ``telemetry_from_diagnostics`` / ``TelemetryWire.to_diagnostics``
(``StepDiagnostics``); ``BeaconWire.build`` and ``TruthWire.build`` take numpy arrays.
"""

from __future__ import annotations

import functools
import math
import operator
import sys
from collections.abc import Callable, Sequence
from typing import Annotated, Any, Final, Literal, TypeVar

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from swarm.core.agent import ConsensusMessage, Detection, StepDiagnostics
from swarm.core.records import record
from swarm.errors import VigilError

Array = NDArray[np.float64]
_W = TypeVar("_W")

# 3: a consensus message carries one packed float64 block (ConsensusWire.data) and its sizes.
WIRE_VERSION: Final = 3

MAX_DRONES: Final = 1024  # codec limits: a swarm larger than this is a configuration error
MAX_TARGETS: Final = 1024
MAX_STATE: Final = 64
MAX_LABEL_CHARS: Final = 64  # qp_status, mavlink_state
MAX_TEXT_CHARS: Final = 512  # ClockWire.detail
DEFAULT_MAX_PAYLOAD_BYTES: Final = 1 << 20  # nothing this swarm sends comes close to 1 MiB
_MAX_REASON_CHARS: Final = 300

ClockState = Literal["waiting", "running", "done", "aborted"]
ClockMode = Literal["lockstep", "realtime"]
CLOCK_STATES: Final = ("waiting", "running", "done", "aborted")
CLOCK_MODES: Final = ("lockstep", "realtime")

_LE_F64: Final = np.dtype("<f8")
_F64: Final = np.dtype(np.float64)
# The wire is little-endian: on such a machine a float64 array's own bytes are the wire bytes.
_NATIVE_LE: Final = sys.byteorder == "little"
# What the short ways (the agent's own encoders, the decoders' quick checks) may meet and then
# hand to the long way, which names the problem: an object of another type or shape than the
# core makes, a number too large for msgpack, and for payloads, bytes that do not decode.
_ODD_OBJECT: Final = (AttributeError, TypeError, ValueError, IndexError, KeyError,
                      OverflowError)
_ODD_PAYLOAD: Final = (msgspec.DecodeError, UnicodeDecodeError, *_ODD_OBJECT)

NonNegativeInt = Annotated[int, msgspec.Meta(ge=0)]
_Dim = Annotated[int, msgspec.Meta(ge=0, le=1 << 20)]
_Shape = Annotated[tuple[_Dim, ...], msgspec.Meta(max_length=4)]
Label = Annotated[str, msgspec.Meta(max_length=MAX_LABEL_CHARS)]
Text = Annotated[str, msgspec.Meta(max_length=MAX_TEXT_CHARS)]
Vector3 = tuple[float, float, float]


class WireError(VigilError, ValueError):
    """A payload (or an outgoing message) that is not a valid wire message.

    ``reason`` (also ``str(error)``) is a single line.
    """

    def __init__(self, reason: str) -> None:
        reason = " ".join(str(reason).split())
        if len(reason) > _MAX_REASON_CHARS:
            reason = reason[:_MAX_REASON_CHARS - 1] + "…"
        super().__init__(reason)
        self.reason = reason


# -- building blocks -------------------------------------------------------------------------


class F64Array(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True,
               gc=False):
    """A float64 array as [shape, raw little-endian bytes]: bit-exact, C order."""

    shape: _Shape
    data: bytes

    @classmethod
    def from_array(cls, values: ArrayLike) -> F64Array:
        array = np.ascontiguousarray(values, dtype=_LE_F64)
        return cls(tuple(int(d) for d in array.shape), array.tobytes())

    def to_array(self) -> Array:
        """A new, writable native float64 array (no validation: decoded messages are checked)."""
        return np.frombuffer(self.data, dtype=_LE_F64).reshape(self.shape).astype(np.float64)


def _array_or_none(values: ArrayLike | None) -> F64Array | None:
    return None if values is None else F64Array.from_array(values)


def _le_bytes(values: Any) -> tuple[tuple[int, ...], bytes]:
    """Shape and little-endian float64 bytes (C order) of an array, as ``F64Array`` has them."""
    if _NATIVE_LE and type(values) is np.ndarray and values.dtype is _F64:
        return values.shape, values.tobytes()
    array = np.ascontiguousarray(values, dtype=_LE_F64)
    return tuple(int(d) for d in array.shape), array.tobytes()


def _sum_finite(raw: bytes | bytearray) -> bool:
    """Every native float64 in ``raw`` (a multiple of 8 bytes) is finite, or maybe not (False):
    their sum is finite, unless it overflows. Plain Python, no numpy call: on the agent's hot
    path the data caches are cold after the core's step, and one more numpy entry point
    costs more there than this loop."""
    total = sum(memoryview(raw).cast("d"))
    return total - total == 0.0


def _all_finite(raw: bytes) -> bool:
    """Every float64 in the little-endian bytes ``raw`` (a multiple of 8 long) is finite."""
    values = np.frombuffer(raw, dtype=_LE_F64)
    return np.count_nonzero(np.isfinite(values)) == values.size  # faster than .all()


class _Wire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True,
            gc=False):
    """Base of every message: [kind tag, version, fields...]. Only immutable data, never a
    reference cycle: the garbage collector need not track them (``gc=False``)."""

    version: int = WIRE_VERSION

    def arrays(self) -> dict[str, Array]:
        """Every (present) array field as a new numpy float64 array, by field name."""
        out: dict[str, Array] = {}
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, F64Array):
                out[name] = value.to_array()
        return out


# The arrays of a consensus message in the order ``ConsensusWire.data`` packs them: the ICF pair,
# then (round 0 only) the consensus states as the core packs them (``DroneAgent._gather``).
CONSENSUS_PAIR: Final = ("information", "information_vector")
CONSENSUS_STATES: Final = ("projector_mean", "weight_mean", "projector_integral",
                           "weight_integral", "gramian")


def consensus_shapes(n_targets: int, n_state: int) -> dict[str, tuple[int, ...]]:
    """The shape of each array of a consensus message, in packing order."""
    M, n = n_targets, n_state
    return {"information": (M, n, n), "information_vector": (M, n),
            "projector_mean": (M, 3, 3), "weight_mean": (M,), "projector_integral": (M, 3, 3),
            "weight_integral": (M,), "gramian": (M, 3, 3)}


@functools.lru_cache(maxsize=64)
def _consensus_layout(n_targets: int, n_state: int, with_states: bool
                      ) -> tuple[tuple[str, tuple[int, ...], int, int], ...]:
    """(name, shape, start, stop) of each array in the packed block, in floats."""
    shapes = consensus_shapes(n_targets, n_state)
    names = CONSENSUS_PAIR + CONSENSUS_STATES if with_states else CONSENSUS_PAIR
    layout = []
    start = 0
    for name in names:
        stop = start + math.prod(shapes[name])
        layout.append((name, shapes[name], start, stop))
        start = stop
    return tuple(layout)


class ConsensusWire(_Wire, tag="consensus", kw_only=True):
    """``ConsensusMessage`` on ``agent/<i>/consensus``: the sender's sizes and every array in
    one packed block of little-endian float64 (``data``): [information (M, n, n) |
    information_vector (M, n)], and in round 0 also [projector_mean (M, 3, 3) | weight_mean (M,)
    | projector_integral (M, 3, 3) | weight_integral (M,) | gramian (M, 3, 3)] — C order, the
    packing of the core's own arrays, so that encoding is one join and decoding one view."""

    sender: NonNegativeInt
    step: NonNegativeInt
    round: NonNegativeInt
    n_targets: NonNegativeInt  # M
    n_state: NonNegativeInt  # n
    data: bytes

    def arrays(self) -> dict[str, Array]:
        """Every array this message carries as a new numpy float64 array, by field name of
        ``ConsensusMessage`` (no validation: decoded messages are checked)."""
        message = consensus_from_wire(self)
        return {name: value for name in CONSENSUS_PAIR + CONSENSUS_STATES
                if (value := getattr(message, name)) is not None}


class BeaconWire(_Wire, tag="beacon", kw_only=True):
    """A drone's position on ``agent/<i>/beacon`` (collision avoidance, formation bearings)."""

    sender: NonNegativeInt
    step: NonNegativeInt
    time_s: float
    position_m: Vector3
    # The velocity the drone is flying (its last setpoint) and the age of ``position_m`` when
    # sent: a realtime receiver extrapolates the position to its own instant.
    velocity_m_s: Vector3 = (0.0, 0.0, 0.0)
    sample_age_s: float = 0.0
    # The autopilot's time_boot_ms of the sample ``position_m`` came from (0: not known). A
    # world rendering this drone's camera from this position stamps the frame with it, so the
    # agent measures from the pose the frame was taken at, not from a newer one.
    vehicle_time_ms: NonNegativeInt = 0

    @classmethod
    def build(cls, sender: int, step: int, time_s: float, position_m: ArrayLike, *,
              velocity_m_s: ArrayLike = (0.0, 0.0, 0.0), sample_age_s: float = 0.0,
              vehicle_time_ms: int = 0) -> BeaconWire:
        return cls(sender=int(sender), step=int(step), time_s=float(time_s),
                   position_m=_vector3(position_m), velocity_m_s=_vector3(velocity_m_s),
                   sample_age_s=float(sample_age_s), vehicle_time_ms=int(vehicle_time_ms))

    def position(self) -> Array:
        return np.array(self.position_m, dtype=np.float64)


class DetectionWire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True,
                    gc=False):
    """One detection: target id and image-plane point [x̄, ȳ]."""

    target: NonNegativeInt
    x: float
    y: float


class CameraFrameWire(_Wire, tag="camera", kw_only=True):
    """Drone ``drone``'s detections at ``step`` on ``world/camera/<i>``.

    ``vehicle_time_ms`` is the MAVLink ``time_boot_ms`` of the vehicle position sample that
    belongs to this step (how an agent pairs its LOCAL_POSITION_NED with the frame).
    """

    drone: NonNegativeInt
    step: NonNegativeInt
    time_s: float
    vehicle_time_ms: NonNegativeInt
    detections: Annotated[tuple[DetectionWire, ...], msgspec.Meta(max_length=MAX_TARGETS)] = ()
    target_velocities: F64Array | None = None  # (M, 3), single-integrator model only

    @classmethod
    def build(
        cls,
        drone: int,
        step: int,
        time_s: float,
        vehicle_time_ms: int,
        detections: Sequence[Detection],
        target_velocities: ArrayLike | None = None,
    ) -> CameraFrameWire:
        dets = []
        for d in detections:
            point = np.asarray(d.image_point, dtype=np.float64).reshape(2)
            dets.append(DetectionWire(int(d.target), float(point[0]), float(point[1])))
        return cls(drone=int(drone), step=int(step), time_s=float(time_s),
                   vehicle_time_ms=int(vehicle_time_ms), detections=tuple(dets),
                   target_velocities=_array_or_none(target_velocities))

    def detection_list(self) -> list[Detection]:
        out = []
        for d in self.detections:
            out.append(record(Detection, {
                "target": d.target, "image_point": np.array((d.x, d.y), dtype=np.float64)}))
        return out

    def target_velocity_array(self) -> Array | None:
        return None if self.target_velocities is None else self.target_velocities.to_array()


class TruthWire(_Wire, tag="truth", kw_only=True):
    """Ground truth on ``world/truth`` (recorder only; agents never read it)."""

    step: NonNegativeInt
    time_s: float
    drone_positions: F64Array  # (N, 3)
    target_positions: F64Array  # (M, 3)
    target_velocities: F64Array  # (M, 3)

    @classmethod
    def build(cls, step: int, time_s: float, drone_positions: ArrayLike,
              target_positions: ArrayLike, target_velocities: ArrayLike) -> TruthWire:
        return cls(step=int(step), time_s=float(time_s),
                   drone_positions=F64Array.from_array(drone_positions),
                   target_positions=F64Array.from_array(target_positions),
                   target_velocities=F64Array.from_array(target_velocities))


class ClockWire(_Wire, tag="clock", kw_only=True):
    """The world's clock and run state on ``world/clock``."""

    step: NonNegativeInt
    time_s: float
    state: ClockState
    mode: ClockMode
    detail: Text = ""
    # Malformed inputs the world dropped so far (Zenoh payloads, MAVLink frames at its
    # vehicles): the world has no telemetry of its own, its clock says it.
    rejected_inputs: NonNegativeInt = 0


class TelemetryCounters(msgspec.Struct, frozen=True, array_like=True,
                        forbid_unknown_fields=True, gc=False):
    """Running totals of one agent process (not per step)."""

    qp_fallbacks: NonNegativeInt = 0
    rejected_messages: NonNegativeInt = 0
    missing_neighbour_messages: NonNegativeInt = 0
    stale_neighbour_messages: NonNegativeInt = 0
    late_steps: NonNegativeInt = 0
    steps: NonNegativeInt = 0  # steps run so far (late_steps / steps is the late rate)
    # Age of the freshest neighbour consensus message a step used, from the neighbour's put
    # (Zenoh timestamp; the hop included) to its use; None: none yet (realtime only).
    neighbour_age_ms: float | None = None
    mavlink_state: Label = ""
    # Drones in the live membership this step (the N of the formulas, SPEC §5-§8): the own
    # drone and every drone heard within ``runtime.member_timeout_s``; 0: not reported.
    swarm_size: NonNegativeInt = 0
    # Steps whose QP had no solution within the rate box and was solved without it.
    rate_limit_releases: NonNegativeInt = 0
    # Times the command reference (position setpoints) was reset to the vehicle's position.
    reference_resets: NonNegativeInt = 0
    # Changes of the vehicle the agent did not ask for (mode, disarm, failsafe, lost position).
    vehicle_events: NonNegativeInt = 0
    # This step: ‖p − r‖ of the vehicle against the command reference [m] and ‖v − u‖ of its
    # velocity against the last command [m/s]; None: not measured (no reference, no sample).
    tracking_error_m: float | None = None
    velocity_error_m_s: float | None = None
    # What the agent does about its vehicle (``vehicles.on_vehicle_event``): "" = flying as
    # asked; otherwise the policy in effect and why, e.g. "degraded: mode Hold".
    vehicle_status: Label = ""
    # Localization guarantee (swarm.watch.localization_watch): breaches of λ̄ ≥ ε − tol by this
    # drone's own copies so far (one per target and episode), when the first began [s of
    # mission time; None: none yet], and the targets below the floor now ("" = none).
    lambda_breaches: NonNegativeInt = 0
    first_lambda_breach_s: float | None = None
    localization_status: Label = ""




def _counters_of(kind: type, *, optional: bool = False) -> tuple[str, ...]:
    """The counters declared as ``kind`` (a ``msgspec.inspect`` type; ``optional``: as
    ``kind | None``), in field order: the groups the checks and the fast encoder walk are read
    from ``TelemetryCounters``' annotations, not listed a second time."""
    names = []
    for f in msgspec.inspect.type_info(TelemetryCounters).fields:
        t, is_optional = f.type, False
        if isinstance(t, msgspec.inspect.UnionType):
            members = [m for m in t.types if not isinstance(m, msgspec.inspect.NoneType)]
            t, is_optional = members[0], len(members) == 1 < len(t.types)
        if isinstance(t, kind) and is_optional == optional:
            names.append(f.name)
    return tuple(names)


# The counters that are integers >= 0, floats (checked >= 0) or None, and bounded labels;
# tests/messages/test_wire.py checks that every counter is in exactly one group.
_INT_COUNTERS: Final = _counters_of(msgspec.inspect.IntType)
_OPTIONAL_FLOAT_COUNTERS: Final = _counters_of(msgspec.inspect.FloatType, optional=True)
_LABEL_COUNTERS: Final = _counters_of(msgspec.inspect.StrType)


class TelemetryWire(_Wire, tag="telemetry", kw_only=True):
    """One agent step on ``agent/<i>/telemetry``: every ``StepDiagnostics`` field (``drone_id``
    is ``drone``), the drone's position and the process's running ``counters``."""

    drone: NonNegativeInt
    step: NonNegativeInt
    time_s: float
    position_m: Vector3
    velocity: F64Array  # (3,)
    nominal_velocity: F64Array  # (3,)
    estimates: F64Array  # (M, n)
    lambda_bar: F64Array  # (M,)
    psi0: F64Array  # (M,)
    psi1: F64Array  # (M,)
    weights: F64Array  # (M,)
    weight_sum_estimate: F64Array  # (M,)
    slacks: F64Array  # (M,)
    weight_slacks: F64Array  # (M,)
    detected: Annotated[tuple[bool, ...], msgspec.Meta(max_length=MAX_TARGETS)]  # (M,)
    control_active: bool
    qp_status: Label
    qp_iterations: NonNegativeInt
    qp_fallback: bool
    qp_solve_us: float
    step_us: float
    bearing_error: float | None = None
    missing_neighbour_messages: NonNegativeInt = 0  # this step
    rejected_inputs: NonNegativeInt = 0  # this step
    counters: TelemetryCounters = TelemetryCounters()
    rate_limit_released: bool = False  # this step's QP was solved without the rate box

    @classmethod
    def from_diagnostics(cls, diag: StepDiagnostics, position: ArrayLike,
                         counters: TelemetryCounters | None = None,
                         **counter_fields: Any) -> TelemetryWire:
        """Same as ``telemetry_from_diagnostics``."""
        return telemetry_from_diagnostics(diag, position, counters, **counter_fields)

    def position(self) -> Array:
        return np.array(self.position_m, dtype=np.float64)

    def to_diagnostics(self) -> StepDiagnostics:
        """The ``StepDiagnostics`` this message was made from (arrays bit-exact)."""
        a = self.arrays()
        return StepDiagnostics(
            drone_id=self.drone, step=self.step, time_s=self.time_s,
            velocity=a["velocity"], nominal_velocity=a["nominal_velocity"],
            estimates=a["estimates"], lambda_bar=a["lambda_bar"], psi0=a["psi0"],
            psi1=a["psi1"], weights=a["weights"], weight_sum_estimate=a["weight_sum_estimate"],
            slacks=a["slacks"], weight_slacks=a["weight_slacks"],
            detected=np.array(self.detected, dtype=bool), control_active=self.control_active,
            qp_status=self.qp_status, qp_iterations=self.qp_iterations,
            qp_fallback=self.qp_fallback, qp_solve_us=self.qp_solve_us, step_us=self.step_us,
            bearing_error=self.bearing_error,
            missing_neighbour_messages=self.missing_neighbour_messages,
            rejected_inputs=self.rejected_inputs,
            rate_limit_released=self.rate_limit_released,
        )


WireMessage = (ConsensusWire | BeaconWire | CameraFrameWire | TruthWire | ClockWire
               | TelemetryWire)
_KINDS: Final[dict[type, str]] = {
    ConsensusWire: "consensus", BeaconWire: "beacon", CameraFrameWire: "camera",
    TruthWire: "truth", ClockWire: "clock", TelemetryWire: "telemetry",
}


class _Header(msgspec.Struct, array_like=True):
    """The first two elements of any message; used only to explain a failed decode."""

    kind: str
    version: int


# -- conversions from the core types -----------------------------------------------------------


def consensus_to_wire(message: ConsensusMessage) -> ConsensusWire:
    """The wire form of ``message`` (sizes from its ``information``; not validated for a swarm:
    ``WireCodec.encode`` does that). Raises ``WireError`` if its arrays do not fit together
    (shapes that disagree, or only some of the round-0 states)."""
    information = np.asarray(message.information)
    if information.ndim != 3 or information.shape[1] != information.shape[2]:
        raise WireError(f"information has shape {information.shape!s:.60}, expected (M, n, n)")
    M, n = int(information.shape[0]), int(information.shape[1])
    states = [getattr(message, name) for name in CONSENSUS_STATES]
    present = [value is not None for value in states]
    if any(present) and not all(present):
        missing = [name for name, there in zip(CONSENSUS_STATES, present, strict=True)
                   if not there]
        raise WireError(f"round-0 consensus states incomplete: {', '.join(missing)} missing")
    parts = [information, message.information_vector]
    if all(present):
        parts += states
    chunks = []
    for (name, shape, _, _), value in zip(_consensus_layout(M, n, all(present)), parts,
                                          strict=True):
        got, raw = _le_bytes(value)
        if got != shape:
            raise WireError(f"{name} has shape {got!s:.60}, expected {shape}")
        chunks.append(raw)
    return ConsensusWire(sender=_plain_int(message.sender), step=_plain_int(message.step),
                         round=_plain_int(message.round), n_targets=M, n_state=n,
                         data=b"".join(chunks))


def _plain_int(value: Any) -> Any:
    """``int(value)`` for an integer (numpy ones included); anything else as it is, for the
    checks to name."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        return value
    return int(value)


def consensus_from_wire(wire: ConsensusWire) -> ConsensusMessage:
    """The ``ConsensusMessage`` of a (checked) wire message: its arrays are writable,
    C-contiguous views of one new native float64 array, bit-exact."""
    M, n = wire.n_targets, wire.n_state
    floats = len(wire.data) // 8
    layout = _consensus_layout(M, n, True)
    if floats != layout[-1][3] or len(wire.data) % 8:
        layout = _consensus_layout(M, n, False)
        if floats != layout[-1][3] or len(wire.data) % 8:
            raise WireError(f"consensus data of {len(wire.data)} bytes does not fit M = {M}, "
                            f"n = {n}")
    block = np.frombuffer(wire.data, dtype=_LE_F64).astype(np.float64)
    fields: dict[str, Any] = dict.fromkeys(CONSENSUS_STATES)
    for name, shape, start, stop in layout:
        view = block[start:stop]
        view.shape = shape
        fields[name] = view
    return _new_message(wire.sender, wire.step, wire.round, fields)


_NO_STATES: Final = dict.fromkeys(CONSENSUS_STATES)
_shape_of: Final = operator.attrgetter("shape")
_dtype_of: Final = operator.attrgetter("dtype")
_tobytes: Final = np.ndarray.tobytes
_ndarray: Final = np.ndarray
_BOOL: Final = np.dtype(np.bool_)


def _new_message(sender: int, step: int, rnd: int, arrays: dict[str, Any]) -> ConsensusMessage:
    """``ConsensusMessage(...)``, every field given (``swarm.core.records``)."""
    return record(ConsensusMessage, {"sender": sender, "step": step, "round": rnd, **arrays})


def _vector3(values: ArrayLike) -> Vector3:
    if type(values) is np.ndarray and values.dtype is _F64 and values.shape == (3,):
        x, y, z = values.tolist()  # Python floats, bit-exact
        return (x, y, z)
    array = np.asarray(values, dtype=np.float64).reshape(3)
    return (float(array[0]), float(array[1]), float(array[2]))


def telemetry_from_diagnostics(
    diag: StepDiagnostics,
    position: ArrayLike,
    counters: TelemetryCounters | None = None,
    **counter_fields: Any,
) -> TelemetryWire:
    """Telemetry for one step: ``diag`` as it is, the drone's ``position`` and the totals.

    The totals come either as ``counters`` or as ``TelemetryCounters`` keyword fields
    (``qp_fallbacks=…, late_steps=…, neighbour_age_ms=…, mavlink_state=…``). A NaN
    ``neighbour_age_ms`` means "no neighbour message yet" and is sent as None.
    """
    return _telemetry(diag, position, _counters(counters, counter_fields))


def _counters(counters: TelemetryCounters | None,
              counter_fields: dict[str, Any]) -> TelemetryCounters:
    if not counter_fields:
        return counters if counters is not None else _NO_COUNTERS
    if counters is not None:
        raise TypeError("pass counters or counter keyword fields, not both")
    if not _COUNTER_NAMES.issuperset(counter_fields):
        unknown = set(counter_fields) - _COUNTER_NAMES
        raise TypeError(f"unknown telemetry counters: {sorted(unknown)}")
    for name in _OPTIONAL_FLOAT_COUNTERS:
        value = counter_fields.get(name)
        if value is not None and isinstance(value, float | int) and math.isnan(value):
            counter_fields[name] = None
        elif value is not None:
            counter_fields[name] = float(value)
    return TelemetryCounters(**counter_fields)


_NO_COUNTERS: Final = TelemetryCounters()
_COUNTER_NAMES: Final = frozenset(TelemetryCounters.__struct_fields__)
_COUNTER_FIELDS: Final = TelemetryCounters.__struct_fields__
_COUNTER_DEFAULTS: Final = msgspec.structs.astuple(_NO_COUNTERS)
# The arrays of a telemetry message, in field order: its F64Array fields.
TELEMETRY_ARRAYS: Final = tuple(
    f.name for f in msgspec.inspect.type_info(TelemetryWire).fields
    if isinstance(f.type, msgspec.inspect.StructType) and f.type.cls is F64Array)
# WireCodec's encode_* write these messages as plain tuples in this field order.
assert TelemetryWire.__struct_fields__ == (
    "version", "drone", "step", "time_s", "position_m", *TELEMETRY_ARRAYS, "detected",
    "control_active", "qp_status", "qp_iterations", "qp_fallback", "qp_solve_us", "step_us",
    "bearing_error", "missing_neighbour_messages", "rejected_inputs", "counters",
    "rate_limit_released")
assert BeaconWire.__struct_fields__ == ("version", "sender", "step", "time_s", "position_m",
                                        "velocity_m_s", "sample_age_s", "vehicle_time_ms")
assert ConsensusWire.__struct_fields__ == ("version", "sender", "step", "round", "n_targets",
                                           "n_state", "data")


def _telemetry(diag: StepDiagnostics, position: ArrayLike,
               counters: TelemetryCounters) -> TelemetryWire:
    arrays: dict[str, F64Array] = {}
    for name in TELEMETRY_ARRAYS:
        arrays[name] = F64Array(*_le_bytes(getattr(diag, name)))
    detected = diag.detected
    if type(detected) is np.ndarray and detected.dtype == np.bool_:
        flags = tuple(detected.reshape(-1).tolist())
    else:
        flags = tuple(bool(v) for v in np.asarray(detected).reshape(-1))
    bearing = diag.bearing_error
    return TelemetryWire(
        drone=int(diag.drone_id), step=int(diag.step), time_s=float(diag.time_s),
        position_m=_vector3(position), **arrays, detected=flags,
        control_active=bool(diag.control_active), qp_status=str(diag.qp_status),
        qp_iterations=int(diag.qp_iterations), qp_fallback=bool(diag.qp_fallback),
        qp_solve_us=float(diag.qp_solve_us), step_us=float(diag.step_us),
        bearing_error=None if bearing is None else float(bearing),
        missing_neighbour_messages=int(diag.missing_neighbour_messages),
        rejected_inputs=int(diag.rejected_inputs), counters=counters,
        rate_limit_released=bool(diag.rate_limit_released))


# -- validation --------------------------------------------------------------------------------


def _fail(reason: str) -> None:
    raise WireError(reason)


def _check_int(name: str, value: Any, upper: int | None = None) -> None:
    if type(value) is not int or value < 0:  # bool is not an id or a count
        _fail(f"{name} must be an integer >= 0, got {value!r:.40}")
    if upper is not None and value >= upper:
        _fail(f"{name} {value} out of range (this swarm has {upper})")


def _check_float(name: str, value: Any, *, non_negative: bool = False) -> None:
    if not isinstance(value, float | int) or isinstance(value, bool):
        _fail(f"{name} must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        _fail(f"{name} is not finite ({value!r})")
    if non_negative and value < 0:
        _fail(f"{name} must be >= 0, got {value!r}")


def _check_vector3(name: str, value: Any) -> None:
    if not isinstance(value, tuple | list) or len(value) != 3:
        _fail(f"{name} must be 3 numbers")
    for k, v in enumerate(value):
        _check_float(f"{name}[{k}]", v)


def _check_bool(name: str, value: Any) -> None:
    if type(value) is not bool:
        _fail(f"{name} must be a bool, got {type(value).__name__}")


def _check_str(name: str, value: Any, limit: int) -> None:
    if type(value) is not str:
        _fail(f"{name} must be a string, got {type(value).__name__}")
    if len(value) > limit:
        _fail(f"{name} longer than {limit} characters")


class _Arrays:
    """Checks the arrays of one message: shapes and lengths one by one, finiteness in one pass
    over all of them (one numpy call instead of one per array)."""

    __slots__ = ("_checked",)

    def __init__(self) -> None:
        self._checked: list[tuple[str, bytes]] = []

    def check(self, name: str, value: Any, shape: tuple[int, ...]) -> None:
        if not isinstance(value, F64Array):
            _fail(f"{name} missing" if value is None else f"{name} must be an F64Array")
        got = tuple(value.shape)
        if got != shape:
            _fail(f"{name} has shape {got!s:.60}, expected {shape}")
        if type(value.data) is not bytes or len(value.data) != 8 * math.prod(shape):
            _fail(f"{name} carries {len(value.data)} bytes, expected {8 * math.prod(shape)} "
                  f"for shape {shape}")
        self._checked.append((name, value.data))

    def all_finite(self) -> None:
        if not self._checked:
            return
        joined = b"".join(data for _, data in self._checked)
        if np.isfinite(np.frombuffer(joined, dtype=_LE_F64)).all():
            return
        for name, data in self._checked:
            if not np.isfinite(np.frombuffer(data, dtype=_LE_F64)).all():
                _fail(f"{name} contains a non-finite value")


class WireCodec:
    """Encodes wire messages and decodes+validates them for one swarm's sizes.

    ``n_state`` is the ICF state dimension (6: double integrator, 3: single integrator);
    ``n_rounds``, if given, bounds a consensus message's ``round`` (0 ≤ round < n_rounds).
    One codec may be shared by threads (zenoh callback threads and the agent's own): msgspec
    keeps per-call state local and the checks here keep none.
    """

    def __init__(self, n_drones: int, n_targets: int, n_state: int, *,
                 n_rounds: int | None = None,
                 max_payload_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES) -> None:
        for name, value, upper in (("n_drones", n_drones, MAX_DRONES),
                                   ("n_targets", n_targets, MAX_TARGETS),
                                   ("n_state", n_state, MAX_STATE)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= upper:
                raise ValueError(f"WireCodec: {name} must be an integer in [1, {upper}], "
                                 f"got {value!r}")
        if n_rounds is not None and (isinstance(n_rounds, bool) or not isinstance(n_rounds, int)
                                     or n_rounds < 1):
            raise ValueError(f"WireCodec: n_rounds must be a positive integer, got {n_rounds!r}")
        if isinstance(max_payload_bytes, bool) or not isinstance(max_payload_bytes, int) \
                or max_payload_bytes < 1:
            raise ValueError("WireCodec: max_payload_bytes must be a positive integer")
        self.n_drones, self.n_targets, self.n_state = n_drones, n_targets, n_state
        self.n_rounds = n_rounds
        self.max_payload_bytes = max_payload_bytes
        self._encoder = msgspec.msgpack.Encoder()
        self._decoders: dict[type, msgspec.msgpack.Decoder[Any]] = {
            cls: msgspec.msgpack.Decoder(cls) for cls in _KINDS}
        self._header = msgspec.msgpack.Decoder(_Header)
        self._checks: dict[type, Callable[[Any], None]] = {
            ConsensusWire: self._check_consensus, BeaconWire: self._check_beacon,
            CameraFrameWire: self._check_camera, TruthWire: self._check_truth,
            ClockWire: self._check_clock, TelemetryWire: self._check_telemetry,
        }
        # Sufficient checks of a decoded message (msgspec has checked the types): True means
        # valid; False means "ask validate", which names the problem or accepts.
        self._quick: dict[type, Callable[[Any], bool]] = {
            ConsensusWire: self._quick_consensus, BeaconWire: self._quick_beacon,
            CameraFrameWire: self._quick_camera, TruthWire: self._quick_truth,
            ClockWire: self._quick_clock, TelemetryWire: self._quick_telemetry,
        }
        self._consensus_decoder = self._decoders[ConsensusWire]
        self._beacon_decoder = self._decoders[BeaconWire]
        M, n = n_targets, n_state
        shapes = tuple(consensus_shapes(M, n).values())
        self._consensus_shapes = (shapes[:2], shapes)  # by round == 0
        self._consensus_arrays = operator.attrgetter(*CONSENSUS_PAIR, *CONSENSUS_STATES)
        self._consensus_dtypes = ((_F64,) * 2, (_F64,) * 7)
        # (name, shape, byte offset) of each array in the packed block; round > 0 has no states.
        self._consensus_views = tuple(
            tuple((name, shape, 8 * start) for name, shape, start, _ in layout)
            for layout in (_consensus_layout(M, n, False), _consensus_layout(M, n, True)))
        self._consensus_bytes = (8 * _consensus_layout(M, n, False)[-1][3],  # round > 0
                                 8 * _consensus_layout(M, n, True)[-1][3])  # round 0
        # The shapes of TELEMETRY_ARRAYS: velocity, nominal_velocity, estimates, then the
        # per-target series.
        self._telemetry_shapes = ((3,), (3,), (M, n)) + ((M,),) * (len(TELEMETRY_ARRAYS) - 3)
        self._telemetry_arrays = operator.attrgetter(*TELEMETRY_ARRAYS)
        # What the arrays must be for the short way: native float64 = the wire's little-endian.
        self._telemetry_dtypes = (_F64 if _NATIVE_LE else None,) * len(TELEMETRY_ARRAYS)
        self._telemetry_sizes = tuple(8 * math.prod(s) for s in self._telemetry_shapes)

    # -- encode --------------------------------------------------------------------------

    consensus_to_wire = staticmethod(consensus_to_wire)
    consensus_from_wire = staticmethod(consensus_from_wire)

    def encode(self, message: WireMessage | ConsensusMessage) -> bytes:
        """Validate ``message`` (a ``ConsensusMessage`` is converted first) and return bytes.

        Raises ``WireError`` if it is not a message this swarm's peers would accept.
        """
        if isinstance(message, ConsensusMessage):
            return self.encode_consensus(message)
        self.validate(message)
        return self._encode_checked(message)

    def _encode_checked(self, message: WireMessage) -> bytes:
        try:
            payload = self._encoder.encode(message)
        except (TypeError, ValueError, OverflowError, msgspec.EncodeError) as exc:
            raise WireError(f"cannot encode {type(message).__name__}: {exc}") from None
        if len(payload) > self.max_payload_bytes:
            raise WireError(f"{type(message).__name__} is {len(payload)} bytes, over the "
                            f"{self.max_payload_bytes}-byte limit")
        return payload

    # The agent's own messages. Each gives exactly the bytes of ``encode`` of the message built
    # the usual way (tests hold them to that), as the plain tuple msgspec encodes the same as the
    # array-like struct, and checks what is not true by construction: ids and counts, shapes and
    # dtypes, bounded strings, and every float finite (one sum over the raw bytes of all arrays,
    # ``_sum_finite``). Anything unusual goes the usual way (``encode``), whose ``validate``
    # names the problem or, if there is none after all (an overflowing sum), encodes.

    def encode_consensus(self, message: ConsensusMessage) -> bytes:
        """``encode(consensus_to_wire(message))`` for the core's own message."""
        sender, step, rnd = message.sender, message.step, message.round
        try:
            if (_NATIVE_LE and type(sender) is int and 0 <= sender < self.n_drones
                    and type(step) is int and step >= 0 and type(rnd) is int and rnd >= 0
                    and (self.n_rounds is None or rnd < self.n_rounds)):
                first = rnd == 0
                arrays = self._consensus_arrays(message)
                if not first and message.gramian is None and message.weight_mean is None \
                        and message.projector_mean is None and message.weight_integral is None \
                        and message.projector_integral is None:
                    arrays = arrays[:2]  # later rounds carry the ICF pair alone
                if (tuple(map(_shape_of, arrays)) == self._consensus_shapes[first]
                        and tuple(map(_dtype_of, arrays)) == self._consensus_dtypes[first]
                        and _sum_finite(raw := b"".join(map(_tobytes, arrays)))):
                    return self._encoder.encode(("consensus", WIRE_VERSION, sender, step, rnd,
                                                 self.n_targets, self.n_state, raw))
        except _ODD_OBJECT:  # something unusual (None, not an array): the usual way says what
            pass
        try:
            wire = consensus_to_wire(message)
        except WireError:
            raise
        except _ODD_OBJECT as exc:  # arrays that are not numbers at all
            raise WireError(f"cannot encode ConsensusMessage: {type(exc).__name__}: {exc}"
                            ) from None
        return self.encode(wire)

    def encode_beacon(self, sender: int, step: int, time_s: float, position_m: ArrayLike, *,
                      velocity_m_s: ArrayLike = (0.0, 0.0, 0.0), sample_age_s: float = 0.0,
                      vehicle_time_ms: int = 0) -> bytes:
        """``encode(BeaconWire.build(...))`` with the same arguments."""
        sender, step, t, age = int(sender), int(step), float(time_s), float(sample_age_s)
        stamp = int(vehicle_time_ms)
        p, v = _vector3(position_m), _vector3(velocity_m_s)
        total = t + age + p[0] + p[1] + p[2] + v[0] + v[1] + v[2]
        if (0 <= sender < self.n_drones and step >= 0 and t >= 0.0 and age >= 0.0
                and stamp >= 0 and total - total == 0.0):
            return self._encoder.encode(
                ("beacon", WIRE_VERSION, sender, step, t, p, v, age, stamp))
        return self.encode(BeaconWire(sender=sender, step=step, time_s=t, position_m=p,
                                      velocity_m_s=v, sample_age_s=age, vehicle_time_ms=stamp))

    def encode_telemetry(self, diag: StepDiagnostics, position: ArrayLike,
                         counters: TelemetryCounters | None = None,
                         **counter_fields: Any) -> bytes:
        """``encode(telemetry_from_diagnostics(diag, position, counters, **counter_fields))``."""
        try:
            payload = self._telemetry_payload(diag, position, counters, counter_fields)
        except _ODD_OBJECT:  # something unusual: the usual way says what
            payload = None
        if payload is None:
            return self.encode(telemetry_from_diagnostics(diag, position, counters,
                                                          **counter_fields))
        return payload

    def _telemetry_payload(self, diag: StepDiagnostics, position: ArrayLike,
                           counters: TelemetryCounters | None,
                           fields: dict[str, Any]) -> bytes | None:
        """The payload of ``encode_telemetry``, or None if anything needs a closer look."""
        if counters is None and _COUNTER_NAMES.issuperset(fields):
            values = dict(zip(_COUNTER_FIELDS, map(fields.get, _COUNTER_FIELDS,
                                                   _COUNTER_DEFAULTS), strict=True))
            for name in _OPTIONAL_FLOAT_COUNTERS:
                value = values[name]
                if value is not None and value != value:  # NaN: not measured
                    values[name] = None
        elif not fields and type(counters) is TelemetryCounters:
            values = dict(zip(_COUNTER_FIELDS, msgspec.structs.astuple(counters), strict=True))
        else:
            return None
        counts = [values[name] for name in _INT_COUNTERS]
        if set(map(type, counts)) != {int} or min(counts) < 0:
            return None
        for name in _LABEL_COUNTERS:
            label = values[name]
            if type(label) is not str or len(label) > MAX_LABEL_CHARS:
                return None
        measured = 0.0
        for name in _OPTIONAL_FLOAT_COUNTERS:
            value = values[name]
            if value is not None:
                if not (type(value) is float and value >= 0.0):
                    return None
                measured += value
        totals = tuple(values.values())
        arrays = self._telemetry_arrays(diag)
        if (tuple(map(_shape_of, arrays)) != self._telemetry_shapes
                or tuple(map(_dtype_of, arrays)) != self._telemetry_dtypes):
            return None
        chunks = tuple(map(_tobytes, arrays))
        detected = diag.detected
        if (not _sum_finite(b"".join(chunks))
                or type(detected) is not np.ndarray or detected.dtype is not _BOOL
                or detected.shape != (self.n_targets,)):
            return None
        drone, step, t = int(diag.drone_id), int(diag.step), float(diag.time_s)
        iterations, status = int(diag.qp_iterations), str(diag.qp_status)
        solve_us, step_us = float(diag.qp_solve_us), float(diag.step_us)
        bearing = None if diag.bearing_error is None else float(diag.bearing_error)
        missing, rejected = int(diag.missing_neighbour_messages), int(diag.rejected_inputs)
        p = _vector3(position)
        total = t + solve_us + step_us + p[0] + p[1] + p[2] + measured + (bearing or 0.0)
        if not (0 <= drone < self.n_drones and min(step, iterations, missing, rejected) >= 0
                and len(status) <= MAX_LABEL_CHARS and t >= 0.0 and solve_us >= 0.0
                and step_us >= 0.0 and total - total == 0.0):
            return None
        payload = self._encoder.encode((
            "telemetry", WIRE_VERSION, drone, step, t, p,
            *zip(self._telemetry_shapes, chunks, strict=True),
            tuple(detected.tolist()), bool(diag.control_active), status, iterations,
            bool(diag.qp_fallback), solve_us, step_us, bearing, missing, rejected, totals,
            bool(diag.rate_limit_released)))
        return payload if len(payload) <= self.max_payload_bytes else None

    def validate(self, message: WireMessage) -> None:
        """Raise ``WireError`` unless ``message`` is a valid message for this swarm."""
        check = self._checks.get(type(message))
        if check is None:
            raise WireError(f"not a wire message: {type(message).__name__}")
        if message.version != WIRE_VERSION:
            raise WireError(self._version_reason(_KINDS[type(message)], message.version))
        try:
            check(message)
        except WireError:
            raise
        except _ODD_OBJECT as exc:  # a hand-built message with wrong field types
            raise WireError(f"invalid {type(message).__name__}: {type(exc).__name__}: {exc}"
                            ) from None

    # -- decode --------------------------------------------------------------------------

    def decode_consensus(self, payload: bytes) -> ConsensusMessage:
        """The ``ConsensusMessage`` in ``payload``, checked; its arrays are writable,
        C-contiguous views of one new float64 array (as ``consensus_from_wire`` makes them)."""
        if _NATIVE_LE and type(payload) is bytes and len(payload) <= self.max_payload_bytes:
            try:
                wire = self._consensus_decoder.decode(payload)
                if self._quick_consensus_sizes(wire):
                    # One writable copy, its finiteness checked, the arrays views into it.
                    buffer = bytearray(wire.data)
                    if _sum_finite(buffer):
                        first = wire.round == 0
                        fields = {name: _ndarray(shape, _F64, buffer, offset)
                                  for name, shape, offset in self._consensus_views[first]}
                        if not first:
                            fields.update(_NO_STATES)
                        fields["sender"], fields["step"] = wire.sender, wire.step
                        fields["round"] = wire.round
                        return record(ConsensusMessage, fields)
            except _ODD_PAYLOAD:  # the long way says what is wrong
                pass
        wire = self._decode_checked(payload, ConsensusWire)
        try:
            return consensus_from_wire(wire)
        except _ODD_OBJECT as exc:  # cannot happen for a checked message; never escapes anyway
            raise WireError(f"internal decoder error on consensus payload: "
                            f"{type(exc).__name__}: {exc}") from None

    def decode_consensus_wire(self, payload: bytes) -> ConsensusWire:
        return self._decode(payload, ConsensusWire)

    def decode_beacon(self, payload: bytes) -> BeaconWire:
        # ``_decode`` spelled out: a drone decodes every other drone's beacon every step.
        if type(payload) is bytes and len(payload) <= self.max_payload_bytes:
            try:
                message = self._beacon_decoder.decode(payload)
                if self._quick_beacon(message):
                    return message
            except _ODD_PAYLOAD:  # the long way says what is wrong
                pass
        return self._decode_checked(payload, BeaconWire)

    def decode_camera(self, payload: bytes) -> CameraFrameWire:
        return self._decode(payload, CameraFrameWire)

    def decode_truth(self, payload: bytes) -> TruthWire:
        return self._decode(payload, TruthWire)

    def decode_clock(self, payload: bytes) -> ClockWire:
        return self._decode(payload, ClockWire)

    def decode_telemetry(self, payload: bytes) -> TelemetryWire:
        return self._decode(payload, TelemetryWire)

    def _decode(self, payload: Any, cls: type[_W],
                quick: Callable[[Any], bool] | None = None) -> _W:
        """Decode and check: a valid message the short way (msgspec, then the quick check),
        anything else again the long way (``_decode_checked``), which says what is wrong."""
        if type(payload) is bytes and len(payload) <= self.max_payload_bytes:
            try:
                message = self._decoders[cls].decode(payload)
                if (quick or self._quick[cls])(message):
                    return message
            except _ODD_PAYLOAD:  # bytes that do not decode, a quick check that tripped
                pass
        return self._decode_checked(payload, cls)

    def _decode_checked(self, payload: Any, cls: type[_W]) -> _W:
        kind = _KINDS[cls]
        try:
            if not isinstance(payload, bytes | bytearray | memoryview):
                raise WireError(f"{kind} payload must be bytes, got {type(payload).__name__}")
            if len(payload) > self.max_payload_bytes:
                raise WireError(f"{kind} payload of {len(payload)} bytes exceeds the "
                                f"{self.max_payload_bytes}-byte limit")
            try:
                message = self._decoders[cls].decode(payload)
            except msgspec.DecodeError as exc:  # includes msgspec.ValidationError
                raise WireError(self._explain(payload, kind, exc)) from None
            except UnicodeDecodeError:  # msgspec raises this, not DecodeError, for bad UTF-8
                raise WireError(f"malformed {kind} message: a string is not valid UTF-8"
                                ) from None
            if not _quick_ok(self._quick[cls], message):
                self.validate(message)
            return message
        except WireError:
            raise
        except Exception as exc:  # the one boundary: nothing but WireError leaves a decoder
            raise WireError(f"internal decoder error on {kind} payload: "
                            f"{type(exc).__name__}: {exc}") from None

    @staticmethod
    def _version_reason(kind: str, version: Any) -> str:
        return (f"{kind} message has wire version {version!r:.20}, this build speaks version "
                f"{WIRE_VERSION}")

    def _explain(self, payload: Any, kind: str, exc: Exception) -> str:
        """Why a payload failed to decode: wrong kind and wrong version say so explicitly."""
        try:
            header = self._header.decode(payload)
        except _ODD_PAYLOAD:
            return f"malformed {kind} message: {exc}"
        if header.kind != kind:
            shown = header.kind if header.kind in _KINDS.values() else f"{header.kind!r:.40}"
            return f"expected a {kind} message, got {shown}"
        if header.version != WIRE_VERSION:
            return self._version_reason(kind, header.version)
        return f"malformed {kind} message: {exc}"

    # -- per-kind checks -----------------------------------------------------------------

    def _check_consensus(self, m: ConsensusWire) -> None:
        M, n = self.n_targets, self.n_state
        _check_int("sender", m.sender, self.n_drones)
        _check_int("step", m.step)
        _check_int("round", m.round, self.n_rounds)
        _check_int("n_targets", m.n_targets)
        _check_int("n_state", m.n_state)
        if (m.n_targets, m.n_state) != (M, n):
            _fail(f"consensus message has shape M = {m.n_targets}, n = {m.n_state}; this swarm "
                  f"has M = {M}, n = {n}")
        data = m.data
        if type(data) is not bytes:
            _fail(f"consensus data must be bytes, got {type(data).__name__}")
        later, first = self._consensus_bytes
        expected = first if m.round == 0 else later
        if len(data) != expected:
            if m.round != 0 and len(data) == first:
                _fail(f"round {m.round} must not carry the round-0 consensus states")
            if m.round == 0 and len(data) == later:
                _fail("round 0 without the consensus states: " + ", ".join(CONSENSUS_STATES)
                      + " missing")
            _fail(f"round-{m.round} consensus data carries {len(data)} bytes, expected "
                  f"{expected} for M = {M}, n = {n}")
        if not _all_finite(data):
            for name, _, start, stop in _consensus_layout(M, n, m.round == 0):
                if not _all_finite(data[8 * start:8 * stop]):
                    _fail(f"{name} contains a non-finite value")

    def _check_beacon(self, m: BeaconWire) -> None:
        _check_int("sender", m.sender, self.n_drones)
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        _check_vector3("position_m", m.position_m)
        _check_vector3("velocity_m_s", m.velocity_m_s)
        _check_float("sample_age_s", m.sample_age_s, non_negative=True)

    def _check_camera(self, m: CameraFrameWire) -> None:
        _check_int("drone", m.drone, self.n_drones)
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        _check_int("vehicle_time_ms", m.vehicle_time_ms)
        if not isinstance(m.detections, tuple | list):
            _fail("detections must be a list")
        if len(m.detections) > self.n_targets:
            _fail(f"{len(m.detections)} detections for {self.n_targets} targets")
        seen: set[int] = set()
        for k, d in enumerate(m.detections):
            if not isinstance(d, DetectionWire):
                _fail(f"detections[{k}] must be a DetectionWire")
            _check_int(f"detections[{k}].target", d.target, self.n_targets)
            if d.target in seen:
                _fail(f"target {d.target} detected twice")
            seen.add(d.target)
            _check_float(f"detections[{k}].x", d.x)
            _check_float(f"detections[{k}].y", d.y)
        if m.target_velocities is not None:
            arrays = _Arrays()
            arrays.check("target_velocities", m.target_velocities, (self.n_targets, 3))
            arrays.all_finite()

    def _check_truth(self, m: TruthWire) -> None:
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        arrays = _Arrays()
        arrays.check("drone_positions", m.drone_positions, (self.n_drones, 3))
        arrays.check("target_positions", m.target_positions, (self.n_targets, 3))
        arrays.check("target_velocities", m.target_velocities, (self.n_targets, 3))
        arrays.all_finite()

    def _check_clock(self, m: ClockWire) -> None:
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        if m.state not in CLOCK_STATES:
            _fail(f"state must be one of {CLOCK_STATES}, got {m.state!r:.40}")
        if m.mode not in CLOCK_MODES:
            _fail(f"mode must be one of {CLOCK_MODES}, got {m.mode!r:.40}")
        _check_str("detail", m.detail, MAX_TEXT_CHARS)
        _check_int("rejected_inputs", m.rejected_inputs)

    def _check_telemetry(self, m: TelemetryWire) -> None:
        M = self.n_targets
        _check_int("drone", m.drone, self.n_drones)
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        _check_vector3("position_m", m.position_m)
        arrays = _Arrays()
        for name, shape in zip(TELEMETRY_ARRAYS, self._telemetry_shapes, strict=True):
            arrays.check(name, getattr(m, name), shape)
        arrays.all_finite()
        if not isinstance(m.detected, tuple | list) or len(m.detected) != M:
            _fail(f"detected must hold {M} bools")
        for k, v in enumerate(m.detected):
            _check_bool(f"detected[{k}]", v)
        _check_bool("control_active", m.control_active)
        _check_str("qp_status", m.qp_status, MAX_LABEL_CHARS)
        _check_int("qp_iterations", m.qp_iterations)
        _check_bool("qp_fallback", m.qp_fallback)
        _check_float("qp_solve_us", m.qp_solve_us, non_negative=True)
        _check_float("step_us", m.step_us, non_negative=True)
        if m.bearing_error is not None:
            _check_float("bearing_error", m.bearing_error)
        _check_int("missing_neighbour_messages", m.missing_neighbour_messages)
        _check_int("rejected_inputs", m.rejected_inputs)
        c = m.counters
        if not isinstance(c, TelemetryCounters):
            _fail("counters must be TelemetryCounters")
        for name in _INT_COUNTERS:
            _check_int(f"counters.{name}", getattr(c, name))
        for name in _OPTIONAL_FLOAT_COUNTERS:
            if getattr(c, name) is not None:
                _check_float(f"counters.{name}", getattr(c, name), non_negative=True)
        for name in _LABEL_COUNTERS:
            _check_str(f"counters.{name}", getattr(c, name), MAX_LABEL_CHARS)

    # -- quick checks ----------------------------------------------------------------------
    # For messages whose field types are right: decoded by msgspec (types, tuple lengths,
    # string and list bounds, ints >= 0 checked) or made by the builders. True: the message is
    # valid; False: it may not be, ``validate`` decides. ``x - x == 0.0`` holds exactly when x
    # is finite, and a sum of finite floats is finite unless it overflows (then validate).

    def _quick_consensus(self, m: ConsensusWire) -> bool:
        return self._quick_consensus_sizes(m) and _all_finite(m.data)

    def _quick_consensus_sizes(self, m: ConsensusWire) -> bool:
        """All but the finiteness of the data (``decode_consensus`` checks that)."""
        return not (m.version != WIRE_VERSION or not 0 <= m.sender < self.n_drones
                    or m.step < 0 or m.round < 0
                    or (self.n_rounds is not None and m.round >= self.n_rounds)
                    or m.n_targets != self.n_targets or m.n_state != self.n_state
                    or type(m.data) is not bytes
                    or len(m.data) != self._consensus_bytes[m.round == 0])

    def _quick_beacon(self, m: BeaconWire) -> bool:
        t, age, p, v = m.time_s, m.sample_age_s, m.position_m, m.velocity_m_s
        if (m.version != WIRE_VERSION or not 0 <= m.sender < self.n_drones or m.step < 0
                or m.vehicle_time_ms < 0 or not (t >= 0.0 and age >= 0.0) or len(p) != 3
                or len(v) != 3):
            return False
        total = t + age + p[0] + p[1] + p[2] + v[0] + v[1] + v[2]
        return total - total == 0.0

    def _quick_camera(self, m: CameraFrameWire) -> bool:
        M, t = self.n_targets, m.time_s
        detections = m.detections
        if (m.version != WIRE_VERSION or not 0 <= m.drone < self.n_drones or m.step < 0
                or m.vehicle_time_ms < 0 or not t >= 0.0 or len(detections) > M):
            return False
        total, seen = t, 0
        for d in detections:
            k = d.target
            if not 0 <= k < M or seen >> k & 1:
                return False
            seen |= 1 << k
            total += d.x + d.y
        if total - total != 0.0:
            return False
        v = m.target_velocities
        return v is None or (v.shape == (M, 3) and len(v.data) == 24 * M
                             and _all_finite(v.data))

    def _quick_truth(self, m: TruthWire) -> bool:
        t, N, M = m.time_s, self.n_drones, self.n_targets
        arrays = (m.drone_positions, m.target_positions, m.target_velocities)
        if (m.version != WIRE_VERSION or m.step < 0 or not t >= 0.0 or t - t != 0.0
                or (arrays[0].shape, arrays[1].shape, arrays[2].shape) != ((N, 3), (M, 3), (M, 3))
                or (len(arrays[0].data), len(arrays[1].data), len(arrays[2].data))
                != (24 * N, 24 * M, 24 * M)):
            return False
        return _all_finite(b"".join(a.data for a in arrays))

    def _quick_clock(self, m: ClockWire) -> bool:
        t = m.time_s
        return (m.version == WIRE_VERSION and m.step >= 0 and t >= 0.0 and t - t == 0.0
                and m.state in CLOCK_STATES and m.mode in CLOCK_MODES
                and len(m.detail) <= MAX_TEXT_CHARS and type(m.rejected_inputs) is int
                and m.rejected_inputs >= 0)

    def _quick_telemetry(self, m: TelemetryWire) -> bool:
        c = m.counters
        if (m.version != WIRE_VERSION or not 0 <= m.drone < self.n_drones
                or len(m.detected) != self.n_targets or len(m.qp_status) > MAX_LABEL_CHARS
                or type(c) is not TelemetryCounters):
            return False
        for name in _LABEL_COUNTERS:
            label = getattr(c, name)
            if type(label) is not str or len(label) > MAX_LABEL_CHARS:
                return False
        for k in (m.step, m.qp_iterations, m.missing_neighbour_messages, m.rejected_inputs,
                  *(getattr(c, name) for name in _INT_COUNTERS)):
            if type(k) is not int or k < 0:
                return False
        t, solve, step, p = m.time_s, m.qp_solve_us, m.step_us, m.position_m
        if not (t >= 0.0 and solve >= 0.0 and step >= 0.0) or len(p) != 3:
            return False
        total = t + solve + step + p[0] + p[1] + p[2]
        if m.bearing_error is not None:
            total += m.bearing_error
        for name in _OPTIONAL_FLOAT_COUNTERS:
            value = getattr(c, name)
            if value is not None:
                if not (type(value) is float and value >= 0.0):
                    return False
                total += value
        if total - total != 0.0:
            return False
        arrays = [getattr(m, name) for name in TELEMETRY_ARRAYS]
        for array, shape, size in zip(arrays, self._telemetry_shapes, self._telemetry_sizes,
                                      strict=True):
            if array.shape != shape or len(array.data) != size:
                return False
        return _all_finite(b"".join(a.data for a in arrays))


def _quick_ok(check: Callable[..., bool], *args: Any) -> bool:
    """``check(*args)``, False if it raises (a field of an unexpected type: validate says)."""
    try:
        return check(*args)
    except _ODD_OBJECT:
        return False
