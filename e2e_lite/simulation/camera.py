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
camera is never projected through infinity. Known simplifications: guard rails are drawn before
all cars, so on a curve a near inner rail never hides a far car (rails are 0.8 m high); and the
road is sampled along its own direction, from 4 m behind the lens's arc length to the draw
distance, so a car turned more than about 90 degrees from the road sees little of it (the
simulation never drives backwards).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..config import check_range
from .geometry import Track, positions_on
from .raster import (
    CAR_COLOURS,
    DASH_D,
    DASH_PERIOD_M,
    DASH_S,
    FACE_COLOURS,
    FACE_INDEX,
    FACES,
    GRASS,
    MARK_WIDTH_M,
    RAIL_HEIGHT_M,
    ROAD,
    SKY,
    STRIPS,
    clip_near,
    clip_strips,
    paint,
    strip_line,
    to_fixed,
)
from .world import CAR_HEIGHT_M, ParkedCars


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
        # inward normals of the view's side planes through the lens: a camera-frame point p is
        # inside when n . p >= 0 for each (left, right, top, bottom edges of the pixel grid)
        w, hgt = cfg.width_px, cfg.height_px
        self._frustum = np.array(
            [
                [self.fx, 0.0, self.cx + 0.5],
                [-self.fx, 0.0, w - 0.5 - self.cx],
                [0.0, self.fy, self.cy + 0.5],
                [0.0, -self.fy, hgt - 0.5 - self.cy],
            ]
        )
        # dashes per divider that cover the sampled window from the period boundary before it
        span = self._s_offsets[-1] - self._s_offsets[0]
        self._n_dashes = math.ceil(span / DASH_PERIOD_M) + 2

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
        rot, t = self._matrices(
            np.array([pose], dtype=np.float64),
            np.array([self.height if height is None else height]),
            np.array([self.pitch if pitch is None else pitch]),
        )
        return rot[0], t[0]

    def _matrices(
        self, poses: np.ndarray, heights: np.ndarray, pitches: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World-to-camera rotations (B, 3, 3) and offsets (B, 3) for poses (B, 3)."""
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        ct, st = np.cos(pitches), np.sin(pitches)
        zero = np.zeros_like(c)
        rot = np.stack(
            [
                np.stack([s, -c, zero], -1),
                np.stack([-st * c, -st * s, -ct], -1),
                np.stack([ct * c, ct * s, -st], -1),
            ],
            axis=1,
        )
        off = self.cfg.forward_offset_m
        lens = np.stack([poses[:, 0] + off * c, poses[:, 1] + off * s, heights], -1)
        return rot, -np.einsum("bij,bj->bi", rot, lens)

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
        batch = None if out is None else out[None]
        return self.render_batch(
            [track],
            [cars],
            np.array([pose], dtype=np.float64),
            None if s is None else np.array([s]),
            rng=rng,
            out=batch,
        )[0]

    def render_batch(
        self,
        tracks: list[Track],
        cars: list[ParkedCars | None],
        poses: np.ndarray,
        s: np.ndarray | None = None,
        rng: np.random.Generator | Sequence[np.random.Generator] | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Draw B views at once (the evaluator's and the data collector's way): (B, H, W, 3) RGB.

        Frame ``b`` shows ``tracks[b]`` and ``cars[b]`` from a car at ``poses[b] = (x, y, heading)``
        (rear axle), with arc length ``s[b]`` if given. The geometry of all frames is computed in
        a few array operations; only the polygon fills are per frame. ``rng`` as in :meth:`render`
        (one generator draws for every frame, in order; or one generator per frame, as the
        evaluator gives each car its own).
        """
        cfg = self.cfg
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        n_frames = len(poses)
        if out is None:
            out = np.empty((n_frames, *self.shape), dtype=np.uint8)
        if s is None:
            s = np.array([float(t.to_frenet(p[0], p[1])[0]) for t, p in zip(tracks, poses)])
        looks = self._looks(out, rng)  # the background drawn, each frame's jitter
        rot, t = self._matrices(poses, looks.heights, looks.pitches)
        s_lens = np.asarray(s, dtype=np.float64) + cfg.forward_offset_m
        s_pts = np.maximum(s_lens[:, None] + self._s_offsets, 0.0)  # (B, n)
        n = s_pts.shape[1]
        all_s, all_d = self._ground_points(tracks[0], s_pts)
        xy = positions_on(tracks, all_s, all_d)  # (B, P, 2)
        cam = xy @ rot[:, :, :2].transpose(0, 2, 1) + t[:, None, :]  # (B, P, 3)
        lines = cam[:, : 6 * n].reshape(n_frames, 6, n, 3)
        tops = lines[:, :2] + (rot[:, :, 2] * RAIL_HEIGHT_M)[:, None, None, :]  # rails' top edges
        strips, ok = clip_strips(np.concatenate([lines, tops], axis=1), cfg.near_m)
        strip_px = to_fixed(self.project(strips))  # (B, 6, 2n, 2)
        dashes = cam[:, 6 * n :].reshape(n_frames, -1, 4, 3)
        dz = dashes[..., 2]
        dash_front = dz.min(axis=-1) >= cfg.near_m
        dash_px = to_fixed(self.project(np.where(dash_front[..., None, None], dashes, 1.0)))
        straddle = ~dash_front & (dz.max(axis=-1) >= cfg.near_m)
        car_faces = self._car_faces(cars, poses, s_lens, looks.heights, rot, t)
        for b in range(n_frames):
            if ok[b]:
                polys = list(strip_px[b])
            else:  # a line that does not cross the near plane once (car turned across the road)
                polys = [self._strip_polygon(lines, tops, b, a, c) for a, c in STRIPS]
            marks = [p for p in polys[2:4] if p is not None] + list(dash_px[b][dash_front[b]])
            for k in np.flatnonzero(straddle[b]).tolist():  # the dash under the lens: cut it
                poly = clip_near(dashes[b, k], cfg.near_m)
                if poly is not None:
                    marks.append(to_fixed(self.project(poly)))
            paint(out[b], polys, looks.road_colours[b], marks, car_faces[b], looks.brightness[b])
        return out

    def _looks(
        self, out: np.ndarray, rng: np.random.Generator | Sequence[np.random.Generator] | None
    ) -> _Looks:
        """Each frame's camera height, pitch, road colour and brightness, and its background
        drawn into ``out``: the mounted camera's, or with ``cfg.augment`` each jittered from
        ``rng`` (one generator for every frame, in order, or one per frame)."""
        cfg, n_frames = self.cfg, len(out)
        looks = _Looks(
            heights=np.full(n_frames, self.height),
            pitches=np.full(n_frames, self.pitch),
            road_colours=[ROAD] * n_frames,
            brightness=[1.0] * n_frames,
        )
        if not cfg.augment:
            out[:] = self._background
            return looks
        if rng is None:
            raise ValueError("Camera.render: rng is required when CameraConfig.augment is on")
        for b in range(n_frames):
            rng_b = rng[b] if isinstance(rng, Sequence) else rng  # (one per frame, or shared)
            looks.heights[b] += rng_b.uniform(-cfg.height_jitter_m, cfg.height_jitter_m)
            looks.pitches[b] += math.radians(
                rng_b.uniform(-cfg.pitch_jitter_deg, cfg.pitch_jitter_deg)
            )
            tint = 1.0 + rng_b.uniform(-cfg.tint_jitter, cfg.tint_jitter, 6)
            looks.road_colours[b] = tuple(int(min(255, c * t)) for c, t in zip(ROAD, tint[:3]))
            grass = tuple(int(min(255, c * t)) for c, t in zip(GRASS, tint[3:]))
            looks.brightness[b] = 1.0 + rng_b.uniform(-cfg.brightness_jitter, cfg.brightness_jitter)
            np.copyto(out[b], self._make_background(looks.pitches[b], SKY, grass))
        return looks

    def _ground_points(self, track: Track, s_pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every ground point of every frame, as arc lengths ``(B, P)`` and offsets ``(P,)`` [m]:
        the 6 lines along the road (rails, edges, edge markings) at ``s_pts``, then the corners
        of the dashes between the lanes. Every track shares ``track``'s cross-section (one
        ``RoadConfig`` per evaluation)."""
        n_frames, n = s_pts.shape
        hw, rd = track.half_width, track.rail_d
        d_lines = np.array([-rd, rd, -hw, hw, hw - MARK_WIDTH_M, -hw + MARK_WIDTH_M])
        n_div = track.n_lanes - 1
        d_div = np.asarray(track.lane_center(np.arange(1, track.n_lanes))) - track.lane_width / 2
        first = np.floor(s_pts[:, :1] / DASH_PERIOD_M) * DASH_PERIOD_M
        starts = first + DASH_PERIOD_M * np.arange(self._n_dashes)  # (B, D)
        dash_s = (starts[:, :, None] + DASH_S).reshape(n_frames, 1, -1)  # (B, 1, 4D)
        along = np.repeat(s_pts, 6, axis=0).reshape(n_frames, 6 * n)
        all_s = np.concatenate([along, np.repeat(dash_s, n_div, axis=1).reshape(n_frames, -1)], 1)
        dash_d = (d_div[:, None] + np.tile(DASH_D, self._n_dashes)).ravel()
        return all_s, np.concatenate([np.repeat(d_lines, n), dash_d])

    def _strip_polygon(
        self, lines: np.ndarray, tops: np.ndarray, b: int, a: int, c: int
    ) -> np.ndarray | None:
        """Frame ``b``'s band between lines ``a`` and ``c``, clipped at the near plane one
        polygon at a time (None: wholly behind it)."""
        both = np.concatenate([strip_line(lines, tops, b, a), strip_line(lines, tops, b, c)[::-1]])
        poly = clip_near(both, self.cfg.near_m)
        return None if poly is None else to_fixed(self.project(poly))

    def _car_faces(
        self,
        cars: list[ParkedCars | None],
        poses: np.ndarray,
        s_lens: np.ndarray,
        heights: np.ndarray,
        rot: np.ndarray,
        t: np.ndarray,
    ) -> list[list[tuple]]:
        """Per frame, the ``(pixels, colour)`` of every visible car face, farthest car first.

        The geometry of every car of every frame is computed together: corners in camera frames,
        which faces point at the lens, frustum culling, projection. Faces of a car straddling the
        near plane are clipped one by one.
        """
        n_frames = len(poses)
        faces: list[list[tuple]] = [[] for _ in range(n_frames)]
        sls = [
            c.between(sl - 12.0, sl + self.cfg.draw_distance_m)
            if c is not None and len(c)
            else slice(0, 0)
            for c, sl in zip(cars, s_lens)
        ]
        counts = np.array([sl.stop - sl.start for sl in sls])
        if counts.sum() == 0:
            return faces
        live = [b for b in range(n_frames) if counts[b]]
        corners = np.concatenate([cars[b].box_corners_3d[sls[b]] for b in live])  # (C, 8, 3)
        x = np.concatenate([cars[b].x[sls[b]] for b in live])
        y = np.concatenate([cars[b].y[sls[b]] for b in live])
        h = np.concatenate([cars[b].heading[sls[b]] for b in live])
        ids = np.concatenate([np.arange(sls[b].start, sls[b].stop) for b in live])
        frame = np.repeat(np.arange(n_frames), counts)
        cam = corners @ rot[frame].transpose(0, 2, 1) + t[frame][:, None, :]  # (C, 8, 3)
        # which faces point at the lens: the lens relative to each car, in the car's frame
        off = self.cfg.forward_offset_m
        rel_x = poses[frame, 0] + off * np.cos(poses[frame, 2]) - x
        rel_y = poses[frame, 1] + off * np.sin(poses[frame, 2]) - y
        c, s = np.cos(h), np.sin(h)
        along = rel_x * c + rel_y * s  # lens ahead (+) / behind (-) of the car's centre
        across = -rel_x * s + rel_y * c  # lens left (+) / right (-)
        hl = np.array([cars[b].length_m for b in live]).repeat(counts[live]) / 2
        hw = np.array([cars[b].width_m for b in live]).repeat(counts[live]) / 2
        seen = np.stack(
            [along < -hl, along > hl, across < -hw, across > hw, heights[frame] > CAR_HEIGHT_M], -1
        )  # (C, 5)
        depth = cam[:, :, 2]
        near = self.cfg.near_m
        in_front = depth.min(axis=1) >= near
        px = self.project(np.where(in_front[:, None, None], cam, 1.0))
        face_px = to_fixed(px[:, FACE_INDEX])  # (C, 5, 4, 2)
        # frustum culling: a box wholly outside one side plane of the view (a half-space test
        # that holds for corners behind the lens too) or wholly behind the near plane is skipped
        drawn = (depth.max(axis=1) >= near) & ~np.any(
            np.all(cam @ self._frustum.T < 0.0, axis=1), axis=1
        )
        order = np.lexsort((-depth.mean(axis=1), frame))  # by frame, farthest first
        seen_l, front_l, frame_l, ids_l = (
            seen.tolist(),
            in_front.tolist(),
            frame.tolist(),
            ids.tolist(),
        )
        for k in order[drawn[order]].tolist():
            colours = FACE_COLOURS[ids_l[k] % len(CAR_COLOURS)]
            out = faces[frame_l[k]]
            for f in range(5):
                if not seen_l[k][f]:
                    continue
                if front_l[k]:
                    out.append((face_px[k, f], colours[f]))
                else:  # straddles the near plane: cut the face first
                    poly = clip_near(cam[k, FACES[f]], near)
                    if poly is not None:
                        out.append((to_fixed(self.project(poly)), colours[f]))
        return faces


@dataclass
class _Looks:
    """Each frame's camera height [m] and pitch [rad], road colour (RGB) and brightness gain."""

    heights: np.ndarray
    pitches: np.ndarray
    road_colours: list[tuple[int, int, int]]
    brightness: list[float]
