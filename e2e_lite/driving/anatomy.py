"""The anatomy of a learned driver's collisions (chapter 12): for each collision, which moment was
still savable and by whom, and what kind of mistake it was.

A driver drives inside :class:`Witness`, which keeps each car's last :data:`HISTORY_S` of states
(and the driver's plans, when it has them) and, at every collision, files them as a
:class:`Collision`. Then, from those states alone:

* **the latest savable moment** (:func:`savable`): the expert, whose plan is read off the state
  (:class:`~e2e_lite.control.expert.Expert`), takes the car over at
  0.5, 1, 2, 3 and 5 s before the impact, from the very state the car was in (the world is
  deterministic and its decision a function of the state), and drives on: does it avoid it?
* **the tracker's share** (:func:`plan_collides`): would the driver's own plans of the last
  second, followed exactly (a perfect tracker), have hit the car? A collision whose plans were
  all clear is the tracker's;
* **how far the plans lay apart** (:func:`disagreement`): the driver's plan against that
  expert's label at the same states, over the seconds before the impact, beside ordinary driving;
* **the kind** (:func:`kind`): a rail, or a parked car hit by a lane change missed, late or
  into an occupied lane, by braking short, or other;
* **which part of a late lane change starts late** (:func:`late_change`, for the two lane-change
  kinds): when the expert, from the same states, begins the change, and when the driver's plan
  does; the parked car's distance and its width on the camera at the expert's start; the
  mixture's weight on its lane-changing modes over the last seconds. *Following*: the plan began
  the change in time and the car still hit; *deciding*: the plan began late, but the network
  showed it had seen the car (its lane-changing modes weighed more than while it keeps its lane,
  or its affordance head read the gap ahead right): seen, not taken; *seeing*: neither. Plans
  and modes are read along the road, not in the car's frame, where a curve looks like a change.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..control.affordances import affordances
from ..control.expert import Expert
from ..learning.labels import CHANGE, FOLLOW, GAP_CAP_M, Decision, interpolated_path
from ..simulation.camera import Camera, CameraConfig
from ..simulation.policy import Observation, Policy, observe
from ..simulation.world import RAIL_RADIUS_M, Fleet, WorldConfig, make_world
from .witness import (  # noqa: F401 (re-exported: the anatomy's readers find the witness here)
    CHANGING_M,
    GAP_AHEAD,
    HISTORY_S,
    PHASE_STRIDE,
    Collision,
    LateChange,
    Moment,
    Witness,
    load_witnessed,
    save_witnessed,
    witnessed_from_dict,
    witnessed_to_dict,
)

#: the hand-over times the anatomy tries, before the impact [s]
HAND_OVER_S = (0.5, 1.0, 2.0, 3.0, 5.0)
#: how long the expert drives on past the original impact to count as having avoided it [s]
AFTER_S = 3.0
#: the plans before the impact that the tracker's share reads [s]
PLAN_WINDOW_S = 1.0
#: the kinds of collision the anatomy tells apart
KINDS = (
    "rail",
    "lane change missed",
    "lane change late",
    "into an occupied lane",
    "braking short",
    "other",
)
#: the kinds whose lane change :func:`late_change` splits, and the parts it splits them into
LATE_KINDS = ("lane change late", "lane change missed")
PARTS = ("seeing", "deciding", "following", "seeing or deciding", "no expert start")
#: a plan that began its change no later than this after the expert's start began it in time [s]
IN_TIME_S = 0.5
#: the ordinary level of the lane-changing modes' weight: this quantile over ordinary moments
#: whose plan keeps the lane
ORDINARY_QUANTILE = 0.95
#: an affordance head read the gap ahead right when within this many metres, or this share of
#: the gap, whichever is larger
READ_TOLERANCE = (5.0, 0.2)


def contact(last: Moment, world_cfg: WorldConfig) -> tuple[str, int]:
    """What the car ran into: its last moment's command driven again from its state in a fresh
    copy of its world (the world is deterministic): ``("car", parked index)`` or ``("rail", -1)``
    (``("", -1)`` if it touches nothing: the collision then came from another cause). A car and a
    rail touched in one step is the car's, as the evaluator counts it."""
    fleet = _fresh_fleet(last, world_cfg)
    hits = fleet.step(np.array([last.command[0]]), np.array([last.command[1]]))[0]
    if not hits:
        return "", -1
    car = next((int(j) for kind, j in hits if kind == "car"), None)
    return ("car", car) if car is not None else (hits[0][0], -1)


def _fresh_fleet(moment: Moment, world_cfg: WorldConfig) -> Fleet:
    """A one-car fleet in a fresh copy of the moment's world, the car in the moment's state."""
    split, index = moment.world.track.track_id
    world = make_world(world_cfg, split, index)  # (never a sealed road: it would raise)
    fleet = Fleet([world], world_cfg)
    fleet.state[0], fleet.seg[0] = moment.state, moment.seg
    world.place_ego(*(float(v) for v in moment.state[:3]))
    world.clear_contacts()
    return fleet


def drive_from(
    moment: Moment, policy: Policy, world_cfg: WorldConfig, seconds: float
) -> int | None:
    """Drive ``policy`` for ``seconds`` from ``moment``'s state in a fresh copy of its world:
    the decision at which it collided (None: it did not)."""
    fleet = _fresh_fleet(moment, world_cfg)
    policy.reset(1)
    for k in range(round(seconds / world_cfg.sim.policy_period_s)):
        act = policy.act(observe(fleet, respawned=k == 0))
        if fleet.step(np.asarray(act.steer_rad), np.asarray(act.accel_mps2))[0]:
            return k
    return None


def savable(
    c: Collision, world_cfg: WorldConfig, hand_over: Policy | None = None
) -> dict[float, bool | None]:
    """For each of :data:`HAND_OVER_S` [s]: does ``hand_over`` (default the expert), taking
    the car over that long before the impact, avoid it for :data:`AFTER_S` past it? ``None``
    where the moments do not reach that far back (the car was placed less long before it)."""
    expert = hand_over or Expert(vehicle=world_cfg.vehicle, sim=world_cfg.sim)
    period = world_cfg.sim.policy_period_s
    out = {}
    for t in HAND_OVER_S:
        back = round(t / period)
        if back > len(c.moments):
            out[t] = None  # (the car was placed less long before the impact)
            continue
        hit = drive_from(c.moments[-back], expert, world_cfg, t + AFTER_S)
        out[t] = hit is None
    return out


def plan_collides(moment: Moment, margin_m: float = 0.2) -> bool:
    """Would the car, its rear axle following the plan exactly (a perfect tracker), touch a
    parked car or a guard rail within the plan's 1.5 s? The body is a box around the path,
    aligned with the road (lane-frame overlap of the two boxes, ``margin_m`` of slack)."""
    if moment.plan is None:
        return False
    world, state = moment.world, moment.state
    x, y, _ = interpolated_path(moment.plan)
    c, s_ = math.cos(state[2]), math.sin(state[2])
    veh = world.vehicle
    ahead = veh.rear_to_centre_m
    wx = state[0] + c * (x + ahead) - s_ * y
    wy = state[1] + s_ * (x + ahead) + c * y
    s, d = world.track.to_frenet(wx, wy)
    if np.any(np.abs(d) + veh.width_m / 2.0 - margin_m > world.track.rail_d - RAIL_RADIUS_M):
        return True
    cars = world.cars
    near = cars.between(float(np.min(s)) - 10.0, float(np.max(s)) + 10.0)
    reach_s = (veh.length_m + cars.length_m) / 2.0 - margin_m
    reach_d = (veh.width_m + cars.width_m) / 2.0 - margin_m
    for j in range(near.start, near.stop):
        hit = (np.abs(s - cars.s[j]) < reach_s) & (np.abs(d - cars.d[j]) < reach_d)
        if hit.any():
            return True
    return False


def _observe_moment(moment: Moment, world_cfg: WorldConfig) -> Observation:
    """A one-car observation of ``moment`` (its own world object: labels only read it)."""
    fleet = Fleet([moment.world], world_cfg)
    fleet.state[0], fleet.seg[0] = moment.state, moment.seg
    return observe(fleet, respawned=True)


def expert_label(moment: Moment, world_cfg: WorldConfig, expert: Expert) -> np.ndarray:
    """The expert's trajectory label at ``moment``'s state, ``(5, 2)`` in the car frame [m] (a
    function of the state alone, as a plan is read)."""
    return expert.trajectory_label(_observe_moment(moment, world_cfg))[0]


def disagreement(moments: list[Moment], world_cfg: WorldConfig, expert: Expert) -> np.ndarray:
    """Per moment, the largest distance over the 5 points between the driver's plan and the
    expert's label at the same state [m] (NaN where the driver had no plan)."""
    out = np.full(len(moments), np.nan)
    for k, m in enumerate(moments):
        if m.plan is not None:
            label = expert_label(m, world_cfg, expert)
            out[k] = float(np.linalg.norm(m.plan - label, axis=-1).max())
    return out


def expert_decisions(
    moments: list[Moment], world_cfg: WorldConfig, expert: Expert
) -> list[Decision]:
    """The expert's decision at each of ``moments``' states (a function of the state alone)."""
    out = []
    for m in moments:
        expert.reset(1)
        expert.act(_observe_moment(m, world_cfg))
        out.append(expert.decisions[0])
    return out


def kind(c: Collision, world_cfg: WorldConfig, expert: Expert, window_s: float = 3.0) -> str:
    """What kind of collision ``c`` was (:data:`KINDS`), from its last ``window_s``: a rail; the
    parked car in another lane than the car's at the window's start (into an occupied lane); the
    expert, at those states, changing lanes where the driver's plans kept to the lane (missed) or
    moved later (late); the expert braking to follow (braking short); else other."""
    if c.contact != "car":
        return "rail" if c.contact == "rail" else "other"
    period = world_cfg.sim.policy_period_s
    window = c.moments[-round(window_s / period) :]
    track = window[0].world.track
    d0 = float(track.to_frenet(window[0].state[0], window[0].state[1])[1])
    hit_lane = int(window[0].world.cars.lane[c.parked])
    if int(track.lane_index(d0)) != hit_lane:
        return "into an occupied lane"
    decisions = expert_decisions(window, world_cfg, expert)
    if any(_overtakes_out(window, decisions, hit_lane)):
        if not any(m.plan_changing for m in window):
            return "lane change missed"
        return "lane change late"
    if any(d.state == FOLLOW for d in decisions):
        return "braking short"
    return "other"


def _overtakes_out(moments: list[Moment], decisions: list[Decision], hit_lane: int) -> list[bool]:
    """Per moment: is the car in lane ``hit_lane`` and the expert, from there, changing out of it
    to overtake? (The end of a lane change, the expert steering back to its own lane's centre, is
    a change of state but not out of the lane.)"""
    track = moments[0].world.track
    out = []
    for m, decision in zip(moments, decisions):
        here = int(track.lane_index(float(track.to_frenet(m.state[0], m.state[1])[1])))
        away = decision.state == CHANGE and decision.overtaking and decision.target != here
        out.append(away and here == hit_lane)
    return out


def ordinary_change_weight(ordinary: list[Moment]) -> float | None:
    """The lane-changing modes' weight that ordinary driving reaches while its plan keeps the
    lane: its :data:`ORDINARY_QUANTILE` over the ``ordinary`` moments whose plan does not change
    lanes (None: no modes). (The driver's own lane changes are left out: their modes weigh
    about 1.)"""
    found = [m.change_weight for m in ordinary if m.plan_changing is False]
    found = [w for w in found if w is not None]
    return float(np.quantile(found, ORDINARY_QUANTILE)) if found else None


def reads_right(read_m: np.ndarray, true_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per reading of the gap ahead [m] against its truth [m]: is it within
    :data:`READ_TOLERANCE`, and can that be scored at all? Not where the truth lies so near the
    head's range (:data:`~e2e_lite.learning.labels.GAP_CAP_M`, its reading for a free lane) that
    reading a free lane would pass too (with 5 m or 20 %: a gap of 50 m or more). ``(right,
    scored)``, boolean arrays."""
    read, true = np.asarray(read_m, dtype=float), np.asarray(true_m, dtype=float)
    metres, share = READ_TOLERANCE
    tolerance = np.maximum(metres, share * true)
    return np.abs(read - true) <= tolerance, GAP_CAP_M - true > tolerance


def read_right(moment: Moment) -> bool | None:
    """Did the driver's affordance head read the gap ahead in its lane right at ``moment``
    (:func:`reads_right`)? None: no head, or a gap where a free lane's reading would pass too:
    there a right reading cannot show that the head saw the car."""
    if moment.gap_read_m is None:
        return None
    track = moment.world.track
    s, d = (np.ravel(v)[:1] for v in track.to_frenet(moment.state[0], moment.state[1]))
    true = float(affordances([moment.world], s, d, np.zeros(1))[0][GAP_AHEAD])
    right, scored = reads_right(np.array(moment.gap_read_m), np.array(true))
    return bool(right) if scored else None


def width_on_camera(moment: Moment, parked: int, camera: CameraConfig | None = None) -> float:
    """Parked car ``parked``'s width on the front camera at ``moment`` [px]: its rear bumper's
    two corners, half its height up, projected (0: behind the lens or past the draw distance)."""
    cfg = camera or CameraConfig()
    world, state = moment.world, moment.state
    cars, track = world.cars, world.track
    s_rear = float(cars.s[parked]) - cars.length_m / 2.0
    d = float(cars.d[parked]) + np.array([-0.5, 0.5]) * cars.width_m
    xy = track.position(np.full(2, s_rear), d)
    camera = Camera(cfg)
    rot, t = camera.world_to_camera_matrix(tuple(float(v) for v in state[:3]))
    pts = np.column_stack([xy, np.full(2, 0.7)]) @ rot.T + t  # (about half a car's height)
    ahead = float(pts[:, 2].min())
    if ahead < cfg.near_m or ahead > cfg.draw_distance_m:
        return 0.0
    cols = np.clip(camera.project(pts)[:, 0], 0.0, float(cfg.width_px))  # (in the frame)
    return float(abs(cols[1] - cols[0]))


def late_change(
    c: Collision,
    world_cfg: WorldConfig,
    expert: Expert,
    ordinary_level: float | None,
    window_s: float = 3.0,
) -> LateChange:
    """Which part of ``c``, a lane-change collision (:data:`LATE_KINDS`), started late.

    The expert's start: the first moment of the last unbroken run of moments from which the
    expert, in the hit car's lane, overtakes out of it (a wobble or an earlier car's overtake is
    another run). The plan's start: the first moment from that start (or from the last
    ``window_s``, :func:`kind`'s window, when that is earlier) whose plan changes lanes
    (:attr:`~e2e_lite.driving.witness.Moment.plan_changing`, read along the road). At the
    expert's start, the parked car's gap and its width on the camera; over the last
    ``window_s``, the lane-changing modes' weight; from the expert's start to the plan's, how
    often an affordance head read the gap ahead right (:func:`read_right`). The part:
    *following* when the plan began no later than :data:`IN_TIME_S` after the expert; else
    *deciding* when the driver showed it had seen the car: from the expert's start to
    :data:`IN_TIME_S` after it its lane-changing modes weighed more than ``ordinary_level``
    (:func:`ordinary_change_weight`, of the same driver), or its affordance head read the gap
    right at half or more of its moments; else *seeing*; *seeing or deciding* for a driver with
    neither modes nor a head to show it; *no expert start* when the expert, from these states,
    never overtakes out of the hit car's lane.
    """
    period = world_cfg.sim.policy_period_s
    n = len(c.moments)
    hit_lane = int(c.moments[0].world.cars.lane[c.parked]) if c.parked >= 0 else -1
    starts = _overtakes_out(c.moments, expert_decisions(c.moments, world_cfg, expert), hit_lane)
    first = None
    if any(starts):
        first = n - 1 - starts[::-1].index(True)
        while first > 0 and starts[first - 1]:
            first -= 1
    window = round(window_s / period)
    since = n - min(window, n) if first is None else min(first, n - min(window, n))
    moved = [k for k in range(since, n) if c.moments[k].plan_changing]
    planned = moved[0] if moved else None
    weights = [m.change_weight for m in c.moments[-window:]]
    expert_s = None if first is None else (n - first) * period
    plan_s = None if planned is None else (n - planned) * period
    gap = width = None
    if first is not None and c.parked >= 0:
        at = c.moments[first]
        s_car = float(at.world.track.to_frenet(at.state[0], at.state[1])[0])
        front = s_car + world_cfg.vehicle.rear_to_front_m
        gap = float(at.world.cars.s[c.parked]) - at.world.cars.length_m / 2.0 - front
        width = width_on_camera(at, c.parked)
    lag = round(IN_TIME_S / period)
    reads = (
        []
        if first is None
        else [read_right(m) for m in c.moments[first : n if planned is None else planned]]
    )
    reads = [r for r in reads if r is not None]
    read_share = sum(reads) / len(reads) if reads else None
    if first is None:
        part = "no expert start"
    elif planned is not None and planned <= first + lag:
        part = "following"
    else:
        seen = [c.moments[k].change_weight for k in range(first, min(n, first + lag + 1))]
        modes = None if ordinary_level is None or None in seen else max(seen) > ordinary_level
        read = None if read_share is None else read_share >= 0.5
        if modes is None and read is None:
            part = "seeing or deciding"
        else:
            part = "deciding" if modes or read else "seeing"
    return LateChange(expert_s, plan_s, gap, width, weights, read_share, part)


def dissect(
    c: Collision,
    world_cfg: WorldConfig,
    hand_over: Policy | None = None,
    ordinary_level: float | None = None,
) -> Collision:
    """Fill ``c``'s findings: the hand-overs that save it (to ``hand_over``, default the
    expert), whether its plans hit, the plans' disagreement with its labels, its kind, and for
    a lane change which part started late (``ordinary_level``: :func:`ordinary_change_weight`
    of the driver's ordinary moments)."""
    expert = Expert(vehicle=world_cfg.vehicle, sim=world_cfg.sim)
    c.contact, c.parked = contact(c.moments[-1], world_cfg)
    c.saved = savable(c, world_cfg, hand_over or expert)
    period = world_cfg.sim.policy_period_s
    last = [m for m in c.moments[-round(PLAN_WINDOW_S / period) :] if m.plan is not None]
    c.plan_hit = any(plan_collides(m) for m in last) if last else None
    c.apart_m = disagreement(c.moments, world_cfg, expert)
    c.kind = kind(c, world_cfg, expert)
    if c.kind in LATE_KINDS:
        c.late = late_change(c, world_cfg, expert, ordinary_level)
    return c


def table(collisions: list[Collision]) -> dict[str, Any]:
    """What the anatomy found, added up: per hand-over time how many collisions the expert saved
    and how many it could not be tried on (the car placed less long before), the latest savable
    moment's counts (``"none tried"``: no hand-over tried saved it), the tracker's share
    (collisions whose plans of the last :data:`PLAN_WINDOW_S` were all clear), the kinds, and
    the late lane changes: their parts, the medians of the expert's and the plan's starts [s
    before the impact], of the gap [m] and the width on the camera [px] at the expert's start,
    and of the share of moments its affordance head read the gap right."""
    n = len(collisions)
    saved = {t: sum(c.saved.get(t) is True for c in collisions) for t in HAND_OVER_S}
    untried = {t: sum(c.saved.get(t) is None for c in collisions) for t in HAND_OVER_S}
    latest = {str(t): sum(c.latest_savable_s == t for c in collisions) for t in HAND_OVER_S}
    latest["none tried"] = sum(c.latest_savable_s is None for c in collisions)
    late = [c.late for c in collisions if c.late is not None]

    def median(values: list[float | None]) -> float | None:
        found = [v for v in values if v is not None]
        return float(np.median(found)) if found else None

    return {
        "collisions": n,
        "saved_by_hand_over": {str(t): saved[t] for t in HAND_OVER_S},
        "untried_by_hand_over": {str(t): untried[t] for t in HAND_OVER_S},
        "latest_savable": latest,
        "plan_clear": sum(c.plan_hit is False for c in collisions),
        "kinds": {k: sum(c.kind == k for c in collisions) for k in KINDS},
        "late_changes": {
            "n": len(late),
            "parts": {p: sum(x.part == p for x in late) for p in PARTS},
            "expert_start_s": median([x.expert_start_s for x in late]),
            "plan_start_s": median([x.plan_start_s for x in late]),
            "never_planned": sum(x.plan_start_s is None for x in late),
            "gap_m": median([x.gap_m for x in late]),
            "width_px": median([x.width_px for x in late]),
            "read_share": median([x.read_share for x in late]),
        },
    }
