"""Noise in the collector's executed commands, never in its labels (chapter 04): random
*bursts* of steering and acceleration offsets (and deep braking), and DART's white noise on
every decision (chapter 12's control). :class:`Bursts` holds the bursts' state of B cars.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..config import check_pair, check_range


@dataclass(frozen=True)
class NoiseConfig:
    """Random bursts added to the executed commands (never to the labels).

    A car not in a burst starts one with probability ``rate_per_s * policy period`` per decision:
    a steering offset of random sign and size and an acceleration offset, for a random duration.
    A share ``brake_share`` of the bursts brake instead (``-brake_mps2``, 1-6 m/s off the speed),
    so the expert's recovery to cruise speed is labelled too; a share ``slow_share`` of those
    brake *deep*, down to a speed drawn from ``slow_to_mps`` (at most 12 s), whatever the expert
    commands: the speeds a braking driver or safety module leaves a learned driver at, which the
    expert's data otherwise hardly holds (chapter 11, section 5, trains with ``slow_share=0.5``).

    Beside the bursts, ``dart_steer_rad`` and ``dart_accel_mps2`` add white Gaussian noise of that
    standard deviation to every decision's commands (DART, Laskey et al. 2017: the noise fitted to
    a learner's errors, so the expert drives into the states the learner would; chapter 12's
    control).

    Attributes:
        rate_per_s: bursts per second of driving [1/s] (0 turns noise off).
        duration_s: (min, max) duration of a burst [s].
        steer_rad: (min, max) magnitude of the steering offset [rad].
        accel_mps2: the acceleration offset is uniform in +-this [m/s^2].
        brake_share: share of bursts that brake, in [0, 1].
        brake_mps2: (min, max) deceleration added by a braking burst [m/s^2].
        slow_share: share of the braking bursts that brake deep, in [0, 1] (0: none, the
            course's default data).
        slow_to_mps: (min, max) speed a deep braking burst brakes the car down to [m/s].
        dart_steer_rad, dart_accel_mps2: standard deviations of the white noise on every
            decision's steering [rad] and acceleration [m/s^2] (0: none).
    """

    #: added after the course's datasets were keyed: at their defaults those keys stay
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = (
        "slow_share",
        "slow_to_mps",
        "dart_steer_rad",
        "dart_accel_mps2",
    )
    #: the longest a deep braking burst lasts [s]
    SLOW_MAX_S: ClassVar[float] = 12.0

    rate_per_s: float = 0.12
    duration_s: tuple[float, float] = (0.5, 1.5)
    steer_rad: tuple[float, float] = (0.003, 0.015)
    accel_mps2: float = 1.0
    brake_share: float = 0.25
    brake_mps2: tuple[float, float] = (2.0, 4.0)
    slow_share: float = 0.0
    slow_to_mps: tuple[float, float] = (6.0, 18.0)
    dart_steer_rad: float = 0.0
    dart_accel_mps2: float = 0.0

    def __post_init__(self) -> None:
        o = "NoiseConfig"
        check_range(o, "rate_per_s", self.rate_per_s, 0.0, 10.0)
        check_pair(o, "duration_s", self.duration_s, lo=0.0)
        check_pair(o, "steer_rad", self.steer_rad, lo=0.0)
        check_range(o, "accel_mps2", self.accel_mps2, 0.0, 10.0)
        check_range(o, "brake_share", self.brake_share, 0.0, 1.0)
        check_pair(o, "brake_mps2", self.brake_mps2, lo=0.0)
        check_range(o, "slow_share", self.slow_share, 0.0, 1.0)
        check_pair(o, "slow_to_mps", self.slow_to_mps, lo=0.0)
        check_range(o, "dart_steer_rad", self.dart_steer_rad, 0.0, 0.5)
        check_range(o, "dart_accel_mps2", self.dart_accel_mps2, 0.0, 10.0)


class Bursts:
    """The noise bursts of B cars: each car's seconds of burst left, its (steer [rad], accel
    [m/s^2]) offsets, and a deep braking burst's target speed (0: none) [m/s].

    Args:
        cfg: the noise settings.
        period_s: the policy period, the time between two updates [s].
        n_cars: B.
    """

    def __init__(self, cfg: NoiseConfig, period_s: float, n_cars: int) -> None:
        self.cfg, self.period_s = cfg, period_s
        self.burst_left = np.zeros(n_cars)
        self.offset_cmd = np.zeros((n_cars, 2))
        self.slow_to = np.zeros(n_cars)

    def update(self, u: np.ndarray, speed: np.ndarray) -> None:
        """Continue the bursts, end finished ones (deep braking ones at their speed [m/s]), maybe
        start new ones, each car from its own uniforms ``u`` ``(B, 9)``: the restart draw (unused
        here), then burst start, duration, sign, steering, brake?, size, deep?, deep target speed."""
        period, nz = self.period_s, self.cfg

        def between(lo_hi: tuple[float, float], x: np.ndarray) -> np.ndarray:
            return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * x

        self.burst_left = np.maximum(self.burst_left - period, 0.0)
        self.burst_left[(self.slow_to > 0) & (speed <= self.slow_to)] = 0.0
        self.offset_cmd[self.burst_left <= 0] = 0.0
        self.slow_to[self.burst_left <= 0] = 0.0
        start = (self.burst_left <= 0) & (u[:, 1] < nz.rate_per_s * period)
        if not start.any():
            return
        us = u[start]
        sign = np.where(us[:, 3] < 0.5, -1.0, 1.0)
        brake = us[:, 5] < nz.brake_share
        self.burst_left[start] = between(nz.duration_s, us[:, 2])
        self.offset_cmd[start, 0] = sign * between(nz.steer_rad, us[:, 4])
        self.offset_cmd[start, 1] = np.where(
            brake,
            -between(nz.brake_mps2, us[:, 6]),
            between((-nz.accel_mps2, nz.accel_mps2), us[:, 6]),
        )
        deep = brake & (us[:, 7] < nz.slow_share)
        cars = np.flatnonzero(start)[deep]
        self.slow_to[cars] = between(nz.slow_to_mps, us[deep, 8])
        self.burst_left[cars] = nz.SLOW_MAX_S
