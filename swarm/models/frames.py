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

All functions take array-likes of shape (3,) and return new float64 arrays of shape (3,);
they are pure and deterministic (no global state, no in-place updates of their inputs).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = [
    "enu_to_ned",
    "local_ned_from_world",
    "ned_to_enu",
    "position_over_link",
    "to_link_float",
    "velocity_over_link",
    "world_from_local_ned",
]


def _vec3(v: ArrayLike, name: str) -> Array:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name} must be a 3-vector, got shape {a.shape}")
    return a


def enu_to_ned(v: ArrayLike) -> Array:
    """W (x, y, z-up) → NED: (north, east, down) = (y, x, -z). Exact (no rounding)."""
    a = _vec3(v, "v")
    return np.array([a[1], a[0], -a[2]], dtype=np.float64)


def ned_to_enu(v: ArrayLike) -> Array:
    """NED (north, east, down) → W: (x, y, z) = (east, north, -down). Exact (no rounding)."""
    a = _vec3(v, "v")
    return np.array([a[1], a[0], -a[2]], dtype=np.float64)


def to_link_float(v: ArrayLike) -> Array:
    """Round each component to float32 and back: what a MAVLink ``float`` field carries.

    Values beyond the float32 range become ±inf (pymavlink itself would raise OverflowError
    when packing them; senders should pass the result of this function instead). NaN stays
    NaN.
    """
    a = _vec3(v, "v")
    with np.errstate(over="ignore"):
        return a.astype(np.float32).astype(np.float64)


def local_ned_from_world(position_w: ArrayLike, origin_w: ArrayLike) -> Array:
    """The vehicle's local NED coordinates of W-position ``position_w`` (float64, exact)."""
    return enu_to_ned(_vec3(position_w, "position_w") - _vec3(origin_w, "origin_w"))


def world_from_local_ned(ned: ArrayLike, origin_w: ArrayLike) -> Array:
    """W-position of local NED coordinates ``ned`` of a vehicle whose origin is ``origin_w``."""
    return _vec3(origin_w, "origin_w") + ned_to_enu(ned)


def position_over_link(position_w: ArrayLike, origin_w: ArrayLike) -> Array:
    """W-position an agent reconstructs from a LOCAL_POSITION_NED report (float32 x, y, z).

    ``origin_w + ned_to_enu(to_link_float(enu_to_ned(position_w - origin_w)))``.
    """
    return world_from_local_ned(
        to_link_float(local_ned_from_world(position_w, origin_w)), origin_w)


def velocity_over_link(velocity_w: ArrayLike) -> Array:
    """W-velocity a vehicle decodes from a velocity setpoint (float32 vx, vy, vz in NED).

    ``ned_to_enu(to_link_float(enu_to_ned(velocity_w)))``; the same rounding applies to the
    vx, vy, vz of LOCAL_POSITION_NED.
    """
    return ned_to_enu(to_link_float(enu_to_ned(velocity_w)))
