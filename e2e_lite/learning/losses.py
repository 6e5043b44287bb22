"""Training objectives: the target of each head, its per-sample loss, and readable metrics.

Losses are computed **per sample** (shape (B,)) in normalised units; the training loop averages
them (chapter 09's CVaR will instead average only the worst). Metrics are per sample too, in
physical units, so a held-out table reads in degrees and metres.

Each head's target, statistics, point loss and metrics are its class in
:mod:`~e2e_lite.learning.heads`; an :class:`Objective` trains a point-estimate head (``steer``,
``actuators``, ``trajectory``) with its mean squared error, :class:`GMMObjective` the ``gmm``
head with its mixture's negative log-likelihood.

Two wrappers change an objective without touching it (seed 000, sections 3.4 and 3.5):

* :class:`WithAffordance` adds ``w x`` the squared error of the affordance head (chapter 08);
* :class:`~e2e_lite.learning.cvar.CVaRObjective` reduces a batch by CVaR instead of the mean, so only the
  worst ``1 - alpha`` of each batch is trained on (chapter 09; :mod:`e2e_lite.learning.cvar`). It wraps
  the others (it is the outermost wrapper).

The held-out measures of what the networks predict (how the modes split, which side they take,
the affordance errors) are :mod:`e2e_lite.learning.heldout`.

The training loop calls :meth:`Objective.batch_loss` and nothing else: :meth:`Objective.reduce`
(the mean unless a wrapper says otherwise) of the per-sample losses.
"""

from __future__ import annotations

import torch

from ..config import check_range
from .heads import HEADS, POINT_HEADS, Batch, head_of
from .labels import AFFORDANCE_NAMES, N_POINTS, POINT_DIMS
from .models import DrivingModel

#: How trajectory targets are scaled before the loss (:func:`~e2e_lite.learning.training.model_stats`):
#: ``"coordinate"``: each of the 10 numbers by its own standard deviation (the paper's
#: practicality); ``"axis"``: every x by one pooled standard deviation and every y by another
#: (so an error keeps its size in metres within an axis: the 0.3 s lateral point, whose spread is
#: about 6 cm, is no longer blown up 15-fold beside the 1.5 s one); ``"none"``: metres.
TARGET_SCALES = ("coordinate", "axis", "none")


def _target_scale(owner: str, normalise_targets: bool, target_scale: str | None) -> str:
    scale = target_scale or ("coordinate" if normalise_targets else "none")
    if scale not in TARGET_SCALES:
        raise ValueError(
            f"{owner}.target_scale={scale!r} is invalid: must be one of {TARGET_SCALES}"
        )
    return scale


_SCALE_SUFFIX = {"coordinate": "", "axis": "-axis", "none": "-raw"}


def target(head: str, batch: Batch, wheelbase_m: float) -> torch.Tensor:
    """The physical target of ``head`` for a batch, (B, target_size) (:mod:`~e2e_lite.learning.heads`)."""
    return head_of(head).target(batch, wheelbase_m)


class Objective:
    """Mean squared error on the normalised target of a point-estimate head.

    Args:
        head: the model's head (``steer``, ``actuators`` or ``trajectory``).
        wheelbase_m: to turn steering angles into curvatures [m].
        normalise_targets: train on targets normalised per coordinate with the training set's
            mean and standard deviation (the paper's practicality; otherwise the far
            longitudinal points dominate); ``False`` trains on physical units (the model then
            carries mean 0 and standard deviation 1).
        target_scale: one of :data:`TARGET_SCALES`; overrides ``normalise_targets`` when given
            (``"axis"``: one scale per axis, trajectories only).
    """

    def __init__(
        self,
        head: str,
        wheelbase_m: float = 2.7,
        normalise_targets: bool = True,
        target_scale: str | None = None,
    ) -> None:
        if head not in POINT_HEADS:
            raise ValueError(f"Objective.head={head!r} is invalid: must be one of {POINT_HEADS}")
        self.head = head
        self.wheelbase_m = wheelbase_m
        self.target_scale = _target_scale("Objective", normalise_targets, target_scale)
        self.normalise_targets = self.target_scale != "none"
        self.name = f"mse-{head}" + _SCALE_SUFFIX[self.target_scale]

    #: the training loop drops an epoch's last batch when it is smaller than this
    min_batch: int = 2

    def frozen_prefixes(self, epoch: int) -> list[str]:
        """Parameter-name prefixes this objective wants frozen in ``epoch`` (none)."""
        return []

    def reduce(self, losses: torch.Tensor) -> torch.Tensor:
        """The batch loss the optimiser minimises, from per-sample losses (B,): their mean."""
        return losses.mean()

    def batch_loss(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """What the training loop minimises for a batch: :meth:`reduce` of :meth:`per_sample`.
        ``epoch``: the training epoch the batch belongs to (None: after training)."""
        return self.reduce(self.per_sample(out, batch, model, epoch=epoch))

    def per_sample(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """Loss of each sample, (B,): the mean over outputs of the squared normalised error."""
        tgt = model.normalise_target(target(self.head, batch, self.wheelbase_m))
        return HEADS[self.head].loss(out["main"], tgt)

    def metrics(self, out: Batch, batch: Batch, model: DrivingModel) -> Batch:
        """Per-sample absolute errors in physical units, by readable name."""
        pred = model.denormalise(out["main"])
        return HEADS[self.head].metrics(pred, batch, self.wheelbase_m)


# ------------------------------------------------------------------------------ GMM
#: What a GMM objective does with the mixture's sigmas (:class:`GMMObjective`'s ``sigma``)
GMM_SIGMAS = ("learned", "held")


class GMMObjective(Objective):
    """The mixture-density loss of seed 000 (section 3.3) on the normalised trajectory.

    The sigma floor belongs to the model (:attr:`~e2e_lite.learning.models.ModelConfig.sigma_floor`,
    ``sigma_floor_m``): the trained network and whoever reads its sigmas use the same one.

    Args:
        n_modes: K (the paper: 2).
        sigma_warmup_epochs: for the first epochs every sigma is held at 1 (the loss is then a
            mixture of squared errors) and the head's log-sigma layer is frozen; then opened
            (the paper froze sigma for 5 epochs).
        sigma: ``"learned"`` (the paper's NLL: the sigmas open after the warm-up) or ``"held"``:
            every sigma is 1 in every epoch and after training, the log-sigma layer never trains
            (a mixture of unit Gaussians: the weights and means are learned, the loss is each
            mode's squared error soft-minimised over the modes; the warm-up is then moot).
        wheelbase_m: unused by the GMM; kept for the common interface.
        normalise_targets: as :class:`Objective` (``False``: the floor and the warm-up's
            sigma = 1 are then in metres).
        target_scale: as :class:`Objective`.
    """

    def __init__(
        self,
        n_modes: int = 2,
        sigma_warmup_epochs: int = 1,
        wheelbase_m: float = 2.7,
        normalise_targets: bool = True,
        target_scale: str | None = None,
        sigma: str = "learned",
    ) -> None:
        check_range("GMMObjective", "n_modes", n_modes, 1, 16, integer=True)
        check_range("GMMObjective", "sigma_warmup_epochs", sigma_warmup_epochs, 0, integer=True)
        if sigma not in GMM_SIGMAS:
            raise ValueError(
                f"GMMObjective: sigma={sigma!r} is invalid: must be one of {GMM_SIGMAS}"
            )
        self.head = "gmm"
        self.n_modes = n_modes
        self.sigma = sigma
        self.sigma_warmup_epochs = 0 if sigma == "held" else sigma_warmup_epochs
        self.wheelbase_m = wheelbase_m
        self.target_scale = _target_scale("GMMObjective", normalise_targets, target_scale)
        self.normalise_targets = self.target_scale != "none"
        sigmas = "sigma1" if sigma == "held" else f"warmup{sigma_warmup_epochs}"
        self.name = f"gmm-nll-K{n_modes}-{sigmas}" + _SCALE_SUFFIX[self.target_scale]

    def sigma_fixed(self, epoch: int | None) -> bool:
        """Whether every sigma is held at 1 in ``epoch`` (held sigmas, or the warm-up; None: after
        training)."""
        return self.sigma == "held" or (epoch is not None and epoch < self.sigma_warmup_epochs)

    def frozen_prefixes(self, epoch: int) -> list[str]:
        """Parameters the training loop freezes this epoch: the log-sigma layer while sigma is
        held."""
        return ["head.log_sigma"] if self.sigma_fixed(epoch) else []

    def modes(
        self, out: dict[str, torch.Tensor], model: DrivingModel
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(weights (B, K), means (B, K, 10) normalised, log_sigma (B, K, 10))``."""
        mix = model.mixture(out["main"])
        return mix.weights, mix.means, mix.log_sigma

    def per_sample(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """The NLL of each sample's normalised trajectory (sigma held at 1 in a warm-up epoch).

        Raises:
            ValueError: the model's head has another number of modes than ``n_modes`` (its name
                would then describe a loss that is not the one trained).
        """
        mix = model.mixture(out["main"], self.sigma_fixed(epoch))
        if mix.weights.shape[-1] != self.n_modes:
            raise ValueError(
                f"GMMObjective: n_modes={self.n_modes}, but the model's head has "
                f"{mix.weights.shape[-1]} modes (ModelConfig.gmm_modes); make them agree"
            )
        return mix.nll(model.normalise_target(target("gmm", batch, self.wheelbase_m)))

    def metrics(self, out: Batch, batch: Batch, model: DrivingModel) -> Batch:
        """ADE/FDE of the most likely mode's mean [m], the best mode's ADE, the top weight."""
        weights, means, _ = self.modes(out, model)
        tgt = target("gmm", batch, self.wheelbase_m).reshape(-1, 1, N_POINTS, POINT_DIMS)
        pts = model.denormalise(means).reshape(*means.shape[:2], N_POINTS, POINT_DIMS)
        dist = (pts - tgt).norm(dim=-1)  # (B, K, 5)
        top = weights.argmax(dim=-1)
        rows = torch.arange(len(top), device=top.device)
        return {
            "ADE [m]": dist[rows, top].mean(dim=-1),
            "FDE [m]": dist[rows, top, -1],
            "min-ADE over modes [m]": dist.mean(dim=-1).min(dim=-1).values,
            "top weight": weights.max(dim=-1).values,
        }


# ------------------------------------------------------------------------------ wrappers
class WrappedObjective(Objective):
    """An objective built on another one: everything is delegated to ``base`` (its settings such
    as ``n_modes`` or ``sigma_warmup_epochs`` read through) unless a subclass overrides it."""

    def __init__(self, base: Objective) -> None:
        self.base = base
        self.head, self.wheelbase_m = base.head, base.wheelbase_m
        self.min_batch = base.min_batch

    def __getattr__(self, name: str):  # n_modes, sigma_fixed(), modes(), ... of the base
        if name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)

    def frozen_prefixes(self, epoch: int) -> list[str]:
        return self.base.frozen_prefixes(epoch)

    def reduce(self, losses: torch.Tensor) -> torch.Tensor:
        return self.base.reduce(losses)

    def per_sample(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        return self.base.per_sample(out, batch, model, epoch=epoch)

    def metrics(self, out: Batch, batch: Batch, model: DrivingModel) -> Batch:
        return self.base.metrics(out, batch, model)


class WithAffordance(WrappedObjective):
    """``base + weight x affordance loss`` (seed 000, section 3.4): the affordance head learns the
    dataset's 9 affordances (normalised per affordance) from the same fused features.

    The affordance loss of a sample is the mean over the 9 of the squared normalised error. With
    ``weight = 0`` this is exactly ``base`` (the head is then not trained).

    Args:
        base: the main objective (e.g. :class:`GMMObjective`); its settings (``n_modes``,
            ``sigma_warmup_epochs``, ...) are read through this wrapper.
        weight: ``w >= 0``.
    """

    def __init__(self, base: Objective, weight: float) -> None:
        check_range("WithAffordance", "weight", weight, 0.0)
        super().__init__(base)
        self.weight = float(weight)
        self.name = f"{base.name}+affordance{self.weight:g}"

    def affordance_loss(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """Per-sample mean squared normalised affordance error, (B,)."""
        if "affordance" not in out:
            raise ValueError(
                "WithAffordance needs a model with an affordance head (affordance=True)"
            )
        tgt = (batch["affordances"] - model.affordance_mean) / model.affordance_std
        return ((out["affordance"] - tgt) ** 2).mean(dim=1)

    def per_sample(
        self, out: Batch, batch: Batch, model: DrivingModel, *, epoch: int | None = None
    ) -> torch.Tensor:
        """``base`` loss + ``weight`` x affordance loss, (B,)."""
        main = self.base.per_sample(out, batch, model, epoch=epoch)
        if self.weight == 0.0:
            return main
        return main + self.weight * self.affordance_loss(out, batch, model)

    def metrics(self, out: Batch, batch: Batch, model: DrivingModel) -> Batch:
        """The base's metrics, its loss alone, and per-affordance absolute errors [m or rad]."""
        m = dict(self.base.metrics(out, batch, model))
        m["main loss"] = self.base.per_sample(out, batch, model)
        if "affordance" in out:
            pred = out["affordance"] * model.affordance_std + model.affordance_mean
            err = (pred - batch["affordances"]).abs()
            for i, name in enumerate(AFFORDANCE_NAMES):
                m[f"|err| {name}"] = err[:, i]
        return m
