"""Training objectives: the target of each head, its per-sample loss, and readable metrics.

Losses are computed **per sample** (shape (B,)) in normalised units; the training loop averages
them (chapter 09's CVaR will instead average only the worst). Metrics are per sample too, in
physical units, so a held-out table reads in degrees and metres.

Targets per head (see :class:`~e2e_lite.models.ModelConfig`):

* ``steer``: the expert's steering as a curvature ``kappa = tan(delta) / L`` [1/m] (seed 003 trained
  on the inverse turning radius, which does not depend on the car's geometry);
* ``actuators``: steering [rad] and acceleration [m/s^2] (seed 002 / the GM paper's baseline);
* ``trajectory``: the 5-point label flattened to 10 numbers [m].
"""

from __future__ import annotations

import math

import torch

from .models import DrivingModel


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
