"""DAgger (Ross, Gordon & Bagnell 2011, "A reduction of imitation learning and structured
prediction to no-regret online learning"), aimed at the states where the learner fails
(chapter 12).

Behaviour cloning trains on the expert's states; a learner that errs by a little drifts into
states the expert never showed, where it errs more: over a horizon of T decisions its mistakes
can grow as ``eps T^2``. Training on the learner's own states, labelled by the expert, bounds
them by ``eps T`` (their Theorem 3.1). Four things make the course's rounds the theory's:

* **one labeller**: the course's expert, whose label is a function of the state alone
  (:mod:`e2e_lite.control.expert`), labelled chapter 04's data and labels every round: every
  sample a fine-tune draws carries its label;
* **rare states reached**: a round drives :attr:`DaggerConfig.drive` times more decisions than
  it keeps, and keeps the states where the network's plan and the expert's disagree most and the
  seconds before each collision (:func:`gate`: Prakash et al.'s filter, HG-DAgger's gate);
* **the whole aggregate**: each round fine-tunes on rows drawn from everything gathered so far,
  chapter 04's data included (:func:`aggregate_draw`), as CS285 and the ``imitation`` library do;
* **the iterate chosen**: no-regret guarantees that *some* iterate is good (Cheng & Boots 2018),
  so every iterate drives validation roads and the one that collides least, among those that
  leave the lane centre no more often than the start, is kept (:func:`kept_iterate`).

Three arms (:data:`ARMS`) differ in one thing each. ``dagger``: the network drives.
``control``: the expert drives, with white noise on its commands fitted to the network's
measured command error (DART, Laskey et al. 2017, :func:`dart_noise`), gated, labelled and
aggregated the same way: only the states differ. ``no_new_data``: the same fine-tunes on chapter
04's data alone, which says what the fine-tunes themselves do. Every round
of every arm stores its samples and its network (:class:`RoundSpec`), so a cut run goes on where
it stopped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..artifacts import added_later, artifact_path, cached, seeded, settings_key
from ..config import Profile, check_range
from ..driving.rollout import EvalConfig, disjoint_runs
from ..learning.checkpoints import train_or_load, training_data_key
from ..learning.dataset import DrivingData, allocate
from ..learning.labels import AFFORDANCE_INDEX
from ..learning.models import DrivingModel
from ..simulation.world import WorldConfig
from ..stats.rates import poisson_ci
from . import recipes
from .agents import TrajectoryAgent
from .collector import (
    DataConfig,
    NoiseConfig,
    OnPolicy,
    collect,
    load_dataset,
    save_dataset,
)

#: the three arms: the network drives; the expert drives with DART's noise; no new data
ARMS = ("dagger", "control", "no_new_data")
#: each seed's rounds drive training tracks from here on, far from the data's own (0 .. 31)
FIRST_TRACK = 100_000
#: tracks a round may use (cars x laps); seeds and rounds are this far apart
TRACK_STRIDE = 1_000
#: the control's DART pilot: decisions per kept sample the expert drives without noise, the
#: network along, to measure the network's command errors
DART_PILOT = 0.25
#: the features of a state whose shift is measured: (name, where the dataset holds it)
SHIFT_FEATURES = {
    "lateral offset [m]": ("affordances", AFFORDANCE_INDEX["center_offset_m"]),
    "heading error [rad]": ("affordances", AFFORDANCE_INDEX["heading_rad"]),
    "speed [m/s]": ("speed", None),
    "gap ahead [m]": ("affordances", AFFORDANCE_INDEX["gap_ego_m"]),
}


@dataclass(frozen=True)
class DaggerConfig:
    """DAgger's rounds, the same for every arm.

    Attributes:
        rounds: rounds of driving, gating, aggregating and fine-tuning.
        samples: samples each round keeps [samples].
        drive: decisions a round drives per sample it keeps (the network's, or the expert's).
        steps_samples: rows each round's fine-tune draws from the whole aggregate (one pass
            over them at chapter 09's fine-tune settings) [samples].
        gate_m: the disagreement the gate counts as a disagreement: the largest distance over
            the 5 points between the network's plan and the expert's label [m].
        beta: the share of decisions the expert executes in DAgger's drives (Ross et al.'s
            first round, the expert alone, is chapter 04's data).
        val_miles: validation miles every iterate of a seed drives, to be chosen on [mi].
        dart_scale: the control's DART noise over the network's measured command errors.
    """

    rounds: int = 4
    samples: int = 8_000
    drive: float = 3.0
    steps_samples: int = 8_000
    gate_m: float = 1.0
    beta: float = 0.0
    val_miles: float = 25.0
    dart_scale: float = 1.0

    def __post_init__(self) -> None:
        o = "DaggerConfig"
        check_range(o, "rounds", self.rounds, 1, 20, integer=True)
        check_range(o, "samples", self.samples, 1, integer=True)
        check_range(o, "drive", self.drive, 1.0, 100.0)
        check_range(o, "steps_samples", self.steps_samples, 1, integer=True)
        check_range(o, "gate_m", self.gate_m, 0.0, 100.0)
        check_range(o, "beta", self.beta, 0.0, 1.0)
        check_range(o, "val_miles", self.val_miles, 0.0, lo_open=True)
        check_range(o, "dart_scale", self.dart_scale, 0.0, 10.0)

    @classmethod
    def for_profile(cls, profile: Profile, **changes: Any) -> DaggerConfig:
        """The profile's rounds: a sixth of the training data kept per round in the full profile,
        as many drawn from the aggregate for each fine-tune."""
        samples = max(profile.collect_worlds * 8, profile.n_train_samples // 6)
        steps = samples
        sizes = {"samples": samples, "steps_samples": steps, "val_miles": profile.eval_miles / 4}
        sizes["rounds"] = 2 if profile.quick else cls.rounds  # (the quick profile tests the code)
        return cls(**{**sizes, **changes})


def val_roads(miles: float, n_worlds: int) -> EvalConfig:
    """Where every iterate drives to be chosen: validation roads (a choice is made there, so
    never on the test roads that the verdicts drive)."""
    return EvalConfig(miles=miles, n_worlds=n_worlds, split="val")


def val_run(profile: Profile, seed: int, miles: float) -> EvalConfig:
    """Training ``seed``'s own validation roads, ``miles`` of them: every iterate of that seed
    drives them, so its iterates are compared on equal terms, and no other seed drives them."""

    ev = val_roads(miles * (seed + 1), profile.ablation_worlds)
    return disjoint_runs(ev, WorldConfig.for_profile(profile), seed + 1)[seed]


@dataclass(frozen=True)
class RoundSpec:
    """Which round: the profile and the rounds' settings, the training ``seed``, the round's
    ``index`` (0-based) and its ``arm``. Everything stored for a round is named and keyed from
    this one value: the roads it drives (:meth:`data`), its samples' key and file, its network's
    name."""

    profile: Profile
    cfg: DaggerConfig
    seed: int
    index: int
    arm: str

    def __post_init__(self) -> None:
        if self.arm not in ARMS:
            raise ValueError(f"arm={self.arm!r} is invalid: must be one of {ARMS}")
        check_range("RoundSpec", "index", self.index, 0, self.cfg.rounds - 1, integer=True)

    def data(self, noise: NoiseConfig | None = None, decisions: int | None = None) -> DataConfig:
        """What the round drives: ``decisions`` (default ``cfg.drive x cfg.samples``) on fresh
        training roads of its own (the same roads and start lanes in DAgger and the control),
        without bursts or take-overs; with ``noise``, the control's DART noise."""
        first = FIRST_TRACK + (self.seed * self.cfg.rounds + self.index) * TRACK_STRIDE
        return DataConfig.for_profile(
            self.profile,
            "train",
            n_samples=decisions or round(self.cfg.drive * self.cfg.samples),
            n_tracks=None,
            first_track=first,
            seed=1_000 + self.seed,
            noise=noise or NoiseConfig(rate_per_s=0.0),
            restart_rate_per_s=0.0,
        )

    @property
    def stem(self) -> str:
        """The stored names' stem: the arm, and for rounds of other settings than the profile's
        a tag of them (an exercise's rounds never overwrite the course's)."""
        default = DaggerConfig.for_profile(self.profile)
        tag = "" if self.cfg == default else "_" + settings_key(self.cfg, length=6)
        return f"12_{self.arm}{tag}"

    @property
    def samples_name(self) -> str:
        """The file of the round's kept samples under ``<outputs>/data/``."""
        return seeded(self.stem, self.seed) + f"_round{self.index + 1}.npz"

    @property
    def network_name(self) -> str:
        """The checkpoint name of the network the round fine-tunes."""
        return seeded(f"{self.stem}_round{self.index + 1}", self.seed, plain_zero=True)

    def on_policy(self, learner: DrivingModel) -> OnPolicy:
        """How the round drives: DAgger's network (the expert executing ``cfg.beta`` of the
        decisions), or the control's expert with the network along, planning at every state (its
        plans are what the gate compares)."""
        beta = self.cfg.beta if self.arm == "dagger" else 1.0
        return OnPolicy(TrajectoryAgent(learner.eval()), beta)

    def samples_key(self, learner: DrivingModel) -> str:
        """The key of the round's kept samples: the drive's settings, the network's weights, and
        the gate (anything else drives anew, and the fine-tunes on it retrain). The control's
        noise is DART's fit to these weights (:meth:`dart`), so they key it too."""
        gate = (self.cfg.samples, self.cfg.gate_m, OnPolicy.BEFORE_COLLISION_S)
        scale = added_later(dart_scale=(self.cfg.dart_scale, 1.0))
        dart = ("dart", DART_PILOT, *scale) if self.arm == "control" else ()
        return settings_key(self.on_policy(learner).key(self.data()), "gate", *gate, *dart)

    def dart(self, learner: DrivingModel, progress: bool = True) -> NoiseConfig:
        """DART's noise for the control's drive: the expert drives a pilot of
        :data:`DART_PILOT` x ``cfg.samples`` decisions without noise, the network along, and the
        noise is the spread of the network's command errors there (:func:`dart_noise`)."""
        pilot = self.data(decisions=max(1, round(DART_PILOT * self.cfg.samples)))
        drive = collect(pilot, progress, on_policy=self.on_policy(learner))
        side = drive.info["on_policy"]
        learner_cmd = np.stack([side["learner_steer_rad"], side["learner_accel_mps2"]], axis=1)
        return dart_noise(learner_cmd, drive.arrays["actuators"], self.cfg.dart_scale)

    def samples(self, learner: DrivingModel, progress: bool = True) -> DrivingData:
        """The round's kept samples (:func:`gate` of its drive), stored and reused while the
        settings and the network's weights are the same."""
        key = self.samples_key(learner)

        def make() -> DrivingData:
            noise = self.dart(learner, progress) if self.arm == "control" else None
            drive = collect(self.data(noise), progress, on_policy=self.on_policy(learner))
            rows, found = gate(drive, self.cfg.samples, self.cfg.gate_m)
            kept = subset(drive, rows, key)
            kept.info.update(found)
            if noise is not None:
                kept.info["dart"] = {
                    "steer_rad": noise.dart_steer_rad,
                    "accel_mps2": noise.dart_accel_mps2,
                }
            return kept

        path = artifact_path("data", self.samples_name)
        return cached(path, key, make, save_dataset, load_dataset)


def gate(drive: DrivingData, keep: int, gate_m: float) -> tuple[np.ndarray, dict[str, Any]]:
    """The ``keep`` rows of a round's ``drive`` to learn from: first the seconds before each
    collision, then the rest by how far the network's plan lay from the expert's label, most
    first (ties by row). Returns the rows (sorted) and what was kept: how many came from before
    a collision, how many disagreed beyond ``gate_m``, of how many driven."""
    side = drive.info["on_policy"]
    apart = np.asarray(side["disagreement_m"], dtype=float)
    before = np.asarray(side["before_collision"], dtype=bool)
    order = np.lexsort((np.arange(len(apart)), -apart, ~before))  # before first, then far apart
    rows = np.sort(order[: min(keep, len(order))])
    return rows, {
        "gate": {
            "driven": len(apart),
            "kept": len(rows),
            "before_collision": int(before[rows].sum()),
            "before_collision_driven": int(before.sum()),
            "beyond_gate": int((apart[rows] > gate_m).sum()),
            "beyond_gate_driven": int((apart > gate_m).sum()),
            "disagreement_median_m": float(np.median(apart)) if len(apart) else 0.0,
        }
    }


def subset(data: DrivingData, rows: np.ndarray, key: str) -> DrivingData:
    """Rows ``rows`` of ``data``, keyed ``key``, with its collection's summary (not its per-row
    side arrays)."""
    arrays = {name: a[rows] for name, a in data.arrays.items()}
    info = {k: v for k, v in data.info.items() if k != "on_policy"}
    return DrivingData(arrays, dict(data.stats), {**info, "key": key, "n_samples": len(rows)})


def dart_noise(learner_cmd: np.ndarray, expert_cmd: np.ndarray, scale: float = 1.0) -> NoiseConfig:
    """DART's noise for the control: white noise whose standard deviations are those of the
    network's command errors, ``learner_cmd - expert_cmd`` ``(N, 2)`` (steer [rad], accel
    [m/s^2]), at the states it was measured on, times ``scale``."""
    err = np.asarray(learner_cmd, dtype=float) - np.asarray(expert_cmd, dtype=float)
    steer, accel = (float(x) for x in scale * err.std(axis=0))
    return NoiseConfig(
        rate_per_s=0.0, dart_steer_rad=min(steer, 0.5), dart_accel_mps2=min(accel, 10.0)
    )


def aggregate_draw(parts: list[DrivingData], n_rows: int, seed: int, r: int) -> DrivingData:
    """A round's fine-tune data: ``n_rows`` rows drawn (seeded, without replacement) from the
    whole aggregate ``parts`` (chapter 04's data first); the normalisation of the first part (the
    network's own). Its key names every part and the rows drawn."""
    sizes = np.array([len(d) for d in parts])
    n = min(n_rows, int(sizes.sum()))
    rows = np.sort(np.random.default_rng([seed, r, 59]).choice(sizes.sum(), n, replace=False))
    arrays = allocate(n, parts[0].arrays["images"].shape[1:3])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    at = 0
    for d, first, end in zip(parts, starts[:-1], starts[1:]):
        mine = rows[(rows >= first) & (rows < end)] - first
        for name in arrays:
            arrays[name][at : at + len(mine)] = d.arrays[name][mine]
        at += len(mine)
    key = settings_key([d.info["key"] for d in parts], rows.tobytes().hex()[:64], n)
    info = {"key": key, "split": "train", "parts": [d.info["key"] for d in parts]}
    return DrivingData(arrays, dict(parts[0].stats), info)


def covariate_shift(visited: DrivingData, trained_on: list[DrivingData]) -> dict[str, float]:
    """How far the states ``visited`` lie from the data the network was trained on: per feature
    of :data:`SHIFT_FEATURES`, the share of visited states outside that data's 1-99 % range, and
    ``"any"``, the share outside in at least one feature (about 2 % x features for the same
    distribution; more when the visits leave the data)."""
    out, outside_any = {}, np.zeros(len(visited), dtype=bool)
    for name, (field, col) in SHIFT_FEATURES.items():

        def column(d: DrivingData, field: str = field, col: int | None = col) -> np.ndarray:
            x = d.arrays[field]
            return x if col is None else x[:, col]

        ref = np.concatenate([column(d) for d in trained_on])
        lo, hi = np.percentile(ref, [1.0, 99.0])
        x = column(visited)
        outside = (x < lo) | (x > hi)
        out[name] = float(outside.mean())
        outside_any |= outside
    out["any"] = float(outside_any.mean())
    return out


def kept_iterate(collisions: list[int], off_centre: list[int]) -> int:
    """The iterate to keep, declared with both outcomes, from each iterate's collisions and
    off-centre episodes on the same validation roads (counts, the start first): among the
    iterates whose off-centre episodes are no more than the start's could be by chance (at most
    the upper end of the exact 95 % interval of the start's count), the one that collided least;
    among ties, the latest (it learned from the most data). The start always qualifies."""
    bound = poisson_ci(int(off_centre[0]), 1.0)[1]  # (the count's own interval: exposure 1)
    allowed = [i for i, o in enumerate(off_centre) if o <= bound]
    least = min(collisions[i] for i in allowed)
    return max(i for i in allowed if collisions[i] == least)


@dataclass
class Round:
    """One round of one arm: its samples and the aggregate's size after it, their covariate
    shift, what the gate kept, its fine-tuned network, and its drive's closed-loop metrics."""

    arm: str
    round: int
    samples: int
    aggregate: int
    shift: dict[str, float]
    gate: dict[str, Any]
    name: str
    model: DrivingModel
    collection: dict[str, Any]


#: what :func:`run` returns: the start network, and each arm's rounds
Run = tuple[DrivingModel, dict[str, list[Round]]]


def run(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    weight: float,
    seed: int,
    cfg: DaggerConfig | None = None,
    *,
    arms: tuple[str, ...] = ARMS,
    progress: bool = True,
) -> Run:
    """The rounds of ``arms`` for training ``seed``, from chapter 09's CVaR network of that seed
    (the start network, trained first if missing): ``(start, {arm: [Round, ...]})``. Every
    round's samples and fine-tune are stored and reused."""
    cfg = cfg or DaggerConfig.for_profile(profile)
    start, _, _ = recipes.gmm_affordance_cvar(profile, train, val, weight, seed)
    start_name = recipes.seeded_name("09_gmm_affordance_cvar", seed)
    objective, tcfg = recipes.finetune_settings(profile, weight, seed, "mean")
    out: dict[str, list[Round]] = {}
    for arm in arms:
        aggregate, parent, model = [train], start_name, start
        parent_key = training_data_key(train, val)
        rounds = []
        for r in range(cfg.rounds):
            spec = RoundSpec(profile, cfg, seed, r, arm)
            new, shift, found, collection = None, {}, {}, {}
            if arm != "no_new_data":
                new = spec.samples(model, progress)
                shift = covariate_shift(new, aggregate[:1])  # against chapter 04's data
                found, collection = new.info.get("gate", {}), new.info.get("collection", {})
                aggregate.append(new)
            data = aggregate_draw(aggregate, cfg.steps_samples, seed, r)
            model, _ = train_or_load(
                spec.network_name,
                recipes.AFFORDANCE_CFG,
                tcfg,
                objective,
                data,
                val,
                init_from=parent,
                parent_data_key=parent_key,
                carry_optimizer=True,
                progress=progress,
            )
            size = sum(len(d) for d in aggregate)
            kept = 0 if new is None else len(new)
            rounds.append(
                Round(arm, r + 1, kept, size, shift, found, spec.network_name, model, collection)
            )
            parent, parent_key = spec.network_name, training_data_key(data, val)
        out[arm] = rounds
    return start, out
