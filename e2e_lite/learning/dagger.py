"""DAgger (Ross, Gordon & Bagnell 2011, "A reduction of imitation learning and structured
prediction to no-regret online learning"): the learner drives, the expert labels what it visits,
the data is aggregated and the network fine-tuned (chapter 12).

Behaviour cloning trains on the expert's states; a learner that errs by a little drifts into
states the expert never showed, where it errs more: over a horizon of T decisions its mistakes
can grow as ``eps T^2``. Training on the learner's own states, labelled by the expert, bounds
them by ``eps T`` (their Theorem 3.1).

A **round** (:func:`run`, one :class:`RoundSpec` each): the current network drives closed loop on
fresh *training* roads (never validation or test roads), the expert executing a share ``beta`` of
the decisions (:func:`~e2e_lite.learning.collector.collect` with an
:class:`~e2e_lite.learning.collector.OnPolicy`); the expert labels every state visited, in the
dataset's schema; collisions and stalls re-place the car as the evaluator does. The round's
samples join the aggregate, and the network is fine-tuned on them plus as many samples replayed
from the earlier data (:func:`finetune_set`), with chapter 09's control fine-tune (the chapter-08
loss reduced by the mean, one epoch, its parent's Adam carried at a tenth of the rate:
:func:`~e2e_lite.learning.recipes.finetune_settings`).

The **control** (:data:`ARMS`): the same rounds with the same number of samples from the expert's
own driving (chapter 04's collector, noise and take-overs included) on the same fresh roads, and
the same fine-tunes from the same parent. DAgger against it asks whether the learner's *states*
help, not merely more data and more epochs.

The **covariate shift** (:func:`covariate_shift`): the share of a round's visited states that lie
outside the 1-99 % range of the data the network was trained on, per feature of
:data:`SHIFT_FEATURES`. It should fall round by round if DAgger works.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..artifacts import artifact_path, cached, seeded, settings_key
from ..config import Profile, check_range
from ..control.drivers import LaneKeeper
from ..control.labels import AFFORDANCE_INDEX
from ..driving.rollout import EvalConfig
from . import recipes
from .agents import TrajectoryAgent
from .checkpoints import train_or_load, training_data_key
from .collector import DataConfig, NoiseConfig, OnPolicy, collect, load_dataset, save_dataset
from .dataset import DrivingData, allocate
from .models import DrivingModel

#: the two arms: DAgger (the learner drives) and its control (the expert drives)
ARMS = ("dagger", "control")
#: who labels a DAgger round's states (:class:`DaggerConfig`)
LABELS = ("expert", "fresh")
#: each seed's rounds drive training tracks from here on, far from the data's own (0 .. 31)
FIRST_TRACK = 100_000
#: tracks a round may use (cars x laps); seeds and rounds are this far apart
TRACK_STRIDE = 1_000
#: the features of a state whose shift is measured: (name, where the dataset holds it)
SHIFT_FEATURES = {
    "lateral offset [m]": ("affordances", AFFORDANCE_INDEX["center_offset_m"]),
    "heading error [rad]": ("affordances", AFFORDANCE_INDEX["heading_rad"]),
    "speed [m/s]": ("speed", None),
    "gap ahead [m]": ("affordances", AFFORDANCE_INDEX["gap_ego_m"]),
}


@dataclass(frozen=True)
class DaggerConfig:
    """DAgger's rounds.

    Attributes:
        rounds: rounds of driving, labelling and fine-tuning.
        samples: samples each round adds [samples].
        betas: per round, the share of decisions the expert executes. Ross et al.'s best was
            beta = 1 in the first round and 0 after; their first round (the expert alone) is
            chapter 04's data, so the course's rounds all let the learner drive alone.
        replay: earlier samples replayed per new sample in a round's fine-tune.
        labels: who labels the learner's states: ``"fresh"`` (the course's), an expert planning
            afresh at every state, so a state's label depends on the state alone, as DAgger
            assumes; or ``"expert"``, the collector's expert, whose plans remember where it meant
            the car to be: it labels a learner that lagged its lane change with the rest of that
            plan, a swerve (lab note "Who labels DAgger's states": those rounds drove worse).
        control_labels: who labels the control's states (the expert's own driving): the
            collector's expert (``"expert"``, the course's: chapter 04's samples), or the fresh
            expert (``"fresh"``), so that DAgger and its control differ in whose states alone
            (lab note "DAgger's states or its labeller").
    """

    rounds: int = 2
    samples: int = 8_000
    betas: tuple[float, ...] = (0.0, 0.0)
    replay: float = 1.0
    labels: str = "fresh"
    control_labels: str = "expert"

    def __post_init__(self) -> None:
        o = "DaggerConfig"
        for name in ("labels", "control_labels"):
            if getattr(self, name) not in LABELS:
                raise ValueError(
                    f"{o}.{name}={getattr(self, name)!r} is invalid: must be one of {LABELS}"
                )
        check_range(o, "rounds", self.rounds, 1, 20, integer=True)
        check_range(o, "samples", self.samples, 1, integer=True)
        check_range(o, "replay", self.replay, 0.0, 100.0)
        if len(self.betas) != self.rounds:
            raise ValueError(
                f"{o}.betas={self.betas!r} is invalid: one beta per round ({self.rounds})"
            )
        for k, beta in enumerate(self.betas):
            check_range(o, f"betas[{k}]", beta, 0.0, 1.0)

    @property
    def fresh(self) -> bool:
        """Whether an expert planning afresh labels the learner's states (``labels="fresh"``)."""
        return self.labels == "fresh"

    @classmethod
    def for_profile(cls, profile: Profile, **changes: Any) -> DaggerConfig:
        """The profile's rounds: a sixth of the training data per round in the full profile."""
        samples = max(profile.collect_worlds * 8, profile.n_train_samples // 6)
        return cls(**{"samples": samples, **changes})


def val_roads(miles: float, n_worlds: int) -> EvalConfig:
    """Where chapter 12 drives each round's network for its figure: validation roads (a choice
    of rounds or beta is made there, so never on the test roads that its verdicts drive)."""
    return EvalConfig(miles=miles, n_worlds=n_worlds, split="val")


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

    def data(self) -> DataConfig:
        """What the round collects: ``cfg.samples`` on fresh training roads of its own (the same
        roads and start lanes in both arms); DAgger's learner drives without noise or take-overs
        (its own errors are the point), the control's expert as chapter 04's collector does."""
        first = FIRST_TRACK + (self.seed * self.cfg.rounds + self.index) * TRACK_STRIDE
        base = DataConfig.for_profile(
            self.profile,
            "train",
            n_samples=self.cfg.samples,
            n_tracks=None,
            first_track=first,
            seed=1_000 + self.seed,
        )
        if self.arm == "control":
            return base
        quiet = NoiseConfig(rate_per_s=0.0)
        return dataclasses.replace(base, noise=quiet, restart_rate_per_s=0.0)

    @property
    def stem(self) -> str:
        """The stored names' stem of the arm's samples and networks (DAgger's say who labelled,
        and the betas when the expert executes any share, so a beta schedule keeps the course's
        own)."""
        cfg, dagger_arm = self.cfg, self.arm == "dagger"
        fresh = cfg.fresh if dagger_arm else cfg.control_labels == "fresh"
        mixed = dagger_arm and any(cfg.betas)
        betas = "_beta" + "-".join(f"{b:g}" for b in cfg.betas) if mixed else ""
        return f"12_{self.arm}" + ("_fresh" if fresh else "") + betas

    @property
    def samples_name(self) -> str:
        """The file of the round's samples under ``<outputs>/data/``."""
        return seeded(self.stem, self.seed) + f"_round{self.index + 1}.npz"

    @property
    def network_name(self) -> str:
        """The checkpoint name of the network the round fine-tunes."""
        return seeded(f"{self.stem}_round{self.index + 1}", self.seed, plain_zero=True)

    def on_policy(self, learner: DrivingModel | None) -> OnPolicy | None:
        """How the round collects: DAgger's ``learner`` drives and the chosen expert labels; the
        control's relabelled states come from a stand-in learner that never drives (beta 1), so
        its states are the collector's own, bit for bit, and only the labels change; the
        course's control is the plain collector (None)."""
        if self.arm == "control":
            return (
                OnPolicy(LaneKeeper(), 1.0, fresh=True)
                if self.cfg.control_labels == "fresh"
                else None
            )
        if learner is None:
            raise ValueError("RoundSpec.on_policy: DAgger's round needs the learner that drives it")
        return OnPolicy(TrajectoryAgent(learner.eval()), self.cfg.betas[self.index], self.cfg.fresh)

    def samples_key(self, learner: DrivingModel | None) -> str:
        """The key of the round's samples: the collection's settings and, for DAgger, the
        learner's weights, the round's beta and the labeller
        (:meth:`~e2e_lite.learning.collector.OnPolicy.key`: anything else collects anew, and the
        fine-tunes on it retrain: their data key holds this)."""
        how = self.on_policy(learner)
        return self.data().key if how is None else how.key(self.data())

    def samples(self, learner: DrivingModel | None = None, progress: bool = True) -> DrivingData:
        """The round's samples, stored under ``<outputs>/data/`` and reused while the settings,
        the learner's weights and its beta are the same."""
        key = self.samples_key(learner)

        def make() -> DrivingData:
            return collect(self.data(), progress, on_policy=self.on_policy(learner))

        path = artifact_path("data", self.samples_name)
        return cached(path, key, make, save_dataset, load_dataset)


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


def finetune_set(
    earlier: list[DrivingData], new: DrivingData, replay: float, seed: int, r: int
) -> DrivingData:
    """A round's fine-tune data: its ``new`` samples and ``replay`` x as many rows drawn (seeded,
    without replacement) from the ``earlier`` data; the normalisation of the first part (the
    network's own). Its key names every part and the rows drawn."""
    sizes = np.array([len(d) for d in earlier])
    n_old = min(round(replay * len(new)), int(sizes.sum()))
    rows = np.sort(np.random.default_rng([seed, r, 53]).choice(sizes.sum(), n_old, replace=False))
    arrays = allocate(n_old + len(new), new.arrays["images"].shape[1:3])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    at = 0
    for d, first, end in zip(earlier, starts[:-1], starts[1:]):
        mine = rows[(rows >= first) & (rows < end)] - first
        for name in arrays:
            arrays[name][at : at + len(mine)] = d.arrays[name][mine]
        at += len(mine)
    for name in arrays:
        arrays[name][at:] = new.arrays[name]
    key = settings_key(
        new.info["key"], [d.info["key"] for d in earlier], rows.tobytes().hex()[:64], len(rows)
    )
    info = {"key": key, "split": "train", "parts": [d.info["key"] for d in earlier]}
    return DrivingData(arrays, dict(earlier[0].stats), info)


@dataclass
class Round:
    """One round of one arm: its beta, its samples, the aggregate's size after it, their
    covariate shift, its fine-tuned network and the drive that collected them (closed-loop
    metrics of the learner, or of the noisy expert)."""

    arm: str
    round: int
    beta: float | None
    samples: int
    aggregate: int
    shift: dict[str, float]
    name: str
    model: DrivingModel
    collection: dict[str, Any]


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
) -> tuple[DrivingModel, dict[str, list[Round]]]:
    """DAgger and its control for training ``seed``, from chapter 09's CVaR network of that seed
    (the start network, trained first if missing): ``(start, {arm: [Round, ...]})``. Every
    round's samples and fine-tune are stored and reused (:meth:`RoundSpec.samples`,
    :func:`~e2e_lite.learning.checkpoints.train_or_load`)."""
    cfg = cfg or DaggerConfig.for_profile(profile)
    start, _, _ = recipes.gmm_affordance_cvar(profile, train, val, weight, seed)
    start_name = recipes.seeded_name("09_gmm_affordance_cvar", seed)
    objective, tcfg = recipes.finetune_settings(profile, weight, seed, "mean")
    out: dict[str, list[Round]] = {}
    for arm in arms:
        earlier, parent, model = [train], start_name, start
        parent_key = training_data_key(train, val)
        rounds = []
        for r in range(cfg.rounds):
            spec = RoundSpec(profile, cfg, seed, r, arm)
            new = spec.samples(model, progress)
            shift = covariate_shift(new, earlier)
            data = finetune_set(earlier, new, cfg.replay, seed, r)
            name = spec.network_name
            model, _ = train_or_load(
                name,
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
            beta = cfg.betas[r] if arm == "dagger" else None
            earlier.append(new)
            aggregate = sum(len(d) for d in earlier)
            collection = new.info.get("collection", {})
            rounds.append(
                Round(arm, r + 1, beta, len(new), aggregate, shift, name, model, collection)
            )
            parent, parent_key = name, training_data_key(data, val)
        out[arm] = rounds
    return start, out
