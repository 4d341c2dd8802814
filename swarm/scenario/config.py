"""Scenario configuration: TOML file → validated, frozen ``ScenarioConfig``.

Types are checked by msgspec (it names the failing key path), values by the ``__post_init__``
of each section and of the core parameter classes, and cross-section rules (graph connected,
consensus steps stable for the graph, …) by ``ScenarioConfig.__post_init__``. Any problem
becomes one ``ConfigError`` whose text is a single line naming the key and the reason.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal, overload

import msgspec
import numpy as np
import tomlkit

from swarm.core import icf
from swarm.core.graph import (
    CommunicationGraph,
    pi_consensus_is_stable,
    pi_consensus_is_stable_on_every_graph,
)
from swarm.core.network import NetworkParams
from swarm.core.params import (
    ControlParams,
    EstimationParams,
    GramianParams,
    PerceptionParams,
    require,
    require_finite,
    require_finite_positive,
)
from swarm.core.safety import KeepOutCylinder, SafetyParams, envelope_margins
from swarm.errors import UsageError
from swarm.mavlink.signing import SigningKeyError, read_signing_key
from swarm.messages.wire import WireCodec
from swarm.models.camera import CameraParams
from swarm.models.kinematics import (
    ARDUCOPTER_SITL_RESPONSE,
    IDEAL_RESPONSE,
    PX4_SITL_RESPONSE,
    InitialPlacementError,
    VelocityResponse,
    sample_initial_positions,
)
from swarm.models.targets import (
    LinearTrajectory,
    OutAndBackTrajectory,
    SinusoidTrajectory,
    Trajectory,
)
from swarm.net.security import OBSERVER_ROLE, SecurityError, TlsIdentity, check_tls_dir
from swarm.scenario.overrides import Override, OverrideError, apply_overrides
from swarm.vision.geometry import (
    CalibrationError,
    calibration_for,
    invertible_lens_rays,
    pixel_grid,
)
from swarm.watch.vehicle_watch import VEHICLE_EVENT_POLICIES, VehicleEventPolicy

Vector3 = tuple[float, float, float]


class ConfigError(UsageError, ValueError):
    """A scenario file that cannot be used; ``str()`` is one line naming key and reason."""

    label: ClassVar[str] = "config error: "


@dataclass(frozen=True)
class ScenarioSection:
    """The mission: its name, length, time step and default seed."""

    name: str  # shown in summaries and recordings
    duration_s: float  # simulated time [s]
    dt_s: float = 0.02  # ΔT of every discretization [s]
    seed: int = 0  # default seed; --seed overrides it

    def __post_init__(self) -> None:
        require(bool(self.name.strip()), "name", "must not be empty", self.name)
        require_finite_positive("duration_s", self.duration_s)
        require(math.isfinite(self.dt_s) and 0 < self.dt_s <= 0.1, "dt_s",
                "must lie in (0, 0.1] s", self.dt_s)
        require(self.duration_s >= self.dt_s, "duration_s", "must be at least one step (dt_s)",
                self.duration_s)
        require(0 <= self.seed < 2**63, "seed", "must be an integer in [0, 2^63)", self.seed)


@dataclass(frozen=True)
class SwarmSection:
    """The drones, their communication graph and the box they start in."""

    n_drones: int  # N, the number of drones
    # undirected communication edges [i, j], drone ids 0..N−1; the graph must be connected
    edges: tuple[tuple[int, int], ...]
    initial_box_center_m: Vector3 = (0.0, 0.0, 3.5)  # centre of the start box [m]
    initial_box_size_m: Vector3 = (4.0, 4.0, 2.0)  # side lengths of the start box [m]
    initial_min_separation_m: float = 1.0  # start positions are resampled until this apart [m]

    def __post_init__(self) -> None:
        require(2 <= self.n_drones <= 256, "n_drones", "must be an integer in [2, 256]",
                self.n_drones)
        for value in self.initial_box_center_m:
            require_finite("initial_box_center_m", value)
        for value in self.initial_box_size_m:
            require(math.isfinite(value) and value >= 0, "initial_box_size_m",
                    "must hold finite sizes >= 0", self.initial_box_size_m)
        require_finite_positive("initial_min_separation_m", self.initial_min_separation_m)
        try:
            graph = self.graph
        except ValueError as err:
            raise ValueError(str(err)) from None
        if not graph.is_connected():
            raise ValueError("edges do not connect every drone: the graph is disconnected")

    @property
    def graph(self) -> CommunicationGraph:
        return CommunicationGraph(self.n_drones, self.edges)


TrajectoryKind = Literal["linear", "sinusoid", "out_and_back"]


@dataclass(frozen=True)
class TargetSection:
    """One ground target and how it moves (``swarm.models.targets``); 1 to 16 of them."""

    # "linear" (cruise at velocity_m_s), "sinusoid" (drift plus a sine per axis) or
    # "out_and_back" (out at velocity_m_s, turn at turn_s, back at rest at start_m at back_s)
    trajectory: TrajectoryKind
    start_m: Vector3  # position at t = 0 [m]
    velocity_m_s: Vector3 = (0.0, 0.0, 0.0)  # cruise, or drift of a sinusoid [m/s]
    amplitude_m: Vector3 = (0.0, 0.0, 0.0)  # sinusoid amplitude per axis [m]
    angular_rate_rad_s: float = 0.0  # sinusoid ω [rad/s]
    turn_s: float = 0.0  # out_and_back: start of the turn [s]
    back_s: float = 0.0  # out_and_back: back at rest at start_m [s]
    ramp_s: float = 5.0  # raised-cosine ramp of every velocity change [s]

    def __post_init__(self) -> None:
        for name in ("start_m", "velocity_m_s", "amplitude_m"):
            for value in getattr(self, name):
                require_finite(name, value)
        require_finite("angular_rate_rad_s", self.angular_rate_rad_s)
        require_finite_positive("ramp_s", self.ramp_s)
        if self.trajectory == "out_and_back":
            require(math.isfinite(self.turn_s) and self.turn_s > self.ramp_s, "turn_s",
                    "must be a finite number > ramp_s", self.turn_s)
            require(math.isfinite(self.back_s) and self.back_s > self.turn_s + 2 * self.ramp_s,
                    "back_s", "must be a finite number > turn_s + 2·ramp_s", self.back_s)

    def build(self) -> Trajectory:
        if self.trajectory == "linear":
            return LinearTrajectory(self.start_m, self.velocity_m_s, self.ramp_s)
        if self.trajectory == "sinusoid":
            return SinusoidTrajectory(self.start_m, self.velocity_m_s, self.amplitude_m,
                                      self.angular_rate_rad_s, self.ramp_s)
        return OutAndBackTrajectory(self.start_m, self.velocity_m_s, self.turn_s, self.back_s,
                                    self.ramp_s)


@dataclass(frozen=True)
class ChecksSection:
    """Tolerances of the SPEC invariants checked after a run (exit code 1 when violated)."""

    lambda_tolerance: float = 0.005  # λ̄ copies may dip to ε − this after control.start_s [s]
    collision_tolerance_m: float = 1e-3  # pairwise distance may dip to Δ − this [m]
    # every drone's distance to the [safety] envelope's boundaries may dip to −this [m]: a
    # first-order barrier holds exactly on a flat boundary for ideal vehicles; a keep-out
    # cylinder's curvature lets one step cut in by ~ΔT²‖u‖²/(2r) (1 mm at 3 m/s, r = 1.5 m)
    envelope_tolerance_m: float = 5e-3

    def __post_init__(self) -> None:
        require(math.isfinite(self.lambda_tolerance) and self.lambda_tolerance >= 0,
                "lambda_tolerance", "must be a finite number >= 0", self.lambda_tolerance)
        require(math.isfinite(self.collision_tolerance_m) and self.collision_tolerance_m >= 0,
                "collision_tolerance_m", "must be a finite number >= 0",
                self.collision_tolerance_m)
        require(math.isfinite(self.envelope_tolerance_m) and self.envelope_tolerance_m >= 0,
                "envelope_tolerance_m", "must be a finite number >= 0",
                self.envelope_tolerance_m)


@dataclass(frozen=True)
class KeepOutSection:
    """One keep-out cylinder of [safety]: a static obstacle no drone's centre may enter."""

    center_m: tuple[float, float]  # [x, y] in the world frame [m]
    radius_m: float  # no drone's centre comes nearer to the axis than this [m]


@dataclass(frozen=True)
class SafetySection:
    """The safety envelope (``swarm.core.safety``): an altitude band, a convex keep-in
    polygon (``keep_in``: vertices [x, y], either way round; or ``keep_in_box_m``:
    [x_min, y_min, x_max, y_max]) and keep-out cylinders, each kind with its barrier gain
    [1/s]; hard rows of every drone's QP. Empty (the default): no envelope."""

    floor_m: float | None = None  # lowest z allowed, world frame (z up) [m]
    ceiling_m: float | None = None  # highest z allowed [m]
    keep_in: tuple[tuple[float, float], ...] = ()  # convex keep-in polygon, vertices [x, y] [m]
    # the keep-in area as a box [x_min, y_min, x_max, y_max] instead of keep_in [m]
    keep_in_box_m: tuple[float, float, float, float] | None = None
    keep_out: tuple[KeepOutSection, ...] = ()  # static obstacles, as vertical cylinders
    altitude_gain: float = 1.0  # α of the floor and ceiling rows [1/s]
    fence_gain: float = 1.0  # α of the keep-in rows [1/s]
    obstacle_gain: float = 1.0  # α of the keep-out rows [1/s]

    @property
    def params(self) -> SafetyParams:
        """The envelope as the core takes it (built and checked once, at load)."""
        return self.__dict__["_params"]

    def __post_init__(self) -> None:
        keep_in = self.keep_in
        if self.keep_in_box_m is not None:
            require(not keep_in, "keep_in_box_m", "and keep_in are two ways of giving the "
                    "keep-in area: give one", list(self.keep_in_box_m))
            x_min, y_min, x_max, y_max = self.keep_in_box_m
            require(all(math.isfinite(v) for v in self.keep_in_box_m), "keep_in_box_m",
                    "must be 4 finite numbers", list(self.keep_in_box_m))
            require(x_min < x_max and y_min < y_max, "keep_in_box_m",
                    "must be [x_min, y_min, x_max, y_max] with min < max",
                    list(self.keep_in_box_m))
            keep_in = ((x_min, y_min), (x_max, y_min), (x_max, y_max), (x_min, y_max))
        obstacles = []
        for k, obstacle in enumerate(self.keep_out):
            try:
                x_m, y_m = obstacle.center_m
                obstacles.append(KeepOutCylinder((x_m, y_m), obstacle.radius_m))
            except ValueError as err:
                raise ValueError(f"keep_out[{k}].{str(err).removeprefix('keep_out.')}") from None
        object.__setattr__(self, "_params", SafetyParams(
            floor_m=self.floor_m, ceiling_m=self.ceiling_m, keep_in=keep_in,
            keep_out=tuple(obstacles), altitude_gain=self.altitude_gain,
            fence_gain=self.fence_gain, obstacle_gain=self.obstacle_gain))


Flavour = Literal["px4", "ardupilot"]
EndAction = Literal["hold", "land", "rtl"]
VehicleStart = Literal["air", "ground"]
ResponseKind = Literal["ideal", "arducopter", "px4", "custom"]
SetpointKind = Literal["velocity", "tracked"]
DEFAULT_SETPOINT_TIMEOUT_S = {"px4": 0.5, "ardupilot": 3.0}  # COM_OF_LOSS_T, GUID_TIMEOUT

# What [control] takes for tracking_error_bound_m_s (ē [m/s]) and command_accel_limit_m_s2
# (a [m/s²]) when the config leaves them out, by how the vehicles move: ideal vehicles fly
# the thesis' QP unchanged; for the SITL fits, ē and a are the values that held Case 1 in
# the in-process runs with each fitted response and on the SITL builds
# (docs/guarantee_real_vehicles.md; sweeps/sitl_soak/).
TRACKING_DEFAULTS: dict[str, tuple[float, float]] = {
    "ideal": (0.0, 0.0), "custom": (0.0, 0.0), "arducopter": (0.1, 4.0), "px4": (0.2, 4.0)}
TRACKING_KEYS = ("tracking_error_bound_m_s", "command_accel_limit_m_s2")
AUTOPILOT_RESPONSE = {"ardupilot": "arducopter", "px4": "px4"}  # flavour → its fitted model
# Where W's origin is on Earth (ArduPilot's SITL test field, CMAC), for autopilots that need
# a home: [latitude deg, longitude deg, altitude m above mean sea level].
DEFAULT_GEO_ORIGIN = (-35.363261, 149.165230, 584.0)


@dataclass(frozen=True)
class VehiclesSection:
    """The autopilots the agents command over MAVLink (SPEC §12)."""

    flavour: Flavour = "px4"  # handshake and failsafe rules: "px4" or "ardupilot"
    origin_offsets_m: tuple[Vector3, ...] = ()  # local-NED origin of each vehicle in W [m]
    setpoint_timeout_s: float = 0.0  # setpoint loss → hold after this [s]; 0 = flavour default
    # MAVLink 2 signing between each agent and its vehicle: a file holding the 32-byte key as
    # 64 hex digits (swarm.mavlink.signing), relative to the config file; "" = no signing.
    # Only the path is kept here (recordings never hold the key).
    signing_key_file: str = ""
    # What every agent has its vehicle do when it leaves (mission end, Ctrl-C, an error):
    # "hold" (ArduPilot BRAKE, PX4 Hold), "land" or "rtl" (return to launch).
    end_action: EndAction = "hold"
    # Emulated vehicles only: "air" = at the start position, armed, hovering (the thesis'
    # start); "ground" = on the ground below it, disarmed (the agents take off; realtime only).
    start: VehicleStart = "air"
    # Emulated vehicles (and the in-process reference) only: how their velocity follows the
    # command (swarm.models.kinematics.VelocityResponse): "ideal" (the thesis' single
    # integrator, v = u), "arducopter" (the lag and acceleration limit fitted to ArduCopter
    # SITL), "px4" (the same, fitted to PX4 SITL) or "custom" (the two values below).
    response: ResponseKind = "ideal"
    response_time_constant_s: float = 0.0  # "custom": the first-order lag τ [s]
    response_accel_limit_m_s2: float = 0.0  # "custom": the acceleration limit, 0 = none [m/s²]
    # One pymavlink connection string per drone for autopilots started elsewhere (launch-swarm
    # then serves no vehicles and supervises agents flying these); () = emulated vehicles.
    mavlink_urls: tuple[str, ...] = ()
    geo_origin: Vector3 = DEFAULT_GEO_ORIGIN  # W's origin on Earth [deg, deg, m]; SITL homes
    # What each agent sends its autopilot every step: "velocity" (u only) or "tracked" (the
    # command reference: position, velocity and acceleration along ṙ = u, so the autopilot's
    # position loop removes its drift; swarm.models.command_reference).
    setpoints: SetpointKind = "tracked"
    # "tracked": the reference is put back on the vehicle when they are this far apart [m].
    reference_reset_m: float = 1.0
    # What an agent does when its vehicle is not as asked during the mission (disarmed,
    # another mode, no position; swarm.watch.vehicle_watch): "continue" (degraded, in the swarm),
    # "leave" (the agent ends, the others go on) or "end" (the mission ends).
    on_vehicle_event: VehicleEventPolicy = "continue"

    def __post_init__(self) -> None:
        require(self.flavour in ("px4", "ardupilot"), "flavour", "must be 'px4' or 'ardupilot'",
                self.flavour)
        for offset in self.origin_offsets_m:
            for value in offset:
                require_finite("origin_offsets_m", value)
        require(math.isfinite(self.setpoint_timeout_s) and self.setpoint_timeout_s >= 0,
                "setpoint_timeout_s", "must be a finite number >= 0", self.setpoint_timeout_s)
        require(self.end_action in ("hold", "land", "rtl"), "end_action",
                "must be 'hold', 'land' or 'rtl'", self.end_action)
        require(self.start in ("air", "ground"), "start", "must be 'air' or 'ground'",
                self.start)
        require(self.on_vehicle_event in VEHICLE_EVENT_POLICIES, "on_vehicle_event",
                "must be 'continue', 'leave' or 'end'", self.on_vehicle_event)
        require(self.setpoints in ("velocity", "tracked"), "setpoints",
                "must be 'velocity' or 'tracked'", self.setpoints)
        require(math.isfinite(self.reference_reset_m) and self.reference_reset_m > 0,
                "reference_reset_m", "must be a finite number > 0", self.reference_reset_m)
        require(self.response in ("ideal", "arducopter", "px4", "custom"), "response",
                "must be 'ideal', 'arducopter', 'px4' or 'custom'", self.response)
        for name in ("response_time_constant_s", "response_accel_limit_m_s2"):
            value = getattr(self, name)
            require(math.isfinite(value) and value >= 0, name, "must be a finite number >= 0",
                    value)
            require(self.response == "custom" or value == 0, name,
                    "is used only with response = 'custom'", value)
        for url in self.mavlink_urls:
            require(bool(url.strip()) and url == url.strip() and " " not in url,
                    "mavlink_urls", "must hold pymavlink connection strings without spaces",
                    url)
        lat, lon, alt = self.geo_origin
        require(math.isfinite(lat) and -85.0 <= lat <= 85.0, "geo_origin",
                "latitude must lie in [-85, 85] deg", lat)
        require(math.isfinite(lon) and -180.0 <= lon <= 180.0, "geo_origin",
                "longitude must lie in [-180, 180] deg", lon)
        require_finite("geo_origin", alt)

    def origin_w(self, drone_id: int) -> np.ndarray:
        if not self.origin_offsets_m:
            return np.zeros(3)
        return np.array(self.origin_offsets_m[drone_id], dtype=float)

    @property
    def failsafe_timeout_s(self) -> float:
        return self.setpoint_timeout_s or DEFAULT_SETPOINT_TIMEOUT_S[self.flavour]

    @property
    def velocity_response(self) -> VelocityResponse:
        """The emulated vehicles' velocity response this section names."""
        if self.response == "arducopter":
            return ARDUCOPTER_SITL_RESPONSE
        if self.response == "px4":
            return PX4_SITL_RESPONSE
        if self.response == "custom":
            return VelocityResponse(self.response_time_constant_s,
                                    self.response_accel_limit_m_s2)
        return IDEAL_RESPONSE

    def signing_key(self) -> bytes | None:
        """The MAVLink signing key read from ``signing_key_file`` now (None: signing off);
        ConfigError (one line, never the file's content) when the file is unusable."""
        if not self.signing_key_file:
            return None
        try:
            return read_signing_key(self.signing_key_file)
        except SigningKeyError as err:
            raise ConfigError(f"vehicles.signing_key_file: {err}") from None


@dataclass(frozen=True)
class RuntimeSection:
    """Timing of the process swarm (SPEC §12)."""

    stale_timeout_s: float = 0.1  # realtime: neighbour data older than this is left out [s]
    lockstep_timeout_s: float = 20.0  # lockstep: a peer silent this long aborts the mission [s]
    start_timeout_s: float = 60.0  # every drone armed and streaming within this [s]
    # realtime: a drone not heard (no beacon) this long leaves the membership whose size is
    # the N of the formulas; heard again, it rejoins [s]
    member_timeout_s: float = 1.0

    def __post_init__(self) -> None:
        require_finite_positive("stale_timeout_s", self.stale_timeout_s)
        require_finite_positive("member_timeout_s", self.member_timeout_s)
        # Shorter, a drone whose data is merely late would leave and rejoin the membership.
        require(self.member_timeout_s >= self.stale_timeout_s, "member_timeout_s",
                f"must be >= stale_timeout_s ({self.stale_timeout_s})", self.member_timeout_s)
        require_finite_positive("lockstep_timeout_s", self.lockstep_timeout_s)
        require_finite_positive("start_timeout_s", self.start_timeout_s)


@dataclass(frozen=True)
class SecuritySection:
    """Zenoh TLS with mutual authentication and the router's access control
    (``swarm.net.security`` describes the directory's layout and the rules)."""

    # The directory of ca.pem, world.pem/.key, observer.pem/.key and agent-<i>.pem/.key,
    # relative to the config file; "" = off (plain TCP on loopback).
    tls_dir: str = ""

    @property
    def enabled(self) -> bool:
        return bool(self.tls_dir)

    def identity(self, role: str = OBSERVER_ROLE) -> TlsIdentity | None:
        """The CA and ``role``'s certificate and key (``swarm.net.security.agent_role(i)``,
        "world", "observer"); None when security is off."""
        return TlsIdentity.of(self.tls_dir, role) if self.tls_dir else None

    def check(self, n_drones: int) -> None:
        """ConfigError (one line) unless every file of the layout is there."""
        if not self.tls_dir:
            return
        try:
            check_tls_dir(self.tls_dir, n_drones)
        except SecurityError as err:
            raise ConfigError(f"security.tls_dir: {err}") from None


@dataclass(frozen=True)
class ScenarioConfig:
    scenario: ScenarioSection
    swarm: SwarmSection
    targets: tuple[TargetSection, ...]
    # the downward camera: range and square field of view (SPEC §2, Fig. 3.1), image noise
    camera: CameraParams = field(default_factory=CameraParams)
    perception: PerceptionParams = field(default_factory=PerceptionParams)
    estimation: EstimationParams = field(default_factory=EstimationParams)
    gramian: GramianParams = field(default_factory=GramianParams)
    control: ControlParams = field(default_factory=ControlParams)
    checks: ChecksSection = field(default_factory=ChecksSection)
    safety: SafetySection = field(default_factory=SafetySection)
    # the radios: the fixed graph of swarm.edges (the default) or a range (swarm.core.network)
    network: NetworkParams = field(default_factory=NetworkParams)
    vehicles: VehiclesSection = field(default_factory=VehiclesSection)
    runtime: RuntimeSection = field(default_factory=RuntimeSection)
    security: SecuritySection = field(default_factory=SecuritySection)
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        _cross_check(self)

    @property
    def n_steps(self) -> int:
        return round(self.scenario.duration_s / self.scenario.dt_s)

    @property
    def camera_steps_per_frame(self) -> int:
        """Steps between a rendered camera's frames (1: a frame every step)."""
        rate = self.camera.frame_rate_hz
        return 1 if rate is None else max(round(1.0 / (rate * self.scenario.dt_s)), 1)

    @property
    def state_dimension(self) -> int:
        """The ICF state size of one target (``icf.state_dimension`` of the model)."""
        return icf.state_dimension(self.estimation.model)

    def wire_codec(self) -> WireCodec:
        """The codec every process of this scenario speaks: N drones, M targets, the
        estimator's state size, and on a range graph the reach stamps of round 0."""
        return WireCodec(self.swarm.n_drones, len(self.targets), self.state_dimension,
                         reach_stamps=self.network.ranged)

    def with_seed(self, seed: int) -> ScenarioConfig:
        """The same scenario with another seed (``--seed``); ConfigError if invalid."""
        try:
            return dataclasses.replace(
                self, scenario=dataclasses.replace(self.scenario, seed=seed))
        except ValueError as err:
            raise ConfigError(f"--seed: {err}") from None

    def with_duration(self, duration_s: float) -> ScenarioConfig:
        """The same scenario with another length (``--duration``); ConfigError if invalid."""
        try:
            return dataclasses.replace(
                self, scenario=dataclasses.replace(self.scenario, duration_s=duration_s))
        except ValueError as err:
            raise ConfigError(f"--duration: {err}") from None


def realtime_only_reason(vehicles: VehiclesSection, *, mode: str, inprocess: bool = False,
                         external: bool = False, restarts_agents: bool = False,
                         kills_agents: bool = False, faulty_consensus: bool = False
                         ) -> str | None:
    """Why this run needs ``--mode realtime`` and does not have it (one line), else None: the
    mode rules of every executable and of the launcher's options, stated here only.
    ``external``: the agents fly autopilots the world does not serve (SITL, --mavlink);
    ``restarts_agents``, ``kills_agents``: --agent-restarts, --kill-agent;
    ``faulty_consensus``: an agent's --drop-consensus or --delay-consensus."""
    if not inprocess and mode == "realtime":
        return None
    if external:
        return ("real or external autopilots (--sitl, --mavlink, vehicles.mavlink_urls) need "
                "--mode realtime: they cannot wait for the simulation")
    for flag, given in (("--agent-restarts", restarts_agents), ("--kill-agent", kills_agents)):
        if given:
            return (f"{flag} needs --mode realtime (in lockstep every drone waits for every "
                    f"other one)")
    if faulty_consensus:
        return ("--drop-consensus and --delay-consensus need --mode realtime (in lockstep a "
                "lost message stalls every neighbour)")
    if vehicles.start == "ground":
        return ("vehicles.start = 'ground' needs --mode realtime: the take-off runs on the wall "
                "clock (lockstep and --inprocess start the drones in the air, as the thesis)")
    return None


def _cross_check(config: ScenarioConfig) -> None:
    """Rules that involve more than one section; each names its key."""
    dt_ms = config.scenario.dt_s * 1000.0
    if abs(dt_ms - round(dt_ms)) > 1e-9:
        raise ConfigError(f"scenario.dt_s must be a whole number of milliseconds (MAVLink "
                          f"time_boot_ms stamps the steps) (got {config.scenario.dt_s})")
    rate = config.camera.frame_rate_hz
    if rate is not None:
        steps = 1.0 / (rate * config.scenario.dt_s)
        if not (steps >= 1.0 - 1e-9 and abs(steps - round(steps)) <= 1e-6):
            raise ConfigError(f"camera.frame_rate_hz must divide the step rate "
                              f"{1.0 / config.scenario.dt_s:g} Hz (a frame every whole number "
                              f"of steps) (got {rate})")
    if config.camera.rendered:
        # A lens whose polynomial folds over the image cannot be rendered or undistorted;
        # checked on a 33 x 33 grid here (the renderer checks every pixel).
        calibration = calibration_for(config.camera)
        side = calibration.width_px
        try:
            invertible_lens_rays(calibration, pixel_grid(side, side, max(side // 32, 1)))
        except CalibrationError as err:
            raise ConfigError(f"camera.distortion: {err}") from None
    offsets = config.vehicles.origin_offsets_m
    if offsets and len(offsets) != config.swarm.n_drones:
        raise ConfigError(f"vehicles.origin_offsets_m needs one [x, y, z] per drone "
                          f"({config.swarm.n_drones}) or none (got {len(offsets)})")
    urls = config.vehicles.mavlink_urls
    if urls and len(urls) != config.swarm.n_drones:
        raise ConfigError(f"vehicles.mavlink_urls needs one connection string per drone "
                          f"({config.swarm.n_drones}) or none (got {len(urls)})")
    if not 1 <= len(config.targets) <= 16:
        raise ConfigError(f"targets: need 1 to 16 [[targets]] entries (got {len(config.targets)})")
    graph = config.swarm.graph
    dt = config.scenario.dt_s
    est, gram, ctrl = config.estimation, config.gramian, config.control
    max_degree = max(graph.degree(i) for i in range(graph.n_nodes))
    if est.consensus_weights == "laplacian" and not est.laplacian_step < 1.0 / max_degree:
        raise ConfigError(
            f"estimation.laplacian_step must be < 1/Δ_max = {1.0 / max_degree:.4g} for this "
            f"graph (got {est.laplacian_step})")
    lam_max = graph.laplacian_max_eigenvalue
    if config.network.ranged:
        # Any graph of N drones may come up: check the consensus on the worst, the complete
        # graph (λ_max(L) = N, the largest of any graph of N nodes).
        graph = CommunicationGraph(graph.n_nodes, tuple(
            (a, b) for a in range(graph.n_nodes) for b in range(a + 1, graph.n_nodes)))
        lam_max = graph.laplacian_max_eigenvalue
        _check_kept_links_at_start(config)
    for name, gains in (("projector_consensus", gram.projector_consensus),
                        ("weight_consensus", gram.weight_consensus)):
        if not gains.kp * lam_max * dt < 2.0:
            where = ("every graph of swarm.n_drones (a range graph may become any)"
                     if config.network.ranged else "this graph")
            raise ConfigError(
                f"gramian.{name}.kp: K_p·λ_max(L)·ΔT = {gains.kp * lam_max * dt:.3g} must be "
                f"< 2 for a stable Euler step on {where} (λ_max(L) = {lam_max:.3g})")
        stable, radius = (pi_consensus_is_stable_on_every_graph(
            graph.n_nodes, gains, dt, own_integral=config.network.integral == "own")
            if config.network.ranged else pi_consensus_is_stable(graph, gains, dt))
        if not stable:
            where = ("some graph of swarm.n_drones (a range graph may become any)"
                     if config.network.ranged else "this graph")
            raise ConfigError(
                f"gramian.{name}: the Euler-discretized PI consensus is unstable on {where} "
                f"(spectral radius {radius:.4f} >= 1); lower zeta/kp/ki or dt_s")
    gramian_mode = 1.0 - dt * (gram.forgetting + gram.consensus_gain * lam_max)
    if not abs(gramian_mode) < 1.0:
        raise ConfigError(
            f"gramian.consensus_gain: ΔT·(ρ + gain·λ_max(L)) = {1 - gramian_mode:.3g} must be "
            f"< 2 for a stable Euler step")
    if not config.camera.range_min_m < config.perception.d_min_th_m:
        raise ConfigError(
            f"perception.d_min_th_m must exceed camera.range_min_m = "
            f"{config.camera.range_min_m} (got {config.perception.d_min_th_m})")
    if not config.perception.d_max_th_m < config.camera.range_max_m:
        raise ConfigError(
            f"perception.d_max_th_m must be below camera.range_max_m = "
            f"{config.camera.range_max_m} (got {config.perception.d_max_th_m})")
    if not config.perception.alpha_th_deg < config.camera.half_fov_deg:
        raise ConfigError(
            f"perception.alpha_th_deg must be below camera.half_fov_deg = "
            f"{config.camera.half_fov_deg} (got {config.perception.alpha_th_deg})")
    if ctrl.start_s >= config.scenario.duration_s:
        raise ConfigError(f"control.start_s must be before scenario.duration_s = "
                          f"{config.scenario.duration_s} (got {ctrl.start_s})")
    box = np.asarray(config.swarm.initial_box_size_m, dtype=float)
    box_list = [float(v) for v in box]
    if config.swarm.initial_min_separation_m < ctrl.collision_distance_m:
        raise ConfigError(
            f"swarm.initial_min_separation_m must be >= control.collision_distance_m = "
            f"{ctrl.collision_distance_m} (got {config.swarm.initial_min_separation_m})")
    if float(np.prod(box + config.swarm.initial_min_separation_m)) < (
            config.swarm.n_drones * config.swarm.initial_min_separation_m**3):
        raise ConfigError(
            f"swarm.initial_box_size_m {box_list} is too small for {config.swarm.n_drones} "
            f"drones {config.swarm.initial_min_separation_m} m apart")
    _check_start_inside_envelope(config)
    _check_targets_seen_at_start(config)
    try:  # the volume bound above is necessary, not sufficient: try the config's own seed
        sample_initial_positions(
            config.swarm.n_drones, np.asarray(config.swarm.initial_box_center_m), box,
            config.swarm.initial_min_separation_m,
            np.random.default_rng(config.scenario.seed), max_tries=2_000)
    except InitialPlacementError as err:
        raise ConfigError(f"swarm.initial_box_size_m: {err}") from None


# -- loading -------------------------------------------------------------------------------


def _check_kept_links_at_start(config: ScenarioConfig) -> None:
    """With a network.keep rule, the start box fits within R_keep (every kept pair starts
    inside its barrier: the box's diagonal is the farthest two drones can start apart)."""
    net = config.network
    if not net.keeps_links:
        return
    diagonal_m = float(np.linalg.norm(config.swarm.initial_box_size_m))
    if diagonal_m > net.kept_range_m:
        raise ConfigError(
            f"network.keep_range_m: R_keep = {net.kept_range_m:g} m is shorter than the start "
            f"box's diagonal ({diagonal_m:.3g} m): kept drones may start out of it")


def _check_start_inside_envelope(config: ScenarioConfig) -> None:
    """Every drone starts inside the [safety] envelope: the start box (whose corners bound
    the convex keep-in area's and the band's worst case) lies inside the band and the
    keep-in polygon, and no keep-out cylinder reaches into it."""
    envelope = config.safety.params
    if envelope.empty:
        return
    center = np.asarray(config.swarm.initial_box_center_m, dtype=float)
    half = np.asarray(config.swarm.initial_box_size_m, dtype=float) / 2.0
    corners = [center + half * np.array(signs) for signs in
               ((sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1))]
    for kind in ("floor", "ceiling", "fence"):
        worst = min((envelope_margins(tuple(c), envelope).get(kind, math.inf), tuple(c))
                    for c in corners)
        if worst[0] < 0.0:
            raise ConfigError(
                f"swarm.initial_box_size_m: drones may start outside the safety envelope "
                f"({kind}: the start box corner {[round(float(v), 3) for v in worst[1]]} is "
                f"{-worst[0]:.3g} m beyond it)")
    for k, obstacle in enumerate(envelope.keep_out):
        nearest = np.clip(obstacle.center_m, center[:2] - half[:2], center[:2] + half[:2])
        if math.dist(nearest, obstacle.center_m) <= obstacle.radius_m:
            raise ConfigError(
                f"safety.keep_out[{k}]: the cylinder reaches into the drones' start box "
                f"(centre {center.tolist()}, size {(2 * half).tolist()}): a drone may start "
                f"inside it")


def _check_targets_seen_at_start(config: ScenarioConfig) -> None:
    """Some drone start in the start box can see every target at t = 0 (SPEC §2: the camera
    looks down, sees D_m < d < D_M and |x̄|, |ȳ| ≤ tan α_M). A target none can see gives no
    information, while G(0) = 2εI decays below ε within ln 2/ρ: the λ̄ ≥ ε barrier, on from
    control.start_s, could never hold. Three necessary conditions, each on its own exact:
    the target below the box's top, nearer than D_M to the box, and inside the field of view
    of a camera at the box's top right above the box's point nearest to it."""
    center = np.asarray(config.swarm.initial_box_center_m, dtype=float)
    half = np.asarray(config.swarm.initial_box_size_m, dtype=float) / 2.0
    low, high = center - half, center + half
    top_z = float(high[2])
    camera = config.camera
    for k, target in enumerate(config.targets):
        start = np.asarray(target.start_m, dtype=float)
        key = f"targets[{k}].start_m"
        if not start[2] < top_z:
            raise ConfigError(
                f"{key}: z = {start[2]:g} m is not below the top of the drones' start box "
                f"(z = {top_z:g} m, swarm.initial_box_center_m and initial_box_size_m): the "
                f"cameras look down, no drone can see this target at the start")
        nearest = np.clip(start, low, high)
        distance = math.dist(nearest, start)
        if not distance < camera.range_max_m:
            raise ConfigError(
                f"{key}: {distance:.3g} m from the nearest point of the drones' start box, "
                f"not within camera.range_max_m = {camera.range_max_m:g} m: no drone can see "
                f"this target at the start")
        reach = (top_z - start[2]) * camera.image_half_width
        aside = float(np.max(np.abs(start[:2] - nearest[:2])))
        if aside > reach:
            raise ConfigError(
                f"{key}: {aside:.3g} m beside the drones' start box, outside every camera's "
                f"field of view at the start (from the box's top, {top_z - start[2]:.3g} m "
                f"above it, camera.half_fov_deg = {camera.half_fov_deg:g} reaches "
                f"{reach:.3g} m aside)")


def _check_unknown_keys(data: object, schema: object, path: str) -> None:
    """msgspec ignores unknown keys of dataclasses; a typo must not pass silently."""
    origin = typing.get_origin(schema)
    if origin is tuple and isinstance(data, list):
        args = typing.get_args(schema)
        if len(args) == 2 and args[1] is Ellipsis:
            for index, item in enumerate(data):
                _check_unknown_keys(item, args[0], f"{path}[{index}]")
        return
    if not (dataclasses.is_dataclass(schema) and isinstance(schema, type)):
        return
    if not isinstance(data, dict):
        return
    hints = typing.get_type_hints(schema)
    known = {f.name for f in dataclasses.fields(schema) if f.init and f.name != "source"}
    for key, value in data.items():
        shown = key if key.isidentifier() else repr(key)
        where = f"{path}.{shown}" if path else shown
        if key not in known:
            raise ConfigError(f"{where}: unknown key (known keys here: {', '.join(sorted(known))})")
        _check_unknown_keys(value, hints[key], where)


def _one_line(error: msgspec.ValidationError) -> str:
    text = str(error)
    message, _, location = text.partition(" - at `$")
    location = location.rstrip("`").lstrip(".")
    if not location:
        if message.startswith("Object missing required field"):
            return (f"{message}: a config needs [scenario], [swarm] and [[targets]]; every "
                    f"other section may be left out (its defaults are used)")
        return message
    if message.startswith(("Expected", "Object missing", "Invalid")):
        return f"{location}: {message}"
    # Value errors from __post_init__ start with the field name inside that section.
    return f"{location}.{message}"


def config_from_dict(data: dict[str, object], source: str = "<memory>", *,
                     autopilot: str | None = None) -> ScenarioConfig:
    """Validate a parsed TOML document; raises ConfigError with a one-line message.

    ``autopilot`` ("ardupilot"/"px4"): the drones fly real autopilots of that flavour (SITL,
    ``mavlink_urls``), so the tracking keys the document leaves out take that firmware's
    fitted values (``TRACKING_DEFAULTS``) rather than those of ``vehicles.response``."""
    _check_unknown_keys(data, ScenarioConfig, "")
    _fill_tracking_defaults(data, autopilot)
    try:
        config = msgspec.convert(data, ScenarioConfig)
    except msgspec.ValidationError as err:
        raise ConfigError(_one_line(err)) from None
    except ConfigError:
        raise
    except ValueError as err:  # raised outside a section, e.g. from _cross_check
        raise ConfigError(str(err)) from None
    return dataclasses.replace(config, source=source)


def _fill_tracking_defaults(data: dict[str, object], autopilot: str | None) -> None:
    """Put the fitted ``TRACKING_DEFAULTS`` into ``data["control"]`` for the tracking keys it
    leaves out (a resolved config has them all, so it stays as written)."""
    control, vehicles = data.get("control", {}), data.get("vehicles", {})
    if not isinstance(control, dict) or not isinstance(vehicles, dict):
        return  # the type error is msgspec's to report
    response = vehicles.get("response", "ideal")
    if autopilot is not None:
        response = AUTOPILOT_RESPONSE.get(autopilot, response)
    defaults = TRACKING_DEFAULTS.get(response) if isinstance(response, str) else None
    if defaults is None:
        return  # an unknown response: VehiclesSection says so
    missing = {k: v for k, v in zip(TRACKING_KEYS, defaults, strict=True) if k not in control}
    if missing:
        data["control"] = {**control, **missing}


def config_to_data(config: ScenarioConfig) -> dict[str, object]:
    """The config as plain JSON-ready data that ``config_from_dict`` turns back into an equal
    config (recordings keep the resolved config this way): every key of every section, the
    defaults and fitted values included; ``source`` is left out."""
    data = msgspec.to_builtins(_every_field(config))
    data.pop("source", None)
    return data


def _every_field(value: object) -> object:
    """``value`` with every dataclass made a dict of all its fields. (msgspec builds a
    dataclass without storing the defaults of the keys a document leaves out, and its
    ``to_builtins`` writes only the stored ones: a default would be missing.)"""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _every_field(getattr(value, f.name))
                for f in dataclasses.fields(value) if f.init}
    if isinstance(value, tuple | list):
        return [_every_field(item) for item in value]
    return value


def config_to_toml(config: ScenarioConfig) -> str:
    """The resolved config as TOML text that ``load_config`` reads back into an equal config
    (``launch-swarm --print-config``): every key of every section, the defaults and the
    fitted values included, written by ``tomlkit``. TOML has no null: a key whose value is
    none (an altitude bound not set) is left out and named in the header, which also says
    which failsafe delay ``vehicles.setpoint_timeout_s = 0`` means."""
    data = config_to_data(config)
    unset = sorted(_unset_keys(data))
    lines = [f"# The resolved config of {config.source}: every value a run of it uses,",
             "# the defaults of the sections and keys it leaves out filled in."]
    if unset:
        lines.append(f"# Not set: {', '.join(unset)}.")
    vehicles = config.vehicles
    if vehicles.setpoint_timeout_s == 0:
        lines.append(f"# vehicles.setpoint_timeout_s = 0: the flavour's default, "
                     f"{DEFAULT_SETPOINT_TIMEOUT_S[vehicles.flavour]:g} s "
                     f"({vehicles.flavour}).")
    return "\n".join(lines) + "\n\n" + tomlkit.dumps(_without_none(data))


def _unset_keys(value: object, path: str = "") -> list[str]:
    """The dotted names of the keys whose value is None."""
    if isinstance(value, dict):
        return [name for key, item in value.items()
                for name in ([f"{path}{key}"] if item is None
                             else _unset_keys(item, f"{path}{key}."))]
    return []


@overload
def _without_none(value: dict[str, object]) -> dict[str, object]: ...
@overload
def _without_none(value: object) -> object: ...
def _without_none(value: object) -> object:
    """``value`` without the None entries of its tables, at every depth (TOML has no null)."""
    if isinstance(value, dict):
        return {key: _without_none(item) for key, item in value.items() if item is not None}
    if isinstance(value, list):
        return [_without_none(item) for item in value]
    return value


def write_resolved_config(config: ScenarioConfig, path: str | Path) -> Path:
    """Write ``config`` as JSON that ``load_config`` reads back into an equal config: how
    ``launch-swarm`` hands every process the config it resolved (e.g. the origin offsets it
    measured on SITL autopilots). Paths in it are absolute already."""
    path = Path(path)
    path.write_bytes(msgspec.json.format(msgspec.json.encode(config_to_data(config))))
    return path


def read_toml_file(path: Path, error: type[Exception], expected: str) -> dict[str, Any]:
    """The TOML document at ``path``; ``error`` with one line naming the path when it cannot
    be read (missing, a directory instead of ``expected``, unreadable, not TOML, not UTF-8)."""
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, expected {expected}") from None
    except PermissionError:
        raise error(f"{path}: permission denied") from None
    except tomllib.TOMLDecodeError as err:
        raise error(f"{path}: not valid TOML: {err}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a UTF-8 text file") from None


def load_config(path: str | Path, *, autopilot: str | None = None,
                overrides: Sequence[Override] = ()) -> ScenarioConfig:
    """Read and validate a scenario TOML file, or a resolved config written by
    ``write_resolved_config`` (``.json``); raises ConfigError, one line. ``autopilot``: see
    ``config_from_dict``; ``overrides``: ``--set`` values applied to the document before it
    is validated (``swarm.scenario.overrides``)."""
    path = Path(path)
    if path.suffix == ".json":
        return _load_resolved(path, autopilot, overrides)
    data = read_toml_file(path, ConfigError, "a .toml file")
    data = _overridden(data, overrides, path)
    _resolve_signing_key_file(data, path.parent)
    _resolve_path(data, "security", "tls_dir", path.parent)
    try:
        config = config_from_dict(data, source=str(path), autopilot=autopilot)
        config.vehicles.signing_key()  # every entry point refuses a bad key file at start-up
        config.security.check(config.swarm.n_drones)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return config


def _overridden(data: dict[str, Any], overrides: Sequence[Override],
                path: Path) -> dict[str, Any]:
    try:
        return apply_overrides(data, overrides)
    except OverrideError as err:
        raise ConfigError(f"{path}: --set {err}") from None


def _load_resolved(path: Path, autopilot: str | None = None,
                   overrides: Sequence[Override] = ()) -> ScenarioConfig:
    try:
        data = msgspec.json.decode(path.read_bytes())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from None
    except msgspec.DecodeError as err:
        raise ConfigError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object (a resolved config)")
    data = _overridden(data, overrides, path)
    try:
        config = config_from_dict(data, source=str(path), autopilot=autopilot)
        config.vehicles.signing_key()
        config.security.check(config.swarm.n_drones)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return config


def _resolve_signing_key_file(data: dict[str, object], base: Path) -> None:
    """Make ``vehicles.signing_key_file`` absolute, relative to the config file's directory:
    every process, whatever its working directory, then reads the same file."""
    vehicles = data.get("vehicles")
    if isinstance(vehicles, dict):
        name = vehicles.get("signing_key_file")
        if isinstance(name, str) and name:
            vehicles["signing_key_file"] = str((base / Path(name).expanduser()).absolute())


def _resolve_path(data: dict[str, object], section: str, key: str, base: Path) -> None:
    """Make ``section.key`` (a path) absolute, relative to the config file's directory."""
    table = data.get(section)
    if isinstance(table, dict):
        name = table.get(key)
        if isinstance(name, str) and name:
            table[key] = str((base / Path(name).expanduser()).absolute())
