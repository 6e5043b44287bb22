"""The heads: what a network's main output means. One small class per head says its output size,
its layer, its target, the statistics the target is normalised with, its loss and how a
prediction reads in physical units; :data:`HEADS` names them. Adding a head is one class here.

* ``steer`` (seed 003): the curvature ``kappa = tan(delta) / L`` [1/m], which does not depend on
  the car's geometry;
* ``actuators`` (seed 002, the GM paper's baseline): steering [rad] and acceleration [m/s^2];
* ``trajectory``: five (x, y) points [m], flattened to 10 numbers;
* ``gmm`` (seed 000, section 3.3): the same 10 numbers as a sample of a K-mode diagonal Gaussian
  mixture. Its flat output ``[K x 10 means | K x 10 raw log-sigmas | K logits]`` is read by
  :meth:`Mixture.from_output` into a :class:`Mixture` (its NLL, weights and most likely mode).

Targets and predictions are physical; losses see them normalised with the model's statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch
from torch import nn

from .labels import N_POINTS, POINT_DIMS, TRAJECTORY_DIMS

if TYPE_CHECKING:  # (only for annotations: the heads import nothing of the dataset)
    from .dataset import DrivingData

LOG_2PI = math.log(2.0 * math.pi)
Batch = dict[str, torch.Tensor]


class Head:
    """A point-estimate head: a linear layer of ``target_size`` outputs, trained with the mean
    squared error of the normalised target."""

    name: ClassVar[str]
    target_size: ClassVar[int]
    #: trained with :meth:`loss` by a plain ``Objective`` (a mixture has an objective of its own)
    point_estimate: ClassVar[bool] = True

    def out_size(self, n_modes: int) -> int:
        """Columns of the layer's output (``n_modes``: the model's mixture size, unused here)."""
        return self.target_size

    def layer(self, width: int, n_modes: int) -> nn.Module:
        """The head's layer on ``width`` features."""
        return nn.Linear(width, self.out_size(n_modes))

    def target(self, batch: Batch, wheelbase_m: float) -> torch.Tensor:
        """The physical target of a batch, (B, target_size)."""
        raise NotImplementedError

    def stats(
        self, data: DrivingData, wheelbase_m: float, scale: str = "coordinate"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mean and standard deviation of the target over the training set (physical units);
        ``scale``: ``"coordinate"`` (one per output) or ``"axis"`` (a trajectory's, pooled per
        axis; the other heads have one scale per output either way)."""
        raise NotImplementedError

    def loss(self, out: torch.Tensor, target_n: torch.Tensor) -> torch.Tensor:
        """Per-sample loss (B,) of the normalised output against the normalised target: the mean
        over outputs of the squared error."""
        return ((out - target_n) ** 2).mean(dim=1)

    def metrics(self, pred: torch.Tensor, batch: Batch, wheelbase_m: float) -> Batch:
        """Per-sample errors of a physical prediction (B, target_size), by readable name."""
        raise NotImplementedError


class Steer(Head):
    """Steering as a curvature ``kappa = tan(delta) / L`` [1/m] (one output)."""

    name, target_size = "steer", 1

    def target(self, batch: Batch, wheelbase_m: float) -> torch.Tensor:
        return torch.tan(batch["actuators"][:, :1]) / wheelbase_m

    def stats(
        self, data: DrivingData, wheelbase_m: float, scale: str = "coordinate"
    ) -> tuple[np.ndarray, np.ndarray]:
        kappa = np.tan(data.actuators[:, 0].astype(np.float64)) / wheelbase_m
        return np.array([kappa.mean()]), np.array([max(kappa.std(), 1e-6)])

    def metrics(self, pred: torch.Tensor, batch: Batch, wheelbase_m: float) -> Batch:
        err = (pred - self.target(batch, wheelbase_m)).abs()
        steer_err = (torch.atan(pred * wheelbase_m) - batch["actuators"][:, :1]).abs()
        return {
            "curvature MAE [1/km]": err[:, 0] * 1000.0,
            "steer MAE [deg]": steer_err[:, 0] * (180 / math.pi),
        }


class Actuators(Head):
    """Steering [rad] and acceleration [m/s^2] (two outputs)."""

    name, target_size = "actuators", 2

    def target(self, batch: Batch, wheelbase_m: float) -> torch.Tensor:
        return batch["actuators"]

    def stats(
        self, data: DrivingData, wheelbase_m: float, scale: str = "coordinate"
    ) -> tuple[np.ndarray, np.ndarray]:
        return data.stats["actuators_mean"], data.stats["actuators_std"]

    def metrics(self, pred: torch.Tensor, batch: Batch, wheelbase_m: float) -> Batch:
        err = (pred - self.target(batch, wheelbase_m)).abs()
        return {"steer MAE [deg]": err[:, 0] * (180 / math.pi), "accel MAE [m/s2]": err[:, 1]}


class Trajectory(Head):
    """Five (x, y) points [m] in the car frame, flattened to ``TRAJECTORY_DIMS`` numbers."""

    name, target_size = "trajectory", TRAJECTORY_DIMS

    def target(self, batch: Batch, wheelbase_m: float) -> torch.Tensor:
        return batch["trajectory"]

    def stats(
        self, data: DrivingData, wheelbase_m: float, scale: str = "coordinate"
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per coordinate; with ``scale="axis"`` one pooled standard deviation per axis,
        ``sqrt(mean_k std_k^2)`` over the 5 points (an error keeps its size in metres)."""
        std = data.stats["trajectory_std"]
        if scale == "axis":
            pooled = np.sqrt(np.mean(std.astype(np.float64) ** 2, axis=0))
            return data.stats["trajectory_mean"].reshape(-1), np.tile(pooled, N_POINTS).astype(
                np.float32
            )
        return data.stats["trajectory_mean"].reshape(-1), std.reshape(-1)

    def metrics(self, pred: torch.Tensor, batch: Batch, wheelbase_m: float) -> Batch:
        tgt = self.target(batch, wheelbase_m)
        pts = (pred - tgt).reshape(-1, N_POINTS, POINT_DIMS).norm(dim=-1)
        return {"ADE [m]": pts.mean(dim=1), "FDE [m]": pts[:, -1]}


# ------------------------------------------------------------------------------ the mixture
def split_gmm(out: torch.Tensor, n_modes: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Split a GMM head's output (B, K x 21) into ``(logits (B, K), means (B, K, 10),
    raw_log_sigma (B, K, 10))``. Layout: the K x 10 means, then the K x 10 log-sigmas, then the K
    mixing logits."""
    if n_modes < 1:
        raise ValueError(f"n_modes={n_modes!r} is invalid: must be >= 1")
    if out.shape[-1] != n_modes * 21:
        raise ValueError(
            f"a GMM output with {n_modes} modes must have {n_modes * 21} columns; got {out.shape[-1]}"
        )
    k10 = n_modes * TRAJECTORY_DIMS
    means = out[..., :k10].reshape(*out.shape[:-1], n_modes, TRAJECTORY_DIMS)
    raw = out[..., k10 : 2 * k10].reshape(*out.shape[:-1], n_modes, TRAJECTORY_DIMS)
    return out[..., 2 * k10 :], means, raw


def log_sigma(raw: torch.Tensor, floor: float | torch.Tensor) -> torch.Tensor:
    """``log(floor + exp(raw))``: a log standard deviation that is smooth in ``raw`` and never
    below ``log(floor)`` (so ``1 / sigma`` stays finite). ``floor``: a number, or one per target
    dimension (the last axis of ``raw``)."""
    log_floor = torch.log(torch.as_tensor(floor, dtype=raw.dtype, device=raw.device))
    return torch.logaddexp(raw, log_floor.expand_as(raw))


def gmm_nll(
    target: torch.Tensor,
    logits: torch.Tensor,
    means: torch.Tensor,
    log_sig: torch.Tensor,
) -> torch.Tensor:
    """Negative log-likelihood of ``target`` (B, D) under a diagonal Gaussian mixture, per sample.

    ``-log sum_k pi_k N(y | mu_k, diag(sigma_k^2))`` with ``pi = softmax(logits)``, computed as
    ``-logsumexp_k(log_softmax(logits)_k + log N_k)`` and
    ``log N_k = -1/2 sum_d [((y_d - mu_kd) / sigma_kd)^2 + 2 log sigma_kd + log 2 pi]``. The constant
    ``D/2 log 2 pi`` is kept, so the value is a true negative log-density (of normalised targets).

    Args:
        target: (B, D). logits: (B, K). means, log_sig: (B, K, D).
    """
    if (
        means.shape != log_sig.shape
        or means.shape[:-2] != target.shape[:-1]
        or means.shape[-1] != target.shape[-1]
    ):
        raise ValueError(
            f"mismatched GMM shapes: target {tuple(target.shape)}, means {tuple(means.shape)}, "
            f"log_sigma {tuple(log_sig.shape)}, logits {tuple(logits.shape)}"
        )
    z = (target.unsqueeze(-2) - means) * torch.exp(-log_sig)
    log_n = -0.5 * (z * z + 2.0 * log_sig + LOG_2PI).sum(dim=-1)  # (B, K)
    return -torch.logsumexp(torch.log_softmax(logits, dim=-1) + log_n, dim=-1)


@dataclass(frozen=True)
class Mixture:
    """What a GMM head predicts for a batch, in the model's normalised target units: a diagonal
    Gaussian mixture per sample.

    Attributes:
        logits: (B, K) mixing logits (weights ``softmax(logits)``).
        means: (B, K, D) mode means.
        log_sigma: (B, K, D) log standard deviations (already floored).
    """

    logits: torch.Tensor
    means: torch.Tensor
    log_sigma: torch.Tensor

    @classmethod
    def from_output(
        cls,
        out: torch.Tensor,
        n_modes: int,
        floor: float | torch.Tensor,
        sigma_fixed: bool = False,
    ) -> Mixture:
        """The mixture in a GMM head's flat output (B, K x 21) (layout: :func:`split_gmm`), its
        sigmas floored at ``floor`` (normalised units; a number or one per dimension), or every
        sigma held at 1 when ``sigma_fixed`` (the warm-up)."""
        logits, means, raw = split_gmm(out, n_modes)
        log_sig = torch.zeros_like(raw) if sigma_fixed else log_sigma(raw, floor)
        return cls(logits, means, log_sig)

    @property
    def weights(self) -> torch.Tensor:
        """(B, K) mixing weights, summing to 1."""
        return torch.softmax(self.logits, dim=-1)

    def nll(self, target: torch.Tensor) -> torch.Tensor:
        """(B,) negative log-likelihood of ``target`` (B, D) (:func:`gmm_nll`)."""
        return gmm_nll(target, self.logits, self.means, self.log_sigma)

    def top(self) -> torch.Tensor:
        """(B,) index of each sample's most likely mode (the paper follows it)."""
        return self.weights.argmax(dim=-1)

    def followed(self, decode: str = "top", modes: torch.Tensor | None = None) -> torch.Tensor:
        """(B, D) the trajectory a driver follows: the most likely mode (``"top"``) or the
        mixture's mean (``"mean"``, the modes averaged with their weights). ``modes``: the same
        modes in other units, e.g. metres (default: :attr:`means`)."""
        modes = self.means if modes is None else modes
        if decode == "mean":
            return (self.weights[..., None] * modes).sum(dim=1)
        top = self.top()
        return modes[torch.arange(len(top), device=top.device), top]


class MixtureLayer(nn.Module):
    """The GMM head's layers: separate ones for the means, the log-sigmas and the mixing logits
    (so the log-sigma layer can be frozen by name, ``head.log_sigma``), concatenated as
    ``[means | log-sigmas | logits]`` (K x 10, K x 10, K)."""

    def __init__(self, width: int, n_modes: int) -> None:
        super().__init__()
        self.means = nn.Linear(width, n_modes * TRAJECTORY_DIMS)
        self.log_sigma = nn.Linear(width, n_modes * TRAJECTORY_DIMS)
        self.logits = nn.Linear(width, n_modes)
        # start every sigma near 1 (log sigma ~ 0) so opening them after a warm-up is smooth
        nn.init.zeros_(self.log_sigma.bias)
        nn.init.normal_(self.log_sigma.weight, std=1e-3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.means(x), self.log_sigma(x), self.logits(x)], dim=-1)


class GMM(Trajectory):
    """A K-mode mixture over the trajectory's 10 numbers: ``K x 21`` outputs."""

    name = "gmm"
    point_estimate = False

    def out_size(self, n_modes: int) -> int:
        return n_modes * (2 * TRAJECTORY_DIMS + 1)

    def layer(self, width: int, n_modes: int) -> nn.Module:
        return MixtureLayer(width, n_modes)

    def loss(self, out: torch.Tensor, target_n: torch.Tensor) -> torch.Tensor:
        raise TypeError("a GMM head's loss is its mixture's NLL: see GMMObjective")


#: every head by name (``ModelConfig.head``)
HEADS: dict[str, Head] = {h.name: h for h in (Steer(), Actuators(), Trajectory(), GMM())}


#: the heads a plain mean-squared-error ``Objective`` trains
POINT_HEADS = tuple(n for n, h in HEADS.items() if h.point_estimate)


def head_of(name: str) -> Head:
    """The head called ``name``; a clear error for an unknown one."""
    if name not in HEADS:
        raise ValueError(f"head={name!r} is invalid: must be one of {list(HEADS)}")
    return HEADS[name]
