"""Training objectives: the target of each head, its per-sample loss, and readable metrics.

Losses are computed **per sample** (shape (B,)) in normalised units; the training loop averages
them (chapter 09's CVaR will instead average only the worst). Metrics are per sample too, in
physical units, so a held-out table reads in degrees and metres.

Targets per head (see :class:`~e2e_lite.models.ModelConfig`):

* ``steer``: the expert's steering as a curvature ``kappa = tan(delta) / L`` [1/m] (seed 003 trained
  on the inverse turning radius, which does not depend on the car's geometry);
* ``actuators``: steering [rad] and acceleration [m/s^2] (seed 002 / the GM paper's baseline);
* ``trajectory``: the 5-point label flattened to 10 numbers [m];
* ``gmm``: the same 10 numbers, as a sample of a K-mode Gaussian mixture (:class:`GMMObjective`).
"""

from __future__ import annotations

import math

import torch

from .config import check_range
from .models import DrivingModel

LOG_2PI = math.log(2.0 * math.pi)


def target(head: str, batch: dict[str, torch.Tensor], wheelbase_m: float) -> torch.Tensor:
    """The physical target of ``head`` for a batch, (B, target_size)."""
    if head == "steer":
        return torch.tan(batch["actuators"][:, :1]) / wheelbase_m
    if head == "actuators":
        return batch["actuators"]
    if head in ("trajectory", "gmm"):
        return batch["trajectory"]
    raise ValueError(f"head={head!r} is invalid: must be steer, actuators, trajectory or gmm")


class Objective:
    """Mean squared error on the normalised target of a point-estimate head.

    Args:
        head: the model's head (``steer``, ``actuators`` or ``trajectory``).
        wheelbase_m: to turn steering angles into curvatures [m].
    """

    def __init__(self, head: str, wheelbase_m: float = 2.7) -> None:
        if head not in ("steer", "actuators", "trajectory"):
            raise ValueError(
                f"Objective.head={head!r} is invalid: must be steer, actuators or trajectory"
            )
        self.head = head
        self.wheelbase_m = wheelbase_m
        self.name = f"mse-{head}"

    def start_epoch(self, epoch: int) -> None:
        """Called by the training loop before each epoch (a hook for schedules)."""

    def frozen_prefixes(self, epoch: int) -> list[str]:
        """Parameter-name prefixes this objective wants frozen in ``epoch`` (none)."""
        return []

    def per_sample(
        self, out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], model: DrivingModel
    ) -> torch.Tensor:
        """Loss of each sample, (B,): the mean over outputs of the squared normalised error."""
        tgt = model.normalise_target(target(self.head, batch, self.wheelbase_m))
        return ((out["main"] - tgt) ** 2).mean(dim=1)

    def metrics(
        self, out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], model: DrivingModel
    ) -> dict[str, torch.Tensor]:
        """Per-sample absolute errors in physical units, by readable name."""
        pred = model.denormalise(out["main"])
        tgt = target(self.head, batch, self.wheelbase_m)
        err = (pred - tgt).abs()
        if self.head == "steer":
            steer_err = (torch.atan(pred * self.wheelbase_m) - batch["actuators"][:, :1]).abs()
            return {
                "curvature MAE [1/km]": err[:, 0] * 1000.0,
                "steer MAE [deg]": steer_err[:, 0] * (180 / math.pi),
            }
        if self.head == "actuators":
            return {"steer MAE [deg]": err[:, 0] * (180 / math.pi), "accel MAE [m/s2]": err[:, 1]}
        pts = (pred - tgt).reshape(-1, 5, 2).norm(dim=-1)
        return {"ADE [m]": pts.mean(dim=1), "FDE [m]": pts[:, -1]}


# ------------------------------------------------------------------------------ GMM
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
    k10 = n_modes * 10
    means = out[..., :k10].reshape(*out.shape[:-1], n_modes, 10)
    raw = out[..., k10 : 2 * k10].reshape(*out.shape[:-1], n_modes, 10)
    return out[..., 2 * k10 :], means, raw


def log_sigma(raw: torch.Tensor, floor: float) -> torch.Tensor:
    """``log(floor + exp(raw))``: a log standard deviation that is smooth in ``raw`` and never
    below ``log(floor)`` (so ``1 / sigma`` stays finite)."""
    return torch.logaddexp(raw, torch.full_like(raw, math.log(floor)))


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


class GMMObjective(Objective):
    """The mixture-density loss of seed 000 (section 3.3) on the normalised trajectory.

    Args:
        n_modes: K (the paper: 2).
        sigma_floor: smallest standard deviation, in normalised units (1 = one dataset standard
            deviation of that coordinate).
        sigma_warmup_epochs: for the first epochs every sigma is held at 1 (the loss is then a
            mixture of squared errors) and the head's log-sigma layer is frozen; then opened
            (the paper froze sigma for 5 epochs).
        wheelbase_m: unused by the GMM; kept for the common interface.
    """

    def __init__(
        self,
        n_modes: int = 2,
        sigma_floor: float = 0.01,
        sigma_warmup_epochs: int = 1,
        wheelbase_m: float = 2.7,
    ) -> None:
        check_range("GMMObjective", "n_modes", n_modes, 1, 16, integer=True)
        check_range("GMMObjective", "sigma_floor", sigma_floor, 0.0, 1.0, lo_open=True)
        check_range("GMMObjective", "sigma_warmup_epochs", sigma_warmup_epochs, 0, integer=True)
        self.head = "gmm"
        self.n_modes = n_modes
        self.sigma_floor = sigma_floor
        self.sigma_warmup_epochs = sigma_warmup_epochs
        self.wheelbase_m = wheelbase_m
        self.name = f"gmm-nll-K{n_modes}-floor{sigma_floor}-warmup{sigma_warmup_epochs}"
        self.sigma_fixed = sigma_warmup_epochs > 0

    def start_epoch(self, epoch: int) -> None:
        """Hold sigma at 1 during the warm-up epochs."""
        self.sigma_fixed = epoch < self.sigma_warmup_epochs

    def frozen_prefixes(self, epoch: int) -> list[str]:
        """Parameters the training loop freezes this epoch: the log-sigma layer during warm-up."""
        return ["head.log_sigma"] if epoch < self.sigma_warmup_epochs else []

    def modes(
        self, out: dict[str, torch.Tensor], model: DrivingModel
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(weights (B, K), means (B, K, 10) normalised, log_sigma (B, K, 10))``."""
        logits, means, raw = split_gmm(out["main"], self.n_modes)
        return torch.softmax(logits, dim=-1), means, log_sigma(raw, self.sigma_floor)

    def per_sample(
        self, out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], model: DrivingModel
    ) -> torch.Tensor:
        """The NLL of each sample's normalised trajectory."""
        logits, means, raw = split_gmm(out["main"], self.n_modes)
        log_sig = torch.zeros_like(raw) if self.sigma_fixed else log_sigma(raw, self.sigma_floor)
        tgt = model.normalise_target(target("gmm", batch, self.wheelbase_m))
        return gmm_nll(tgt, logits, means, log_sig)

    def metrics(
        self, out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], model: DrivingModel
    ) -> dict[str, torch.Tensor]:
        """ADE/FDE of the most likely mode's mean [m], the best mode's ADE, the top weight."""
        weights, means, _ = self.modes(out, model)
        tgt = target("gmm", batch, self.wheelbase_m).reshape(-1, 1, 5, 2)
        pts = model.denormalise(means).reshape(*means.shape[:2], 5, 2)
        dist = (pts - tgt).norm(dim=-1)  # (B, K, 5)
        top = weights.argmax(dim=-1)
        rows = torch.arange(len(top), device=top.device)
        return {
            "ADE [m]": dist[rows, top].mean(dim=-1),
            "FDE [m]": dist[rows, top, -1],
            "min-ADE over modes [m]": dist.mean(dim=-1).min(dim=-1).values,
            "top weight": weights.max(dim=-1).values,
        }


def most_likely(weights: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    """The mean of the mode with the largest weight (the paper's inference): (B, D)."""
    top = weights.argmax(dim=-1)
    return means[torch.arange(len(top), device=top.device), top]
