"""A top-down view: an ego-centred bird's-eye raster of the road, the parked cars, the ego and a
planned trajectory (ego heading up; 0.25 m per pixel by default)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..config import check_range
from .geometry import Track
from .raster import (
    CAR_COLOURS,
    DASH_D,
    DASH_PERIOD_M,
    DASH_S,
    EGO_COLOUR,
    GRASS,
    MARK_WIDTH_M,
    MARKING,
    RAIL,
    ROAD,
    SCALE,
    SHIFT,
    SHOULDER,
    to_fixed,
)
from .vehicle import VehicleParams
from .world import ParkedCars


@dataclass(frozen=True)
class TopDownConfig:
    """An ego-centred bird's-eye raster (ego heading up).

    Attributes:
        size_px: (height, width) of the image.
        m_per_px: scale [m/px].
        ego_row_frac: the ego's rear axle sits at this fraction of the height from the top.
    """

    size_px: tuple[int, int] = (240, 160)
    m_per_px: float = 0.25
    ego_row_frac: float = 0.8

    def __post_init__(self) -> None:
        check_range("TopDownConfig", "size_px[0]", self.size_px[0], 16, 4096, integer=True)
        check_range("TopDownConfig", "size_px[1]", self.size_px[1], 16, 4096, integer=True)
        check_range("TopDownConfig", "m_per_px", self.m_per_px, 0.01, 10.0)
        check_range("TopDownConfig", "ego_row_frac", self.ego_row_frac, 0.0, 1.0)


def render_topdown(
    track: Track,
    cars: ParkedCars | None,
    pose: tuple[float, float, float],
    cfg: TopDownConfig | None = None,
    trajectory: np.ndarray | None = None,
    vehicle: VehicleParams | None = None,
) -> np.ndarray:
    """An ego-centred bird's-eye RGB view: road, lanes, rails, parked cars, the ego, a trajectory.

    Args:
        track, cars: the scene.
        pose: the ego's rear-axle pose ``(x, y, heading)`` [m, m, rad]; heading points up.
        cfg: size and scale.
        trajectory: optional car-frame points ``(K, 2)`` [m] drawn as dots joined by a line.
        vehicle: the ego's dimensions (default :class:`~e2e_lite.simulation.vehicle.VehicleParams`).
    """
    cfg = cfg or TopDownConfig()
    rows, cols = cfg.size_px
    img = np.empty((rows, cols, 3), dtype=np.uint8)
    img[:] = GRASS
    row0, col0 = cfg.ego_row_frac * (rows - 1), (cols - 1) / 2.0
    c, s_ = math.cos(pose[2]), math.sin(pose[2])

    def to_px(xy: np.ndarray) -> np.ndarray:
        dx, dy = xy[..., 0] - pose[0], xy[..., 1] - pose[1]
        fwd, left = dx * c + dy * s_, -dx * s_ + dy * c
        return car_to_topdown(np.stack([fwd, left], -1), row0, col0, cfg.m_per_px)

    s_ego = float(track.to_frenet(pose[0], pose[1])[0])
    reach_back = (rows - row0) * cfg.m_per_px + 5
    reach_fwd = row0 * cfg.m_per_px + 5
    s_pts = np.linspace(max(0.0, s_ego - reach_back), s_ego + reach_fwd, 60)

    def band(d0: float, d1: float) -> np.ndarray:
        return np.concatenate(
            [to_px(track.position(s_pts, d0)), to_px(track.position(s_pts[::-1], d1))]
        )

    def fill(polys: list[np.ndarray], colour: tuple) -> None:
        cv2.fillPoly(img, [to_fixed(p) for p in polys], colour, cv2.LINE_AA, SHIFT)

    hw, rd = track.half_width, track.rail_d
    fill([band(-rd, rd)], SHOULDER)
    fill([band(-hw, hw)], ROAD)
    fill([band(hw - MARK_WIDTH_M, hw), band(-hw, -hw + MARK_WIDTH_M)], MARKING)
    fill([band(rd, rd + 0.3), band(-rd - 0.3, -rd)], RAIL)
    if track.n_lanes > 1:  # every dash of every divider in one lookup
        d_div = np.asarray(track.lane_center(np.arange(1, track.n_lanes))) - track.lane_width / 2
        first = math.floor(s_pts[0] / DASH_PERIOD_M) * DASH_PERIOD_M
        starts = np.arange(first, s_pts[-1], DASH_PERIOD_M)
        dash_s = np.broadcast_to(starts[:, None] + DASH_S, (len(d_div), len(starts), 4))
        dash_d = np.broadcast_to(d_div[:, None, None] + DASH_D, dash_s.shape)
        dashes = to_px(track.position(dash_s, dash_d)).reshape(-1, 4, 2)
        if len(dashes):
            fill(list(dashes), MARKING)
    if cars is not None and len(cars):
        sl = cars.between(s_pts[0] - 5, s_pts[-1] + 5)
        boxes = cars.corners()[sl]
        for k, box in enumerate(boxes):
            fill([to_px(box)], CAR_COLOURS[(sl.start + k) % len(CAR_COLOURS)])
    ego = (vehicle or VehicleParams()).box_corners()
    fill([car_to_topdown(ego, row0, col0, cfg.m_per_px)], EGO_COLOUR)
    if trajectory is not None:
        pts = to_fixed(
            car_to_topdown(np.r_[[[0.0, 0.0]], np.asarray(trajectory)], row0, col0, cfg.m_per_px)
        )
        cv2.polylines(img, [pts], False, (255, 40, 40), 1, cv2.LINE_AA, SHIFT)
        for p in pts[1:]:
            cv2.circle(
                img, (int(p[0]), int(p[1])), 2 * int(SCALE), (255, 40, 40), -1, cv2.LINE_AA, SHIFT
            )
    return img


def car_to_topdown(fwd_left: np.ndarray, row0: float, col0: float, m_per_px: float) -> np.ndarray:
    """Car-frame (forward, left) [m] to top-down pixels (col, row)."""
    return np.stack([col0 - fwd_left[..., 1] / m_per_px, row0 - fwd_left[..., 0] / m_per_px], -1)
