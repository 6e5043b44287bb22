"""Scripted drivers: simple proportional controllers on the lane frame (chapter 01).

They are deliberately plain: no LQR (chapter 03) and no planner (chapter 04's expert). They show
that a collision count says as much about what a driver sees and does as about the road.

Steering law (speed-scheduled proportional control plus curvature feed-forward)::

    steer = atan(L * kappa) - k_d * (d - d_target) - k_h * heading_error
    k_d = wn^2 L / v^2,   k_h = 2 zeta wn L / v

For the linearised lateral dynamics ``d'' = v^2 / L * steer`` this places the poles at natural
frequency ``wn`` [rad/s] and damping ``zeta`` at every speed. The steering is clipped so that the
lateral acceleration ``v^2 tan(steer) / L`` stays under ``max_lat_accel_mps2``.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import check_range
from ..simulation.policy import Actuation, Observation


class LaneKeeper:
    """Follows the centre of the lane it is in at (re)spawn, at a constant target speed.

    It ignores obstacles entirely: it only looks at its own lane-frame position.

    Args:
        target_speed_mps: cruise speed [m/s].
        wn_radps: natural frequency of the lateral loop [rad/s].
        zeta: damping ratio of the lateral loop.
        speed_gain_per_s: acceleration per unit speed error [1/s].
        max_lat_accel_mps2: steering is clipped to keep lateral acceleration under this [m/s^2].
        wheelbase_m: the car's wheelbase [m].
    """

    def __init__(
        self,
        target_speed_mps: float = 25.0,
        wn_radps: float = 1.0,
        zeta: float = 0.9,
        speed_gain_per_s: float = 0.5,
        max_lat_accel_mps2: float = 4.0,
        wheelbase_m: float = 2.7,
    ) -> None:
        check_range("LaneKeeper", "target_speed_mps", target_speed_mps, 0.0, 60.0, lo_open=True)
        check_range("LaneKeeper", "wn_radps", wn_radps, 0.0, 10.0, lo_open=True)
        check_range("LaneKeeper", "zeta", zeta, 0.0, 5.0, lo_open=True)
        check_range("LaneKeeper", "speed_gain_per_s", speed_gain_per_s, 0.0, 10.0, lo_open=True)
        check_range("LaneKeeper", "max_lat_accel_mps2", max_lat_accel_mps2, 0.0, 20.0, lo_open=True)
        self.target_speed_mps = target_speed_mps
        self.wn, self.zeta = wn_radps, zeta
        self.speed_gain = speed_gain_per_s
        self.max_lat_accel = max_lat_accel_mps2
        self.wheelbase = wheelbase_m
        self.target_lane = np.zeros(0, dtype=np.int64)

    def identity(self) -> list[float]:
        """What decides its behaviour (:func:`~e2e_lite.simulation.policy.fingerprint`): its
        settings."""
        return [
            self.target_speed_mps,
            self.wn,
            self.zeta,
            self.speed_gain,
            self.max_lat_accel,
            self.wheelbase,
        ]

    def reset(self, n_worlds: int) -> None:
        """Forget the target lanes of ``n_worlds`` cars."""
        self.target_lane = np.zeros(n_worlds, dtype=np.int64)

    def _update_targets(self, obs: Observation) -> None:
        """Keep the lane: a (re)spawned car adopts the lane it is in."""
        self.target_lane = np.where(obs.respawned, obs.lane, self.target_lane)

    def act(self, obs: Observation) -> Actuation:
        """Steer to the target lane centre, hold the target speed."""
        self._update_targets(obs)
        track = obs.worlds[0].track
        d_target = np.asarray(track.lane_center(self.target_lane))
        big_l = self.wheelbase
        v = np.maximum(obs.speed, 3.0)
        k_d = self.wn**2 * big_l / v**2
        k_h = 2.0 * self.zeta * self.wn * big_l / v
        steer = (
            np.arctan(big_l * obs.curvature) - k_d * (obs.d - d_target) - k_h * obs.heading_error
        )
        steer_max = np.arctan(self.max_lat_accel * big_l / v**2)
        steer = np.clip(steer, -steer_max, steer_max)
        accel = self.speed_gain * (self.target_speed_mps - obs.speed)
        return Actuation(steer_rad=steer, accel_mps2=accel)


class LaneChanger(LaneKeeper):
    """A :class:`LaneKeeper` that moves to a free neighbouring lane when a parked car is close.

    Each decision it asks the world (a pymunk range query, privileged information) for the gap to
    the nearest parked car ahead in its target lane. Under ``trigger_m`` it switches the target to
    the neighbour with the largest gap (left first on a tie), if that gap is at least ``trigger_m``.
    It never looks behind or beside itself, and steers with the same proportional law.

    Args:
        trigger_m: gap that triggers a lane change [m].
        **kwargs: passed to :class:`LaneKeeper`.
    """

    def __init__(self, trigger_m: float = 70.0, **kwargs: float) -> None:
        super().__init__(**kwargs)
        check_range("LaneChanger", "trigger_m", trigger_m, 0.0, 500.0, lo_open=True)
        self.trigger_m = trigger_m

    def identity(self) -> list[float]:
        """The lane keeper's settings and the gap that triggers a lane change."""
        return [*super().identity(), self.trigger_m]

    def _update_targets(self, obs: Observation) -> None:
        super()._update_targets(obs)
        for i, world in enumerate(obs.worlds):
            lane = int(self.target_lane[i])
            front = float(obs.s[i]) + world.vehicle.rear_to_front_m
            if world.gap_ahead(front, lane, self.trigger_m) < self.trigger_m:
                options = [
                    (world.gap_ahead(front, j, 2 * self.trigger_m), j)
                    for j in (lane + 1, lane - 1)
                    if 0 <= j < world.track.n_lanes
                ]
                gap, best = max(options, key=lambda g: (g[0], g[1]))
                if gap >= self.trigger_m or math.isinf(gap):
                    self.target_lane[i] = best
