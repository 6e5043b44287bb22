"""The oracle: the LQR tracker following the expert's own 5-point trajectories (chapter 04).

No camera and no network: each decision it asks the expert for its trajectory label and drives
it with the tracker, as a trajectory network would. It is the ceiling of every network that
predicts trajectories (chapter 07 adds the network's point noise to it to choose the reading).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from ..artifacts import added_later
from ..simulation.policy import Actuation, Observation, car_rng, seeded_cars
from .expert import Expert
from .tracker import check_reading, follow_trajectory


class Oracle:
    """The LQR tracker following the expert's own 5-point trajectories (no camera, no network).

    It shows that the trajectory representation plus the tracker is enough to drive: the ceiling
    of every trajectory-predicting network. Each decision it asks the expert for its label from
    the current state, lets the expert act there (its commands are discarded: it counts its
    manoeuvres) and follows
    the label with :func:`~e2e_lite.control.tracker.follow_trajectory`.

    With ``point_noise_m`` it follows the label plus Gaussian noise of that standard deviation
    per point coordinate (a scalar, or ``(5, 2)`` per coordinate [m]): a stand-in for a network
    whose errors have that size, to choose how a trajectory is read (chapter 07) without using
    any network's closed-loop collisions.

    Args:
        expert: the expert whose labels are followed.
        preview_s: where the trajectory is read [s] (see :func:`~e2e_lite.control.tracker.trajectory_reference`).
        speed: the speed reading, one of :data:`~e2e_lite.control.tracker.SPEED_READINGS`.
        point_noise_m: noise added to every label point [m] (None: none).
        seed: seeds the noise.
    """

    camera = None

    def __init__(
        self,
        expert: Expert | None = None,
        preview_s: float = 0.0,
        speed: str = "trajectory",
        point_noise_m: float | np.ndarray | None = None,
        seed: int = 0,
    ) -> None:
        check_reading("Oracle", preview_s, speed)
        self.expert = expert or Expert()
        self.preview_s, self.speed = preview_s, speed
        self.point_noise_m = None if point_noise_m is None else np.asarray(point_noise_m, float)
        self.seed = seed
        self.rngs: list[np.random.Generator] = []  # each car's noise (see :meth:`reset`)

    def seed_cars(self, cars: np.ndarray) -> None:
        """Seed each car's draws by its index among the evaluation's cars (see
        :class:`~e2e_lite.simulation.policy.Policy`)."""
        self.cars = np.asarray(cars, dtype=np.int64)
        self.expert.seed_cars(cars)

    def fork(self, k: int) -> list[Oracle]:
        """``k`` oracles for an evaluation's parallel shards (no state is shared)."""
        return [copy.deepcopy(self) for _ in range(k)]

    def identity(self) -> list[Any]:
        """What decides its behaviour (:func:`~e2e_lite.simulation.policy.fingerprint`): how it
        reads the labels, its expert's identity, its noise's seed, and its expert's class when
        that is not the :class:`~e2e_lite.control.expert.Expert`."""
        kind = added_later(expert=(type(self.expert).__name__, "Expert"))
        preview = [repr(self.preview_s), repr(self.speed), repr(self.point_noise_m)]
        return [*preview, *self.expert.identity(), self.seed, *kind]

    def reset(self, n_worlds: int) -> None:
        """Reset the expert (its counters) and each car's noise."""
        self.expert.reset(n_worlds)
        self.rngs = [car_rng(self.seed, 31, int(c)) for c in seeded_cars(self, n_worlds)]

    def act(self, obs: Observation) -> Actuation:
        """Follow the expert's trajectory from the current state."""
        points = self.expert.trajectory_label(obs)
        if self.point_noise_m is not None:
            noise = np.stack([r.normal(size=points.shape[1:]) for r in self.rngs])  # (B, 5, 2)
            points = points + noise * self.point_noise_m
        self.expert.act(obs)
        steer, accel = follow_trajectory(
            self.expert.tracker, points, obs.speed, self.preview_s, self.speed
        )
        return Actuation(steer_rad=steer, accel_mps2=accel)
