"""The lockstep rollout: B cars in B independent worlds (:class:`~e2e_lite.simulation.world.Fleet`), one
policy decision per policy period, until each car has driven its share of the miles.

World ``i`` drives the tracks of its split (by default the test split) ``f + i, f + i + B, f + i + 2B, ...`` (``f =
first_track``; :func:`track_index`), each from its start (:func:`start_state`), and restarts
after a collision or a stall where :func:`restart_state` says; so every policy with the same
settings drives the same roads with the same parked cars, and no road twice. (Tracks are
procedural: there are as many as asked for. ``n_tracks`` cycles through a fixed few instead, for
tests and demos.) :func:`drive_shard` runs one shard's cars and returns what it measured
(:class:`ShardResult`); :func:`~e2e_lite.driving.metrics.merge_shards` sums shards into an
:class:`~e2e_lite.driving.metrics.EvalResult`. :func:`drive` drives one car in a hand-made world.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from ..config import check_range
from ..simulation.camera import Camera
from ..simulation.geometry import SPLITS
from ..simulation.policy import Actuation, Observation, Policy, car_rng, observe
from ..simulation.vehicle import H, V
from ..simulation.world import Fleet, World, WorldConfig
from .metrics import M_PER_MILE, ShardResult, add_info, speed_histogram
from .roads import ROAD_BLOCKS, WorldPool


@dataclass(frozen=True)
class EvalConfig:
    """Settings of a closed-loop evaluation.

    Attributes:
        miles: distance budget over all cars [mi].
        n_worlds: cars driven in lockstep (B).
        split: which tracks: ``"test"`` (the default: roads that no training and no choice
            has seen; every closed-loop number of the course drives them) or ``"val"`` (the
            roads the validation data, and so every choice made on it, comes from).
        n_tracks: ``None`` (default): every car drives tracks no other car and no earlier lap
            drove, so every mile is new road. An integer cycles through that many tracks
            (indices modulo ``n_tracks``), which repeats roads.
        first_track: index of the first track (car ``i``'s tracks are ``first_track + i + k B``);
            :func:`disjoint_runs` uses it to give repeated runs roads of their own.
        start_speed_mps: speed at every (re)spawn [m/s].
        start_s_m: arc length of the spawn point on a new track [m].
        end_margin_m: a car moves to its next track this far before the end [m].
        offcentre_m: off-centre distance that starts an off-centre episode [m].
        offcentre_grace_s: an off-centre episode longer than this is an intervention [s].
        intervention_cost_s: time charged per intervention in the autonomy metric [s].
        stall_speed_mps, stall_time_s: below this speed for this long is a stall [m/s, s].
        seed: seeds the start lanes (each car's own: :func:`start_lane`).
        block: which block of test tracks (:data:`ROAD_BLOCKS`): ``"open"`` (the default; every
            drive of the course) or ``"record-2"`` (sealed: the numbers of record alone; the
            spent ``"record"`` is named only to read the records that drove it). Track indices
            count from the block's first track; a drive never leaves its block.

    Where cars (re)start is one rule, :func:`start_state` and :func:`restart_state`, shared with
    the data collector. A restart is at ``start_speed_mps`` (20 m/s), below the roads' 25 m/s
    cruise speed, as a car rejoining a highway after a stop would be; the expert's data must show
    these states (chapter 04), the evaluation is not changed to avoid them.

    Why fresh roads by default: the collision counts' confidence intervals treat collisions as
    independent events, and a deterministic driver that drives a road again crashes at the same
    places, so cycled roads make clusters of collisions and intervals too narrow (lab note "The
    evaluator drove each road four times").
    """

    miles: float = 100.0
    n_worlds: int = 16
    split: str = "test"
    n_tracks: int | None = None
    first_track: int = 0
    start_speed_mps: float = 20.0
    start_s_m: float = 30.0
    end_margin_m: float = 120.0
    offcentre_m: float = 1.0
    offcentre_grace_s: float = 3.0
    intervention_cost_s: float = 6.0
    stall_speed_mps: float = 0.5
    stall_time_s: float = 20.0
    seed: int = 0
    block: str = "open"

    #: added after evaluations were stored: at its default it stays out of their keys
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = ("block",)

    def __post_init__(self) -> None:
        o = "EvalConfig"
        check_range(o, "miles", self.miles, 0.0, 1e6, lo_open=True)
        check_range(o, "n_worlds", self.n_worlds, 1, 4096, integer=True)
        if self.split not in SPLITS:
            raise ValueError(
                f"EvalConfig.split={self.split!r} is invalid: must be one of {sorted(SPLITS)}"
            )
        if self.n_tracks is not None:
            check_range(o, "n_tracks", self.n_tracks, 1, integer=True)
        check_range(o, "first_track", self.first_track, 0, integer=True)
        check_range(o, "start_speed_mps", self.start_speed_mps, 0.0, 100.0)
        check_range(o, "start_s_m", self.start_s_m, 0.0)
        check_range(o, "end_margin_m", self.end_margin_m, 0.0)
        check_range(o, "offcentre_m", self.offcentre_m, 0.0, lo_open=True)
        check_range(o, "offcentre_grace_s", self.offcentre_grace_s, 0.0)
        check_range(o, "intervention_cost_s", self.intervention_cost_s, 0.0)
        check_range(o, "stall_speed_mps", self.stall_speed_mps, 0.0)
        check_range(o, "stall_time_s", self.stall_time_s, 0.0, lo_open=True)
        check_range(o, "seed", self.seed, 0, integer=True)
        if self.block not in ROAD_BLOCKS:
            raise ValueError(
                f"EvalConfig.block={self.block!r} is invalid: must be one of {sorted(ROAD_BLOCKS)}"
            )
        if self.block != "open" and self.split != "test":
            raise ValueError(
                f"EvalConfig.block={self.block!r} is a block of test roads: split='test'"
            )


def drive(
    policy: Policy,
    world: World,
    world_cfg: WorldConfig,
    s_m: float,
    d_m: float,
    speed_mps: float,
    seconds: float,
    on_decision: Callable[[Observation, Actuation], None] | None = None,
) -> tuple[np.ndarray, list[tuple[str, int]]]:
    """Drive one car in a hand-made ``world`` from ``(s_m, d_m)`` at ``speed_mps`` (for figures
    and tests; :func:`evaluate` is the measurement).

    Returns:
        ``(states, contacts)``: the state ``(T + 1, 5)`` at every decision and the first contacts
        (the drive stops at a collision). ``on_decision(obs, act)`` is called every decision.
    """
    fleet = Fleet([world], world_cfg)
    fleet.place(0, s_m, d_m, speed_mps)
    policy.reset(1)
    cam_cfg = getattr(policy, "camera", None)
    camera = None if cam_cfg is None else Camera(cam_cfg)
    states = [fleet.state[0].copy()]
    contacts: list[tuple[str, int]] = []
    period = world_cfg.sim.policy_period_s
    for k in range(round(seconds / period)):
        frame = fleet.lane_frame()
        images = None
        if camera is not None:
            images = camera.render(world.track, world.cars, tuple(fleet.state[0, :3]), frame[0][0])[
                None
            ]
        obs = observe(fleet, k == 0, k * period, images, frame)
        act = policy.act(obs)
        if on_decision is not None:
            on_decision(obs, act)
        contacts = fleet.step(np.asarray(act.steer_rad), np.asarray(act.accel_mps2))[0]
        states.append(fleet.state[0].copy())
        if contacts:
            break
    return np.array(states), contacts


def start_state(world: World, lane: int, cfg: EvalConfig) -> tuple[float, float, float]:
    """Where a car starts on a new track: ``(s [m], d [m], speed [m/s])``.

    At ``cfg.start_s_m`` on the centre of ``lane`` (drawn by the caller), or of the next lane to
    the left (cyclically) when a parked car is within 10 m behind to 30 m ahead, at
    ``cfg.start_speed_mps``. The evaluator and the data collector both start cars here.
    """
    s0 = cfg.start_s_m
    for _ in range(world.track.n_lanes):
        if world.lane_free(s0, lane, 10.0, 30.0):
            break
        lane = (lane + 1) % world.track.n_lanes
    return s0, float(world.track.lane_center(lane)), cfg.start_speed_mps


def restart_state(
    world: World, s_obstacle: float, d_now: float, cfg: EvalConfig
) -> tuple[float, float, float]:
    """Where a car restarts after a collision, a stall or a take-over: ``(s, d, speed)``.

    :meth:`~e2e_lite.simulation.world.World.respawn_pose` (15 m past the obstacle, the nearest free lane),
    never past the line where the car moves on to its next track, at ``cfg.start_speed_mps``.
    """
    s_new, lane = world.respawn_pose(s_obstacle, d_now)
    # past the move-on line: the next decision moves the car to its next track before any physics
    s_new = min(s_new, world.track.length - cfg.end_margin_m + 1.0)
    return s_new, float(world.track.lane_center(lane)), cfg.start_speed_mps


def check_policy_rate(policy: Policy, world_cfg: WorldConfig) -> None:
    """Raise when ``policy`` (or the driver it wraps, ``policy.agent`` or ``policy.expert``) was
    built for other time steps than the world's: its trackers would be discretised at the wrong
    period."""
    while policy is not None:
        sim = getattr(policy, "sim", None)
        if sim is not None and sim != world_cfg.sim:
            raise ValueError(
                f"{type(policy).__name__} was built for {sim!r} but the world runs "
                f"{world_cfg.sim!r}: build it with sim=world_cfg.sim"
            )
        policy = getattr(policy, "agent", None) or getattr(policy, "expert", None)


def start_lane(cfg: EvalConfig, car: int, visit: int, n_lanes: int) -> int:
    """The lane car ``car`` starts in on its ``visit``-th track (before :func:`start_state` moves
    it off a parked car): drawn from the car's own generator, so no other car's draws and no
    shard change it."""
    return int(car_rng(cfg.seed, 7, car, visit).integers(0, n_lanes))


def track_index(cfg: EvalConfig, car: int, visit: int) -> int:
    """Index (in ``cfg.split``) of the ``visit``-th track car ``car`` drives (see :class:`EvalConfig`),
    inside the block ``cfg.block`` of test roads (:data:`ROAD_BLOCKS`; a drive that would leave
    its block raises ``ValueError``)."""
    index = cfg.first_track + car + visit * cfg.n_worlds
    index = index if cfg.n_tracks is None else index % cfg.n_tracks
    if cfg.split != "test":
        return index
    first, end = ROAD_BLOCKS[cfg.block]
    if first + index >= end:
        raise ValueError(
            f"test track {first + index} is past the {cfg.block!r} block of test roads "
            f"[{first}, {end}): the {'sealed ' if cfg.block != 'open' else ''}block ends there"
        )
    return first + index


def disjoint_runs(cfg: EvalConfig, world_cfg: WorldConfig, n: int) -> list[EvalConfig]:
    """``n`` evaluations that share ``cfg.miles`` equally and drive disjoint sets of tracks.

    Used to pool ``n`` drivers (training seeds of one recipe) over ``cfg.miles`` of road that is
    all distinct. Run ``k`` starts at track ``cfg.first_track + k * B * laps``, where ``laps``
    bounds how many tracks one car needs for its share (every restart puts a car 15 m further on,
    so a car never needs more road than its share). With ``cfg.n_tracks`` set, roads repeat
    anyway and the runs are only shifted.
    """
    check_range("disjoint_runs", "n", n, 1, integer=True)
    share = replace(cfg, miles=cfg.miles / n)
    usable_m = world_cfg.road.length_m - cfg.start_s_m - cfg.end_margin_m
    laps = int(np.ceil(share.miles * M_PER_MILE / cfg.n_worlds / usable_m)) + 1
    return [replace(share, first_track=cfg.first_track + k * cfg.n_worlds * laps) for k in range(n)]


class _Shard:
    """One shard's cars in lockstep: their worlds, odometers and clocks, and the named steps of
    a decision period (:func:`drive_shard` runs them in order)."""

    def __init__(
        self, policy: Policy, world_cfg: WorldConfig, cfg: EvalConfig, cars: np.ndarray
    ) -> None:
        self.policy, self.world_cfg, self.cfg, self.cars = policy, world_cfg, cfg, cars
        self.out = ShardResult()
        n = self.n = len(cars)
        self.pool = WorldPool(world_cfg, cfg.split, cfg.block)
        self.visit = np.zeros(n, dtype=np.int64)  # how many tracks each car has started
        self.fleet = Fleet(
            [self.pool.get(j, track_index(cfg, int(c), 0)) for j, c in enumerate(cars)], world_cfg
        )
        self.dt = world_cfg.sim.policy_period_s  # [s]
        self.share_m = cfg.miles * M_PER_MILE / cfg.n_worlds  # each car's share [m]
        self.odometer, self.sim_time = np.zeros(n), np.zeros(n)  # [m], [s]
        self.active = np.ones(n, dtype=bool)
        self.respawned = np.ones(n, dtype=bool)
        self.collided = np.zeros(n, dtype=bool)
        for i in range(n):
            self.spawn_new_track(i)
        seed_cars = getattr(policy, "seed_cars", None)
        if seed_cars is not None:
            seed_cars(cars)
        policy.reset(n)
        self.episode_t, self.offcentre_t, self.slow_t = np.zeros(n), np.zeros(n), np.zeros(n)
        self.offcentre_counted = np.zeros(n, dtype=bool)
        self.t_sim = 0.0
        track0 = self.fleet.worlds[0].track  # every track shares the cross-section
        self.lane_centers = np.asarray(track0.lane_center(np.arange(track0.n_lanes)))
        cam_cfg = getattr(policy, "camera", None)
        self.camera = None if cam_cfg is None else Camera(cam_cfg)
        self.images = (
            None if self.camera is None else np.empty((n, *self.camera.shape), dtype=np.uint8)
        )
        # used only if the camera augments: each car's jitter from its own generator
        self.cam_rngs = [car_rng(cfg.seed, 11, int(c)) for c in cars]
        self.lengths = np.array([w.track.length for w in self.fleet.worlds])  # current tracks [m]

    # ------------------------------------------------------------------ placing cars
    def spawn_new_track(self, i: int) -> None:
        w = self.fleet.worlds[i]
        lane = start_lane(self.cfg, int(self.cars[i]), int(self.visit[i]), w.track.n_lanes)
        self.fleet.place(i, *start_state(w, lane, self.cfg))

    def respawn(self, i: int, s_obstacle: float, d_now: float) -> None:
        self.fleet.place(i, *restart_state(self.fleet.worlds[i], s_obstacle, d_now, self.cfg))
        self.respawned[i] = True

    def position(self, i: int) -> tuple[float, float]:
        fleet = self.fleet
        s_i, d_i, _ = fleet.worlds[i].track.to_frenet_hint(
            fleet.state[i, 0], fleet.state[i, 1], int(fleet.seg[i])
        )
        return s_i, d_i

    # ------------------------------------------------------------------ a decision period
    def move_on(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Cars near their track's end move on to their next track; the lane frame after."""
        cfg, fleet = self.cfg, self.fleet
        frame = fleet.lane_frame()
        moving_on = np.flatnonzero(self.active & (frame[0] > self.lengths - cfg.end_margin_m))
        for i in moving_on.tolist():
            car = int(self.cars[i])
            if cfg.n_tracks is None:  # never driven again
                self.pool.release(i, track_index(cfg, car, int(self.visit[i])))
            self.visit[i] += 1
            fleet.worlds[i] = self.pool.get(i, track_index(cfg, car, int(self.visit[i])))
            self.lengths[i] = fleet.worlds[i].track.length
            self.spawn_new_track(i)
            self.respawned[i] = True
        return fleet.lane_frame() if len(moving_on) else frame

    def render(self, s: np.ndarray) -> None:
        """Every car's camera frame into ``self.images`` (a policy with a camera only)."""
        tick = time.perf_counter()
        if self.camera is not None:
            worlds = self.fleet.worlds
            self.camera.render_batch(
                [w.track for w in worlds],
                [w.cars for w in worlds],
                self.fleet.state[:, :3],
                s,
                rng=self.cam_rngs,
                out=self.images,
            )
            self.out.timing["frames"] += self.n
        self.out.timing["render"] += time.perf_counter() - tick

    def decide(self, frame: tuple[np.ndarray, ...], record_traces: bool) -> Actuation:
        """What the policy sees and answers (its info added up; traces kept if asked)."""
        out, fleet = self.out, self.fleet
        tick = time.perf_counter()
        obs = observe(
            fleet, self.respawned, self.t_sim, self.images, frame, self.collided, self.active
        )
        self.respawned[:] = self.collided[:] = False
        out.speed_hist += speed_histogram(fleet.state[self.active, V])
        act = self.policy.act(obs)
        if act.info:
            add_info(out.info, act.info)
        out.timing["policy"] += time.perf_counter() - tick
        if record_traces:
            for i in np.flatnonzero(self.active).tolist():
                key = "-".join(map(str, fleet.worlds[i].track.track_id))
                out.traces.setdefault(key, []).append(
                    [float(fleet.state[i, 0]), float(fleet.state[i, 1])]
                )
        return act

    def step(self, act: Actuation, d: np.ndarray) -> list:
        """Physics for one period, the odometers and clocks, and the off-centre episodes
        (autonomy metric only; ``d`` is the cars' offset before the step). Returns the contacts."""
        cfg, fleet, active, dt = self.cfg, self.fleet, self.active, self.dt
        tick = time.perf_counter()
        xy_before = fleet.state[:, :2].copy()
        contacts = fleet.step(np.asarray(act.steer_rad), np.asarray(act.accel_mps2), active)
        self.out.timing["physics"] += time.perf_counter() - tick
        self.odometer += np.where(active, np.hypot(*(fleet.state[:, :2] - xy_before).T), 0.0)
        dt_active = np.where(active, dt, 0.0)
        self.sim_time += dt_active
        self.episode_t += dt_active
        self.t_sim += dt
        off = np.min(np.abs(d[:, None] - self.lane_centers[None, :]), axis=1) > cfg.offcentre_m
        self.offcentre_t = np.where(active & off, self.offcentre_t + dt, 0.0)
        new_int = (self.offcentre_t > cfg.offcentre_grace_s) & ~self.offcentre_counted
        self.out.interventions += int(new_int.sum())
        self.offcentre_counted = (self.offcentre_counted | new_int) & (self.offcentre_t > 0)
        return contacts

    def count_collisions(self, contacts: list) -> None:
        """One event per car per period, then the car is put back past the obstacle."""
        fleet, out = self.fleet, self.out
        for i, c in enumerate(contacts):
            if not c:
                continue
            w = fleet.worlds[i]
            s_i, d_i = self.position(i)
            car_idx = next((j for kind, j in c if kind == "car"), None)
            s_obst = (
                s_i if car_idx is None else max(s_i, float(w.cars.s[car_idx]) + w.cars.length_m / 2)
            )
            out.events.append(
                {
                    "world": int(self.cars[i]),
                    "track": list(w.track.track_id),
                    "kind": "rail" if car_idx is None else "car",
                    "car": car_idx,
                    "s_m": round(s_i, 2),
                    "d_m": round(d_i, 3),
                    "x_m": round(float(fleet.state[i, 0]), 2),
                    "y_m": round(float(fleet.state[i, 1]), 2),
                    "heading_rad": round(float(fleet.state[i, H]), 4),
                    "speed_mps": round(float(fleet.state[i, V]), 2),
                    "time_s": round(float(self.sim_time[i]), 2),
                    "miles": round(float(self.odometer[i] / M_PER_MILE), 4),
                }
            )
            self.collided[i] = True
            out.ttc.append(float(self.episode_t[i]))
            self.episode_t[i] = 0.0
            out.interventions += 1
            self.respawn(i, s_obst, d_i)

    def restart_stalled_and_taken_over(self, act: Actuation, contacts: list) -> None:
        """A car slow for too long is a stall, put back; a car the policy asks to have taken over
        (the data collector's restarts, not collisions) is put back the same way."""
        slow = self.active & (self.fleet.state[:, V] < self.cfg.stall_speed_mps)
        self.slow_t = np.where(slow, self.slow_t + self.dt, 0.0)
        for i in np.flatnonzero(self.slow_t > self.cfg.stall_time_s).tolist():
            self.out.stalls += 1
            self.out.interventions += 1
            self.slow_t[i] = 0.0
            self.respawn(i, *self.position(i))
        if act.restart is not None:
            for i in np.flatnonzero(act.restart & self.active).tolist():
                if not contacts[i] and not self.respawned[i]:
                    self.episode_t[i] = 0.0
                    self.respawn(i, *self.position(i))

    def result(self) -> ShardResult:
        """What the shard measured, once every car is done."""
        out = self.out
        out.car_miles_m, out.car_sim_s = self.odometer, self.sim_time
        out.censored = int(np.count_nonzero(self.episode_t > 0))
        out.tracks = int((self.visit + 1).sum())
        return out


def drive_shard(
    policy: Policy,
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    cars: np.ndarray,
    advance: Callable[[float], None] | None = None,
    record_traces: bool = False,
    stop_when: Callable[[], bool | np.ndarray] | None = None,
) -> ShardResult:
    """Drive the cars ``cars`` (their indices among ``cfg.n_worlds``) to their shares.

    Every random choice is the car's own (:func:`start_lane`, the camera's jitter, the policy's
    ``seed_cars``), so a car drives the same in any shard of any size. ``advance`` is told the
    miles driven since its last call (a progress bar; None: nobody is told). ``stop_when`` is
    called after every decision: True stops every car, an array of bools the cars it marks."""
    shard = _Shard(policy, world_cfg, cfg, cars)
    reported = 0.0
    while shard.active.any():
        frame = shard.move_on()
        shard.render(frame[0])
        act = shard.decide(frame, record_traces)
        contacts = shard.step(act, frame[1])
        shard.count_collisions(contacts)
        shard.restart_stalled_and_taken_over(act, contacts)
        shard.active &= shard.odometer < shard.share_m
        if stop_when is not None:
            shard.active &= ~np.broadcast_to(np.asarray(stop_when(), dtype=bool), (shard.n,))
        done = float(np.minimum(shard.odometer, shard.share_m).sum() / M_PER_MILE)
        if advance is not None:
            advance(max(0.0, done - reported))
        reported = max(reported, done)
    return shard.result()
