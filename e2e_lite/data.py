"""The expert's dataset (chapter 04): camera frames with clean labels, collected under noise.

The collector drives the :class:`~e2e_lite.expert.Expert` through the closed-loop evaluator on
the training (or validation) tracks, with random steering and acceleration *bursts* added to the
commands it executes, so the recording also holds off-centre and off-heading states and the
expert's recovery from them. Some bursts brake hard, and now and then a car is taken over and
re-placed exactly as the evaluator re-places a car after a collision
(:func:`~e2e_lite.evaluation.restart_state`: 20 m/s, below the cruise speed), so the data shows
the expert getting back to speed from the states a learned driver restarts in (covariate shift;
chapter 04 compares the two speed distributions). One sample per policy step (10 Hz) stores:

=================  ==============  ===========================================================
field              shape, dtype    meaning
=================  ==============  ===========================================================
``images``         (N,66,200,3) u8 the front camera frame, RGB
``speed``          (N,) f32        the car's speed [m/s]
``actuators``      (N,2) f32       the expert's **clean** command: steering [rad], accel [m/s^2]
``trajectory``     (N,5,2) f32     the expert's noise-free rollout, rear axle in the car frame at
                                   0.3 ... 1.5 s [m] (x forward, y left)
``affordances``    (N,9) f32       see :data:`AFFORDANCE_NAMES`
``track``          (N,) i32        the track index within the split
``s``, ``d``       (N,) f32        lane-frame position of the rear axle [m]
``lane``           (N,) i8         nearest lane (0 = rightmost)
``curvature``      (N,) f32        the road's curvature at ``s`` [1/m]
``expert_state``   (N,) i8         KEEP 0, CHANGE 1, PASS 2, FOLLOW 3 (see :mod:`e2e_lite.expert`)
``change_side``    (N,) i8         during a change: +1 to the left, -1 to the right; else 0
``overtaking``     (N,) bool       during a change: True for an overtake, False for a return
``noise``          (N,) bool       a noise burst was active (the executed command differed)
=================  ==============  ===========================================================

Throttle and brake (seed 002's outputs) are recoverable from the acceleration label:
``throttle = max(a, 0) / max_accel``, ``brake = max(-a, 0) / max_brake`` (see :func:`throttle_brake`).

Labels are clean: the actuator label is the expert's command from the recorded state *before*
the noise is added, and the trajectory is what the expert would drive from that state without
noise (:meth:`~e2e_lite.expert.Expert.trajectory_label`), not the noisy future.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .artifacts import artifact_path, cached, settings_key, to_json
from .camera import Camera, CameraConfig
from .config import Profile, check_pair, check_range, tqdm
from .evaluation import Actuation, EvalConfig, EvalResult, Observation, evaluate
from .expert import CHANGE, FOLLOW, PASS, Expert, ExpertConfig
from .tracker import N_POINTS, LQRTracker, follow_trajectory
from .vehicle import VehicleParams
from .world import World, WorldConfig, make_world

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
  (a pymunk segment query, :meth:`~e2e_lite.world.World.gap_ahead`) [m]. A car alongside
  (overlapping the ego's length) gives 0. Capped at ``GAP_CAP_M`` (60 m), which also
  encodes "no car"; a lane that does not exist (left of the leftmost) gives 0 (blocked).
"""


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
        front = float(s[i]) + veh.length_m - veh.rear_overhang_m
        # start one parked-car length behind the rear bumper: a segment query does not see a
        # shape it starts inside, and any car found from there reaches at least to our rear
        start = front - veh.length_m - world.cars.length_m
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


def throttle_brake(accel_mps2: np.ndarray, vehicle: VehicleParams) -> tuple[np.ndarray, np.ndarray]:
    """Seed 002's throttle and brake in [0, 1] from accelerations [m/s^2]."""
    a = np.asarray(accel_mps2)
    return np.maximum(a, 0.0) / vehicle.max_accel_mps2, np.maximum(-a, 0.0) / vehicle.max_brake_mps2


@dataclass(frozen=True)
class NoiseConfig:
    """Random bursts added to the executed commands (never to the labels).

    A car not in a burst starts one with probability ``rate_per_s * policy period`` per decision.
    A burst holds a steering offset of random sign and magnitude, and an acceleration offset, for
    a random duration. A share ``brake_share`` of the bursts brake instead (acceleration offset
    ``-brake_mps2``), taking 1-6 m/s off the speed, so the expert's recovery to its cruise speed
    is labelled too.

    Attributes:
        rate_per_s: bursts per second of driving [1/s] (0 turns noise off).
        duration_s: (min, max) duration of a burst [s].
        steer_rad: (min, max) magnitude of the steering offset [rad].
        accel_mps2: the acceleration offset is uniform in +-this [m/s^2].
        brake_share: share of bursts that brake, in [0, 1].
        brake_mps2: (min, max) deceleration added by a braking burst [m/s^2].
    """

    rate_per_s: float = 0.12
    duration_s: tuple[float, float] = (0.5, 1.5)
    steer_rad: tuple[float, float] = (0.003, 0.015)
    accel_mps2: float = 1.0
    brake_share: float = 0.25
    brake_mps2: tuple[float, float] = (2.0, 4.0)

    def __post_init__(self) -> None:
        o = "NoiseConfig"
        check_range(o, "rate_per_s", self.rate_per_s, 0.0, 10.0)
        check_pair(o, "duration_s", self.duration_s, lo=0.0)
        check_pair(o, "steer_rad", self.steer_rad, lo=0.0)
        check_range(o, "accel_mps2", self.accel_mps2, 0.0, 10.0)
        check_range(o, "brake_share", self.brake_share, 0.0, 1.0)
        check_pair(o, "brake_mps2", self.brake_mps2, lo=0.0)


@dataclass(frozen=True)
class DataConfig:
    """What to collect.

    Attributes:
        split: ``"train"`` or ``"val"`` tracks.
        n_samples: samples to record.
        n_tracks: tracks of the split the cars cycle through.
        n_worlds: cars driven in lockstep.
        world: roads, traffic, car, time steps.
        expert: the expert's settings.
        noise: the noise bursts.
        camera: the camera (66 x 200 by default).
        restart_rate_per_s: take-overs per second of driving [1/s]: the car is re-placed as the
            evaluator re-places it after a collision (:func:`~e2e_lite.evaluation.restart_state`).
            The default, one per 20 s, is about twice as often as chapter 10's GMM collided (once
            per 39 s of driving) and doubles the share of samples between 20 and 24 m/s (7.6 % ->
            17.8 % on 16,000 training samples); chapter 04 measures it.
        seed: seeds the expert's draws, the noise and the start lanes.
    """

    split: str = "train"
    n_samples: int = 48_000
    n_tracks: int = 32
    n_worlds: int = 16
    world: WorldConfig = field(default_factory=WorldConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    restart_rate_per_s: float = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        o = "DataConfig"
        if self.split not in ("train", "val"):
            raise ValueError(f"{o}.split={self.split!r} is invalid: must be 'train' or 'val'")
        check_range(o, "n_samples", self.n_samples, 1, integer=True)
        check_range(o, "n_tracks", self.n_tracks, 1, integer=True)
        check_range(o, "n_worlds", self.n_worlds, 1, 1024, integer=True)
        check_range(o, "restart_rate_per_s", self.restart_rate_per_s, 0.0, 1.0)
        check_range(o, "seed", self.seed, 0, integer=True)

    @classmethod
    def for_profile(cls, profile: Profile, split: str = "train", **overrides: Any) -> DataConfig:
        """The profile's sizes: its sample counts, training tracks or validation tracks."""
        train = split == "train"
        kwargs: dict[str, Any] = {
            "split": split,
            "n_samples": profile.n_train_samples if train else profile.n_val_samples,
            "n_tracks": profile.n_train_tracks if train else profile.n_val_tracks,
            "n_worlds": profile.n_worlds,
            "world": WorldConfig.for_profile(profile),
            "seed": 0 if train else 1,
        }
        kwargs.update(overrides)
        return cls(**kwargs)

    @property
    def key(self) -> str:
        """Settings key of the dataset these settings make."""
        return settings_key("dataset-v2", self)


FIELDS = (
    "speed",
    "actuators",
    "trajectory",
    "affordances",
    "track",
    "s",
    "d",
    "lane",
    "curvature",
    "expert_state",
    "change_side",
    "overtaking",
    "noise",
)


@dataclass
class DrivingData:
    """A collected dataset: the arrays of the module table, their statistics and how it was made.

    Attributes:
        arrays: field name -> array (``images`` and every name in :data:`FIELDS`).
        stats: normalisation statistics, ``{"<field>_mean": ..., "<field>_std": ...}`` for speed,
            actuators, trajectory (per coordinate, (5, 2)) and affordances (per affordance).
        info: shares of situations, the collection's closed-loop metrics, the settings key.
    """

    arrays: dict[str, np.ndarray]
    stats: dict[str, np.ndarray]
    info: dict[str, Any]

    def __len__(self) -> int:
        return len(self.arrays["speed"])

    def __getattr__(self, name: str) -> np.ndarray:
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(name)


class _Recorder:
    """A policy: the expert plus noise bursts, recording every decision until ``n`` samples."""

    def __init__(self, cfg: DataConfig, progress: bool) -> None:
        self.cfg = cfg
        self.camera = cfg.camera
        self.expert = Expert(
            cfg.expert, vehicle=cfg.world.vehicle, sim=cfg.world.sim, seed=cfg.seed
        )
        self.rng = np.random.default_rng([cfg.seed, 23])
        n = cfg.n_samples
        h, w = cfg.camera.height_px, cfg.camera.width_px
        self.a: dict[str, np.ndarray] = {
            "images": np.empty((n, h, w, 3), dtype=np.uint8),
            "speed": np.empty(n, np.float32),
            "actuators": np.empty((n, 2), np.float32),
            "trajectory": np.empty((n, N_POINTS, 2), np.float32),
            "affordances": np.empty((n, len(AFFORDANCE_NAMES)), np.float32),
            "track": np.empty(n, np.int32),
            "s": np.empty(n, np.float32),
            "d": np.empty(n, np.float32),
            "lane": np.empty(n, np.int8),
            "curvature": np.empty(n, np.float32),
            "expert_state": np.empty(n, np.int8),
            "change_side": np.empty(n, np.int8),
            "overtaking": np.empty(n, bool),
            "noise": np.empty(n, bool),
        }
        self.count = 0
        self.bar = tqdm(
            total=n,
            desc=f"collect {cfg.split}",
            unit="sample",
            disable=not progress,
            leave=False,
            mininterval=0.5,
        )

    def reset(self, n_worlds: int) -> None:
        self.expert.reset(n_worlds)
        self.burst_left = np.zeros(n_worlds)  # seconds of burst left per car
        self.offset = np.zeros((n_worlds, 2))  # (steer, accel) offsets of the current bursts

    def done(self) -> bool:
        return self.count >= self.cfg.n_samples

    def act(self, obs: Observation) -> Actuation:
        traj = self.expert.trajectory_label(obs)  # before act: plans as they are now
        clean = self.expert.act(obs)
        n = len(obs.s)
        self._update_noise(n)
        take = min(n, self.cfg.n_samples - self.count)
        if take > 0:
            self._record(obs, clean, traj, take)
        period = self.cfg.world.sim.policy_period_s
        return Actuation(
            steer_rad=clean.steer_rad + self.offset[:, 0],
            accel_mps2=clean.accel_mps2 + self.offset[:, 1],
            restart=self.rng.random(n) < self.cfg.restart_rate_per_s * period,
        )

    def _update_noise(self, n: int) -> None:
        """Continue the bursts, end finished ones, maybe start new ones."""
        period = self.cfg.world.sim.policy_period_s
        nz = self.cfg.noise
        self.burst_left = np.maximum(self.burst_left - period, 0.0)
        self.offset[self.burst_left <= 0] = 0.0
        start = (self.burst_left <= 0) & (self.rng.random(n) < nz.rate_per_s * period)
        k = int(start.sum())
        if k:
            self.burst_left[start] = self.rng.uniform(*nz.duration_s, k)
            sign = self.rng.choice([-1.0, 1.0], k)
            self.offset[start, 0] = sign * self.rng.uniform(*nz.steer_rad, k)
            brake = self.rng.random(k) < nz.brake_share
            self.offset[start, 1] = np.where(
                brake,
                -self.rng.uniform(*nz.brake_mps2, k),
                self.rng.uniform(-nz.accel_mps2, nz.accel_mps2, k),
            )

    def _record(self, obs: Observation, clean: Actuation, traj: np.ndarray, take: int) -> None:
        sl = slice(self.count, self.count + take)
        a, plans, t = self.a, self.expert.plans[:take], slice(0, take)
        a["images"][sl] = obs.images[t]
        a["speed"][sl] = obs.speed[t]
        a["actuators"][sl, 0] = clean.steer_rad[t]
        a["actuators"][sl, 1] = clean.accel_mps2[t]
        a["trajectory"][sl] = traj[t]
        a["affordances"][sl] = affordances(obs.worlds[t], obs.s[t], obs.d[t], obs.heading_error[t])
        a["track"][sl] = [w.track.track_id[1] for w in obs.worlds[t]]
        a["s"][sl], a["d"][sl] = obs.s[t], obs.d[t]
        a["lane"][sl] = obs.lane[t]
        a["curvature"][sl] = obs.curvature[t]
        a["expert_state"][sl] = [p.state for p in plans]
        a["change_side"][sl] = [
            0 if p.state != CHANGE or p.path is None else (1 if p.path.d_to > p.path.d_from else -1)
            for p in plans
        ]
        a["overtaking"][sl] = [p.state == CHANGE and p.overtaking for p in plans]
        a["noise"][sl] = self.burst_left[t] > 0
        self.count += take
        self.bar.update(take)


def dataset_stats(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-column mean and standard deviation (floored at 1e-6) of speed, actuators, trajectory
    and affordances: ``{"<field>_mean": ..., "<field>_std": ...}``, float32."""
    out = {}
    for name in ("speed", "actuators", "trajectory", "affordances"):
        x = arrays[name].astype(np.float64)
        out[f"{name}_mean"] = x.mean(axis=0).astype(np.float32)
        out[f"{name}_std"] = np.maximum(x.std(axis=0), 1e-6).astype(np.float32)
    return out


def situation_shares(
    arrays: dict[str, np.ndarray], rows: np.ndarray | None = None
) -> dict[str, float]:
    """Shares of samples (0..1): on curves (|kappa| > 1e-4 1/m), in a lane change, overtaking to
    the left / right, returning, following (blocked), with a noise burst active. ``rows``: only
    these samples (default all)."""
    if rows is not None:
        keys = ("expert_state", "change_side", "overtaking", "curvature", "noise")
        arrays = {k: arrays[k][rows] for k in keys}
    state, side, over = arrays["expert_state"], arrays["change_side"], arrays["overtaking"]
    change = state == CHANGE
    return {
        "curve": float(np.mean(np.abs(arrays["curvature"]) > 1e-4)),
        "lane_change": float(np.mean(change)),
        "overtake_left": float(np.mean(change & over & (side > 0))),
        "overtake_right": float(np.mean(change & over & (side < 0))),
        "return": float(np.mean(change & ~over)),
        "pass": float(np.mean(state == PASS)),
        "follow": float(np.mean(state == FOLLOW)),
        "noise": float(np.mean(arrays["noise"])),
    }


#: Below this speed a sample is "slow" [m/s]: the evaluator restarts cars at 20 m/s and the roads'
#: cruise speed is 25 m/s.
SLOW_MPS = 22.0
#: An overtake whose rear axle has moved less than this from its lane centre towards its side has
#: just started [m].
CHANGE_START_M = 0.5


def situations(
    arrays: dict[str, np.ndarray], rows: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Masks of the situations that decide collisions, each (N,) bool (``rows``: only these):

    * ``"overtake_start"``: the expert has just started an overtake (in a lane change that is an
      overtake, the rear axle has moved less than :data:`CHANGE_START_M` from its lane centre
      towards the change's side: the change's end, near the target lane's centre, is left out);
    * ``"slow"``: speed below :data:`SLOW_MPS` (the states a learned driver restarts in);
    * ``"curve"``: on an arc (|curvature| > 1e-4 1/m).
    """
    take = (lambda x: x) if rows is None else (lambda x: x[rows])
    state, over = take(arrays["expert_state"]), take(arrays["overtaking"]).astype(bool)
    offset = take(arrays["affordances"])[:, AFFORDANCE_NAMES.index("center_offset_m")]
    moved = offset * take(arrays["change_side"])  # towards the change's side [m]
    return {
        "overtake_start": (state == CHANGE) & over & (moved >= 0.0) & (moved < CHANGE_START_M),
        "slow": take(arrays["speed"]) < SLOW_MPS,
        "curve": np.abs(take(arrays["curvature"])) > 1e-4,
    }


def road_lateral(
    points_m: np.ndarray, heading_rad: np.ndarray, curvature: np.ndarray
) -> np.ndarray:
    """The lateral offset [m] of the last of each trajectory's points from where the car would be
    keeping its lane, in the road's frame (left positive), ``(B,)``: the car-frame ``y`` plus what
    the car's heading error turns away (``psi x``) minus the road's own bend (``kappa x^2 / 2``).
    So "which side" does not depend on the car's heading or on the curve (small-angle forms).

    Args:
        points_m: (B, 5, 2) car-frame trajectories [m].
        heading_rad: (B,) heading minus the road's [rad] (the ``heading_rad`` affordance).
        curvature: (B,) the road's curvature [1/m].
    """
    x, y = np.asarray(points_m)[:, -1, 0], np.asarray(points_m)[:, -1, 1]
    return y + np.asarray(heading_rad) * x - np.asarray(curvature) * x * x / 2.0


def collect(cfg: DataConfig, progress: bool = True) -> DrivingData:
    """Drive the noisy expert until ``cfg.n_samples`` samples are recorded (no caching)."""
    rec = _Recorder(cfg, progress)
    ev = EvalConfig(
        miles=1e6,
        n_worlds=cfg.n_worlds,
        split=cfg.split,
        n_tracks=cfg.n_tracks,
        seed=cfg.seed,
    )
    result: EvalResult = evaluate(rec, cfg.world, ev, progress=False, stop_when=rec.done)
    rec.bar.close()
    info = {
        "key": cfg.key,
        "split": cfg.split,
        "n_samples": cfg.n_samples,
        "shares": situation_shares(rec.a),
        "manoeuvres": dict(rec.expert.manoeuvres),
        "collection": result.to_dict(with_events=False),
        "collision_events": result.events,
    }
    return DrivingData(rec.a, dataset_stats(rec.a), info)


def _save(path: Path, data: DrivingData, key: str) -> None:
    np.savez(
        path,
        **data.arrays,
        **{f"stat_{k}": v for k, v in data.stats.items()},
        info=np.array(to_json({**data.info, "key": key})),
    )


def _load(path: Path) -> tuple[DrivingData, str]:
    with np.load(path, allow_pickle=False) as z:
        info = json.loads(str(z["info"]))
        arrays = {k: z[k] for k in ("images", *FIELDS)}
        stats = {k[5:]: z[k] for k in z.files if k.startswith("stat_")}
    return DrivingData(arrays, stats, info), info["key"]


def dataset_path(cfg: DataConfig, name: str | None = None) -> Path:
    """Where the dataset of ``cfg`` is stored: ``<outputs>/data/<split>-<n>.npz``, or
    ``<outputs>/data/<name>.npz`` for a variant kept beside it (e.g. chapter 07's data collected
    the old way)."""
    return artifact_path("data", f"{name or f'{cfg.split}-{cfg.n_samples}'}.npz")


def load_or_collect(cfg: DataConfig, progress: bool = True, name: str | None = None) -> DrivingData:
    """The dataset of ``cfg`` from disk if it was made by these settings; else collect and save it
    (``name``: see :func:`dataset_path`)."""
    return cached(dataset_path(cfg, name), cfg.key, lambda: collect(cfg, progress), _save, _load)


def describe(data: DrivingData) -> str:
    """A few readable lines: size, shares of situations, the collection's collisions."""
    info = data.info
    sh = info["shares"]
    col = info["collection"]
    miles = col["miles"]
    return (
        f"{len(data)} samples ({info['split']}), {miles:.1f} mi driven, "
        f"{col['collisions']} collisions under noise\n"
        f"  curves {sh['curve']:.1%}, lane changes {sh['lane_change']:.1%} "
        f"(overtake left {sh['overtake_left']:.1%}, right {sh['overtake_right']:.1%}, "
        f"return {sh['return']:.1%}), passing {sh['pass']:.1%}, following {sh['follow']:.1%}, "
        f"noise active {sh['noise']:.1%}"
    )


# ------------------------------------------------------------------ recovery views (seed 003)
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
    worlds: dict[int, World] = {}
    camera = Camera(data_cfg.camera)
    tracker = LQRTracker(vehicle=data_cfg.world.vehicle)
    chunk = 256
    bar = tqdm(
        total=m,
        desc="recovery views",
        unit="view",
        disable=not progress,
        leave=False,
        mininterval=0.5,
    )
    for lo in range(0, m, chunk):
        sl = slice(lo, min(m, lo + chunk))
        r = rows[sl]
        tracks_idx = data.track[r]
        for t_idx in np.unique(tracks_idx).tolist():
            if t_idx not in worlds:
                worlds[t_idx] = make_world(data_cfg.world, data_cfg.split, t_idx)
        ws = [worlds[int(t_idx)] for t_idx in tracks_idx]
        s = data.s[r].astype(np.float64)
        d0 = data.d[r].astype(np.float64)
        d1 = d0 + shift[sl]
        he0 = data.affordances[r, 0].astype(np.float64)
        he1 = he0 + turn[sl]
        pose0 = np.array([w.track.pose(si, di) for w, si, di in zip(ws, s, d0)])
        pose1 = np.array([w.track.pose(si, di) for w, si, di in zip(ws, s, d1)])
        pose0[:, 2] += he0
        pose1[:, 2] += he1
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
        bar.update(len(r))
    bar.close()
    info = {
        "key": settings_key("recovery-v1", data.info["key"], cfg),
        "split": data.info["split"],
        "n_samples": m,
        "source_key": data.info["key"],
        "recovery": cfg,
        "source_rows": rows,
    }
    return DrivingData(out, dict(data.stats), info)


def load_or_make_recovery(
    data: DrivingData,
    data_cfg: DataConfig,
    cfg: RecoveryConfig | None = None,
    progress: bool = True,
) -> DrivingData:
    """The recovery views of ``data`` from disk if made by these settings, else render and save."""
    cfg = cfg or RecoveryConfig()
    key = settings_key("recovery-v1", data.info["key"], cfg)
    path = artifact_path("data", f"{data_cfg.split}-{data_cfg.n_samples}-recovery.npz")
    return cached(path, key, lambda: recovery_views(data, data_cfg, cfg, progress), _save, _load)


def concat(first: DrivingData, second: DrivingData) -> DrivingData:
    """Rows of ``first`` then ``second``; statistics (normalisation) of ``first``."""
    arrays = {k: np.concatenate([first.arrays[k], second.arrays[k]]) for k in first.arrays}
    info = {
        **first.info,
        "key": settings_key(first.info["key"], second.info["key"]),
        "parts": [first.info["key"], second.info["key"]],
    }
    return DrivingData(arrays, dict(first.stats), info)


def synthetic_data(n: int = 64, seed: int = 0) -> DrivingData:
    """Random frames and plausible random labels with every field of a real dataset: for tests and
    speed benchmarks that must not depend on a collected dataset (nothing to learn in it)."""
    rng = np.random.default_rng([seed, 97])
    arrays: dict[str, np.ndarray] = {
        "images": rng.integers(0, 256, (n, 66, 200, 3), dtype=np.uint8),
        "speed": rng.uniform(15.0, 25.0, n).astype(np.float32),
        "actuators": np.stack([rng.normal(0, 0.02, n), rng.normal(0, 1, n)], 1).astype(np.float32),
        "trajectory": (
            rng.normal(0, 1, (n, N_POINTS, 2)) + np.array([7.5, 0.0]) * np.arange(1, 6)[:, None]
        ).astype(np.float32),
        "affordances": rng.normal(0, 1, (n, len(AFFORDANCE_NAMES))).astype(np.float32),
    }
    for name in FIELDS:
        arrays.setdefault(name, np.zeros(n, dtype=np.float32))
    return DrivingData(
        arrays, dataset_stats(arrays), {"key": f"synthetic-{seed}-{n}", "split": "train"}
    )


class DrivingDataset(torch.utils.data.Dataset):
    """A ``torch`` view of :class:`DrivingData` (or a subset of its rows).

    Each item is a dict of tensors: ``image`` (3, H, W) uint8 (CHW; the models normalise),
    ``speed`` (1,) [m/s], ``actuators`` (2,) [rad, m/s^2], ``trajectory`` (10,) [m] (the 5 points
    flattened as x1, y1, ..., x5, y5), ``affordances`` (9,) (units in :data:`AFFORDANCE_NAMES`).
    Targets are in physical units; normalise them with ``data.stats``.

    Args:
        data: the dataset.
        indices: rows to expose (default: all).
    """

    def __init__(self, data: DrivingData, indices: np.ndarray | None = None) -> None:
        self.data = data
        self.indices = np.arange(len(data)) if indices is None else np.asarray(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.batch(np.array([self.indices[i]]), squeeze=True)

    def batch(
        self, rows: np.ndarray, squeeze: bool = False, device: torch.device | str | None = None
    ) -> dict[str, torch.Tensor]:
        """Items of dataset rows ``rows`` stacked along a first axis (one copy, no Python loop),
        on ``device`` when given (a model's, e.g. ``next(model.parameters()).device``)."""
        a = self.data.arrays
        out = {
            # NHWC rows permuted to NCHW: a channels-last view, no second copy
            "image": torch.from_numpy(a["images"][rows]).permute(0, 3, 1, 2),
            "speed": torch.from_numpy(a["speed"][rows, None].astype(np.float32)),
            "actuators": torch.from_numpy(a["actuators"][rows]),
            "trajectory": torch.from_numpy(a["trajectory"][rows].reshape(len(rows), -1)),
            "affordances": torch.from_numpy(a["affordances"][rows]),
        }
        if device is not None:
            out = {k: v.to(device) for k, v in out.items()}
        return {k: v[0] for k, v in out.items()} if squeeze else out
