"""``EmulatedVehicle.push``: a disturbance (a gust) that moves the vehicle at once, for tests
of what takes such an offset out (the command reference in tests/mavlink/test_link.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_world.vehicle import EmulatedVehicle
from tests.helpers.vehicle_tools import DRONE, ORIGIN, START


def test_a_push_moves_the_vehicle_at_once_and_leaves_its_velocity() -> None:
    vehicle = EmulatedVehicle(DRONE, "px4", START, ORIGIN)
    vehicle.integrate(0.02, [0.5, 0.0, 0.0])
    before_p, before_v = vehicle.position_w, vehicle.velocity_w
    vehicle.push([0.0, 0.4, 0.0])
    np.testing.assert_allclose(vehicle.position_w, before_p + np.array([0.0, 0.4, 0.0]),
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(vehicle.velocity_w, before_v)
    assert before_v[0] == 0.5  # it was moving: the push left that alone


def test_a_push_below_the_ground_stops_on_it_and_a_non_finite_one_is_refused() -> None:
    vehicle = EmulatedVehicle(DRONE, "ardupilot", START, ORIGIN)
    vehicle.push([0.0, 0.0, -100.0])
    assert vehicle.position_w[2] == ORIGIN[2]
    with pytest.raises(ValueError, match=r"^offset_w must be 3 finite numbers \[m\]"):
        vehicle.push([0.0, math.nan, 0.0])
    assert vehicle.position_w[2] == ORIGIN[2]
