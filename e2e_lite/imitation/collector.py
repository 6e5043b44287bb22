"""The expert's dataset (chapter 04): camera frames with clean labels, collected under noise.

The collector drives the :class:`~e2e_lite.control.expert.Expert` through the evaluator's
lockstep loop (:func:`~e2e_lite.driving.rollout.drive_shard`) on the training (or validation)
tracks, with random steering and acceleration *bursts* added to the commands it executes, so the
data also holds off-centre states and the expert's recovery; now and then a car is taken over and
re-placed as the evaluator re-places it after a collision (20 m/s, below cruise speed), so the
expert is shown getting back to speed from where a learned driver restarts (chapter 04). With a
learner it collects DAgger's rounds (chapter 12). One sample per policy step (10 Hz).

What one sample holds is :mod:`e2e_lite.learning.dataset`'s schema, re-exported here with the
labels of :mod:`e2e_lite.learning.labels`; seed 003's recovery views are :mod:`e2e_lite.imitation.recovery`.
"""

from __future__ import annotations

import contextlib
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..artifacts import artifact_path, cached, settings_key, versioned
from ..config import Profile, check_range, default_workers, tqdm
from ..control.affordances import affordances
from ..control.expert import Expert
from ..control.rules import ExpertConfig
from ..driving.evaluation import shard_cars
from ..driving.metrics import ShardResult, merge_shards
from ..driving.parallel import drive_in_processes, pinned_threads
from ..driving.rollout import EvalConfig, drive_shard
from ..learning.dataset import (  # noqa: F401 (re-exported: the chapters read the data's names here)
    CHANGE_START_M,
    FIELDS,
    SCHEMA,
    SLOW_MPS,
    DrivingData,
    DrivingDataset,
    allocate,
    concat,
    dataset_stats,
    load_dataset,
    road_lateral,
    save_dataset,
    situation_shares,
    situations,
    synthetic_data,
)
from ..learning.labels import AFFORDANCE_NAMES, CHANGE, GAP_CAP_M, N_POINTS, throttle_brake  # noqa: F401 (re-exported, as above)
from ..learning.models import weights_digest
from ..simulation.camera import CameraConfig
from ..simulation.policy import Actuation, Observation, car_rng
from ..simulation.world import WorldConfig
from .noise import Bursts, NoiseConfig


@dataclass(frozen=True)
class DataConfig:
    """What to collect.

    Attributes:
        split: ``"train"`` or ``"val"`` tracks.
        n_samples: samples to record.
        n_tracks: tracks of the split the cars cycle through (None: every car drives roads no
            other car and no earlier lap drove, from ``first_track`` on: fresh roads).
        n_worlds: cars driven in lockstep.
        world: roads, traffic, car, time steps.
        expert: the expert's settings (its home lane among them), who drives and labels.
        noise: the noise bursts.
        camera: the camera (66 x 200 by default).
        restart_rate_per_s: take-overs per second of driving [1/s], re-placing the car as the
            evaluator does after a collision (:func:`~e2e_lite.driving.rollout.restart_state`); one
            per 20 s doubles the samples between 20 and 24 m/s (chapter 04 measures it).
        seed: seeds the expert's draws, the noise and the start lanes.
        first_track: index of the split's first track the cars drive (DAgger's rounds and their
            control drive fresh training roads, chapter 12).
    """

    #: added after the course's datasets were keyed: at their defaults those keys stay
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = ("first_track",)

    split: str = "train"
    n_samples: int = 48_000
    n_tracks: int | None = 32
    n_worlds: int = 16
    world: WorldConfig = field(default_factory=WorldConfig)
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    restart_rate_per_s: float = 0.05
    seed: int = 0
    first_track: int = 0

    def __post_init__(self) -> None:
        o = "DataConfig"
        if self.split not in ("train", "val"):
            raise ValueError(f"{o}.split={self.split!r} is invalid: must be 'train' or 'val'")
        check_range(o, "n_samples", self.n_samples, 1, integer=True)
        if self.n_tracks is not None:
            check_range(o, "n_tracks", self.n_tracks, 1, integer=True)
        check_range(o, "first_track", self.first_track, 0, integer=True)
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
            "n_worlds": profile.collect_worlds,
            "world": WorldConfig.for_profile(profile),
            "seed": 0 if train else 1,
        }
        kwargs.update(overrides)
        return cls(**kwargs)

    @property
    def key(self) -> str:
        """Settings key of the dataset these settings make (v3: the fixed ``World.gap_ahead``)."""
        return settings_key(versioned("dataset"), self)


#: the fewest samples a collecting process is started for by default: a worker's start costs about
#: 3,000 samples on one core (4,000 took 3.4 s here in-process, 6.0 s in two workers)
MIN_SAMPLES_PER_WORKER = 6_000


def car_quotas(cfg: DataConfig) -> np.ndarray:
    """Samples each car records, ``(n_worlds,)``: ``n_samples`` shared out, the first cars one
    more when it does not divide. The dataset holds car 0's samples, then car 1's, and so on."""
    base, extra = divmod(cfg.n_samples, cfg.n_worlds)
    return base + (np.arange(cfg.n_worlds) < extra)


@dataclass(frozen=True)
class OnPolicy:
    """A DAgger collection (chapter 12), passed to :func:`collect`: ``learner`` drives, the expert
    executing a share ``beta`` of the decisions and labelling every state (its label is a
    function of the state, so it labels the learner's states as its own)."""

    learner: Any
    beta: float = 1.0

    #: how long before a collision a sample counts as "before a collision" [s]
    BEFORE_COLLISION_S: ClassVar[float] = 3.0

    def __post_init__(self) -> None:
        check_range("OnPolicy", "beta", self.beta, 0.0, 1.0)

    def key(self, cfg: DataConfig) -> str:
        """Its samples' key: the settings, the learner's weights (or class) and beta."""

        net = getattr(self.learner, "model", self.learner)
        who = weights_digest(net) if hasattr(net, "state_dict") else type(net).__name__
        return settings_key(cfg.key, "dagger", who, self.beta)


class _Recorder:
    """A policy: the expert plus noise bursts, recording every decision of cars ``cars`` until
    each has recorded its quota (:func:`car_quotas`). Every draw is the car's own (seeded by its
    index among all ``cfg.n_worlds`` cars), so a car records the same samples in any process.
    With ``on_policy`` its learner drives instead (:class:`OnPolicy`)."""

    #: uniforms each car draws per decision (a fixed count, so one draw never shifts another):
    #: restart, then :data:`~e2e_lite.imitation.noise.Bursts.DRAWS` for the bursts
    DRAWS = 9

    def __init__(
        self,
        cfg: DataConfig,
        cars: np.ndarray,
        advance: Callable[[float], None],
        on_policy: OnPolicy | None = None,
    ) -> None:
        self.cfg, self.advance, self.on_policy = cfg, advance, on_policy
        # the mixing draws: a stream of their own, so the expert's and the noise's are untouched
        self.mix_rngs = [car_rng(cfg.seed, 29, int(c)) for c in cars]
        self.camera = cfg.camera
        world = cfg.world
        self.expert = Expert(cfg.expert, vehicle=world.vehicle, sim=world.sim, seed=cfg.seed)
        self.quota = car_quotas(cfg)[cars]
        self.offset = np.concatenate([[0], np.cumsum(self.quota)[:-1]])  # car i's first row
        self.count = np.zeros(len(cars), dtype=np.int64)
        self.rngs = [car_rng(cfg.seed, 23, int(c)) for c in cars]
        h, w = cfg.camera.height_px, cfg.camera.width_px
        self.a = allocate(int(self.quota.sum()), (h, w))
        self.dart_rngs = [car_rng(cfg.seed, 37, int(c)) for c in cars]  # (a stream of its own)
        n = int(self.quota.sum())
        #: with a learner, per sample: its plan's distance from the expert's label (the largest
        #: over the 5 points) [m], its commands, and whether a collision followed within
        #: OnPolicy.BEFORE_COLLISION_S
        self.side = {
            "disagreement_m": np.zeros(n),
            "learner_steer_rad": np.zeros(n),
            "learner_accel_mps2": np.zeros(n),
            "before_collision": np.zeros(n, dtype=bool),
        }

    def seed_cars(self, cars: np.ndarray) -> None:
        self.expert.seed_cars(cars)

    def reset(self, n_worlds: int) -> None:
        self.expert.reset(n_worlds)
        if self.on_policy is not None:
            self.on_policy.learner.reset(n_worlds)
        self.bursts = Bursts(self.cfg.noise, self.cfg.world.sim.policy_period_s, n_worlds)

    def done(self) -> np.ndarray:
        """Which cars have recorded their quota (the rollout stops them)."""
        return self.count >= self.quota

    def act(self, obs: Observation) -> Actuation:
        traj = self.expert.trajectory_label(obs)
        clean = self.expert.act(obs)
        u = np.stack([r.random(self.DRAWS) for r in self.rngs])  # (B, DRAWS) in [0, 1)
        self.bursts.update(u, obs.speed)
        learned = None if self.on_policy is None else self.on_policy.learner.act(obs)
        if learned is not None and obs.collided is not None:
            self._mark_before_collision(np.flatnonzero(obs.collided))
        rows = np.flatnonzero(self.count < self.quota)
        if len(rows):
            if learned is not None:
                self._record_learner(learned, traj, rows)
            self._record(obs, clean, traj, rows)
        period = self.cfg.world.sim.policy_period_s
        deep = self.bursts.slow_to > 0  # braked whatever the expert commands
        steer, accel = clean.steer_rad, clean.accel_mps2
        if learned is not None:  # DAgger: the learner drives, but on the expert's turns
            expert_turn = np.array([r.random() for r in self.mix_rngs]) < self.on_policy.beta
            steer = np.where(expert_turn, steer, learned.steer_rad)
            accel = np.where(expert_turn, accel, learned.accel_mps2)
        nz = self.cfg.noise
        if nz.dart_steer_rad or nz.dart_accel_mps2:  # DART: white noise on every decision
            white = np.stack([r.normal(size=2) for r in self.dart_rngs])  # (B, 2)
            steer = steer + nz.dart_steer_rad * white[:, 0]
            accel = accel + nz.dart_accel_mps2 * white[:, 1]
        return Actuation(
            steer_rad=steer + self.bursts.offset_cmd[:, 0],
            accel_mps2=np.where(deep, 0.0, accel) + self.bursts.offset_cmd[:, 1],
            restart=u[:, 0] < self.cfg.restart_rate_per_s * period,
        )

    def _record_learner(self, learned: Actuation, traj: np.ndarray, t: np.ndarray) -> None:
        """Record, for cars ``t``, the learner's commands and how far its plan (the trajectory it
        follows) lies from the expert's label ``traj``."""
        sl = self.offset[t] + self.count[t]
        self.side["learner_steer_rad"][sl] = learned.steer_rad[t]
        self.side["learner_accel_mps2"][sl] = learned.accel_mps2[t]
        plan = getattr(self.on_policy.learner, "last", {}).get("points")
        if plan is not None:
            apart = np.linalg.norm(plan[t] - traj[t], axis=-1).max(axis=-1)
            self.side["disagreement_m"][sl] = apart

    def _mark_before_collision(self, cars: np.ndarray) -> None:
        """Cars ``cars`` collided since their last decision: their samples of the last
        :data:`OnPolicy.BEFORE_COLLISION_S` led there."""
        period = self.cfg.world.sim.policy_period_s
        back = round(OnPolicy.BEFORE_COLLISION_S / period)
        for i in cars.tolist():
            end = self.offset[i] + self.count[i]
            self.side["before_collision"][max(self.offset[i], end - back) : end] = True

    def _record(
        self,
        obs: Observation,
        clean: Actuation,
        traj: np.ndarray,
        t: np.ndarray,
    ) -> None:
        """Record cars ``t`` (rows of ``obs``), each at its next row of the arrays (``traj``: the
        expert's labels)."""
        sl = self.offset[t] + self.count[t]
        a, decisions = self.a, [self.expert.decisions[i] for i in t.tolist()]
        worlds = [obs.worlds[i] for i in t.tolist()]
        a["images"][sl] = obs.images[t]
        a["speed"][sl] = obs.speed[t]
        a["actuators"][sl, 0] = clean.steer_rad[t]
        a["actuators"][sl, 1] = clean.accel_mps2[t]
        a["trajectory"][sl] = traj[t]
        a["affordances"][sl] = affordances(worlds, obs.s[t], obs.d[t], obs.heading_error[t])
        a["track"][sl] = [w.track.track_id[1] for w in worlds]
        a["s"][sl], a["d"][sl] = obs.s[t], obs.d[t]
        a["lane"][sl] = obs.lane[t]
        a["curvature"][sl] = obs.curvature[t]
        a["expert_state"][sl] = [dec.state for dec in decisions]
        a["change_side"][sl] = [dec.side if dec.state == CHANGE else 0 for dec in decisions]
        a["overtaking"][sl] = [dec.state == CHANGE and dec.overtaking for dec in decisions]
        a["noise"][sl] = self.bursts.burst_left[t] > 0
        self.count[t] += 1
        self.advance(len(t))


def collect_cars(
    cfg: DataConfig,
    cars: np.ndarray,
    advance: Callable[[float], None],
    on_policy: OnPolicy | None = None,
) -> tuple[dict[str, np.ndarray], ShardResult, dict[str, int]]:
    """Drive cars ``cars`` (of ``cfg.n_worlds``) to their quotas: their samples (car after car),
    the drive's metrics and the expert's manoeuvres; one process's share of :func:`collect`."""
    rec = _Recorder(cfg, cars, advance, on_policy)
    roads = {"split": cfg.split, "n_tracks": cfg.n_tracks, "first_track": cfg.first_track}
    ev = EvalConfig(miles=1e6, n_worlds=cfg.n_worlds, seed=cfg.seed, **roads)
    shard = drive_shard(rec, cfg.world, ev, cars, stop_when=rec.done)  # (it counts samples)
    return (
        {**rec.a, **{f"side/{k}": v for k, v in rec.side.items()}},
        shard,
        dict(rec.expert.manoeuvres),
    )


def collect(
    cfg: DataConfig,
    progress: bool = True,
    workers: int | None = None,
    *,
    on_policy: OnPolicy | None = None,
) -> DrivingData:
    """Drive the noisy expert until ``cfg.n_samples`` samples are recorded (no caching), or with
    ``on_policy`` a DAgger collection: its learner drives, the expert labels (:class:`OnPolicy`).

    The cars are shared out over ``workers`` processes (default: every core,
    :func:`~e2e_lite.config.default_workers`, at most one per :data:`MIN_SAMPLES_PER_WORKER`);
    the arrays are the same bytes for any count. A learner's cars are cut in whole forward
    groups, one torch thread each, so its samples do not depend on the count either."""
    t_wall = time.perf_counter()
    if workers is None:  # every core, but no worker for fewer samples than its start is worth
        workers = min(default_workers(), max(1, cfg.n_samples // MIN_SAMPLES_PER_WORKER))
    check_range("collect", "workers", workers, 1, integer=True)
    bar = tqdm(
        total=cfg.n_samples,
        desc=f"collect {cfg.split}",
        unit="sample",
        disable=not progress,
        leave=False,
        mininterval=0.5,
    )
    if on_policy is None:
        cars = np.array_split(np.arange(cfg.n_worlds), min(workers, cfg.n_worlds))
    else:
        cars = shard_cars(cfg.n_worlds, workers)
    try:
        if len(cars) == 1:
            with pinned_threads() if on_policy is not None else contextlib.nullcontext():
                parts = [collect_cars(cfg, cars[0], lambda k: bar.update(int(k)), on_policy)]
        else:
            jobs = [(collect_cars, (cfg, c), {"on_policy": on_policy}) for c in cars]
            parts = drive_in_processes(jobs, lambda k: bar.update(int(k)))
    finally:
        bar.close()
    h, w = cfg.camera.height_px, cfg.camera.width_px
    a = allocate(cfg.n_samples, (h, w))
    side_names = [name for name in parts[0][0] if name.startswith("side/")]
    side = {
        name[5:]: np.concatenate([arrays[name] for arrays, _, _ in parts]) for name in side_names
    }
    row = 0
    for k, (arrays, shard, counts) in enumerate(parts):  # car after car: blocks of cars in order
        n = len(arrays["speed"])
        for name in a:
            a[name][row : row + n] = arrays[name]
        row += n
        parts[k] = ({}, shard, counts)  # (the part's frames are copied: free them now)
    result = merge_shards([shard for _, shard, _ in parts], 0.0, time.perf_counter() - t_wall)
    manoeuvres: Counter = Counter()
    for _, _, counts in parts:
        manoeuvres.update(counts)
    info = {
        "key": cfg.key if on_policy is None else on_policy.key(cfg),
        "split": cfg.split,
        "n_samples": cfg.n_samples,
        "shares": situation_shares(a),
        "manoeuvres": {k: int(manoeuvres[k]) for k in parts[0][2]},
        "collection": result.to_dict(with_events=False),
        "collision_events": result.events,
    }
    if on_policy is not None:  # (not stored: DAgger keeps a gated part of its drives)
        info["on_policy"] = side
    return DrivingData(a, dataset_stats(a), info)


def dataset_path(cfg: DataConfig, name: str | None = None) -> Path:
    """Where the dataset of ``cfg`` is stored: ``<outputs>/data/<split>-<n>.npz``, or
    ``<outputs>/data/<name>.npz`` for a variant kept beside it."""
    return artifact_path("data", f"{name or f'{cfg.split}-{cfg.n_samples}'}.npz")


def load_or_collect(
    cfg: DataConfig, progress: bool = True, name: str | None = None, workers: int | None = None
) -> DrivingData:
    """The dataset of ``cfg`` from disk if it was made by these settings; else collect it (on
    ``workers`` processes, see :func:`collect`) and save it (``name``: see :func:`dataset_path`)."""
    return cached(
        dataset_path(cfg, name),
        cfg.key,
        lambda: collect(cfg, progress, workers),
        save_dataset,
        load_dataset,
    )


def describe(data: DrivingData) -> str:
    """A few readable lines: size, shares of situations, the collection's collisions. Returns and
    passing, which an expert keeping its own lane (the course's) never does, are left out at 0."""
    info = data.info
    sh = info["shares"]
    col = info["collection"]
    miles = col["miles"]
    back = f", return {sh['return']:.1%}" if sh["return"] else ""
    passing = f"passing {sh['pass']:.1%}, " if sh["pass"] else ""
    return (
        f"{len(data)} samples ({info['split']}), {miles:.1f} mi driven, "
        f"{col['collisions']} collisions under noise\n"
        f"  curves {sh['curve']:.1%}, lane changes {sh['lane_change']:.1%} "
        f"(overtake left {sh['overtake_left']:.1%}, right {sh['overtake_right']:.1%}{back}), "
        f"{passing}following {sh['follow']:.1%}, noise active {sh['noise']:.1%}"
    )
