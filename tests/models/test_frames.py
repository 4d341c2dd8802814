"""swarm.models.frames: W (ENU-like) ↔ MAVLink local NED, and what float32 link fields do."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from swarm.models import frames

F32_EPS = float(np.finfo(np.float32).eps)  # 2^-23; rounding error ≤ eps/2 relative
F32_TINY = float(np.finfo(np.float32).smallest_subnormal)

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
world = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False)
vec = arrays(np.float64, 3, elements=finite)
world_vec = arrays(np.float64, 3, elements=world)
speed_vec = arrays(np.float64, 3, elements=st.floats(-50, 50, allow_nan=False))


def bits(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).view(np.uint64)


# ---------------------------------------------------------------- axis mapping
@pytest.mark.parametrize(("enu", "ned"), [
    ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),   # +x of W is east
    ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),   # +y of W is north
    ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]),  # +z of W (up) is -down
    ([2.0, -3.0, 5.0], [-3.0, 2.0, -5.0]),
])
def test_axis_mapping(enu: list[float], ned: list[float]) -> None:
    np.testing.assert_array_equal(frames.enu_to_ned(enu), ned)
    np.testing.assert_array_equal(frames.ned_to_enu(ned), enu)


def test_local_ned_uses_the_vehicle_origin() -> None:
    origin = np.array([10.0, -5.0, 1.0])
    p = np.array([12.0, -1.0, 4.0])  # 2 m east, 4 m north, 3 m above the origin
    np.testing.assert_array_equal(frames.local_ned_from_world(p, origin), [4.0, 2.0, -3.0])
    np.testing.assert_array_equal(frames.world_from_local_ned([4.0, 2.0, -3.0], origin), p)


def test_outputs_are_new_float64_arrays_and_inputs_untouched() -> None:
    v = np.array([1, 2, 3], dtype=np.int64)
    for fn in (frames.enu_to_ned, frames.ned_to_enu, frames.to_link_float,
               frames.velocity_over_link):
        out = fn(v)
        assert out.dtype == np.float64 and out.shape == (3,)
        assert out is not v
    np.testing.assert_array_equal(v, [1, 2, 3])


@pytest.mark.parametrize("bad", [[1.0, 2.0], [[1.0, 2.0, 3.0]], 1.0, [1, 2, 3, 4]])
def test_rejects_non_3_vectors(bad: object) -> None:
    with pytest.raises(ValueError, match="3-vector"):
        frames.enu_to_ned(bad)  # type: ignore[arg-type]


# ---------------------------------------------------------------- the float forms
any_float = st.floats(width=64)  # NaN and ±inf included
xyz = st.tuples(any_float, any_float, any_float)


def same_bits(a: object, b: object) -> bool:
    """Equal float64 bits, NaN where the other is NaN (any payload)."""
    x, y = np.array(a, dtype=np.float64), np.array(b, dtype=np.float64)
    nan = np.isnan(x)
    return bool(np.array_equal(nan, np.isnan(y))
                and np.array_equal(bits(x[~nan]), bits(y[~nan])))


@given(xyz, xyz)
def test_float_forms_are_the_array_forms_bit_for_bit(v: tuple, o: tuple) -> None:
    """What the MAVLink paths call (three floats) is what the array API returns."""
    assert same_bits(frames.enu_to_ned_xyz(*v), frames.enu_to_ned(np.array(v)))
    assert same_bits(frames.ned_to_enu_xyz(*v), frames.ned_to_enu(list(v)))
    assert same_bits(frames.link_float_xyz(*v), frames.to_link_float(np.array(v)))
    assert same_bits(frames.local_ned_from_world_xyz(v, o),
                     frames.local_ned_from_world(np.array(v), np.array(o)))
    assert same_bits(frames.world_from_local_ned_xyz(v, o),
                     frames.world_from_local_ned(np.array(v), np.array(o)))
    for out in (frames.link_float_xyz(*v), frames.world_from_local_ned_xyz(v, o)):
        assert type(out) is tuple and all(type(c) is float for c in out)


@given(st.lists(finite, min_size=3, max_size=3))
def test_link_float_xyz_is_numpys_float32_cast(v: list[float]) -> None:
    """Rounding as numpy's float64 → float32 cast does (±inf beyond the range), which the
    array form used before it was written on floats."""
    with np.errstate(over="ignore"):
        cast = np.array(v).astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(bits(np.array(frames.link_float_xyz(*v))), bits(cast))


def test_as_xyz_keeps_float_tuples_and_checks_the_rest() -> None:
    t = (1.0, -0.0, 3.5)
    assert frames.as_xyz(t) is t
    assert frames.as_xyz(np.array([1, 2, 3])) == (1.0, 2.0, 3.0)
    assert frames.as_xyz((1, 2, 3)) == (1.0, 2.0, 3.0)
    assert all(type(c) is float for c in frames.as_xyz((np.float32(1.5), 2, 3.0)))
    for bad in ((1.0, 2.0), [[1.0, 2.0, 3.0]], 1.0, (1.0, 2.0, 3.0, 4.0)):
        with pytest.raises(ValueError, match="position_w must be a 3-vector"):
            frames.as_xyz(bad, "position_w")  # type: ignore[arg-type]


# ---------------------------------------------------------------- exact round trips
@given(vec)
def test_enu_ned_round_trip_is_bit_exact(v: np.ndarray) -> None:
    np.testing.assert_array_equal(bits(frames.ned_to_enu(frames.enu_to_ned(v))), bits(v))
    np.testing.assert_array_equal(bits(frames.enu_to_ned(frames.ned_to_enu(v))), bits(v))


@given(world_vec, world_vec)
def test_world_local_round_trip(p: np.ndarray, origin: np.ndarray) -> None:
    back = frames.world_from_local_ned(frames.local_ned_from_world(p, origin), origin)
    # (p - o) + o: at most one rounding of each float64 operation
    scale = np.maximum(np.abs(p), np.abs(origin))
    assert np.all(np.abs(back - p) <= 2 * np.finfo(np.float64).eps * scale)


# ---------------------------------------------------------------- float32 link fields
@given(finite)
def test_to_link_float_is_what_struct_float32_carries(x: float) -> None:
    try:
        carried = struct.unpack("<f", struct.pack("<f", x))[0]
    except OverflowError:  # CPython refuses to pack a finite value beyond float32 range
        assert np.isinf(frames.to_link_float([x, 0.0, 0.0])[0])
        return
    got = frames.to_link_float([x, 0.0, 0.0])[0]
    assert bits(np.array([got]))[0] == bits(np.array([carried]))[0]


@given(vec)
def test_to_link_float_rounding_bound_and_idempotence(v: np.ndarray) -> None:
    once = frames.to_link_float(v)
    np.testing.assert_array_equal(bits(frames.to_link_float(once)), bits(once))
    small = np.abs(v) < 3e38
    err = np.abs(once - v)[small]
    assert np.all(err <= 0.5 * F32_EPS * np.abs(v[small]) + F32_TINY)


def test_to_link_float_specials() -> None:
    out = frames.to_link_float([np.nan, np.inf, -1e300])
    assert np.isnan(out[0]) and out[1] == np.inf and out[2] == -np.inf


@given(world_vec, world_vec)
def test_position_over_link_error_is_float32_of_the_local_offset(p: np.ndarray,
                                                                o: np.ndarray) -> None:
    got = frames.position_over_link(p, o)
    local = np.abs(p - o)
    assert np.all(np.abs(got - p) <= 0.5 * F32_EPS * local + F32_TINY
                  + 2 * np.finfo(np.float64).eps * np.maximum(np.abs(p), np.abs(o)))
    # definition, bit for bit
    expected = o + frames.ned_to_enu(frames.to_link_float(frames.enu_to_ned(p - o)))
    np.testing.assert_array_equal(bits(got), bits(expected))


@given(speed_vec)
def test_velocity_over_link_round_trip(u: np.ndarray) -> None:
    got = frames.velocity_over_link(u)
    assert np.all(np.abs(got - u) <= 0.5 * F32_EPS * np.abs(u) + F32_TINY)
    np.testing.assert_array_equal(bits(frames.velocity_over_link(got)), bits(got))


def test_deterministic() -> None:
    rng = np.random.default_rng(7)
    p, o, u = rng.normal(size=(3, 3)) * 100
    a = [frames.position_over_link(p, o), frames.velocity_over_link(u)]
    b = [frames.position_over_link(p.copy(), o.copy()), frames.velocity_over_link(u.copy())]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(bits(x), bits(y))


# ---------------------------------------------------------------- against real pymavlink
class _Sink:
    def __init__(self) -> None:
        self.packets: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.packets.append(bytes(buf))


def _round_trip(msg: object) -> object:
    sink = _Sink()
    tx = mavlink2.MAVLink(sink, srcSystem=1, srcComponent=1)
    tx.send(msg)
    rx = mavlink2.MAVLink(None)
    (decoded,) = rx.parse_buffer(sink.packets[0])
    return decoded


@settings(max_examples=200)
@given(world_vec, world_vec, speed_vec)
def test_local_position_ned_through_pymavlink_matches_position_over_link(
        p: np.ndarray, o: np.ndarray, u: np.ndarray) -> None:
    x, y, z = frames.local_ned_from_world(p, o)
    vx, vy, vz = frames.enu_to_ned(u)
    tx = mavlink2.MAVLink(None)
    msg = _round_trip(tx.local_position_ned_encode(20, x, y, z, vx, vy, vz))
    pos = frames.world_from_local_ned([msg.x, msg.y, msg.z], o)  # type: ignore[attr-defined]
    vel = frames.ned_to_enu([msg.vx, msg.vy, msg.vz])  # type: ignore[attr-defined]
    np.testing.assert_array_equal(bits(pos), bits(frames.position_over_link(p, o)))
    np.testing.assert_array_equal(bits(vel), bits(frames.velocity_over_link(u)))


@settings(max_examples=200)
@given(speed_vec)
def test_velocity_setpoint_through_pymavlink_matches_velocity_over_link(u: np.ndarray) -> None:
    vn, ve, vd = frames.to_link_float(frames.enu_to_ned(u))
    tx = mavlink2.MAVLink(None)
    msg = _round_trip(tx.set_position_target_local_ned_encode(
        0, 1, 1, mavlink2.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0))
    decoded = frames.ned_to_enu([msg.vx, msg.vy, msg.vz])  # type: ignore[attr-defined]
    np.testing.assert_array_equal(bits(decoded), bits(frames.velocity_over_link(u)))


@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-60, 60))
def test_homes_are_the_offsets_away_on_the_earth(east: float, north: float, lat: float
                                                 ) -> None:
    origin = frames.GeoPoint(lat, 149.0, 584.0)
    moved = origin.moved(east, north, 2.0)
    # back to metres on the sphere (equirectangular at the mid latitude)
    radius = 6_371_008.8
    north_back = math.radians(moved.lat_deg - origin.lat_deg) * radius
    east_back = (math.radians(moved.lon_deg - origin.lon_deg) * radius
                 * math.cos(math.radians(origin.lat_deg)))
    assert north_back == pytest.approx(north, abs=1e-6)
    assert east_back == pytest.approx(east, abs=1e-6)
    assert moved.alt_m == origin.alt_m + 2.0
