"""The expert (seed 000, section 4.1.1): a finite-state machine on top of the LQR tracker, whose
state is read off the world at every decision, so its label is a function of the state alone. It
drives and labels chapter 04's data, labels every DAgger round (chapter 12), and the oracle
follows its labels: one expert for the whole course.

It sees the world as it is (the true positions of the parked cars) and follows three rules:

1. its speed never exceeds a limit set by the road's curvature ahead and a friction bound,
   ``v <= sqrt(a_lat_max / |kappa|)``, nor a top speed (:mod:`e2e_lite.control.rules`);
2. the LQR tracker keeps it on its lane centre, or on a lane-change path;
3. the states of the machine say when it **should** overtake (a parked car ahead in its lane is
   nearer than a trigger distance) and when it **can** (the target lane is free over a window).

==========  =====================================================================================
state       what it does, read off the state at every decision
==========  =====================================================================================
``keep``    in its home lane (``ExpertConfig.home``: the lane it is in, the middle one or the
            rightmost), on its centre. A parked car ahead nearer than ``trigger``: a free
            neighbour (at random when both are free) -> ``change``; none free or the change would
            be too sharp -> ``follow``.
``change``  heading for a neighbouring lane: a quintic path from its lane's centre, whose progress
            is read off how far across the car already is; past the dashed line, the tracker
            brings it to the new lane's centre.
``pass``    in another lane than home; once ``finish`` metres past the last parked car it passed
            in the home lane, and the home lane is free ahead -> ``change`` back. A parked car
            ahead is handled as in ``keep``, preferring home. (With its own lane as home there is
            no ``pass``: every lane change is an overtake.)
``follow``  no lane is free: brake to stop ``follow_margin`` behind the car, and keep looking
            for a free lane (a slower car needs a shorter lane change).
==========  =====================================================================================

**A label is a function of the state.** Nothing is carried from one decision to the next: the
lane the car is in, where it is heading (its offset and its lateral speed towards a free lane),
the parked cars and their draws say everything. The trigger and finish distances, the lane
change's duration and the side coin are drawn per *parked car*, seeded by the expert's seed, the
track and the car's index (:meth:`Expert.draws`): the same state gets the same label whatever
drove there, which DAgger's labeller must (chapter 12); across parked cars they vary, so the same
scene is overtaken on either side, like human driving. A lane change already under way (the car
moving towards a free neighbour while a parked car ahead asks for one) is continued; one whose
start would be too sharp is not begun.

Trajectory labels (:meth:`Expert.trajectory_label`) are the expert's noise-free rollout: a copy of
the car driven 1.5 s by the same rules (no physics), every 0.3 s in the car frame. Until 2026-12
the course had two such machines, one that carried its plan from decision to decision and this
one; the lab note "One expert for the whole course" says how its home rule was chosen.
"""

from __future__ import annotations

import copy
import math
import zlib
from collections import Counter
from typing import NamedTuple

import numpy as np

from ..learning.labels import CHANGE, FOLLOW, KEEP, N_POINTS, PASS, POINT_DT_S, Decision
from ..simulation.geometry import Track, wrap_angle
from ..simulation.policy import Actuation, Observation
from ..simulation.vehicle import H, V, VehicleParams, bicycle_step
from ..simulation.world import SimConfig, World, lane_frame
from .rules import ExpertConfig, SpeedLimits, car_ahead, lane_clear
from .tracker import LaneChangePath, LQRTracker, default_tracker

QUINTIC_PEAK = 10.0 / math.sqrt(3.0)  # max |b''| of the quintic blend: 5.77
#: the quintic blend b(u) = u^3 (10 - 15 u + 6 u^2) on a grid, to read u off a change's progress
_U = np.linspace(0.0, 1.0, 2001)
_BLEND = _U**3 * (10.0 - 15.0 * _U + 6.0 * _U**2)


class Draws(NamedTuple):
    """A parked car's draws: the gap at which the expert starts to overtake it [m], how far past
    it the return may start [m], how long a lane change takes [s], and the side coin (< 0.5:
    left, when both sides are free)."""

    trigger_m: float
    finish_m: float
    change_time_s: float
    coin: float


class _Car(NamedTuple):
    """One car at one decision, as the state machine reads it."""

    world: World
    s: float  # arc length of the rear axle [m]
    d: float  # lateral offset from the reference line [m]
    v: float  # speed [m/s]
    v_lat: float  # speed across the road, left positive [m/s]


_NOTHING = Decision(KEEP, -1, 0, False)


class Expert:
    """The privileged expert driver, a :class:`~e2e_lite.simulation.policy.Policy` without a
    camera, whose every decision (and every label) is a function of the state alone.

    Args:
        cfg: the state machine's settings.
        tracker: the LQR tracker it drives with (None: default weights at ``sim``'s policy period).
        vehicle, sim: the car and time steps of the rollouts (must match the world's).
        seed: seeds the parked cars' draws (:meth:`draws`).
    Attributes:
        decisions: each car's last :class:`Decision` (what the data records).
        manoeuvres: counters ``{"left", "right", "return", "follow"}`` since :meth:`reset` (of the
            driven decisions; counting is the only thing remembered, and no decision reads it).
    """

    camera = None
    #: a lane change is under way when the car moves towards the target lane faster than this
    #: [m/s] and is not more than ``COMMIT_M`` [m] on the other side of its lane's centre
    COMMIT_MPS, COMMIT_M = 0.05, 0.3
    #: the least progress of a lane change's path (a change from a lane's centre has to begin)
    U_MIN = 0.1

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
        self.speed_limits = SpeedLimits(self.cfg)
        self.manoeuvres = {"left": 0, "right": 0, "return": 0, "follow": 0}
        self.decisions: list[Decision] = []
        self._front = self.vehicle.rear_to_front_m
        self._draws: dict[tuple, Draws] = {}

    # ------------------------------------------------------------------ Policy
    def seed_cars(self, cars: np.ndarray) -> None:
        """The evaluation's indices of the cars of the next :meth:`reset` (the expert's draws are
        the parked cars', so they do not depend on them)."""
        self.cars = np.asarray(cars, dtype=np.int64)

    def fork(self, k: int) -> list[Expert]:
        """``k`` experts for an evaluation's parallel shards (no state is shared)."""
        return [copy.deepcopy(self) for _ in range(k)]

    def identity(self) -> list[str]:
        """What decides its behaviour (:func:`~e2e_lite.simulation.policy.fingerprint`): its
        settings (its home lane among them)."""
        return [repr(self.cfg)]

    def reset(self, n_worlds: int) -> None:
        """Forget the last decisions of ``n_worlds`` cars; counters zeroed."""
        self.decisions = [_NOTHING] * n_worlds
        self.manoeuvres = dict.fromkeys(self.manoeuvres, 0)

    def act(self, obs: Observation) -> Actuation:
        """The expert's (clean) commands. The manoeuvres it starts are reported in
        ``info["manoeuvres"]`` (summed over an evaluation's decisions and shards)."""
        before = [
            _NOTHING if placed else d for d, placed in zip(self.decisions, obs.respawned.tolist())
        ]
        steer, accel, self.decisions = self._decide(
            obs.state, obs.s, obs.d, obs.heading_error, obs.curvature, obs.worlds
        )
        started = Counter(m for m in map(_started, before, self.decisions) if m)
        for k, n in started.items():
            self.manoeuvres[k] += n
        return Actuation(steer, accel, info={"manoeuvres": started} if started else None)

    def states(self) -> np.ndarray:
        """Each car's state (``KEEP`` ...) at its last decision, ``(B,)`` int."""
        return np.array([d.state for d in self.decisions], dtype=np.int64)

    # ------------------------------------------------------------------ labels
    def trajectory_label(self, obs: Observation) -> np.ndarray:
        """What the expert would drive from ``obs`` over the next 1.5 s, without noise: copies of
        the cars driven with the same rules. Returns ``(B, 5, 2)`` points ``(x forward, y left)``
        [m] of the rear axle in the car frame at the sample time, at ``0.3, 0.6, ..., 1.5`` s."""
        st = obs.state.copy()
        tracks = [w.track for w in obs.worlds]
        seg = np.array([int(t.segment_index(si)) for t, si in zip(tracks, obs.s)], dtype=np.int64)
        x0, y0 = st[:, 0].copy(), st[:, 1].copy()
        c, sn = np.cos(st[:, H]), np.sin(st[:, H])  # the car frame at the sample time
        per_point = round(POINT_DT_S / self.sim.policy_period_s)
        out = np.empty((len(st), N_POINTS, 2))
        s, d, he, kap = obs.s, obs.d, obs.heading_error, obs.curvature
        for k in range(N_POINTS * per_point):
            if k:
                s, d, road_h, kap = lane_frame(tracks, st, seg)
                he = wrap_angle(st[:, H] - road_h)
            steer, accel, _ = self._decide(st, s, d, he, kap, obs.worlds)
            for _ in range(self.sim.steps_per_policy):
                bicycle_step(st, steer, accel, self.vehicle, self.sim.dt_s)
            if (k + 1) % per_point == 0:
                dx, dy = st[:, 0] - x0, st[:, 1] - y0
                j = (k + 1) // per_point - 1
                out[:, j, 0] = c * dx + sn * dy
                out[:, j, 1] = -sn * dx + c * dy
        return out

    # ------------------------------------------------------------------ the machine
    def _decide(
        self,
        state: np.ndarray,
        s: np.ndarray,
        d: np.ndarray,
        heading_error: np.ndarray,
        curvature: np.ndarray,
        worlds: list[World],
    ) -> tuple[np.ndarray, np.ndarray, list[Decision]]:
        """Every car's decision from its state: ``(steer [rad], accel [m/s^2], decisions)``."""
        n = len(worlds)
        e, psi, kap = np.empty(n), np.empty(n), np.empty(n)
        v_ref, brake = np.empty(n), np.zeros(n)
        speeds = state[:, V]
        decisions = []
        for i in range(n):
            v, he = float(speeds[i]), float(heading_error[i])
            car = _Car(worlds[i], float(s[i]), float(d[i]), v, v * math.sin(he))
            decision, gap, path = self._choose(car)
            decisions.append(decision)
            k = float(curvature[i])
            if path is not None:
                e[i], psi[i], kap[i] = path.reference(car.s, car.d, he, k)
            else:  # the target lane's centre line (tracker.lane_reference, in scalars)
                centre = _centre(car.world.track, decision.target)
                e[i], psi[i], kap[i] = car.d - centre, he, k / (1.0 - k * centre)
            v_ref[i], brake[i] = self._speed_reference(decision, car, gap)
        steer = self.tracker.steer(e, psi, kap, speeds)
        accel = self.tracker.accel(speeds, v_ref)
        accel = np.where(brake > 0, np.minimum(accel, -brake), accel)
        return steer, accel, decisions

    def _choose(self, car: _Car) -> tuple[Decision, float, LaneChangePath | None]:
        """The state table for one car: its decision, the gap ahead in the lane it drives for
        [m], and its lane-change path (None: it follows its target lane's centre)."""
        track = car.world.track
        here = _lane_of(track, car.d)
        home = self._home(track, here)
        gap, j = self._gap(car, here)
        if j >= 0 and gap < self.draws(car.world, j).trigger_m:  # should overtake
            target = self._overtake_lane(car, here, home, gap, j)
            if target is None:
                return Decision(FOLLOW, here, 0, False), gap, None
            path = self._path(car, here, target, self.draws(car.world, j), gap)
            side = 1 if target > here else -1
            return Decision(CHANGE, target, side, True), self._gap(car, target)[0], path
        if here != home:  # passing: back home once past, and free
            back = self._return(car, here, home)
            if back is not None:
                target, draws, g_back = back
                side = 1 if target > here else -1
                path = self._path(car, here, target, draws, g_back)
                return Decision(CHANGE, target, side, False), g_back, path
        centre = _centre(track, here)
        toward = 1 if centre > car.d else -1
        if abs(car.d - centre) > self.COMMIT_M and car.v_lat * toward > self.COMMIT_MPS:
            # the end of a lane change, past the dashed line: the tracker brings it in
            # (with its own lane as home there are no returns: every change is an overtake)
            overtaking = here != home or self.cfg.home == "own"
            return Decision(CHANGE, here, toward, overtaking), gap, None
        return Decision(KEEP if here == home else PASS, here, 0, False), gap, None

    def _home(self, track: Track, here: int) -> int:
        """The home lane of a car in lane ``here`` (``ExpertConfig.home``)."""
        if self.cfg.home == "middle":
            return (track.n_lanes - 1) // 2
        return 0 if self.cfg.home == "right" else here

    def draws(self, world: World, j: int) -> Draws:
        """Parked car ``j``'s draws on ``world``'s track, from a generator seeded by the expert's
        seed, the track and ``j`` (so the same state always gets the same decision)."""
        key = (world.track.track_id, j)
        found = self._draws.get(key)
        if found is None:
            split, index = world.track.track_id
            rng = np.random.default_rng([self.seed, zlib.crc32(str(split).encode()), index, j])
            cfg = self.cfg
            found = Draws(
                float(rng.uniform(*cfg.trigger_m)),
                float(rng.uniform(*cfg.finish_m)),
                float(rng.uniform(*cfg.change_time_s)),
                float(rng.random()),
            )
            if len(self._draws) > 100_000:  # (a cache of a pure function: any size is right)
                self._draws.clear()
            self._draws[key] = found
        return found

    def _gap(self, car: _Car, lane: int) -> tuple[float, int]:
        """The parked car ahead of ``car``'s front bumper in ``lane``: ``(gap [m], index)``."""
        return car_ahead(car.world, car.s + self._front, lane, self.cfg.lookahead_m)

    def _under_way(self, car: _Car, here: int, target: int) -> bool:
        """Whether ``car`` is already moving from lane ``here`` towards ``target``."""
        side = 1 if target > here else -1
        from_centre = (car.d - _centre(car.world.track, here)) * side
        return from_centre > -self.COMMIT_M and car.v_lat * side > self.COMMIT_MPS

    def _overtake_lane(self, car: _Car, here: int, home: int, gap: float, j: int) -> int | None:
        """The lane to overtake parked car ``j`` (``gap`` metres ahead) in: a free neighbour the
        car is already heading for, else one whose lane change is not too sharp (home first,
        else by ``j``'s coin when both are free); None: follow."""
        cfg, world, track = self.cfg, car.world, car.world.track
        s_obst_front = float(world.cars.s[j]) + world.cars.length_m / 2.0
        window = (car.s - cfg.clear_behind_m, s_obst_front + cfg.clear_past_m)
        free = [
            lane
            for lane in (here + 1, here - 1)
            if 0 <= lane < track.n_lanes and lane_clear(world, lane, *window)
        ]
        under_way = [lane for lane in free if self._under_way(car, here, lane)]
        if under_way:
            return under_way[0]
        draws = self.draws(world, j)
        if not free or self._change_length(draws, car.v, gap, track.lane_width) is None:
            return None
        if here != home and home in free:
            return home
        if len(free) == 2:
            return free[0] if draws.coin < 0.5 else free[1]
        return free[0]

    def _return(self, car: _Car, here: int, home: int) -> tuple[int, Draws, float] | None:
        """``(lane, draws, gap ahead in it)`` of a change one lane towards ``home``, or None: the
        last parked car passed in that lane is less than its ``finish`` behind, or the lane is
        not free over the change (the rest of it, for a change under way) and a clear distance."""
        cfg, world, cars = self.cfg, car.world, car.world.cars
        lane = here + (1 if home > here else -1)
        half = cars.length_m / 2.0
        near = cars.between(car.s - cfg.lookahead_m, car.s + half)
        passed = [
            near.start + int(k)
            for k in np.flatnonzero(cars.lane[near] == lane)
            if float(cars.s[near.start + int(k)]) + half <= car.s
        ]
        draws = Draws(
            *(sum(r) / 2.0 for r in (cfg.trigger_m, cfg.finish_m, cfg.change_time_s)), 0.5
        )
        if passed:
            draws = self.draws(world, passed[-1])
            if car.s - (float(cars.s[passed[-1]]) + half) < draws.finish_m:
                return None
        g_back, _ = self._gap(car, lane)
        if self._under_way(car, here, lane):
            u = self._progress(car, here, lane)
            length = self._path_length(draws, car.v, g_back, u) * (1.0 - u)
        else:
            length = self._change_length(draws, car.v, g_back, world.track.lane_width)
            if length is None:
                return None
        if not lane_clear(
            world, lane, car.s - cfg.clear_behind_m, car.s + length + cfg.clear_past_m
        ):
            return None
        return lane, draws, g_back

    def _change_length(
        self, draws: Draws, speed: float, gap: float, lane_width_m: float
    ) -> float | None:
        """Length of a lane change that starts now and has the car ~84 % across (``b(0.7)``) when
        its front reaches a car ``gap`` metres ahead; None if it would need more lateral
        acceleration than ``change_lat_accel_mps2``."""
        length = max(self.cfg.min_change_m, speed * draws.change_time_s)
        if math.isfinite(gap):
            length = min(length, max(self.cfg.min_change_m, (gap - 2.0) / 0.7))
            if length * 0.7 > gap - 2.0:
                return None
        if QUINTIC_PEAK * lane_width_m * speed**2 / length**2 > self.cfg.change_lat_accel_mps2:
            return None
        return length

    def _progress(self, car: _Car, here: int, target: int) -> float:
        """How far along its quintic a change from lane ``here`` to ``target`` is, read off how far
        across the car is: ``u`` with ``b(u)`` the share crossed (at least :attr:`U_MIN`)."""
        track = car.world.track
        c_from, c_to = _centre(track, here), _centre(track, target)
        crossed = min(1.0, max(0.0, (car.d - c_from) / (c_to - c_from)))
        return max(self.U_MIN, float(np.interp(crossed, _BLEND, _U)))

    def _path_length(self, draws: Draws, speed: float, gap: float, u: float) -> float:
        """The whole change's length [m] for a car ``u`` along it: as :meth:`_change_length` at its
        start, with a car ``gap`` metres ahead now (so the length stays the same as it goes)."""
        length = max(self.cfg.min_change_m, speed * draws.change_time_s)
        if math.isfinite(gap) and u < 0.7:
            length = min(length, max(self.cfg.min_change_m, (gap - 2.0) / (0.7 - u)))
        return length

    def _path(self, car: _Car, here: int, target: int, draws: Draws, gap: float) -> LaneChangePath:
        """The quintic from lane ``here``'s centre to ``target``'s, placed so that the car is on it
        where its offset says."""
        track = car.world.track
        u = self._progress(car, here, target)
        length = self._path_length(draws, car.v, gap, u)
        c_from, c_to = _centre(track, here), _centre(track, target)
        return LaneChangePath(car.s - u * length, length, c_from, c_to)

    def _speed_reference(self, decision: Decision, car: _Car, gap: float) -> tuple[float, float]:
        """``(v_ref [m/s], brake [m/s^2])``: the curve profile, capped outside ``keep`` so the car
        could still stop ``follow_margin_m`` behind the car ahead (``gap`` metres), and in
        ``follow`` the deceleration that stops it there (0: none)."""
        cfg = self.cfg
        v_ref, brake = self.speed_limits.at(car.world.track, car.s), 0.0
        room = gap - cfg.follow_margin_m
        if decision.state == FOLLOW:
            v_ref = min(v_ref, math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
            if car.v > 0.1:
                brake = car.v * car.v / (2.0 * max(room, 0.5))
        elif decision.state != KEEP and math.isfinite(gap):
            v_ref = min(v_ref, math.sqrt(2.0 * cfg.approach_brake_mps2 * max(room, 0.0)))
        return v_ref, brake


def _centre(track: Track, lane: int) -> float:
    """Lane ``lane``'s centre offset [m]: :meth:`~e2e_lite.simulation.geometry.Track.lane_center`
    in scalars (the same float, without numpy's overhead on one number)."""
    return (lane - (track.n_lanes - 1) / 2.0) * track.lane_width + 0.0


def _lane_of(track: Track, d: float) -> int:
    """The lane whose centre is nearest offset ``d`` [m]:
    :meth:`~e2e_lite.simulation.geometry.Track.lane_index` in scalars."""
    return min(max(math.floor(d / track.lane_width + track.n_lanes / 2.0), 0), track.n_lanes - 1)


def _started(before: Decision, now: Decision) -> str | None:
    """The manoeuvre a car started between two decisions, for the counters (None: none)."""
    if now.state == FOLLOW and before.state != FOLLOW:
        return "follow"
    if now.state != CHANGE or now.target == before.target:
        return None
    if not now.overtaking:
        return "return"
    return "left" if now.side > 0 else "right"


def expert_labels(
    obs: Observation,
    idx: list[int],
    sim: SimConfig | None = None,
    limits: SpeedLimits | None = None,
) -> np.ndarray:
    """What the expert (default settings) drives from cars ``idx``'s states: ``(len(idx), 5, 2)``
    points in each car's frame [m], as :meth:`Expert.trajectory_label`.

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
    return expert.trajectory_label(sub)
