"""Agents: a trained network plus whatever turns its output into actuation, as a Policy.

The evaluator renders one camera frame per car and calls :meth:`NetworkAgent.act` once per
decision with the whole batch; the agent runs the network once on the B frames (under
``torch.inference_mode``) and returns B commands:

* :class:`SteeringAgent` (PilotNet, seed 003): the network gives a curvature, steering is
  ``atan(L kappa)``; the speed is held by a cruise control that follows the expert's speed
  profile of the road (it knows the curves ahead, as the expert does, but not the parked cars);
* :class:`ActuatorAgent` (seed 002 / the GM paper's Baseline E2E): the network gives steering and
  acceleration, applied directly; no controller.

* :class:`TrajectoryAgent` (seed 000): the network proposes a 5-point trajectory (for a GMM head,
  the mean of the most likely mode), the LQR tracker follows it (steering and speed). Where the
  speed comes from is a switch (:data:`SPEED_SOURCES`) so chapter 07 can separate lateral from
  longitudinal failures.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..artifacts import added_later
from ..control.rules import ExpertConfig, SpeedLimits
from ..control.tracker import (
    SPEED_READINGS,
    LQRTracker,
    check_reading,
    default_tracker,
    follow_trajectory,
)
from ..learning.heads import GMM, HEADS, Trajectory
from ..learning.labels import N_POINTS, POINT_DIMS
from ..learning.models import DrivingModel, images_to_tensor, weights_digest
from ..simulation.camera import CameraConfig
from ..simulation.policy import FORWARD_GROUP, Actuation, Observation, fingerprint
from ..simulation.vehicle import VehicleParams
from ..simulation.world import SimConfig


def _frames(obs: Observation) -> np.ndarray:
    if obs.images is None:
        raise ValueError("this agent needs camera frames: give it a `camera` attribute")
    return obs.images


class NetworkAgent:
    """Base: holds the model, the camera it was trained with and the device.

    Args:
        model: a trained model (eval mode).
        camera: the camera the training frames came from.
        vehicle: the car (wheelbase, steering limit).
        sim: the world's time steps (its policy period discretises the default trackers; the
            evaluator checks it against the world's).
    """

    def __init__(
        self,
        model: DrivingModel,
        camera: CameraConfig | None = None,
        vehicle: VehicleParams | None = None,
        sim: SimConfig | None = None,
    ) -> None:
        self.model = model.eval()
        self.camera = camera or CameraConfig()
        self.vehicle = vehicle or VehicleParams()
        self.sim = sim or SimConfig()
        self.device = next(model.parameters()).device

    def identity(self) -> list[Any]:
        """What decides its behaviour (:func:`~e2e_lite.simulation.policy.fingerprint`): a digest
        of the network's weights and buffers, its settings, how the agent reads its output
        (:meth:`reading`), its camera and its device."""
        model = [weights_digest(self.model), repr(self.model.cfg)]
        return [*model, *self.reading(), repr(self.camera), str(self.device)]

    def reading(self) -> list[Any]:
        """How the agent reads the network's output, as its identity holds it: the speed and the
        preview (a steering or actuators agent reads neither: None, 0.0)."""
        return [None, 0.0]

    def reset(self, n_worlds: int) -> None:
        """Networks are stateless between decisions."""

    def fork(self, k: int) -> list[NetworkAgent]:
        """``k`` agents for :func:`~e2e_lite.driving.evaluation.evaluate`'s parallel shards: they share
        the model (read-only at inference) and controllers (stateless), each with its own
        :attr:`last`."""
        copies = [copy.copy(self) for _ in range(k)]
        for agent in copies:
            if hasattr(agent, "last"):
                agent.last = {}
        return copies

    def predict(self, obs: Observation) -> dict[str, torch.Tensor]:
        """The network's raw (normalised) outputs for the batch of frames in ``obs``."""
        return self.predict_frames(_frames(obs), obs.speed)

    def predict_frames(
        self, images: np.ndarray, speed_mps: np.ndarray, **kw: Any
    ) -> dict[str, torch.Tensor]:
        """The network's raw outputs for frames ``(B, H, W, 3)`` uint8 at speeds ``(B,)`` [m/s]
        (e.g. recorded frames of a dataset); ``kw`` goes to the model's ``forward``."""
        image = images_to_tensor(images, self.device)
        speed = torch.as_tensor(speed_mps, dtype=torch.float32, device=self.device)[:, None]
        with torch.inference_mode():
            # one pass per group of FORWARD_GROUP frames: a frame's outputs are then the same bits
            # in any shard of an evaluation (see simulation.policy.FORWARD_GROUP)
            parts = [
                self.model(image[i : i + FORWARD_GROUP], speed[i : i + FORWARD_GROUP], **kw)
                for i in range(0, len(image), FORWARD_GROUP)
            ]
            if len(parts) == 1:
                return parts[0]
            return {name: torch.cat([p[name] for p in parts]) for name in parts[0]}

    def act(self, obs: Observation) -> Actuation:  # pragma: no cover - abstract
        raise NotImplementedError


class CruiseControl:
    """Speed for agents that only steer: the expert's curve-speed profile of the road, tracked
    by the LQR tracker's speed loop. It knows the road's curvature ahead, not the parked cars."""

    def __init__(
        self,
        cfg: ExpertConfig | None = None,
        tracker: LQRTracker | None = None,
        vehicle: VehicleParams | None = None,
        sim: SimConfig | None = None,
    ) -> None:
        self.limits = SpeedLimits(cfg or ExpertConfig())
        self.tracker = tracker or default_tracker(vehicle, sim)

    def accel(self, obs: Observation) -> np.ndarray:
        """Acceleration [m/s^2] towards each car's speed limit at its position."""
        v_ref = np.array([self.limits.at(w.track, s) for w, s in zip(obs.worlds, obs.s)])
        return self.tracker.accel(obs.speed, v_ref)


class SteeringAgent(NetworkAgent):
    """PilotNet: the network steers (curvature 1/r -> ``atan(L kappa)``), cruise control holds speed."""

    def __init__(self, model: DrivingModel, cruise: CruiseControl | None = None, **kwargs) -> None:
        super().__init__(model, **kwargs)
        self.cruise = cruise or CruiseControl(vehicle=self.vehicle, sim=self.sim)

    def act(self, obs: Observation) -> Actuation:
        """Steer from the frames; accelerate towards the road's speed limit."""
        kappa = self.model.denormalise(self.predict(obs)["main"])[:, 0].double().cpu().numpy()
        steer = np.arctan(self.vehicle.wheelbase_m * kappa)
        lim = self.vehicle.max_steer_rad
        return Actuation(steer_rad=np.clip(steer, -lim, lim), accel_mps2=self.cruise.accel(obs))


class ActuatorAgent(NetworkAgent):
    """The all-actuators baseline: steering and acceleration straight from the network."""

    def act(self, obs: Observation) -> Actuation:
        """Apply the predicted steering and acceleration (clipped to the car's limits)."""
        out = self.model.denormalise(self.predict(obs)["main"]).double().cpu().numpy()
        v = self.vehicle
        return Actuation(
            steer_rad=np.clip(out[:, 0], -v.max_steer_rad, v.max_steer_rad),
            accel_mps2=np.clip(out[:, 1], -v.max_brake_mps2, v.max_accel_mps2),
        )


#: Where a :class:`TrajectoryAgent` takes its speed from: ``"trajectory"`` (the paper: reference
#: speed and acceleration read from the trajectory, ``a = a_ref + k (v_ref - v)``),
#: ``"trajectory_no_ff"`` (reference speed only, no acceleration feed-forward) or ``"cruise"``
#: (the trajectory steers, :class:`CruiseControl` holds the speed, as for PilotNet).
SPEED_SOURCES = (*SPEED_READINGS, "cruise")
#: The reading the course's trajectory drivers use (chapter 07, section 6c, measures it with the
#: oracle plus network-sized noise on the training tracks and the held-out decoding errors).
DEFAULT_PREVIEW_S = 0.0
DECODES = ("top", "mean")  # which trajectory of a GMM a TrajectoryAgent follows
DEFAULT_SPEED = "trajectory"


class TrajectoryAgent(NetworkAgent):
    """The network proposes, the LQR tracker follows (seed 000's Fig. 1).

    For a ``trajectory`` head the prediction is de-normalised and followed. For a ``gmm`` head
    the mean of the mode with the largest weight is followed; every mode, its weight and its
    sigma are kept in :attr:`last` (for figures and the safety module).

    Args:
        model: a trajectory or GMM model.
        tracker: the LQR tracker (None: :func:`default_tracker` for this car and policy period).
        speed: where the speed command comes from, one of :data:`SPEED_SOURCES`.
        preview_s: where along the predicted trajectory the tracker reads its references [s]
            (:func:`~e2e_lite.control.tracker.trajectory_reference`; 0 = the car's position now).
        decode: for a GMM, which trajectory is followed, one of :data:`DECODES`: ``"top"`` (the
            paper's: the mean of the heaviest mode) or ``"mean"`` (the mixture's mean, the
            weighted average of the modes: what an L2 head estimates; a diagnostic control).

    Attributes:
        last: the latest decision's ``{"points": (B, 5, 2) followed [m], "modes": (B, K, 5, 2) [m],
            "weights": (B, K), "sigmas": (B, K, 5, 2) [m], "affordances": (B, 9)}`` (modes,
            weights and sigmas for GMMs only; the predicted affordances, in the dataset's units,
            for models with an affordance head only).
    """

    def __init__(
        self,
        model: DrivingModel,
        tracker: LQRTracker | None = None,
        speed: str = DEFAULT_SPEED,
        preview_s: float = DEFAULT_PREVIEW_S,
        decode: str = "top",
        **kwargs,
    ) -> None:
        super().__init__(model, **kwargs)
        check_reading("TrajectoryAgent", preview_s, speed, SPEED_SOURCES)
        if decode not in DECODES:
            raise ValueError(
                f"TrajectoryAgent.decode={decode!r} is invalid: must be one of {DECODES}"
            )
        self.speed, self.preview_s, self.decode = speed, preview_s, decode
        if not isinstance(HEADS[model.cfg.head], Trajectory):  # (a GMM is one too)
            raise ValueError(
                f"TrajectoryAgent needs a trajectory or gmm head, not {model.cfg.head!r}"
            )
        self.tracker = tracker or default_tracker(self.vehicle, self.sim)
        self.cruise = CruiseControl(tracker=self.tracker) if speed == "cruise" else None
        self.last: dict[str, np.ndarray] = {}

    def reading(self) -> list[Any]:
        """How it reads the network's output: its speed and preview, and how it decodes a GMM
        (kept out of the key at its default, :func:`~e2e_lite.artifacts.added_later`)."""
        return [self.speed, self.preview_s, *added_later(decode=(self.decode, "top"))]

    def trajectories(self, obs: Observation) -> np.ndarray:
        """The trajectories to follow (B, 5, 2) [m]; fills :attr:`last`."""
        return self.trajectories_from(_frames(obs), obs.speed)

    def trajectories_from(self, images: np.ndarray, speed_mps: np.ndarray) -> np.ndarray:
        """:meth:`trajectories` for frames ``(B, H, W, 3)`` uint8 at speeds ``(B,)`` [m/s]."""
        outputs = self.predict_frames(images, speed_mps)
        out, model = outputs["main"], self.model
        extra = {}
        if "affordance" in outputs:
            aff = outputs["affordance"] * model.affordance_std + model.affordance_mean
            extra["affordances"] = aff.double().cpu().numpy()
        if not isinstance(HEADS[model.cfg.head], GMM):  # a point estimate of the trajectory
            pts = model.denormalise(out).reshape(-1, N_POINTS, POINT_DIMS).double().cpu().numpy()
            self.last = {"points": pts, **extra}
            return pts
        mix = model.mixture(out)  # sigmas floored as the model was trained
        weights, modes = mix.weights, model.denormalise(mix.means)
        sig = torch.exp(mix.log_sigma) * model.target_std
        pts = mix.followed(self.decode, modes)
        self.last = {
            "points": pts.reshape(-1, N_POINTS, POINT_DIMS).double().cpu().numpy(),
            "modes": modes.reshape(*modes.shape[:2], N_POINTS, POINT_DIMS).double().cpu().numpy(),
            "weights": weights.double().cpu().numpy(),
            "sigmas": sig.reshape(*sig.shape[:2], N_POINTS, POINT_DIMS).double().cpu().numpy(),
            **extra,
        }
        return self.last["points"]

    def act(self, obs: Observation) -> Actuation:
        """Follow the predicted trajectory with the LQR tracker (speed as :attr:`speed` says)."""
        return self.follow(self.trajectories(obs), obs)

    def follow(self, points: np.ndarray, obs: Observation) -> Actuation:
        """Commands that follow trajectories ``(B, 5, 2)`` [m] (car frame) with the tracker,
        the speed as :attr:`speed` says (e.g. a trajectory the safety module chose instead)."""
        reading = "trajectory" if self.cruise is not None else self.speed
        steer, accel = follow_trajectory(self.tracker, points, obs.speed, self.preview_s, reading)
        if self.cruise is not None:
            accel = self.cruise.accel(obs)
        return Actuation(steer_rad=steer, accel_mps2=accel)


class Recorder:
    """Wraps an agent for the evaluator; after every decision calls ``record(obs, agent)`` and
    keeps what it returns in :attr:`rows` (for diagnosis: what the agent saw and proposed).

    Args:
        agent: any policy (its ``camera``, if any, is passed through).
        record: ``(observation, agent) -> row``; the agent's :attr:`last` is already filled.
    """

    def __init__(self, agent: Any, record: Callable[[Observation, Any], Any]) -> None:
        self.agent, self.record, self.rows = agent, record, []
        self.camera = getattr(agent, "camera", None)

    def identity(self) -> list[str]:
        """It drives as its agent does (:func:`~e2e_lite.simulation.policy.fingerprint`)."""
        return [fingerprint(self.agent)]

    def reset(self, n_worlds: int) -> None:
        self.agent.reset(n_worlds)

    def act(self, obs: Observation) -> Actuation:
        act = self.agent.act(obs)
        self.rows.append(self.record(obs, self.agent))
        return act
