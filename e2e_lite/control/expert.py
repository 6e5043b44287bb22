"""The expert (seed 000, section 4.1.1): a finite-state machine on top of the LQR tracker, which
carries its plan from decision to decision. It drives and labels chapter 04's data, so every
network of the course learns it, and the oracle follows its plans.

It sees the world as it is (the true positions of the parked cars) and follows three rules:

1. its speed never exceeds a limit set by the road's curvature ahead and a friction bound,
   ``v <= sqrt(a_lat_max / |kappa|)``, nor a top speed (:mod:`e2e_lite.control.rules`);
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
Because the plan is memory, the same state can get two labels (a car the plan meant to be further
across its lane change is labelled with the rest of that plan), and at a state no plan of its own
led to it has none: DAgger's labels come from :class:`~e2e_lite.control.state_expert.StateExpert`,
the same machine with its state read off the world (chapter 12; lab notes "Does the labeller
drive?" and "Do networks learn the labeller?").
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..learning.labels import CHANGE, FOLLOW, KEEP, N_POINTS, PASS, POINT_DT_S, Decision
from ..simulation.geometry import wrap_angle
from ..simulation.policy import Actuation, Observation, seeded_cars
from ..simulation.vehicle import H, V, VehicleParams, bicycle_step
from ..simulation.world import SimConfig, World, lane_frame
from .rules import ExpertConfig, SpeedLimits, car_ahead, lane_clear
from .tracker import LaneChangePath, LQRTracker, default_tracker, lane_reference

QUINTIC_PEAK = 10.0 / math.sqrt(3.0)  # max |b''| of the quintic blend: 5.77


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

    @property
    def decision(self) -> Decision:
        """The plan as a :class:`~e2e_lite.learning.labels.Decision` (what the data records): its
        ``side`` is the side the current lane change moves to, a return's too (``Plan.side``
        keeps the overtake's)."""
        moving = self.state == CHANGE and self.path is not None
        side = (1 if self.path.d_to > self.path.d_from else -1) if moving else 0
        return Decision(self.state, self.lane, side, self.state == CHANGE and self.overtaking)

    def rollout_copy(self) -> Plan:
        """A copy without the generator (see ``rng``)."""
        out = copy.copy(self)
        out.rng = None
        return out


class Expert:
    """The privileged expert driver, a :class:`~e2e_lite.simulation.policy.Policy` without a
    camera.

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
        self._front = self.vehicle.rear_to_front_m

    # ------------------------------------------------------------------ Policy
    def seed_cars(self, cars: np.ndarray) -> None:
        """Car ``i`` of the next :meth:`reset` is car ``cars[i]`` of the evaluation: its draws are
        seeded by that index (see :class:`~e2e_lite.simulation.policy.Policy`)."""
        self.cars = np.asarray(cars, dtype=np.int64)

    def fork(self, k: int) -> list[Expert]:
        """``k`` experts for an evaluation's parallel shards (no state is shared)."""
        return [copy.deepcopy(self) for _ in range(k)]

    def identity(self) -> list[str]:
        """What decides its behaviour (:func:`~e2e_lite.simulation.policy.fingerprint`): its
        settings."""
        return [repr(self.cfg)]

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
            self.plans,
            obs.state,
            obs.s,
            obs.d,
            obs.heading_error,
            obs.curvature,
            obs.worlds,
            count_manoeuvres=True,
        )
        started = Counter({k: n - before[k] for k, n in self.manoeuvres.items() if n > before[k]})
        return Actuation(steer, accel, info={"manoeuvres": started} if started else None)

    def states(self) -> np.ndarray:
        """Each car's state-machine state (``KEEP`` ...), ``(B,)`` int."""
        return np.array([p.state for p in self.plans], dtype=np.int64)

    @property
    def decisions(self) -> list[Decision]:
        """Each car's plan as a decision (:attr:`Plan.decision`), as the state expert reports
        its own: what the data records."""
        return [p.decision for p in self.plans]

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
            steer, accel = self._decide(
                plans, st, s, d, he, kap, obs.worlds, count_manoeuvres=False
            )
            for _ in range(self.sim.steps_per_policy):
                bicycle_step(st, steer, accel, self.vehicle, self.sim.dt_s)
            if (k + 1) % per_point == 0:
                dx, dy = st[:, 0] - x0, st[:, 1] - y0
                j = (k + 1) // per_point - 1
                out[:, j, 0] = c * dx + sn * dy
                out[:, j, 1] = -sn * dx + c * dy
        return out

    # ------------------------------------------------------------------ machine
    # One decision per car, in the three phases of the state table (module docstring): the
    # transitions move the plan, then the lateral and the speed references follow from it.
    def _decide(
        self,
        plans: list[Plan],
        state: np.ndarray,
        s: np.ndarray,
        d: np.ndarray,
        heading_error: np.ndarray,
        curvature: np.ndarray,
        worlds: list[World],
        count_manoeuvres: bool,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advance every plan one decision and return ``(steer [rad], accel [m/s^2])``.
        ``count_manoeuvres``: add the manoeuvres started to :attr:`manoeuvres` (the driven
        decision does; a label's rollout does not)."""
        n = len(plans)
        e, psi, kap = np.empty(n), np.empty(n), np.empty(n)
        v_ref = np.empty(n)
        brake = np.zeros(n)  # extra deceleration demanded by a car ahead [m/s^2]
        speeds = state[:, V]
        for i, plan in enumerate(plans):
            car = _Car(worlds[i], float(s[i]), float(d[i]), float(speeds[i]))
            gap = self._transition(plan, car, count_manoeuvres)
            e[i], psi[i], kap[i] = self._lateral_reference(
                plan, car, heading_error[i], curvature[i]
            )
            v_ref[i], brake[i] = self._speed_reference(plan, car, gap)
        steer = self.tracker.steer(e, psi, kap, speeds)
        accel = self.tracker.accel(speeds, v_ref)
        accel = np.where(brake > 0, np.minimum(accel, -brake), accel)
        return steer, accel

    @staticmethod
    def _restart(plan: Plan, lane: int) -> None:
        """A car (re-)placed in ``lane``: ``keep`` there, no manoeuvre under way."""
        plan.state, plan.lane, plan.origin, plan.path = KEEP, lane, lane, None
        plan.overtaking, plan.obstacle_front_m = False, -math.inf

    def _gap_ahead(self, plan: Plan, car: _Car, lane: int | None = None) -> tuple[float, int]:
        """The parked car ahead of ``car``'s front bumper in ``lane`` (default: the plan's)."""
        front = car.s + self._front
        return car_ahead(
            car.world, front, plan.lane if lane is None else lane, self.cfg.lookahead_m
        )

    def _transition(self, plan: Plan, car: _Car, count_manoeuvres: bool) -> float:
        """The state machine's transitions for one decision (the module docstring's table);
        returns the gap to the parked car ahead in the lane the plan now drives for [m]."""
        if plan.state == CHANGE and plan.path is not None and plan.path.done(car.s):
            self._end_change(plan)
        gap, j = self._gap_ahead(plan, car)
        should_overtake = plan.state in (KEEP, PASS, FOLLOW) and gap < plan.trigger_m
        if should_overtake:
            if self._start_overtake(plan, car, gap, j, count_manoeuvres):
                gap, _ = self._gap_ahead(plan, car)
            elif plan.state != FOLLOW:
                plan.state = FOLLOW
                self._count("follow", count_manoeuvres)
        elif plan.state == FOLLOW:
            plan.state = KEEP
        passed = plan.state == PASS and car.s > plan.obstacle_front_m + plan.finish_m
        if passed and plan.origin != plan.lane and self._start_return(plan, car, count_manoeuvres):
            gap, _ = self._gap_ahead(plan, car)
        if plan.state == PASS and plan.origin == plan.lane:
            plan.state = KEEP
        return gap

    def _count(self, manoeuvre: str, count_manoeuvres: bool) -> None:
        if count_manoeuvres:
            self.manoeuvres[manoeuvre] += 1

    @staticmethod
    def _end_change(plan: Plan) -> None:
        """``change`` -> ``pass`` (an overtake) or ``keep`` (a return) at the path's end."""
        plan.state = PASS if plan.overtaking else KEEP
        plan.path = None
        if plan.state == KEEP:
            plan.origin = plan.lane

    def _start_overtake(
        self, plan: Plan, car: _Car, gap: float, j: int, count_manoeuvres: bool
    ) -> bool:
        """``keep``/``pass``/``follow`` -> ``change``: a lane change around parked car ``j``
        (``gap`` metres ahead) if a neighbouring lane is free; True if started."""
        cfg, world, track = self.cfg, car.world, car.world.track
        s_obst_front = float(world.cars.s[j]) + world.cars.length_m / 2.0
        free = [
            lane
            for lane in (plan.lane + 1, plan.lane - 1)
            if 0 <= lane < track.n_lanes
            and lane_clear(world, lane, car.s - cfg.clear_behind_m, s_obst_front + cfg.clear_past_m)
        ]
        if not free:
            return False
        length = self._change_length(plan, car.v, gap, track.lane_width)
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
        plan.path = LaneChangePath(car.s, length, car.d, float(track.lane_center(target)))
        plan.state, plan.lane, plan.overtaking, plan.side = CHANGE, target, True, side
        plan.obstacle_front_m = s_obst_front
        self._count("left" if side > 0 else "right", count_manoeuvres)
        plan.draw(cfg)
        return True

    def _start_return(self, plan: Plan, car: _Car, count_manoeuvres: bool) -> bool:
        """``pass`` -> ``change``: back to the origin lane once it is free far enough ahead;
        True if started."""
        cfg, track = self.cfg, car.world.track
        g_back, _ = self._gap_ahead(plan, car, plan.origin)
        length = self._change_length(plan, car.v, g_back, track.lane_width)
        if length is None or not lane_clear(
            car.world, plan.origin, car.s - cfg.clear_behind_m, car.s + length + cfg.clear_past_m
        ):
            return False
        plan.path = LaneChangePath(car.s, length, car.d, float(track.lane_center(plan.origin)))
        plan.state, plan.lane, plan.overtaking = CHANGE, plan.origin, False
        self._count("return", count_manoeuvres)
        plan.draw(cfg)
        return True

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

    @staticmethod
    def _lateral_reference(
        plan: Plan, car: _Car, heading_error: float, curvature: float
    ) -> tuple[float, float, float]:
        """``(e [m], psi [rad], kappa [1/m])`` for the tracker: the lane-change path in
        ``change``, else the centre of the plan's lane."""
        if plan.state == CHANGE and plan.path is not None:
            return plan.path.reference(car.s, car.d, float(heading_error), float(curvature))
        ei, pi, ki = lane_reference(
            car.d, heading_error, curvature, car.world.track.lane_center(plan.lane)
        )
        return float(ei), float(pi), float(ki)

    def _speed_reference(self, plan: Plan, car: _Car, gap: float) -> tuple[float, float]:
        """``(v_ref [m/s], brake [m/s^2])``: the curve profile, capped outside ``keep`` so the car
        could still stop ``follow_margin_m`` behind the car ahead (``gap`` metres), and in
        ``follow`` the deceleration that stops it there (0: none)."""
        cfg = self.cfg
        v_ref, brake = self.speed_limits.at(car.world.track, car.s), 0.0
        room = gap - cfg.follow_margin_m
        if plan.state == FOLLOW:
            v_ref = min(v_ref, math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
            if car.v > 0.1:
                brake = car.v * car.v / (2.0 * max(room, 0.5))
        elif plan.state != KEEP and math.isfinite(gap):
            v_ref = min(v_ref, math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
        return v_ref, brake


class _Car(NamedTuple):
    """One car at one decision, as the state machine reads it."""

    world: World
    s: float  # arc length of the rear axle [m]
    d: float  # lateral offset from the reference line [m]
    v: float  # speed [m/s]


class WipedExpert(Expert):
    """The expert with every plan wiped before each label (every car restarted in
    ``keep`` at its lane): chapter 12's old DAgger labeller, kept to show that a label is a
    driver (the tracker following these labels runs into parked cars, chapter 12, section 2)."""

    def trajectory_label(self, obs: Observation) -> np.ndarray:
        wiped = dataclasses.replace(obs, respawned=np.ones(len(obs.s), dtype=bool))
        return super().trajectory_label(wiped)
