"""The course's trained drivers, one recipe each, shared by the chapters that train them and the
chapters that reuse them (chapter 10 drives them all).

Each recipe fixes the settings of one model, trains it with :func:`~e2e_lite.learning.checkpoints.train_or_load`
(so a valid checkpoint is reused, and a missing or stale one is retrained, seeded) and returns
``(model, objective, history)``. The settings per profile:

* every model: Adam 1e-3, batch 64, ``profile.train_epochs`` epochs, validation on up to 4,000
  held-out samples; every network trained from scratch keeps the epoch that collides least when
  it drives :data:`SELECT_MILES` on validation roads (``select_by="val_roads"``,
  :mod:`~e2e_lite.imitation.selection`; ties: the lower decisive ADE of the followed trajectory,
  or validation loss); with one epoch (quick) nothing is driven;
* GMM models (K = 2): gradient clipping at 10, every sigma held at 1 (:data:`GMM_SIGMA`; the
  paper's learned sigmas open after a warm-up of a third of the epochs), targets scaled per axis
  (:data:`GMM_TARGET_SCALE`) with a sigma floor in metres (:data:`GMM_SIGMA_FLOOR_M`, a setting
  of the model); chapter 07 measures these choices;
* the affordance weight ``w``: a grid search (:func:`affordance_grid`) on a quarter of the
  training set, two epochs per candidate, scored by held-out trajectory NLL; the affordance head
  reads the trunk's features (:data:`AFFORDANCE_FROM`, chosen by chapter 08's probes);
* the affordances the course reads (chapter 08's figures, chapter 11's module) come from the
  head refit alone on the kept network's frozen trunk (:func:`perceiving`, :data:`HEAD_REFIT`);
* CVaR: one epoch fine-tuning the GMM + affordance model on the worst 10 % of each batch of 256
  (the tail then holds 25.6 samples), continuing the base training's Adam state at learning rate
  1e-4; its control is the same fine-tune with the batch mean.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from ..artifacts import artifact_path, seeded
from ..config import Profile
from ..learning.checkpoints import refit_or_load, train_or_load
from ..learning.cvar import CVaRObjective
from ..learning.dataset import DrivingData, DrivingDataset
from ..learning.labels import AFFORDANCE_NAMES
from ..learning.losses import GMM_SIGMAS, GMMObjective, Objective, WithAffordance
from ..learning.models import DrivingModel, ModelConfig
from ..learning.probes import HeadRefit
from ..learning.training import History, TrainConfig, evaluate_loss
from ..simulation.world import WorldConfig
from .selection import road_scorer

Trained = tuple[DrivingModel, Objective, History]

GMM_MODES = 2
#: The GMM's target scale and sigma floor (chapter 07, section 3b: the per-coordinate scale blows
#: the 0.3 s lateral point up 15-fold and the modes split by speed; per axis, in metres, they
#: split into left and right).
GMM_TARGET_SCALE = "axis"
GMM_SIGMA_FLOOR_M = 0.1
#: The course's GMM sigmas (:data:`~e2e_lite.learning.losses.GMM_SIGMAS`): ``"held"`` at 1, a
#: mixture of unit Gaussians whose weights and means are learned. Chosen on validation roads
#: (lab note "Every epoch on the road", ``lab/epochs_on_the_road.py``): with the paper's learned
#: sigmas, five training seeds' kept epochs collided far more often than with sigmas held, and
#: far less alike; chapter 07 trains the learned variant beside it and shows the difference.
GMM_SIGMA = "held"
#: How a network trained from scratch keeps an epoch: the one that drives best on validation roads,
#: ``SELECT_MILES`` each (:class:`~e2e_lite.learning.training.TrainConfig`'s ``select_by="val_roads"``,
#: :mod:`~e2e_lite.imitation.selection`). Chosen on the first Table 1 of record, whose GMM seeds 1 and 4 kept
#: by their decisive ADE an epoch that drove 2-4 times worse than the next (lab note "The GMM's
#: worst seeds of record, epoch by epoch"). With one epoch (the quick profile) there is nothing to
#: choose: the single epoch is kept without a drive.
SELECT_MILES = 20.0
#: The rule trajectory models kept epochs by before (and chapter 07's lesson on it).
TRAJECTORY_SELECT_BY = "decisive_ade"
CVAR_ALPHA = 0.9
CVAR_BATCH = 256  # the tail of a batch then holds 25.6 samples


def _train_cfg(profile: Profile, **changes: Any) -> TrainConfig:
    base = {"epochs": profile.train_epochs, "batch_size": 64, "max_val_samples": 4000}
    return TrainConfig(**{**base, **changes})


def _selecting(
    profile: Profile, kw: dict[str, Any], **changes: Any
) -> tuple[TrainConfig, dict[str, Any]]:
    """The training settings of a network trained from scratch (``changes`` on top) that keeps
    the epoch driving best on validation roads (:data:`SELECT_MILES` each), and ``kw`` with the drive as
    its ``on_epoch`` hook (after the caller's own hook, if any)."""
    cfg = _train_cfg(profile, **changes)
    if cfg.epochs < 2:  # one epoch: nothing to choose, nothing to drive
        return cfg, kw

    scorer = road_scorer(WorldConfig.for_profile(profile), SELECT_MILES, kw.get("on_epoch"))
    cfg = replace(cfg, select_by="val_roads", select_miles=SELECT_MILES)
    return cfg, {**kw, "on_epoch": scorer}


def sigma_warmup(epochs: int) -> int:
    """Epochs with sigma frozen: a third of the schedule (at least one when there are two or
    more epochs, none for a single epoch)."""
    return max(1, epochs // 3) if epochs > 1 else 0


PILOTNET_CFG = ModelConfig(kind="pilotnet", head="steer")
ACTUATORS_CFG = ModelConfig(kind="fusion", head="actuators")


def seeded_name(name: str, seed: int) -> str:
    """The checkpoint name of training seed ``seed`` of the recipe whose seed-0 checkpoint is
    ``name`` (chapter 10 trains seeds 1, 2, ... beside the chapters' own seed 0)."""
    return seeded(f"10_{name.split('_', 1)[1]}", seed) if seed else name


def pilotnet(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    name: str = "05_pilotnet",
    seed: int = 0,
    **kw: Any,
) -> Trained:
    """Chapter 05: PilotNet (seed 003), steering (curvature) only. ``train`` may hold recovery
    views (chapter 05 trains ``"05_pilotnet_views"`` that way); ``seed``: the training seed."""
    objective = Objective("steer")
    cfg, kw = _selecting(profile, kw, seed=seed)
    model, hist = train_or_load(name, PILOTNET_CFG, cfg, objective, train, val, **kw)
    return model, objective, hist


def actuators(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    name: str = "05_actuators",
    seed: int = 0,
    **kw: Any,
) -> Trained:
    """Chapter 05: the all-actuators baseline (seed 002 / the paper's Baseline E2E): image and
    speed to steering and acceleration."""
    objective = Objective("actuators")
    cfg, kw = _selecting(profile, kw, seed=seed)
    model, hist = train_or_load(name, ACTUATORS_CFG, cfg, objective, train, val, **kw)
    return model, objective, hist


def trajectory_l2(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    name: str = "06_trajectory_l2",
    seed: int = 0,
    **kw: Any,
) -> Trained:
    """Chapter 06: fusion network, 5-point trajectory head, L2 on normalised targets."""
    objective = Objective("trajectory")
    cfg, kw = _selecting(profile, kw, select_by=TRAJECTORY_SELECT_BY, seed=seed)
    model, hist = train_or_load(
        name,
        ModelConfig(kind="fusion", head="trajectory"),
        cfg,
        objective,
        train,
        val,
        **kw,
    )
    return model, objective, hist


def gmm_config(modes: int = GMM_MODES, **changes: Any) -> ModelConfig:
    """The course's GMM network: the fusion model, a ``modes``-component mixture head, sigmas
    floored at :data:`GMM_SIGMA_FLOOR_M`; ``changes`` override settings (an affordance head)."""
    settings = {"kind": "fusion", "head": "gmm", "gmm_modes": modes}
    return ModelConfig(**{**settings, "sigma_floor_m": GMM_SIGMA_FLOOR_M, **changes})


def gmm_objective(
    profile: Profile,
    epochs: int | None = None,
    warmup: int | None = None,
    sigma: str = GMM_SIGMA,
    **changes: Any,
) -> GMMObjective:
    """The course's GMM NLL: K modes, targets scaled per axis, sigmas as ``sigma`` says (one of
    :data:`~e2e_lite.learning.losses.GMM_SIGMAS`; learned ones after the warm-up for a schedule
    of ``epochs``, or ``warmup`` epochs); ``changes`` override settings (chapter 07 trains the
    per-coordinate variant this way). The sigma floor is the model's (:func:`gmm_config`)."""
    if sigma not in GMM_SIGMAS:
        raise ValueError(f"gmm_objective: sigma={sigma!r} is invalid: must be one of {GMM_SIGMAS}")
    settings = {
        "n_modes": GMM_MODES,
        "sigma_warmup_epochs": sigma_warmup(epochs or profile.train_epochs)
        if warmup is None
        else warmup,
        "target_scale": GMM_TARGET_SCALE,
        "sigma": sigma,
    }
    return GMMObjective(**{**settings, **changes})


def gmm(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    seed: int = 0,
    name: str = "07_gmm",
    objective: GMMObjective | None = None,
    modes: int = GMM_MODES,
    sigma: str = GMM_SIGMA,
    sigma_floor_m: float | None = GMM_SIGMA_FLOOR_M,
    **kw: Any,
) -> Trained:
    """Chapter 07: the same network with a K = 2 mixture head (``seed``: the training seed;
    ``objective``: another loss than :func:`gmm_objective`'s, and ``modes``: another K, for
    chapter 07's comparisons; K = 1 is the same NLL without a choice of modes; ``sigma``:
    ``"learned"`` is the paper's NLL, whose sigmas open after the warm-up, chapter 07's
    comparison for the course's held sigmas (:data:`GMM_SIGMA`); ``sigma_floor_m``: the
    model's sigma floor in metres, None for :class:`~e2e_lite.learning.models.ModelConfig`'s
    default floor in normalised units)."""
    if objective is None:
        objective = gmm_objective(profile, n_modes=modes, sigma=sigma)
    elif sigma != GMM_SIGMA:
        raise ValueError("give sigma or an objective, not both")
    if objective.n_modes != modes:
        raise ValueError(f"the objective has {objective.n_modes} modes, the model {modes}")
    cfg, kw = _selecting(profile, kw, grad_clip=10.0, seed=seed, select_by=TRAJECTORY_SELECT_BY)
    model, hist = train_or_load(
        name,
        gmm_config(modes, sigma_floor_m=sigma_floor_m),
        cfg,
        objective,
        train,
        val,
        **kw,
    )
    return model, objective, hist


#: Where the course's affordance head reads: the trunk's image features. The paper's Fig. 1 puts
#: it on the fusion network's output; chapter 08's probes on a network trained that way find the
#: affordances in the trunk (a probe there: gap to a car ahead 0.35 of the mean predictor's MAE,
#: offset 0.48, heading 0.31 of its RMSE) and only partly in the fused features (0.52 / 0.56 /
#: 0.46; the head itself 0.62 / 0.63 / 0.54). Chosen on those held-out errors, not on collisions;
#: chapter 10's control ``gmm_affordance_fused`` keeps the paper's placement.
AFFORDANCE_FROM = "trunk"
AFFORDANCE_CFG = gmm_config(affordance=True, affordance_from=AFFORDANCE_FROM)


def affordance_grid(
    profile: Profile, train: DrivingData, val: DrivingData, **kw: Any
) -> dict[float, dict[str, float]]:
    """Chapter 08's grid search over the affordance weight ``w``.

    Each candidate trains on the same rows (every 4th training sample in the full profile, all in
    the quick one) for 2 epochs (1 in quick) with seed 1, and is scored on the validation set.

    Returns:
        ``{w: {"trajectory_nll", "ADE_m", "gap_ego_mae_m", "affordance_rel_mae", ...}}``
        (held-out means; ``affordance_rel_mae``: each affordance's MAE over its training
        standard deviation, averaged over the 9).
    """
    grid = _grid(profile)
    epochs = 1 if profile.quick else 2
    rows = np.arange(len(train)) if profile.quick else np.arange(0, len(train), 4)
    cfg = _train_cfg(profile, epochs=epochs, max_val_samples=2000, grad_clip=10.0, seed=1)
    scores = {}
    for w in grid:
        objective = WithAffordance(gmm_objective(profile, epochs), w)
        model, _ = train_or_load(
            _grid_name(w), AFFORDANCE_CFG, cfg, objective, train, val, train_rows=rows, **kw
        )
        _, metrics = evaluate_loss(model, objective, DrivingDataset(val))
        scores[w] = {
            "trajectory_nll": float(metrics["main loss"].mean()),
            "ADE_m": float(metrics["ADE [m]"].mean()),
            "gap_ego_mae_m": float(metrics["|err| gap_ego_m"].mean()),
            # the 9 affordances' held-out MAE, each over its training spread, averaged
            "affordance_rel_mae": float(
                np.mean(
                    [
                        metrics[f"|err| {name}"].mean() / max(float(std), 1e-9)
                        for name, std in zip(AFFORDANCE_NAMES, train.stats["affordances_std"])
                    ]
                )
            ),
            "train_samples": len(rows),
            "epochs": epochs,
        }
    return scores


def choose_affordance_weight(scores: dict[float, dict[str, float]]) -> tuple[float, str]:
    """The ``w`` with the lowest held-out trajectory NLL, and a line saying why.

    If ``w = 0`` wins, the auxiliary loss does not help the trajectory, and the head is there to
    perceive (chapter 11's safety module reads it): the ``w > 0`` whose head has the lowest
    held-out affordance error (``affordance_rel_mae``) is returned, and the line says so. (Before,
    the runner-up by trajectory NLL was taken; on the trunk-reading head that picked w = 0.3, a
    head no better than the training mean.)"""
    best = min(scores, key=lambda w: scores[w]["trajectory_nll"])
    if best > 0 or len(scores) == 1:
        return best, f"w = {best:g}: the lowest held-out trajectory NLL of the grid"
    runner = min((w for w in scores if w > 0), key=lambda w: scores[w]["affordance_rel_mae"])
    return runner, (
        f"w = 0 had the lowest held-out trajectory NLL: the auxiliary loss did not help the "
        f"trajectory on this grid; the head is there to perceive, so w = {runner:g}, the w > 0 "
        "with the lowest held-out affordance error"
    )


def _grid(profile: Profile) -> tuple[float, ...]:
    """The affordance weights chapter 08's grid tries."""
    return (0.0, 1.0) if profile.quick else (0.0, 0.1, 0.3, 1.0, 3.0)


def _grid_name(weight: float) -> str:
    """The checkpoint name of the grid's candidate ``weight``."""
    return f"08_grid_w{weight:g}"


#: :func:`affordance_weight`'s answers in this process, by profile, data and the grid's files
_CHOSEN_WEIGHTS: dict[tuple[Any, ...], float] = {}


def affordance_weight(profile: Profile, train: DrivingData, val: DrivingData, **kw: Any) -> float:
    """Chapter 08's choice of ``w`` (the grid's checkpoints are reused when valid).

    Scoring the grid takes a validation pass per candidate (about 23 s in the full profile); the
    answer is remembered in this process for the same profile, data and grid checkpoint files
    (path, size and modification time), so chapters that build several training seeds score it
    once, and a grid retrained in between is scored again."""

    def grid_files() -> tuple[Any, ...]:
        paths = [artifact_path("checkpoints", f"{_grid_name(w)}.pt") for w in _grid(profile)]
        stats = [p.stat() if p.exists() else None for p in paths]
        return tuple((str(p), s and (s.st_size, s.st_mtime_ns)) for p, s in zip(paths, stats))

    data = (train.info.get("key"), val.info.get("key"))
    if None not in data and (key := (profile, data, grid_files())) in _CHOSEN_WEIGHTS:
        return _CHOSEN_WEIGHTS[key]
    weight = choose_affordance_weight(affordance_grid(profile, train, val, **kw))[0]
    if None not in data:  # (data without a settings key, e.g. synthetic, is never remembered)
        _CHOSEN_WEIGHTS[(profile, data, grid_files())] = weight
    return weight


def gmm_affordance(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    weight: float,
    name: str = "08_gmm_affordance",
    seed: int = 0,
    affordance_from: str = AFFORDANCE_FROM,
    **kw: Any,
) -> Trained:
    """Chapter 08: the chapter-07 GMM plus the affordance head, loss GMM + ``weight`` x
    affordance (chapter 10's controls train the same network with ``weight = 0``, and with the
    head on the fused features, ``affordance_from="fused"``; ``seed``: the training seed, for
    more runs per row)."""
    objective = WithAffordance(gmm_objective(profile), weight)
    cfg, kw = _selecting(profile, kw, grad_clip=10.0, seed=seed, select_by=TRAJECTORY_SELECT_BY)
    model, hist = train_or_load(
        name,
        replace(AFFORDANCE_CFG, affordance_from=affordance_from),
        cfg,
        objective,
        train,
        val,
        **kw,
    )
    return model, objective, hist


#: How a driving network's affordance head is refit on its kept trunk before anything reads its
#: affordances (:func:`perceiving`): the probes' schedule, 30 epochs at 1e-3.
HEAD_REFIT = HeadRefit()


def perceiving(
    model: DrivingModel,
    train: DrivingData,
    name: str,
    **kw: Any,
) -> DrivingModel:
    """The network whose affordances the course reads (chapter 08's scatter, chapter 11's safety
    module): ``model`` with its affordance head refit alone on its frozen trunk
    (:data:`HEAD_REFIT`, stored as ``<name>_head.pt``). It drives exactly as ``model`` (every
    other weight is ``model``'s); ``kw``: ``progress``.

    Why: a trajectory network keeps the epoch that drives best (``select_by``), and the head
    rides along; when an early epoch wins, the head it carries has trained for one epoch
    (chapter 08, "the head over the epochs")."""
    return refit_or_load(name, model, train, HEAD_REFIT, **kw)


#: How chapter 09's fine-tunes reduce a batch (:func:`gmm_affordance_cvar`): the paper's CVaR
#: and its control, the plain mean with every other setting the same.
REDUCTIONS = ("cvar", "mean")
#: The fine-tune's learning rate: a tenth of the base training's, continuing its Adam state.
CVAR_LR = 1e-4
#: What the CVaR fine-tune ranks its tail by (:data:`~e2e_lite.learning.cvar.RANK_BY`).
CVAR_RANK_BY = "loss"
#: What a fine-tune does with the mixture's sigmas: ``"held"`` at 1 for the whole epoch (the loss
#: is then each sample's squared trajectory error, soft-minimised over the modes, and the tail is
#: ranked by it), or ``"open"`` (the paper's NLL with the learned sigmas).
FINETUNE_SIGMAS = ("held", "open")
#: The course's choice: held, as the base network trained (:data:`GMM_SIGMA`). With sigma open, a
#: CVaR fine-tune lowers its tail by widening the sigmas of its worst samples (chapter 09, "why
#: sigma is held"); on the course's base those sigmas start from a layer that never trained.
CVAR_SIGMA = "held"


def finetune_settings(
    profile: Profile,
    weight: float,
    seed: int = 0,
    reduction: str = "cvar",
    sigma: str = CVAR_SIGMA,
) -> tuple[Objective, TrainConfig]:
    """The objective and training settings of chapter 09's fine-tunes: the chapter-08 loss
    (GMM NLL + ``weight`` x affordance error), reduced by CVaR-0.9 or, for the control, by the
    mean; one epoch, batches of 256, learning rate :data:`CVAR_LR`. The two differ in the
    reduction only.

    ``sigma``: one of :data:`FINETUNE_SIGMAS`. ``"held"`` (the course's :data:`CVAR_SIGMA`): every
    sigma is 1 and the log-sigma layer is frozen, so the trajectory term is the modes' squared
    error in target units. ``"open"`` trains the sigmas, as the paper's NLL does."""
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction={reduction!r} is invalid: must be one of {REDUCTIONS}")
    if sigma not in FINETUNE_SIGMAS:
        raise ValueError(f"sigma={sigma!r} is invalid: must be one of {FINETUNE_SIGMAS}")
    base = WithAffordance(
        gmm_objective(profile, warmup=0, sigma="held" if sigma == "held" else "learned"), weight
    )
    objective = (
        CVaRObjective(base, CVAR_ALPHA, rank_by=CVAR_RANK_BY) if reduction == "cvar" else base
    )
    cfg = _train_cfg(
        profile, epochs=1, batch_size=CVAR_BATCH, lr=CVAR_LR, grad_clip=10.0, seed=seed
    )
    return objective, cfg


def gmm_affordance_cvar(
    profile: Profile,
    train: DrivingData,
    val: DrivingData,
    weight: float,
    seed: int = 0,
    reduction: str = "cvar",
    sigma: str = CVAR_SIGMA,
    tag: str = "",
    **kw: Any,
) -> Trained:
    """Chapter 09: one epoch of fine-tuning :func:`gmm_affordance`'s checkpoint of the same
    training ``seed`` (trained first if missing, or if it did not keep its optimiser state),
    continuing its Adam state at a tenth of the rate, sigmas as ``sigma`` says
    (:func:`finetune_settings`). ``tag``: appended to both checkpoints' names, for a lab's
    variant of the recipe (e.g. other ``train_rows``) beside the course's own.

    ``reduction="cvar"``: CVaR-0.9 of each batch of 256 (the tail holds 25.6 samples);
    ``"mean"``: the control, the same fine-tune with the batch mean (checkpoint
    ``09_gmm_affordance_control``): what one more epoch does without CVaR. ``sigma="open"``
    stores them as ``09_gmm_affordance_cvar_open`` and ``09_gmm_affordance_control_open``.
    """
    parent = seeded_name(f"08_gmm_affordance{tag}", seed)
    gmm_affordance(profile, train, val, weight, name=parent, seed=seed, keep_optimizer=True, **kw)
    objective, cfg = finetune_settings(profile, weight, seed, reduction, sigma)
    name = "09_gmm_affordance_cvar" if reduction == "cvar" else "09_gmm_affordance_control"
    name += ("_open" if sigma == "open" else "") + tag
    model, hist = train_or_load(
        seeded_name(name, seed),
        AFFORDANCE_CFG,
        cfg,
        objective,
        train,
        val,
        init_from=parent,
        carry_optimizer=True,
        **kw,
    )
    return model, objective, hist
