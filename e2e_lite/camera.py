"""The front camera: a pinhole model rasterised with OpenCV polygon fills, plus a top-down view.

Frames
------
* **car frame**: origin at the rear axle, ``x`` forward, ``y`` left, ``z`` up [m] (the frame the
  paper's trajectories are given in).
* **camera frame**: origin at the lens, ``x`` right, ``y`` down, ``z`` along the optical axis.
  The camera sits ``forward_offset_m`` ahead of the rear axle, ``mount_height_m`` above the road,
  pitched down by ``pitch``. A car-frame point ``(f, l, u)`` relative to the lens is::

      z_c = f cos(pitch) - u sin(pitch)
      y_c = -(f sin(pitch) + u cos(pitch))
      x_c = -l

* **pixels**: ``col = cx + fx x_c / z_c``, ``row = cy + fy y_c / z_c`` with pixel centres at
  integer coordinates, ``cx = (W - 1) / 2``, ``cy = (H - 1) / 2`` and ``fx = fy = (W / 2) / tan(hfov / 2)``.
  The pitch is chosen so the horizon (``row = cy - fy tan(pitch)``) lies at ``horizon_frac`` of
  the height: the sky is cropped, as in PilotNet and the paper.

Images are **RGB**, ``uint8``, shape ``(H, W, 3)``, everywhere in the course (convert with
``image[..., ::-1]`` only when handing a frame to ``cv2.imwrite``; :func:`save_image` does that).

Drawing (painter's algorithm, far to near)
------------------------------------------
A prebuilt background (sky above the horizon, grass below) is copied, then the shoulder band and
the road surface (polygons between samples of the edges, so curves look curved), the dashed lane
markings and solid edge lines, the guard rails (low walls), and finally every car within the draw
distance as a box (visible faces only, shaded per face), farthest first. Every polygon is clipped
at the near plane ``z_c >= near_m`` (Sutherland-Hodgman) before projection, so geometry behind the
camera is never projected through infinity. Known simplification: guard rails are drawn before
all cars, so on a curve a near inner rail never hides a far car (rails are 0.8 m high).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .artifacts import atomic_write
from .config import check_range
from .geometry import Track
from .world import CAR_HEIGHT_M, ParkedCars

_SHIFT = 4  # sub-pixel bits for OpenCV fills
_SCALE = float(1 << _SHIFT)

# colours (RGB)
SKY = (160, 196, 232)
GRASS = (92, 138, 70)
SHOULDER = (120, 120, 118)
ROAD = (78, 78, 84)
MARKING = (236, 236, 236)
RAIL = (190, 190, 196)
CAR_COLOURS = ((200, 40, 40), (40, 90, 200), (230, 190, 40), (235, 235, 235), (60, 60, 60))
EGO_COLOUR = (30, 110, 255)
FACE_SHADE = {"back": 0.72, "front": 0.72, "left": 0.55, "right": 0.55, "top": 1.0}

RAIL_HEIGHT_M = 0.8
MARK_WIDTH_M = 0.15
DASH_M, DASH_PERIOD_M = 3.0, 12.0


@dataclass(frozen=True)
class CameraConfig:
    """The front camera.

    Attributes:
        height_px, width_px: image size (PilotNet's 66 x 200 by default).
        hfov_deg: horizontal field of view [deg]. 50 deg makes a 1.8 m wide car 60 m ahead
            about 6 px wide at 200 px (at 90 deg it would be 3 px).
        mount_height_m: lens height above the road [m].
        forward_offset_m: lens position ahead of the rear axle [m].
        horizon_frac: where the horizon lies, as a fraction of the image height from the top;
            a small value crops the sky.
        near_m: near clipping plane [m].
        draw_distance_m: nothing farther along the road than this is drawn [m].
        augment: draw with seeded appearance variation (see :meth:`Camera.render`); off by default.
        brightness_jitter: +- relative brightness when augmenting.
        tint_jitter: +- relative per-channel tint of road and grass when augmenting.
        height_jitter_m, pitch_jitter_deg: +- camera height [m] and pitch [deg] when augmenting.
    """

    height_px: int = 66
    width_px: int = 200
    hfov_deg: float = 50.0
    mount_height_m: float = 1.4
    forward_offset_m: float = 1.5
    horizon_frac: float = 0.06
    near_m: float = 0.3
    draw_distance_m: float = 100.0
    augment: bool = False
    brightness_jitter: float = 0.15
    tint_jitter: float = 0.08
    height_jitter_m: float = 0.05
    pitch_jitter_deg: float = 0.5

    def __post_init__(self) -> None:
        o = "CameraConfig"
        check_range(o, "height_px", self.height_px, 8, 2048, integer=True)
        check_range(o, "width_px", self.width_px, 8, 4096, integer=True)
        check_range(o, "hfov_deg", self.hfov_deg, 5.0, 150.0)
        check_range(o, "mount_height_m", self.mount_height_m, 0.2, 5.0)
        check_range(o, "forward_offset_m", self.forward_offset_m, -2.0, 5.0)
        check_range(o, "horizon_frac", self.horizon_frac, 0.0, 0.5)
        check_range(o, "near_m", self.near_m, 0.01, 5.0)
        check_range(o, "draw_distance_m", self.draw_distance_m, 10.0, 1000.0)
        check_range(o, "brightness_jitter", self.brightness_jitter, 0.0, 0.9)
        check_range(o, "tint_jitter", self.tint_jitter, 0.0, 0.9)
        check_range(o, "height_jitter_m", self.height_jitter_m, 0.0, 0.5)
        check_range(o, "pitch_jitter_deg", self.pitch_jitter_deg, 0.0, 5.0)

    @classmethod
    def human(cls, **kwargs: float) -> CameraConfig:
        """A larger view for people: 240 x 640, the same optics otherwise."""
        return cls(height_px=240, width_px=640, **kwargs)


class Camera:
    """A pinhole front camera that rasterises a track, its parked cars and guard rails.

    Args:
        cfg: the camera settings.
    """

    def __init__(self, cfg: CameraConfig | None = None) -> None:
        self.cfg = cfg = cfg or CameraConfig()
        self.shape = (cfg.height_px, cfg.width_px, 3)
        self.fx = self.fy = (cfg.width_px / 2.0) / math.tan(math.radians(cfg.hfov_deg) / 2.0)
        self.cx = (cfg.width_px - 1) / 2.0
        self.cy = (cfg.height_px - 1) / 2.0
        horizon_row = cfg.horizon_frac * (cfg.height_px - 1)
        self.pitch = math.atan((self.cy - horizon_row) / self.fy)  # [rad], down is positive
        self.height = cfg.mount_height_m
        # distances along the road at which the edges are sampled: dense near, sparse far
        far = cfg.draw_distance_m
        self._s_offsets = np.unique(np.r_[-4.0, -1.0, 0.0, np.geomspace(1.0, far, 28)])
        self._background = self._make_background(self.pitch, SKY, GRASS)

    # -------------------------------------------------------------- geometry
    def horizon_row(self, pitch: float | None = None) -> float:
        """Image row of the horizon (may be fractional or negative)."""
        return self.cy - self.fy * math.tan(self.pitch if pitch is None else pitch)

    def _make_background(self, pitch: float, sky: tuple, grass: tuple) -> np.ndarray:
        img = np.empty(self.shape, dtype=np.uint8)
        img[:] = grass
        row = self.horizon_row(pitch)
        top = int(np.clip(math.floor(row + 0.5), 0, self.shape[0]))
        img[:top] = sky
        return img

    def car_to_camera(self, pts_car: np.ndarray) -> np.ndarray:
        """Car-frame points ``(..., 3)`` (x fwd, y left, z up; rear-axle origin) to the camera frame."""
        rot, t = self.world_to_camera_matrix((0.0, 0.0, 0.0))
        return pts_car @ rot.T + t

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` with ``z > 0`` to pixel coordinates ``(..., 2)`` (col, row)."""
        z = pts_cam[..., 2]
        return np.stack(
            [self.cx + self.fx * pts_cam[..., 0] / z, self.cy + self.fy * pts_cam[..., 1] / z],
            axis=-1,
        )

    def project_car(self, pts_car: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Car-frame points to pixels; also a mask of the points in front of the near plane."""
        cam = self.car_to_camera(np.asarray(pts_car, dtype=np.float64))
        front = cam[..., 2] >= self.cfg.near_m
        z = np.where(front, cam[..., 2], 1.0)
        return self.project(np.concatenate([cam[..., :2], z[..., None]], axis=-1)), front

    def world_to_camera_matrix(
        self,
        pose: tuple[float, float, float],
        height: float | None = None,
        pitch: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` with ``p_cam = R @ p_world + t`` for a car at ``pose = (x, y, heading)``.

        The rows of ``R`` are the camera's right, down and optical axes in world coordinates.
        """
        h = self.height if height is None else height
        th = self.pitch if pitch is None else pitch
        x0, y0, hd = pose
        c, s = math.cos(hd), math.sin(hd)
        ct, st = math.cos(th), math.sin(th)
        rot = np.array([[s, -c, 0.0], [-st * c, -st * s, -ct], [ct * c, ct * s, -st]])
        lens = np.array([x0 + self.cfg.forward_offset_m * c, y0 + self.cfg.forward_offset_m * s, h])
        return rot, -rot @ lens

    # -------------------------------------------------------------- drawing
    def render(
        self,
        track: Track,
        cars: ParkedCars | None,
        pose: tuple[float, float, float],
        s: float | None = None,
        rng: np.random.Generator | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Draw the view from a car at ``pose = (x, y, heading)`` (rear axle) [m, m, rad].

        Args:
            track, cars: the scene.
            pose: the car's pose.
            s: the car's arc length on the track, if known (saves a lookup) [m].
            rng: required when ``cfg.augment``: draws brightness, road/grass tint and camera
                height/pitch jitter for this frame.
            out: an array of shape ``self.shape`` to draw into (saves an allocation).

        Returns:
            The RGB ``uint8`` image, shape ``(height_px, width_px, 3)``.
        """
        cfg = self.cfg
        height, pitch = self.height, self.pitch
        road_col, bright = ROAD, 1.0
        if cfg.augment:
            if rng is None:
                raise ValueError("Camera.render: rng is required when CameraConfig.augment is on")
            height += rng.uniform(-cfg.height_jitter_m, cfg.height_jitter_m)
            pitch += math.radians(rng.uniform(-cfg.pitch_jitter_deg, cfg.pitch_jitter_deg))
            tint = 1.0 + rng.uniform(-cfg.tint_jitter, cfg.tint_jitter, 6)
            road_col = tuple(int(min(255, c * t)) for c, t in zip(ROAD, tint[:3]))
            grass_col = tuple(int(min(255, c * t)) for c, t in zip(GRASS, tint[3:]))
            bright = 1.0 + rng.uniform(-cfg.brightness_jitter, cfg.brightness_jitter)
        img = np.empty(self.shape, dtype=np.uint8) if out is None else out
        if cfg.augment:
            np.copyto(img, self._make_background(pitch, SKY, grass_col))
        else:
            np.copyto(img, self._background)
        if s is None:
            s = float(track.to_frenet(pose[0], pose[1])[0])
        rot, t = self.world_to_camera_matrix(pose, height, pitch)
        s_lens = s + cfg.forward_offset_m
        s_pts = np.maximum(s_lens + self._s_offsets, 0.0)
        n = len(s_pts)
        # --- every ground point in one lane-frame lookup: 6 band lines, then the dash corners
        hw, rd = track.half_width, track.rail_d
        d_lines = np.array([-rd, rd, -hw, hw, hw - MARK_WIDTH_M, -hw + MARK_WIDTH_M])
        first = math.floor(s_pts[0] / DASH_PERIOD_M) * DASH_PERIOD_M
        starts = np.arange(first, s_pts[-1], DASH_PERIOD_M)
        n_div = track.n_lanes - 1
        d_div = np.asarray(track.lane_center(np.arange(1, track.n_lanes))) - track.lane_width / 2
        dash_s = np.stack([starts, starts + DASH_M, starts + DASH_M, starts], -1)  # (D, 4)
        dash_d = np.array([-1.0, -1.0, 1.0, 1.0]) * (MARK_WIDTH_M / 2)
        n_dash = dash_s.size
        all_s = np.empty(6 * n + n_div * n_dash)
        all_s[: 6 * n].reshape(6, n)[:] = s_pts
        all_s[6 * n :].reshape(n_div, n_dash)[:] = dash_s.ravel()
        all_d = np.empty_like(all_s)
        all_d[: 6 * n].reshape(6, n)[:] = d_lines[:, None]
        all_d[6 * n :].reshape(n_div, -1, 4)[:] = d_div[:, None, None] + dash_d
        xy = track.position(all_s, all_d)  # (6n + 4 D n_div, 2)
        cam = xy @ rot[:, :2].T + t  # ground points in the camera frame
        lines = cam[: 6 * n].reshape(6, n, 3)
        # rail tops: the rail lines lifted by RAIL_HEIGHT_M (a world z offset is R[:, 2] * dz)
        tops = lines[:2] + rot[:, 2] * RAIL_HEIGHT_M
        polys = _clip_strips(
            np.concatenate([lines, tops]),
            cfg.near_m,
            [(0, 1), (2, 3), (3, 4), (5, 2), (0, 6), (1, 7)],
        )
        shoulder, road, edge_l, edge_r, wall_r, wall_l = polys
        dashes = cam[6 * n :].reshape(-1, 4, 3)
        dash_z = dashes[:, :, 2]
        dash_list = list(dashes[dash_z.min(axis=1) >= cfg.near_m])
        for k in np.flatnonzero(
            (dash_z.min(axis=1) < cfg.near_m) & (dash_z.max(axis=1) >= cfg.near_m)
        ):
            dash_list.append(clip_near(dashes[k], cfg.near_m))  # straddles the near plane: cut
        groups = [
            ([shoulder], SHOULDER),
            ([road], road_col),
            ([edge_l, edge_r, *dash_list], MARKING),
            ([wall_r, wall_l], RAIL),
        ]
        self._fill_groups(img, groups)
        # --- parked cars, farthest first
        if cars is not None and len(cars):
            sl = cars.between(s_lens - 12.0, s_lens + cfg.draw_distance_m)
            if sl.stop > sl.start:
                self._draw_cars(img, cars, sl, pose, rot, t)
        if bright != 1.0:
            cv2.convertScaleAbs(img, dst=img, alpha=bright)
        return img

    def _fill_groups(self, img: np.ndarray, groups: list[tuple[list, tuple]]) -> None:
        """Project polygons already clipped at the near plane (``None`` entries are skipped) in one
        go, and fill each group with its colour in one call."""
        flat, spans = [], []
        for polys, colour in groups:
            kept = [p for p in polys if p is not None]
            spans.append((len(flat), len(flat) + len(kept), colour))
            flat.extend(kept)
        if not flat:
            return
        px = np.round(self.project(np.concatenate(flat)) * _SCALE).astype(np.int32)
        ends = np.cumsum([len(p) for p in flat]).tolist()
        pieces = [px[a:b] for a, b in zip([0, *ends[:-1]], ends)]
        for a, b, colour in spans:
            if b > a:
                cv2.fillPoly(img, pieces[a:b], colour, cv2.LINE_AA, _SHIFT)

    def _draw_cars(
        self,
        img: np.ndarray,
        cars: ParkedCars,
        sl: slice,
        pose: tuple[float, float, float],
        rot: np.ndarray,
        t: np.ndarray,
    ) -> None:
        x, y, h = cars.x[sl], cars.y[sl], cars.heading[sl]
        hl, hw = cars.length_m / 2, cars.width_m / 2
        cam = cars.box_corners_3d[sl] @ rot.T + t  # (C, 8, 3)
        c, s = np.cos(h)[:, None], np.sin(h)[:, None]
        # which faces point at the camera: the lens relative to each car, in the car's frame
        lens_x = pose[0] + self.cfg.forward_offset_m * math.cos(pose[2])
        lens_y = pose[1] + self.cfg.forward_offset_m * math.sin(pose[2])
        rel_x, rel_y = lens_x - x, lens_y - y
        along = rel_x * c[:, 0] + rel_y * s[:, 0]  # lens ahead (+) / behind (-) of the car's centre
        across = -rel_x * s[:, 0] + rel_y * c[:, 0]  # lens left (+) / right (-)
        seen = np.stack(
            [
                along < -hl,
                along > hl,
                across < -hw,
                across > hw,
                np.full(len(x), self.height > CAR_HEIGHT_M),
            ],
            -1,
        )  # (C, 5)
        depth = cam[:, :, 2]
        near = self.cfg.near_m
        in_front = depth.min(axis=1) >= near
        px = np.round(self.project(np.where(in_front[:, None, None], cam, 1.0)) * _SCALE).astype(
            np.int32
        )
        for k in np.argsort(-depth.mean(axis=1)).tolist():
            if depth[k].max() < near:
                continue  # wholly behind the camera
            colours = _FACE_COLOURS[(sl.start + k) % len(CAR_COLOURS)]
            for f in np.flatnonzero(seen[k]).tolist():
                if in_front[k]:
                    pts = px[k, _FACES[f]]
                else:  # straddles the near plane: cut the face first
                    poly = clip_near(cam[k, _FACES[f]], near)
                    if poly is None:
                        continue
                    pts = np.round(self.project(poly) * _SCALE).astype(np.int32)
                cv2.fillConvexPoly(img, pts, colours[f], cv2.LINE_AA, _SHIFT)


# faces of ParkedCars.box_corners_3d, in the order of the visibility tests: back, front, right, left, top
_FACES = ([0, 3, 7, 4], [1, 5, 6, 2], [0, 4, 5, 1], [3, 2, 6, 7], [4, 5, 6, 7])
_FACE_COLOURS = tuple(
    tuple(
        tuple(int(ch * FACE_SHADE[f]) for ch in base)
        for f in ("back", "front", "right", "left", "top")
    )
    for base in CAR_COLOURS
)


def _clip_strips(lines: np.ndarray, near: float, pairs: list[tuple[int, int]]) -> list:
    """Polygons ``[line a forward, line b backward]`` for each pair, clipped at ``z >= near``.

    ``lines`` is ``(P, n, 3)``: P polylines sampled at the same arc lengths. When every line's
    depth grows along it (the car faces roughly along the road), each line is cut once at the
    near plane, vectorised, which equals Sutherland-Hodgman on the strip; otherwise each strip
    falls back to :func:`clip_near`. A strip wholly behind the camera gives ``None``.
    """
    z = lines[:, :, 2]
    if not np.all(np.diff(z, axis=1) > 0):
        out = []
        for a, b in pairs:
            out.append(clip_near(np.concatenate([lines[a], lines[b, ::-1]]), near))
        return out
    n = z.shape[1]
    first = np.argmax(z >= near, axis=1)  # first sample in front (0 if none: checked below)
    behind = ~np.any(z >= near, axis=1)
    prev = np.maximum(first - 1, 0)
    rows = np.arange(len(lines))
    za, zb = z[rows, prev], z[rows, first]
    frac = np.where(first > 0, (near - za) / np.where(zb > za, zb - za, 1.0), 0.0)
    cut = lines[rows, prev] + frac[:, None] * (lines[rows, first] - lines[rows, prev])
    out = []
    for a, b in pairs:
        if behind[a] or behind[b]:
            out.append(None)
            continue
        fa, fb = int(first[a]), int(first[b])
        line_a = lines[a, fa:] if fa == 0 else np.concatenate([cut[a : a + 1], lines[a, fa:]])
        line_b = lines[b, fb:] if fb == 0 else np.concatenate([cut[b : b + 1], lines[b, fb:]])
        out.append(np.concatenate([line_a, line_b[::-1]]) if n else None)
    return out


def clip_near(poly: np.ndarray, near: float) -> np.ndarray | None:
    """Sutherland-Hodgman clip of a camera-frame polygon ``(N, 3)`` to the half-space ``z >= near``.

    Returns the clipped polygon, or ``None`` when nothing is in front. For each edge ``i -> i+1``:
    keep vertex ``i`` if it is inside, and add the edge's crossing point if the edge crosses.
    """
    z = poly[:, 2]
    inside = z >= near
    if inside.all():
        return poly
    if not inside.any():
        return None
    n = len(poly)
    i = np.flatnonzero(inside != np.roll(inside, -1))  # edges i -> i+1 that cross
    j = (i + 1) % n
    frac = (near - z[i]) / (z[j] - z[i])
    crossing = poly[i] + frac[:, None] * (poly[j] - poly[i])
    crossing[:, 2] = near
    # each crossing goes right after the inside vertices up to and including vertex i
    out = np.insert(poly[inside], np.cumsum(inside)[i], crossing, axis=0)
    return out if len(out) >= 3 else None


def draw_trajectory(
    image: np.ndarray,
    points_car: np.ndarray,
    camera: Camera,
    colour: tuple[int, int, int] = (255, 40, 40),
    radius_px: int | None = None,
    thickness_px: int | None = None,
    label: str | None = None,
) -> np.ndarray:
    """Draw a car-frame trajectory ``(K, 2)`` (x forward, y left; metres) on a camera image.

    Points are projected on the road surface; points behind the near plane are skipped. The
    polyline starts at the road point below the camera's near plane. Draws in place; returns it.
    """
    pts = np.asarray(points_car, dtype=np.float64).reshape(-1, 2)
    start = np.array([[camera.cfg.forward_offset_m + camera.cfg.near_m * 4, 0.0]])
    ground = np.concatenate([np.r_[start, pts], np.zeros((len(pts) + 1, 1))], axis=1)
    px, front = camera.project_car(ground)
    scale = max(1, round(image.shape[1] / 200))
    radius = radius_px if radius_px is not None else 1 + scale
    thick = thickness_px if thickness_px is not None else scale
    fixed = np.round(px[front] * _SCALE).astype(np.int32)
    if len(fixed) >= 2:
        cv2.polylines(image, [fixed], False, colour, thick, cv2.LINE_AA, _SHIFT)
    for p in fixed[1:] if front[0] else fixed:
        cv2.circle(
            image, (int(p[0]), int(p[1])), radius * int(_SCALE), colour, -1, cv2.LINE_AA, _SHIFT
        )
    if label and len(fixed):
        tip = fixed[-1] / _SCALE
        cv2.putText(
            image,
            label,
            (int(tip[0]) + 3, int(tip[1])),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.3 * scale,
            colour,
            1,
            cv2.LINE_AA,
        )
    return image


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
    ego_length_m: float = 4.5,
    ego_width_m: float = 1.8,
    ego_rear_overhang_m: float = 0.9,
) -> np.ndarray:
    """An ego-centred bird's-eye RGB view: road, lanes, rails, parked cars, the ego, a trajectory.

    Args:
        track, cars: the scene.
        pose: the ego's rear-axle pose ``(x, y, heading)`` [m, m, rad]; heading points up.
        cfg: size and scale.
        trajectory: optional car-frame points ``(K, 2)`` [m] drawn as dots joined by a line.
        ego_length_m, ego_width_m, ego_rear_overhang_m: the ego's box [m].
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
        return _car_to_topdown(np.stack([fwd, left], -1), row0, col0, cfg.m_per_px)

    s_ego = float(track.to_frenet(pose[0], pose[1])[0])
    reach_back = (rows - row0) * cfg.m_per_px + 5
    reach_fwd = row0 * cfg.m_per_px + 5
    s_pts = np.linspace(max(0.0, s_ego - reach_back), s_ego + reach_fwd, 60)

    def band(d0: float, d1: float) -> np.ndarray:
        return np.concatenate(
            [to_px(track.position(s_pts, d0)), to_px(track.position(s_pts[::-1], d1))]
        )

    def fill(polys: list[np.ndarray], colour: tuple) -> None:
        cv2.fillPoly(
            img, [np.round(p * _SCALE).astype(np.int32) for p in polys], colour, cv2.LINE_AA, _SHIFT
        )

    hw, rd = track.half_width, track.rail_d
    fill([band(-rd, rd)], SHOULDER)
    fill([band(-hw, hw)], ROAD)
    fill([band(hw - MARK_WIDTH_M, hw), band(-hw, -hw + MARK_WIDTH_M)], MARKING)
    fill([band(rd, rd + 0.3), band(-rd - 0.3, -rd)], RAIL)
    for lane in range(1, track.n_lanes):
        d = float(track.lane_center(lane)) - track.lane_width / 2
        first = math.floor(s_pts[0] / DASH_PERIOD_M) * DASH_PERIOD_M
        dashes = []
        for st in np.arange(first, s_pts[-1], DASH_PERIOD_M):
            ss = np.array([st, st + DASH_M, st + DASH_M, st])
            dd = d + np.array([-1, -1, 1, 1]) * MARK_WIDTH_M / 2
            dashes.append(to_px(track.position(ss, dd)))
        if dashes:
            fill(dashes, MARKING)
    if cars is not None and len(cars):
        sl = cars.between(s_pts[0] - 5, s_pts[-1] + 5)
        boxes = cars.corners()[sl]
        for k, box in enumerate(boxes):
            fill([to_px(box)], CAR_COLOURS[(sl.start + k) % len(CAR_COLOURS)])
    r, f, w = -ego_rear_overhang_m, ego_length_m - ego_rear_overhang_m, ego_width_m / 2
    ego = np.array([[r, -w], [f, -w], [f, w], [r, w]])
    fill([_car_to_topdown(ego, row0, col0, cfg.m_per_px)], EGO_COLOUR)
    if trajectory is not None:
        pts = np.round(
            _car_to_topdown(np.r_[[[0.0, 0.0]], np.asarray(trajectory)], row0, col0, cfg.m_per_px)
            * _SCALE
        ).astype(np.int32)
        cv2.polylines(img, [pts], False, (255, 40, 40), 1, cv2.LINE_AA, _SHIFT)
        for p in pts[1:]:
            cv2.circle(
                img, (int(p[0]), int(p[1])), 2 * int(_SCALE), (255, 40, 40), -1, cv2.LINE_AA, _SHIFT
            )
    return img


def _car_to_topdown(fwd_left: np.ndarray, row0: float, col0: float, m_per_px: float) -> np.ndarray:
    """Car-frame (forward, left) [m] to top-down pixels (col, row)."""
    return np.stack([col0 - fwd_left[..., 1] / m_per_px, row0 - fwd_left[..., 0] / m_per_px], -1)


def save_image(path: Path | str, rgb: np.ndarray) -> Path:
    """Write an RGB image as PNG (OpenCV wants BGR), atomically. Returns the path."""
    path = Path(path)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise OSError(f"could not encode {path}")
    with atomic_write(path) as f:
        f.write(buf.tobytes())
    return path
