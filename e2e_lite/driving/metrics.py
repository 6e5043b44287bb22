"""What a closed-loop evaluation measured (:class:`EvalResult`) and how to read it; the per-shard
sums it is merged from (:class:`ShardResult`, :func:`merge_shards`, :func:`add_info`).

* collisions per 100 miles, with an exact (Garwood) 95 % Poisson confidence interval
  (:func:`poisson_ci`);
* time before a collision (seed 002): an *episode* starts at a (re)spawn and ends at the next
  collision; the mean length of the episodes that ended in a collision. Episodes cut off by the
  budget are censored and only counted in ``episodes_censored``;
* autonomy % (seed 003): ``(1 - interventions * 6 s / elapsed s) * 100``, floored at 0. An
  intervention is a collision (the re-spawn is the human taking over) or an *off-centre episode*:
  the car more than 1 m from every lane centre for longer than ``offcentre_grace_s`` (3 s, longer
  than a normal lane change takes). We only count off-centre interventions; we do not move the car,
  so the intervention rule cannot change the collision count;
* a *stall* (speed under 0.5 m/s for 20 s) is re-spawned and reported, so a policy that stops cannot
  hang the evaluation.

Beside them: pooling runs (training seeds) into one result (:func:`pool_results`), collisions
sorted by kind (:func:`collision_kinds`) and the Markdown table the chapters print
(:func:`results_table`). The statistics that read a result live in :mod:`e2e_lite.stats`.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from ..simulation.world import World, WorldConfig, make_world
from ..stats.rates import poisson_ci

M_PER_MILE = 1609.344


MPS_TO_MPH = 3600.0 / M_PER_MILE


@dataclass
class EvalResult:
    """What a closed-loop evaluation measured. Distances in miles, times in seconds.

    ``timing_s`` splits the wall time of the loop, summed over shards: ``render`` (camera
    frames), ``policy`` (the driver's ``act``: the network and the tracker), ``physics``
    (bicycle and pymunk steps); ``frames`` counts the frames rendered; ``startup`` is the
    wall-clock time shard processes took to start (an interpreter and the imports each).
    ``speed_hist[k]`` counts the decisions taken at a speed in ``[k, k + 1)`` m/s (the last bin
    holds everything faster): the states the driver visited (chapter 04 compares them with the
    data's). ``info`` adds up what the policy reported with its actuations (``Actuation.info``,
    e.g. the safety module's counts; stored beside the result, :meth:`to_json`). ``seeds``: a
    pooled result's drives, one per training seed (:func:`pool_results`; empty for one drive),
    each without its events.
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
    info: dict[str, Any] = field(default_factory=dict, repr=False)
    seeds: tuple[EvalResult, ...] = ()

    def to_dict(self, with_events: bool = True) -> dict[str, Any]:
        """JSON-ready dict (traces and info left out; events optional; a pooled result's
        ``seeds`` last, each without events)."""
        out = asdict(dataclasses.replace(self, info={}, traces={}, seeds=()))
        for name in ("traces", "info", "seeds"):
            out.pop(name)
        if not with_events:
            out.pop("events")
        if self.seeds:
            out["seeds"] = [s.to_dict(with_events=False) for s in self.seeds]
        return out

    def to_json(self) -> dict[str, Any]:
        """What a stored drive holds: :meth:`to_dict` and, when the policy reported any, its
        ``info`` (which must be JSON-able)."""
        return {"result": self.to_dict(), **({"info": self.info} if self.info else {})}

    @classmethod
    def from_dict(cls, d: dict[str, Any], info: dict[str, Any] | None = None) -> EvalResult:
        """The result a :meth:`to_dict` wrote (and the ``info`` stored beside it)."""
        names = {f.name for f in dataclasses.fields(cls)} - {"seeds", "info", "ci95_per_100mi"}
        return cls(
            **{k: v for k, v in d.items() if k in names},
            ci95_per_100mi=tuple(d["ci95_per_100mi"]),
            seeds=tuple(cls.from_dict(s) for s in d.get("seeds") or ()),
            info=dict(info or {}),
        )

    @classmethod
    def from_json(cls, stored: dict[str, Any]) -> EvalResult:
        """The result a :meth:`to_json` wrote."""
        return cls.from_dict(stored["result"], stored.get("info"))

    @property
    def off_centre(self) -> int:
        """Off-centre episodes: the interventions that were neither collisions nor stalls (the
        car more than ``EvalConfig.offcentre_m`` from every lane centre for longer than its
        grace; the autonomy metric counts all three)."""
        return int(self.interventions - self.collisions - self.stalls)

    def brief(self) -> dict[str, float]:
        """The drive's off-centre episodes and collisions (counts) and its miles [mi]: what the
        lab scripts keep of each drive."""
        return {"off_centre": self.off_centre, "collisions": self.collisions, "miles": self.miles}

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


def results_table(
    rows: Sequence[tuple[str, EvalResult]],
    extra: Sequence[tuple[str, Sequence[str]]] = (),
) -> str:
    """A markdown table of closed-loop results, one row per
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
    for k, (name, r) in enumerate(rows):
        lo, hi = r.ci95_per_100mi
        ttc = "-" if r.time_to_collision_s is None else f"{r.time_to_collision_s:.1f} s"
        lines.append(
            f"| {name} | {r.miles:.3g} | {r.collisions} ({r.car_collisions} / "
            f"{r.rail_collisions}) | {r.collisions_per_100mi:.1f} [{lo:.1f}-{hi:.1f}] | "
            f"{r.mean_speed_mph:.1f} | {ttc} | {r.autonomy_pct:.1f}% |"
            + "".join(f" {cells[k]} |" for _, cells in extra)
        )
    return "\n".join(lines)


#: How :func:`collision_kinds` sorts a collision.
COLLISION_KINDS = ("rail", "parked car in its lane, car centred", "parked car, off centre")


def collision_kinds(result: EvalResult, world_cfg: WorldConfig) -> dict[str, int]:
    """Count a result's collisions by kind (:data:`COLLISION_KINDS`).

    A car collision is *in its lane, car centred* when the parked car's centre is within a third
    of a lane width of the ego's lateral position and the ego is within 0.8 m of a lane centre:
    the driver stayed in a lane with a parked car ahead and neither left it nor stopped. Every
    other car collision happened off centre (changing lanes, or clipping a car beside). The
    parked car's position comes from the track the event names (rebuilt from its seed).
    """
    counts = dict.fromkeys(COLLISION_KINDS, 0)
    worlds: dict[tuple[str, int], World] = {}
    for e in result.events:
        if e["kind"] == "rail":
            counts["rail"] += 1
            continue
        track_id = (str(e["track"][0]), int(e["track"][1]))  # (split, index)
        if track_id not in worlds:
            worlds[track_id] = make_world(world_cfg, *track_id)
        track, d_ego = worlds[track_id].track, float(e["d_m"])
        d_car = float(worlds[track_id].cars.d[e["car"]])
        centres = track.lane_center(np.arange(track.n_lanes))  # (every track: one cross-section)
        centred = float(np.min(np.abs(d_ego - centres))) <= 0.8
        in_lane = abs(d_ego - d_car) < track.lane_width / 3
        counts[COLLISION_KINDS[1] if centred and in_lane else COLLISION_KINDS[2]] += 1
    return counts


def pool_results(results: Sequence[EvalResult], intervention_cost_s: float = 6.0) -> EvalResult:
    """One result from several evaluations of the same kind of driver (e.g. one per training
    seed), as if they were one drive: counts, miles and times summed, rates, the interval, mean
    speed, autonomy (``intervention_cost_s`` per intervention, as :class:`EvalConfig`) and the
    time to collision recomputed from the sums; ``events``: every input's, in input order (a
    car's ``world`` number is its index in its own evaluation); ``seeds`` keeps each input
    without its events, traces or what its policy reported."""
    if not results:
        raise ValueError("pool_results needs at least one result")
    rs = [dataclasses.replace(r, events=[], traces={}, info={}, seeds=()) for r in results]
    events = [e for r in results for e in r.events]
    total = {
        k: sum(getattr(r, k) for r in rs)
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
    ttc = [(r.time_to_collision_s, r.collisions) for r in rs if r.collisions]
    hist = [r.speed_hist for r in rs]
    return EvalResult(
        **total,
        collisions_per_100mi=100.0 * n / miles,
        ci95_per_100mi=poisson_ci(n, miles / 100.0),
        mean_speed_mph=sum(r.mean_speed_mph * r.sim_time_s for r in rs) / sim_s,
        time_to_collision_s=sum(t * k for t, k in ttc) / n if n else None,
        miles_per_collision=miles / n if n else None,
        autonomy_pct=max(0.0, 1.0 - total["interventions"] * intervention_cost_s / sim_s) * 100,
        sim_miles_per_wall_s=miles / max(total["wall_time_s"], 1e-9),
        timing_s={k: sum(r.timing_s.get(k, 0.0) for r in rs) for k in rs[0].timing_s},
        speed_hist=[int(sum(c)) for c in zip(*hist)] if all(hist) else [],
        events=events,
        seeds=tuple(rs),
    )


SPEED_BINS = 41  # 1 m/s bins of EvalResult.speed_hist: 0-1, ..., 39-40, >= 40 m/s


def speed_histogram(speeds_mps: np.ndarray) -> np.ndarray:
    """Counts of ``speeds_mps`` in :data:`SPEED_BINS` bins of 1 m/s (the last one open), int64."""
    bins = np.clip(np.asarray(speeds_mps, dtype=np.float64), 0.0, SPEED_BINS - 1).astype(np.int64)
    return np.bincount(bins, minlength=SPEED_BINS)


# ------------------------------------------------------------------------------ shards
class ShardResult:
    """What one shard of :func:`~e2e_lite.driving.evaluation.evaluate` measured on its cars (summed by
    :func:`merge_shards`)."""

    def __init__(self) -> None:
        self.car_miles_m = np.zeros(0)  # each car's distance [m]
        self.car_sim_s = np.zeros(0)  # each car's driven time [s]
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
        self.info: dict[str, Any] = {}  # what the policy reported (Actuation.info), added up


def add_info(total: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    r"""Add a decision's (or a shard's) ``info`` into ``total``, in place; returns ``total``.

    Numbers and ``Counter``\ s are summed, lists concatenated (so examples stay in decision
    order, shard after shard); a name must keep its type.
    """
    for name, value in info.items():
        if name not in total:
            total[name] = list(value) if isinstance(value, list) else copy.copy(value)
        elif isinstance(value, list):
            total[name].extend(value)
        elif isinstance(value, (Counter, int, float, np.integer, np.floating)):
            total[name] += value
        else:
            raise TypeError(f"cannot add up info {name!r} of type {type(value).__name__}")
    return total


def merge_shards(shards: list[ShardResult], intervention_cost_s: float, wall: float) -> EvalResult:
    """One :class:`EvalResult` from the shards' sums (events in car order, then time);
    ``intervention_cost_s`` [s] of autonomy per intervention, ``wall`` [s] the wall time."""
    # exactly rounded sums (math.fsum) and sorted lists: the same numbers for any sharding
    total_m = math.fsum(m for sh in shards for m in sh.car_miles_m.tolist())
    total_t = math.fsum(t for sh in shards for t in sh.car_sim_s.tolist())
    miles = total_m / M_PER_MILE
    events = sorted((e for sh in shards for e in sh.events), key=lambda e: e["world"])
    ttc = sorted(t for sh in shards for t in sh.ttc)
    traces: dict[str, list[list[float]]] = {}
    for sh in shards:
        for key, pts in sh.traces.items():
            traces.setdefault(key, []).extend(pts)
    interventions = sum(sh.interventions for sh in shards)
    info: dict[str, Any] = {}
    for sh in shards:  # in shard order: shard 0's examples first
        add_info(info, sh.info)
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
        time_to_collision_s=math.fsum(ttc) / len(ttc) if ttc else None,
        episodes_censored=sum(sh.censored for sh in shards),
        miles_per_collision=miles / n_col if n_col else None,
        autonomy_pct=max(0.0, 1.0 - interventions * intervention_cost_s / total_t) * 100.0,
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
        info=info,
    )
