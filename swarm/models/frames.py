"""Frame conversions between the world frame W (ENU-like) and MAVLink local NED (SPEC §1, §12).

This is the ONE module of the project that converts frames; nothing else may swap axes or
flip signs. W has x, y horizontal and z up; MAVLink's local frame is north-east-down with

    (north, east, down) = (y, x, -z) of W.

Each vehicle has its own local NED origin; ``origin_w`` is that origin expressed in W (the
per-drone origin offset from the configuration).

MAVLink carries positions and velocities as IEEE-754 float32. ``to_link_float`` reproduces
exactly what a float32 field does to a float64 value (round to nearest, ties to even, the
same rounding CPython's ``struct.pack('<f')`` inside pymavlink applies), so that the
in-process reference simulator can reproduce a multi-process run bit for bit:

* ``position_over_link(p, o)`` is what an agent reconstructs from a LOCAL_POSITION_NED report
  of a vehicle at W-position ``p`` with local origin ``o``;
* ``velocity_over_link(u)`` is what a vehicle decodes from a SET_POSITION_TARGET_LOCAL_NED
  velocity setpoint of W-velocity ``u``.

Each conversion is written once, on three floats (``*_xyz``, tuples in and out: what the
MAVLink paths call, once or more per vehicle and step, where a numpy call costs more than the
arithmetic); the array functions take array-likes of shape (3,), check them and return new
float64 arrays of shape (3,) from those. All are pure and deterministic (no global state, no
in-place updates of their inputs), and both forms give the same floats bit for bit.

``GeoPoint`` places W on the Earth: a WGS84 point, and ``moved`` the point a few metres east,
north and up of it on the local tangent plane (the homes of SITL vehicles, the geodetic
positions a ground station is told).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
Xyz = tuple[float, float, float]

__all__ = [
    "MEAN_EARTH_RADIUS_M",
    "GeoPoint",
    "Xyz",
    "as_xyz",
    "enu_to_ned",
    "enu_to_ned_xyz",
    "link_float_xyz",
    "local_ned_from_world",
    "local_ned_from_world_xyz",
    "ned_to_enu",
    "ned_to_enu_xyz",
    "position_over_link",
    "to_link_float",
    "velocity_over_link",
    "world_from_local_ned",
    "world_from_local_ned_xyz",
]

MEAN_EARTH_RADIUS_M = 6_371_008.8  # IUGG mean radius; offsets of metres, errors of micrometres
_FLOAT32 = struct.Struct("<f")
_FLOAT32_XYZ = struct.Struct("<3f")


def _vec3(v: ArrayLike, name: str) -> Array:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {a.shape}")
    return a


def as_xyz(v: ArrayLike, name: str = "v") -> Xyz:
    """``v`` as three Python floats: a tuple of three floats as it is, anything else checked
    as the array functions check it (ValueError unless it is a 3-vector)."""
    if isinstance(v, tuple) and type(v) is tuple and len(v) == 3 \
            and all(type(c) is float for c in v):
        return v
    x, y, z = _vec3(v, name).tolist()
    return x, y, z


def enu_to_ned_xyz(x: float, y: float, z: float) -> Xyz:
    """W (x, y, z-up) → NED: (north, east, down) = (y, x, -z). Exact (no rounding)."""
    return y, x, -z


def ned_to_enu_xyz(north: float, east: float, down: float) -> Xyz:
    """NED (north, east, down) → W: (x, y, z) = (east, north, -down). Exact (no rounding)."""
    return east, north, -down


def _link_float(value: float) -> float:
    try:
        rounded: float = _FLOAT32.unpack(_FLOAT32.pack(value))[0]
        return rounded
    except OverflowError:  # rounds beyond the float32 range: what the C cast gives, ±inf
        return math.copysign(math.inf, value)


def link_float_xyz(a: float, b: float, c: float) -> Xyz:
    """Each value rounded to float32 and back: what a MAVLink ``float`` field carries (round
    to nearest, ties to even). Values beyond the float32 range become ±inf (``struct``, which
    pymavlink packs with, would raise OverflowError); NaN stays NaN."""
    try:
        return _FLOAT32_XYZ.unpack(_FLOAT32_XYZ.pack(a, b, c))
    except OverflowError:
        return _link_float(a), _link_float(b), _link_float(c)


def local_ned_from_world_xyz(position_w: Xyz, origin_w: Xyz) -> Xyz:
    """The vehicle's local NED coordinates of W-position ``position_w`` (exact differences)."""
    return enu_to_ned_xyz(position_w[0] - origin_w[0], position_w[1] - origin_w[1],
                          position_w[2] - origin_w[2])


def world_from_local_ned_xyz(ned: Xyz, origin_w: Xyz) -> Xyz:
    """W-position of local NED coordinates ``ned`` of a vehicle whose origin is ``origin_w``."""
    x, y, z = ned_to_enu_xyz(ned[0], ned[1], ned[2])
    return origin_w[0] + x, origin_w[1] + y, origin_w[2] + z


def enu_to_ned(v: ArrayLike) -> Array:
    """``enu_to_ned_xyz`` of a 3-vector."""
    return np.array(enu_to_ned_xyz(*as_xyz(v)))


def ned_to_enu(v: ArrayLike) -> Array:
    """``ned_to_enu_xyz`` of a 3-vector."""
    return np.array(ned_to_enu_xyz(*as_xyz(v)))


def to_link_float(v: ArrayLike) -> Array:
    """``link_float_xyz`` of a 3-vector: what MAVLink ``float`` fields carry of it (senders
    pass the result, whose values beyond float32 are already ±inf)."""
    return np.array(link_float_xyz(*as_xyz(v)))


def local_ned_from_world(position_w: ArrayLike, origin_w: ArrayLike) -> Array:
    """``local_ned_from_world_xyz`` of two 3-vectors."""
    return np.array(local_ned_from_world_xyz(as_xyz(position_w, "position_w"),
                                             as_xyz(origin_w, "origin_w")))


def world_from_local_ned(ned: ArrayLike, origin_w: ArrayLike) -> Array:
    """``world_from_local_ned_xyz`` of two 3-vectors."""
    return np.array(world_from_local_ned_xyz(as_xyz(ned, "ned"), as_xyz(origin_w, "origin_w")))


def position_over_link(position_w: ArrayLike, origin_w: ArrayLike) -> Array:
    """W-position an agent reconstructs from a LOCAL_POSITION_NED report (float32 x, y, z).

    ``origin_w + ned_to_enu(to_link_float(enu_to_ned(position_w - origin_w)))``.
    """
    origin = as_xyz(origin_w, "origin_w")
    local = link_float_xyz(*local_ned_from_world_xyz(as_xyz(position_w, "position_w"), origin))
    return np.array(world_from_local_ned_xyz(local, origin))


def velocity_over_link(velocity_w: ArrayLike) -> Array:
    """W-velocity a vehicle decodes from a velocity setpoint (float32 vx, vy, vz in NED).

    ``ned_to_enu(to_link_float(enu_to_ned(velocity_w)))``; the same rounding applies to the
    vx, vy, vz of LOCAL_POSITION_NED.
    """
    return np.array(ned_to_enu_xyz(*link_float_xyz(*enu_to_ned_xyz(*as_xyz(velocity_w)))))


@dataclass(frozen=True)
class GeoPoint:
    """A WGS84 position: latitude and longitude [deg], altitude above mean sea level [m]."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def moved(self, east_m: float, north_m: float, up_m: float = 0.0) -> GeoPoint:
        """The point ``east_m``, ``north_m``, ``up_m`` away (local tangent plane; for the few
        metres between drones the error is micrometres)."""
        lat = self.lat_deg + math.degrees(north_m / MEAN_EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(
            east_m / (MEAN_EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg))))
        return GeoPoint(lat, lon, self.alt_m + up_m)
