"""Recovery views of the recorded frames (seed 003, PilotNet; chapter 05), rendered exactly (a
real car would need extra cameras and a view synthesis): the same frames seen from a car shifted
sideways and turned, each labelled with the steering that brings it back (recomputed with the
LQR tracker from the shifted pose, the expert's clean trajectory expressed in the new car frame).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..artifacts import artifact_path, cached, settings_key, versioned
from ..config import check_pair, check_range, tqdm
from ..control.tracker import LQRTracker, follow_trajectory
from ..learning.dataset import FIELDS, DrivingData, load_dataset, save_dataset
from ..simulation.camera import Camera
from ..simulation.world import World, make_world
from .collector import DataConfig, affordances


@dataclass(frozen=True)
class RecoveryConfig:
    """Seed 003's extra views from shifted and rotated cameras, rendered exactly.

    For a random subset of samples the frame is re-rendered with the car moved sideways and turned,
    at the same arc length. Labels of a view:

    * trajectory: the sample's own 5 points, expressed in the moved car's frame (where the expert
      was going, seen from the new pose);
    * steering: the sample's clean steering plus the correction the LQR tracker makes towards that
      trajectory from the new pose, ``delta + (follow(view) - follow(original))``: the tracker settles
      a 1 m error within about 50 m, so this is seed 003's "steering that brings the car back
      within 2 s" at highway speed. The acceleration label is unchanged;
    * affordances: recomputed at the new pose.

    A car slower than ``min_speed_mps`` gets no view: "the steering that brings it back within
    2 s" has no meaning for a car standing behind a parked one, and the tracker's gains grow as
    1 / v, so such a view's label was up to 0.55 rad (lab note "One expert for the whole
    course": the one expert stops behind blocked lanes more often, and 113 such views of 24,000
    were enough to ruin PilotNet's training on them).

    Attributes:
        fraction: share of samples that get one view (drawn among those fast enough).
        shift_m: (min, max) magnitude of the lateral shift of the rear axle, random sign [m].
        rotation_rad: the heading offset is uniform in +-this [rad].
        seed: seeds which samples and which offsets.
        min_speed_mps: the slowest sample that gets a view [m/s].
    """

    fraction: float = 0.5
    shift_m: tuple[float, float] = (0.3, 1.2)
    rotation_rad: float = 0.06
    seed: int = 0
    min_speed_mps: float = 5.0

    def __post_init__(self) -> None:
        o = "RecoveryConfig"
        check_range(o, "fraction", self.fraction, 0.0, 1.0, lo_open=True)
        check_pair(o, "shift_m", self.shift_m, lo=0.0)
        check_range(o, "rotation_rad", self.rotation_rad, 0.0, 0.5)
        check_range(o, "seed", self.seed, 0, integer=True)
        check_range(o, "min_speed_mps", self.min_speed_mps, 0.0, 30.0)


def to_car_frame(points: np.ndarray, pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """Car-frame points ``(B, K, 2)`` of poses ``pose_from`` (B, 3) re-expressed in the frames of
    ``pose_to`` (B, 3); poses are ``(x, y, heading)`` of the rear axle [m, m, rad]."""
    c0, s0 = np.cos(pose_from[:, 2])[:, None], np.sin(pose_from[:, 2])[:, None]
    wx = pose_from[:, :1] + c0 * points[..., 0] - s0 * points[..., 1]
    wy = pose_from[:, 1:2] + s0 * points[..., 0] + c0 * points[..., 1]
    dx, dy = wx - pose_to[:, :1], wy - pose_to[:, 1:2]
    c1, s1 = np.cos(pose_to[:, 2])[:, None], np.sin(pose_to[:, 2])[:, None]
    return np.stack([c1 * dx + s1 * dy, -s1 * dx + c1 * dy], axis=-1)


def _world_cache(data_cfg: DataConfig) -> Callable[[np.ndarray], list[World]]:
    """``worlds(track_ids)``: each row's world, every track built once."""
    made: dict[int, World] = {}

    def worlds(track_ids: np.ndarray) -> list[World]:
        for t_idx in np.unique(track_ids).tolist():
            if t_idx not in made:
                made[t_idx] = make_world(data_cfg.world, data_cfg.split, t_idx)
        return [made[int(t_idx)] for t_idx in track_ids]

    return worlds


def _poses(ws: list[World], s: np.ndarray, d: np.ndarray, heading_error: np.ndarray) -> np.ndarray:
    """World poses ``(B, 3)`` of rear axles at lane-frame ``(s, d)`` turned by ``heading_error``
    from the road [m, m, rad]."""
    pose = np.array([w.track.pose(si, di) for w, si, di in zip(ws, s, d)])
    pose[:, 2] += heading_error
    return pose


def _chunks(m: int, desc: str, progress: bool, size: int = 256) -> Iterator[slice]:
    """Slices of ``size`` rows over ``m`` views, with a progress bar."""
    bar = tqdm(total=m, desc=desc, unit="view", disable=not progress, leave=False, mininterval=0.5)
    for lo in range(0, m, size):
        sl = slice(lo, min(m, lo + size))
        yield sl
        bar.update(sl.stop - sl.start)
    bar.close()


def _key(tag: str, data: DrivingData, cfg: Any) -> str:
    """The views' key: their kind's tag, the source data's key and their settings (what the
    disk cache compares)."""
    return settings_key(tag, data.info["key"], cfg)


def _views(
    tag: str, name: str, data: DrivingData, cfg: Any, rows: np.ndarray, out: dict
) -> DrivingData:
    """The views' container: the source's statistics, their key and where they came from."""
    info = {
        "key": _key(tag, data, cfg),
        "split": data.info["split"],
        "n_samples": len(rows),
        "source_key": data.info["key"],
        name: cfg,
        "source_rows": rows,
    }
    return DrivingData(out, dict(data.stats), info)


def recovery_views(
    data: DrivingData, data_cfg: DataConfig, cfg: RecoveryConfig, progress: bool = True
) -> DrivingData:
    """Render recovery views of ``data`` (made with ``data_cfg``); see :class:`RecoveryConfig`."""
    rng = np.random.default_rng([cfg.seed, 31])
    n = len(data)
    moving = np.flatnonzero(data.speed >= cfg.min_speed_mps)
    k = min(len(moving), max(1, round(cfg.fraction * n)))
    rows = np.sort(rng.choice(moving, k, replace=False))
    m = len(rows)
    shift = rng.uniform(*cfg.shift_m, m) * rng.choice([-1.0, 1.0], m)
    turn = rng.uniform(-cfg.rotation_rad, cfg.rotation_rad, m)
    out = {name: data.arrays[name][rows].copy() for name in ("images", *FIELDS)}
    out["noise"][:] = False
    worlds = _world_cache(data_cfg)
    camera = Camera(data_cfg.camera)
    tracker = LQRTracker(vehicle=data_cfg.world.vehicle)
    for sl in _chunks(m, "recovery views", progress):
        r = rows[sl]
        ws = worlds(data.track[r])
        s = data.s[r].astype(np.float64)
        d0 = data.d[r].astype(np.float64)
        d1 = d0 + shift[sl]
        he0 = data.affordances[r, 0].astype(np.float64)
        he1 = he0 + turn[sl]
        pose0, pose1 = _poses(ws, s, d0, he0), _poses(ws, s, d1, he1)
        pts0 = data.trajectory[r].astype(np.float64)
        pts1 = to_car_frame(pts0, pose0, pose1)
        speed = data.speed[r].astype(np.float64)
        steer0, _ = follow_trajectory(tracker, pts0, speed)
        steer1, _ = follow_trajectory(tracker, pts1, speed)
        out["trajectory"][sl] = pts1
        out["actuators"][sl, 0] = data.actuators[r, 0] + (steer1 - steer0)
        out["d"][sl] = d1
        out["lane"][sl] = ws[0].track.lane_index(d1)
        out["affordances"][sl] = affordances(ws, s, d1, he1)
        camera.render_batch(
            [w.track for w in ws], [w.cars for w in ws], pose1, s, out=out["images"][sl]
        )
    return _views(versioned("recovery"), "recovery", data, cfg, rows, out)


def _load_or_make(
    tag: str,
    kind: str,
    make: Callable[..., DrivingData],
    data: DrivingData,
    data_cfg: DataConfig,
    cfg: Any,
    progress: bool,
) -> DrivingData:
    """Views of ``data`` from ``<outputs>/data/<split>-<n>-<kind>.npz`` if made by these settings,
    else ``make(data, data_cfg, cfg, progress)``, saved there."""
    path = artifact_path("data", f"{data_cfg.split}-{data_cfg.n_samples}-{kind}.npz")
    return cached(
        path,
        _key(tag, data, cfg),
        lambda: make(data, data_cfg, cfg, progress),
        save_dataset,
        load_dataset,
    )


def load_or_make_recovery(
    data: DrivingData,
    data_cfg: DataConfig,
    cfg: RecoveryConfig | None = None,
    progress: bool = True,
) -> DrivingData:
    """The recovery views of ``data`` from disk if made by these settings, else render and save."""
    cfg = cfg or RecoveryConfig()
    return _load_or_make(
        versioned("recovery"), "recovery", recovery_views, data, data_cfg, cfg, progress
    )
