"""The rules the expert (:mod:`e2e_lite.control.expert`) drives by, and what it may see of the
world: its settings, the speed limit the road's curvature sets (rule 1 of the expert's docstring),
and the two questions it asks of the parked cars (the car ahead in a lane, a lane free over a
stretch). The learned drivers' speed caps and the safety module's audits read the same limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import check_pair, check_range
from ..simulation.geometry import Track
from ..simulation.world import World

#: the expert's home-lane rules (:attr:`ExpertConfig.home`)
HOMES = ("own", "middle", "right")


@dataclass(frozen=True)
class ExpertConfig:
    """Settings of the expert.

    Attributes:
        top_speed_mps: cruise speed on straights [m/s].
        max_lat_accel_mps2: the friction bound of the speed limit in curves [m/s^2].
        curve_brake_mps2: deceleration planned when slowing down for a curve ahead [m/s^2].
        trigger_m: (min, max) gap from the front bumper to a parked car's rear that triggers an
            overtake, drawn per manoeuvre [m]. At 25 m/s a comfortable lane change needs about
            60 m, so the range starts at 45 m (the change is shortened to fit, see
            ``change_lat_accel_mps2``).
        finish_m: (min, max) distance of the rear axle past the overtaken car's front before the
            return, drawn per manoeuvre [m].
        change_time_s: (min, max) duration of a lane change, drawn per manoeuvre [s].
        min_change_m: shortest lane change [m].
        change_lat_accel_mps2: a lane change that would need more peak lateral acceleration than
            this is not started (the expert slows down instead) [m/s^2].
        clear_behind_m: the target lane must be free from this far behind the rear axle (parked
            cars never move, so this only has to cover the car's own length) [m].
        clear_past_m: ... to this far past the overtaken car's front [m].
        follow_margin_m: when it cannot overtake it stops this far behind the car ahead [m].
        approach_brake_mps2: outside ``keep`` the speed is capped so that the car could stop
            ``follow_margin_m`` behind the next parked car in the lane it is heading for, braking at
            this rate [m/s^2].
        lookahead_m: range of the gap search [m].
        home: the lane it keeps when no parked car holds it out, one of :data:`HOMES`:
            ``"own"``, the lane it is in (it never returns: every lane change is an overtake);
            ``"middle"``, back to the middle lane once past; ``"right"``, back to the rightmost
            lane once past and free, one lane at a time, as a driver keeps right (lab note
            "One expert for the whole course" measures the three).
    """

    top_speed_mps: float = 25.0
    max_lat_accel_mps2: float = 2.5
    curve_brake_mps2: float = 1.5
    trigger_m: tuple[float, float] = (45.0, 75.0)
    finish_m: tuple[float, float] = (5.0, 40.0)
    change_time_s: tuple[float, float] = (2.5, 3.5)
    min_change_m: float = 15.0
    change_lat_accel_mps2: float = 4.0
    clear_behind_m: float = 5.0
    clear_past_m: float = 40.0
    follow_margin_m: float = 15.0
    approach_brake_mps2: float = 3.0
    lookahead_m: float = 150.0
    home: str = "own"

    def __post_init__(self) -> None:
        o = "ExpertConfig"
        if self.home not in HOMES:
            raise ValueError(f"{o}.home={self.home!r} is invalid: must be one of {HOMES}")
        check_range(o, "top_speed_mps", self.top_speed_mps, 0.0, 60.0, lo_open=True)
        check_range(o, "max_lat_accel_mps2", self.max_lat_accel_mps2, 0.0, 10.0, lo_open=True)
        check_range(o, "curve_brake_mps2", self.curve_brake_mps2, 0.0, 10.0, lo_open=True)
        check_pair(o, "trigger_m", self.trigger_m, lo=self.follow_margin_m)
        check_pair(o, "finish_m", self.finish_m, lo=0.0)
        check_pair(o, "change_time_s", self.change_time_s, lo=0.5)
        check_range(o, "min_change_m", self.min_change_m, 1.0, 500.0)
        check_range(o, "change_lat_accel_mps2", self.change_lat_accel_mps2, 0.0, 10.0, lo_open=True)
        check_range(o, "clear_behind_m", self.clear_behind_m, 0.0, 500.0)
        check_range(o, "clear_past_m", self.clear_past_m, 0.0, 500.0)
        check_range(o, "follow_margin_m", self.follow_margin_m, 1.0, 100.0)
        check_range(o, "approach_brake_mps2", self.approach_brake_mps2, 0.0, 10.0, lo_open=True)
        check_range(o, "lookahead_m", self.lookahead_m, self.trigger_m[1], 1000.0)


def speed_profile(track: Track, cfg: ExpertConfig, step_m: float = 5.0) -> np.ndarray:
    """The expert's speed limit every ``step_m`` metres of ``track`` [m/s].

    ``v(s) = min(top, sqrt(a_lat / |kappa(s)|))``, then a backward pass
    ``v_i = min(v_i, sqrt(v_{i+1}^2 + 2 b step))`` so that it slows down *before* a curve at no more
    than ``curve_brake_mps2``. The curvature is sampled at both ends of each step.
    """
    s = np.arange(0.0, track.length + step_m, step_m)
    kappa = np.maximum(np.abs(track.curvature(s)), np.abs(track.curvature(s + step_m)))
    v = np.minimum(cfg.top_speed_mps, np.sqrt(cfg.max_lat_accel_mps2 / np.maximum(kappa, 1e-9)))
    reach = 2.0 * cfg.curve_brake_mps2 * step_m
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + reach))
    return v


class SpeedLimits:
    """The expert's speed limit at any ``(track, s)``: :func:`speed_profile` computed once per
    track object (keyed by identity: two roads may share a ``track_id`` but not a profile)."""

    STEP_M = 5.0

    def __init__(self, cfg: ExpertConfig) -> None:
        self.cfg = cfg
        self._profiles: dict[int, tuple[Track, np.ndarray]] = {}

    def at(self, track: Track, s: float) -> float:
        """Speed limit [m/s] at arc length ``s`` [m]."""
        entry = self._profiles.get(id(track))
        if entry is None or entry[0] is not track:
            entry = (track, speed_profile(track, self.cfg, self.STEP_M))
            self._profiles[id(track)] = entry
        profile = entry[1]
        return float(profile[min(len(profile) - 1, max(0, int(s / self.STEP_M)))])


def car_ahead(world: World, s_from: float, lane: int, range_m: float) -> tuple[float, int]:
    """The first parked car in ``lane`` whose rear is ahead of ``s_from`` (or overlaps it), from
    the world's car list: ``(gap from s_from to its rear [m], index)``, or ``(inf, -1)``."""
    cars = world.cars
    half = cars.length_m / 2.0
    sl = cars.between(s_from - half, s_from + range_m + half)
    hits = np.flatnonzero(cars.lane[sl] == lane)
    if hits.size == 0:
        return math.inf, -1
    j = sl.start + int(hits[0])
    return float(cars.s[j]) - half - s_from, j


def lane_clear(world: World, lane: int, s_lo: float, s_hi: float) -> bool:
    """No parked car's body in ``lane`` overlaps ``[s_lo, s_hi]`` [m] of arc length."""
    half = world.cars.length_m / 2.0
    return world.lane_free(s_lo, lane, half, s_hi - s_lo + half)
