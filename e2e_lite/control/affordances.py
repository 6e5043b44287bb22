"""The affordances of cars in their worlds, measured: each car's heading to the road, its
offsets from the lane and the road, and the free gaps ahead in its lane and the lanes beside
(:data:`~e2e_lite.learning.labels.AFFORDANCE_NAMES`, their units and their cap there). The
collector labels its frames with them (:mod:`e2e_lite.imitation.collector`), and the safety
module audits what a network perceived against them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..learning.labels import AFFORDANCE_NAMES, GAP_CAP_M

if TYPE_CHECKING:  # (annotations only)
    from ..simulation.world import World


def affordances(
    worlds: list[World], s: np.ndarray, d: np.ndarray, heading_error: np.ndarray
) -> np.ndarray:
    """The affordances of B cars, ``(B, 9)`` float64 (see :data:`AFFORDANCE_NAMES` for units).

    Args:
        worlds: car i's world.
        s, d: lane-frame position of each rear axle [m].
        heading_error: heading minus the road's [rad].
    """
    n = len(worlds)
    out = np.empty((n, len(AFFORDANCE_NAMES)))
    for i, world in enumerate(worlds):
        track, veh = world.track, world.vehicle
        di = float(d[i])
        lane = int(track.lane_index(di))
        centre = float(track.lane_center(lane))
        half_lane = track.lane_width / 2.0
        front = float(s[i]) + veh.rear_to_front_m
        start = front - veh.length_m  # the rear bumper: a car reaching past it is alongside
        gaps = []
        for other in (lane, lane + 1, lane - 1):
            if not 0 <= other < track.n_lanes:
                gaps.append(0.0)
                continue
            hit = world.gap_ahead(start, other, GAP_CAP_M + front - start)
            gaps.append(min(GAP_CAP_M, max(0.0, start + hit - front)))
        out[i] = (
            float(heading_error[i]),
            di - centre,
            centre + half_lane - di,
            di - (centre - half_lane),
            track.half_width - di,
            di + track.half_width,
            *gaps,
        )
    return out
