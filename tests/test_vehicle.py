"""Kinematic bicycle: straight lines, circles, limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from e2e_lite.simulation.vehicle import STEER, V, VehicleParams, X, Y, bicycle_step, make_state

CAR = VehicleParams()


def test_straight_line_at_constant_speed():
    st = make_state(1.0, 2.0, math.radians(30), speed=20.0)
    for _ in range(500):
        bicycle_step(st, np.zeros(1), np.zeros(1), CAR, 0.02)
    dist = 20.0 * 10.0
    assert st[0, X] == pytest.approx(1.0 + dist * math.cos(math.radians(30)), abs=1e-9)
    assert st[0, Y] == pytest.approx(2.0 + dist * math.sin(math.radians(30)), abs=1e-9)
    assert st[0, V] == 20.0


@pytest.mark.parametrize("delta", [0.05, -0.2, 0.4])
def test_constant_steering_drives_a_circle_of_radius_l_over_tan_delta(delta):
    st = make_state(0.0, 0.0, 0.0, speed=12.0, steer=delta)
    radius = CAR.wheelbase_m / math.tan(delta)  # signed: centre at (0, radius)
    for _ in range(3000):
        bicycle_step(st, np.array([delta]), np.zeros(1), CAR, 0.02)
        assert math.hypot(st[0, X], st[0, Y] - radius) == pytest.approx(abs(radius), rel=1e-9)


def test_limits_are_respected():
    st = make_state(0.0, 0.0, 0.0, speed=39.0)
    prev = st.copy()
    for _ in range(100):
        bicycle_step(st, np.array([5.0]), np.array([100.0]), CAR, 0.02)
        assert abs(st[0, STEER] - prev[0, STEER]) <= CAR.max_steer_rate_radps * 0.02 + 1e-12
        assert st[0, V] - prev[0, V] <= CAR.max_accel_mps2 * 0.02 + 1e-12
        prev = st.copy()
    assert st[0, STEER] == pytest.approx(CAR.max_steer_rad)
    assert st[0, V] == pytest.approx(CAR.max_speed_mps)
    for _ in range(1000):  # hard braking never reverses
        bicycle_step(st, np.zeros(1), np.array([-100.0]), CAR, 0.02)
        assert st[0, V] >= 0.0
    assert st[0, V] == 0.0


def test_braking_is_bounded():
    st = make_state(0.0, 0.0, 0.0, speed=30.0)
    bicycle_step(st, np.zeros(1), np.array([-100.0]), CAR, 0.1)
    assert st[0, V] == pytest.approx(30.0 - CAR.max_brake_mps2 * 0.1)


def test_batch_rows_are_independent():
    st = np.vstack([make_state(0, 0, 0, 10.0), make_state(5, 5, 1.0, 20.0)])
    one = make_state(5, 5, 1.0, 20.0)
    for _ in range(50):
        bicycle_step(st, np.array([0.0, 0.1]), np.array([1.0, -1.0]), CAR, 0.02)
        bicycle_step(one, np.array([0.1]), np.array([-1.0]), CAR, 0.02)
    assert np.array_equal(st[1], one[0])
