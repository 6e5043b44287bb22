"""The interface between the world and a driver: what a policy sees at each decision
(:class:`Observation`), what it answers (:class:`Actuation`), the :class:`Policy` protocol, and
:func:`observe`, which reads an observation off a fleet of cars. Everything that drives (the
expert, the scripted drivers, the networks, the safety module) is written against this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..artifacts import settings_key
from .geometry import wrap_angle
from .vehicle import H, V
from .world import Fleet, World

#: cars whose frames a network sees in one forward pass. The evaluator cuts its shards at whole
#: groups and a network agent runs one pass per group, so every frame is computed in the same
#: batch, at the same place, whatever the number of shards: torch's kernels give a frame other
#: bits in a batch of another size (or, for small layers, at another place in it), and a closed
#: loop amplifies the difference. 8 costs about 7 % of a batch of 32's speed per frame on one
#: CPU thread and lets 64 cars drive in 8 processes.
FORWARD_GROUP = 8


def seeded_cars(policy: object, n_worlds: int) -> np.ndarray:
    """The evaluation's indices of the ``n_worlds`` cars a policy is about to drive: those its
    ``seed_cars`` was last given when they are that many, else ``0 .. n_worlds - 1`` (a policy
    driven without the evaluator, e.g. in a hand-made scene)."""
    cars = getattr(policy, "cars", None)
    return np.arange(n_worlds) if cars is None or len(cars) != n_worlds else cars


def car_rng(seed: int, stream: int, car: int, *more: int) -> np.random.Generator:
    """The generator of one car's draws of one kind (``stream``): seeded by the car's index among
    the evaluation's (or the collection's) cars, never by its place in a shard, so the draws do
    not depend on how many processes drive the cars."""
    return np.random.default_rng([seed, stream, car, *more])


@dataclass
class Observation:
    """What a policy sees at one decision, for B cars.

    Attributes:
        state: ``(B, 5)`` ego states ``x, y, heading, speed, steer`` (rear axle; m, rad, m/s).
        s, d: lane-frame position of the rear axle [m], ``(B,)``.
        heading_error: heading minus the road's heading at ``s`` [rad], wrapped to (-pi, pi].
        curvature: the road's curvature at ``s`` [1/m].
        lane: index of the nearest lane (0 = rightmost), ``(B,)`` int.
        respawned: ``(B,)`` bool, True when car i was (re)placed since the last decision (start,
            new track, collision, stall): a stateful policy should forget car i's plan.
        time_s: simulated time since the start [s].
        worlds: the B worlds (privileged access for scripted drivers and the expert).
        images: camera frames ``(B, H, W, 3)`` RGB uint8 when the policy has a ``camera``, else None.
        collided: ``(B,)`` bool, True when car i collided since the last decision (it was then
            re-placed, so ``respawned`` is True too); None when the caller does not say.
        active: ``(B,)`` bool, False for a car that has driven its share of an evaluation's
            miles (it stands still while the others finish); None when the caller does not say.
    """

    state: np.ndarray
    s: np.ndarray
    d: np.ndarray
    heading_error: np.ndarray
    curvature: np.ndarray
    lane: np.ndarray
    respawned: np.ndarray
    time_s: float
    worlds: list[World]
    images: np.ndarray | None = None
    collided: np.ndarray | None = None
    active: np.ndarray | None = None

    @property
    def speed(self) -> np.ndarray:
        """Speed of each car [m/s], ``(B,)``."""
        return self.state[:, V]


@dataclass
class Actuation:
    r"""A batch of actuator commands: road-wheel angle [rad] and acceleration [m/s^2], each ``(B,)``.

    ``restart`` (optional, ``(B,)`` bool) asks the evaluator to take car i over and re-place it
    exactly as after a collision (:func:`restart_state`), without counting a collision: the data
    collector's way of showing the expert the states a learned driver restarts from.

    ``info`` (optional) is what the policy wants counted about this decision, by name: numbers
    and ``Counter``\ s are summed, lists concatenated, over the decisions and the shards of an
    evaluation, into its result's ``info`` (:func:`~e2e_lite.driving.rollout.add_info`; the
    safety module's interventions and false alarms come home this way, from threads or
    processes alike, so no policy needs to know how it is run).
    """

    steer_rad: np.ndarray
    accel_mps2: np.ndarray
    restart: np.ndarray | None = None
    info: dict[str, Any] | None = None


@runtime_checkable
class Policy(Protocol):
    """Anything that drives: ``reset`` once per evaluation, then ``act`` every policy period.

    A policy that sees through the front camera also has an attribute ``camera`` holding a
    :class:`~e2e_lite.simulation.camera.CameraConfig`; the evaluator then renders one frame per car every
    decision into ``obs.images`` (B, H, W, 3) RGB uint8. That buffer is reused: copy a frame to
    keep it past the next decision. A policy without the attribute (or with ``None``) gets no
    images and costs no rendering.

    A driver declares what decides its behaviour with a method ``identity()``: a list of
    JSON-able parts (its settings; for a network, a digest of its weights), read by
    :func:`fingerprint` to key its stored drives. A driver without settings needs none.
    """

    def reset(self, n_worlds: int) -> None:
        """Forget everything; ``n_worlds`` cars are about to be driven."""

    def act(self, obs: Observation) -> Actuation:
        """Commands for every car in the batch."""


def fingerprint(policy: object) -> str:
    """What identifies a driver's behaviour, for the drives stored under it
    (:mod:`e2e_lite.record.stored`): a key of its class and what its ``identity()`` declares."""
    declared = getattr(policy, "identity", None)
    return settings_key(type(policy).__name__, *(declared() if declared is not None else []))


def observe(
    fleet: Fleet,
    respawned: np.ndarray | bool = False,
    time_s: float = 0.0,
    images: np.ndarray | None = None,
    frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    collided: np.ndarray | None = None,
    active: np.ndarray | None = None,
) -> Observation:
    """The observation of a fleet's cars now (``frame``: a lane frame already computed;
    ``collided``: which cars collided since the last decision; ``active``: which still drive)."""
    s, d, road_h, kappa = fleet.lane_frame() if frame is None else frame
    n = len(fleet)
    return Observation(
        images=images,
        state=fleet.state.copy(),
        s=s,
        d=d,
        heading_error=wrap_angle(fleet.state[:, H] - road_h),
        curvature=kappa,
        lane=np.atleast_1d(fleet.worlds[0].track.lane_index(d)),
        respawned=np.broadcast_to(np.asarray(respawned, dtype=bool), (n,)).copy(),
        time_s=time_s,
        worlds=list(fleet.worlds),
        collided=None if collided is None else np.asarray(collided, dtype=bool).copy(),
        active=None if active is None else np.asarray(active, dtype=bool).copy(),
    )
