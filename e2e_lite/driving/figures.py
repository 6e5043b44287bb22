"""Figures: top-down maps of tracks, parked cars, driven paths and collisions.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot, no window, no backend switch), so
the library stays headless and a notebook still shows a returned figure inline.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure

from ..artifacts import save_figure  # noqa: F401 (re-exported: the chapters save figures through viz)
from ..simulation.geometry import Track
from ..simulation.world import ParkedCars
from .metrics import EvalResult

ROAD_GREY = "#5a5a5a"
GRASS = "#cfe3c3"
RAIL = "#8a8a8a"
CAR = "#d62728"


def draw_road(
    ax: Axes,
    track: Track,
    s_range: tuple[float, float] | None = None,
    cars: ParkedCars | None = None,
    step_m: float = 2.0,
) -> None:
    """Draw the road top-down: surface, lane markings (dashed inside, solid edges), rails, cars.

    Args:
        ax: where to draw.
        track: the road.
        s_range: the stretch to draw ``(s_from, s_to)`` [m]; the whole track by default.
        cars: parked cars to draw as boxes (only those in the stretch).
        step_m: sampling step along the road [m].
    """
    s_from, s_to = (0.0, track.length) if s_range is None else s_range
    left = track.sample(step_m, track.half_width, s_from, s_to)
    right = track.sample(step_m, -track.half_width, s_from, s_to)
    ax.set_facecolor(GRASS)
    ax.fill(
        np.r_[left[:, 0], right[::-1, 0]],
        np.r_[left[:, 1], right[::-1, 1]],
        color=ROAD_GREY,
        lw=0,
        zorder=1,
    )
    for side in (-1, 1):
        rail = track.sample(step_m, side * track.rail_d, s_from, s_to)
        ax.plot(rail[:, 0], rail[:, 1], color=RAIL, lw=2.0, zorder=2)
        edge = track.sample(step_m, side * track.half_width, s_from, s_to)
        ax.plot(edge[:, 0], edge[:, 1], color="white", lw=1.2, zorder=3)
    for lane in range(1, track.n_lanes):
        d = float(track.lane_center(lane)) - track.lane_width / 2
        pts = track.sample(step_m, d, s_from, s_to)
        ax.plot(pts[:, 0], pts[:, 1], color="white", lw=0.9, ls=(0, (3, 9)), zorder=3)
    if cars is not None and len(cars):
        sl = cars.between(s_from - cars.length_m, s_to + cars.length_m)
        boxes = cars.corners()[sl]
        ax.add_collection(
            PolyCollection(list(boxes), facecolor=CAR, edgecolor="black", lw=0.6, zorder=5)
        )
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_path(
    ax: Axes, xy: np.ndarray, color: str, label: str | None = None, lw: float = 1.5
) -> None:
    """Draw a driven path ``(N, 2)`` [m], breaking it where consecutive points jump (re-spawns)."""
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 2:
        return
    jumps = np.hypot(*np.diff(xy, axis=0).T) > 10.0
    segs = np.stack([xy[:-1], xy[1:]], axis=1)[~jumps]
    ax.add_collection(LineCollection(list(segs), colors=color, lw=lw, zorder=6, label=label))


def track_overview(ax: Axes, track: Track, cars: ParkedCars | None = None) -> None:
    """A whole-track map: the centre line coloured by |curvature|, parked cars as dots."""
    s = np.arange(0.0, track.length, 10.0)
    xy = track.position(s)
    curv = np.abs(track.curvature(s))
    segs = np.stack([xy[:-1], xy[1:]], axis=1)
    lc = LineCollection(list(segs), array=curv[:-1] * 1000.0, cmap="viridis", lw=3)
    ax.add_collection(lc)
    if cars is not None and len(cars):
        ax.scatter(cars.x, cars.y, s=6, color=CAR, zorder=3, label=f"{len(cars)} parked cars")
        ax.legend(loc="best", fontsize=8)
    ax.figure.colorbar(lc, ax=ax, label="|curvature| [1/km]", shrink=0.7)
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def highway_figure(
    track: Track,
    cars: ParkedCars,
    s_range: tuple[float, float],
    paths: Sequence[tuple[str, np.ndarray, str]] = (),
    crashes: Sequence[tuple[float, float]] = (),
) -> Figure:
    """Chapter 01's picture: the whole track on top, a zoomed stretch with driven paths below.

    Args:
        track, cars: the world.
        s_range: the zoomed stretch ``(s_from, s_to)`` [m].
        paths: ``(label, xy (N, 2), colour)`` of driven paths to overlay on the zoom.
        crashes: ``(x, y)`` of collisions to mark on the zoom [m].
    """
    fig = Figure(figsize=(11, 7.5))
    ax_map, ax_zoom = fig.subplots(2, 1, gridspec_kw={"height_ratios": [1.3, 1]})
    track_overview(ax_map, track, cars)
    ax_map.set_title(
        f"track {track.track_id[0]}-{track.track_id[1]}: {track.length / 1000:.1f} km, "
        f"{track.curve_share():.0%} on curves"
    )
    band = track.sample(5.0, 0.0, *s_range)
    ax_map.plot(band[:, 0], band[:, 1], color="orange", lw=6, alpha=0.6, zorder=2)
    draw_road(ax_zoom, track, s_range, cars)
    for label, xy, color in paths:
        draw_path(ax_zoom, xy, color, label)
    if len(crashes):
        c = np.asarray(crashes)
        ax_zoom.scatter(
            c[:, 0],
            c[:, 1],
            marker="X",
            s=90,
            color="yellow",
            edgecolor="black",
            zorder=8,
            label="collision",
        )
    pts = np.concatenate([track.sample(5.0, side * track.rail_d, *s_range) for side in (-1, 1)])
    pad = 5.0
    ax_zoom.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
    ax_zoom.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    ax_zoom.set_title(f"s = {s_range[0]:.0f}-{s_range[1]:.0f} m (orange on the map)")
    if ax_zoom.get_legend_handles_labels()[0]:  # (a stretch no path or crash reached has none)
        ax_zoom.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    return fig


def collision_chart(
    rows: Sequence[tuple[str, EvalResult]],
    title: str = "closed loop on the test tracks",
    reference: Sequence[tuple[str, float]] = (),
    marks: Sequence[float | None] = (),
    marks_label: str = "paper",
    log: bool = False,
) -> Figure:
    """Collisions per 100 miles as horizontal bars with their 95 % intervals.

    Args:
        rows: ``(driver, result)`` with an :class:`EvalResult`, drawn top to
            bottom.
        title: the axes title.
        reference: ``(label, collisions per 100 mi)`` drawn as dashed vertical lines (e.g. a
            paper's figure).
        marks: one value per row (None: no mark) drawn as a red diamond on that row, e.g. the
            paper's figure for the same method.
        marks_label: the legend entry of the marks.
        log: a symmetric-log x axis (linear below 1 per 100 mi), for rates spanning decades.

    A pooled result (:func:`~e2e_lite.driving.evaluation.pool_results`, with ``seeds``) also gets one
    grey dot per training seed with that seed's 95 % interval, spread around its bar.
    """
    if not rows:
        raise ValueError("collision_chart needs at least one row")
    names = [name for name, _ in rows]
    results = [r for _, r in rows]
    rate = np.array([r.collisions_per_100mi for r in results], dtype=float)
    lo = np.array([r.ci95_per_100mi[0] for r in results], dtype=float)
    hi = np.array([r.ci95_per_100mi[1] for r in results], dtype=float)
    fig = Figure(figsize=(8.5, 0.55 * len(rows) + 1.4))
    ax = fig.subplots()
    y = np.arange(len(rows))[::-1]
    ax.barh(y, rate, color="#4c72b0", alpha=0.8)
    ax.errorbar(rate, y, xerr=[rate - lo, hi - rate], fmt="none", ecolor="black", capsize=4)
    seeds_shown = False
    for yi, res in zip(y, results):
        per_seed = res.seeds
        for j, sr in enumerate(per_seed):
            dy = 0.25 * (j - (len(per_seed) - 1) / 2) / max(1, len(per_seed) - 1) * 2
            sl, sh = sr.ci95_per_100mi
            sv = sr.collisions_per_100mi
            label = None if seeds_shown else "one training seed (95 % interval)"
            look = {"fmt": "o", "color": "0.35", "ms": 3.5, "elinewidth": 0.8, "capsize": 0}
            ax.errorbar([sv], [yi + dy], xerr=[[sv - sl], [sh - sv]], zorder=4, label=label, **look)
            seeds_shown = True
            hi = np.maximum(hi, np.where(y == yi, sh, 0.0))
    # each row's value is written right of everything drawn on it: interval, seeds, paper mark
    ends = hi.copy()
    if len(marks) == len(rows):
        ends = np.maximum(ends, [0.0 if v is None else v for v in marks])
    for yi, r, h in zip(y, rate, ends):
        x_text = h * 1.3 + 0.05 if log else h + 0.01 * max(ends.max(), 1.0)
        ax.text(x_text, yi, f"{r:.1f}", va="center", fontsize=9)
    if len(marks):
        if len(marks) != len(rows):
            raise ValueError(f"marks has {len(marks)} values for {len(rows)} rows")
        mx = [(v, yi) for v, yi in zip(marks, y) if v is not None]
        if mx:
            ax.plot(*zip(*mx), "D", color="#c44e52", ms=7, label=marks_label, zorder=5)
    if seeds_shown or any(v is not None for v in marks):
        ax.legend(loc="upper right", fontsize=8)
    for label, value in reference:
        ax.axvline(value, color="#c44e52", ls="--", lw=1)
        ax.text(value, len(rows) - 0.45, f" {label}", color="#c44e52", fontsize=8, va="bottom")
    ax.set_yticks(y, names)
    ax.set_xlabel("collisions per 100 miles (bar: measured; line: 95 % interval)")
    top = max(hi.max(), *(v for _, v in reference), *(v for v in marks if v is not None), 1.0)
    if log:
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlim(0, 3.0 * top)
    else:
        ax.set_xlim(0, 1.15 * top)
    ax.set_title(title)
    fig.tight_layout()
    return fig
