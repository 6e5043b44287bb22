"""Agents: a trained network plus whatever turns its output into actuation, as a Policy.

The evaluator renders one camera frame per car and calls :meth:`NetworkAgent.act` once per
decision with the whole batch; the agent runs the network once on the B frames (under
``torch.inference_mode``) and returns B commands:

* :class:`SteeringAgent` (PilotNet, seed 003): the network gives a curvature, steering is
  ``atan(L kappa)``; the speed is held by a cruise control that follows the expert's speed
  profile of the road (it knows the curves ahead, as the expert does, but not the parked cars);
* :class:`ActuatorAgent` (seed 002 / the GM paper's Baseline E2E): the network gives steering and
  acceleration, applied directly; no controller.

Trajectory agents (the network proposes, the LQR tracker follows) are added by chapter 06.
"""

from __future__ import annotations

import numpy as np
import torch

from .camera import CameraConfig
from .evaluation import Actuation, Observation
from .expert import ExpertConfig, speed_profile
from .geometry import Track
from .models import DrivingModel, images_to_tensor
from .tracker import LQRTracker
from .vehicle import VehicleParams


class NetworkAgent:
    """Base: holds the model, the camera it was trained with and the device.

    Args:
        model: a trained model (eval mode).
        camera: the camera the training frames came from.
        vehicle: the car (wheelbase, steering limit).
    """

    def __init__(
        self,
        model: DrivingModel,
        camera: CameraConfig | None = None,
        vehicle: VehicleParams | None = None,
    ) -> None:
        self.model = model.eval()
        self.camera = camera or CameraConfig()
        self.vehicle = vehicle or VehicleParams()
        self.device = next(model.parameters()).device

    def reset(self, n_worlds: int) -> None:
        """Networks are stateless between decisions."""

    def predict(self, obs: Observation) -> dict[str, torch.Tensor]:
        """The network's raw (normalised) outputs for the batch of frames in ``obs``."""
        if obs.images is None:
            raise ValueError("this agent needs camera frames: give it a `camera` attribute")
        image = images_to_tensor(obs.images, self.device)
        speed = torch.as_tensor(obs.speed, dtype=torch.float32, device=self.device)[:, None]
        with torch.inference_mode():
            return self.model(image, speed)

    def act(self, obs: Observation) -> Actuation:  # pragma: no cover - abstract
        raise NotImplementedError


class CruiseControl:
    """Speed for agents that only steer: the expert's curve-speed profile of the road, tracked
    by the LQR tracker's speed loop. It knows the road's curvature ahead, not the parked cars."""

    def __init__(self, cfg: ExpertConfig | None = None, tracker: LQRTracker | None = None) -> None:
        self.cfg = cfg or ExpertConfig()
        self.tracker = tracker or LQRTracker()
        self._profiles: dict[tuple, np.ndarray] = {}

    def _profile(self, track: Track) -> np.ndarray:
        if track.track_id not in self._profiles:
            self._profiles[track.track_id] = speed_profile(track, self.cfg)
        return self._profiles[track.track_id]

    def accel(self, obs: Observation) -> np.ndarray:
        """Acceleration [m/s^2] towards each car's speed limit at its position."""
        v_ref = np.array(
            [
                self._profile(w.track)[min(int(s / 5.0), len(self._profile(w.track)) - 1)]
                for w, s in zip(obs.worlds, obs.s)
            ]
        )
        return self.tracker.accel(obs.speed, v_ref)


class SteeringAgent(NetworkAgent):
    """PilotNet: the network steers (curvature 1/r -> ``atan(L kappa)``), cruise control holds speed."""

    def __init__(self, model: DrivingModel, cruise: CruiseControl | None = None, **kwargs) -> None:
        super().__init__(model, **kwargs)
        self.cruise = cruise or CruiseControl()

    def act(self, obs: Observation) -> Actuation:
        """Steer from the frames; accelerate towards the road's speed limit."""
        kappa = self.model.denormalise(self.predict(obs)["main"])[:, 0].float().cpu().numpy()
        steer = np.arctan(self.vehicle.wheelbase_m * kappa)
        lim = self.vehicle.max_steer_rad
        return Actuation(steer_rad=np.clip(steer, -lim, lim), accel_mps2=self.cruise.accel(obs))


class ActuatorAgent(NetworkAgent):
    """The all-actuators baseline: steering and acceleration straight from the network."""

    def act(self, obs: Observation) -> Actuation:
        """Apply the predicted steering and acceleration (clipped to the car's limits)."""
        out = self.model.denormalise(self.predict(obs)["main"]).float().cpu().numpy()
        v = self.vehicle
        return Actuation(
            steer_rad=np.clip(out[:, 0], -v.max_steer_rad, v.max_steer_rad),
            accel_mps2=np.clip(out[:, 1], -v.max_brake_mps2, v.max_accel_mps2),
        )
