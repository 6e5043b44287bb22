"""The LQR tracker: gains, closed-loop behaviour, the 5-point conversion."""

from __future__ import annotations

import numpy as np
import pytest

from e2e_lite.control.tracker import (
    LaneChangePath,
    LQRTracker,
    TrackerConfig,
    follow_trajectory,
    gain_table,
    lane_reference,
    lateral_model,
    trajectory_reference,
)
from e2e_lite.learning.labels import POINT_DT_S
from e2e_lite.simulation.geometry import Track
from e2e_lite.simulation.vehicle import VehicleParams, bicycle_step, make_state

T = np.arange(1, 6) * POINT_DT_S


def test_gains_give_a_stable_closed_loop_over_the_speed_grid():
    cfg = TrackerConfig()
    speeds, gains, poles = gain_table(cfg, 2.7)
    assert len(speeds) == cfg.speed_grid_mps[2]
    assert np.all(np.abs(poles) < 1.0)
    # recompute A - B K independently at a few speeds
    for v, k in zip(speeds[::17], gains[::17]):
        sysd = lateral_model(float(v), 2.7, cfg.period_s)
        closed = sysd.A - sysd.B @ k[None, :]
        assert np.max(np.abs(np.linalg.eigvals(closed))) < 1.0
    assert np.all(gains > 0)  # steer against a left offset and a left heading


def simulate_offset(speed: float, offset: float = 1.0, seconds: float = 10.0) -> np.ndarray:
    """Lateral position of a car starting ``offset`` metres left of a straight line, every 0.1 s."""
    tracker, veh = LQRTracker(), VehicleParams()
    st = make_state(0.0, offset, 0.0, speed)
    ys = []
    for _ in range(int(seconds / 0.1)):
        steer = tracker.steer(st[:, 1], st[:, 2], np.zeros(1), st[:, 3])
        for _ in range(5):
            bicycle_step(st, steer, np.zeros(1), veh, 0.02)
        ys.append(float(st[0, 1]))
    return np.array(ys)


@pytest.mark.parametrize("speed", [10.0, 20.0, 30.0])
def test_recovers_from_a_one_metre_offset_without_overshoot(speed):
    ys = simulate_offset(speed, seconds=200.0 / speed)
    settle = np.flatnonzero(np.abs(ys) >= 0.1)
    t_settle = (settle[-1] + 1) * 0.1 if settle.size else 0.0
    assert t_settle < 60.0 / speed  # within a distance of ~60 m (2 s at 30 m/s, 3 s at 20 m/s)
    assert ys.min() > -0.2  # no overshoot towards the next lane (1.85 m away)
    assert abs(ys[-1]) < 0.01  # after 200 m


def test_straight_trajectory_gives_zero_errors_and_the_speed():
    v = 17.0
    pts = np.stack([v * T, np.zeros(5)], axis=-1)
    e, psi, kappa, v_ref, a_ref = trajectory_reference(pts)
    assert abs(e) < 1e-9 and abs(psi) < 1e-9 and abs(kappa) < 1e-9
    assert v_ref == pytest.approx(v, rel=1e-9)
    assert abs(a_ref) < 1e-9


@pytest.mark.parametrize(("radius", "speed"), [(150.0, 20.0), (-400.0, 25.0), (60.0, 8.0)])
def test_constant_curvature_trajectory_gives_that_curvature(radius, speed):
    angle = speed * T / radius
    pts = np.stack([radius * np.sin(angle), radius * (1 - np.cos(angle))], axis=-1)
    e, psi, kappa, v_ref, _ = trajectory_reference(pts[None])
    assert kappa[0] == pytest.approx(1.0 / radius, rel=0.02)
    assert v_ref[0] == pytest.approx(speed, rel=0.01)
    assert abs(e[0]) < 0.02 and abs(psi[0]) < 0.01


def test_accelerating_trajectory_gives_the_acceleration():
    v0, a = 10.0, 2.0
    pts = np.stack([v0 * T + 0.5 * a * T**2, np.zeros(5)], axis=-1)
    _, _, _, v_ref, a_ref = trajectory_reference(pts)
    assert v_ref == pytest.approx(v0, rel=1e-6) and a_ref == pytest.approx(a, rel=1e-6)


def test_standing_still_gives_no_direction():
    _, psi, kappa, v_ref, _ = trajectory_reference(np.zeros((2, 5, 2)))
    assert np.all(psi == 0) and np.all(kappa == 0) and np.all(v_ref == 0)


def test_bad_trajectory_shape_is_refused():
    with pytest.raises(ValueError, match="shape"):
        trajectory_reference(np.zeros((3, 4, 2)))


def test_following_a_curved_trajectory_drives_its_curve():
    radius, speed = 120.0, 15.0
    tracker, veh = LQRTracker(), VehicleParams()
    angle = speed * T / radius
    pts = np.stack([radius * np.sin(angle), radius * (1 - np.cos(angle))], axis=-1)[None]
    st = make_state(0.0, 0.0, 0.0, speed)
    for _ in range(40):  # re-plan the same (frame-relative) trajectory every 0.1 s
        steer, accel = follow_trajectory(tracker, pts, st[:, 3])
        for _ in range(5):
            bicycle_step(st, steer, accel, veh, 0.02)
    # after 4 s the car is on the circle of that radius about (0, R)
    assert np.hypot(st[0, 0], st[0, 1] - radius) == pytest.approx(radius, abs=0.3)


def test_lane_change_path_ends_on_the_target_lane():
    path = LaneChangePath(s_start=100.0, length_m=60.0, d_from=0.0, d_to=3.7)
    assert path.offset(90.0) == (0.0, 0.0, 0.0)
    d, slope, curv = path.offset(130.0)
    assert d == pytest.approx(1.85) and slope > 0 and abs(curv) < 1e-12
    assert path.offset(170.0)[0] == pytest.approx(3.7)
    assert path.done(160.0) and not path.done(159.9)
    # peak lateral acceleration formula in the docstring
    s = np.linspace(100, 160, 2001)
    peak = max(abs(path.offset(float(x))[2]) for x in s)
    assert peak == pytest.approx(5.7735 * 3.7 / 60.0**2, rel=1e-3)


def test_lane_reference_on_an_offset_lane_of_a_curve():
    e, psi, kappa = lane_reference(np.array([3.9]), np.array([0.01]), np.array([1 / 200]), 3.7)
    assert e[0] == pytest.approx(0.2) and psi[0] == 0.01
    assert kappa[0] == pytest.approx(1 / (200 - 3.7))


def test_tracker_drives_a_lane_change_on_a_curve():
    track = Track([0.0], [0.0], [0.0], [1 / 300], [500.0])
    tracker, veh = LQRTracker(), VehicleParams()
    x, y, h = track.pose(10.0, 0.0)
    st = make_state(float(x), float(y), float(h), 20.0)
    path = LaneChangePath(50.0, 70.0, 0.0, 3.7)
    worst = 0.0
    for _ in range(120):
        s, d = track.to_frenet(st[:, 0], st[:, 1])
        he = st[0, 2] - track.heading(s)[0]
        e, psi, k = path.reference(float(s[0]), float(d[0]), float(he), 1 / 300)
        worst = max(worst, abs(e))
        steer = tracker.steer(np.array([e]), np.array([psi]), np.array([k]), st[:, 3])
        for _ in range(5):
            bicycle_step(st, steer, np.zeros(1), veh, 0.02)
    assert worst < 0.25
    assert float(track.to_frenet(st[:, 0], st[:, 1])[1][0]) == pytest.approx(3.7, abs=0.05)


def test_speed_control_is_bounded():
    tracker = LQRTracker()
    a = tracker.accel(np.array([0.0, 30.0, 20.0]), np.array([30.0, 0.0, 20.0]))
    assert a[0] == tracker.cfg.max_accel_mps2 and a[1] == -tracker.cfg.max_brake_mps2 and a[2] == 0


def test_bad_tracker_settings_raise():
    with pytest.raises(ValueError, match=r"TrackerConfig\.steer_max_rad"):
        TrackerConfig(steer_max_rad=0.0)


def _arc_pose(v0: float, accel: float, kappa: float, t: float) -> tuple[float, float, float, float]:
    """Exact ``(x, y, heading, speed)`` at time ``t`` of a car starting at the origin along +x at
    ``v0`` [m/s], accelerating at ``accel`` [m/s^2] on a circle of curvature ``kappa`` [1/m]
    (heading = kappa x distance; position integrated finely)."""
    tt = np.linspace(0.0, t, 20_001)
    v = v0 + accel * tt
    heading = kappa * (v0 * tt + accel * tt**2 / 2)
    return (
        float(np.trapezoid(v * np.cos(heading), tt)),
        float(np.trapezoid(v * np.sin(heading), tt)),
        float(heading[-1]),
        float(v[-1]),
    )


@pytest.mark.parametrize("v0, accel, kappa", [(20.0, 1.5, 0.004), (25.0, -2.0, -0.01)])
@pytest.mark.parametrize("preview_s", [0.3, 0.6, 0.9])
def test_preview_reading_of_a_constant_acceleration_arc(v0, accel, kappa, preview_s):
    pts = np.array([_arc_pose(v0, accel, kappa, t)[:2] for t in T])
    e, psi, kap, v_ref, a_ref = trajectory_reference(pts, preview_s)
    _, y, heading, speed = _arc_pose(v0, accel, kappa, preview_s)
    assert e == pytest.approx(-y, abs=1e-3)  # the path is y to the left of the car: e = -y
    assert psi == pytest.approx(-heading, abs=1e-3)
    assert kap == pytest.approx(kappa, abs=1e-4)
    assert v_ref == pytest.approx(speed, abs=0.02)
    assert a_ref == pytest.approx(accel, abs=0.05)
    # the reading at t = 0 is the least-squares end point: its acceleration is the worst read
    a0 = trajectory_reference(pts, 0.0)[4]
    assert abs(a0 - accel) > abs(a_ref - accel)


def test_speed_reading_without_feed_forward_ignores_the_acceleration():
    tracker = LQRTracker()
    points = np.stack([25.0 * T - 1.0 * T**2, np.zeros(5)], axis=-1)  # braking at 2 m/s^2
    _, a_ff = follow_trajectory(tracker, points[None], np.array([25.0]), 0.0, "trajectory")
    _, a_no = follow_trajectory(tracker, points[None], np.array([25.0]), 0.0, "trajectory_no_ff")
    assert a_ff[0] == pytest.approx(-2.0, abs=0.05)
    assert a_no[0] == pytest.approx(0.0, abs=0.05)  # v_ref = v now: no feedback either
    with pytest.raises(ValueError, match="speed"):
        follow_trajectory(tracker, points[None], np.array([25.0]), 0.0, "cruise")
    with pytest.raises(ValueError, match="preview_s"):
        follow_trajectory(tracker, points[None], np.array([25.0]), 2.0)
