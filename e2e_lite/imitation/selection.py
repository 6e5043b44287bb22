"""Keeping the epoch that drives best: each epoch of a training drives a few miles on
validation roads, and the epoch with the fewest collisions is kept.

Why: held-out errors do not predict closed-loop driving (seed 000's own point). Two of the five
GMM seeds of the first Table 1 of record kept, by their decisive ADE, an epoch that collided 2-4
times as often on validation and on test roads as the epoch after it (lab note "The GMM's worst
seeds of record, epoch by epoch"). Our closed loop drives about 5 simulated miles a second on two
cores, so driving every epoch 20 mi costs seconds per epoch.

The roads are the validation split's (:class:`~e2e_lite.driving.rollout.EvalConfig`
``split="val"``), never the test roads that every number of record drives. Every epoch of a
training drives the same roads with the same start lanes, so the epochs are compared on equal
terms. :func:`road_scorer` builds the ``on_epoch`` hook that
:func:`~e2e_lite.learning.training.fit` calls for ``TrainConfig(select_by="val_roads")``; the
recipes (:mod:`e2e_lite.imitation.recipes`) pass it. This module drives the simulator, so the
learning modules that must load without it import it where they use it.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

from ..driving.evaluation import evaluate
from ..driving.rollout import EvalConfig
from ..learning.models import DrivingModel
from ..learning.training import VAL_ROADS
from ..simulation.policy import Policy
from ..simulation.world import WorldConfig
from .agents import ActuatorAgent, SteeringAgent, TrajectoryAgent

#: Cars driven in lockstep by a selection drive (the ablation's batch: the network runs near its
#: per-frame floor). Part of the checkpoint's settings through its version (``"checkpoint"``).
SELECT_WORLDS = 64


def driver_for(model: DrivingModel) -> Policy:
    """The closed-loop driver of a network, as chapter 10 drives it: PilotNet's steering with
    the cruise control, the actuator baseline's own actuations, a trajectory (L2 or GMM) head's
    top mode followed by the LQR tracker."""
    head = model.cfg.head
    if head == "steer":
        return SteeringAgent(model)
    if head == "actuators":
        return ActuatorAgent(model)
    return TrajectoryAgent(model)


@dataclass(frozen=True)
class RoadScorer:
    """``fit``'s ``on_epoch`` hook for ``select_by="val_roads"``: drives a copy of the epoch's
    network ``miles`` on validation roads and returns :data:`~e2e_lite.learning.training.VAL_ROADS`
    (collisions per 100 mi) with the drive's mph and stalls.

    Attributes:
        world: roads, traffic and car of the drive (the profile's).
        miles: miles per epoch [mi].
        workers: shards of the drive (None: every core; the result does not depend on it).
    """

    world: WorldConfig
    miles: float
    workers: int | None = None

    def __call__(self, epoch: int, model: DrivingModel) -> dict[str, float]:
        net = copy.deepcopy(model).cpu().eval()
        ev = EvalConfig(miles=self.miles, n_worlds=SELECT_WORLDS, split="val")
        result = evaluate(driver_for(net), self.world, ev, progress=False, workers=self.workers)
        return {
            VAL_ROADS: float(result.collisions_per_100mi),
            "val roads mph": float(result.mean_speed_mph),
            "val roads stalls": float(result.stalls),
        }


def road_scorer(
    world: WorldConfig,
    miles: float,
    also: Callable[[int, DrivingModel], dict[str, float] | None] | None = None,
    workers: int | None = None,
) -> Callable[[int, DrivingModel], dict[str, float]]:
    """The ``on_epoch`` hook that drives each epoch ``miles`` on validation roads; ``also``: a
    caller's own hook (e.g. keeping every epoch's weights), called first, its record joined."""
    scorer = RoadScorer(world, miles, workers)
    if also is None:
        return scorer

    def both(epoch: int, model: DrivingModel) -> dict[str, float]:
        return {**(also(epoch, model) or {}), **scorer(epoch, model)}

    return both
