"""The safety envelope as control barrier rows of the local QP.

A drone is a single integrator, ṗ_i = u_i, so each barrier h(p_i) ≥ 0 of the envelope gives
one first-order CBF row ∇h(p_i)ᵀ u_i ≥ −α h(p_i): if every step's u meets it, h stays
non-negative (up to the discretization of one step). The rows are *hard*: no slack of the
localization barrier enters them, so when they conflict with it, the QP relaxes localization,
never the envelope. All positions are in the world frame (x east, y north, z up) [m].

* altitude floor z_f:   h = z − z_f,                    ∇h = (0, 0, 1),   gain α_alt;
* altitude ceiling z_c: h = z_c − z,                    ∇h = (0, 0, −1),  gain α_alt;
* keep-in polygon, convex, vertices v_k counter-clockwise, one row per edge k:
  h_k = n_kᵀ(p_xy − v_k) with n_k the inward unit normal of edge v_k → v_k+1
  (the signed distance to the edge's line, positive inside),  ∇h_k = (n_k, 0),  gain α_fence;
* keep-out cylinder (a vertical obstacle of centre c and radius r):
  h = ‖p_xy − c‖² − r²,   ∇h = (2(p_xy − c), 0),  gain α_obs.

``safety_rows`` gives the rows (a, lower) with a·u ≥ lower; ``envelope_margins`` the distances
[m] to each boundary (negative: outside), which the run checks hold ≥ −tolerance;
``safety_conflict`` says whether a solved QP bought localization slack while an envelope row
held u back (the conflict the drone counts: safety won).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

from swarm.core.params import require, require_finite, require_finite_positive

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class KeepOutCylinder:
    """A static obstacle: no drone's centre inside this vertical cylinder."""

    center_m: Vec2
    radius_m: float

    def __post_init__(self) -> None:
        for value in self.center_m:
            require_finite("keep_out.center_m", value)
        require_finite_positive("keep_out.radius_m", self.radius_m)


@dataclass(frozen=True)
class SafetyParams:
    """The envelope: an altitude band, a convex keep-in polygon, keep-out cylinders, and the
    gain of each kind of barrier [1/s]. Every part is optional; the polygon's vertices may be
    listed either way round (they are kept counter-clockwise)."""

    floor_m: float | None = None
    ceiling_m: float | None = None
    keep_in: tuple[Vec2, ...] = ()
    keep_out: tuple[KeepOutCylinder, ...] = ()
    altitude_gain: float = 1.0
    fence_gain: float = 1.0
    obstacle_gain: float = 1.0

    def __post_init__(self) -> None:
        for name in ("floor_m", "ceiling_m"):
            value = getattr(self, name)
            if value is not None:
                require_finite(name, value)
        if self.floor_m is not None and self.ceiling_m is not None:
            require(self.floor_m < self.ceiling_m, "floor_m",
                    f"must be below ceiling_m = {self.ceiling_m}", self.floor_m)
        for name in ("altitude_gain", "fence_gain", "obstacle_gain"):
            require_finite_positive(name, getattr(self, name))
        if self.keep_in:
            object.__setattr__(self, "keep_in", convex_counter_clockwise(self.keep_in))

    @property
    def empty(self) -> bool:
        return (self.floor_m is None and self.ceiling_m is None and not self.keep_in
                and not self.keep_out)

    @cached_property
    def fence_edges(self) -> tuple[tuple[Vec2, Vec2], ...]:
        """(inward unit normal n_k, vertex v_k) of each keep-in edge, worked out once (every
        step's rows and every margin use them)."""
        return tuple(fence_edges(self.keep_in))

    @property
    def n_rows(self) -> int:
        """Rows this envelope adds to every QP: one per barrier."""
        return ((self.floor_m is not None) + (self.ceiling_m is not None) + len(self.keep_in)
                + len(self.keep_out))


def convex_counter_clockwise(vertices: tuple[Vec2, ...]) -> tuple[Vec2, ...]:
    """The vertices of a strictly convex polygon, counter-clockwise; ValueError with one line
    when they are not one (fewer than 3, a repeated or non-finite vertex, collinear edges,
    a reflex or self-crossing turn)."""
    points = tuple((float(x), float(y)) for x, y in vertices)
    n = len(points)
    require(n >= 3, "keep_in", "needs at least 3 vertices [x, y]", n)
    for x, y in points:
        require(math.isfinite(x) and math.isfinite(y), "keep_in",
                "vertices must be finite", (x, y))
    turns = [_cross(points[k], points[(k + 1) % n], points[(k + 2) % n]) for k in range(n)]
    area2 = sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(points, points[1:] + points[:1],
                                                                  strict=True))
    require(all(t > 0 for t in turns) or all(t < 0 for t in turns), "keep_in",
            "must be a convex polygon (every turn the same way, no three vertices on a line)",
            list(points))
    winding = sum(_angle(points[k], points[(k + 1) % n], points[(k + 2) % n])
                  for k in range(n))
    require(abs(abs(winding) - 2 * math.pi) < 1e-6, "keep_in",
            "must not cross itself (its edges wind more than once)", list(points))
    return points if area2 > 0 else tuple(reversed(points))


def _cross(a: Vec2, b: Vec2, c: Vec2) -> float:
    """z of (b − a) × (c − b): > 0 for a left (counter-clockwise) turn at b."""
    return (b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])


def _angle(a: Vec2, b: Vec2, c: Vec2) -> float:
    """The signed turn at b from direction a → b to direction b → c [rad]."""
    return math.atan2(_cross(a, b, c),
                      (b[0] - a[0]) * (c[0] - b[0]) + (b[1] - a[1]) * (c[1] - b[1]))


def fence_edges(keep_in: tuple[Vec2, ...]) -> list[tuple[Vec2, Vec2]]:
    """(inward unit normal n_k, vertex v_k) of each edge of a counter-clockwise polygon."""
    edges = []
    for k, (x0, y0) in enumerate(keep_in):
        x1, y1 = keep_in[(k + 1) % len(keep_in)]
        length = math.hypot(x1 - x0, y1 - y0)
        edges.append(((-(y1 - y0) / length, (x1 - x0) / length), (x0, y0)))
    return edges


def safety_rows(position: Sequence[float], params: SafetyParams
                ) -> tuple[list[Vec3], list[float]]:
    """The envelope's CBF rows at p_i: (a, lower) with a·u_i ≥ lower, in the order floor,
    ceiling, keep-in edges, keep-out cylinders (module docstring)."""
    px, py, pz = position
    rows: list[Vec3] = []
    lower: list[float] = []
    if params.floor_m is not None:
        rows.append((0.0, 0.0, 1.0))
        lower.append(-params.altitude_gain * (pz - params.floor_m))
    if params.ceiling_m is not None:
        rows.append((0.0, 0.0, -1.0))
        lower.append(-params.altitude_gain * (params.ceiling_m - pz))
    for (nx, ny), (vx, vy) in params.fence_edges:
        rows.append((nx, ny, 0.0))
        lower.append(-params.fence_gain * (nx * (px - vx) + ny * (py - vy)))
    for obstacle in params.keep_out:
        cx, cy = obstacle.center_m
        ox, oy = px - cx, py - cy
        rows.append((2.0 * ox, 2.0 * oy, 0.0))
        lower.append(-params.obstacle_gain * (ox * ox + oy * oy - obstacle.radius_m ** 2))
    return rows, lower


def envelope_margins(position: Vec3, params: SafetyParams) -> dict[str, float]:
    """Distance [m] from p_i to each kind of boundary, negative outside: ``floor``,
    ``ceiling``, ``fence`` (to the nearest keep-in edge's line), ``obstacle`` (to the nearest
    keep-out cylinder's surface); only the kinds the envelope has."""
    px, py, pz = position
    margins: dict[str, float] = {}
    if params.floor_m is not None:
        margins["floor"] = pz - params.floor_m
    if params.ceiling_m is not None:
        margins["ceiling"] = params.ceiling_m - pz
    if params.keep_in:
        margins["fence"] = min(nx * (px - vx) + ny * (py - vy)
                               for (nx, ny), (vx, vy) in params.fence_edges)
    if params.keep_out:
        margins["obstacle"] = min(math.hypot(px - o.center_m[0], py - o.center_m[1])
                                  - o.radius_m for o in params.keep_out)
    return margins


# A row is active at u when a·u − lower ≤ this (DAQP ends on the active set and solves its
# equations: an active row's residual is round-off, ~1e-15 relative); a slack counts as used
# above ``SLACK_USED`` (its bound, 0, is then not active).
ACTIVE_ROW_TOLERANCE = 1e-9
SLACK_USED = 1e-9


def safety_conflict(u_columns: list[float], lower: list[float], n_safety: int,
                    velocity: list[float], slacks: list[float], *, skip_last: int = 0) -> bool:
    """Whether the QP solution (u, slacks) used some localization or weight slack while one
    of the ``n_safety`` rows before the last ``skip_last`` (the envelope's, in the
    column-major layout of the QP's rows; the keep rows of ``swarm.core.network`` follow
    them) was active: the drone gave up some localization because those rows stopped it."""
    if not any(slack > SLACK_USED for slack in slacks):
        return False
    n_rows = len(lower)
    u0, u1, u2 = velocity
    for r in range(n_rows - skip_last - n_safety, n_rows - skip_last):
        residual = (u_columns[r] * u0 + u_columns[n_rows + r] * u1
                    + u_columns[2 * n_rows + r] * u2 - lower[r])
        if residual <= ACTIVE_ROW_TOLERANCE * max(1.0, abs(lower[r])):
            return True
    return False
