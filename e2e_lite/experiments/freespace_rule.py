"""The safety rule on the free-space profile (chapter 11): parked cars as the camera sees them, in
the car's frame (:mod:`e2e_lite.learning.freespace`), instead of lane gaps.

:func:`~e2e_lite.experiments.safety.check` calls :func:`check_profile` when it is given a profile;
the road edges stay with the lane rule. The same lengths and margins as the lane rule
(:class:`~e2e_lite.experiments.safety.SafetyConfig`):

1. The body along the proposal. The rear axle's path is interpolated between the 5 points; the
   body spans from the rear axle to the front bumper, ``car_length_m - rear overhang`` ahead along
   the path's direction, ``+- car_width_m / 2`` sideways. It meets a strip when it overlaps it
   by more than :data:`STRIP_OVERLAP_M`.
2. Collision course: along the 1.5 s, the front comes within ``margin_m`` of a car read in a
   strip the body meets (a read at or above the strip's threshold ``free_m`` is "nothing seen").
3. Cannot stop: from the last point the car brakes (``v rho + v^2 / 2 beta``), extrapolated along
   the path's last direction and the road's curvature; the body meets a car within that.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..control.labels import N_POINTS, POINT_DT_S, interpolated_path
from ..learning.freespace import FRONT_M, STRIP_CENTRES_M, STRIP_HALF_M

#: How far a body must overlap a strip to meet what is in it [m].
STRIP_OVERLAP_M = 0.2


def nearest_car(
    profile_m: np.ndarray, free_m: np.ndarray, y_lo: np.ndarray, y_hi: np.ndarray
) -> np.ndarray:
    """For bodies spanning ``[y_lo, y_hi]`` sideways (car frame, (P,) each) [m], the nearest car
    read in the strips each overlaps, ``(P,)`` [m] from the front bumper (inf: nothing seen)."""
    lo_edge, hi_edge = STRIP_CENTRES_M - STRIP_HALF_M, STRIP_CENTRES_M + STRIP_HALF_M
    overlap = np.minimum(y_hi[:, None], hi_edge) - np.maximum(y_lo[:, None], lo_edge)
    seen = np.where(np.asarray(profile_m) >= np.asarray(free_m), np.inf, profile_m)
    return np.where(overlap > STRIP_OVERLAP_M, seen[None], np.inf).min(axis=1)


def _meets(
    x: np.ndarray,
    y: np.ndarray,
    slope: np.ndarray | float,
    profile_m: np.ndarray,
    free_m: np.ndarray,
    cfg: Any,
) -> tuple[np.ndarray, np.ndarray]:
    """The body at rear-axle positions ``(x, y)`` [m] heading along ``slope`` (dy/dx): whether
    its front reaches a car read in the strips it overlaps, and that car's distance [m]."""
    half = cfg.car_width_m / 2.0
    y_front = y + slope * FRONT_M
    near = nearest_car(
        profile_m, free_m, np.minimum(y, y_front) - half, np.maximum(y, y_front) + half
    )
    hit = (x > near - cfg.margin_m) & (x - cfg.car_length_m < near + cfg.parked_length_m)
    return hit, near


def check_profile(
    points: np.ndarray,
    profile_m: np.ndarray,
    free_m: np.ndarray,
    curvature: float,
    cfg: Any,
) -> tuple[str, float, float]:
    """Does following ``points`` (``(5, 2)`` [m], car frame) meet a car of the profile?

    Args:
        points: the proposal, rear-axle positions 0.3 s apart [m].
        profile_m: ``(15,)`` distances from the front bumper per strip [m].
        free_m: ``(15,)`` (or a scalar) reads from which a strip is free [m].
        curvature: the road's curvature [1/m] (left positive), for the stop's extrapolation.
        cfg: the lengths and margins (a :class:`~e2e_lite.experiments.safety.SafetyConfig`; that
            module imports this one).

    Returns:
        ``(kind, distance_m, t_s)``: kind ``""`` (nothing met), ``"collision course"`` or
        ``"cannot stop"``; the car's read distance [m]; when the violation begins [s].
    """
    pts = np.asarray(points, dtype=np.float64)
    x, y, t = interpolated_path(pts)
    slope = np.gradient(y, x) if np.all(np.diff(x) > 1e-6) else np.zeros_like(x)
    hit, near = _meets(x, y, slope, profile_m, free_m, cfg)
    if hit.any():
        k = int(np.argmax(hit))
        return "collision course", float(near[k]), float(t[k])
    v_end = float(np.hypot(*(pts[-1] - pts[-2]))) / POINT_DT_S
    need = v_end * cfg.reaction_s + v_end**2 / (2.0 * cfg.brake_mps2)
    ahead = np.arange(0.0, need + 0.01, 1.0)
    y_e = y[-1] + slope[-1] * ahead + curvature * ahead**2 / 2.0
    hit, near = _meets(x[-1] + ahead, y_e, slope[-1], profile_m, free_m, cfg)
    if hit.any():
        return "cannot stop", float(near[int(np.argmax(hit))]), N_POINTS * POINT_DT_S
    return "", float("inf"), float("inf")
