"""Extra views of the recorded frames, rendered exactly (a real car would need extra cameras and
a view synthesis):

* recovery views (seed 003, PilotNet; chapter 05): the same frames seen from a car shifted
  sideways and turned, each labelled with the steering that brings it back (recomputed with the
  LQR tracker from the shifted pose, the expert's clean trajectory expressed in the new car
  frame);
* approach views (chapter 11): the car moved along its lane to a random distance behind the
  next parked car in it, and sideways, labelled with their affordances only. The expert changes
  lanes long before a parked car comes near, so its frames almost never show one within 30 m
  (4 of 4,000 validation frames within 15 m); a safety module reads the affordance head exactly
  there, when the network it guards has not changed lanes in time.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ..artifacts import artifact_path, cached, settings_key
from ..config import check_pair, check_range, tqdm
from ..control.tracker import LQRTracker, follow_trajectory
from ..simulation.camera import Camera
from ..simulation.world import World, make_world
from .data import DataConfig, affordances
from .dataset import FIELDS, DrivingData, load_dataset, save_dataset


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

    Attributes:
        fraction: share of samples that get one view.
        shift_m: (min, max) magnitude of the lateral shift of the rear axle, random sign [m].
        rotation_rad: the heading offset is uniform in +-this [rad].
        seed: seeds which samples and which offsets.
    """

    fraction: float = 0.5
    shift_m: tuple[float, float] = (0.3, 1.2)
    rotation_rad: float = 0.06
    seed: int = 0

    def __post_init__(self) -> None:
        o = "RecoveryConfig"
        check_range(o, "fraction", self.fraction, 0.0, 1.0, lo_open=True)
        check_pair(o, "shift_m", self.shift_m, lo=0.0)
        check_range(o, "rotation_rad", self.rotation_rad, 0.0, 0.5)
        check_range(o, "seed", self.seed, 0, integer=True)


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
    rows = np.sort(rng.choice(n, max(1, round(cfg.fraction * n)), replace=False))
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
    return _views("recovery-v1", "recovery", data, cfg, rows, out)


@dataclass(frozen=True)
class ApproachConfig:
    """Approach views: frames re-rendered with the car behind the next parked car in its lane.

    For a random subset of samples the car keeps its speed and its heading error (plus a turn),
    moves sideways by a random shift, and moves along the road to ``gap_m`` behind the rear of
    the next parked car in its lane (the gap measured from the front bumper, as the affordance).
    Samples whose lane holds no parked car further on are skipped. The views carry the
    recomputed affordances; their trajectory and commands are the source sample's, **not** labels
    of the new pose, so the views train an affordance head only (:func:`~e2e_lite.learning.
    recipes.perceiving`), never a driver (``noise`` is set on every view, which marks them).

    Attributes:
        fraction: share of samples that get one view.
        gap_m: (min, max) of the uniform distance to the parked car [m].
        shift_m: the lateral shift is uniform in +-this [m] (half a lane: the car may straddle a
            marking, as a network does when it starts its lane change late).
        rotation_rad: the heading offset is uniform in +-this [rad].
        seed: seeds which samples and which offsets.
        entry_share: share of the views that show the car **entering** a lane instead: the parked
            car is the next one in a lane beside the sample's (left or right at random, the other
            side at the road's edge), and the car is placed ``gap_m`` behind it with its rear
            axle 0.5 m short of to 1.5 m past the marking between the lanes, turned towards the
            lane it enters by up to ``entry_turn_rad`` more than the sample's heading error.
            That is where chapter 11's module misread the gap ahead (a car that has just changed
            lanes, turned, with a parked car 13-32 m ahead in its new lane). Drawn from a
            generator of their own: ``entry_share=0`` gives the plain approach views, bit for bit.
        entry_turn_rad: the entering car's extra turn is uniform in 0-this [rad].
        side_share: share of the other views that look at a parked car in a lane **beside** the
            car's instead: the car keeps its lane (and its shift and turn) and stands
            ``side_gap_m`` behind the next parked car in the lane on its left or right (the other
            side at the road's edge). The head learns the side lanes' gaps from the expert's
            frames alone, where a parked car 40-60 m ahead in a neighbouring lane is rare (about
            6 % of side-lane readings, chapter 11), and reads free side lanes less sharply than
            its own: chapter 11's module calibrated the side lanes' "nothing seen" at about 42 m,
            under the 55 m its rule needs at cruise speed. Drawn from a generator of their own:
            ``side_share=0`` leaves the other views as they were, bit for bit.
        side_gap_m: (min, max) of the uniform distance to the side lane's parked car [m]; past
            the gap cap (60 m) the label reads "nothing seen" while the car is still drawn,
            which is what the cap's edge looks like.
    """

    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = (
        "entry_share",
        "entry_turn_rad",
        "side_share",
        "side_gap_m",
    )

    fraction: float = 0.25
    gap_m: tuple[float, float] = (0.5, 50.0)
    shift_m: float = 1.8
    rotation_rad: float = 0.06
    seed: int = 0
    entry_share: float = 0.0
    entry_turn_rad: float = 0.15
    side_share: float = 0.0
    side_gap_m: tuple[float, float] = (20.0, 75.0)

    def __post_init__(self) -> None:
        o = "ApproachConfig"
        check_range(o, "fraction", self.fraction, 0.0, 1.0, lo_open=True)
        check_pair(o, "gap_m", self.gap_m, lo=0.0)
        check_range(o, "shift_m", self.shift_m, 0.0, 5.0)
        check_range(o, "rotation_rad", self.rotation_rad, 0.0, 0.5)
        check_range(o, "seed", self.seed, 0, integer=True)
        check_range(o, "entry_share", self.entry_share, 0.0, 1.0)
        check_range(o, "entry_turn_rad", self.entry_turn_rad, 0.0, 0.5)
        check_range(o, "side_share", self.side_share, 0.0, 1.0)
        check_pair(o, "side_gap_m", self.side_gap_m, lo=0.0)


def approach_views(
    data: DrivingData, data_cfg: DataConfig, cfg: ApproachConfig, progress: bool = True
) -> DrivingData:
    """Render approach views of ``data`` (made with ``data_cfg``); see :class:`ApproachConfig`."""
    rng = np.random.default_rng([cfg.seed, 37])
    n = len(data)
    rows = np.sort(rng.choice(n, max(1, round(cfg.fraction * n)), replace=False))
    gap = rng.uniform(*cfg.gap_m, len(rows))
    shift = rng.uniform(-cfg.shift_m, cfg.shift_m, len(rows))
    turn = rng.uniform(-cfg.rotation_rad, cfg.rotation_rad, len(rows))
    d_new = data.d[rows].astype(np.float64) + shift
    he_new = data.affordances[rows, 0].astype(np.float64) + turn
    # the entering views draw from a generator of their own: the plain views stay as they were
    entry = np.random.default_rng([cfg.seed, 41])
    entering = entry.random(len(rows)) < cfg.entry_share
    side = entry.choice([-1, 1], len(rows))  # +1: into the lane on the left
    past = entry.uniform(-0.5, 1.5, len(rows))  # rear axle past the marking [m]
    towards = entry.uniform(0.0, cfg.entry_turn_rad, len(rows))
    beside = np.random.default_rng([cfg.seed, 43])  # the side views' own draws
    looking = (beside.random(len(rows)) < cfg.side_share) & ~entering
    side_of = beside.choice([-1, 1], len(rows))
    gap = np.where(looking, beside.uniform(*cfg.side_gap_m, len(rows)), gap)
    worlds = _world_cache(data_cfg)
    s_new = np.full(len(rows), np.nan)
    for j, (w, r) in enumerate(zip(worlds(data.track[rows]), rows.tolist())):  # (no rendering)
        cars, lane, track = w.cars, int(data.lane[r]), w.track
        # the lane beside whose car it enters (or looks at: the car stays where it is)
        toward = int(side[j]) if entering[j] else int(side_of[j]) if looking[j] else 0
        if not 0 <= lane + toward < track.n_lanes:
            toward = -toward  # (the other side at the road's edge)
        if entering[j]:
            marking = float(track.lane_center(lane)) + toward * track.lane_width / 2.0
            d_new[j] = marking + toward * past[j]
            he_new[j] = float(data.affordances[r, 0]) + toward * towards[j]
        lane += toward
        rear = cars.s - cars.length_m / 2.0  # (a jittered car's box reaches a few cm further)
        ahead = np.flatnonzero((cars.lane == lane) & (rear > float(data.s[r])))
        front = w.vehicle.length_m - w.vehicle.rear_overhang_m  # rear axle to front bumper
        if len(ahead) and rear[ahead[0]] - front - gap[j] > 0.0:
            s_new[j] = rear[ahead[0]] - front - gap[j]
    keep = np.isfinite(s_new)
    rows, s_new, d_new, he_new = rows[keep], s_new[keep], d_new[keep], he_new[keep]
    out = {name: data.arrays[name][rows].copy() for name in ("images", *FIELDS)}
    out["noise"][:] = True  # not the expert's clean driving: no driver may train on these rows
    camera = Camera(data_cfg.camera)
    for sl in _chunks(len(rows), "approach views", progress):
        r = rows[sl]
        ws = worlds(data.track[r])
        s, d, he = s_new[sl], d_new[sl], he_new[sl]
        out["s"][sl], out["d"][sl] = s, d
        out["lane"][sl] = ws[0].track.lane_index(d)
        out["affordances"][sl] = affordances(ws, s, d, he)
        camera.render_batch(
            [w.track for w in ws], [w.cars for w in ws], _poses(ws, s, d, he), s,
            out=out["images"][sl],
        )  # fmt: skip
    return _views("approach-v1", "approach", data, cfg, rows, out)


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


def load_or_make_approach(
    data: DrivingData,
    data_cfg: DataConfig,
    cfg: ApproachConfig | None = None,
    progress: bool = True,
) -> DrivingData:
    """The approach views of ``data`` from disk if made by these settings, else render and save
    (views with entering or side cars in a file of their own: ``...-approach-entry<share>.npz``,
    ``...-approach-side<share>.npz``; any other setting changed adds a digest of the settings to
    the name, so two settings never take turns overwriting one file)."""
    cfg = cfg or ApproachConfig()
    kind = "approach"
    kind += f"-entry{cfg.entry_share:g}" if cfg.entry_share else ""
    kind += f"-side{cfg.side_share:g}" if cfg.side_share else ""
    named = ApproachConfig(entry_share=cfg.entry_share, side_share=cfg.side_share)
    if cfg != named:
        kind += "-" + settings_key("approach-file", cfg, length=8)
    return _load_or_make("approach-v1", kind, approach_views, data, data_cfg, cfg, progress)


def load_or_make_recovery(
    data: DrivingData,
    data_cfg: DataConfig,
    cfg: RecoveryConfig | None = None,
    progress: bool = True,
) -> DrivingData:
    """The recovery views of ``data`` from disk if made by these settings, else render and save."""
    cfg = cfg or RecoveryConfig()
    return _load_or_make("recovery-v1", "recovery", recovery_views, data, data_cfg, cfg, progress)
