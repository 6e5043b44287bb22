"""Closed-loop evaluation: drive any policy on unseen tracks and count collisions per 100 miles.

The evaluator drives B cars in B independent worlds in lockstep (:class:`~e2e_lite.world.Fleet`),
asking the policy once per policy period for a batch of actuator commands. World ``i`` drives the
validation tracks ``f + i, f + i + B, f + i + 2B, ...`` (``f = first_track``), each from its start,
until it has driven its share (``miles / B``) of the budget; so every policy with the same settings
drives the same roads with the same parked cars, and no road twice. (Tracks are procedural: there
are as many as asked for. ``n_tracks`` cycles through a fixed few instead, for tests and demos.)

Metrics (see :class:`EvalResult`):

* collisions per 100 miles, with an exact (Garwood) 95 % Poisson confidence interval;
* time before a collision (seed 002): an *episode* starts at a (re)spawn and ends at the next
  collision; the mean length of the episodes that ended in a collision. Episodes cut off by the
  budget are censored and only counted in ``episodes_censored``;
* autonomy % (seed 003): ``(1 - interventions * 6 s / elapsed s) * 100``, floored at 0. An
  intervention is a collision (the re-spawn is the human taking over) or an *off-centre episode*:
  the car more than 1 m from every lane centre for longer than ``offcentre_grace_s`` (3 s, longer
  than a normal lane change takes). We only count off-centre interventions; we do not move the car,
  so the intervention rule cannot change the collision count.
* a *stall* (speed under 0.5 m/s for 20 s) is re-spawned and reported, so a policy that stops cannot
  hang the evaluation.
"""

from __future__ import annotations

import atexit
import contextlib
import pickle
import queue
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Protocol, runtime_checkable

import numpy as np
from scipy.stats import binomtest, chi2

from .camera import Camera
from .config import check_range, tqdm
from .geometry import SPLITS
from .vehicle import H, V
from .world import Fleet, World, WorldConfig, make_world

M_PER_MILE = 1609.344
MPS_TO_MPH = 3600.0 / M_PER_MILE


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

    @property
    def speed(self) -> np.ndarray:
        """Speed of each car [m/s], ``(B,)``."""
        return self.state[:, V]


@dataclass
class Actuation:
    """A batch of actuator commands: road-wheel angle [rad] and acceleration [m/s^2], each ``(B,)``.

    ``restart`` (optional, ``(B,)`` bool) asks the evaluator to take car i over and re-place it
    exactly as after a collision (:func:`restart_state`), without counting a collision: the data
    collector's way of showing the expert the states a learned driver restarts from.
    """

    steer_rad: np.ndarray
    accel_mps2: np.ndarray
    restart: np.ndarray | None = None


@runtime_checkable
class Policy(Protocol):
    """Anything that drives: ``reset`` once per evaluation, then ``act`` every policy period.

    A policy that sees through the front camera also has an attribute ``camera`` holding a
    :class:`~e2e_lite.camera.CameraConfig`; the evaluator then renders one frame per car every
    decision into ``obs.images`` (B, H, W, 3) RGB uint8. That buffer is reused: copy a frame to
    keep it past the next decision. A policy without the attribute (or with ``None``) gets no
    images and costs no rendering.
    """

    def reset(self, n_worlds: int) -> None:
        """Forget everything; ``n_worlds`` cars are about to be driven."""

    def act(self, obs: Observation) -> Actuation:
        """Commands for every car in the batch."""


@dataclass(frozen=True)
class EvalConfig:
    """Settings of a closed-loop evaluation.

    Attributes:
        miles: distance budget over all cars [mi].
        n_worlds: cars driven in lockstep (B).
        split: which tracks: ``"val"`` (unseen by training) or ``"test"``.
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
        seed: seeds the start lanes.

    Where cars (re)start is one rule, :func:`start_state` and :func:`restart_state`, shared with
    the data collector. A restart is at ``start_speed_mps`` (20 m/s), below the roads' 25 m/s
    cruise speed, as a car rejoining a highway after a stop would be; the expert's data must show
    these states (chapter 04), the evaluation is not changed to avoid them.

    Why fresh roads by default: the collision counts' confidence intervals treat collisions as
    independent events. Cycling 64 cars through 16 tracks drove each road 4 times from the same
    start, and a deterministic driver crashed at the same places each time: in chapter 10 (code
    8f946b2) the GMM's 177 collisions over 500 mi were 65 distinct places, the L2 row's 86 were 32.
    Collisions came in clusters of 2.7, so the intervals were about sqrt(2.7) = 1.6 times too
    narrow and the tests' p-values far too small.
    """

    miles: float = 100.0
    n_worlds: int = 16
    split: str = "val"
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


@dataclass
class EvalResult:
    """What a closed-loop evaluation measured. Distances in miles, times in seconds.

    ``timing_s`` splits the wall time of the loop, summed over shards: ``render`` (camera
    frames), ``policy`` (the driver's ``act``: the network and the tracker), ``physics``
    (bicycle and pymunk steps); ``frames`` counts the frames rendered; ``startup`` is the
    wall-clock time shard processes took to start (an interpreter and the imports each).
    ``speed_hist[k]`` counts the decisions taken at a speed in ``[k, k + 1)`` m/s (the last bin
    holds everything faster): the states the driver visited (chapter 04 compares them with the
    data's).
    """

    miles: float
    collisions: int
    car_collisions: int
    rail_collisions: int
    collisions_per_100mi: float
    ci95_per_100mi: tuple[float, float]
    mean_speed_mph: float
    time_to_collision_s: float | None
    episodes_censored: int
    miles_per_collision: float | None
    autonomy_pct: float
    interventions: int
    stalls: int
    sim_time_s: float
    wall_time_s: float
    sim_miles_per_wall_s: float
    tracks_driven: int
    events: list[dict[str, Any]] = field(default_factory=list)
    timing_s: dict[str, float] = field(default_factory=dict)
    traces: dict[str, list[list[float]]] = field(default_factory=dict)
    speed_hist: list[int] = field(default_factory=list)

    def to_dict(self, with_events: bool = True) -> dict[str, Any]:
        """JSON-ready dict (traces left out; events optional)."""
        out = asdict(self)
        out.pop("traces")
        if not with_events:
            out.pop("events")
        return out

    def summary(self) -> str:
        """One readable line."""
        lo, hi = self.ci95_per_100mi
        ttc = "n/a" if self.time_to_collision_s is None else f"{self.time_to_collision_s:.1f} s"
        return (
            f"{self.miles:.1f} mi, {self.collisions} collisions ({self.car_collisions} car, "
            f"{self.rail_collisions} rail) = {self.collisions_per_100mi:.1f} per 100 mi "
            f"[95% CI {lo:.1f}-{hi:.1f}], {self.mean_speed_mph:.1f} mph, time to collision {ttc}, "
            f"autonomy {self.autonomy_pct:.1f}%"
        )


def miles_text(miles: float) -> str:
    """``"1 mile"``, ``"0.5 miles"``, ``"500 miles"``: a distance for prose."""
    return f"{miles:g} {'mile' if miles == 1 else 'miles'}"


def poisson_ci(count: int, exposure: float, level: float = 0.95) -> tuple[float, float]:
    """Exact (Garwood) confidence interval of a Poisson rate: ``count`` events over ``exposure``.

    lower = chi2.ppf(a/2, 2k) / 2 / exposure,  upper = chi2.ppf(1 - a/2, 2k + 2) / 2 / exposure,
    with a = 1 - level. For k = 0 the lower bound is 0 and the upper is -ln(a/2) / exposure
    (3.69 per 100 miles over 100 miles at 95 %).
    """
    check_range("poisson_ci", "count", count, 0, integer=True)
    check_range("poisson_ci", "exposure", exposure, 0.0, lo_open=True)
    check_range("poisson_ci", "level", level, 0.0, 1.0, lo_open=True, hi_open=True)
    a = 1.0 - level
    lo = 0.0 if count == 0 else chi2.ppf(a / 2, 2 * count) / 2.0
    hi = chi2.ppf(1 - a / 2, 2 * count + 2) / 2.0
    return float(lo / exposure), float(hi / exposure)


def result_dict(r: EvalResult | dict[str, Any]) -> dict[str, Any]:
    """An ``EvalResult`` as its ``to_dict()`` (without events); a dict as it is."""
    return r.to_dict(with_events=False) if isinstance(r, EvalResult) else r


def result_events(r: EvalResult | dict[str, Any]) -> list[dict[str, Any]]:
    """A result's collision events (an ``EvalResult``'s, or a stored or pooled dict's)."""
    return r.events if isinstance(r, EvalResult) else r.get("events", [])


def results_table(
    rows: Sequence[tuple[str, EvalResult | dict[str, Any]]],
    extra: Sequence[tuple[str, Sequence[str]]] = (),
) -> str:
    """A markdown table of closed-loop results (``EvalResult`` or its ``to_dict()``), one row per
    ``(driver, result)``: miles, collisions (car / rail), per 100 mi with the 95 % interval, mph,
    time to collision, autonomy; then ``extra`` columns, each ``(header, one cell per row)``."""
    for header, cells in extra:
        if len(cells) != len(rows):
            raise ValueError(f"column {header!r} has {len(cells)} cells for {len(rows)} rows")
    lines = [
        "| driver | miles | collisions (car / rail) | per 100 mi [95% CI] | mph | time to collision "
        "| autonomy |" + "".join(f" {h} |" for h, _ in extra),
        "|---|---:|---:|---|---:|---:|---:|" + "---:|" * len(extra),
    ]
    for k, (name, result) in enumerate(rows):
        r = result_dict(result)
        lo, hi = r["ci95_per_100mi"]
        ttc = "-" if r["time_to_collision_s"] is None else f"{r['time_to_collision_s']:.1f} s"
        lines.append(
            f"| {name} | {r['miles']:.3g} | {r['collisions']} ({r['car_collisions']} / "
            f"{r['rail_collisions']}) | {r['collisions_per_100mi']:.1f} [{lo:.1f}-{hi:.1f}] | "
            f"{r['mean_speed_mph']:.1f} | {ttc} | {r['autonomy_pct']:.1f}% |"
            + "".join(f" {cells[k]} |" for _, cells in extra)
        )
    return "\n".join(lines)


#: How :func:`collision_kinds` sorts a collision.
COLLISION_KINDS = ("rail", "parked car in its lane, car centred", "parked car, off centre")


def collision_kinds(
    result: EvalResult | dict[str, Any], world_cfg: WorldConfig, split: str = "val"
) -> dict[str, int]:
    """Count a result's collisions by kind (:data:`COLLISION_KINDS`).

    A car collision is *in its lane, car centred* when the parked car's centre is within a third
    of a lane width of the ego's lateral position and the ego is within 0.8 m of a lane centre:
    the driver stayed in a lane with a parked car ahead and neither left it nor stopped. Every
    other car collision happened off centre (changing lanes, or clipping a car beside). The
    parked car's position comes from the track the event names (rebuilt from its seed).
    """
    counts = dict.fromkeys(COLLISION_KINDS, 0)
    worlds: dict[int, World] = {}
    for e in result_events(result):
        if e["kind"] == "rail":
            counts["rail"] += 1
            continue
        index = int(e["track"][1])
        if index not in worlds:
            worlds[index] = make_world(world_cfg, split, index)
        track, d_ego = worlds[index].track, float(e["d_m"])
        d_car = float(worlds[index].cars.d[e["car"]])
        centres = track.lane_center(np.arange(track.n_lanes))  # (every track: one cross-section)
        centred = float(np.min(np.abs(d_ego - centres))) <= 0.8
        in_lane = abs(d_ego - d_car) < track.lane_width / 3
        counts[COLLISION_KINDS[1] if centred and in_lane else COLLISION_KINDS[2]] += 1
    return counts


def pool_results(
    results: Sequence[EvalResult | dict[str, Any]], intervention_cost_s: float = 6.0
) -> dict[str, Any]:
    """One result from several evaluations of the same kind of driver (e.g. one per training
    seed), as if they were one drive: counts, miles and times summed, rates, the interval, mean
    speed, autonomy (``intervention_cost_s`` per intervention, as :class:`EvalConfig`) and the
    time to collision recomputed from the sums; ``events``: every input's, in input order (a
    car's ``world`` number is its index in its own evaluation); ``seeds`` keeps each input (as
    :func:`result_dict`, without events)."""
    events = [e for r in results for e in result_events(r)]
    rs = [{k: v for k, v in result_dict(r).items() if k != "events"} for r in results]
    if not rs:
        raise ValueError("pool_results needs at least one result")
    total = {
        k: sum(r[k] for r in rs)
        for k in (
            "miles",
            "collisions",
            "car_collisions",
            "rail_collisions",
            "episodes_censored",
            "interventions",
            "stalls",
            "sim_time_s",
            "wall_time_s",
            "tracks_driven",
        )
    }
    n, miles, sim_s = total["collisions"], total["miles"], total["sim_time_s"]
    # the mean episode length: each seed's mean weighted by its count of ended episodes
    ttc = [(r["time_to_collision_s"], r["collisions"]) for r in rs if r["collisions"]]
    hist = [r.get("speed_hist") or [] for r in rs]
    return {
        **total,
        "collisions_per_100mi": 100.0 * n / miles,
        "ci95_per_100mi": poisson_ci(n, miles / 100.0),
        "mean_speed_mph": sum(r["mean_speed_mph"] * r["sim_time_s"] for r in rs) / sim_s,
        "time_to_collision_s": sum(t * k for t, k in ttc) / n if n else None,
        "miles_per_collision": miles / n if n else None,
        "autonomy_pct": max(0.0, 1.0 - total["interventions"] * intervention_cost_s / sim_s) * 100,
        "sim_miles_per_wall_s": miles / max(total["wall_time_s"], 1e-9),
        "timing_s": {
            k: sum(r.get("timing_s", {}).get(k, 0.0) for r in rs) for k in rs[0].get("timing_s", {})
        },
        "speed_hist": [int(sum(c)) for c in zip(*hist)] if all(hist) else [],
        "events": events,
        "seeds": rs,
    }


def compare_rates(
    a: EvalResult | dict[str, Any], b: EvalResult | dict[str, Any], level: float = 0.95
) -> dict[str, Any]:
    """Is driver a's collision rate different from b's beyond chance?

    The exact conditional test of two Poisson rates: given ``n = k_a + k_b`` collisions in
    ``m_a`` and ``m_b`` miles, ``k_a ~ Binomial(n, m_a / (m_a + m_b))`` when the rates are equal;
    the two-sided p-value of that binomial test.

    Returns:
        ``{"ratio": rate_a / rate_b (None when b has none), "p_value", "different": p < 1 - level,
        "verdict": one readable line}``.
    """
    ra, rb = result_dict(a), result_dict(b)
    ka, kb, ma, mb = ra["collisions"], rb["collisions"], ra["miles"], rb["miles"]
    n = ka + kb
    p = 1.0 if n == 0 else float(binomtest(ka, n, ma / (ma + mb)).pvalue)
    rate_a, rate_b = 100.0 * ka / ma, 100.0 * kb / mb
    different = p < 1.0 - level
    if not different:
        verdict = (
            f"{rate_a:.1f} vs {rate_b:.1f} per 100 mi: no difference beyond chance (p = {p:.2f})"
        )
    else:
        word = "fewer" if rate_a < rate_b else "more"
        verdict = f"{rate_a:.1f} vs {rate_b:.1f} per 100 mi: {word} collisions beyond chance (p = {p:.2g})"
    return {
        "ratio": None if kb == 0 else rate_a / rate_b,
        "p_value": p,
        "different": different,
        "verdict": verdict,
    }


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2 * np.pi) - np.pi


def observe(
    fleet: Fleet,
    respawned: np.ndarray | bool = False,
    time_s: float = 0.0,
    images: np.ndarray | None = None,
    frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> Observation:
    """The observation of a fleet's cars now (``frame``: a lane frame already computed)."""
    s, d, road_h, kappa = fleet.lane_frame() if frame is None else frame
    n = len(fleet)
    return Observation(
        images=images,
        state=fleet.state.copy(),
        s=s,
        d=d,
        heading_error=_wrap(fleet.state[:, H] - road_h),
        curvature=kappa,
        lane=np.atleast_1d(fleet.worlds[0].track.lane_index(d)),
        respawned=np.broadcast_to(np.asarray(respawned, dtype=bool), (n,)).copy(),
        time_s=time_s,
        worlds=list(fleet.worlds),
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


SPEED_BINS = 41  # 1 m/s bins of EvalResult.speed_hist: 0-1, ..., 39-40, >= 40 m/s


def speed_histogram(speeds_mps: np.ndarray) -> np.ndarray:
    """Counts of ``speeds_mps`` in :data:`SPEED_BINS` bins of 1 m/s (the last one open), int64."""
    bins = np.clip(np.asarray(speeds_mps, dtype=np.float64), 0.0, SPEED_BINS - 1).astype(np.int64)
    return np.bincount(bins, minlength=SPEED_BINS)


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

    :meth:`~e2e_lite.world.World.respawn_pose` (15 m past the obstacle, the nearest free lane),
    never past the line where the car moves on to its next track, at ``cfg.start_speed_mps``.
    """
    s_new, lane = world.respawn_pose(s_obstacle, d_now)
    # past the move-on line: the next decision moves the car to its next track before any physics
    s_new = min(s_new, world.track.length - cfg.end_margin_m + 1.0)
    return s_new, float(world.track.lane_center(lane)), cfg.start_speed_mps


class _WorldPool:
    """Worlds of the evaluation split: a road and its cars are made once per track, and every car
    gets its own pymunk world of it (two cars on one track must not share an ego body)."""

    def __init__(self, world_cfg: WorldConfig, split: str) -> None:
        self.world_cfg, self.split = world_cfg, split
        self._roads: dict[int, World] = {}
        self._worlds: dict[tuple[int, int], World] = {}

    def release(self, car: int, index: int) -> None:
        """Forget car ``car``'s world of track ``index`` (it moved on and never comes back)."""
        self._worlds.pop((car, index), None)
        if not any(k[1] == index for k in self._worlds):
            self._roads.pop(index, None)

    def get(self, car: int, index: int) -> World:
        if (car, index) not in self._worlds:
            if index not in self._roads:
                self._roads[index] = make_world(self.world_cfg, self.split, index)
            road = self._roads[index]
            self._worlds[(car, index)] = (
                road
                if not any(k[1] == index for k in self._worlds)
                else World(road.track, road.cars, self.world_cfg.vehicle)
            )
        return self._worlds[(car, index)]


class _Shard:
    """What one thread of :func:`evaluate` measured on its cars (summed by :func:`_merge`)."""

    def __init__(self) -> None:
        self.miles_m = 0.0
        self.sim_s = 0.0
        self.ttc: list[float] = []
        self.censored = 0
        self.interventions = 0
        self.stalls = 0
        self.tracks = 0
        self.speed_hist = np.zeros(SPEED_BINS, dtype=np.int64)
        self.events: list[dict[str, Any]] = []
        self.traces: dict[str, list[list[float]]] = {}
        # seconds per part (summed over shards); "startup": the wall-clock time the shard
        # workers took to start (process shards only)
        self.timing = {"render": 0.0, "policy": 0.0, "physics": 0.0, "frames": 0.0, "startup": 0.0}


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


def evaluate(
    policy: Policy,
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    *,
    progress: bool = True,
    desc: str = "closed loop",
    record_traces: bool = False,
    stop_when: Callable[[], bool] | None = None,
    workers: int | None = None,
    parallel: str = "auto",
) -> EvalResult:
    """Drive ``policy`` closed-loop until ``cfg.miles`` are driven; return the metrics.

    Car ``i`` drives tracks ``f + i, f + i + B, ...`` (:func:`track_index`) until it has driven
    ``miles / B``. With
    ``workers > 1`` the cars are split into that many shards, each driven with its own copy of
    the policy: a policy that can be split has a ``fork(k)`` method returning ``k`` independent
    copies. The shards run in worker processes (interpreters of their own, ``python -m
    e2e_lite.shard_worker``, the job pickled to them; started once and kept for the next
    evaluations, see :func:`close_shard_workers`) when the policy declares
    ``forks_in_processes`` (the network agents on the CPU and the safety module), else in threads
    (the network's forward pass releases the GIL, so one shard renders and steps physics while
    the other runs convolutions, but their Python still takes turns). Either way the torch threads
    are shared out (one core per shard on two cores) and the results are the same. Each shard
    draws its cars' start lanes from its own generator (shard 0's is the one a single thread
    uses), so ``workers`` is part of the settings: compare drivers evaluated with the same value
    (chapter 10 uses 2 for every driver).

    Args:
        policy: the driver (see :class:`Policy`).
        world_cfg: roads, traffic, car and time steps.
        cfg: the evaluation settings.
        progress: show a progress bar of miles driven.
        desc: the progress bar's label.
        record_traces: keep every car's rear-axle path per track (for top-down figures), in
            ``result.traces["<split>-<track>"] = [[x, y], ...]``.
        stop_when: called after every decision; the drive ends early when it returns True (the
            data collector stops at a sample count this way). The metrics cover what was driven.
        workers: shards of cars (threads or processes, see ``parallel``), default 1; a policy
            without ``fork``, or a call with ``stop_when``, always runs in one. The network then sees batches of
            ``B / workers`` frames on ``1 / workers`` of the cores.
        parallel: how shards run: ``"auto"`` (processes where possible, see above),
            ``"threads"`` or ``"processes"`` (the policy must pickle, and its forks keep nothing
            the caller reads afterwards unless they have ``shard_report``/``absorb_report``).
    """
    t_wall = time.perf_counter()
    n = cfg.n_worlds
    check_policy_rate(policy, world_cfg)
    workers = 1 if workers is None else workers
    check_range("evaluate", "workers", workers, 1, integer=True)
    if parallel not in ("auto", "threads", "processes"):
        raise ValueError(f"parallel must be 'auto', 'threads' or 'processes', not {parallel!r}")
    if stop_when is not None or not hasattr(policy, "fork"):
        workers = 1
    workers = min(workers, n)
    bar = tqdm(
        total=round(cfg.miles, 2),
        desc=desc,
        unit="mi",
        disable=not progress,
        leave=False,
        mininterval=0.5,
        bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} mi [{elapsed}<{remaining}]",
    )
    lock = threading.Lock()

    def advance(miles: float) -> None:
        with lock:  # (the shards' rounded sums may overshoot the total by a hair)
            bar.update(max(0.0, min(miles, bar.total - bar.n)))

    cars = np.array_split(np.arange(n), workers)
    if workers == 1:
        shards = [_drive(policy, world_cfg, cfg, cars[0], 0, advance, record_traces, stop_when)]
    else:
        policies = policy.fork(workers)  # type: ignore[attr-defined]
        jobs = [
            (p, world_cfg, cfg, c, k, record_traces) for k, (p, c) in enumerate(zip(policies, cars))
        ]
        if parallel == "auto":
            parallel = "processes" if _processes_ok(policy) else "threads"
        if parallel == "processes":
            shards = _in_processes(jobs, advance)
        else:
            shards = _in_threads(jobs, advance)
    bar.close()
    return _merge(shards, cfg, time.perf_counter() - t_wall)


def _processes_ok(policy: Policy) -> bool:
    """Shards may run in worker processes for a policy whose forks keep nothing the caller reads
    afterwards (``forks_in_processes``) and that a fresh interpreter can unpickle (its class is
    not defined in a script run as ``__main__``)."""
    return bool(getattr(policy, "forks_in_processes", False)) and (
        type(policy).__module__ != "__main__"
    )


def _in_threads(jobs: list[tuple], advance: Callable[[float], None]) -> list[_Shard]:
    """Drive each job's shard in its own thread (torch on ``1 / workers`` of the cores each)."""
    torch = sys.modules.get("torch")  # loaded when the policy is a network
    threads = None if torch is None else torch.get_num_threads()
    interval = sys.getswitchinterval()
    try:
        if torch is not None:  # one core per shard instead of every shard on every core
            torch.set_num_threads(max(1, threads // len(jobs)))
        sys.setswitchinterval(5e-4)  # hand the GIL over soon after a forward pass ends
        with ThreadPoolExecutor(len(jobs)) as pool:
            futures = [pool.submit(_drive_job, job, advance) for job in jobs]
            return [f.result() for f in futures]
    finally:
        sys.setswitchinterval(interval)
        if torch is not None:
            torch.set_num_threads(threads)


def _drive_job(job: tuple, advance: Callable[[float], None]) -> _Shard:
    """Drive one shard's job ``(policy, world_cfg, cfg, cars, shard, record_traces)``."""
    policy, world_cfg, cfg, cars, shard, record_traces = job
    return _drive(policy, world_cfg, cfg, cars, shard, advance, record_traces, None)


def _send(stream: Any, message: Any) -> None:
    """One length-prefixed pickle on a binary stream (the shard workers' protocol)."""
    blob = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(len(blob).to_bytes(8, "little") + blob)
    stream.flush()


def _receive(stream: Any) -> Any:
    """The next message of :func:`_send` (EOFError when the writer is gone)."""
    head = stream.read(8)
    size = int.from_bytes(head, "little") if len(head) == 8 else -1
    blob = stream.read(size) if size >= 0 else b""
    if size < 0 or len(blob) < size:
        raise EOFError
    return pickle.loads(blob)


def shard_worker(inbox: Any, outbox: Any) -> None:
    """Body of a shard process (``python -m e2e_lite.shard_worker``): for each job until its
    input ends, read ``(sys.path, torch threads, job)``, drive the shard, send ``("ready", None)``,
    progress ``("miles", m)`` now and then and finally ``("ok", (shard, report))`` or ``("error",
    traceback)``. A worker serves its parent's evaluations until :func:`close_shard_workers`."""
    while True:
        try:
            sys.path[:] = _receive(inbox)  # where the parent found the policy's classes
        except EOFError:  # the parent closed the pool, or is gone
            return
        try:
            torch_threads, job = _receive(inbox)
            if torch_threads > 0:  # the parent ran torch (0: it had not imported it)
                import torch

                torch.set_num_threads(torch_threads)
            _send(outbox, ("ready", None))
            last = [time.perf_counter(), 0.0]

            def advance(m: float, last: list[float] = last) -> None:
                last[1] += m
                if time.perf_counter() - last[0] > 0.25:
                    _send(outbox, ("miles", last[1]))
                    last[:] = [time.perf_counter(), 0.0]

            shard = _drive_job(job, advance)
            report = getattr(job[0], "shard_report", None)
            _send(outbox, ("miles", last[1]))
            _send(outbox, ("ok", (shard, None if report is None else report())))
            del job, shard  # the next job's policy replaces this one's
        except BaseException:  # everything goes back to the parent, which then ends the pool
            _send(outbox, ("error", traceback.format_exc()))
            return


class _Workers:
    """Shard processes kept alive between evaluations: an interpreter and the imports (about 4 s
    here) are paid once per process instead of once per evaluation. Messages of every worker go
    to one queue as ``(k, message)``; an evaluation that fails or is interrupted ends them all
    (the next one starts fresh), so no message of an old job can reach a new one."""

    def __init__(self, n: int) -> None:
        self.messages: queue.Queue = queue.Queue()
        self.procs = []
        for k in range(n):
            proc = subprocess.Popen(
                [sys.executable, "-m", "e2e_lite.shard_worker"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
            self.procs.append(proc)
            threading.Thread(target=self._listen, args=(k, proc.stdout), daemon=True).start()

    def _listen(self, k: int, stream: Any) -> None:
        try:
            while True:
                self.messages.put((k, _receive(stream)))
        except (EOFError, OSError, ValueError):
            self.messages.put((k, ("gone", None)))

    def alive(self) -> bool:
        return all(proc.poll() is None for proc in self.procs)

    def close(self) -> None:
        """End every worker (closing its input ends it; a stuck one is killed) and wait."""
        for proc in self.procs:
            with contextlib.suppress(OSError, ValueError):
                proc.stdin.close()
        for proc in self.procs:
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            proc.stdout.close()


_WORKERS: dict[int, _Workers] = {}
_WORKERS_LOCK = threading.Lock()


def close_shard_workers() -> None:
    """End the shard processes kept for later evaluations (also done when Python exits)."""
    with _WORKERS_LOCK:
        while _WORKERS:
            _WORKERS.popitem()[1].close()


atexit.register(close_shard_workers)


def _in_processes(jobs: list[tuple], advance: Callable[[float], None]) -> list[_Shard]:
    """Drive each job's shard in a worker process: no shared GIL, so one shard's rendering and
    physics never wait on the other's Python, and no ``fork`` of a process whose torch threads are
    running (that can deadlock the child). The workers are fresh interpreters (``python -m
    e2e_lite.shard_worker``), started at the first evaluation that needs that many and kept for
    the next ones (:func:`close_shard_workers` ends them). Each gets its job pickled (policy,
    model included), sends its :class:`_Shard` back and, for a policy with ``shard_report()``,
    that report, which the parent's copy of the fork takes in with ``absorb_report(report)`` (how
    the safety module's counters come home)."""
    torch = sys.modules.get("torch")
    per_shard = 0 if torch is None else max(1, torch.get_num_threads() // len(jobs))
    started, ready, startup_s = time.perf_counter(), 0, 0.0
    with _WORKERS_LOCK:  # one evaluation at a time uses a pool
        workers = _WORKERS.pop(len(jobs), None)
    if workers is None or not workers.alive():
        if workers is not None:
            workers.close()
        workers = _Workers(len(jobs))
    results: dict[int, _Shard] = {}
    try:
        for k, job in enumerate(jobs):
            _send(workers.procs[k].stdin, list(sys.path))
            _send(workers.procs[k].stdin, (per_shard, job))
        while len(results) < len(jobs):
            try:
                k, (status, payload) = workers.messages.get(timeout=0.5)
            except queue.Empty:
                continue
            if status == "miles":
                advance(payload)
            elif status == "ready":
                ready += 1
                if ready == len(jobs):
                    startup_s = time.perf_counter() - started
            elif status == "ok":
                results[k], report = payload
                if report is not None:  # what the worker's policy counted, into the parent's fork
                    jobs[k][0].absorb_report(report)
            elif status == "error":
                raise RuntimeError(f"evaluation shard {k} failed:\n{payload}")
            elif k not in results:  # the worker's output ended before its result
                raise RuntimeError(
                    f"evaluation shard {k} died (exit code {workers.procs[k].wait()})"
                )
    except BaseException:
        for proc in workers.procs:  # a failed or interrupted evaluation ends its workers
            if proc.poll() is None:
                proc.kill()
        workers.close()
        raise
    with _WORKERS_LOCK:
        spare = _WORKERS.setdefault(len(jobs), workers)
    if spare is not workers:  # another thread kept a pool of this size meanwhile
        workers.close()
    for shard in results.values():  # the workers' start, counted once in the merged timing
        shard.timing["startup"] = startup_s / len(jobs)
    return [results[k] for k in range(len(jobs))]


def track_index(cfg: EvalConfig, car: int, visit: int) -> int:
    """Index (in ``cfg.split``) of the ``visit``-th track car ``car`` drives (see :class:`EvalConfig`)."""
    index = cfg.first_track + car + visit * cfg.n_worlds
    return index if cfg.n_tracks is None else index % cfg.n_tracks


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


def _drive(
    policy: Policy,
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    cars: np.ndarray,
    shard: int,
    advance: Callable[[float], None],
    record_traces: bool,
    stop_when: Callable[[], bool] | None,
) -> _Shard:
    """Drive the cars ``cars`` (their indices among ``cfg.n_worlds``) to their shares; start
    lanes come from shard ``shard``'s generator."""
    out = _Shard()
    n = len(cars)
    pool = _WorldPool(world_cfg, cfg.split)
    rng = np.random.default_rng([cfg.seed, 7] if shard == 0 else [cfg.seed, 7, shard])
    visit = np.zeros(n, dtype=np.int64)  # how many tracks each car has started
    fleet = Fleet([pool.get(j, track_index(cfg, int(c), 0)) for j, c in enumerate(cars)], world_cfg)
    dt_pol = world_cfg.sim.policy_period_s
    share_m = cfg.miles * M_PER_MILE / cfg.n_worlds
    odometer = np.zeros(n)
    sim_time = np.zeros(n)
    active = np.ones(n, dtype=bool)
    respawned = np.ones(n, dtype=bool)

    def spawn_new_track(i: int) -> None:
        w = fleet.worlds[i]
        fleet.place(i, *start_state(w, int(rng.integers(0, w.track.n_lanes)), cfg))

    def respawn(i: int, s_obstacle: float, d_now: float) -> None:
        fleet.place(i, *restart_state(fleet.worlds[i], s_obstacle, d_now, cfg))
        respawned[i] = True

    def position(i: int) -> tuple[float, float]:
        s_i, d_i, _ = fleet.worlds[i].track.to_frenet_hint(
            fleet.state[i, 0], fleet.state[i, 1], int(fleet.seg[i])
        )
        return s_i, d_i

    for i in range(n):
        spawn_new_track(i)
    policy.reset(n)

    episode_t = np.zeros(n)
    offcentre_t = np.zeros(n)
    offcentre_counted = np.zeros(n, dtype=bool)
    slow_t = np.zeros(n)
    t_sim = 0.0
    reported = 0.0
    track0 = fleet.worlds[0].track  # every track shares the cross-section
    cam_cfg = getattr(policy, "camera", None)
    camera = None if cam_cfg is None else Camera(cam_cfg)
    images = None if camera is None else np.empty((n, *camera.shape), dtype=np.uint8)
    # used only if the camera augments
    cam_rng = np.random.default_rng([cfg.seed, 11] if shard == 0 else [cfg.seed, 11, shard])
    lane_centers = np.asarray(track0.lane_center(np.arange(track0.n_lanes)))
    lengths = np.array([w.track.length for w in fleet.worlds])  # of each car's current track [m]
    while active.any():
        s, d, road_h, kappa = fleet.lane_frame()
        # a car near its track's end moves on to its next track
        moving_on = np.flatnonzero(active & (s > lengths - cfg.end_margin_m)).tolist()
        for i in moving_on:
            if cfg.n_tracks is None:  # never driven again
                pool.release(i, track_index(cfg, int(cars[i]), int(visit[i])))
            visit[i] += 1
            fleet.worlds[i] = pool.get(i, track_index(cfg, int(cars[i]), int(visit[i])))
            lengths[i] = fleet.worlds[i].track.length
            spawn_new_track(i)
            respawned[i] = True
        if moving_on:
            s, d, road_h, kappa = fleet.lane_frame()
        tick = time.perf_counter()
        if camera is not None:
            camera.render_batch(
                [w.track for w in fleet.worlds],
                [w.cars for w in fleet.worlds],
                fleet.state[:, :3],
                s,
                rng=cam_rng,
                out=images,
            )
            out.timing["frames"] += n
        tock = time.perf_counter()
        out.timing["render"] += tock - tick
        obs = observe(fleet, respawned, t_sim, images, (s, d, road_h, kappa))
        respawned[:] = False
        out.speed_hist += speed_histogram(fleet.state[active, V])
        act = policy.act(obs)
        tick = time.perf_counter()
        out.timing["policy"] += tick - tock
        if record_traces:
            for i in np.flatnonzero(active).tolist():
                key = "-".join(map(str, fleet.worlds[i].track.track_id))
                out.traces.setdefault(key, []).append(
                    [float(fleet.state[i, 0]), float(fleet.state[i, 1])]
                )
        xy_before = fleet.state[:, :2].copy()
        contacts = fleet.step(np.asarray(act.steer_rad), np.asarray(act.accel_mps2), active)
        out.timing["physics"] += time.perf_counter() - tick
        odometer += np.where(active, np.hypot(*(fleet.state[:, :2] - xy_before).T), 0.0)
        dt_active = np.where(active, dt_pol, 0.0)
        sim_time += dt_active
        episode_t += dt_active
        t_sim += dt_pol
        # off-centre episodes (autonomy metric only; the car is not moved)
        off = np.min(np.abs(d[:, None] - lane_centers[None, :]), axis=1) > cfg.offcentre_m
        offcentre_t = np.where(active & off, offcentre_t + dt_pol, 0.0)
        new_int = (offcentre_t > cfg.offcentre_grace_s) & ~offcentre_counted
        out.interventions += int(new_int.sum())
        offcentre_counted = (offcentre_counted | new_int) & (offcentre_t > 0)
        # collisions: one event per car per period, then a re-spawn
        for i, c in enumerate(contacts):
            if not c:
                continue
            w = fleet.worlds[i]
            s_i, d_i = position(i)
            car_idx = next((j for kind, j in c if kind == "car"), None)
            s_obst = (
                s_i if car_idx is None else max(s_i, float(w.cars.s[car_idx]) + w.cars.length_m / 2)
            )
            out.events.append(
                {
                    "world": int(cars[i]),
                    "track": list(w.track.track_id),
                    "kind": "rail" if car_idx is None else "car",
                    "car": car_idx,
                    "s_m": round(s_i, 2),
                    "d_m": round(d_i, 3),
                    "x_m": round(float(fleet.state[i, 0]), 2),
                    "y_m": round(float(fleet.state[i, 1]), 2),
                    "heading_rad": round(float(fleet.state[i, H]), 4),
                    "speed_mps": round(float(fleet.state[i, V]), 2),
                    "time_s": round(float(sim_time[i]), 2),
                    "miles": round(float(odometer[i] / M_PER_MILE), 4),
                }
            )
            out.ttc.append(float(episode_t[i]))
            episode_t[i] = 0.0
            out.interventions += 1
            respawn(i, s_obst, d_i)
        # stalls
        slow_t = np.where(active & (fleet.state[:, V] < cfg.stall_speed_mps), slow_t + dt_pol, 0.0)
        for i in np.flatnonzero(slow_t > cfg.stall_time_s).tolist():
            out.stalls += 1
            out.interventions += 1
            slow_t[i] = 0.0
            respawn(i, *position(i))
        # take-overs the policy asked for (the data collector's restarts; not collisions)
        if act.restart is not None:
            for i in np.flatnonzero(act.restart & active).tolist():
                if not contacts[i] and not respawned[i]:
                    episode_t[i] = 0.0
                    respawn(i, *position(i))
        active &= odometer < share_m
        if stop_when is not None and stop_when():
            active[:] = False
        done = float(np.minimum(odometer, share_m).sum() / M_PER_MILE)
        advance(max(0.0, done - reported))
        reported = max(reported, done)
    out.miles_m = float(odometer.sum())
    out.sim_s = float(sim_time.sum())
    out.censored = int(np.count_nonzero(episode_t > 0))
    out.tracks = int((visit + 1).sum())
    return out


def _merge(shards: list[_Shard], cfg: EvalConfig, wall: float) -> EvalResult:
    """One :class:`EvalResult` from the shards' sums (events in car order, then time)."""
    total_m = sum(sh.miles_m for sh in shards)
    total_t = sum(sh.sim_s for sh in shards)
    miles = total_m / M_PER_MILE
    events = sorted((e for sh in shards for e in sh.events), key=lambda e: e["world"])
    ttc = [t for sh in shards for t in sh.ttc]
    traces: dict[str, list[list[float]]] = {}
    for sh in shards:
        for key, pts in sh.traces.items():
            traces.setdefault(key, []).extend(pts)
    interventions = sum(sh.interventions for sh in shards)
    n_col = len(events)
    n_car = sum(e["kind"] == "car" for e in events)
    lo, hi = poisson_ci(n_col, miles / 100.0)
    return EvalResult(
        miles=miles,
        collisions=n_col,
        car_collisions=n_car,
        rail_collisions=n_col - n_car,
        collisions_per_100mi=100.0 * n_col / miles,
        ci95_per_100mi=(lo, hi),
        mean_speed_mph=total_m / total_t * MPS_TO_MPH,
        time_to_collision_s=float(np.mean(ttc)) if ttc else None,
        episodes_censored=sum(sh.censored for sh in shards),
        miles_per_collision=miles / n_col if n_col else None,
        autonomy_pct=max(0.0, 1.0 - interventions * cfg.intervention_cost_s / total_t) * 100.0,
        interventions=interventions,
        stalls=sum(sh.stalls for sh in shards),
        sim_time_s=total_t,
        wall_time_s=wall,
        sim_miles_per_wall_s=miles / wall,
        tracks_driven=sum(sh.tracks for sh in shards),
        timing_s={k: sum(sh.timing[k] for sh in shards) for k in shards[0].timing},
        events=events,
        traces=traces,
        speed_hist=[int(c) for c in sum(sh.speed_hist for sh in shards)],
    )
