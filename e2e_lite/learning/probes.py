"""Probes, and the affordance head refit on the features it reads.

A probe is a small network (one hidden layer) trained on the *frozen* features of a trained model
(:func:`layer_features`, at one of :data:`PROBE_LAYERS`) and asked on held-out frames
(:func:`probe_affordances`). A probe that beats the network's own head says the information is
there and the head does not get it out (chapter 08).

:func:`refit_affordance_head` does the same to the network's own head: it trains the head alone,
for a fixed schedule, on the frozen features it reads. Every other weight stays as it was, so the
network drives exactly as before; only what it perceives changes. The reason (chapter 08): a
driving network keeps the epoch that *drives* best, and when that is an early one the head it
carries has barely trained.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from .dataset import DrivingDataset
from .models import DrivingModel

# ------------------------------------------------------------------ probes
PROBE_LAYERS = ("trunk", "fused")


def layer_features(
    model: DrivingModel, dataset: DrivingDataset, layer: str, batch_size: int = 256
) -> np.ndarray:
    """A fusion model's ``layer`` features (:data:`PROBE_LAYERS`; see ``FusionNet.features``) on
    every sample of ``dataset``, eval mode, as (N, width) float32."""
    if layer not in PROBE_LAYERS:
        raise ValueError(f"layer={layer!r} is invalid: must be one of {PROBE_LAYERS}")
    if not hasattr(model, "features"):
        raise ValueError(f"{type(model).__name__} has no fused features: probe a fusion model")
    device = next(model.parameters()).device
    was_training = model.training
    model.eval()
    out = []
    with torch.inference_mode():
        for start in range(0, len(dataset), batch_size):  # in order, batch by batch
            rows = np.arange(start, min(start + batch_size, len(dataset)))
            batch = dataset.batch(dataset.indices[rows], device=device)
            out.append(model.features(batch["image"], batch["speed"])[layer].float().cpu().numpy())
    model.train(was_training)
    return np.concatenate(out)


def _standardiser(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-unit mean and spread of features ``x`` (N, width). A unit (nearly) constant on the
    training set, e.g. a ReLU that rarely fires, is not blown up by its tiny spread: the floor is
    a hundredth of the typical unit's."""
    x_mean, x_std = x.mean(0), x.std(0)
    floor = 1e-2 * float(np.median(x_std[x_std > 0])) if (x_std > 0).any() else 1.0
    return x_mean, np.maximum(x_std, floor)


def _fit_squared_error(
    net: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, epochs: int, lr: float, seed: int
) -> None:
    """Adam on the mean squared error of ``net(x)`` against ``y``, batches of 256 in a seeded
    order, ``epochs`` passes (in place)."""
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    for _ in range(epochs):
        for rows in torch.randperm(len(x), generator=gen).split(256):
            loss = ((net(x[rows]) - y[rows]) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()


def probe_affordances(
    model: DrivingModel,
    train: DrivingDataset,
    val: DrivingDataset,
    layer: str,
    *,
    hidden: int = 256,
    epochs: int = 30,
    lr: float = 1e-3,
    seed: int = 0,
) -> np.ndarray:
    """Is the affordance information in ``model``'s ``layer``? A probe (one hidden ReLU layer of
    ``hidden`` units, Adam, squared error on standardised targets, as the affordance head's loss)
    trained on the *frozen* features of ``train``, then asked on ``val``.

    A probe that beats the model's own head says the information is in the layer and the head
    does not get it out (its place, its training); a probe no better than the head says the layer
    does not hold it.

    Returns:
        (N_val, 9) predicted affordances, in the units of
        :data:`~e2e_lite.imitation.collector.AFFORDANCE_NAMES`.
    """
    x_train = layer_features(model, train, layer)
    x_val = layer_features(model, val, layer)
    x_mean, x_std = _standardiser(x_train)
    y = train.data.arrays["affordances"][train.indices].astype(np.float32)
    y_mean, y_std = y.mean(0), y.std(0) + 1e-6
    xt = torch.from_numpy((x_train - x_mean) / x_std)
    yt = torch.from_numpy((y - y_mean) / y_std)
    torch.manual_seed(seed)
    probe = torch.nn.Sequential(
        torch.nn.Linear(xt.shape[1], hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, y.shape[1])
    )
    _fit_squared_error(probe, xt, yt, epochs, lr, seed)
    with torch.no_grad():
        pred = probe(torch.from_numpy((x_val - x_mean) / x_std)).numpy()
    return (pred * y_std + y_mean).astype(np.float64)


# ------------------------------------------------------------------ the head, refit
@dataclass(frozen=True)
class HeadRefit:
    """How :func:`refit_affordance_head` trains a network's affordance head on its frozen
    features: the probes' schedule (Adam at ``lr``, batches of 256, ``epochs`` passes over the
    training frames), on inputs standardised per unit (folded back into the head's first layer
    afterwards), from the head's own weights, seeded."""

    epochs: int = 30
    lr: float = 1e-3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.epochs < 0:
            raise ValueError(f"HeadRefit.epochs={self.epochs} is invalid: must be >= 0")
        if not self.lr > 0:
            raise ValueError(f"HeadRefit.lr={self.lr} is invalid: must be > 0")


def refit_affordance_head(
    model: DrivingModel, train: DrivingDataset, settings: HeadRefit = HeadRefit()
) -> DrivingModel:
    """A copy of ``model`` whose affordance head has trained on, alone, on the frozen features it
    reads (``model.cfg.affordance_from``), with the loss the head trained with: the squared error
    of the affordances normalised by the model's own statistics.

    The head's first layer reads standardised features while it trains (the probes' recipe: the
    trunk's units span orders of magnitude) and the standardisation is folded back into its
    weights, ``W <- W / std`` and ``b <- b - W mean``, so the copy is an ordinary network of the
    same settings. Every weight outside the head is the original's: the copy's trajectory output
    is the original's, to the bit.

    Args:
        model: a fusion network with an affordance head (its checkpoint, unchanged).
        train: the frames the head trains on (the network's own training set).
        settings: the schedule (:class:`HeadRefit`).

    Returns:
        The copy, in eval mode, on ``model``'s device.
    """
    if getattr(model, "affordance_head", None) is None:
        raise ValueError(f"{type(model).__name__} has no affordance head to refit")
    device = next(model.parameters()).device
    x = layer_features(model, train, model.cfg.affordance_from)
    x_mean, x_std = _standardiser(x)
    a = train.data.arrays["affordances"][train.indices].astype(np.float32)
    a_mean = model.affordance_mean.detach().cpu().numpy()
    a_std = model.affordance_std.detach().cpu().numpy()
    head = copy.deepcopy(model.affordance_head).float().cpu()
    first = head[0]
    mean_t, std_t = torch.from_numpy(x_mean), torch.from_numpy(x_std)
    with torch.no_grad():  # the same function of standardised inputs
        first.bias += first.weight @ mean_t
        first.weight *= std_t
    torch.manual_seed(settings.seed)
    _fit_squared_error(
        head,
        torch.from_numpy((x - x_mean) / x_std),
        torch.from_numpy((a - a_mean) / a_std),
        settings.epochs,
        settings.lr,
        settings.seed,
    )
    with torch.no_grad():  # folded back: a function of the raw features again
        first.weight /= std_t
        first.bias -= first.weight @ mean_t
    out = copy.deepcopy(model)
    out.affordance_head.load_state_dict(head.state_dict())
    return out.to(device).eval()
