"""Typed, versioned wire messages (SPEC §12), encoded as msgpack by msgspec.

Every message is a frozen, array-like msgspec ``Struct`` whose first two elements are its kind
(the msgspec tag) and ``version`` (== ``WIRE_VERSION``). numpy float64 arrays travel as raw
little-endian bytes — ``F64Array`` = [shape, bytes], or for a consensus message one packed block
of every array (``ConsensusWire.data``) — so every value, including -0.0, subnormals and the last
bit of every mantissa, arrives exactly as it was sent; scalar floats are msgpack float64, which
is exact too. A lockstep multi-process run therefore sees bit-identical inputs.

**Each message's rules are declared once, on its fields** (``swarm.messages.rules``): types,
``>= 0``, finite floats, bounded strings and lists, literals as msgspec constraints, which
msgspec checks in C while it decodes; ids below the swarm's counts, array shapes, list lengths
and the consensus block's layout as ``Meta(extra=...)`` markers that ``SwarmRules`` compiles
for one swarm.

``WireCodec(n_drones, n_targets, n_state)`` knows the sizes of one swarm. Its decoders run
msgspec and then the swarm's rules; a payload that fails either raises ``WireError`` with a
one-line reason naming the field (and ``rule``, the kind of rule it broke, for the rejection
counts). ``encode`` checks a message before it leaves by decoding its own bytes the same way:
a process cannot emit what its peers would reject, and there is no second statement of the
rules for the sender. What a decoder allocates is proportional to the payload (msgspec checks
every length prefix against the bytes actually present; payloads over ``max_payload_bytes``
are refused before decoding).

Conversions to and from the core types: ``consensus_to_wire`` / ``consensus_from_wire`` /
``decode_consensus`` (``ConsensusMessage``), ``CameraFrameWire.build`` / ``.detection_list``
(``Detection``), ``telemetry_from_diagnostics`` / ``TelemetryWire.to_diagnostics``
(``StepDiagnostics``); ``BeaconWire.build`` and ``TruthWire.build`` take numpy arrays. The
agent's own messages have ``encode_consensus``, ``encode_beacon`` and ``encode_telemetry``,
which convert and encode in one call.
"""

from __future__ import annotations

import functools
import itertools
import math
import operator
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Annotated, Any, Final, Literal, TypeVar

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from swarm.core.consensus_message import (
    STATE_NAMES,
    ConsensusMessage,
    message_layout,
    message_size,
)
from swarm.core.drone_step import Detection, StepDiagnostics
from swarm.core.fast_dataclass import record
from swarm.messages.native import (
    RELAY_HELD,
    RELAY_POSITION,
    RELAY_SAMPLE_AGE,
    RELAY_VELOCITY,
    RELAY_WIDTH,
    join_native,
    native_finite,
)
from swarm.messages.rules import (
    Check,
    Finite,
    NonNegativeFinite,
    NonNegativeInt,
    SwarmRules,
    WireError,
    declared_fields,
    explain,
    fail,
    finite_floats,
)

Array = NDArray[np.float64]
_W = TypeVar("_W")

# 3: a consensus message carries one packed float64 block (ConsensusWire.data) and its sizes.
# 4: telemetry carries the position covariance of each estimate (estimate_covariance).
# 5: the world relays every drone's beacon to the agents (BeaconRelayWire): an agent of an
#    older build would wait for beacons that no longer come to it.
# 6: lockstep camera frames carry every drone's reported position (drone_positions) in place
#    of the relay of the drones' beacons: a lockstep agent of an older build would wait for a
#    relay that no longer comes.
# 7: telemetry packs its arrays in one block (TelemetryWire.data, with n_targets and n_state).
# 8: the beacon relay is packed (BeaconRelayWire.senders, .data): no struct per drone.
# 9: a lockstep agent sends its telemetry a few steps at a time (TelemetryBatchWire): an
#    observer of an older build would reject the batches.
# 10: radios with a range (docs/network.md): a frame's radio links, the truth's link matrix,
#    telemetry's neighbours heard, reach and keep figures, round 0's reach stamps.
WIRE_VERSION: Final = 11

MAX_DRONES: Final = 1024  # codec limits: a swarm larger than this is a configuration error
MAX_TARGETS: Final = 1024
MAX_STATE: Final = 64
MAX_LABEL_CHARS: Final = 64  # qp_status, mavlink_state
MAX_TEXT_CHARS: Final = 512  # ClockWire.detail
MAX_TELEMETRY_BATCH: Final = 64  # TelemetryBatchWire.items
MAX_IMAGE_BYTES: Final = 1 << 19  # CameraImageWire.image: a 512 KiB JPEG (480 px: ~50 KiB)
DEFAULT_MAX_PAYLOAD_BYTES: Final = 1 << 20  # nothing this swarm sends comes close to 1 MiB

ClockState = Literal["waiting", "running", "done", "aborted"]
ClockMode = Literal["lockstep", "realtime"]
CLOCK_STATES: Final = ("waiting", "running", "done", "aborted")
CLOCK_MODES: Final = ("lockstep", "realtime")

_LE_F64: Final = np.dtype("<f8")
_F64: Final = np.dtype(np.float64)
_ndarray: Final = np.ndarray
# The wire is little-endian: on such a machine a float64 array's own bytes are the wire bytes.
_NATIVE_LE: Final = sys.byteorder == "little"
# What converting the caller's objects may raise (an array of strings, a shape that is not
# one): said as a WireError.
_ODD_OBJECT: Final = (AttributeError, TypeError, ValueError, IndexError, KeyError,
                      OverflowError)

# The declarations (swarm.messages.rules): msgspec constraints, and the swarm's markers.
Version = Annotated[int, msgspec.Meta(ge=WIRE_VERSION, le=WIRE_VERSION)]
DroneId = Annotated[int, msgspec.Meta(ge=0, extra={"below": "drones"})]
TargetId = Annotated[int, msgspec.Meta(ge=0, extra={"below": "targets"})]
Round = Annotated[int, msgspec.Meta(ge=0, extra={"below": "rounds"})]
_Dim = Annotated[int, msgspec.Meta(ge=0, le=1 << 20)]
_Shape = Annotated[tuple[_Dim, ...], msgspec.Meta(max_length=4)]
Label = Annotated[str, msgspec.Meta(max_length=MAX_LABEL_CHARS)]
Text = Annotated[str, msgspec.Meta(max_length=MAX_TEXT_CHARS)]
Vector3 = tuple[Finite, Finite, Finite]


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

    def native(self) -> memoryview[float] | Array:
        """The values as a C-contiguous native float64 buffer, flat (no validation: decoded
        messages are checked): on a little-endian machine the bytes themselves, read-only."""
        if _NATIVE_LE:
            return memoryview(self.data).cast("d")
        return self.to_array().reshape(-1)

    def to_list(self) -> list[Any]:
        """The values as (nested) lists of floats, bit-exact (no validation: decoded messages
        are checked). On a little-endian machine the bytes are read in place, no array made."""
        values: list[Any]
        if _NATIVE_LE and all(self.shape):  # memoryview cannot cast to an empty shape
            values = memoryview(self.data).cast("d", self.shape).tolist()
        else:
            values = self.to_array().tolist()
        return values


# ``F64Array`` fields of a declared shape (dims: swarm size names or ints), checked against
# the swarm's sizes by the wire rules (``swarm.messages.rules``).
DronesBy3 = Annotated[F64Array, msgspec.Meta(extra={"shape": ("drones", 3)})]  # (N, 3)
TargetsBy3 = Annotated[F64Array, msgspec.Meta(extra={"shape": ("targets", 3)})]  # (M, 3)


def _array_or_none(values: ArrayLike | None) -> F64Array | None:
    return None if values is None else F64Array.from_array(values)


def _le_bytes(values: Any) -> tuple[tuple[int, ...], bytes]:
    """Shape and little-endian float64 bytes (C order) of an array, as ``F64Array`` has them."""
    if _NATIVE_LE and type(values) is np.ndarray and values.dtype is _F64:
        return values.shape, values.tobytes()
    array = np.ascontiguousarray(values, dtype=_LE_F64)
    return tuple(int(d) for d in array.shape), array.tobytes()


class _Wire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True,
            gc=False):
    """Base of every message: [kind tag, version, fields...]. Only immutable data, never a
    reference cycle: the garbage collector need not track them (``gc=False``)."""

    version: Version = WIRE_VERSION

    def arrays(self) -> dict[str, Array]:
        """Every (present) array field as a new numpy float64 array, by field name."""
        out: dict[str, Array] = {}
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, F64Array):
                out[name] = value.to_array()
        return out


class ConsensusWire(_Wire, tag="consensus", kw_only=True, frozen=True):
    """``ConsensusMessage`` on ``agent/<i>/consensus``: the sender's sizes and its ``data``
    as little-endian float64 bytes: [information (M, n, n) | information_vector (M, n)], and
    in round 0 also [projector_mean (M, 3, 3) | weight_mean (M,) | projector_integral
    (M, 3, 3) | weight_integral (M,) | gramian (M, 3, 3)] — C order, the core's own packing
    (``swarm.core.consensus_message``), so that encoding is one copy and decoding one."""

    sender: DroneId
    step: NonNegativeInt
    round: Round
    n_targets: Annotated[int, msgspec.Meta(ge=0, extra={"equals": "targets"})]  # M
    n_state: Annotated[int, msgspec.Meta(ge=0, extra={"equals": "state"})]  # n
    data: Annotated[bytes, msgspec.Meta(extra={"packed": "consensus"})]

    def arrays(self) -> dict[str, Array]:
        """Every array this message carries as a numpy float64 array (views of one new
        block), by ``ConsensusMessage``'s names (no validation: decoded messages are
        checked)."""
        return consensus_from_wire(self).arrays()


class BeaconWire(_Wire, tag="beacon", kw_only=True, frozen=True):
    """A drone's position on ``agent/<i>/beacon`` (collision avoidance, formation bearings)."""

    sender: DroneId
    step: NonNegativeInt
    time_s: NonNegativeFinite
    position_m: Vector3
    # The velocity the drone is flying (its last setpoint) and the age of ``position_m`` when
    # sent: a realtime receiver extrapolates the position to its own instant.
    velocity_m_s: Vector3 = (0.0, 0.0, 0.0)
    sample_age_s: NonNegativeFinite = 0.0
    # The autopilot's time_boot_ms of the sample ``position_m`` came from (0: not known). A
    # world rendering this drone's camera from this position stamps the frame with it, so the
    # agent measures from the pose the frame was taken at, not from a newer one.
    vehicle_time_ms: NonNegativeInt = 0

    @classmethod
    def build(cls, sender: int, step: int, time_s: float, position_m: ArrayLike, *,
              velocity_m_s: ArrayLike = (0.0, 0.0, 0.0), sample_age_s: float = 0.0,
              vehicle_time_ms: int = 0) -> BeaconWire:
        return cls(**dict(zip(_BEACON_FIELDS, _beacon_fields(
            sender, step, time_s, position_m, velocity_m_s, sample_age_s, vehicle_time_ms),
            strict=True)))

    def position(self) -> Array:
        return np.array(self.position_m, dtype=np.float64)


# A relayed beacon's row in ``BeaconRelayWire.data``: the ``RELAY_*`` columns of
# ``swarm.messages.native`` (stated once, in the C source the exchange's reader shares).
_LE_U16: Final = np.dtype("<u2")


class BeaconRelayWire(_Wire, tag="beacons", kw_only=True, frozen=True):
    """Every drone's newest beacon as the world holds it, relayed on ``world/beacons`` at each
    realtime tick: one message per agent and tick instead of one per other drone, packed so
    that a receiver decodes it without a Python object per drone.

    ``senders``: the drones' ids as little-endian uint16, distinct, each below N. ``data``: one
    row of little-endian float64 per sender (``RELAY_*`` columns): the beacon's position and
    velocity [m, m/s, W], its ``sample_age_s``, and ``held_s``, how long the world had held it
    when the relay left [s] (the world's clock: a duration, whatever the hosts' clocks say)."""

    step: NonNegativeInt  # the world's step when it relayed them
    senders: Annotated[bytes, msgspec.Meta(max_length=2 * MAX_DRONES)] = b""
    data: Annotated[bytes, msgspec.Meta(max_length=8 * RELAY_WIDTH * MAX_DRONES,
                                        extra={"packed": "beacon_relay"})] = b""

    @classmethod
    def build(cls, step: int, beacons: Iterable[tuple[BeaconWire, float]]) -> BeaconRelayWire:
        """The relay of ``(beacon, held_s)`` pairs, in the order given."""
        entries = list(beacons)
        ids = [b.sender for b, _ in entries]
        if not all(type(j) is int and 0 <= j <= 0xFFFF for j in ids):
            raise WireError(f"relay senders must be drone ids in [0, 65535], got {ids!r:.60}",
                            rule="range")
        rows = np.empty((len(entries), RELAY_WIDTH), dtype=_LE_F64)
        if entries:
            rows[:, RELAY_POSITION] = [b.position_m for b, _ in entries]
            rows[:, RELAY_VELOCITY] = [b.velocity_m_s for b, _ in entries]
            rows[:, RELAY_SAMPLE_AGE] = [b.sample_age_s for b, _ in entries]
            rows[:, RELAY_HELD] = [held_s for _, held_s in entries]
        return cls(step=int(step), senders=np.array(ids, dtype=_LE_U16).tobytes(),
                   data=rows.tobytes())

    def sender_ids(self) -> NDArray[np.intp]:
        """``senders`` as a new array of ids."""
        return np.frombuffer(self.senders, dtype=_LE_U16).astype(np.intp)

    def rows(self) -> Array:
        """``data`` as an (n, ``RELAY_WIDTH``) native float64 array (read-only on a
        little-endian machine: a view of the message's bytes)."""
        rows = np.frombuffer(self.data, dtype=_LE_F64).reshape(-1, RELAY_WIDTH)
        return rows if _NATIVE_LE else rows.astype(np.float64)


class DetectionWire(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True,
                    gc=False):
    """One detection: target id and image-plane point [x̄, ȳ]."""

    target: TargetId
    x: Finite
    y: Finite


class CameraFrameWire(_Wire, tag="camera", kw_only=True, frozen=True):
    """Drone ``drone``'s detections at ``step`` on ``world/camera/<i>``.

    ``vehicle_time_ms`` is the MAVLink ``time_boot_ms`` of the vehicle position sample that
    belongs to this step (how an agent pairs its LOCAL_POSITION_NED with the frame).
    ``drone_positions`` (lockstep only): every drone's position at this step as its vehicle
    reports it, i.e. what that drone's agent reads from LOCAL_POSITION_NED, in W (N, 3): the
    positions the drones' beacons of this step would carry, in this one message instead of a
    relay that waits for all of them (``sim_world.world``).
    ``radio_links`` (network.topology = "range"): one byte per drone, 1 where this drone's
    radio hears that drone at this step, as the world's simulated radio decides
    (``swarm.scenario.world_step.Scene``); the agent takes its neighbours of the step from it.
    """

    drone: DroneId
    step: NonNegativeInt
    time_s: NonNegativeFinite
    vehicle_time_ms: NonNegativeInt
    detections: Annotated[tuple[DetectionWire, ...], msgspec.Meta(
        max_length=MAX_TARGETS, extra={"max_items": "targets", "distinct": "target"})] = ()
    # (M, 3), single-integrator model only
    target_velocities: TargetsBy3 | None = None
    drone_positions: DronesBy3 | None = None  # (N, 3), lockstep only
    radio_links: Annotated[bytes, msgspec.Meta(extra={"packed": "radio_links"})] | None = None

    @classmethod
    def build(
        cls,
        drone: int,
        step: int,
        time_s: float,
        vehicle_time_ms: int,
        detections: Sequence[Detection],
        target_velocities: ArrayLike | None = None,
        drone_positions: ArrayLike | F64Array | None = None,
        radio_links: ArrayLike | None = None,
    ) -> CameraFrameWire:
        """The frame; ``drone_positions`` may come as an ``F64Array`` already (the world
        converts a step's positions once for all N frames)."""
        dets = []
        for d in detections:
            point = np.asarray(d.image_point, dtype=np.float64).reshape(2)
            dets.append(DetectionWire(int(d.target), float(point[0]), float(point[1])))
        positions = (drone_positions if isinstance(drone_positions, F64Array)
                     else _array_or_none(drone_positions))
        links = (None if radio_links is None
                 else np.asarray(radio_links, dtype=bool).astype(np.uint8).tobytes())
        return cls(drone=int(drone), step=int(step), time_s=float(time_s),
                   vehicle_time_ms=int(vehicle_time_ms), detections=tuple(dets),
                   target_velocities=_array_or_none(target_velocities),
                   drone_positions=positions, radio_links=links)

    def radio_neighbours(self) -> tuple[int, ...] | None:
        """The drones this frame's drone hears at its step (``radio_links``; itself never),
        None when the frame has no radio links (the fixed graph)."""
        if self.radio_links is None:
            return None
        return tuple(j for j, linked in enumerate(self.radio_links)
                     if linked and j != self.drone)

    def detection_list(self) -> list[Detection]:
        out = []
        for d in self.detections:
            out.append(record(Detection, {
                "target": d.target, "image_point": np.array((d.x, d.y), dtype=np.float64)}))
        return out

    def target_velocity_array(self) -> Array | None:
        return None if self.target_velocities is None else self.target_velocities.to_array()

    def drone_position_array(self) -> Array | None:
        """``drone_positions`` as a new (N, 3) float64 array, None when the frame has none."""
        return None if self.drone_positions is None else self.drone_positions.to_array()

    def drone_position_rows(self) -> list[list[float]] | None:
        """``drone_positions`` as N lists [x, y, z] of floats, None when the frame has none."""
        return None if self.drone_positions is None else self.drone_positions.to_list()


class CameraImageWire(_Wire, tag="image", kw_only=True, frozen=True):
    """Drone ``drone``'s rendered camera image at ``step`` on ``world/image/<i>``
    (``camera.model = "rendered"``, docs/camera.md): the fields of its ``CameraFrameWire``
    with the encoded frame (JPEG; empty on a step without a frame, ``camera.frame_rate_hz``)
    in place of the detections. The drone's detector (``swarm-camera``) turns it into that
    ``CameraFrameWire`` (``frame``) on ``world/camera/<i>``, where the agent reads it."""

    drone: DroneId
    step: NonNegativeInt
    time_s: NonNegativeFinite
    vehicle_time_ms: NonNegativeInt
    image: Annotated[bytes, msgspec.Meta(max_length=MAX_IMAGE_BYTES)] = b""
    target_velocities: TargetsBy3 | None = None
    drone_positions: DronesBy3 | None = None  # (N, 3), lockstep only
    radio_links: Annotated[bytes, msgspec.Meta(extra={"packed": "radio_links"})] | None = None

    def frame(self, detections: Sequence[Detection]) -> CameraFrameWire:
        """The camera frame of this image with ``detections``: every other field as is."""
        return CameraFrameWire(
            drone=self.drone, step=self.step, time_s=self.time_s,
            vehicle_time_ms=self.vehicle_time_ms,
            detections=tuple(DetectionWire(int(d.target), float(d.image_point[0]),
                                           float(d.image_point[1])) for d in detections),
            target_velocities=self.target_velocities, drone_positions=self.drone_positions,
            radio_links=self.radio_links)

    @classmethod
    def of_frame(cls, frame: CameraFrameWire, image: bytes) -> CameraImageWire:
        """The image message carrying ``frame``'s fields (its detections left out)."""
        return cls(drone=frame.drone, step=frame.step, time_s=frame.time_s,
                   vehicle_time_ms=frame.vehicle_time_ms, image=image,
                   target_velocities=frame.target_velocities,
                   drone_positions=frame.drone_positions, radio_links=frame.radio_links)


class TruthWire(_Wire, tag="truth", kw_only=True, frozen=True):
    """Ground truth on ``world/truth`` (recorder only; agents never read it)."""

    step: NonNegativeInt
    time_s: NonNegativeFinite
    drone_positions: DronesBy3
    target_positions: TargetsBy3
    target_velocities: TargetsBy3
    # network.topology = "range": which drones' radios hear each other at this step, (N, N),
    # 1.0 or 0.0 (the world's simulated radio); None for the fixed graph.
    radio_links: Annotated[F64Array, msgspec.Meta(extra={"shape": ("drones", "drones")})] \
        | None = None

    @classmethod
    def build(cls, step: int, time_s: float, drone_positions: ArrayLike,
              target_positions: ArrayLike, target_velocities: ArrayLike,
              radio_links: ArrayLike | None = None) -> TruthWire:
        return cls(step=int(step), time_s=float(time_s),
                   drone_positions=F64Array.from_array(drone_positions),
                   target_positions=F64Array.from_array(target_positions),
                   target_velocities=F64Array.from_array(target_velocities),
                   radio_links=(None if radio_links is None else F64Array.from_array(
                       np.asarray(radio_links, dtype=bool).astype(np.float64))))

    def radio_link_matrix(self) -> NDArray[np.bool_] | None:
        """``radio_links`` as an (N, N) bool array (None for the fixed graph)."""
        return None if self.radio_links is None else self.radio_links.to_array() != 0.0


class ClockWire(_Wire, tag="clock", kw_only=True, frozen=True):
    """The world's clock and run state on ``world/clock``."""

    step: NonNegativeInt
    time_s: NonNegativeFinite
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
    neighbour_age_ms: NonNegativeFinite | None = None
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
    tracking_error_m: NonNegativeFinite | None = None
    velocity_error_m_s: NonNegativeFinite | None = None
    # What the agent does about its vehicle (``vehicles.on_vehicle_event``): "" = flying as
    # asked; otherwise the policy in effect and why, e.g. "degraded: mode Hold".
    vehicle_status: Label = ""
    # Localization guarantee (swarm.watch.localization_watch): breaches of λ̄ ≥ ε − tol by this
    # drone's own copies so far (one per target and episode), when the first began [s of
    # mission time; None: none yet], and the targets below the floor now ("" = none).
    lambda_breaches: NonNegativeInt = 0
    first_lambda_breach_s: NonNegativeFinite | None = None
    localization_status: Label = ""
    # Steps whose QP used localization slack while a safety-envelope row held u back (safety
    # won; swarm.core.safety.safety_conflict).
    safety_conflicts: NonNegativeInt = 0
    # The same for a keep row of the radio (network.keep; docs/network.md), and the times
    # this drone found the swarm split (its news reaching fewer than N drones).
    link_conflicts: NonNegativeInt = 0
    splits_said: NonNegativeInt = 0




# The counters a caller may give as NaN for "not measured": sent as None (the fields declared
# ``float | None``, read from the declarations like every rule).
_OPTIONAL_FLOAT_COUNTERS: Final = tuple(
    name for name, t, _, optional in declared_fields(TelemetryCounters)
    if optional and isinstance(t, msgspec.inspect.FloatType))


# The arrays of a telemetry message, in the order ``TelemetryWire.data`` packs them: the
# ``StepDiagnostics`` arrays of these names.
TELEMETRY_ARRAYS: Final = ("velocity", "nominal_velocity", "estimates", "estimate_covariance",
                           "lambda_bar", "psi0", "psi1", "weights", "weight_sum_estimate",
                           "slacks", "weight_slacks")


def telemetry_shapes(n_targets: int, n_state: int) -> dict[str, tuple[int, ...]]:
    """The shape of each array of a telemetry message, in packing order."""
    m = n_targets
    return {"velocity": (3,), "nominal_velocity": (3,), "estimates": (m, n_state),
            "estimate_covariance": (m, 3, 3), "lambda_bar": (m,), "psi0": (m,), "psi1": (m,),
            "weights": (m,), "weight_sum_estimate": (m,), "slacks": (m,),
            "weight_slacks": (m,)}


@functools.lru_cache(maxsize=64)
def telemetry_layout(n_targets: int, n_state: int
                     ) -> tuple[tuple[str, tuple[int, ...], int, int], ...]:
    """(name, shape, start, stop) of each array in ``TelemetryWire.data``, in floats."""
    layout, start = [], 0
    for name, shape in telemetry_shapes(n_targets, n_state).items():
        stop = start + math.prod(shape)
        layout.append((name, shape, start, stop))
        start = stop
    return tuple(layout)


class TelemetryWire(_Wire, tag="telemetry", kw_only=True, frozen=True):
    """One agent step on ``agent/<i>/telemetry``: every ``StepDiagnostics`` field (``drone_id``
    is ``drone``), the drone's position and the process's running ``counters``.

    The step's arrays (``TELEMETRY_ARRAYS``: velocity, estimates, λ̄, …) travel packed in
    ``data``, little-endian float64 in ``telemetry_layout(n_targets, n_state)``: one bytes
    field where eleven ``F64Array``s cost eleven objects to build and to decode every step.
    Each array is still read by its name (``tel.lambda_bar``: an ``F64Array`` over its bytes);
    ``TelemetryWire.build`` makes a message from arrays."""

    drone: DroneId
    step: NonNegativeInt
    time_s: NonNegativeFinite
    position_m: Vector3
    n_targets: Annotated[int, msgspec.Meta(ge=0, extra={"equals": "targets"})]  # M
    n_state: Annotated[int, msgspec.Meta(ge=0, extra={"equals": "state"})]  # n
    data: Annotated[bytes, msgspec.Meta(extra={"packed": "telemetry"})]
    detected: Annotated[tuple[bool, ...], msgspec.Meta(max_length=MAX_TARGETS,
                                                       extra={"length": "targets"})]
    control_active: bool
    qp_status: Label
    qp_iterations: NonNegativeInt
    qp_fallback: bool
    qp_solve_us: NonNegativeFinite
    step_us: NonNegativeFinite
    bearing_error: Finite | None = None
    missing_neighbour_messages: NonNegativeInt = 0  # this step
    rejected_inputs: NonNegativeInt = 0  # this step
    counters: TelemetryCounters = TelemetryCounters()
    rate_limit_released: bool = False  # this step's QP was solved without the rate box
    safety_conflict: bool = False  # localization slack used while an envelope row was active
    # The radio (docs/network.md): one byte per drone, 1 for the neighbours heard this step
    # (None: not sent, older agents); the drones this one's news reaches (itself included; 0:
    # not sent); R_keep − the longest kept link [m] (None: no keep rows); a keep row held u
    # back while localization slack was used.
    neighbours_heard: Annotated[bytes, msgspec.Meta(extra={"packed": "neighbours_heard"})] \
        | None = None
    reached: NonNegativeInt = 0
    keep_margin_m: Finite | None = None
    link_conflict: bool = False

    @classmethod
    def build(cls, **fields: Any) -> TelemetryWire:
        """The message of these fields, the arrays (``TELEMETRY_ARRAYS``, array-likes; an
        ``F64Array`` as its values) packed in ``data`` with their sizes from ``estimates``
        (M, n). Raises ``WireError`` for an array missing or of another shape."""
        missing = [name for name in TELEMETRY_ARRAYS if name not in fields]
        if missing:
            raise WireError(f"telemetry arrays missing: {', '.join(missing)}", rule="shape")
        arrays = {name: fields.pop(name) for name in TELEMETRY_ARRAYS}
        arrays = {name: a.to_array() if isinstance(a, F64Array) else a
                  for name, a in arrays.items()}
        m, n, data = _pack_telemetry(tuple(arrays.values()))
        return cls(n_targets=m, n_state=n, data=data, **fields)

    def array(self, name: str) -> F64Array:
        """The array ``name`` (one of ``TELEMETRY_ARRAYS``) as an ``F64Array`` over its bytes."""
        for field_name, shape, start, stop in telemetry_layout(self.n_targets, self.n_state):
            if field_name == name:
                return F64Array(shape, self.data[8 * start:8 * stop])
        raise KeyError(f"a telemetry message has no array {name!r}")

    def arrays(self) -> dict[str, Array]:
        """Every array as a new numpy float64 array, by name (no validation: decoded messages
        are checked)."""
        block = np.frombuffer(self.data, dtype=_LE_F64).astype(np.float64)
        return {name: block[start:stop].reshape(shape) for name, shape, start, stop
                in telemetry_layout(self.n_targets, self.n_state)}

    velocity = property(lambda self: self.array("velocity"))
    nominal_velocity = property(lambda self: self.array("nominal_velocity"))
    estimates = property(lambda self: self.array("estimates"))
    # the position block of P⁺ = pinv(W⁺) [m²]
    estimate_covariance = property(lambda self: self.array("estimate_covariance"))
    lambda_bar = property(lambda self: self.array("lambda_bar"))
    psi0 = property(lambda self: self.array("psi0"))
    psi1 = property(lambda self: self.array("psi1"))
    weights = property(lambda self: self.array("weights"))
    weight_sum_estimate = property(lambda self: self.array("weight_sum_estimate"))
    slacks = property(lambda self: self.array("slacks"))
    weight_slacks = property(lambda self: self.array("weight_slacks"))

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
            estimates=a["estimates"], estimate_covariance=a["estimate_covariance"],
            lambda_bar=a["lambda_bar"], psi0=a["psi0"],
            psi1=a["psi1"], weights=a["weights"], weight_sum_estimate=a["weight_sum_estimate"],
            slacks=a["slacks"], weight_slacks=a["weight_slacks"],
            detected=np.array(self.detected, dtype=bool), control_active=self.control_active,
            qp_status=self.qp_status, qp_iterations=self.qp_iterations,
            qp_fallback=self.qp_fallback, qp_solve_us=self.qp_solve_us, step_us=self.step_us,
            bearing_error=self.bearing_error,
            missing_neighbour_messages=self.missing_neighbour_messages,
            rejected_inputs=self.rejected_inputs,
            rate_limit_released=self.rate_limit_released,
            safety_conflict=self.safety_conflict,
            neighbours_heard=(() if self.neighbours_heard is None else tuple(
                j for j, heard in enumerate(self.neighbours_heard) if heard)),
            reached=self.reached,
            keep_margin_m=math.inf if self.keep_margin_m is None else self.keep_margin_m,
            link_conflict=self.link_conflict,
        )


@functools.lru_cache(maxsize=64)
def _telemetry_shapes(n_targets: int, n_state: int) -> tuple[tuple[int, ...], ...]:
    """The shape of each of a telemetry message's arrays, in packing order."""
    return tuple(shape for _, shape, _, _ in telemetry_layout(n_targets, n_state))


def _pack_telemetry(arrays: tuple[Any, ...]) -> tuple[int, int, bytes]:
    """(M, n, data) of the ``TELEMETRY_ARRAYS`` in order: M and n from ``estimates``, every
    shape checked against the layout, the bytes joined as they are for native float64
    arrays (the agent's own: one compiled call, ``join_native``), converted otherwise. Raises
    ``WireError`` (shape)."""
    estimates = arrays[2]
    shape: tuple[int, ...] = (estimates.shape if type(estimates) is _ndarray
             else np.shape(estimates) if estimates is not None else ())
    if len(shape) != 2:
        raise WireError(f"estimates has shape {shape!s:.60}, expected (M, n)", rule="shape")
    m, n = int(shape[0]), int(shape[1])
    if _NATIVE_LE:
        data = join_native(arrays, _telemetry_shapes(m, n))
        if data is not None:
            return m, n, data
    chunks = []
    for array, (name, expected, _, _) in zip(arrays, telemetry_layout(m, n), strict=True):
        got, raw = _le_bytes(array)
        if got != expected:
            raise WireError(f"{name} has shape {got!s:.60}, expected {expected}",
                            rule="shape")
        chunks.append(raw)
    return m, n, b"".join(chunks)


class TelemetryBatchWire(_Wire, tag="telemetry_batch", kw_only=True, frozen=True):
    """Consecutive steps of one agent's telemetry in one message on ``agent/<i>/telemetry``
    (a lockstep agent: ``Exchange.telemetry_steps``): each item is the bytes of one
    ``TelemetryWire``, checked as that message is on its own (``WireCodec.
    decode_telemetry_items``); every item is the same drone's, in increasing steps."""

    items: Annotated[list[msgspec.Raw], msgspec.Meta(min_length=1,
                                                     max_length=MAX_TELEMETRY_BATCH)]


WireMessage = (ConsensusWire | BeaconWire | BeaconRelayWire | CameraFrameWire
               | CameraImageWire | TruthWire | ClockWire | TelemetryWire | TelemetryBatchWire)
_KINDS: Final[dict[type, str]] = {
    ConsensusWire: "consensus", BeaconWire: "beacon", BeaconRelayWire: "beacons",
    CameraFrameWire: "camera", CameraImageWire: "image", TruthWire: "truth",
    ClockWire: "clock",
    TelemetryWire: "telemetry", TelemetryBatchWire: "telemetry_batch",
}


class _Header(msgspec.Struct, array_like=True):
    """The first two elements of any message; used only to explain a failed decode."""

    kind: str
    version: int


# -- conversions from the core types -----------------------------------------------------------


def consensus_to_wire(message: ConsensusMessage) -> ConsensusWire:
    """The wire form of ``message`` (not validated for a swarm: ``WireCodec.encode`` does
    that). Raises ``WireError`` if it is not a ``ConsensusMessage`` whose ``data`` is a 1-D
    float64 array of a size its M and n give (without the round-0 states, with them, or with
    them and reach stamps after, whose count the codec checks)."""
    if not isinstance(message, ConsensusMessage):
        raise WireError(f"not a consensus message: {type(message).__name__}", rule="type")
    data = message.data
    M, n = message.n_targets, message.n_state
    if type(M) is not int or type(n) is not int or M < 0 or n < 0:
        raise WireError(f"consensus sizes must be integers >= 0, got M = {M!r:.20}, "
                        f"n = {n!r:.20}", rule="type")
    if (not isinstance(data, np.ndarray) or data.ndim != 1
            or not (data.shape[0] == message_size(M, n, False)
                    or data.shape[0] >= message_size(M, n, True))):
        shape = np.shape(data) if isinstance(data, np.ndarray) else type(data).__name__
        raise WireError(f"consensus data {shape!s:.40} does not fit M = {M}, n = {n}",
                        rule="shape")
    if data.dtype is not _F64 or not _NATIVE_LE:
        if data.dtype.kind != "f":
            raise WireError(f"consensus data must be floats, got {data.dtype}", rule="type")
        data = np.ascontiguousarray(data, dtype=_LE_F64)
    return ConsensusWire(sender=_plain_int(message.sender), step=_plain_int(message.step),
                         round=_plain_int(message.round), n_targets=M, n_state=n,
                         data=data.tobytes())


def _plain_int(value: Any) -> Any:
    """``int(value)`` for an integer (numpy ones included); anything else as it is, for the
    checks to name."""
    if type(value) is int or isinstance(value, bool) \
            or not isinstance(value, int | np.integer):
        return value
    return int(value)


def consensus_from_wire(wire: ConsensusWire) -> ConsensusMessage:
    """The ``ConsensusMessage`` of a (checked) wire message: ``data`` one new native float64
    array, bit-exact."""
    M, n = wire.n_targets, wire.n_state
    floats, odd = divmod(len(wire.data), 8)
    if odd or not (floats == message_size(M, n, False) or floats >= message_size(M, n, True)):
        raise WireError(f"consensus data of {len(wire.data)} bytes does not fit M = {M}, "
                        f"n = {n}", rule="shape")
    block = np.frombuffer(wire.data, dtype=_LE_F64).astype(np.float64)
    return record(ConsensusMessage, {"sender": wire.sender, "step": wire.step,
                                     "round": wire.round, "n_targets": M, "n_state": n,
                                     "data": block})


def _vector3(values: ArrayLike) -> tuple[float, float, float]:
    if type(values) is np.ndarray and values.dtype is _F64 and values.shape == (3,):
        x, y, z = values.tolist()  # Python floats, bit-exact
        return (x, y, z)
    array = np.asarray(values, dtype=np.float64).reshape(3)
    return (float(array[0]), float(array[1]), float(array[2]))


def telemetry_from_diagnostics(
    diag: StepDiagnostics,
    position: ArrayLike,
    counters: TelemetryCounters | None = None,
    *,
    n_drones: int | None = None,
    **counter_fields: Any,
) -> TelemetryWire:
    """Telemetry for one step: ``diag`` as it is, the drone's ``position`` and the totals.

    The totals come either as ``counters`` or as ``TelemetryCounters`` keyword fields
    (``qp_fallbacks=…, late_steps=…, neighbour_age_ms=…, mavlink_state=…``). A NaN
    ``neighbour_age_ms`` means "no neighbour message yet" and is sent as None. ``n_drones``
    (the swarm's N) sends the neighbours heard as one byte per drone; without it, not at all.
    """
    return _telemetry(diag, position, _counters(counters, counter_fields), n_drones)


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


def _beacon_fields(sender: int, step: int, time_s: float, position_m: ArrayLike,
                   velocity_m_s: ArrayLike, sample_age_s: float, vehicle_time_ms: int
                   ) -> tuple[Any, ...]:
    """``BeaconWire``'s fields after ``version``, in order: the one conversion of the
    arguments that ``BeaconWire.build`` and ``WireCodec.encode_beacon`` share."""
    return (int(sender), int(step), float(time_s), _vector3(position_m),
            _vector3(velocity_m_s), float(sample_age_s), int(vehicle_time_ms))


def _telemetry_fields(diag: StepDiagnostics, position: ArrayLike,
                      counters: TelemetryCounters, n_drones: int | None = None
                      ) -> tuple[Any, ...]:
    """``TelemetryWire``'s fields after ``version``, in order, the arrays packed: the one
    conversion of a step's diagnostics that ``telemetry_from_diagnostics`` and
    ``WireCodec.encode_telemetry`` share."""
    m, n, data = _pack_telemetry(_telemetry_arrays(diag))
    detected = diag.detected
    if type(detected) is np.ndarray and detected.dtype == np.bool_:
        flags = tuple(detected.reshape(-1).tolist())
    else:
        flags = tuple(bool(v) for v in np.asarray(detected).reshape(-1))
    bearing = diag.bearing_error
    return (int(diag.drone_id), int(diag.step), float(diag.time_s), _vector3(position),
            m, n, data, flags, bool(diag.control_active), str(diag.qp_status),
            int(diag.qp_iterations), bool(diag.qp_fallback), float(diag.qp_solve_us),
            float(diag.step_us), None if bearing is None else float(bearing),
            int(diag.missing_neighbour_messages), int(diag.rejected_inputs), counters,
            bool(diag.rate_limit_released), bool(diag.safety_conflict),
            None if n_drones is None else _id_mask(diag.neighbours_heard, n_drones),
            int(diag.reached),
            None if math.isinf(margin := float(diag.keep_margin_m)) else margin,
            bool(diag.link_conflict))


def _id_mask(ids: Sequence[int], n_drones: int) -> bytes:
    """One byte per drone, 1 for each of ``ids``."""
    mask = bytearray(n_drones)
    for j in ids:
        if 0 <= j < n_drones:
            mask[j] = 1
    return bytes(mask)


def _telemetry(diag: StepDiagnostics, position: ArrayLike,
               counters: TelemetryCounters, n_drones: int | None = None) -> TelemetryWire:
    return TelemetryWire(**dict(zip(_TELEMETRY_FIELDS,
                                    _telemetry_fields(diag, position, counters, n_drones),
                                    strict=True)))


_BEACON_FIELDS: Final = BeaconWire.__struct_fields__[1:]
_TELEMETRY_FIELDS: Final = TelemetryWire.__struct_fields__[1:]
_telemetry_arrays: Final = operator.attrgetter(*TELEMETRY_ARRAYS)
# _telemetry_fields lists the fields in this order.
assert TelemetryWire.__struct_fields__[1:] == (
    "drone", "step", "time_s", "position_m", "n_targets", "n_state", "data", "detected",
    "control_active", "qp_status", "qp_iterations", "qp_fallback", "qp_solve_us", "step_us",
    "bearing_error", "missing_neighbour_messages", "rejected_inputs", "counters",
    "rate_limit_released", "safety_conflict", "neighbours_heard", "reached", "keep_margin_m",
    "link_conflict")


def _finite_block(data: bytes, layout: tuple[tuple[str, Any, int, int], ...]) -> None:
    """Every float of a packed block finite (one compiled pass), or fail naming the first
    array of ``layout`` (name, shape, start, stop in floats) that holds one that is not."""
    if not (_NATIVE_LE and native_finite(data)):
        finite_floats([(name, data[8 * start:8 * stop]) for name, _, start, stop in layout],
                      native=False)


def _telemetry_block(sizes: Mapping[str, int | None]) -> Check:
    """The rule of ``TelemetryWire.data`` (its ``"packed"`` marker): the arrays of this
    swarm's M and n (``telemetry_layout``), every float finite."""
    M, n = sizes["targets"], sizes["state"]
    assert M is not None and n is not None
    layout = telemetry_layout(M, n)
    expected = 8 * layout[-1][3]

    def check(m: TelemetryWire) -> None:
        data = m.data
        if len(data) != expected:
            fail(f"telemetry data carries {len(data)} bytes, expected {expected} for M = {M}, "
                 f"n = {n}", "shape")
        _finite_block(data, layout)
    return check


def _drone_mask(field: str) -> Callable[[Mapping[str, int | None]], Check]:
    """The rule of a per-drone mask (its ``"packed"`` marker): one byte per drone of this
    swarm, each 0 or 1."""
    def rule(sizes: Mapping[str, int | None]) -> Check:
        n = sizes["drones"]

        def check(m: Any) -> None:
            mask = getattr(m, field)
            if mask is None:
                return
            if len(mask) != n:
                fail(f"{field} carries {len(mask)} bytes, expected one per drone ({n})",
                     "shape")
            if mask.translate(None, b"\x00\x01"):
                fail(f"{field} holds a byte that is neither 0 nor 1", "range")
        return check
    return rule


def _relay_block(sizes: Mapping[str, int | None]) -> Check:
    """The rule of ``BeaconRelayWire.data`` (its ``"packed"`` marker): two bytes per sender,
    one row per sender, every sender a distinct drone of this swarm, every float finite, the
    two ages >= 0 (checked on arrays, not per drone in Python)."""
    n_drones = sizes["drones"]
    assert n_drones is not None

    def check(m: BeaconRelayWire) -> None:
        senders, data = m.senders, m.data
        if len(senders) % 2:
            fail(f"senders carries {len(senders)} bytes, not 2 per drone id", "shape")
        n = len(senders) // 2
        if n > n_drones:
            fail(f"senders holds {n} ids, more than this swarm's {n_drones} drones", "length")
        if len(data) != 8 * RELAY_WIDTH * n:
            fail(f"data carries {len(data)} bytes, expected {8 * RELAY_WIDTH * n} for {n} "
                 "senders", "shape")
        if n == 0:
            return
        ids = np.frombuffer(senders, dtype=_LE_U16)
        if (top := int(ids.max())) >= n_drones:
            fail(f"sender {top} out of range (this swarm has {n_drones} drones)", "range")
        counts = np.bincount(ids)
        if counts.max() > 1:
            fail(f"sender {int(counts.argmax())} appears twice in senders", "duplicate")
        _finite_block(data, (("data", None, 0, RELAY_WIDTH * n),))
        ages = np.frombuffer(data, dtype=_LE_F64).reshape(n, RELAY_WIDTH)[
            :, [RELAY_SAMPLE_AGE, RELAY_HELD]]
        if ages.min() < 0.0:
            fail("data holds a negative sample age or held time", "range")
    return check


def _consensus_block(sizes: Mapping[str, int | None]) -> Check:
    """The rule of ``ConsensusWire.data`` (its ``"packed"`` marker): the block of one round
    for this swarm's M and n — round 0 with the consensus states, later rounds without —
    every float finite."""
    M, n, reach = sizes["targets"], sizes["state"], sizes.get("reach") or 0
    assert M is not None and n is not None
    layouts = (message_layout(M, n, False), message_layout(M, n, True))
    if reach:  # a range graph's round 0 ends with the N reach stamps
        stop = layouts[1][-1][3]
        layouts = (layouts[0], (*layouts[1], ("reach_stamps", (reach,), stop, stop + reach)))
    later, first = (8 * layout[-1][3] for layout in layouts)

    def check(m: ConsensusWire) -> None:
        data, rnd = m.data, m.round
        expected = first if rnd == 0 else later
        if len(data) != expected:
            if rnd != 0 and len(data) == first:
                fail(f"round {rnd} must not carry the round-0 consensus states", "shape")
            if rnd == 0 and len(data) == later:
                fail("round 0 without the consensus states: " + ", ".join(STATE_NAMES)
                     + " missing", "shape")
            fail(f"round-{rnd} consensus data carries {len(data)} bytes, expected {expected} "
                 f"for M = {M}, n = {n}" + (f", N = {reach} reach stamps" if reach and rnd == 0
                                            else ""), "shape")
        _finite_block(data, layouts[rnd == 0])
    return check


class WireCodec:
    """Encodes wire messages and decodes+checks them for one swarm's sizes.

    ``n_state`` is the ICF state dimension (6: double integrator, 3: single integrator);
    ``n_rounds``, if given, bounds a consensus message's ``round`` (0 ≤ round < n_rounds).
    One codec may be shared by threads (zenoh callback threads and the agent's own): msgspec
    keeps per-call state local and the checks here keep none.
    """

    def __init__(self, n_drones: int, n_targets: int, n_state: int, *,
                 n_rounds: int | None = None, reach_stamps: bool = False,
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
        self._telemetry_or_batch = msgspec.msgpack.Decoder(TelemetryWire | TelemetryBatchWire)
        self.reach_stamps = reach_stamps
        sizes = {"drones": n_drones, "targets": n_targets, "state": n_state,
                 "rounds": n_rounds, "reach": n_drones if reach_stamps else 0}
        self._rules: dict[type, Check] = SwarmRules(
            sizes, tuple(_KINDS), array_type=F64Array,
            packings={"consensus": _consensus_block, "telemetry": _telemetry_block,
                      "beacon_relay": _relay_block,
                      "radio_links": _drone_mask("radio_links"),
                      "neighbours_heard": _drone_mask("neighbours_heard")}).checks

    # -- encode --------------------------------------------------------------------------

    consensus_to_wire = staticmethod(consensus_to_wire)
    consensus_from_wire = staticmethod(consensus_from_wire)

    def encode(self, message: WireMessage | ConsensusMessage) -> bytes:
        """The bytes of ``message`` (a ``ConsensusMessage`` is converted first), checked as a
        peer will check them: raises ``WireError`` if it is not a message this swarm's peers
        would accept."""
        if isinstance(message, ConsensusMessage):
            return self.encode_consensus(message)
        cls = type(message)
        if cls not in _KINDS:
            raise WireError(f"not a wire message: {cls.__name__}", rule="kind")
        try:
            payload = self._encoder.encode(message)
        except (TypeError, ValueError, OverflowError, msgspec.EncodeError) as exc:
            raise WireError(f"cannot encode {cls.__name__}: {exc}", rule="type") from None
        self._decode(payload, cls)
        return payload

    def validate(self, message: WireMessage) -> None:
        """Raise ``WireError`` unless ``message`` is a valid message for this swarm (exactly
        when its bytes would decode)."""
        self.encode(message)

    # The agent's own messages, from the core's types: one conversion (the one the usual
    # builders use), then ``encode``.

    def encode_consensus(self, message: ConsensusMessage) -> bytes:
        """``encode(consensus_to_wire(message))``."""
        return self.encode(_converted(consensus_to_wire, "ConsensusMessage", message))

    def encode_beacon(self, sender: int, step: int, time_s: float, position_m: ArrayLike, *,
                      velocity_m_s: ArrayLike = (0.0, 0.0, 0.0), sample_age_s: float = 0.0,
                      vehicle_time_ms: int = 0) -> bytes:
        """``encode(BeaconWire.build(...))`` with the same arguments (the same bytes)."""
        return self._encode_fields("beacon", BeaconWire, _beacon_fields(
            sender, step, time_s, position_m, velocity_m_s, sample_age_s, vehicle_time_ms))

    def encode_telemetry(self, diag: StepDiagnostics, position: ArrayLike,
                         counters: TelemetryCounters | None = None,
                         **counter_fields: Any) -> bytes:
        """``encode(telemetry_from_diagnostics(diag, position, counters, n_drones=N,
        **counter_fields))`` (N: this codec's); a wrong counter argument raises ``TypeError``
        as there."""
        totals = _counters(counters, counter_fields)
        return self._encode_fields("telemetry", TelemetryWire, _converted(
            _telemetry_fields, "StepDiagnostics", diag, position, totals, self.n_drones))

    def encode_telemetry_batch(self, payloads: Sequence[bytes]) -> bytes:
        """One ``TelemetryBatchWire`` of these ``TelemetryWire`` payloads (each as
        ``encode_telemetry`` made it), checked as ``decode_telemetry_items`` checks it."""
        if isinstance(payloads, bytes | bytearray | memoryview | str):
            raise WireError("a telemetry batch takes a sequence of payloads, not one",
                            rule="type")
        try:
            payload = self._encoder.encode(("telemetry_batch", WIRE_VERSION,
                                            [msgspec.Raw(p) for p in payloads]))
        except (TypeError, ValueError, OverflowError, msgspec.EncodeError) as exc:
            raise WireError(f"cannot encode TelemetryBatchWire: {exc}", rule="type") from None
        self.decode_telemetry_items(payload)
        return payload

    def _encode_fields(self, kind: str, cls: type, fields: tuple[Any, ...]) -> bytes:
        """The bytes of a ``cls`` message with these fields (after ``version``), checked as
        ``encode`` checks: msgspec writes a tuple as it writes the array-like struct."""
        try:
            payload = self._encoder.encode((kind, WIRE_VERSION, *fields))
        except (TypeError, ValueError, OverflowError, msgspec.EncodeError) as exc:
            raise WireError(f"cannot encode {cls.__name__}: {exc}", rule="type") from None
        self._decode(payload, cls)
        return payload

    # -- decode --------------------------------------------------------------------------

    def decode_consensus(self, payload: bytes) -> ConsensusMessage:
        """The ``ConsensusMessage`` in ``payload``, checked; its ``data`` is one new, writable
        native float64 array (as ``consensus_from_wire`` makes it)."""
        wire = self._decode(payload, ConsensusWire)
        if not _NATIVE_LE:
            return consensus_from_wire(wire)
        data = bytearray(wire.data)  # one writable copy, the array over it
        return record(ConsensusMessage, {
            "sender": wire.sender, "step": wire.step, "round": wire.round,
            "n_targets": wire.n_targets, "n_state": wire.n_state,
            "data": _ndarray((len(data) // 8,), _F64, data)})

    def decode_consensus_wire(self, payload: bytes) -> ConsensusWire:
        return self._decode(payload, ConsensusWire)

    def decode_beacon(self, payload: bytes) -> BeaconWire:
        return self._decode(payload, BeaconWire)

    def decode_beacon_relay(self, payload: bytes) -> BeaconRelayWire:
        return self._decode(payload, BeaconRelayWire)

    def decode_camera(self, payload: bytes) -> CameraFrameWire:
        return self._decode(payload, CameraFrameWire)

    def decode_image(self, payload: bytes) -> CameraImageWire:
        return self._decode(payload, CameraImageWire)

    def decode_truth(self, payload: bytes) -> TruthWire:
        return self._decode(payload, TruthWire)

    def decode_clock(self, payload: bytes) -> ClockWire:
        return self._decode(payload, ClockWire)

    def decode_telemetry(self, payload: bytes) -> TelemetryWire:
        return self._decode(payload, TelemetryWire)

    def decode_telemetry_items(self, payload: bytes) -> tuple[TelemetryWire, ...]:
        """What an agent's telemetry key carries: one ``TelemetryWire`` or a
        ``TelemetryBatchWire``, as the telemetry messages in it, in order. Each item is
        checked as ``decode_telemetry`` checks a message of its own; a batch whose items
        are not one drone's in increasing steps is refused whole."""
        self._check_payload(payload, TelemetryBatchWire)
        try:
            message = self._telemetry_or_batch.decode(payload)
        except msgspec.DecodeError as exc:
            kind = self._kind_of(payload)
            raise self._explain(payload, TelemetryBatchWire if kind == "telemetry_batch"
                                else TelemetryWire, exc) from None
        except UnicodeDecodeError:
            raise WireError("malformed telemetry message: a string is not valid UTF-8",
                            rule="malformed") from None
        if isinstance(message, TelemetryWire):
            self._rules[TelemetryWire](message)
            return (message,)
        items = []
        for index, raw in enumerate(message.items):
            try:
                items.append(self._decode(memoryview(raw), TelemetryWire))
            except WireError as err:
                raise WireError(f"telemetry batch item {index}: {err.reason}",
                                rule=err.rule) from None
        first = items[0]
        for index, (before, item) in enumerate(itertools.pairwise(items), 1):
            if item.drone != first.drone:
                raise WireError(f"telemetry batch item {index} is drone {item.drone}'s, "
                                f"item 0 drone {first.drone}'s", rule="value")
            if item.step <= before.step:
                raise WireError(f"telemetry batch item {index} has step {item.step}, not "
                                f"after {before.step}", rule="value")
        return tuple(items)

    def _kind_of(self, payload: Any) -> str | None:
        try:
            return self._header.decode(payload).kind
        except (msgspec.DecodeError, UnicodeDecodeError):
            return None

    def _check_payload(self, payload: Any, cls: type) -> None:
        """Bytes, and no more of them than ``max_payload_bytes``."""
        if type(payload) is not bytes and not isinstance(payload, bytearray | memoryview):
            raise WireError(f"{_KINDS[cls]} payload must be bytes, got "
                            f"{type(payload).__name__}", rule="type")
        if len(payload) > self.max_payload_bytes:
            raise WireError(f"{_KINDS[cls]} payload of {len(payload)} bytes exceeds the "
                            f"{self.max_payload_bytes}-byte limit", rule="size")

    def _decode(self, payload: Any, cls: type[_W]) -> _W:
        """msgspec's decode (types and constraints, in C), then this swarm's rules."""
        self._check_payload(payload, cls)
        try:
            message: _W = self._decoders[cls].decode(payload)
        except msgspec.DecodeError as exc:  # includes msgspec.ValidationError
            raise self._explain(payload, cls, exc) from None
        except UnicodeDecodeError:  # msgspec raises this, not DecodeError, for bad UTF-8
            raise WireError(f"malformed {_KINDS[cls]} message: a string is not valid UTF-8",
                            rule="malformed") from None
        self._rules[cls](message)
        return message

    def _explain(self, payload: Any, cls: type, exc: msgspec.DecodeError) -> WireError:
        """Why a payload failed to decode: wrong kind and wrong version say so explicitly,
        a broken field rule names the field."""
        kind = _KINDS[cls]
        try:
            header = self._header.decode(payload)
        except (msgspec.DecodeError, UnicodeDecodeError):
            return WireError(f"malformed {kind} message: {exc}", rule="malformed")
        if header.kind != kind:
            shown = header.kind if header.kind in _KINDS.values() else f"{header.kind!r:.40}"
            return WireError(f"expected a {kind} message, got {shown}", rule="kind")
        if header.version != WIRE_VERSION:
            return WireError(f"{kind} message has wire version {header.version!r:.20}, this "
                             f"build speaks version {WIRE_VERSION}", rule="version")
        if isinstance(exc, msgspec.ValidationError):
            return explain(cls, bytes(payload), exc, kind)
        return WireError(f"malformed {kind} message: {exc}", rule="malformed")


def _converted(convert: Callable[..., _W], what: str, *args: Any) -> _W:
    """``convert(*args)``; what converting odd objects raises (an array of strings, a shape
    that is not one) as a ``WireError``."""
    try:
        return convert(*args)
    except WireError:
        raise
    except _ODD_OBJECT as exc:
        raise WireError(f"cannot encode {what}: {type(exc).__name__}: {exc}", rule="type"
                        ) from None
