"""Probes: is an affordance in a network's features, or only not read out by its head?

A probe is a small network (one hidden layer) trained on the *frozen* features of a trained model
(:func:`layer_features`, at one of :data:`PROBE_LAYERS`) and asked on held-out frames
(:func:`probe_affordances`). A probe that beats the network's own head says the information is
there and the head does not get it out (chapter 08).
"""

from __future__ import annotations

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
        :data:`~e2e_lite.learning.data.AFFORDANCE_NAMES`.
    """
    x_train = layer_features(model, train, layer)
    x_val = layer_features(model, val, layer)
    x_mean, x_std = x_train.mean(0), x_train.std(0)
    # a unit (nearly) constant on the training set, e.g. a ReLU that rarely fires, is not blown up
    # by its tiny spread: the floor is a hundredth of the typical unit's
    x_std = np.maximum(
        x_std, 1e-2 * float(np.median(x_std[x_std > 0])) if (x_std > 0).any() else 1.0
    )
    y = train.data.arrays["affordances"][train.indices].astype(np.float32)
    y_mean, y_std = y.mean(0), y.std(0) + 1e-6
    xt = torch.from_numpy((x_train - x_mean) / x_std)
    yt = torch.from_numpy((y - y_mean) / y_std)
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    probe = torch.nn.Sequential(
        torch.nn.Linear(xt.shape[1], hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, y.shape[1])
    )
    opt = torch.optim.Adam(probe.parameters(), lr=lr)
    for _ in range(epochs):
        for rows in torch.randperm(len(xt), generator=gen).split(256):
            loss = ((probe(xt[rows]) - yt[rows]) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    with torch.no_grad():
        pred = probe(torch.from_numpy((x_val - x_mean) / x_std)).numpy()
    return (pred * y_std + y_mean).astype(np.float64)
