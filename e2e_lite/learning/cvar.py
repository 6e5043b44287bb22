"""CVaR (seed 000, section 3.5): train on the worst ``1 - alpha`` of each batch (chapter 09).

:func:`cvar` is the statistic (the mean of the worst share, the boundary sample weighted by the
fraction left); :func:`cvar_ru` is Rockafellar and Uryasev's form with a threshold ``nu``;
:func:`cvar_loss` is the training reduction (gradients reach the tail only); :func:`cvar_curve`
reads CVaR over alphas (the paper's Fig. 5); :class:`CVaRObjective` wraps any objective to reduce
its batch by CVaR, ranking the tail by the loss itself or by the followed trajectory's error.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from ..config import check_range
from .heads import Batch
from .losses import Objective, WrappedObjective
from .models import DrivingModel


def cvar(losses: np.ndarray | torch.Tensor, alpha: float) -> float:
    """Conditional value at risk: the mean of the worst ``1 - alpha`` share of ``losses``.

    ``CVaR_alpha(L) = E[L | L >= nu_alpha]`` with ``nu_alpha`` the alpha-quantile. On a finite
    sample of n losses the tail holds ``k = (1 - alpha) n`` samples; when k is not an integer (a
    tiny batch) or several losses tie at the quantile, the boundary sample enters with the
    fractional weight ``k - floor(k)``. This is Rockafellar and Uryasev's
    ``min_nu nu + E[(L - nu)+] / (1 - alpha)``, so: ``alpha = 0`` gives the mean, the value never
    decreases with alpha, and as alpha -> 1 it tends to the maximum.

    Args:
        losses: (N,) per-sample losses, N >= 1.
        alpha: the quantile level, ``0 <= alpha < 1``.
    """
    values = torch.as_tensor(losses).detach().double().reshape(-1)
    return float(_tail_mean(values, alpha))


def _check_alpha(alpha: float, n: int, lo_closed: bool, owner: str = "cvar") -> None:
    """``alpha`` a number in [0, 1) (``lo_closed``) or (0, 1), named with its ``owner``."""
    check_range(owner, "alpha", alpha, 0.0, 1.0, lo_open=not lo_closed, hi_open=True)
    if n < 1:
        raise ValueError("CVaR of an empty set of losses is undefined: give at least one sample")


def _tail_weights(n: int, alpha: float, like: torch.Tensor) -> torch.Tensor:
    """Weights of the n samples sorted worst first: 1 for the whole tail, the fraction left for
    the boundary sample, 0 below it."""
    k = (1.0 - alpha) * n
    # k within rounding of an integer counts as that integer; dividing by the weights actually
    # given (not by k) keeps the result a convex combination of the tail, so never above the max.
    whole = math.floor(k + 1e-9)
    frac = k - whole
    weights = torch.zeros(n, dtype=like.dtype, device=like.device)
    weights[:whole] = 1.0
    if whole < n and frac > 1e-9:
        weights[whole] = frac
    return weights


def _tail_mean(
    values: torch.Tensor, alpha: float, rank: torch.Tensor | None = None
) -> torch.Tensor:
    """The mean of ``values`` over the worst ``1 - alpha`` share, worst by ``rank`` (default: by
    the values themselves)."""
    _check_alpha(alpha, values.numel(), lo_closed=True)
    order = torch.argsort(values.detach() if rank is None else rank, descending=True)
    weights = _tail_weights(values.numel(), alpha, values)
    return (weights * values[order]).sum() / weights.sum()


def cvar_ru(losses: torch.Tensor, nu: torch.Tensor | float, alpha: float) -> torch.Tensor:
    """Rockafellar and Uryasev's form of CVaR: ``nu + E[(L - nu)+] / (1 - alpha)``, a scalar.

    For every threshold ``nu`` it is at least :func:`cvar` of the same losses, and it equals it
    at the alpha-quantile (the boundary sample of :func:`cvar`'s sorted tail), so minimising it
    over ``nu`` gives CVaR. Unlike the sorted tail it needs no sort: with ``nu`` a trained
    parameter shared across batches, each sample's gradient is ``1 / ((1 - alpha) n)`` when its
    loss is above ``nu``, whatever the batch's own quantile.

    Args:
        losses: (N,) per-sample losses (with gradients or not).
        nu: the threshold (a tensor to learn it, or a number), in the losses' units.
        alpha: the quantile level, ``0 <= alpha < 1``.
    """
    _check_alpha(alpha, losses.numel(), lo_closed=True, owner="cvar_ru")
    nu = torch.as_tensor(nu, dtype=losses.dtype, device=losses.device)
    return nu + torch.relu(losses.reshape(-1) - nu).mean() / (1.0 - alpha)


def cvar_loss(losses: torch.Tensor, alpha: float, min_tail: int = 10) -> torch.Tensor:
    """The CVaR training loss of seed 000 (eq. 3): :func:`cvar` of a batch's per-sample losses,
    differentiable; gradients flow only into the samples of the tail (the boundary sample with its
    fractional weight), so the samples below the batch's alpha-quantile get exactly zero.

    Args:
        losses: (B,) per-sample losses with gradients.
        alpha: in (0, 1); 0.9 trains on the worst 10 %.
        min_tail: warn when the batch leaves fewer tail samples than this (the batch size must
            grow with alpha: B >= min_tail / (1 - alpha)).
    """
    if losses.dim() != 1:
        raise ValueError(
            f"cvar_loss takes per-sample losses of shape (B,), got {tuple(losses.shape)}"
        )
    _check_alpha(alpha, losses.numel(), lo_closed=False, owner="cvar_loss")
    check_range("cvar_loss", "min_tail", min_tail, 1, integer=True)
    k = (1.0 - alpha) * losses.numel()
    if k < min_tail:
        warnings.warn(
            f"CVaR-{alpha:g} on a batch of {losses.numel()} keeps only {k:.1f} samples in the tail "
            f"(< {min_tail}); use batches of at least {math.ceil(min_tail / (1 - alpha) - 1e-9)}",
            stacklevel=2,
        )
    return _tail_mean(losses, alpha)


def cvar_curve(
    losses: np.ndarray, alphas: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(alphas, CVaR_alpha(losses))`` over a percentile grid (default 0, 1, ..., 99 %): seed
    000's Fig. 5."""
    alphas = np.arange(100) / 100.0 if alphas is None else np.asarray(alphas, dtype=float)
    values = torch.as_tensor(np.asarray(losses, dtype=np.float64)).reshape(-1)
    return alphas, np.array([float(_tail_mean(values, float(a))) for a in alphas])


#: What a CVaR fine-tune ranks a batch's samples by to find its tail: ``"loss"`` (the paper's:
#: the loss trained on, for a GMM mostly its sigma terms) or ``"followed_error"`` (the followed
#: mode's trajectory error, ADE [m]: the samples the driver gets most wrong).
RANK_BY = ("loss", "followed_error")


class CVaRObjective(WrappedObjective):
    """Train on the worst ``1 - alpha`` of every batch (seed 000, section 3.5).

    The per-sample losses and metrics are the base's; only the batch's reduction changes, to the
    mean over its tail (:func:`cvar_loss` when the tail is ranked by the loss itself). Validation
    losses stay per-sample means, comparable with the base's.

    Args:
        base: the objective whose tail is trained on (e.g. ``WithAffordance(GMMObjective(), w)``).
        alpha: in (0, 1) (the paper: 0.9).
        min_tail: see :func:`cvar_loss`.
        rank_by: one of :data:`RANK_BY`; ``"followed_error"`` needs a trajectory or GMM base.
    """

    def __init__(
        self, base: Objective, alpha: float = 0.9, min_tail: int = 10, rank_by: str = "loss"
    ) -> None:
        _check_alpha(alpha, 1, lo_closed=False, owner="CVaRObjective")
        check_range("CVaRObjective", "min_tail", min_tail, 1, integer=True)
        if rank_by not in RANK_BY:
            raise ValueError(f"CVaRObjective.rank_by={rank_by!r} is invalid: must be in {RANK_BY}")
        super().__init__(base)
        self.alpha, self.min_tail, self.rank_by = float(alpha), min_tail, rank_by
        self.min_batch = max(2, math.ceil(min_tail / (1.0 - self.alpha) - 1e-9))
        ranked = "" if rank_by == "loss" else "-by-followed-error"
        self.name = f"cvar{self.alpha:g}{ranked}({base.name})"

    def reduce(self, losses: torch.Tensor) -> torch.Tensor:
        """:func:`cvar_loss` of the batch (the tail ranked by the losses)."""
        return cvar_loss(losses, self.alpha, self.min_tail)

    def batch_loss(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """The mean loss over the batch's tail, ranked as :attr:`rank_by` says."""
        losses = self.per_sample(out, batch, model, epoch=epoch)
        if self.rank_by == "loss":
            return self.reduce(losses)
        cvar_loss(losses.detach(), self.alpha, self.min_tail)  # the same checks and warning
        return _tail_mean(losses, self.alpha, rank=self.tail_rank(out, batch, model))

    def tail_rank(self, out: Batch, batch: Batch, model: DrivingModel) -> torch.Tensor:
        """Each sample's rank score, (B,), larger is worse: the loss, or the followed
        trajectory's ADE [m]."""
        if self.rank_by == "loss":
            return self.per_sample(out, batch, model).detach()
        with torch.no_grad():
            return self.base.metrics(out, batch, model)["ADE [m]"]
