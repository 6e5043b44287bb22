"""Checkpoints that know what they were trained on, and :func:`train_or_load`.

A checkpoint stores the model's settings, its weights *and normalisation buffers*, the training
settings, the objective's name and the dataset's key (and Adam's state after the kept epoch, for
a fine-tune to continue). :func:`load_checkpoint` refuses a checkpoint made with other settings
or statistics (:class:`CheckpointMismatch`) instead of letting a driver run with the wrong
normalisation; :func:`train_or_load` reuses a valid one and trains (seeded) otherwise.
"""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from ..artifacts import (
    CorruptArtifact,
    artifact_path,
    atomic_write,
    check_seal,
    key_fields,
    settings_key,
    versioned,
)
from ..config import precision
from .dataset import DrivingData, DrivingDataset
from .losses import Objective
from .models import DrivingModel, ModelConfig, build_model, pick_device, prepare, weights_digest
from .probes import HeadRefit, refit_affordance_head
from .training import History, TrainConfig, fit, kept_epoch, model_stats


class CheckpointMismatch(ValueError):
    """A checkpoint was made with other settings, statistics or data than asked for."""


# ------------------------------------------------------------------ checkpoints
def checkpoint_key(
    model_cfg: ModelConfig, train_cfg: TrainConfig, objective: Objective, data_key: str
) -> str:
    """The settings key of a training run (the device is left out: CPU and GPU runs share it;
    the precision, :func:`~e2e_lite.config.precision`, is in)."""
    return settings_key(
        versioned("checkpoint"),
        model_cfg,
        key_fields(train_cfg, device=None),
        objective.name,
        data_key,
        precision(),
    )


def save_checkpoint(
    path: Path | str,
    model: DrivingModel,
    train_cfg: TrainConfig,
    objective: Objective,
    data_key: str,
    history: History | None = None,
    key: str | None = None,
) -> Path:
    """Write a checkpoint (weights, normalisation, settings, data key, history) atomically.
    ``key`` overrides the settings key (a fine-tune's includes its parent's)."""
    blob = {
        "key": key or checkpoint_key(model.cfg, train_cfg, objective, data_key),
        "model_config": model.config_dict(),
        "train_config": asdict(train_cfg),
        "objective": objective.name,
        "data_key": data_key,
        "normalisation": model.normalisation(),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "history": None if history is None else history.to_dict(),
        "optimizer": None if history is None else history.optimizer_state,
    }
    with atomic_write(path, sealed=True) as f:
        torch.save(blob, f)
    return Path(path)


def load_checkpoint(
    path: Path | str,
    model_cfg: ModelConfig | None = None,
    data_key: str | None = None,
    normalisation: dict[str, np.ndarray] | None = None,
    device: torch.device | str = "cpu",
) -> tuple[DrivingModel, dict[str, Any]]:
    """Load a checkpoint; refuse it (:class:`CheckpointMismatch`) when what is asked differs.

    Args:
        path: the file.
        model_cfg: the settings the caller expects (None: accept the stored ones).
        data_key: the dataset the caller drives/evaluates with (None: do not check).
        normalisation: the statistics the caller expects (None: do not check).
        device: where to put the model.

    Returns:
        ``(model in eval mode, the checkpoint's metadata)``.

    Raises:
        CorruptArtifact: the file does not match the digest sealed beside it (``torch.load``
            checks nothing: a flipped bit in a weight would load).
    """
    check_seal(path)
    blob = torch.load(path, map_location="cpu", weights_only=False)
    stored_cfg = ModelConfig(**blob["model_config"])
    if model_cfg is not None and stored_cfg != model_cfg:
        differ = ", ".join(
            f"{f} {getattr(stored_cfg, f)!r} (asked: {getattr(model_cfg, f)!r})"
            for f in asdict(stored_cfg)
            if getattr(stored_cfg, f) != getattr(model_cfg, f)
        )
        raise CheckpointMismatch(
            f"{Path(path).name} holds a model of other settings: {differ}; retrain or ask for "
            "the stored settings"
        )
    if data_key is not None and blob["data_key"] != data_key:
        raise CheckpointMismatch(
            f"{Path(path).name} was trained on dataset {blob['data_key']}, not {data_key}: its "
            "normalisation belongs to that data; retrain on this one"
        )
    if normalisation is not None:
        for name, value in normalisation.items():
            stored = np.asarray(blob["normalisation"][name], dtype=np.float32).ravel()
            value = np.asarray(value, dtype=np.float32).ravel()
            if stored.shape != value.shape or not np.allclose(stored, value, rtol=1e-5, atol=1e-7):
                raise CheckpointMismatch(
                    f"{Path(path).name} normalises with other statistics ({name}: stored "
                    f"{np.round(np.asarray(stored).ravel()[:4], 4).tolist()}..., expected "
                    f"{np.round(np.asarray(value).ravel()[:4], 4).tolist()}...); refusing to drive "
                    "with the wrong normalisation"
                )
    model = build_model(stored_cfg)
    model.load_state_dict(blob["state_dict"])
    model = prepare(model, torch.device(device))
    model.eval()
    meta = {k: blob[k] for k in ("key", "train_config", "objective", "data_key", "history")}
    meta["optimizer"] = blob.get("optimizer")  # None in checkpoints saved before it was kept
    return model, meta


def training_data_key(
    train_data: DrivingData, val_data: DrivingData, train_rows: np.ndarray | None = None
) -> str:
    """The key of the data a network is trained on (its checkpoint's ``data_key``): the training
    and validation sets and, when given, the rows of the training set used."""
    rows = None if train_rows is None else np.asarray(train_rows, dtype=np.int64).tobytes()
    return settings_key(
        train_data.info["key"],
        val_data.info["key"],
        None if rows is None else hashlib.sha256(rows).hexdigest(),
    )


def train_or_load(
    name: str,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    objective: Objective,
    train_data: DrivingData,
    val_data: DrivingData,
    *,
    train_rows: np.ndarray | None = None,
    init_from: str | None = None,
    parent_data_key: str | None = None,
    carry_optimizer: bool = False,
    keep_optimizer: bool = False,
    progress: bool = True,
    on_epoch: Callable[[int, DrivingModel], dict[str, float] | None] | None = None,
) -> tuple[DrivingModel, History]:
    """The model ``name`` from ``<outputs>/checkpoints/<name>.pt`` if it was trained with these
    settings on this data; otherwise train it (seeded), save it and return it.

    The objective holds no training state (a GMM's warm-up is the ``epoch`` its loss is given;
    scored without one, the warm-up is over), so a reused and a freshly trained model are scored
    alike.

    Args:
        name: checkpoint and figure name.
        model_cfg, train_cfg, objective: what to train and how.
        train_data, val_data: the datasets (statistics come from ``train_data``).
        train_rows: train on these rows of ``train_data`` only (e.g. without recovery views).
        init_from: fine-tune: start from the weights of checkpoint ``<init_from>.pt`` (same model
            settings and data; its key joins this checkpoint's, so a retrained parent makes this
            one stale). Raises :class:`CheckpointMismatch` when it is missing or does not fit.
        parent_data_key: with ``init_from``, the parent was trained on this other dataset (DAgger's
            fine-tune on the aggregate, chapter 12); the normalisation must still be the parent's
            (an aggregate keeps its first part's statistics, :func:`~e2e_lite.learning.dataset.concat`).
        carry_optimizer: with ``init_from``, continue the parent's Adam state (at this run's
            learning rate) instead of a fresh Adam; the parent must have kept it
            (``keep_optimizer``), else :class:`CheckpointMismatch`.
        keep_optimizer: a stored checkpoint without its optimiser state is retrained, so a
            fine-tune can carry the state on.
        progress: progress bars and per-epoch lines.
        on_epoch: given to :func:`~e2e_lite.learning.training.fit` when the model is trained
            (not called for a stored one).
    """
    device = pick_device(train_cfg.device)
    rows = np.arange(len(train_data)) if train_rows is None else np.asarray(train_rows)
    data_key = training_data_key(train_data, val_data, train_rows)
    path = artifact_path("checkpoints", f"{name}.pt")
    stats = model_stats(model_cfg, train_data, objective)
    key = checkpoint_key(model_cfg, train_cfg, objective, data_key)
    parent, parent_meta = None, {"optimizer": None}
    if init_from is not None:
        parent, parent_meta, key = _parent(
            name, init_from, key, model_cfg, parent_data_key or data_key, stats, device
        )
        if carry_optimizer:
            if parent_meta["optimizer"] is None:
                raise CheckpointMismatch(
                    f"{name} continues the optimiser of {init_from}, but {init_from}.pt has "
                    "no optimiser state: retrain it with keep_optimizer=True"
                )
            key = settings_key(key, "optimizer carried")
    elif carry_optimizer:
        raise ValueError("carry_optimizer needs init_from: whose optimiser would it carry?")
    stored = _stored(path, key, model_cfg, train_cfg, data_key, stats, device, keep_optimizer)
    if stored.model is not None:
        if progress:
            print(f"[checkpoints] {name}: reusing {path.name}")
        return stored.model, stored.history
    if progress and stored.why:
        print(f"[checkpoints] {name}: {stored.why}; retraining")
    torch.manual_seed(train_cfg.seed)
    if parent is not None:
        model = parent
    else:
        model = build_model(model_cfg)
        model.set_normalisation(stats)
        model = prepare(model, device)
    history = fit(
        model,
        objective,
        DrivingDataset(train_data, rows),
        DrivingDataset(val_data),
        train_cfg,
        name=name,
        progress=progress,
        optimizer_state=parent_meta["optimizer"] if carry_optimizer else None,
        on_epoch=on_epoch,
    )
    model.eval()
    save_checkpoint(path, model, train_cfg, objective, data_key, history, key=key)
    return model, history


def _parent(
    name: str,
    init_from: str,
    key: str,
    model_cfg: ModelConfig,
    data_key: str,
    stats: dict[str, Any],
    device: torch.device,
) -> tuple[DrivingModel, dict[str, Any], str]:
    """A fine-tune's parent checkpoint ``init_from``: its model, its metadata, and the fine-tune's
    ``key`` joined with the parent's key and weights (a parent retrained with the same settings,
    another kept epoch, makes the fine-tune stale)."""
    parent_path = artifact_path("checkpoints", f"{init_from}.pt")
    if not parent_path.exists():
        raise CheckpointMismatch(
            f"{name} fine-tunes {init_from}, but {parent_path} does not exist: train it first"
        )
    parent, meta = load_checkpoint(parent_path, model_cfg, data_key, stats, device)
    return parent, meta, settings_key(key, meta["key"], weights_digest(parent))


class _Stored(NamedTuple):
    """A stored checkpoint that may be reused (``model`` and ``history``), or why it may not
    (``why``, "" when there is none)."""

    model: DrivingModel | None = None
    history: History | None = None
    why: str = ""


def _stored(
    path: Path,
    key: str,
    model_cfg: ModelConfig,
    train_cfg: TrainConfig,
    data_key: str,
    stats: dict[str, Any],
    device: torch.device,
    keep_optimizer: bool,
) -> _Stored:
    """The checkpoint at ``path`` if it was trained with ``key`` and its kept epoch is the one
    ``train_cfg``'s rule keeps (a rule fixed since it was trained retrains it, and only it);
    with ``keep_optimizer``, only if it kept its optimiser state. A corrupt or unreadable file is
    retrained, never trusted."""
    if not path.exists():
        return _Stored()
    try:
        model, meta = load_checkpoint(path, model_cfg, data_key, stats, device)
    except (CheckpointMismatch, CorruptArtifact) as err:
        return _Stored(why=str(err))
    except Exception as err:
        return _Stored(why=f"unreadable ({type(err).__name__})")
    hist = meta["history"]
    if meta["key"] != key or hist is None:
        return _Stored(why="trained with other settings")
    if meta["optimizer"] is None and keep_optimizer:
        return _Stored(why="trained with no optimiser state kept")
    if kept_epoch(hist["epochs"], train_cfg) != hist["best_epoch"]:
        why = f"epoch {hist['best_epoch'] + 1} kept, which train_cfg's rule would not keep"
        return _Stored(why=f"trained with {why}")
    return _Stored(model, History(**hist))


def refit_or_load(
    name: str,
    model: DrivingModel,
    train_data: DrivingData,
    settings: HeadRefit,
    *,
    progress: bool = True,
) -> DrivingModel:
    """``model`` with its affordance head refit on its frozen features
    (:func:`~e2e_lite.learning.probes.refit_affordance_head`, every training frame), the head
    stored as ``<outputs>/checkpoints/<name>_head.pt`` and read back while the network's weights
    (:func:`weights_digest`), the data and ``settings`` are the same; otherwise refit (seeded)
    and stored. Only the head is stored: the rest of the network is ``model``'s own checkpoint.

    Returns:
        A copy of ``model`` (eval mode) with the refit head; ``model`` is left as it was.
    """
    key = settings_key(
        versioned("head-refit"), settings, weights_digest(model), train_data.info["key"]
    )
    path = artifact_path("checkpoints", f"{name}_head.pt")
    if path.exists():
        try:
            check_seal(path)
            blob = torch.load(path, map_location="cpu", weights_only=True)
            if blob["key"] == key:
                out = copy.deepcopy(model)
                out.affordance_head.load_state_dict(blob["head"])
                if progress:
                    print(f"[checkpoints] {name}: reusing the refit head {path.name}")
                return out.eval()
            if progress:
                print(f"[checkpoints] {name}: head refit for another network or data; refitting")
        except CorruptArtifact as err:
            if progress:
                print(f"[checkpoints] {name}: {err}; refitting")
        except Exception as err:  # a corrupt file is refit, never trusted
            if progress:
                print(f"[checkpoints] {name}: unreadable head ({type(err).__name__}); refitting")
    if progress:
        print(f"[checkpoints] {name}: refitting the affordance head on the frozen features")
    out = refit_affordance_head(model, DrivingDataset(train_data), settings)
    head = {k: v.detach().cpu() for k, v in out.affordance_head.state_dict().items()}
    with atomic_write(path, sealed=True) as f:
        torch.save({"key": key, "head": head}, f)
    return out
