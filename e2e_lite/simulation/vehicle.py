"""The kinematic bicycle, vectorised over a batch of cars.

State per car (columns of a ``(B, 5)`` float64 array, indices below)::

    X, Y     rear-axle position [m]
    H        heading [rad]
    V        speed [m/s], >= 0
    STEER    road-wheel angle [rad]

Model (reference point: rear axle, wheelbase L)::

    dx/dt = v cos h,   dy/dt = v sin h,   dh/dt = v tan(steer) / L

Actuation is physical: a commanded road-wheel angle [rad] (reached at a bounded steering rate)
and a longitudinal acceleration [m/s^2] (bounded by ``max_accel`` and ``max_brake``). Any
normalised actuator form lives at the learning layer, not here.

Integration is exact for one step at constant curvature: the car moves along the chord of the arc
it would drive. So a constant steering angle drives a circle of radius ``L / tan(steer)``
whatever the time step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import check_range

X, Y, H, V, STEER = range(5)
STATE_SIZE = 5


@dataclass(frozen=True)
class VehicleParams:
    """Dimensions and limits of a car.

    Attributes:
        wheelbase_m: distance between the axles [m].
        length_m, width_m: body size [m].
        rear_overhang_m: rear bumper to rear axle [m].
        max_steer_rad: largest road-wheel angle [rad].
        max_steer_rate_radps: fastest change of road-wheel angle [rad/s].
        max_accel_mps2: strongest acceleration [m/s^2].
        max_brake_mps2: strongest braking, a positive number [m/s^2].
        max_speed_mps: top speed [m/s].
    """

    wheelbase_m: float = 2.7
    length_m: float = 4.5
    width_m: float = 1.8
    rear_overhang_m: float = 0.9
    max_steer_rad: float = 0.6
    max_steer_rate_radps: float = 0.8
    max_accel_mps2: float = 3.0
    max_brake_mps2: float = 8.0
    max_speed_mps: float = 40.0

    def __post_init__(self) -> None:
        o = "VehicleParams"
        check_range(o, "wheelbase_m", self.wheelbase_m, 0.0, 10.0, lo_open=True)
        check_range(o, "length_m", self.length_m, self.wheelbase_m, 20.0)
        check_range(o, "width_m", self.width_m, 0.0, 5.0, lo_open=True)
        check_range(
            o, "rear_overhang_m", self.rear_overhang_m, 0.0, self.length_m - self.wheelbase_m
        )
        check_range(o, "max_steer_rad", self.max_steer_rad, 0.0, 1.2, lo_open=True)
        check_range(o, "max_steer_rate_radps", self.max_steer_rate_radps, 0.0, 20.0, lo_open=True)
        check_range(o, "max_accel_mps2", self.max_accel_mps2, 0.0, 20.0, lo_open=True)
        check_range(o, "max_brake_mps2", self.max_brake_mps2, 0.0, 20.0, lo_open=True)
        check_range(o, "max_speed_mps", self.max_speed_mps, 0.0, 100.0, lo_open=True)

    @property
    def rear_to_centre_m(self) -> float:
        """Distance from the rear axle forward to the body's centre [m]."""
        return self.length_m / 2.0 - self.rear_overhang_m

    @property
    def rear_to_front_m(self) -> float:
        """Distance from the rear axle forward to the front bumper [m]."""
        return self.length_m - self.rear_overhang_m

    def box_corners(self) -> np.ndarray:
        """The body's corners in the rear-axle frame (x forward, y left) [m], counter-clockwise; (4, 2)."""
        r, f, w = -self.rear_overhang_m, self.rear_to_front_m, self.width_m / 2
        return np.array([[r, -w], [f, -w], [f, w], [r, w]])


def make_state(
    x: float, y: float, heading: float, speed: float = 0.0, steer: float = 0.0
) -> np.ndarray:
    """A one-car state array ``(1, 5)``."""
    return np.array([[x, y, heading, speed, steer]], dtype=np.float64)


def bicycle_step(
    state: np.ndarray,
    steer_cmd: np.ndarray,
    accel_cmd: np.ndarray,
    params: VehicleParams,
    dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Advance a batch of cars by ``dt`` seconds (in place) and return the step's velocities.

    Args:
        state: ``(B, 5)`` states, updated in place.
        steer_cmd: commanded road-wheel angle [rad], ``(B,)``; clipped to the steering limit and
            approached at no more than ``max_steer_rate``.
        accel_cmd: commanded acceleration [m/s^2], ``(B,)``; clipped to ``[-max_brake, max_accel]``.
        params: the car.
        dt: time step [s].

    Returns:
        ``(state, vx, vy, omega)``: the chord velocity [m/s] and yaw rate [rad/s] that move each car
        from its old to its new pose in ``dt``, so a physics engine that integrates
        ``p += v dt, h += omega dt`` lands exactly where this model does.
    """
    max_steer, max_dsteer = params.max_steer_rad, params.max_steer_rate_radps * dt
    target = np.minimum(np.maximum(steer_cmd, -max_steer), max_steer)
    steer0 = state[:, STEER]
    steer = steer0 + np.minimum(np.maximum(target - steer0, -max_dsteer), max_dsteer)
    accel = np.minimum(np.maximum(accel_cmd, -params.max_brake_mps2), params.max_accel_mps2)
    v0 = state[:, V]
    v1 = np.minimum(np.maximum(v0 + accel * dt, 0.0), params.max_speed_mps)
    v_mid = 0.5 * (v0 + v1)  # exact distance for constant acceleration
    omega = v_mid * np.tan(steer) / params.wheelbase_m
    half = 0.5 * omega * dt
    # chord of an arc of angle 2*half: length = arc * sin(half) / half (-> arc as half -> 0)
    small = np.abs(half) < 1e-9
    chord_speed = v_mid * np.where(small, 1.0, np.sin(half) / np.where(small, 1.0, half))
    direction = state[:, H] + half
    vx = chord_speed * np.cos(direction)
    vy = chord_speed * np.sin(direction)
    state[:, X] = state[:, X] + vx * dt
    state[:, Y] = state[:, Y] + vy * dt
    state[:, H] = state[:, H] + omega * dt
    state[:, V] = v1
    state[:, STEER] = steer
    return state, vx, vy, omega
