"""One training loop for every chapter, and checkpoints that know what they were trained on.

:func:`fit` trains with Adam (the paper: learning rate 1e-3, no weight decay), shuffles with a
seeded generator, validates every epoch, keeps the weights of the best validation loss (as seed
002 did), stops early after ``patience`` epochs without improvement, and can freeze parameters by
name for a range of epochs. It writes per-epoch metrics as JSON and a training-curve PNG.

Checkpoints and :func:`~e2e_lite.learning.checkpoints.train_or_load` are :mod:`e2e_lite.learning.checkpoints`;
probes on frozen features are :mod:`e2e_lite.learning.probes`.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from matplotlib.figure import Figure

from ..artifacts import artifact_path, save_figure, save_json
from ..config import check_range, tqdm
from .dataset import DrivingData, DrivingDataset, situations
from .heads import HEADS
from .losses import Objective
from .models import DrivingModel, ModelConfig

SELECT_BY = ("val_loss", "decisive_ade", "val_roads")
DECISIVE = "decisive ADE [m]"
#: What a driving scorer (``fit``'s ``on_epoch``) returns for ``select_by="val_roads"``: the
#: epoch's collisions per 100 mi on validation roads (:mod:`e2e_lite.imitation.selection`).
VAL_ROADS = "val roads collisions /100 mi"


def decisive_errors(ade_m: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, float]:
    """The held-out ADE [m] on each situation of ``masks`` (``"ADE <name> [m]"``; situations with
    no sample are left out) and their unweighted mean (:data:`DECISIVE`)."""
    out = {f"ADE {k} [m]": float(ade_m[m].mean()) for k, m in masks.items() if m.any()}
    if not out:
        raise ValueError("no validation sample falls in any decisive situation")
    out[DECISIVE] = float(np.mean(list(out.values())))
    return out


@dataclass(frozen=True)
class TrainConfig:
    """Training settings.

    Attributes:
        epochs: passes over the training set.
        batch_size: samples per step.
        lr: Adam's learning rate (the paper: 1e-3).
        weight_decay: Adam's weight decay (the paper: none).
        grad_clip: clip the gradient's global norm to this (None: no clipping).
        freeze: ``(name_prefix, first_epoch, stop_epoch)`` triples: parameters whose name starts
            with the prefix are frozen for epochs ``first_epoch <= e < stop_epoch`` (0-based).
        patience: stop after this many epochs without a better validation loss (None: never).
        select_by: which epoch's weights are kept: ``"val_loss"`` (the lowest validation loss) or
            ``"decisive_ade"`` (the lowest error of the followed trajectory on the situations that
            decide collisions: the mean over overtake starts, slow frames and curves of each
            one's held-out ADE, see :func:`~e2e_lite.imitation.collector.situations`; trajectory heads only).
            A GMM's NLL keeps falling as its sigmas sharpen while its driving gets worse.
            ``"val_roads"``: the fewest collisions per 100 mi when the epoch drives
            ``select_miles`` on validation roads (``fit``'s ``on_epoch`` drives it and returns
            :data:`VAL_ROADS`); ties go to the lower decisive ADE (trajectory heads) or
            validation loss (the others). Held-out errors do not predict the driving (seed 000,
            and the lab note "The GMM's worst seeds of record, epoch by epoch").
        select_miles: miles each epoch drives for ``select_by="val_roads"`` (None otherwise).
        max_val_samples: validate on at most this many samples (evenly spaced) to save time.
        seed: seeds the weights, the dropout and the shuffling.
        device: ``"auto"`` (CUDA if present, else CPU), ``"cpu"`` or ``"cuda"``.
    """

    epochs: int = 4
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 0.0
    grad_clip: float | None = None
    freeze: tuple[tuple[str, int, int], ...] = ()
    patience: int | None = None
    max_val_samples: int | None = None
    select_by: str = "val_loss"
    select_miles: float | None = None
    seed: int = 0
    device: str = "auto"

    #: added after the course's networks were keyed: at its default (None) those keys stay
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = ("select_miles",)

    def __post_init__(self) -> None:
        o = "TrainConfig"
        check_range(o, "epochs", self.epochs, 1, 10_000, integer=True)
        check_range(o, "batch_size", self.batch_size, 2, 65_536, integer=True)
        check_range(o, "lr", self.lr, 0.0, 1.0, lo_open=True)
        check_range(o, "weight_decay", self.weight_decay, 0.0, 1.0)
        if self.grad_clip is not None:
            check_range(o, "grad_clip", self.grad_clip, 0.0, lo_open=True)
        if self.patience is not None:
            check_range(o, "patience", self.patience, 1, integer=True)
        if self.max_val_samples is not None:
            check_range(o, "max_val_samples", self.max_val_samples, 1, integer=True)
        check_range(o, "seed", self.seed, 0, integer=True)
        if self.select_by not in SELECT_BY:
            raise ValueError(
                f"{o}.select_by={self.select_by!r} is invalid: must be one of {SELECT_BY}"
            )
        if (self.select_by == "val_roads") != (self.select_miles is not None):
            raise ValueError(
                f"{o}.select_miles={self.select_miles!r} with select_by={self.select_by!r}: "
                "give select_miles (> 0) exactly when select_by is 'val_roads'"
            )
        if self.select_miles is not None:
            check_range(o, "select_miles", self.select_miles, 0.0, 1e4, lo_open=True)
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"{o}.device={self.device!r} is invalid: must be auto, cpu or cuda")
        for prefix, first, stop in self.freeze:
            if not isinstance(prefix, str) or not 0 <= first <= stop:
                raise ValueError(
                    f"{o}.freeze entry {(prefix, first, stop)!r} is invalid: must be "
                    "(name_prefix, first_epoch, stop_epoch) with 0 <= first <= stop"
                )


@dataclass
class History:
    """What training did: one dict per epoch, the best epoch and the wall time.

    Each epoch dict holds ``epoch``, ``train_loss``, ``val_loss``, the objective's validation
    metrics (means, physical units), ``frozen`` (parameter prefixes frozen) and ``seconds``.
    """

    epochs: list[dict[str, Any]]
    best_epoch: int
    seconds: float
    samples_per_s: float
    #: Adam's state after the kept epoch (saved in the checkpoint, not in the JSON history), so a
    #: fine-tune can continue the optimiser instead of restarting it; None when not known.
    optimizer_state: dict[str, Any] | None = field(default=None, repr=False, compare=False)

    @property
    def best(self) -> dict[str, Any]:
        """The best epoch's record."""
        return self.epochs[self.best_epoch]

    def to_dict(self) -> dict[str, Any]:
        """The history as JSON-ready data (without the optimiser state)."""
        return {k: v for k, v in asdict(self).items() if k != "optimizer_state"}


def model_stats(cfg: ModelConfig, data: DrivingData, objective: Objective) -> dict[str, np.ndarray]:
    """The normalisation a model of ``cfg`` trained on ``data`` carries (from the training set,
    as its head computes it for ``objective.target_scale``; the identity for the target when
    ``objective.normalise_targets`` is off)."""
    s = data.stats
    scale = getattr(objective, "target_scale", "coordinate")
    t_mean, t_std = HEADS[cfg.head].stats(data, objective.wheelbase_m, scale)
    if not getattr(objective, "normalise_targets", True):
        t_mean, t_std = np.zeros_like(t_mean), np.ones_like(t_std)
    return {
        "speed_mean": s["speed_mean"],
        "speed_std": s["speed_std"],
        "target_mean": t_mean,
        "target_std": t_std,
        "affordance_mean": s["affordances_mean"],
        "affordance_std": s["affordances_std"],
    }


def _batches(n: int, batch_size: int, rng: np.random.Generator | None) -> list[np.ndarray]:
    order = np.arange(n) if rng is None else rng.permutation(n)
    return [order[i : i + batch_size] for i in range(0, n, batch_size)]


def epoch_batches(n: int, batch_size: int, seed: int, epoch: int) -> list[np.ndarray]:
    """The rows (positions in the training set, ``0 .. n-1``) of each batch of one training
    epoch, in the order :func:`fit` takes them: a permutation seeded by ``(seed, epoch)``, cut
    into batches of ``batch_size`` (the last one may be shorter)."""
    return _batches(n, batch_size, np.random.default_rng([seed, epoch]))


def _to(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def evaluate_loss(
    model: DrivingModel,
    objective: Objective,
    dataset: DrivingDataset,
    batch_size: int = 256,
    device: torch.device | None = None,
    epoch: int | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Per-sample losses (N,) and per-sample metrics of ``model`` on ``dataset`` (eval mode);
    ``epoch``: score as in that training epoch (a GMM's warm-up holds sigma at 1), None: as after
    training."""
    device = device or next(model.parameters()).device
    was_training = model.training
    model.eval()
    losses, metrics = [], {}
    with torch.inference_mode():
        for rows in _batches(len(dataset), batch_size, None):
            batch = _to(dataset.batch(dataset.indices[rows]), device)
            out = model(batch["image"], batch["speed"])
            loss = objective.per_sample(out, batch, model, epoch=epoch)
            losses.append(loss.float().cpu().numpy())
            for k, v in objective.metrics(out, batch, model).items():
                metrics.setdefault(k, []).append(v.float().cpu().numpy())
    model.train(was_training)
    return np.concatenate(losses), {k: np.concatenate(v) for k, v in metrics.items()}


def train_epoch(
    model: DrivingModel,
    objective: Objective,
    train: DrivingDataset,
    opt: torch.optim.Optimizer,
    cfg: TrainConfig,
    epoch: int,
    desc: str = "epoch",
    progress: bool = True,
) -> tuple[float, int]:
    """One pass over ``train`` in ``cfg.seed``'s shuffled batches (:func:`epoch_batches`): forward,
    the objective's batch loss, backward, clipping, Adam. Returns the summed loss (each batch's
    mean times its size) and the samples seen."""
    device = next(model.parameters()).device
    model.train()
    batches = epoch_batches(len(train), cfg.batch_size, cfg.seed, epoch)
    # batch norm needs two samples, a CVaR batch enough for its tail
    if len(batches) > 1 and len(batches[-1]) < getattr(objective, "min_batch", 2):
        batches = batches[:-1]
    total, count = 0.0, 0
    bar = tqdm(batches, desc=desc, unit="batch", disable=not progress, leave=False, mininterval=0.5)
    for rows in bar:
        batch = _to(train.batch(train.indices[rows]), device)
        out = model(batch["image"], batch["speed"])
        loss = objective.batch_loss(out, batch, model, epoch=epoch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        opt.step()
        total += float(loss.detach()) * len(rows)
        count += len(rows)
        bar.set_postfix(loss=f"{total / count:.4f}", refresh=False)
    bar.close()
    return total, count


def fit(
    model: DrivingModel,
    objective: Objective,
    train: DrivingDataset,
    val: DrivingDataset,
    cfg: TrainConfig,
    *,
    name: str = "model",
    progress: bool = True,
    optimizer_state: dict[str, Any] | None = None,
    on_epoch: Callable[[int, DrivingModel], dict[str, float] | None] | None = None,
) -> History:
    """Train ``model`` in place; on return it holds the weights of the best epoch by
    ``cfg.select_by`` (the validation loss, or the decisive-situation error), and the history
    holds Adam's state after that epoch.

    ``on_epoch(epoch, model)``: called after each epoch's validation, the model in eval mode
    (e.g. to keep each epoch's weights, or drive them); what it returns joins the epoch's record.

    ``optimizer_state``: continue that Adam state (a fine-tune of the checkpoint it was saved
    with: its moment estimates and step count carry over) at ``cfg.lr``; None starts a fresh Adam.

    Writes ``<outputs>/training/<name>.json`` (the history) and ``<outputs>/figures/train_<name>.png``.
    """
    device = next(model.parameters()).device
    params = dict(model.named_parameters())
    opt = _adam(model, cfg, optimizer_state)
    val_ds = _validation_rows(val, cfg)
    epochs: list[dict[str, Any]] = []
    best_score, best_epoch, best_state, best_opt = (float("inf"),), 0, None, None
    masks = situations(val_ds.data.arrays, val_ds.indices) if cfg.select_by != "val_loss" else None
    t_start, n_seen, t_train = time.perf_counter(), 0, 0.0
    for epoch in range(cfg.epochs):
        t0 = time.perf_counter()
        frozen = sorted(
            {p for p, a, b in cfg.freeze if a <= epoch < b} | set(objective.frozen_prefixes(epoch))
        )
        for pname, param in params.items():
            param.requires_grad_(not any(pname.startswith(p) for p in frozen))
        desc = f"{name} epoch {epoch + 1}/{cfg.epochs}"
        total, count = train_epoch(model, objective, train, opt, cfg, epoch, desc, progress)
        t_train += time.perf_counter() - t0
        n_seen += count
        losses, decisive = _validate(model, objective, val_ds, cfg, epoch, masks, device)
        record = {"epoch": epoch, "train_loss": total / max(count, 1), **losses}
        record |= {"frozen": frozen, "seconds": time.perf_counter() - t0, **decisive}
        if on_epoch is not None:
            model.eval()
            record.update(on_epoch(epoch, model) or {})
        score = selection_score(record, cfg)
        epochs.append(record)
        if progress:
            print(_epoch_line(name, cfg, record))
        if score < best_score:
            best_score, best_epoch = score, epoch
            best_state = copy.deepcopy(model.state_dict())
            best_opt = copy.deepcopy(opt.state_dict())
        elif cfg.patience is not None and epoch - best_epoch >= cfg.patience:
            if progress:
                print(f"{name}: early stop, no better {cfg.select_by} for {cfg.patience} epochs")
            break
    for param in params.values():
        param.requires_grad_(True)
    if best_state is not None:
        model.load_state_dict(best_state)
    history = History(
        epochs=epochs,
        best_epoch=best_epoch,
        seconds=time.perf_counter() - t_start,
        samples_per_s=n_seen / max(t_train, 1e-9),
        optimizer_state=best_opt,
    )
    save_json(artifact_path("training", f"{name}.json"), history.to_dict())
    save_figure(training_curve(history, name), artifact_path("figures", f"train_{name}.png"))
    return history


def _adam(model: DrivingModel, cfg: TrainConfig, state: dict[str, Any] | None) -> torch.optim.Adam:
    """Adam at ``cfg``'s rate, continuing ``state`` when given (its moments and step count carry
    over; the rate and weight decay are this run's)."""
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    if state is not None:
        opt.load_state_dict(state)
        for group in opt.param_groups:
            group["lr"], group["weight_decay"] = cfg.lr, cfg.weight_decay
    return opt


def _validation_rows(val: DrivingDataset, cfg: TrainConfig) -> DrivingDataset:
    """The validation set, thinned evenly to at most ``cfg.max_val_samples`` rows."""
    if cfg.max_val_samples is None or len(val) <= cfg.max_val_samples:
        return val
    keep = np.linspace(0, len(val) - 1, cfg.max_val_samples).round().astype(int)
    return DrivingDataset(val.data, val.indices[keep])


def _validate(
    model: DrivingModel,
    objective: Objective,
    val: DrivingDataset,
    cfg: TrainConfig,
    epoch: int,
    masks: dict[str, np.ndarray] | None,
    device: torch.device,
) -> tuple[dict[str, float], dict[str, float]]:
    """One epoch's validation: the mean loss and each metric's mean; and (with ``masks``) the
    errors on the decisive situations that ``cfg.select_by`` may keep an epoch by."""
    losses, metrics = evaluate_loss(model, objective, val, device=device, epoch=epoch)
    means = {"val_loss": float(losses.mean()), **{k: float(v.mean()) for k, v in metrics.items()}}
    if masks is not None and "ADE [m]" in metrics:
        return means, decisive_errors(metrics["ADE [m]"], masks)
    if cfg.select_by == "decisive_ade":
        raise ValueError(
            f"TrainConfig.select_by={cfg.select_by!r} needs a trajectory head (ADE metric)"
        )
    return means, {}


def _epoch_line(name: str, cfg: TrainConfig, record: dict[str, Any]) -> str:
    """The line printed after an epoch: its losses, the errors that choose the kept epoch, and
    the parts frozen."""
    shown = ("ADE [m]", DECISIVE, VAL_ROADS)
    extras = ", ".join(f"{k} {v:.3g}" for k, v in record.items() if k in shown or "MAE" in k)
    frozen = record["frozen"]
    return (
        f"{name} epoch {record['epoch'] + 1}/{cfg.epochs}: train {record['train_loss']:.4f}, "
        f"val {record['val_loss']:.4f}"
        + (f" ({extras})" if extras else "")
        + (f", frozen {frozen}" if frozen else "")
    )


def selection_score(record: dict[str, Any], cfg: TrainConfig) -> tuple[float, ...]:
    """What ``cfg.select_by`` ranks an epoch's record by, lower is better: a tuple whose later
    entries break ties. ``"val_roads"``: the collisions of the drive, counted in whole collisions
    (the rate times ``select_miles``, rounded: drives of one budget end a few metres apart, so
    equal counts give rates that differ in the third digit and must tie), then the decisive ADE
    (or the validation loss)."""
    if cfg.select_by == "val_loss":
        return (record["val_loss"],)
    if cfg.select_by == "decisive_ade":
        return (record[DECISIVE],)
    if VAL_ROADS not in record:
        raise ValueError(
            "TrainConfig.select_by='val_roads' needs fit's on_epoch to drive each epoch and "
            f"return {VAL_ROADS!r} (e2e_lite.imitation.selection.road_scorer)"
        )
    collisions = round(record[VAL_ROADS] * float(cfg.select_miles or 0.0) / 100.0)
    return (collisions, record.get(DECISIVE, record["val_loss"]))


def kept_epoch(epochs: list[dict[str, Any]], cfg: TrainConfig) -> int:
    """The epoch ``fit`` keeps from its epochs' records under ``cfg``: the first with the lowest
    :func:`selection_score` (early stopping aside)."""
    scores = [selection_score(r, cfg) for r in epochs]
    return min(range(len(scores)), key=lambda e: scores[e])


def training_curve(history: History, title: str) -> Figure:
    """Training and validation loss per epoch, the best epoch marked, frozen epochs shaded."""
    fig = Figure(figsize=(5.5, 3.4))
    ax = fig.subplots()
    ep = [r["epoch"] + 1 for r in history.epochs]
    ax.plot(ep, [r["train_loss"] for r in history.epochs], "o-", label="train")
    ax.plot(ep, [r["val_loss"] for r in history.epochs], "s-", label="validation")
    ax.axvline(history.best_epoch + 1, color="0.5", ls=":", label="best (kept)")
    for r in history.epochs:
        if r["frozen"]:
            ax.axvspan(r["epoch"] + 0.5, r["epoch"] + 1.5, color="C2", alpha=0.12, lw=0)
    ax.set(xlabel="epoch", ylabel="loss", title=title)
    ax.legend()
    return fig
