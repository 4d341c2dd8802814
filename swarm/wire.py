"""Typed, versioned, validated wire messages (SPEC §12), encoded as msgpack by msgspec.

Every message is a frozen, array-like msgspec ``Struct`` whose first two elements are its kind
(the msgspec tag) and ``version`` (== ``WIRE_VERSION``). numpy float64 arrays travel as
``F64Array`` = [shape, raw little-endian bytes], so every value — including -0.0, subnormals and
the last bit of every mantissa — arrives exactly as it was sent; scalar floats are msgpack
float64, which is exact too. A lockstep multi-process run therefore sees bit-identical inputs.

``WireCodec(n_drones, n_targets, n_state)`` knows the sizes of one swarm. ``encode`` checks a
message before it leaves (so a process cannot emit what its peers would reject) and the
``decode_*`` methods check what arrives: message kind, version, ids in range, steps ≥ 0, exact
array shapes and byte lengths, every float finite, bounded strings and lists. Any problem — and
any byte string at all that is not a valid message — raises ``WireError`` with a one-line
reason; nothing else escapes a decoder, and what it allocates is proportional to the payload
(msgspec checks every length prefix against the bytes actually present; payloads over
``max_payload_bytes`` are refused before decoding).

Conversions to and from the core types: ``consensus_to_wire`` / ``decode_consensus``
(``ConsensusMessage``), ``CameraFrameWire.build`` / ``.detection_list`` (``Detection``),
``telemetry_from_diagnostics`` / ``TelemetryWire.to_diagnostics`` (``StepDiagnostics``);
``BeaconWire.build`` and ``TruthWire.build`` take numpy arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Annotated, Any, Final, Literal, TypeVar

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from swarm.core.agent import ConsensusMessage, Detection, StepDiagnostics

Array = NDArray[np.float64]
_W = TypeVar("_W")

WIRE_VERSION: Final = 2

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

NonNegativeInt = Annotated[int, msgspec.Meta(ge=0)]
_Dim = Annotated[int, msgspec.Meta(ge=0, le=1 << 20)]
_Shape = Annotated[tuple[_Dim, ...], msgspec.Meta(max_length=4)]
Label = Annotated[str, msgspec.Meta(max_length=MAX_LABEL_CHARS)]
Text = Annotated[str, msgspec.Meta(max_length=MAX_TEXT_CHARS)]
Vector3 = tuple[float, float, float]


class WireError(ValueError):
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


class F64Array(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
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


class _Wire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
    """Base of every message: [kind tag, version, fields...]."""

    version: int = WIRE_VERSION

    def arrays(self) -> dict[str, Array]:
        """Every (present) array field as a new numpy float64 array, by field name."""
        out: dict[str, Array] = {}
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, F64Array):
                out[name] = value.to_array()
        return out


class ConsensusWire(_Wire, tag="consensus", kw_only=True):
    """``ConsensusMessage`` on ``agent/<i>/consensus``; round 0 carries the five extra fields."""

    sender: NonNegativeInt
    step: NonNegativeInt
    round: NonNegativeInt
    information: F64Array  # (M, n, n)
    information_vector: F64Array  # (M, n)
    projector_mean: F64Array | None = None  # (M, 3, 3)
    projector_integral: F64Array | None = None  # (M, 3, 3)
    weight_mean: F64Array | None = None  # (M,)
    weight_integral: F64Array | None = None  # (M,)
    gramian: F64Array | None = None  # (M, 3, 3)


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

    @classmethod
    def build(cls, sender: int, step: int, time_s: float, position_m: ArrayLike, *,
              velocity_m_s: ArrayLike = (0.0, 0.0, 0.0), sample_age_s: float = 0.0
              ) -> BeaconWire:
        return cls(sender=int(sender), step=int(step), time_s=float(time_s),
                   position_m=_vector3(position_m), velocity_m_s=_vector3(velocity_m_s),
                   sample_age_s=float(sample_age_s))

    def position(self) -> Array:
        return np.array(self.position_m, dtype=np.float64)


class DetectionWire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
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
        return [Detection(d.target, np.array([d.x, d.y], dtype=np.float64))
                for d in self.detections]

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


class TelemetryCounters(msgspec.Struct, frozen=True, array_like=True,
                        forbid_unknown_fields=True):
    """Running totals of one agent process (not per step)."""

    qp_fallbacks: NonNegativeInt = 0
    rejected_messages: NonNegativeInt = 0
    missing_neighbour_messages: NonNegativeInt = 0
    stale_neighbour_messages: NonNegativeInt = 0
    late_steps: NonNegativeInt = 0
    steps: NonNegativeInt = 0  # steps run so far (late_steps / steps is the late rate)
    neighbour_age_ms: float | None = None  # age of the freshest neighbour message; None: none yet
    mavlink_state: Label = ""


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
    return ConsensusWire(
        sender=int(message.sender), step=int(message.step), round=int(message.round),
        information=F64Array.from_array(message.information),
        information_vector=F64Array.from_array(message.information_vector),
        projector_mean=_array_or_none(message.projector_mean),
        projector_integral=_array_or_none(message.projector_integral),
        weight_mean=_array_or_none(message.weight_mean),
        weight_integral=_array_or_none(message.weight_integral),
        gramian=_array_or_none(message.gramian),
    )


def consensus_from_wire(wire: ConsensusWire) -> ConsensusMessage:
    def opt(a: F64Array | None) -> Array | None:
        return None if a is None else a.to_array()

    return ConsensusMessage(
        sender=wire.sender, step=wire.step, round=wire.round,
        information=wire.information.to_array(),
        information_vector=wire.information_vector.to_array(),
        projector_mean=opt(wire.projector_mean), projector_integral=opt(wire.projector_integral),
        weight_mean=opt(wire.weight_mean), weight_integral=opt(wire.weight_integral),
        gramian=opt(wire.gramian),
    )


def _vector3(values: ArrayLike) -> Vector3:
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
    if counter_fields:
        if counters is not None:
            raise TypeError("pass counters or counter keyword fields, not both")
        unknown = set(counter_fields) - set(TelemetryCounters.__struct_fields__)
        if unknown:
            raise TypeError(f"unknown telemetry counters: {sorted(unknown)}")
        age = counter_fields.get("neighbour_age_ms")
        if age is not None and isinstance(age, float | int) and math.isnan(age):
            counter_fields["neighbour_age_ms"] = None
        elif age is not None:
            counter_fields["neighbour_age_ms"] = float(age)
        counters = TelemetryCounters(**counter_fields)
    f = F64Array.from_array
    return TelemetryWire(
        drone=int(diag.drone_id), step=int(diag.step), time_s=float(diag.time_s),
        position_m=_vector3(position),
        velocity=f(diag.velocity), nominal_velocity=f(diag.nominal_velocity),
        estimates=f(diag.estimates), lambda_bar=f(diag.lambda_bar), psi0=f(diag.psi0),
        psi1=f(diag.psi1), weights=f(diag.weights),
        weight_sum_estimate=f(diag.weight_sum_estimate), slacks=f(diag.slacks),
        weight_slacks=f(diag.weight_slacks),
        detected=tuple(bool(v) for v in np.asarray(diag.detected).reshape(-1)),
        control_active=bool(diag.control_active), qp_status=str(diag.qp_status),
        qp_iterations=int(diag.qp_iterations), qp_fallback=bool(diag.qp_fallback),
        qp_solve_us=float(diag.qp_solve_us), step_us=float(diag.step_us),
        bearing_error=None if diag.bearing_error is None else float(diag.bearing_error),
        missing_neighbour_messages=int(diag.missing_neighbour_messages),
        rejected_inputs=int(diag.rejected_inputs),
        counters=counters if counters is not None else TelemetryCounters(),
    )


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

    # -- encode --------------------------------------------------------------------------

    consensus_to_wire = staticmethod(consensus_to_wire)
    consensus_from_wire = staticmethod(consensus_from_wire)

    def encode(self, message: WireMessage | ConsensusMessage) -> bytes:
        """Validate ``message`` (a ``ConsensusMessage`` is converted first) and return bytes.

        Raises ``WireError`` if it is not a message this swarm's peers would accept.
        """
        if isinstance(message, ConsensusMessage):
            message = consensus_to_wire(message)
        self.validate(message)
        try:
            payload = self._encoder.encode(message)
        except (TypeError, ValueError, OverflowError, msgspec.EncodeError) as exc:
            raise WireError(f"cannot encode {type(message).__name__}: {exc}") from None
        if len(payload) > self.max_payload_bytes:
            raise WireError(f"{type(message).__name__} is {len(payload)} bytes, over the "
                            f"{self.max_payload_bytes}-byte limit")
        return payload

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
        except Exception as exc:  # a hand-built message with wrong field types
            raise WireError(f"invalid {type(message).__name__}: {type(exc).__name__}: {exc}"
                            ) from None

    # -- decode --------------------------------------------------------------------------

    def decode_consensus(self, payload: bytes) -> ConsensusMessage:
        return consensus_from_wire(self._decode(payload, ConsensusWire))

    def decode_consensus_wire(self, payload: bytes) -> ConsensusWire:
        return self._decode(payload, ConsensusWire)

    def decode_beacon(self, payload: bytes) -> BeaconWire:
        return self._decode(payload, BeaconWire)

    def decode_camera(self, payload: bytes) -> CameraFrameWire:
        return self._decode(payload, CameraFrameWire)

    def decode_truth(self, payload: bytes) -> TruthWire:
        return self._decode(payload, TruthWire)

    def decode_clock(self, payload: bytes) -> ClockWire:
        return self._decode(payload, ClockWire)

    def decode_telemetry(self, payload: bytes) -> TelemetryWire:
        return self._decode(payload, TelemetryWire)

    def _decode(self, payload: Any, cls: type[_W]) -> _W:
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
            self.validate(message)
            return message
        except WireError:
            raise
        except Exception as exc:  # never let anything but WireError out of a decoder
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
        except Exception:
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
        arrays = _Arrays()
        arrays.check("information", m.information, (M, n, n))
        arrays.check("information_vector", m.information_vector, (M, n))
        extras: Mapping[str, tuple[F64Array | None, tuple[int, ...]]] = {
            "projector_mean": (m.projector_mean, (M, 3, 3)),
            "projector_integral": (m.projector_integral, (M, 3, 3)),
            "weight_mean": (m.weight_mean, (M,)),
            "weight_integral": (m.weight_integral, (M,)),
            "gramian": (m.gramian, (M, 3, 3)),
        }
        for name, (value, shape) in extras.items():
            if m.round == 0:
                arrays.check(name, value, shape)
            elif value is not None:
                _fail(f"round {m.round} must not carry the round-0 field {name}")
        arrays.all_finite()

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

    def _check_telemetry(self, m: TelemetryWire) -> None:
        M = self.n_targets
        _check_int("drone", m.drone, self.n_drones)
        _check_int("step", m.step)
        _check_float("time_s", m.time_s, non_negative=True)
        _check_vector3("position_m", m.position_m)
        arrays = _Arrays()
        arrays.check("velocity", m.velocity, (3,))
        arrays.check("nominal_velocity", m.nominal_velocity, (3,))
        arrays.check("estimates", m.estimates, (M, self.n_state))
        for name in ("lambda_bar", "psi0", "psi1", "weights", "weight_sum_estimate", "slacks",
                     "weight_slacks"):
            arrays.check(name, getattr(m, name), (M,))
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
        for name in ("qp_fallbacks", "rejected_messages", "missing_neighbour_messages",
                     "stale_neighbour_messages", "late_steps", "steps"):
            _check_int(f"counters.{name}", getattr(c, name))
        if c.neighbour_age_ms is not None:
            _check_float("counters.neighbour_age_ms", c.neighbour_age_ms, non_negative=True)
        _check_str("counters.mavlink_state", c.mavlink_state, MAX_LABEL_CHARS)
