"""Chapter 10's ablation: every driver of the course on the same test tracks with the same
seeds, beside the paper's Table 1 (seed 000) and seed 002's times to collision.

The drivers, in the order of the table (:data:`DRIVERS`): the expert (the ceiling), the oracle
(the LQR tracker following the expert's own trajectories: the ceiling of any trajectory network),
PilotNet steering only, the all-actuators baseline (the paper's Baseline E2E), trajectory L2,
trajectory GMM, GMM + affordance, GMM + affordance + CVaR. The trained ones come from
:mod:`e2e_lite.imitation.recipes`, so they are the chapters' checkpoints when those are valid and are
trained (seeded) when not.

Each learned row is trained with several seeds (:func:`build_seeded_drivers`; seed 0 is the
chapters' own checkpoint, seeds 1, 2, ... are ``10_<name>_seed<k>``); the row's miles are shared
among the seeds and their counts pooled (:func:`~e2e_lite.driving.evaluation.pool_results`), each seed's
result kept under ``seeds``. A drive is stored under a key of the driver's weights and settings and
the evaluation's, and read back while nothing changed (:func:`~e2e_lite.record.stored.evaluate_stored`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ..artifacts import cached, seeded, versioned
from ..config import Profile
from ..control.expert import Expert
from ..control.oracle import Oracle
from ..driving import anatomy
from ..driving.evaluation import evaluate
from ..driving.metrics import EvalResult, pool_results, results_table
from ..driving.rollout import EvalConfig, disjoint_runs
from ..imitation import dagger, recipes
from ..imitation.agents import ActuatorAgent, SteeringAgent, TrajectoryAgent
from ..imitation.collector import DataConfig, DrivingData, load_or_collect
from ..simulation.policy import Policy
from ..simulation.world import WorldConfig
from .stored import evaluate_stored, stored_at


@dataclass
class Build:
    """What a driver's build function gets: the sizes, the chapter-04 data and the training seed.

    Attributes:
        profile: sizes (and the data the recipes train on).
        train, val: the chapter-04 datasets (None for the drivers that train nothing).
        seed: the training seed (0: the chapters' own checkpoints).
        kw: passed to the recipes (e.g. ``progress=False``).
    """

    profile: Profile
    train: DrivingData | None
    val: DrivingData | None
    seed: int = 0
    kw: dict[str, Any] = field(default_factory=dict)
    _weight: float | None = field(default=None, init=False, repr=False)

    @property
    def data(self) -> tuple[Profile, DrivingData, DrivingData]:
        """``(profile, train, val)``: a recipe's first three arguments."""
        if self.train is None or self.val is None:
            raise ValueError("this driver trains: give build_drivers the chapter-04 datasets")
        return self.profile, self.train, self.val

    @property
    def seeded(self) -> dict[str, Any]:
        """The recipes' keyword arguments: the seed and ``kw``."""
        return {"seed": self.seed, **self.kw}

    def name(self, chapter_name: str) -> str:
        """The checkpoint name of this seed (:func:`~e2e_lite.imitation.recipes.seeded_name`)."""
        return recipes.seeded_name(chapter_name, self.seed)

    def weight(self) -> float:
        """Chapter 08's affordance weight (chosen once per build, its grid's checkpoints reused)."""
        if self._weight is None:
            self._weight = recipes.affordance_weight(*self.data, **self.kw)
        return self._weight


def _gmm(b: Build, decode: str = "top", **recipe: Any) -> Policy:
    """A GMM recipe's network (``recipe``: ``modes``, ``sigma``) as a trajectory driver."""
    chapter_name = {(): "07_gmm", ("modes",): "07_gmm_k1", ("sigma",): "07_gmm_sigma_learned"}
    name = b.name(chapter_name[tuple(recipe)])
    return TrajectoryAgent(recipes.gmm(*b.data, name=name, **recipe, **b.seeded)[0], decode=decode)


def _affordance(b: Build, **recipe: Any) -> Policy:
    """Chapter 08's network at the chosen weight (``recipe``: e.g. ``affordance_from``)."""
    base = "08_gmm_affordance_fused" if recipe else "08_gmm_affordance"
    model = recipes.gmm_affordance(*b.data, b.weight(), name=b.name(base), **recipe, **b.seeded)[0]
    return TrajectoryAgent(model)


def _finetune(b: Build, reduction: str, sigma: str = recipes.CVAR_SIGMA) -> Policy:
    """Chapter 09's fine-tune of this seed's affordance network, reduced by ``reduction``, its
    sigmas ``sigma`` (:func:`~e2e_lite.imitation.recipes.finetune_settings`)."""
    model = recipes.gmm_affordance_cvar(
        *b.data, b.weight(), reduction=reduction, sigma=sigma, **b.seeded
    )[0]
    return TrajectoryAgent(model)


def _dagger(b: Build, arm: str) -> Policy:
    """Chapter 12's kept iterate of ``arm`` for this seed (:func:`dagger_iterates`)."""
    found = dagger_iterates(b, arm)
    return TrajectoryAgent(found.networks[found.kept][1])


@dataclass(frozen=True)
class Iterates:
    """One arm's iterates for one seed and their drives on the seed's validation roads.

    Attributes:
        networks: ``[(name, network), ...]``, the CVaR network the rounds started from first.
        rates: each one's collisions per 100 mi on the validation roads.
        off_centre: each one's off-centre episodes there (the autonomy metric's interventions
            that were neither collisions nor stalls).
        collisions: each one's collisions there (the count the kept iterate reads).
        kept: the index of the one kept (:func:`~e2e_lite.imitation.dagger.kept_iterate`).
    """

    networks: list[tuple[str, Any]]
    rates: list[float]
    off_centre: list[int]
    collisions: list[int]
    kept: int


def dagger_iterates(
    b: Build, arm: str, cfg: dagger.DaggerConfig | None = None, ran: dagger.Run | None = None
) -> Iterates:
    """``arm``'s iterates for this seed, each driven on the seed's own validation roads (each
    drive stored), and the one kept (:func:`~e2e_lite.imitation.dagger.kept_iterate`: both
    outcomes). The rounds are
    :func:`~e2e_lite.imitation.dagger.run`'s: ``ran``, what it returned for this seed and ``cfg``
    (chapter 12 has them; not read again from their files), or run (or read) here."""
    cfg = cfg or dagger.DaggerConfig.for_profile(b.profile)
    if ran is None:
        ran = dagger.run(*b.data, b.weight(), b.seed, cfg, arms=(arm,), **b.kw)
    start, arms = ran
    start_name = recipes.seeded_name("09_gmm_affordance_cvar", b.seed)
    networks = [(start_name, start), *((r.name, r.model) for r in arms[arm])]
    run = dagger.val_run(b.profile, b.seed, cfg.val_miles)
    world_cfg = WorldConfig.for_profile(b.profile)
    drives = [
        evaluate_stored(
            f"{name}_val",
            f"{name} on validation roads",
            TrajectoryAgent(model),
            world_cfg,
            run,
            **b.kw,
        )
        for name, model in networks
    ]
    rates = [res.collisions_per_100mi for res in drives]
    off_centre, collisions = [res.off_centre for res in drives], [res.collisions for res in drives]
    kept = dagger.kept_iterate(collisions, off_centre)
    return Iterates(networks, rates, off_centre, collisions, kept)


def _w0(b: Build) -> Policy:
    """The affordance network trained with ``w = 0`` (the head present, its loss off)."""
    name = seeded("10_gmm_affordance_w0", b.seed)
    return TrajectoryAgent(recipes.gmm_affordance(*b.data, 0.0, name=name, **b.seeded)[0])


@dataclass(frozen=True)
class Driver:
    """One row of the ablation. Adding a driver is one row: its recipe lives in
    :mod:`e2e_lite.imitation.recipes`, and ``build`` turns it into a policy.

    Attributes:
        key: short name (file names, JSON keys).
        label: the row's name in tables and figures.
        paper_per_100mi: seed 000's Table 1 for the same method, if it has one.
        paper_ttc_s: seed 002's mean time to collision for the same method, if it has one [s].
        build: the driver from a :class:`Build` (trained or reused via the recipes).
    """

    key: str
    label: str
    paper_per_100mi: float | None = None
    paper_ttc_s: float | None = None
    build: Callable[[Build], Policy] | None = field(default=None, compare=False, repr=False)


DRIVERS = (
    Driver("expert", "expert (privileged, the ceiling)", build=lambda b: Expert()),
    Driver("oracle", "oracle: LQR on the expert's trajectories", build=lambda b: Oracle()),
    Driver(
        "pilotnet",
        "PilotNet, steering only",
        paper_ttc_s=10.2,
        build=lambda b: SteeringAgent(
            recipes.pilotnet(*b.data, b.name("05_pilotnet"), **b.seeded)[0]
        ),
    ),
    Driver(
        "actuators",
        "Baseline E2E: image + speed -> actuators",
        183.3,
        1.1,
        build=lambda b: ActuatorAgent(
            recipes.actuators(*b.data, b.name("05_actuators"), **b.seeded)[0]
        ),
    ),
    Driver(
        "trajectory_l2",
        "trajectory L2 + LQR",
        build=lambda b: TrajectoryAgent(
            recipes.trajectory_l2(*b.data, b.name("06_trajectory_l2"), **b.seeded)[0]
        ),
    ),
    Driver("gmm", "trajectory GMM + LQR", 12.7, build=_gmm),
    Driver("gmm_affordance", "GMM + affordance", 0.83, build=_affordance),
    Driver(
        "gmm_affordance_cvar",
        "GMM + affordance + CVaR",
        0.0,
        build=lambda b: _finetune(b, "cvar"),
    ),
)
#: The controls of chapter 10's table (not in the paper), same seeds and roads as the rows: a
#: fine-tune needs its control and an auxiliary loss its ``w = 0``. ``gmm_affordance_w0``, the
#: affordance network trained with ``w = 0`` (its head then learns nothing): is the affordance
#: step the auxiliary loss? ``gmm_affordance_control``, the CVaR row's fine-tune with the batch
#: mean instead of CVaR: is the CVaR step CVaR, or one more epoch?
CONTROLS = (
    Driver("gmm_affordance_w0", "GMM + affordance head, w = 0", build=_w0),
    Driver(
        "gmm_affordance_control",
        "GMM + affordance, the fine-tune with the mean",
        build=lambda b: _finetune(b, "mean"),
    ),
)
#: Rows beyond the paper that the record drives (chapter 12): DAgger's kept iterate, its control
#: (the expert's noisy states: is it the network's?) and its fine-tunes on no new data.
BEYOND = (
    Driver(
        "dagger", "+ DAgger (chapter 12), its kept iterate", build=lambda b: _dagger(b, "dagger")
    ),
    Driver(
        "dagger_control",
        "+ DAgger's control: the expert's noisy states",
        build=lambda b: _dagger(b, "control"),
    ),
    Driver(
        "dagger_no_new_data",
        "+ DAgger's fine-tunes on no new data",
        build=lambda b: _dagger(b, "no_new_data"),
    ),
)
#: Drivers of the exercises and the lab notes, which the course does not drive: the affordance
#: head on the fused features (Fig. 1); the GMM by its mean, with one mode, with learned sigmas;
#: CVaR and its control with sigmas open (:data:`~e2e_lite.imitation.recipes.CVAR_SIGMA`: 1).
DIAGNOSTICS = (
    Driver(
        "gmm_affordance_fused",
        "GMM + affordance, head on the fused features",
        build=lambda b: _affordance(b, affordance_from="fused"),
    ),
    Driver("gmm_mean", "GMM, following the mixture's mean", build=lambda b: _gmm(b, decode="mean")),
    Driver("gmm_k1", "GMM loss with one mode (K = 1)", build=lambda b: _gmm(b, modes=1)),
    Driver(
        "gmm_sigma_learned",
        "GMM with learned sigmas (the paper's NLL)",
        build=lambda b: _gmm(b, sigma="learned"),
    ),
    Driver(
        "gmm_affordance_cvar_open",
        "GMM + affordance + CVaR, sigma open",
        build=lambda b: _finetune(b, "cvar", "open"),
    ),
    Driver(
        "gmm_affordance_control_open",
        "GMM + affordance, the fine-tune with the mean, sigma open",
        build=lambda b: _finetune(b, "mean", "open"),
    ),
)
#: The drivers with no training (one run each: they have no training seed).
UNTRAINED = ("expert", "oracle")
#: seed 000: "Our agent drives smoothly in an average speed of 48 mile per hour".
PAPER_MPH = 48.0
#: seed 000: the paper's closed-loop distance, "more than 480 miles".
BY_KEY = {d.key: d for d in (*DRIVERS, *BEYOND, *CONTROLS, *DIAGNOSTICS)}


def build_drivers(
    profile: Profile,
    keys: Sequence[str] | None = None,
    train: DrivingData | None = None,
    val: DrivingData | None = None,
    seed: int = 0,
    **kw: Any,
) -> dict[str, Policy]:
    """The policies of ``keys`` (default: every row of :data:`DRIVERS`; :data:`CONTROLS` on
    request), trained or reused via the recipes.

    Args:
        profile: sizes (and the data the recipes train on).
        train, val: the chapter-04 datasets; loaded (or collected) when not given.
        seed: the training seed of the learned drivers (0: the chapters' checkpoints).
        **kw: passed to the recipes (e.g. ``progress=False``).
    """
    keys = [d.key for d in DRIVERS] if keys is None else list(keys)
    unknown = [k for k in keys if k not in BY_KEY]
    if unknown:
        raise ValueError(f"unknown drivers {unknown}; known: {list(BY_KEY)}")
    if any(k not in UNTRAINED for k in keys):
        train = train or load_or_collect(DataConfig.for_profile(profile, "train"))
        val = val or load_or_collect(DataConfig.for_profile(profile, "val"))
    build = Build(profile, train, val, seed, dict(kw))  # one affordance weight for every row
    out: dict[str, Policy] = {}
    for key in keys:
        driver = BY_KEY[key]
        if driver.build is None:
            raise ValueError(f"driver {key!r} has no build function")
        out[key] = driver.build(build)
    return out


#: rows chapter 10 and the record drive with the chapters' own networks (training seed 0) alone:
#: they are not steps of the paper's Table 1, and training them with every seed would take the
#: full course past its 2 h on 2 cores and the record past a sitting.
SEED_ZERO_ONLY = ("pilotnet", "trajectory_l2")


def build_seeded_drivers(
    profile: Profile,
    keys: Sequence[str] | None = None,
    seeds: int | None = None,
    train: DrivingData | None = None,
    val: DrivingData | None = None,
    single: Sequence[str] = (),
    **kw: Any,
) -> dict[str, Policy | list[Policy]]:
    """Like :func:`build_drivers`, but every learned driver as a list of ``seeds`` policies
    (training seeds ``0 .. seeds - 1``; default ``profile.ablation_seeds``), those in ``single``
    as a list of seed 0's alone; the expert and the oracle stay single (nothing of theirs is
    trained)."""
    seeds = profile.ablation_seeds if seeds is None else seeds
    keys = [d.key for d in DRIVERS] if keys is None else list(keys)
    if any(k not in UNTRAINED for k in keys):
        train = train or load_or_collect(DataConfig.for_profile(profile, "train"))
        val = val or load_or_collect(DataConfig.for_profile(profile, "val"))
    per_seed = []
    for s in range(seeds):
        keys_of_seed = [k for k in keys if k not in single or s == 0]
        per_seed.append(build_drivers(profile, keys_of_seed, train, val, seed=s, **kw))
    return {
        key: per_seed[0][key] if key in UNTRAINED else [p[key] for p in per_seed if key in p]
        for key in keys
    }


def first(policy: Policy | Sequence[Policy]) -> Policy:
    """The seed-0 policy of a row of :func:`build_seeded_drivers` (the policy itself if single)."""
    return policy[0] if isinstance(policy, (list, tuple)) else policy


def evaluate_drivers(
    drivers: dict[str, Policy | Sequence[Policy]],
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    *,
    reuse: bool = True,
    progress: bool = True,
    workers: int | None = None,
) -> dict[str, EvalResult]:
    """Every driver on the same tracks with the same seeds (``cfg``), in ``workers`` shards
    (default: every core; the results do not depend on it). A driver given as a list (one policy
    per training seed, :func:`build_seeded_drivers`) drives ``cfg.miles / len(list)`` per seed,
    seed ``k`` of every driver on the same tracks (:func:`~e2e_lite.driving.evaluation.disjoint_runs`),
    and its result pools theirs (its ``seeds``). With ``reuse``, a stored result is read back
    (:func:`~e2e_lite.record.stored.evaluate_stored`); every other driver is evaluated and stored."""
    out: dict[str, EvalResult] = {}
    for key, policy in drivers.items():
        label = BY_KEY[key].label if key in BY_KEY else key
        if isinstance(policy, (list, tuple)):
            runs = disjoint_runs(cfg, world_cfg, len(policy))
            parts = []
            for k, (p, run) in enumerate(zip(policy, runs)):
                name, seed_label = seeded(key, k), f"{label} (seed {k})"
                kw = {"reuse": reuse, "progress": progress, "workers": workers}
                parts.append(evaluate_stored(name, seed_label, p, world_cfg, run, **kw))
            out[key] = pool_results(parts, cfg.intervention_cost_s)
        else:
            out[key] = evaluate_stored(
                key, label, policy, world_cfg, cfg, reuse=reuse, progress=progress, workers=workers
            )
    return out


def witnessed(
    file: str, label: str, driver: Policy, world_cfg: WorldConfig, cfg: EvalConfig
) -> tuple[list[anatomy.Collision], list[anatomy.Moment]]:
    """``driver``'s collisions and ordinary moments on ``cfg``'s roads, witnessed
    (:class:`~e2e_lite.driving.anatomy.Witness`), stored and read back as
    :func:`~e2e_lite.record.stored.evaluate_stored` stores a result (each moment back in a fresh copy of its world)."""

    witness = anatomy.Witness(driver, world_cfg.sim.policy_period_s)

    def drive() -> dict[str, Any]:
        evaluate(witness, world_cfg, cfg, desc=label)
        return anatomy.witnessed_to_dict(witness)

    kept = (versioned("witness"), anatomy.HISTORY_S, witness.every)
    path, key = stored_at(file, driver, world_cfg, cfg, *kept)
    stored = cached(path, key, drive, anatomy.save_witnessed, anatomy.load_witnessed)
    return anatomy.witnessed_from_dict(stored, world_cfg)


def _fmt(value: float | None, unit: str = "") -> str:
    return "-" if value is None else f"{value:g}{unit}"


def per_seed(result: EvalResult) -> str:
    """A pooled result's per-seed rates, ``"a / b / c"`` per 100 mi (``"-"`` for one run)."""
    return " / ".join(f"{s.collisions_per_100mi:.1f}" for s in result.seeds) or "-"


def ablation_table(results: dict[str, EvalResult]) -> str:
    """The markdown table: ours (miles, collisions car / rail, per 100 mi with the 95 % interval,
    mph, time to collision, autonomy, the rate of each training seed) beside the papers' figures
    for the same method."""
    drivers = [BY_KEY.get(key, Driver(key, key)) for key in results]
    return results_table(
        [(d.label, r) for d, r in zip(drivers, results.values())],
        extra=[
            ("per seed, per 100 mi", [per_seed(r) for r in results.values()]),
            ("stalls", [f"{r.stalls:,}" for r in results.values()]),
            ("paper: per 100 mi (seed 000)", [_fmt(d.paper_per_100mi) for d in drivers]),
            ("paper: time to collision (seed 002)", [_fmt(d.paper_ttc_s, " s") for d in drivers]),
        ],
    )
