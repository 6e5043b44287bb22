"""The labels: what the networks learn from a frame, in one place (numpy only: no simulator,
no driver).

* The trajectory format (the paper's): :data:`N_POINTS` points :data:`POINT_DT_S` apart, in the
  car frame at the rear axle [m], its path interpolated between them (:func:`interpolated_path`),
  and a trajectory re-timed along its own path (:func:`along_path`).
* The expert's manoeuvre states (:data:`KEEP`, :data:`CHANGE`, :data:`PASS`, :data:`FOLLOW`), which
  the dataset records with every sample.
* The 9 affordances (:data:`AFFORDANCE_NAMES`, after DeepDriving) and the cap of their gaps.
* Seed 002's throttle and brake, recovered from the acceleration label (:func:`throttle_brake`).

The expert writes its labels in this format (:mod:`e2e_lite.control.expert`), the affordances of
cars in their worlds are measured in it (:func:`e2e_lite.control.affordances.affordances`), and
the dataset (:mod:`e2e_lite.learning.dataset`), the losses and the safety module read it from
here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

#: The paper's trajectory: 5 points, 0.3 s apart, 1.5 s ahead.
N_POINTS = 5
#: Time between two trajectory points [s].
POINT_DT_S = 0.3
#: Coordinates per trajectory point (x forward, y left) [m].
POINT_DIMS = 2
#: A trajectory flattened as x1, y1, ..., x5, y5: the networks' trajectory output per mode.
TRAJECTORY_DIMS = N_POINTS * POINT_DIMS

#: The expert's manoeuvre states (:class:`~e2e_lite.control.expert.Expert`), as recorded in the dataset.
KEEP, CHANGE, PASS, FOLLOW = 0, 1, 2, 3
STATE_NAMES = ("keep", "change", "pass", "follow")


class Decision(NamedTuple):
    """One car's decision, as either expert reports it and the dataset records it: its state
    (``KEEP`` ...), the lane it drives for, the side of a lane change under way (+1 left, -1
    right, 0 none), and whether that change is an overtake."""

    state: int
    target: int
    side: int
    overtaking: bool


GAP_CAP_M = 60.0
AFFORDANCE_NAMES = (
    "heading_rad",
    "center_offset_m",
    "left_marking_m",
    "right_marking_m",
    "left_edge_m",
    "right_edge_m",
    "gap_ego_m",
    "gap_left_m",
    "gap_right_m",
)
"""The affordances (after DeepDriving), all at the rear axle:

* ``heading_rad``: heading minus the road tangent's [rad], left positive;
* ``center_offset_m``: signed distance from the centre of the ego lane (the nearest lane) [m],
  left positive;
* ``left_marking_m`` / ``right_marking_m``: distance to the ego lane's left / right marking [m]
  (positive inside the lane);
* ``left_edge_m`` / ``right_edge_m``: distance to the road's left / right edge [m];
* ``gap_ego_m`` / ``gap_left_m`` / ``gap_right_m``: free distance ahead of the front bumper to the
  nearest parked car in the ego lane / the lane to its left / to its right, along the lane
  (the parked cars' boxes in the lane frame, :meth:`~e2e_lite.simulation.world.World.gap_ahead`)
  [m]. A car alongside
  (overlapping the ego's length) gives 0. Capped at ``GAP_CAP_M`` (60 m), which also
  encodes "no car"; a lane that does not exist (left of the leftmost) gives 0 (blocked).
"""

#: The three gaps ahead (ego, left and right lanes), in that order.
GAP_NAMES = ("gap_ego_m", "gap_left_m", "gap_right_m")

#: Each affordance's column in an ``(N, 9)`` array, by name.
AFFORDANCE_INDEX = {name: i for i, name in enumerate(AFFORDANCE_NAMES)}


class Limits(Protocol):
    """What :func:`throttle_brake` reads of a car (a
    :class:`~e2e_lite.simulation.vehicle.VehicleParams`): its largest acceleration and braking
    [m/s^2]."""

    max_accel_mps2: float
    max_brake_mps2: float


def throttle_brake(accel_mps2: np.ndarray, vehicle: Limits) -> tuple[np.ndarray, np.ndarray]:
    """Seed 002's throttle and brake in [0, 1] from accelerations [m/s^2]."""
    a = np.asarray(accel_mps2)
    return np.maximum(a, 0.0) / vehicle.max_accel_mps2, np.maximum(-a, 0.0) / vehicle.max_brake_mps2


#: Positions interpolated per 0.3 s between a trajectory's points (:func:`interpolated_path`).
PATH_SUBSTEPS = 4


def interpolated_path(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rear axle's positions between the origin and a trajectory's 5 points ``(5, 2)`` [m],
    :data:`PATH_SUBSTEPS` per 0.3 s: ``(x, y, t)`` [m, m, s] (what the safety rules sweep the
    body along)."""
    pts = np.concatenate([np.zeros((1, 2)), np.asarray(points, dtype=np.float64)])
    u = np.linspace(0.0, N_POINTS, N_POINTS * PATH_SUBSTEPS + 1)
    x = np.interp(u, np.arange(N_POINTS + 1), pts[:, 0])
    y = np.interp(u, np.arange(N_POINTS + 1), pts[:, 1])
    return x, y, u * POINT_DT_S


def along_path(points: np.ndarray, progress: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Trajectories ``(..., 5, 2)`` [m] re-timed along their own paths: each point moved along its
    polyline (from the origin) to the distance ``progress(along)`` [m], where ``along`` ``(M, 5)``
    holds each point's own distance; never past the path's end. All at once, to the bit as
    :func:`numpy.interp` (the safety module's braking and speed caps)."""
    pts = np.asarray(points, dtype=np.float64)
    poly = np.pad(pts.reshape(-1, N_POINTS, 2), ((0, 0), (1, 0), (0, 0)))
    step = np.diff(poly, axis=1)
    along = np.pad(np.cumsum(np.hypot(step[..., 0], step[..., 1]), axis=1), ((0, 0), (1, 0)))
    covered = np.minimum(progress(along[:, 1:]), along[:, -1:])
    out = poly[:, 1:].copy()
    moved = np.any(np.abs(covered - along[:, 1:]) > 1e-9, axis=1)  # (re-timed)
    a, x, p = along[moved], covered[moved], poly[moved]
    j = np.minimum((x[:, :, None] >= a[:, None, :]).sum(axis=2) - 1, N_POINTS - 1)  # segment
    lo, hi = np.take_along_axis(a, j, axis=1), np.take_along_axis(a, j + 1, axis=1)
    p_lo, p_hi = (np.take_along_axis(p, i[..., None], axis=1) for i in (j, j + 1))
    with np.errstate(divide="ignore", invalid="ignore"):  # (a zero-length step is replaced)
        at = (p_hi - p_lo) / (hi - lo)[..., None] * (x - lo)[..., None] + p_lo
    end = (x >= a[:, -1:])[..., None]  # on a vertex or at the end: that point (as np.interp)
    out[moved] = np.where((x == lo)[..., None] | end, np.where(end, p[:, -1:], p_lo), at)
    return out.reshape(pts.shape)
