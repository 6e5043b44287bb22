"""Road geometry: procedural multi-lane tracks and the lane (Frenet) frame.

A track is a chain of straight segments and circular arcs joined with continuous heading. Its
reference line is the road's centre line; a point is named by ``(s, d)``: arc length ``s`` along
the reference line [m] and signed lateral offset ``d`` [m], positive to the **left**.

Lanes are numbered from the right: lane 0 is the rightmost, lane ``n_lanes - 1`` the leftmost.
Lane ``i`` has its centre at ``d = (i - (n_lanes - 1) / 2) * lane_width``. The road edges are
at ``d = +-half_width`` and the guard rails a shoulder further out.

Everything else (world, camera, expert, tracker, affordance labels) asks this module where things
are: ``position(s, d)``, ``to_frenet(x, y)``, ``heading(s)``, ``curvature(s)``, ``lane_center(i)``,
``lane_index(d)``. All of it is analytic per segment (no nearest-point search over samples).

Per segment, with start point ``p0``, start heading ``h0``, curvature ``k`` (1/m, positive for a
left turn) and local arc length ``u``::

    h(u) = h0 + k u
    p(u) = p0 + ((sin h - sin h0) / k, (cos h0 - cos h) / k)       (-> p0 + u (cos h0, sin h0) as k -> 0)
    point at (u, d) = p(u) + d n(h),   n(h) = (-sin h, cos h)        (left normal)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import check_pair, check_range

SPLITS = {"train": 1, "val": 2, "test": 3}
_STRAIGHT_EPS = 1e-12  # |curvature| below this is a straight [1/m]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles [rad] wrapped to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class RoadConfig:
    """Settings of the procedural road.

    Attributes:
        n_lanes: number of lanes (>= 2, so there is a lane to overtake in).
        lane_width_m: lane width [m].
        shoulder_m: distance from the road edge to the guard rail [m].
        length_m: track length [m].
        first_straight_m: length of the opening straight (where cars spawn) [m].
        straight_m: (min, max) length of the other straights [m].
        radius_m: (min, max) arc radius of the centre line [m].
        arc_deg: (min, max) heading change of one arc [deg].
        max_heading_deg: the generator keeps the heading within +-this of the start heading, so a
            track never turns back on itself [deg].
        seed: root seed; track ``(split, index)`` uses ``numpy.random.default_rng([seed, split, index])``.
    """

    n_lanes: int = 3
    lane_width_m: float = 3.7
    shoulder_m: float = 2.5
    length_m: float = 8_000.0
    first_straight_m: float = 300.0
    straight_m: tuple[float, float] = (300.0, 1_200.0)
    radius_m: tuple[float, float] = (200.0, 900.0)
    arc_deg: tuple[float, float] = (10.0, 50.0)
    max_heading_deg: float = 60.0
    seed: int = 0

    def __post_init__(self) -> None:
        o = "RoadConfig"
        check_range(o, "n_lanes", self.n_lanes, 2, 8, integer=True)
        check_range(o, "lane_width_m", self.lane_width_m, 0.0, 10.0, lo_open=True)
        check_range(o, "shoulder_m", self.shoulder_m, 0.0, 20.0)
        check_range(o, "length_m", self.length_m, 200.0, 1e6)
        check_range(o, "first_straight_m", self.first_straight_m, 0.0, self.length_m)
        check_pair(o, "straight_m", self.straight_m, lo=1.0)
        check_pair(o, "radius_m", self.radius_m, lo=self.n_lanes * self.lane_width_m + 10.0)
        check_pair(o, "arc_deg", self.arc_deg, lo=0.0)
        check_range(o, "max_heading_deg", self.max_heading_deg, 0.0, 89.0)
        if self.arc_deg[1] > self.max_heading_deg:
            raise ValueError(
                f"RoadConfig.arc_deg={self.arc_deg!r} is invalid: the largest arc must be <= "
                f"max_heading_deg={self.max_heading_deg:g}"
            )
        check_range(o, "seed", self.seed, 0, integer=True)

    def lane_centers(self) -> np.ndarray:
        """Lateral offset ``d`` of every lane's centre, lane 0 (the rightmost) first [m]."""
        return lane_center(np.arange(self.n_lanes), self.n_lanes, self.lane_width_m)


def lane_center(lane: int | np.ndarray, n_lanes: int, lane_width_m: float) -> float | np.ndarray:
    """Lateral offset ``d`` of the centre of lane ``lane`` (0 = rightmost) on a road of
    ``n_lanes`` lanes ``lane_width_m`` wide [m]."""
    return (np.asarray(lane) - (n_lanes - 1) / 2.0) * lane_width_m + 0.0


class Track:
    """A road made of straight and arc segments, with lanes, edges and guard rails.

    Args:
        x0, y0, h0: start point [m] and heading [rad] of each segment, shape (M,).
        k: curvature of each segment [1/m], 0 for straights, positive turning left, shape (M,).
        seg_len: length of each segment [m], shape (M,).
        n_lanes, lane_width_m, shoulder_m: the cross-section (see :class:`RoadConfig`).
        track_id: a name for the track, e.g. ``("val", 3)``.
    """

    def __init__(
        self,
        x0: np.ndarray,
        y0: np.ndarray,
        h0: np.ndarray,
        k: np.ndarray,
        seg_len: np.ndarray,
        n_lanes: int = 3,
        lane_width_m: float = 3.7,
        shoulder_m: float = 2.5,
        track_id: tuple[str, int] = ("custom", 0),
    ) -> None:
        self.x0 = np.asarray(x0, dtype=np.float64)
        self.y0 = np.asarray(y0, dtype=np.float64)
        self.h0 = np.asarray(h0, dtype=np.float64)
        self.k = np.asarray(k, dtype=np.float64)
        self.seg_len = np.asarray(seg_len, dtype=np.float64)
        self.s0 = np.concatenate([[0.0], np.cumsum(self.seg_len)[:-1]])
        self.length = float(self.seg_len.sum())
        self.n_lanes = int(n_lanes)
        self.lane_width = float(lane_width_m)
        self.half_width = self.n_lanes * self.lane_width / 2.0
        self.rail_d = self.half_width + float(shoulder_m)
        self.track_id = track_id
        # arc centres (nan for straights): c = p0 + n0 / k
        safe_k = np.where(np.abs(self.k) < _STRAIGHT_EPS, np.nan, self.k)
        self.cx = self.x0 - np.sin(self.h0) / safe_k
        self.cy = self.y0 + np.cos(self.h0) / safe_k
        # plain-Python rows (s0, length, x0, y0, h0, k, cx, cy) for scalar per-step lookups
        self.seg_table = [
            (
                float(a),
                float(b),
                float(c),
                float(d),
                float(e),
                float(f),
                float(g),
                float(h),
            )
            for a, b, c, d, e, f, g, h in zip(
                self.s0, self.seg_len, self.x0, self.y0, self.h0, self.k, self.cx, self.cy
            )
        ]

    # ------------------------------------------------------------------ lanes
    def lane_center(self, lane: int | np.ndarray) -> float | np.ndarray:
        """Lateral offset ``d`` of the centre of lane ``lane`` (0 = rightmost) [m]."""
        return lane_center(lane, self.n_lanes, self.lane_width)

    def lane_index(self, d: float | np.ndarray) -> int | np.ndarray:
        """Index of the lane whose centre is nearest to offset ``d`` [m], clipped to the road."""
        idx = np.clip(
            np.floor(np.asarray(d) / self.lane_width + self.n_lanes / 2.0), 0, self.n_lanes - 1
        ).astype(int)
        return int(idx) if idx.ndim == 0 else idx

    # ------------------------------------------------------------- s -> world
    def segment_index(self, s: float | np.ndarray) -> np.ndarray:
        """Index of the segment holding arc length ``s`` (clipped to the first/last)."""
        return np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.s0) - 1)

    def heading(self, s: float | np.ndarray) -> np.ndarray:
        """Heading of the reference line at ``s`` [rad] (continuous across joins)."""
        i = self.segment_index(s)
        return self.h0[i] + self.k[i] * (np.asarray(s) - self.s0[i])

    def curvature(self, s: float | np.ndarray) -> np.ndarray:
        """Signed curvature of the reference line at ``s`` [1/m], positive turning left."""
        return self.k[self.segment_index(s)]

    def position(self, s: float | np.ndarray, d: float | np.ndarray = 0.0) -> np.ndarray:
        """World point at arc length ``s`` and lateral offset ``d`` [m]; shape ``(..., 2)``.

        ``s`` beyond the ends extrapolates the first/last segment.
        """
        s = np.asarray(s, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        i = self.segment_index(s)
        u = s - self.s0[i]
        k, h0 = self.k[i], self.h0[i]
        h = h0 + k * u
        straight = np.abs(k) < _STRAIGHT_EPS
        k_safe = np.where(straight, 1.0, k)
        dx = np.where(straight, u * np.cos(h0), (np.sin(h) - np.sin(h0)) / k_safe)
        dy = np.where(straight, u * np.sin(h0), (np.cos(h0) - np.cos(h)) / k_safe)
        x = self.x0[i] + dx - d * np.sin(h)
        y = self.y0[i] + dy + d * np.cos(h)
        return np.stack([x, y], axis=-1)

    def pose(self, s: float | np.ndarray, d: float | np.ndarray = 0.0) -> np.ndarray:
        """``(x, y, heading)`` at ``(s, d)``, heading along the road; shape ``(..., 3)``."""
        xy = self.position(s, d)
        return np.concatenate([xy, self.heading(s)[..., None]], axis=-1)

    # ------------------------------------------------------------- world -> s
    def to_frenet(
        self, x: float | np.ndarray, y: float | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World points to ``(s, d)`` [m], vectorised over points.

        For every segment the point is projected analytically (onto the line, or radially onto the
        arc); among the segments whose projection falls inside them, the one with the smallest
        ``|d|`` wins. Points beyond the ends project onto the first/last segment's extension.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        shape = np.broadcast(x, y).shape
        px = np.broadcast_to(x, shape).reshape(-1, 1)  # (P, 1)
        py = np.broadcast_to(y, shape).reshape(-1, 1)
        u, d = _project(px, py, self.x0, self.y0, self.h0, self.k, self.cx, self.cy)  # (P, M)
        tol = 1e-9
        inside = (u >= -tol) & (u <= self.seg_len + tol)
        m = len(self.seg_len)
        inside[:, 0] |= u[:, 0] < 0  # before the start: extend the first segment
        inside[:, m - 1] |= u[:, m - 1] > self.seg_len[m - 1]  # past the end: extend the last
        score = np.where(inside, np.abs(d), np.inf)
        best = np.argmin(score, axis=1)
        rows = np.arange(len(best))
        no_hit = ~np.isfinite(score[rows, best])
        if np.any(no_hit):  # should not happen on a generated track; fall back to nearest end
            best[no_hit] = np.argmin(np.abs(d[no_hit]), axis=1)
        s = self.s0[best] + u[rows, best]
        return s.reshape(shape), d[rows, best].reshape(shape)

    def to_frenet_hint(self, x: float, y: float, hint: int) -> tuple[float, float, int]:
        """Scalar :meth:`to_frenet` starting at segment ``hint``: ``(s, d, segment)``.

        Tries the hinted segment and its neighbours in plain Python (a few microseconds), which is
        what a car moving along the road needs every step; falls back to the full search.
        """
        segs = self.seg_table
        m = len(segs)
        for j in (hint, hint + 1, hint - 1, hint + 2):
            if not 0 <= j < m:
                continue
            s0, ln, x0, y0, h0, k, cx, cy = segs[j]
            if abs(k) < _STRAIGHT_EPS:
                dx, dy = x - x0, y - y0
                c, sn = math.cos(h0), math.sin(h0)
                u, d = dx * c + dy * sn, -dx * sn + dy * c
            else:
                rx, ry = x - cx, y - cy
                sign = 1.0 if k > 0 else -1.0
                h = math.atan2(ry, rx) + sign * math.pi / 2.0
                dh = (h - h0 + math.pi) % (2.0 * math.pi) - math.pi
                u, d = dh / k, 1.0 / k - sign * math.hypot(rx, ry)
            if (-1e-9 <= u <= ln + 1e-9) or (j == 0 and u < 0) or (j == m - 1 and u > ln):
                return float(s0 + u), float(d), j
        s, d = self.to_frenet(x, y)
        s = float(s)
        return s, float(d), int(self.segment_index(s))

    # ------------------------------------------------------------- sampling
    def sample(
        self, step_m: float = 5.0, d: float = 0.0, s_from: float = 0.0, s_to: float | None = None
    ) -> np.ndarray:
        """Points along the road at offset ``d``, every ``step_m`` or closer, ends included; (N, 2).

        Each segment's joins are included exactly, so straights are exact and arcs are chords.
        """
        s_to = self.length if s_to is None else s_to
        n = max(2, math.ceil((s_to - s_from) / step_m) + 1)
        s = np.linspace(s_from, s_to, n)
        joins = self.s0[(self.s0 > s_from) & (self.s0 < s_to)]
        s = np.unique(np.concatenate([s, joins]))
        return self.position(s, d)

    def polyline(self, d: float = 0.0, max_sag_m: float = 0.02) -> np.ndarray:
        """The line at offset ``d`` as few points as possible; (N, 2) [m].

        Straights are one chord each; arcs are cut so that no chord strays more than
        ``max_sag_m`` from the arc (sagitta ``r (1 - cos(a/2))`` for chord angle ``a``).
        """
        s_pts = [0.0]
        for s0, ln, k in zip(self.s0, self.seg_len, self.k):
            if abs(k) < _STRAIGHT_EPS:
                n = 1
            else:
                radius = max(abs(1.0 / k - d), 1.0)  # the offset line's radius
                angle = 2.0 * math.acos(max(0.0, 1.0 - max_sag_m / radius))
                n = max(1, math.ceil(abs(k) * ln / angle))
            s_pts.extend(np.linspace(s0, s0 + ln, n + 1)[1:].tolist())
        return self.position(np.array(s_pts), d)

    def curve_share(self) -> float:
        """Fraction of the track length on arcs (the rare events of a highway)."""
        return float(self.seg_len[np.abs(self.k) >= _STRAIGHT_EPS].sum() / self.length)


def positions_on(tracks: list[Track], s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """:meth:`Track.position` for B tracks at once: row ``b`` of ``s`` (B, P) lies on ``tracks[b]``.

    ``d`` is (P,) or (B, P). Rows whose points all lie on one segment (a camera window of 100 m
    usually does) are computed together with per-row segment constants; the others row by row.
    Returns (B, P, 2) [m].
    """
    s = np.asarray(s, dtype=np.float64)
    d = np.broadcast_to(np.asarray(d, dtype=np.float64), s.shape)
    out = np.empty((*s.shape, 2))
    lo, hi = s.min(axis=1), s.max(axis=1)
    rows, consts = [], []
    for b, track in enumerate(tracks):
        j = int(np.searchsorted(track.s0, lo[b], side="right")) - 1
        if j >= 0 and (j == len(track.s0) - 1 or hi[b] < track.s0[j + 1]):
            rows.append(b)
            consts.append(track.seg_table[j])
        else:
            out[b] = track.position(s[b], d[b])
    if rows:
        c = np.array(consts)  # (R, 8): s0, length, x0, y0, h0, k, cx, cy
        s0, x0, y0, h0, k, cx, cy = (c[:, i : i + 1] for i in (0, 2, 3, 4, 5, 6, 7))
        u, dd = s[rows] - s0, d[rows]
        straight = np.abs(k) < _STRAIGHT_EPS
        k_safe = np.where(straight, 1.0, k)
        h = h0 + k * u
        r = 1.0 / k_safe - dd  # arcs: radius of the offset point about the centre
        sin_h, cos_h = np.sin(h), np.cos(h)
        out[rows, :, 0] = np.where(straight, x0 + u * cos_h - dd * sin_h, cx + r * sin_h)
        out[rows, :, 1] = np.where(straight, y0 + u * sin_h + dd * cos_h, cy - r * cos_h)
    return out


def _project(
    px: np.ndarray,
    py: np.ndarray,
    x0: np.ndarray,
    y0: np.ndarray,
    h0: np.ndarray,
    k: np.ndarray,
    cx: np.ndarray,
    cy: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Local arc length ``u`` and offset ``d`` of points (P,1) on every segment (M,): (P, M) each."""
    straight = np.abs(k) < _STRAIGHT_EPS
    # straight: u = (p - p0) . t0,  d = (p - p0) . n0
    dx, dy = px - x0, py - y0
    u_line = dx * np.cos(h0) + dy * np.sin(h0)
    d_line = -dx * np.sin(h0) + dy * np.cos(h0)
    # arc: h = atan2(p - c) + sign(k) pi/2,  u = wrap(h - h0) / k,  d = 1/k - sign(k) |p - c|
    with np.errstate(invalid="ignore", divide="ignore"):
        rx, ry = px - cx, py - cy
        sign = np.sign(k)
        h = np.arctan2(ry, rx) + sign * np.pi / 2.0
        dh = wrap_angle(h - h0)
        k_safe = np.where(straight, 1.0, k)
        u_arc = dh / k_safe
        d_arc = 1.0 / k_safe - sign * np.hypot(rx, ry)
    return np.where(straight, u_line, u_arc), np.where(straight, d_line, d_arc)


def track_rng(seed: int, split: str, index: int, stream: int = 0) -> np.random.Generator:
    """The generator for track ``(split, index)``; ``stream`` separates geometry (0) from traffic (1).

    Splits have disjoint seed sequences by construction: ``default_rng([seed, split_code, index,
    stream])`` with a different ``split_code`` per split.
    """
    if split not in SPLITS:
        raise ValueError(f"split={split!r} is invalid: must be one of {sorted(SPLITS)}")
    check_range("track", "index", index, 0, integer=True)
    return np.random.default_rng([int(seed), SPLITS[split], int(index), int(stream)])


def generate_track(cfg: RoadConfig, split: str = "train", index: int = 0) -> Track:
    """A procedural track: an opening straight, then straights and arcs alternating.

    Arcs turn left or right at random, flipping side whenever the heading would leave
    ``+-max_heading_deg``; the last segment is cut so the track is exactly ``length_m`` long.
    Deterministic in ``(cfg, split, index)``.
    """
    rng = track_rng(cfg.seed, split, index, stream=0)
    max_h = math.radians(cfg.max_heading_deg)
    x, y, h = 0.0, 0.0, 0.0
    x0s, y0s, h0s, ks, lens = [], [], [], [], []
    total = 0.0
    is_arc = False
    while total < cfg.length_m - 1e-9:
        if not x0s:
            k, ln = 0.0, cfg.first_straight_m
        elif is_arc:
            radius = rng.uniform(*cfg.radius_m)
            turn = math.radians(rng.uniform(*cfg.arc_deg))
            side = 1.0 if rng.random() < 0.5 else -1.0
            if abs(h + side * turn) > max_h:
                side = -side
            k, ln = side / radius, turn * radius
        else:
            k, ln = 0.0, rng.uniform(*cfg.straight_m)
        is_arc = not is_arc if x0s else True
        ln = min(ln, cfg.length_m - total)
        if ln <= 0:
            break
        x0s.append(x)
        y0s.append(y)
        h0s.append(h)
        ks.append(k)
        lens.append(ln)
        # advance to the end of this segment
        if abs(k) < _STRAIGHT_EPS:
            x, y = x + ln * math.cos(h), y + ln * math.sin(h)
        else:
            h1 = h + k * ln
            x, y = x + (math.sin(h1) - math.sin(h)) / k, y + (math.cos(h) - math.cos(h1)) / k
            h = h1
        total += ln
    return Track(
        np.array(x0s),
        np.array(y0s),
        np.array(h0s),
        np.array(ks),
        np.array(lens),
        n_lanes=cfg.n_lanes,
        lane_width_m=cfg.lane_width_m,
        shoulder_m=cfg.shoulder_m,
        track_id=(split, index),
    )
