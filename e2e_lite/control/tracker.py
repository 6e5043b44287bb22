"""The paper's "LQR controller": lateral LQR with a speed-scheduled gain table, plus speed control.

Lateral error model (chapter 03 derives it). Let ``e`` be the rear axle's signed lateral offset
from the reference path [m] (left positive) and ``psi`` the heading error [rad] (car minus path).
For the kinematic bicycle at speed ``v`` with wheelbase ``L`` and steering ``delta``, on a path of
curvature ``kappa``, linearised for small errors::

    e'   = v psi
    psi' = v tan(delta) / L - v kappa  ~=  (v / L) (delta - delta_ff),   delta_ff = atan(L kappa)

so with the feed-forward ``delta_ff`` taken out, ``x = (e, psi)`` obeys ``x' = A x + B u`` with
``A = [[0, v], [0, 0]]``, ``B = [[0], [v / L]]`` and ``u = delta - delta_ff``. The policy holds its
command for one policy period, so the model is discretised with a zero-order hold at that period
(``control.c2d``) and ``control.dlqr`` gives the gain ``K(v)`` of ``u = -K x`` for the weights
``Q = diag(1 / e_max^2, 1 / psi_max^2)``, ``R = 1 / delta_max^2`` (Bryson's rule). The gain depends
on ``v``: :func:`gain_table` solves ``dlqr`` once per speed of a grid (about 0.5 ms each) and
:meth:`LQRTracker.steer` interpolates the table; no Riccati equation is solved in the loop.

Longitudinal control: ``accel = a_ff + k_v (v_ref - v)``, clipped to comfortable bounds.

Three kinds of reference, each turned into ``(e, psi, kappa)`` (and a speed):

* a lane centre (:func:`lane_reference`);
* a lateral path in the lane frame, such as a lane change (:class:`LaneChangePath`);
* a 5-point trajectory in the car frame, the networks' output (:func:`trajectory_reference`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..config import check_range
from ..learning.labels import N_POINTS, POINT_DT_S
from ..simulation.vehicle import VehicleParams
from ..simulation.world import SimConfig

if TYPE_CHECKING:
    import control

#: How the speed command is read off a trajectory (:func:`follow_trajectory`): ``"trajectory"``
#: (the paper: ``a = a_ref + k (v_ref - v)``) or ``"trajectory_no_ff"`` (``a = k (v_ref - v)``,
#: no acceleration feed-forward).
SPEED_READINGS = ("trajectory", "trajectory_no_ff")


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of the LQR tracker.

    Attributes:
        lateral_max_m: Bryson scale of the lateral error [m] (larger: gentler).
        heading_max_rad: Bryson scale of the heading error [rad].
        steer_max_rad: Bryson scale of the feedback steering [rad] (larger: more aggressive).
        period_s: the period the command is held for (the policy period) [s].
        speed_grid_mps: (min, max, count) of the speed grid of the gain table [m/s].
        speed_gain_per_s: feedback gain of the speed loop [1/s].
        max_accel_mps2, max_brake_mps2: bounds of the commanded acceleration [m/s^2].
    """

    lateral_max_m: float = 1.0
    heading_max_rad: float = 0.1
    steer_max_rad: float = 0.01
    period_s: float = 0.1
    speed_grid_mps: tuple[float, float, int] = (0.5, 50.0, 100)
    speed_gain_per_s: float = 1.0
    max_accel_mps2: float = 2.5
    max_brake_mps2: float = 6.0

    def __post_init__(self) -> None:
        o = "TrackerConfig"
        check_range(o, "lateral_max_m", self.lateral_max_m, 0.0, 100.0, lo_open=True)
        check_range(o, "heading_max_rad", self.heading_max_rad, 0.0, 3.0, lo_open=True)
        check_range(o, "steer_max_rad", self.steer_max_rad, 0.0, 1.0, lo_open=True)
        check_range(o, "period_s", self.period_s, 0.0, 1.0, lo_open=True)
        lo, hi, count = self.speed_grid_mps
        check_range(o, "speed_grid_mps[0]", lo, 0.0, 100.0, lo_open=True)
        check_range(o, "speed_grid_mps[1]", hi, lo, 200.0, lo_open=True)
        check_range(o, "speed_grid_mps[2]", count, 2, 10_000, integer=True)
        check_range(o, "speed_gain_per_s", self.speed_gain_per_s, 0.0, 20.0, lo_open=True)
        check_range(o, "max_accel_mps2", self.max_accel_mps2, 0.0, 20.0, lo_open=True)
        check_range(o, "max_brake_mps2", self.max_brake_mps2, 0.0, 20.0, lo_open=True)


def lateral_model(speed_mps: float, wheelbase_m: float, period_s: float) -> control.StateSpace:
    """The ZOH-discretised lateral error model at one speed: states ``(e [m], psi [rad])``,
    input feedback steering [rad], sampled every ``period_s`` [s]."""
    import control  # (here, not at the top: python-control and the matplotlib it loads cost an
    # evaluation worker 0.3 s to import, and a worker is handed trackers already built)

    a = np.array([[0.0, speed_mps], [0.0, 0.0]])
    b = np.array([[0.0], [speed_mps / wheelbase_m]])
    return control.c2d(control.ss(a, b, np.eye(2), np.zeros((2, 1))), period_s)


@functools.lru_cache(maxsize=16)
def gain_table(cfg: TrackerConfig, wheelbase_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve ``control.dlqr`` over the speed grid.

    Returns:
        ``(speeds [m/s] (S,), gains (S, 2) [rad/m, rad/rad], closed-loop eigenvalues (S, 2))``.
        Cached per ``(cfg, wheelbase_m)``: the table is computed once per process.
    """
    import control  # (see lateral_model)

    lo, hi, count = cfg.speed_grid_mps
    speeds = np.linspace(lo, hi, count)
    q = np.diag([1.0 / cfg.lateral_max_m**2, 1.0 / cfg.heading_max_rad**2])
    r = np.array([[1.0 / cfg.steer_max_rad**2]])
    gains, poles = np.empty((count, 2)), np.empty((count, 2), dtype=complex)
    for i, v in enumerate(speeds):
        sysd = lateral_model(float(v), wheelbase_m, cfg.period_s)
        k, _, e = control.dlqr(sysd.A, sysd.B, q, r)
        gains[i], poles[i] = np.asarray(k)[0], e
    return speeds, gains, poles


class LQRTracker:
    """Steering and acceleration for batches of cars, given references.

    Args:
        cfg: the tracker's settings.
        vehicle: the car (wheelbase and steering limit).
    """

    def __init__(
        self, cfg: TrackerConfig | None = None, vehicle: VehicleParams | None = None
    ) -> None:
        self.cfg = cfg or TrackerConfig()
        self.vehicle = vehicle or VehicleParams()
        self.speeds, self.gains, self.poles = gain_table(self.cfg, self.vehicle.wheelbase_m)

    def gain(self, speed_mps: np.ndarray) -> np.ndarray:
        """The interpolated LQR gain ``(B, 2)`` at each speed [m/s] (clamped to the grid)."""
        v = np.asarray(speed_mps, dtype=np.float64)
        return np.stack(
            [
                np.interp(v, self.speeds, self.gains[:, 0]),
                np.interp(v, self.speeds, self.gains[:, 1]),
            ],
            axis=-1,
        )

    def steer(
        self,
        lateral_m: np.ndarray,
        heading_rad: np.ndarray,
        curvature: np.ndarray,
        speed_mps: np.ndarray,
    ) -> np.ndarray:
        """Road-wheel angle [rad]: ``atan(L kappa) - K(v) (e, psi)``, within the steering limit.

        Args:
            lateral_m: lateral error ``e`` of the rear axle from the path, left positive [m].
            heading_rad: heading error ``psi``, car minus path [rad].
            curvature: the path's curvature at the car [1/m].
            speed_mps: the car's speed [m/s].
        """
        k = self.gain(speed_mps)
        e, psi = np.asarray(lateral_m), np.asarray(heading_rad)
        delta = np.arctan(self.vehicle.wheelbase_m * np.asarray(curvature)) - (
            k[..., 0] * e + k[..., 1] * psi
        )
        lim = self.vehicle.max_steer_rad
        return np.clip(delta, -lim, lim)

    def accel(
        self,
        speed_mps: np.ndarray,
        ref_speed_mps: np.ndarray,
        ff_accel_mps2: np.ndarray | float = 0.0,
    ) -> np.ndarray:
        """Acceleration [m/s^2]: ``a_ff + k_v (v_ref - v)``, within ``[-max_brake, max_accel]``."""
        a = np.asarray(ff_accel_mps2) + self.cfg.speed_gain_per_s * (
            np.asarray(ref_speed_mps) - np.asarray(speed_mps)
        )
        return np.clip(a, -self.cfg.max_brake_mps2, self.cfg.max_accel_mps2)


# ------------------------------------------------------------------------ references
def lane_reference(
    d: np.ndarray, heading_error: np.ndarray, road_curvature: np.ndarray, d_target: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(e, psi, kappa)`` for following the line ``d = d_target`` of the lane frame.

    The line at offset ``d`` from a reference line of curvature ``k`` has curvature
    ``k / (1 - k d)`` (a left curve's inner lanes bend more).
    """
    d_target = np.asarray(d_target, dtype=np.float64)
    kappa = np.asarray(road_curvature)
    return np.asarray(d) - d_target, np.asarray(heading_error), kappa / (1.0 - kappa * d_target)


@dataclass
class LaneChangePath:
    """A lateral move in the lane frame from ``d_from`` at ``s_start`` to ``d_to`` at
    ``s_start + length_m``: ``d(s) = d_from + (d_to - d_from) b((s - s_start) / length_m)`` with
    the quintic blend ``b``. Its peak lateral acceleration at speed ``v`` is
    ``5.77 |d_to - d_from| v^2 / length^2``."""

    s_start: float
    length_m: float
    d_from: float
    d_to: float

    def offset(self, s: float) -> tuple[float, float, float]:
        """``(d, dd/ds, d^2d/ds^2)`` of the path at arc length ``s`` [m, -, 1/m] (scalar maths:
        it runs once per car per decision)."""
        u = min(1.0, max(0.0, (s - self.s_start) / self.length_m))
        span = self.d_to - self.d_from
        b = u**3 * (10.0 - 15.0 * u + 6.0 * u * u)
        db = 30.0 * u * u * (1.0 - u) ** 2
        ddb = 60.0 * u * (1.0 - u) * (1.0 - 2.0 * u)
        return self.d_from + span * b, span * db / self.length_m, span * ddb / self.length_m**2

    def reference(
        self, s: float, d: float, heading_error: float, road_curvature: float
    ) -> tuple[float, float, float]:
        """``(e, psi, kappa)`` of a car at ``(s, d)`` following this path (small-slope form:
        ``psi = heading_error - atan(d')``, ``kappa = k / (1 - k d_ref) + d''``)."""
        d_ref, slope, dd = self.offset(s)
        k = road_curvature / (1.0 - road_curvature * d_ref)
        return d - d_ref, heading_error - math.atan(slope), k + dd

    def done(self, s: float) -> bool:
        """Whether arc length ``s`` is past the path's end."""
        return s >= self.s_start + self.length_m


def _fit_matrix(n_points: int, point_dt_s: float, degree: int) -> np.ndarray:
    """The least-squares map from ``n_points + 1`` samples (origin first) at times
    ``0, dt, ..., n dt`` to the coefficients of a polynomial in ``t`` of ``degree``."""
    t = np.arange(n_points + 1) * point_dt_s
    vander = np.vander(t, degree + 1, increasing=True)
    return np.linalg.pinv(vander)


_FIT = _fit_matrix(N_POINTS, POINT_DT_S, 3)


def trajectory_reference(
    points: np.ndarray, preview_s: float = 0.0, min_speed_mps: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Turn 5-point trajectories in the car frame into tracker references.

    The conversion: prepend the origin (the rear axle now, ``t = 0``) to the points
    ``p_k`` at ``t = 0.3 k`` s, fit ``x(t)`` and ``y(t)`` each with a cubic in ``t`` by least
    squares (one fixed 4 x 6 matrix for every sample), and read the fit at ``t = preview_s``:

    * ``e = -y(t_p)`` (the car is at ``y = 0``; the path at ``y(t_p)``: left of the car means the
      car is to the right of the path, ``e < 0``),
    * ``psi = -atan2(y', x')`` (the car's heading, 0 in its own frame, minus the path's),
    * ``kappa = (x' y'' - y' x'') / (x'^2 + y'^2)^(3/2)``,
    * ``v_ref = sqrt(x'^2 + y'^2)`` and ``a_ref`` = its time derivative.

    Below ``min_speed_mps`` the direction is undefined: there ``psi = kappa = 0``.

    Args:
        points: ``(B, 5, 2)`` or ``(5, 2)`` points ``(x forward, y left)`` [m], 0.3 s apart.
        preview_s: where along the fit to read the reference [s].
        min_speed_mps: speeds below this count as standing still [m/s].

    Returns:
        ``(e [m], psi [rad], kappa [1/m], v_ref [m/s], a_ref [m/s^2])``, each ``(B,)`` (or scalars'
        shape ``()`` for a single trajectory).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[-2:] != (N_POINTS, 2):
        raise ValueError(f"points must have shape (B, {N_POINTS}, 2); got {pts.shape}")
    samples = np.concatenate([np.zeros((*pts.shape[:-2], 1, 2)), pts], axis=-2)
    coef = np.einsum("cn,...nk->...ck", _FIT, samples)  # (..., 4, 2): x and y coefficients in t
    t = preview_s
    pos = coef[..., 0, :] + coef[..., 1, :] * t + coef[..., 2, :] * t**2 + coef[..., 3, :] * t**3
    vel = coef[..., 1, :] + 2 * coef[..., 2, :] * t + 3 * coef[..., 3, :] * t**2
    acc = 2 * coef[..., 2, :] + 6 * coef[..., 3, :] * t
    speed = np.hypot(vel[..., 0], vel[..., 1])
    moving = speed >= min_speed_mps
    safe = np.where(moving, speed, 1.0)
    psi = np.where(moving, -np.arctan2(vel[..., 1], vel[..., 0]), 0.0)
    cross = vel[..., 0] * acc[..., 1] - vel[..., 1] * acc[..., 0]
    kappa = np.where(moving, cross / safe**3, 0.0)
    a_ref = np.where(moving, (vel * acc).sum(-1) / safe, acc[..., 0])
    return -pos[..., 1], psi, kappa, speed, a_ref


def check_reading(
    owner: str, preview_s: float, speed: str, readings: tuple = SPEED_READINGS
) -> None:
    """Validate a trajectory reading: ``preview_s`` within the 1.5 s horizon, ``speed`` one of
    ``readings``."""
    check_range(owner, "preview_s", preview_s, 0.0, N_POINTS * POINT_DT_S)
    if speed not in readings:
        raise ValueError(f"{owner}.speed={speed!r} is invalid: must be one of {readings}")


def follow_trajectory(
    tracker: LQRTracker,
    points: np.ndarray,
    speed_mps: np.ndarray,
    preview_s: float = 0.0,
    speed: str = "trajectory",
) -> tuple[np.ndarray, np.ndarray]:
    """Steering [rad] and acceleration [m/s^2] that follow 5-point trajectories ``(B, 5, 2)``
    from the cars' speeds ``(B,)`` [m/s]: the references are read at ``preview_s`` (see
    :func:`trajectory_reference`), the speed as ``speed`` says (:data:`SPEED_READINGS`)."""
    check_reading("follow_trajectory", preview_s, speed)
    e, psi, kappa, v_ref, a_ref = trajectory_reference(points, preview_s)
    feed_forward = a_ref if speed == "trajectory" else 0.0
    return tracker.steer(e, psi, kappa, speed_mps), tracker.accel(speed_mps, v_ref, feed_forward)


def default_tracker(
    vehicle: VehicleParams | None = None, sim: SimConfig | None = None
) -> LQRTracker:
    """The LQR tracker with default weights for this car, discretised at the world's policy
    period ``sim.policy_period_s`` [s] (defaults: :class:`VehicleParams`, :class:`SimConfig`)."""
    period_s = (sim or SimConfig()).policy_period_s
    return LQRTracker(TrackerConfig(period_s=period_s), vehicle or VehicleParams())
