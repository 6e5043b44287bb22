"""The expert (seed 000, section 4.1.1): a finite-state machine on top of the LQR tracker.

It sees the world as it is (the true positions of the parked cars) and follows three rules:

1. its speed never exceeds a limit set by the road's curvature ahead and a friction bound,
   ``v <= sqrt(a_lat_max / |kappa|)``, nor a top speed;
2. the LQR tracker keeps it on its lane centre (or on a lane-change path);
3. the states of the machine say when it **should** overtake (a parked car ahead in its lane is
   nearer than a trigger distance) and when it **can** (the target lane is free over a window).

==========  =====================================================================================
state       what it does, and when it leaves
==========  =====================================================================================
``keep``    follow the lane centre. A car ahead nearer than ``trigger``: pick a free neighbour
            (at random when both are free) -> ``change``; none free -> ``follow``.
``change``  follow a quintic lane-change path; at its end -> ``pass`` (overtaking) or ``keep``
            (returning).
``pass``    follow the overtaking lane's centre; once ``finish`` metres past the overtaken car,
            return to the original lane when it is free -> ``change``. A car ahead nearer than
            ``trigger`` is handled as in ``keep``, preferring the original lane.
``follow``  no lane is free: brake to stop ``follow_margin`` behind the car, and keep looking
            for a free lane (a slower car needs a shorter lane change).
==========  =====================================================================================

The trigger and finish distances, the lane change's duration and the side coin are drawn per
manoeuvre from the car's own seeded generator: the same scene is overtaken on either side, and
the moment it starts and ends varies, like human driving.

Trajectory labels (:meth:`Expert.trajectory_label`) are the expert's noise-free rollout: a copy of
the car and its plan driven 1.5 s by the same rules (no physics), every 0.3 s in the car frame.
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ..config import check_pair, check_range
from ..simulation.geometry import Track, wrap_angle
from ..simulation.policy import Actuation, Observation, seeded_cars
from ..simulation.vehicle import H, V, VehicleParams, bicycle_step
from ..simulation.world import SimConfig, World, lane_frame
from .labels import CHANGE, FOLLOW, KEEP, N_POINTS, PASS, POINT_DT_S
from .tracker import (
    LaneChangePath,
    LQRTracker,
    default_tracker,
    lane_reference,
)

QUINTIC_PEAK = 10.0 / math.sqrt(3.0)  # max |b''| of the quintic blend: 5.77


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

    def __post_init__(self) -> None:
        o = "ExpertConfig"
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


@dataclass
class Plan:
    """One car's place in the state machine (copied for label rollouts).

    Attributes:
        state: ``KEEP``, ``CHANGE``, ``PASS`` or ``FOLLOW``.
        lane: the lane it drives in (the target lane while changing).
        origin: the lane an overtake started from (where ``pass`` returns to).
        path: the lane-change path while in ``change``.
        overtaking: whether the current change is an overtake (False: a return).
        side: +1 left, -1 right, 0 none: the side of the current or last overtake.
        obstacle_front_m: arc length of the overtaken car's front [m].
        trigger_m, finish_m, change_time_s, coin: this manoeuvre's random draws.
        rng: the car's generator (None in rollouts: a rollout never starts a second manoeuvre,
            a change lasts longer than the 1.5 s horizon, so it needs no new draws).
    """

    state: int = KEEP
    lane: int = 0
    origin: int = 0
    path: LaneChangePath | None = None
    overtaking: bool = False
    side: int = 0
    obstacle_front_m: float = -math.inf
    trigger_m: float = 60.0
    finish_m: float = 20.0
    change_time_s: float = 3.0
    coin: float = 0.5
    rng: np.random.Generator | None = field(default=None, repr=False)

    def draw(self, cfg: ExpertConfig) -> None:
        """Draw the next manoeuvre's trigger, finish, duration and side coin."""
        if self.rng is None:
            return
        self.trigger_m = float(self.rng.uniform(*cfg.trigger_m))
        self.finish_m = float(self.rng.uniform(*cfg.finish_m))
        self.change_time_s = float(self.rng.uniform(*cfg.change_time_s))
        self.coin = float(self.rng.random())

    def rollout_copy(self) -> Plan:
        """A copy without the generator (see ``rng``)."""
        out = copy.copy(self)
        out.rng = None
        return out


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


class Expert:
    """The privileged expert driver; a :class:`~e2e_lite.driving.evaluation.Policy` without a camera.

    Args:
        cfg: the state machine's settings.
        tracker: the LQR tracker it drives with (None: default weights at ``sim``'s policy period).
        vehicle, sim: the car and time steps of the rollouts (must match the world's).
        seed: seeds every car's manoeuvre draws (car ``i`` of the evaluation uses
            ``default_rng([seed, i])``, in whichever shard it drives; see :meth:`seed_cars`).

    Attributes:
        plans: each car's :class:`Plan`.
        manoeuvres: counters ``{"left", "right", "return", "follow"}`` since :meth:`reset`.
    """

    camera = None

    def __init__(
        self,
        cfg: ExpertConfig | None = None,
        tracker: LQRTracker | None = None,
        vehicle: VehicleParams | None = None,
        sim: SimConfig | None = None,
        seed: int = 0,
    ) -> None:
        self.cfg = cfg or ExpertConfig()
        self.vehicle = vehicle or VehicleParams()
        self.sim = sim or SimConfig()
        # discretised at the world's policy period: a tracker built for another rate mis-steers
        self.tracker = tracker or default_tracker(self.vehicle, self.sim)
        self.seed = seed
        self.plans: list[Plan] = []
        self.manoeuvres = {"left": 0, "right": 0, "return": 0, "follow": 0}
        self.speed_limits = SpeedLimits(self.cfg)
        self._front = self.vehicle.length_m - self.vehicle.rear_overhang_m

    # ------------------------------------------------------------------ Policy
    def seed_cars(self, cars: np.ndarray) -> None:
        """Car ``i`` of the next :meth:`reset` is car ``cars[i]`` of the evaluation: its draws are
        seeded by that index (see :class:`~e2e_lite.simulation.policy.Policy`)."""
        self.cars = np.asarray(cars, dtype=np.int64)

    def fork(self, k: int) -> list[Expert]:
        """``k`` experts for an evaluation's parallel shards (no state is shared)."""
        return [copy.deepcopy(self) for _ in range(k)]

    def reset(self, n_worlds: int) -> None:
        """New plans for ``n_worlds`` cars; counters zeroed."""
        self.plans = []
        cars = seeded_cars(self, n_worlds)
        for i in range(n_worlds):
            plan = Plan(rng=np.random.default_rng([self.seed, int(cars[i])]))
            plan.draw(self.cfg)
            self.plans.append(plan)
        self.manoeuvres = dict.fromkeys(self.manoeuvres, 0)

    def act(self, obs: Observation) -> Actuation:
        """The expert's (clean) commands; advances every car's plan. The manoeuvres it starts are
        reported in ``info["manoeuvres"]`` (summed over an evaluation's decisions and shards: a
        copy in a worker process counts them there)."""
        for i in np.flatnonzero(obs.respawned).tolist():
            self._restart(self.plans[i], int(obs.lane[i]))
        before = dict(self.manoeuvres)
        steer, accel = self._decide(
            self.plans, obs.state, obs.s, obs.d, obs.heading_error, obs.curvature, obs.worlds, True
        )
        started = Counter({k: n - before[k] for k, n in self.manoeuvres.items() if n > before[k]})
        return Actuation(steer, accel, info={"manoeuvres": started} if started else None)

    def states(self) -> np.ndarray:
        """Each car's state-machine state (``KEEP`` ...), ``(B,)`` int."""
        return np.array([p.state for p in self.plans], dtype=np.int64)

    # ------------------------------------------------------------------ labels
    def trajectory_label(self, obs: Observation) -> np.ndarray:
        """What the expert would drive from ``obs`` over the next 1.5 s, without noise.

        Copies of the cars and of their plans are driven with the same rules (plans as they are
        *before* this decision's :meth:`act`; call this first). Returns ``(B, 5, 2)`` points
        ``(x forward, y left)`` [m] of the rear axle in the car frame at the sample time, at
        ``0.3, 0.6, ..., 1.5`` s.
        """
        plans = [p.rollout_copy() for p in self.plans]
        for i in np.flatnonzero(obs.respawned).tolist():
            self._restart(plans[i], int(obs.lane[i]))
        st = obs.state.copy()
        tracks = [w.track for w in obs.worlds]
        seg = np.array([int(t.segment_index(si)) for t, si in zip(tracks, obs.s)], dtype=np.int64)
        x0, y0 = st[:, 0].copy(), st[:, 1].copy()
        c, sn = np.cos(st[:, H]), np.sin(st[:, H])  # the car frame at the sample time
        per_point = round(POINT_DT_S / self.sim.policy_period_s)
        out = np.empty((len(plans), N_POINTS, 2))
        s, d, he, kap = obs.s, obs.d, obs.heading_error, obs.curvature
        for k in range(N_POINTS * per_point):
            if k:
                s, d, road_h, kap = lane_frame(tracks, st, seg)
                he = wrap_angle(st[:, H] - road_h)
            steer, accel = self._decide(plans, st, s, d, he, kap, obs.worlds, False)
            for _ in range(self.sim.steps_per_policy):
                bicycle_step(st, steer, accel, self.vehicle, self.sim.dt_s)
            if (k + 1) % per_point == 0:
                dx, dy = st[:, 0] - x0, st[:, 1] - y0
                j = (k + 1) // per_point - 1
                out[:, j, 0] = c * dx + sn * dy
                out[:, j, 1] = -sn * dx + c * dy
        return out

    # ------------------------------------------------------------------ machine
    def _restart(self, plan: Plan, lane: int) -> None:
        plan.state, plan.lane, plan.origin, plan.path = KEEP, lane, lane, None
        plan.overtaking, plan.obstacle_front_m = False, -math.inf

    def _change_length(
        self, plan: Plan, speed: float, gap: float, lane_width_m: float
    ) -> float | None:
        """Length of a lane change that starts now and has the car ~84 % across (``b(0.7)``) when
        its front reaches a car ``gap`` metres ahead; None if it would need more lateral
        acceleration than ``change_lat_accel_mps2``."""
        length = max(self.cfg.min_change_m, speed * plan.change_time_s)
        if math.isfinite(gap):
            length = min(length, max(self.cfg.min_change_m, (gap - 2.0) / 0.7))
            if length * 0.7 > gap - 2.0:
                return None
        if QUINTIC_PEAK * lane_width_m * speed**2 / length**2 > self.cfg.change_lat_accel_mps2:
            return None
        return length

    def _try_overtake(
        self,
        plan: Plan,
        world: World,
        s: float,
        d: float,
        speed: float,
        gap: float,
        j: int,
        count: bool,
    ) -> bool:
        """Start a lane change around car ``j`` if a neighbouring lane is free; True if started."""
        cfg, track = self.cfg, world.track
        s_obst_front = float(world.cars.s[j]) + world.cars.length_m / 2.0
        free = [
            lane
            for lane in (plan.lane + 1, plan.lane - 1)
            if 0 <= lane < track.n_lanes
            and lane_clear(world, lane, s - cfg.clear_behind_m, s_obst_front + cfg.clear_past_m)
        ]
        if not free:
            return False
        length = self._change_length(plan, speed, gap, track.lane_width)
        if length is None:
            return False
        if plan.state == PASS and plan.origin in free:
            target = plan.origin
        elif len(free) == 2:
            target = free[0] if plan.coin < 0.5 else free[1]
        else:
            target = free[0]
        side = 1 if target > plan.lane else -1
        if target != plan.origin:  # the lane it leaves is where it returns to (one lane at a time)
            plan.origin = plan.lane
        plan.path = LaneChangePath(s, length, d, float(track.lane_center(target)))
        plan.state, plan.lane, plan.overtaking, plan.side = CHANGE, target, True, side
        plan.obstacle_front_m = s_obst_front
        if count:
            self.manoeuvres["left" if side > 0 else "right"] += 1
        plan.draw(cfg)
        return True

    def _decide(
        self,
        plans: list[Plan],
        state: np.ndarray,
        s: np.ndarray,
        d: np.ndarray,
        heading_error: np.ndarray,
        curvature: np.ndarray,
        worlds: list[World],
        count: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advance every plan one decision and return ``(steer [rad], accel [m/s^2])``."""
        cfg = self.cfg
        n = len(plans)
        e, psi, kap = np.empty(n), np.empty(n), np.empty(n)
        v_ref = np.empty(n)
        brake = np.zeros(n)  # extra deceleration demanded by a car ahead [m/s^2]
        speeds = state[:, V]
        for i, plan in enumerate(plans):
            world, si, di, v = worlds[i], float(s[i]), float(d[i]), float(speeds[i])
            track = world.track
            front = si + self._front
            if plan.state == CHANGE and plan.path is not None and plan.path.done(si):
                plan.state = PASS if plan.overtaking else KEEP
                plan.path = None
                if plan.state == KEEP:
                    plan.origin = plan.lane
            gap, j = car_ahead(world, front, plan.lane, cfg.lookahead_m)
            if plan.state in (KEEP, PASS, FOLLOW) and gap < plan.trigger_m:
                if self._try_overtake(plan, world, si, di, v, gap, j, count):
                    gap, j = car_ahead(world, front, plan.lane, cfg.lookahead_m)
                elif plan.state != FOLLOW:
                    plan.state = FOLLOW
                    if count:
                        self.manoeuvres["follow"] += 1
            elif plan.state == FOLLOW:
                plan.state = KEEP
            if (
                plan.state == PASS
                and si > plan.obstacle_front_m + plan.finish_m
                and plan.origin != plan.lane
            ):
                g_back, _ = car_ahead(world, front, plan.origin, cfg.lookahead_m)
                length = self._change_length(plan, v, g_back, track.lane_width)
                if length is not None and lane_clear(
                    world, plan.origin, si - cfg.clear_behind_m, si + length + cfg.clear_past_m
                ):
                    plan.path = LaneChangePath(
                        si, length, di, float(track.lane_center(plan.origin))
                    )
                    plan.state, plan.lane, plan.overtaking = CHANGE, plan.origin, False
                    if count:
                        self.manoeuvres["return"] += 1
                    plan.draw(cfg)
                    gap, j = car_ahead(world, front, plan.lane, cfg.lookahead_m)
            if plan.state == PASS and plan.origin == plan.lane:
                plan.state = KEEP
            # lateral reference
            if plan.state == CHANGE and plan.path is not None:
                e[i], psi[i], kap[i] = plan.path.reference(
                    si, di, float(heading_error[i]), float(curvature[i])
                )
            else:
                ei, pi, ki = lane_reference(
                    di, heading_error[i], curvature[i], track.lane_center(plan.lane)
                )
                e[i], psi[i], kap[i] = float(ei), float(pi), float(ki)
            # speed: the curve profile, then any car ahead it must not reach
            v_ref[i] = self.speed_limits.at(track, si)
            room = gap - cfg.follow_margin_m
            if plan.state == FOLLOW:
                v_ref[i] = min(v_ref[i], math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
                if v > 0.1:
                    brake[i] = v * v / (2.0 * max(room, 0.5))
            elif plan.state != KEEP and math.isfinite(gap):
                v_ref[i] = min(v_ref[i], math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
        steer = self.tracker.steer(e, psi, kap, speeds)
        accel = self.tracker.accel(speeds, v_ref)
        accel = np.where(brake > 0, np.minimum(accel, -brake), accel)
        return steer, accel


def fresh_labels(
    obs: Observation,
    idx: list[int],
    sim: SimConfig | None = None,
    limits: SpeedLimits | None = None,
) -> np.ndarray:
    """What a fresh expert (default settings, new plans) would drive from cars ``idx``'s states:
    ``(len(idx), 5, 2)`` points in each car's frame [m], as :meth:`Expert.trajectory_label`.

    ``sim``: the driven agent's time steps (default :class:`~e2e_lite.simulation.world.SimConfig`);
    ``limits``: speed limits of the default expert to reuse across calls (the safety module's
    audits), so a track's profile is computed once, not at every call: the same numbers.
    """
    sub = Observation(
        state=obs.state[idx],
        s=obs.s[idx],
        d=obs.d[idx],
        heading_error=obs.heading_error[idx],
        curvature=obs.curvature[idx],
        lane=obs.lane[idx],
        respawned=np.ones(len(idx), dtype=bool),
        time_s=obs.time_s,
        worlds=[obs.worlds[i] for i in idx],
    )
    # the expert of the car and time steps being driven, not a default one
    expert = Expert(vehicle=obs.worlds[idx[0]].vehicle, sim=sim)
    if limits is not None:
        expert.speed_limits = limits
    expert.reset(len(idx))
    return expert.trajectory_label(sub)
