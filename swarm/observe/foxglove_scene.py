"""The swarm as a 3D scene in Foxglove's well-known schemas (``foxglove.SceneUpdate``).

One scene per instant, in the thesis' world frame (``world``: x east, y north, z up, as
Foxglove's 3D panel draws it), built from what an observer already receives — the world's
truth message and each drone's telemetry — so it costs the swarm nothing:

* ``drones``: a sphere per drone, green while it senses some target (a weight above
  ``SENSING_WEIGHT``), grey while idle, with its id;
* ``collision``: a translucent sphere of radius Δ (``control.collision_distance_m``) around
  each drone: no other drone's centre may enter it;
* ``fov``: each camera's square FoV pyramid, to the ground or to D_M (``fov_segments``);
* ``graph``: the communication graph's edges;
* ``targets``: the targets' true positions, labelled T0, T1, …;
* ``estimates``: every drone's estimate of every target's position;
* ``envelope``: the [safety] envelope, when the scenario has one: the keep-in polygon's
  edges at the floor and the ceiling (the ground and 1 m above the start box when not set)
  with a post at each vertex, and each keep-out cylinder between the same heights;
* ``uncertainty``: around each estimate, the ellipsoid holding the target with probability
  ``ELLIPSOID_PROBABILITY`` if the drone's filter covariance P⁺ = pinv(W⁺) (its position
  block, sent in telemetry) were exact: semi-axes ``ELLIPSOID_SIGMAS``·√(eigenvalue) along
  P⁺'s eigenvectors (``ellipsoid_axes``).

``SceneAssembler`` gathers one step's truth and N telemetry messages (from any thread's
order) and hands over a ``SceneState`` every ``period_steps`` steps once it is complete; a
step still incomplete when a later scene step completes is given up and counted
(``incomplete``). ``scene_update(config, state)`` turns a state into the message, whose
``encode()`` is the protobuf payload and ``SceneUpdate.get_schema()`` its schema.
``LogBook().lines(state)`` is what the ``log`` topic (``foxglove.Log``) says at that instant.
``plot_values(state, i)`` is what ``drone/<i>/plot`` carries at the same instant (JSON,
``plot_schema``): λ̄ − ε per target (``lambda_margin``), weights, slacks and ‖u‖, for a Plot
panel, live and in recordings alike.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove.messages import (
    Color,
    CylinderPrimitive,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from swarm.messages.wire import TelemetryCounters, TelemetryWire, TruthWire
from swarm.models.camera import fov_segments
from swarm.observe.collector import wire_values
from swarm.observe.events import URGENT_LABELS, increased_counters
from swarm.runs.checks import SENSING_WEIGHT
from swarm.scenario.config import ScenarioConfig

Array = NDArray[np.float64]

FRAME = "world"
SCENE_TOPIC = "scene"
LOG_TOPIC = "log"
SCENE_PERIOD_S = 0.1  # a scene every this much sim time (10 Hz): smooth, and small on disk
DRONE_DIAMETER_M = 0.3
TARGET_DIAMETER_M = 0.3
ESTIMATE_DIAMETER_M = 0.12
SENSING_COLOUR = (0.13, 0.70, 0.30, 1.0)
IDLE_COLOUR = (0.55, 0.55, 0.55, 1.0)
COLLISION_COLOUR = (0.95, 0.55, 0.10, 0.12)
FOV_COLOUR = (0.25, 0.45, 0.90, 0.6)
GRAPH_COLOUR = (0.13, 0.60, 0.25, 0.8)  # a link (the fixed graph's, or one in radio range)
KEPT_COLOUR = (0.10, 0.35, 0.85, 0.9)  # a link the keep rows hold, in range
LOST_COLOUR = (0.90, 0.10, 0.10, 0.9)  # a link the keep rows should hold, out of range
TARGET_COLOUR = (0.85, 0.15, 0.15, 1.0)
ESTIMATE_COLOUR = (0.10, 0.75, 0.20, 1.0)
UNCERTAINTY_COLOUR = (0.10, 0.75, 0.20, 0.25)
ELLIPSOID_PROBABILITY = 0.95
ELLIPSOID_SIGMAS = 2.7954834829151074  # √(χ²₃ quantile at 0.95): a 3-D Gaussian's 95 % region
ENVELOPE_COLOUR = (0.80, 0.10, 0.10, 0.8)
OBSTACLE_COLOUR = (0.80, 0.10, 0.10, 0.3)
ENTITIES = ("drones", "collision", "fov", "graph", "targets", "estimates", "uncertainty",
            "envelope")


@dataclass(frozen=True)
class SceneState:
    """One instant: true positions, and what each drone reports."""

    step: int
    time_s: float
    drones_m: Array  # (N, 3) true positions
    targets_m: Array  # (M, 3) true positions
    weights: Array  # (N, M)
    estimates_m: Array  # (N, M, 3) estimated target positions
    estimate_covariance_m2: Array | None = None  # (N, M, 3, 3) their covariance P⁺ [m²]
    psi0: Array | None = None  # (N, M) λ̄ − ε of each drone's copy
    slacks: Array | None = None  # (N, M)
    velocities_m_s: Array | None = None  # (N, 3) commanded
    counters: tuple[TelemetryCounters, ...] = ()  # each drone's running totals
    links: NDArray[np.bool_] | None = None  # (N, N) the radio's links (None: the fixed graph)

    @property
    def sensing(self) -> NDArray[np.bool_]:
        """(N,) whether each drone senses some target (a weight above SENSING_WEIGHT)."""
        return np.nan_to_num(self.weights, nan=0.0).max(axis=1) > SENSING_WEIGHT


def _colour(rgba: tuple[float, float, float, float]) -> Color:
    return Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _pose(position: Array) -> Pose:
    x, y, z = (float(c) for c in position)
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0, y=0, z=0, w=1))


def _sphere(position: Array, diameter_m: float,
            rgba: tuple[float, float, float, float]) -> SpherePrimitive:
    return SpherePrimitive(pose=_pose(position),
                           size=Vector3(x=diameter_m, y=diameter_m, z=diameter_m),
                           color=_colour(rgba))


def ellipsoid_axes(covariance_m2: Array) -> tuple[Array, Array]:
    """The ``ELLIPSOID_PROBABILITY`` ellipsoids of a stack of 3×3 position covariances
    (..., 3, 3): their full axis lengths [m] (2·``ELLIPSOID_SIGMAS``·√eigenvalue, a negative
    round-off eigenvalue taken as 0) and the rotations whose columns are the axes
    (P = R diag(λ) Rᵀ, det R = +1)."""
    eigenvalues, rotation = np.linalg.eigh(0.5 * (covariance_m2
                                                  + np.swapaxes(covariance_m2, -1, -2)))
    rotation[..., :, 2] *= np.sign(np.linalg.det(rotation))[..., None]
    return 2.0 * ELLIPSOID_SIGMAS * np.sqrt(np.maximum(eigenvalues, 0.0)), rotation


def _ellipsoids(positions: Array, covariances_m2: Array) -> list[SpherePrimitive]:
    """One translucent sphere primitive per (position, covariance), sized and turned as its
    ellipsoid (all of them through eigh and the quaternion conversion at once)."""
    if len(positions) == 0:
        return []
    lengths, rotations = ellipsoid_axes(covariances_m2)
    quaternions = Rotation.from_matrix(rotations).as_quat()  # (x, y, z, w) each
    colour = _colour(UNCERTAINTY_COLOUR)
    return [SpherePrimitive(pose=Pose(position=Vector3(x=p[0], y=p[1], z=p[2]),
                                      orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])),
                            size=Vector3(x=d[0], y=d[1], z=d[2]), color=colour)
            for p, q, d in zip(positions.tolist(), quaternions.tolist(), lengths.tolist(),
                               strict=True)]


def _label(position: Array, text: str, rgba: tuple[float, float, float, float]) -> TextPrimitive:
    return TextPrimitive(pose=_pose(position + np.array([0.0, 0.0, 0.35])), billboard=True,
                         font_size=14.0, scale_invariant=True, color=_colour(rgba), text=text)


def _lines(segments: list[Array], rgba: tuple[float, float, float, float],
           thickness_px: float) -> LinePrimitive:
    points = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
              for segment in segments for p in segment]
    return LinePrimitive(type=LinePrimitiveLineType.LineList, pose=_pose(np.zeros(3)),
                         thickness=thickness_px, scale_invariant=True, points=points,
                         color=_colour(rgba))


def _entity(name: str, stamp: Timestamp, **primitives: Any) -> SceneEntity:
    return SceneEntity(timestamp=stamp, frame_id=FRAME, id=name, frame_locked=False,
                       **primitives)


def envelope_heights(config: ScenarioConfig) -> tuple[float, float]:
    """The heights [m] the envelope is drawn between: its floor and ceiling, or the ground
    and 1 m above the start box where it has none."""
    envelope = config.safety.params
    top = config.swarm.initial_box_center_m[2] + config.swarm.initial_box_size_m[2] / 2 + 1.0
    return (envelope.floor_m if envelope.floor_m is not None else 0.0,
            envelope.ceiling_m if envelope.ceiling_m is not None else top)


def _envelope_entity(config: ScenarioConfig, stamp: Timestamp) -> SceneEntity:
    envelope = config.safety.params
    low, high = envelope_heights(config)
    vertices = envelope.keep_in
    segments = [np.array([[*vertices[k], z], [*vertices[(k + 1) % len(vertices)], z]])
                for z in (low, high) for k in range(len(vertices))]
    segments += [np.array([[x, y, low], [x, y, high]]) for x, y in vertices]
    cylinders = [CylinderPrimitive(
        pose=_pose(np.array([*obstacle.center_m, (low + high) / 2])),
        size=Vector3(x=2 * obstacle.radius_m, y=2 * obstacle.radius_m, z=high - low),
        bottom_scale=1.0, top_scale=1.0, color=_colour(OBSTACLE_COLOUR))
        for obstacle in envelope.keep_out]
    return _entity("envelope", stamp,
                   lines=[_lines(segments, ENVELOPE_COLOUR, 2.0)] if segments else [],
                   cylinders=cylinders)


def _graph_lines(config: ScenarioConfig, state: SceneState,
                 present: NDArray[np.bool_]) -> list[LinePrimitive]:
    """The communication graph: the fixed graph's edges; with radios of limited range the
    links in range (green), those the keep rows hold (blue) and kept links out of range (red,
    docs/network.md)."""
    drawn = [(i, j) for i, j in config.swarm.graph.edges if present[i] and present[j]]
    if state.links is None or not config.network.ranged:
        edges = [state.drones_m[[i, j]] for i, j in drawn]
        return [_lines(edges, GRAPH_COLOUR, 2.0)] if edges else []
    n = state.links.shape[0]
    kept = {(i, j) for i, j in config.network.kept_edges(n, config.swarm.edges)}
    groups: dict[tuple[float, float, float, float], list[Array]] = {
        GRAPH_COLOUR: [], KEPT_COLOUR: [], LOST_COLOUR: []}
    for i in range(n):
        for j in range(i + 1, n):
            if not (present[i] and present[j]):
                continue
            linked = bool(state.links[i, j])
            colour = (KEPT_COLOUR if (i, j) in kept and linked else LOST_COLOUR
                      if (i, j) in kept else GRAPH_COLOUR if linked else None)
            if colour is not None:
                groups[colour].append(state.drones_m[[i, j]])
    thickness = {GRAPH_COLOUR: 1.5, KEPT_COLOUR: 3.0, LOST_COLOUR: 3.0}
    return [_lines(segments, colour, thickness[colour])
            for colour, segments in groups.items() if segments]


def scene_update(config: ScenarioConfig, state: SceneState) -> SceneUpdate:
    """The scene of ``state`` (entities ``ENTITIES``, each replacing its previous self)."""
    stamp = sim_stamp(state.time_s)
    present = np.all(np.isfinite(state.drones_m), axis=1)
    drones = [i for i in range(state.drones_m.shape[0]) if present[i]]
    sensing = state.sensing
    targets = [r for r in range(state.targets_m.shape[0])
               if np.isfinite(state.targets_m[r]).all()]
    ground_z = (float(np.mean(state.targets_m[targets, 2])) if targets else 0.0)
    camera = config.camera
    fov = [segment for i in drones
           for segment in fov_segments(state.drones_m[i], camera.half_fov_deg,
                                       camera.range_max_m, ground_z)]
    graph_lines = _graph_lines(config, state, present)
    estimates = state.estimates_m.reshape(-1, 3)
    known = np.all(np.isfinite(estimates), axis=1)
    ellipsoids = []
    if state.estimate_covariance_m2 is not None:
        covariances = state.estimate_covariance_m2.reshape(-1, 3, 3)
        drawn = known & np.isfinite(covariances).all(axis=(1, 2))
        ellipsoids = _ellipsoids(estimates[drawn], covariances[drawn])
    estimates = estimates[known]
    delta = config.control.collision_distance_m
    entities = [
        _entity("drones", stamp,
                spheres=[_sphere(state.drones_m[i], DRONE_DIAMETER_M,
                                 SENSING_COLOUR if sensing[i] else IDLE_COLOUR)
                         for i in drones],
                texts=[_label(state.drones_m[i], str(i), (0.1, 0.1, 0.1, 1.0))
                       for i in drones]),
        _entity("collision", stamp,
                spheres=[_sphere(state.drones_m[i], 2.0 * delta, COLLISION_COLOUR)
                         for i in drones]),
        _entity("fov", stamp, lines=[_lines(fov, FOV_COLOUR, 1.0)] if fov else []),
        _entity("graph", stamp, lines=graph_lines),
        _entity("targets", stamp,
                spheres=[_sphere(state.targets_m[r], TARGET_DIAMETER_M, TARGET_COLOUR)
                         for r in targets],
                texts=[_label(state.targets_m[r], f"T{r}", TARGET_COLOUR) for r in targets]),
        _entity("estimates", stamp,
                spheres=[_sphere(p, ESTIMATE_DIAMETER_M, ESTIMATE_COLOUR) for p in estimates]),
        _entity("uncertainty", stamp, spheres=ellipsoids),
        _envelope_entity(config, stamp),
    ]
    return SceneUpdate(entities=entities)


def plot_topic(drone: int) -> str:
    return f"drone/{drone}/plot"


def plot_schema(n_targets: int) -> dict[str, Any]:
    per_target = {"type": "array", "items": {"type": "number"}, "minItems": n_targets,
                  "maxItems": n_targets}
    return {"title": "vigil.DronePlot", "type": "object", "properties": {
        "time_s": {"type": "number", "description": "sim time [s]"},
        "lambda_margin": per_target | {"description": "λ̄ − ε of this drone's copy, per target"},
        "weights": per_target | {"description": "sensing weight per target"},
        "slacks": per_target | {"description": "HOCBF slack per target"},
        "speed_m_s": {"type": "number", "description": "‖u‖, the commanded speed [m/s]"},
    }}


def plot_values(state: SceneState, drone: int) -> dict[str, Any]:
    """What ``drone/<drone>/plot`` carries for one scene."""
    def listed(values: np.ndarray | None) -> list[float]:
        return [] if values is None else [float(v) for v in values[drone]]

    speed = (float(np.linalg.norm(state.velocities_m_s[drone]))
             if state.velocities_m_s is not None else float("nan"))
    return {"time_s": state.time_s, "lambda_margin": listed(state.psi0),
            "weights": listed(state.weights), "slacks": listed(state.slacks),
            "speed_m_s": speed}


def sim_stamp(time_s: float) -> Timestamp:
    """Foxglove's timestamp of a simulated time (the clock every topic is stamped in)."""
    seconds, nanoseconds = divmod(round(time_s * 1e9), 1_000_000_000)
    return Timestamp(sec=seconds, nsec=nanoseconds)


class LogBook:
    """The ``log`` topic: a ``foxglove.Log`` line for each drone whose warned counters
    (``swarm.observe.events``) rose since the previous scene — Warning, or Error for an
    urgent one (a λ̄ breach, a vehicle event) — with what the drone says is wrong now. The
    totals are running counts, so a scene every 0.1 s misses no increase."""

    def __init__(self) -> None:
        self._reported: dict[int, TelemetryCounters] = {}

    def lines(self, state: SceneState) -> list[Log]:
        out = []
        for drone, counters in enumerate(state.counters):
            increases = increased_counters(self._reported.get(drone), counters)
            self._reported[drone] = counters
            if not increases:
                continue
            urgent = any(label in URGENT_LABELS for label, _, _ in increases)
            what = ", ".join(f"+{inc} {label} ({total} total)"
                             for label, inc, total in increases)
            status = counters.vehicle_status or counters.localization_status
            out.append(Log(timestamp=sim_stamp(state.time_s),
                           level=LogLevel.Error if urgent else LogLevel.Warning,
                           message=what + (f"; now: {status}" if status else ""),
                           name=f"drone {drone}"))
        return out


class SceneAssembler:
    """Gathers truth and telemetry per step; calls ``emit(state)`` for every complete scene
    step (every ``period_steps`` steps). Not thread-safe: feed it from one thread."""

    def __init__(self, config: ScenarioConfig, emit: Callable[[SceneState], None],
                 period_steps: int | None = None) -> None:
        self.config = config
        self.n, self.m = config.swarm.n_drones, len(config.targets)
        self.period_steps = period_steps or max(1, round(SCENE_PERIOD_S / config.scenario.dt_s))
        self._emit = emit
        self._pending: dict[int, _Pending] = {}
        self.emitted = 0
        self.incomplete = 0  # scene steps given up: a message never came

    def wants(self, step: int) -> bool:
        """Whether a message of this step can be part of a scene (a scene step)."""
        return step % self.period_steps == 0

    def on_truth(self, truth: TruthWire) -> None:
        pending = self._slot(truth.step)
        if pending is not None:
            pending.truth = truth
            self._check(truth.step)

    def on_telemetry(self, tel: TelemetryWire) -> None:
        pending = self._slot(tel.step)
        if pending is not None and 0 <= tel.drone < self.n:
            pending.telemetry[tel.drone] = tel
            self._check(tel.step)

    def _slot(self, step: int) -> _Pending | None:
        if not self.wants(step):
            return None
        return self._pending.setdefault(step, _Pending(self.n))

    def _check(self, step: int) -> None:
        pending = self._pending[step]
        if pending.truth is None or any(t is None for t in pending.telemetry):
            return
        del self._pending[step]
        for older in [k for k in self._pending if k < step]:
            del self._pending[older]
            self.incomplete += 1
        self.emitted += 1
        self._emit(pending.state(self.m))


class _Pending:
    def __init__(self, n: int) -> None:
        self.truth: TruthWire | None = None
        self.telemetry: list[TelemetryWire | None] = [None] * n

    def state(self, m: int) -> SceneState:
        truth = self.truth
        assert truth is not None
        telemetry = [t for t in self.telemetry if t is not None]
        n = len(telemetry)

        def stack(field: str, shape: tuple[int, ...]) -> Array:
            return np.array([wire_values(getattr(t, field)) for t in telemetry]).reshape(shape)

        return SceneState(step=truth.step, time_s=truth.time_s,
                          drones_m=wire_values(truth.drone_positions),
                          targets_m=wire_values(truth.target_positions),
                          weights=stack("weights", (n, m)),
                          estimates_m=np.array([wire_values(t.estimates)[:, :3]
                                                for t in telemetry]).reshape(n, m, 3),
                          estimate_covariance_m2=stack("estimate_covariance", (n, m, 3, 3)),
                          psi0=stack("psi0", (n, m)), slacks=stack("slacks", (n, m)),
                          velocities_m_s=stack("velocity", (n, 3)),
                          counters=tuple(t.counters for t in telemetry),
                          links=truth.radio_link_matrix())


