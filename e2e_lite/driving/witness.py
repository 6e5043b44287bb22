"""What a witnessed drive keeps (chapter 12's anatomy, :mod:`e2e_lite.driving.anatomy`): a
:class:`Witness` drives a driver unchanged and keeps each car's last :data:`HISTORY_S` of
:class:`Moment` s, filed as a :class:`Collision` at each collision, and ordinary moments to
compare with; stored and read back as JSON (:func:`witnessed_to_dict`,
:func:`witnessed_from_dict`). What the anatomy finds of a collision is filled in there.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..artifacts import load_json, save_json
from ..learning.labels import AFFORDANCE_NAMES
from ..simulation.policy import Actuation, Observation, Policy
from ..simulation.world import World, WorldConfig, make_world

#: how long before each collision the witness keeps a car's states [s]
HISTORY_S = 6.0
#: the witness's ordinary moments: car ``c`` keeps its decisions ``n`` with ``n % every`` equal
#: to ``PHASE_STRIDE * c % every`` (a stride prime to the course's ``every`` spreads the cars)
PHASE_STRIDE = 61
#: a plan (or a mode) changes lanes when its 1.5 s point lies this far from the centre of the
#: car's lane, read along the road (:meth:`Moment.lane_offset`) [m]
CHANGING_M = 1.0
#: where a network's affordance head puts its reading of the gap ahead in its lane
GAP_AHEAD = AFFORDANCE_NAMES.index("gap_ego_m")


@dataclass
class Moment:
    """One decision of one car: its state ``(5,)``, its lane-frame segment hint, its world, the
    driver's plan ``(5, 2)`` there (None: the driver has none), the command it gave
    ``(steer [rad], accel [m/s^2])``; for a mixture its modes' 1.5 s points ``mode_ends``
    ``(K, 2)`` and their ``weights`` ``(K,)`` (None: not a mixture); for a network with an
    affordance head its reading of the gap ahead in its lane ``gap_read_m`` (None: no head).
    Plans and points are in the car frame at the rear axle [m], as the labels are."""

    state: np.ndarray
    seg: int
    world: World
    plan: np.ndarray | None
    command: tuple[float, float] = (0.0, 0.0)
    mode_ends: np.ndarray | None = None
    weights: np.ndarray | None = None
    gap_read_m: float | None = None

    def lane_offset(self, points: np.ndarray) -> np.ndarray:
        """How far each car-frame point of ``points`` ``(..., 2)`` lies from the centre of the
        car's lane, read along the road [m] (on a curve a plan that keeps its lane ends metres
        to the side of the car's heading: the car's frame cannot tell a change from a curve)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        x, y, heading = (float(v) for v in self.state[:3])
        c, s = math.cos(heading), math.sin(heading)
        track = self.world.track
        wx = np.r_[x, x + c * pts[:, 0] - s * pts[:, 1]]  # (the car first, then the points)
        wy = np.r_[y, y + s * pts[:, 0] + c * pts[:, 1]]
        d = np.asarray(track.to_frenet(wx, wy)[1], dtype=float).reshape(-1)
        return d[1:] - float(track.lane_center(track.lane_index(float(d[0]))))

    @property
    def plan_changing(self) -> bool | None:
        """Whether the driver's plan changes lanes: its 1.5 s point more than
        :data:`CHANGING_M` from the centre of the car's lane (None: no plan)."""
        if self.plan is None:
            return None
        return bool(abs(self.lane_offset(self.plan[-1])[0]) > CHANGING_M)

    @property
    def change_weight(self) -> float | None:
        """The mixture's weight on its lane-changing modes (1.5 s point more than
        :data:`CHANGING_M` from the centre of the car's lane); None for a driver without
        modes."""
        if self.mode_ends is None or self.weights is None:
            return None
        return float(self.weights[np.abs(self.lane_offset(self.mode_ends)) > CHANGING_M].sum())


@dataclass
class LateChange:
    """Which part of a lane-change collision started late (:func:`~e2e_lite.driving.anatomy.late_change`).

    Attributes:
        expert_start_s: how long before the impact the expert, from the car's states, began the
            overtake [s] (None: not within the witnessed seconds).
        plan_start_s: ... the driver's plan began it [s] (None: never).
        gap_m: at the expert's start, the gap from the car's front to the parked car's rear [m].
        width_px: ... the parked car's width on the camera [px] (0: not drawn).
        change_weights: per moment of the last 3 s, the lane-changing modes' weight (None: no
            modes).
        read_share: from the expert's start until the plan's (or the impact), of the moments
            with a car ahead within the affordance head's range, the share whose reading of the
            gap ahead was right (:func:`~e2e_lite.driving.anatomy.read_right`); None: no head
            or no such moment.
        part: one of :data:`~e2e_lite.driving.anatomy.PARTS`.
    """

    expert_start_s: float | None
    plan_start_s: float | None
    gap_m: float | None
    width_px: float | None
    change_weights: list[float | None]
    read_share: float | None
    part: str


@dataclass
class Collision:
    """One collision and the moments before it (oldest first, the last one the decision before
    the impact), with what the anatomy found (filled by :func:`~e2e_lite.driving.anatomy.dissect`).

    Attributes:
        car: the car's index in its drive; step: its decision count at the impact.
        contact: ``"car"`` or ``"rail"``; parked: the parked car's index (-1: a rail); what the
            last moment's command, driven again, ran into (:func:`~e2e_lite.driving.anatomy.contact`).
        moments: its last :data:`HISTORY_S` of decisions.
        saved: per hand-over time [s], whether the expert taking over then avoided it (None: the
            moments do not reach that far back: the car was placed less long before).
        plan_hit: whether any of the driver's plans of the last
            :data:`~e2e_lite.driving.anatomy.PLAN_WINDOW_S`, followed exactly, hits a parked car
            (None: the driver has no plans).
        apart_m: per moment, the largest distance between the driver's plan and the expert's
            label [m] (NaN where the driver has no plan).
        kind: one of :data:`~e2e_lite.driving.anatomy.KINDS`.
        late: for the kinds of :data:`~e2e_lite.driving.anatomy.LATE_KINDS`, which part started
            late (else None).
    """

    car: int
    step: int
    moments: list[Moment]
    contact: str = ""
    parked: int = -1
    saved: dict[float, bool | None] = field(default_factory=dict)
    plan_hit: bool | None = None
    apart_m: np.ndarray | None = None
    kind: str = ""
    late: LateChange | None = None

    @property
    def latest_savable_s(self) -> float | None:
        """The latest hand-over (fewest seconds before the impact) that avoided it (None: none
        of those tried)."""
        ok = [t for t, saved in self.saved.items() if saved]
        return min(ok) if ok else None


class Witness:
    """A policy wrapper that drives ``driver`` unchanged and keeps, for every car, its last
    :data:`HISTORY_S` of moments; a car's collision files them in :attr:`collisions`, and each
    car keeps one decision in every ``every`` of its own as an ordinary moment (driving with no
    collision in sight, to compare with), at a phase of its own (:data:`PHASE_STRIDE` x its
    index, modulo ``every``): the moments are spread over the cars and the drive, and a short
    drive whose cars each decide fewer than ``every`` times keeps some too. A network's plan is
    read from ``driver.last["points"]``.

    It keeps its states in this process, so its shards are threads (:attr:`threads_only`): a
    driver that forks gives a witness that forks, and the forks file into their parent's lists.
    Both lists are read in the order of the drive (decision, then car), and a car is known by
    its index in the whole drive, so what is witnessed is the same for any number of shards. A
    car whose share of the miles is driven (``obs.active``) is no longer witnessed, nor is a
    collision on its last step (a shard whose cars are all done decides no more)."""

    #: its forks keep their states in this process: the evaluator drives them in threads
    threads_only = True

    def __init__(self, driver: Policy, period_s: float, every: int = 200) -> None:
        self.driver, self.period_s, self.every = driver, period_s, every
        self.camera = getattr(driver, "camera", None)
        self.sim = getattr(driver, "sim", None)
        self.history = round(HISTORY_S / period_s)
        self._filed: list[tuple[int, int, Collision]] = []  # (decision, car, collision)
        self._ordinary: list[tuple[int, int, Moment]] = []  # (decision, car, moment)
        self._cars: np.ndarray | None = None

    @property
    def collisions(self) -> list[Collision]:
        """Every collision filed, by this witness or its forks, in the order of the drive."""
        return [c for *_, c in sorted(self._filed, key=lambda x: x[:2])]

    @property
    def ordinary(self) -> list[Moment]:
        """Every ordinary moment kept, by this witness or its forks, in the order of the drive,
        but those of a car's last :data:`HISTORY_S` before one of its collisions: they are that
        collision's moments, not driving with no collision in sight."""
        ends: dict[int, list[int]] = {}
        for step, car, _ in self._filed:  # (a collision's step: its last decision's, plus one)
            ends.setdefault(car, []).append(step)

        def before_a_collision(step: int, car: int) -> bool:
            return any(end - self.history <= step < end for end in ends.get(car, ()))

        return [m for step, car, m in self.kept if not before_a_collision(step, car)]

    @property
    def kept(self) -> list[tuple[int, int, Moment]]:
        """Every moment kept as an ordinary one, those of a car's last seconds before a collision
        included (:attr:`ordinary` leaves them out), in the order of the drive: ``[(the car's
        decision, the car, moment), ...]`` (a car's decisions counted from 0; a collision's
        :attr:`~Collision.step` is its last decision's plus one; moments set through
        :attr:`ordinary`'s setter read ``(their index, -1, moment)``)."""
        return sorted(self._ordinary, key=lambda x: x[:2])

    @ordinary.setter
    def ordinary(self, moments: list[Moment]) -> None:
        self._ordinary[:] = [(k, -1, m) for k, m in enumerate(moments)]  # (no car's: all kept)

    @property
    def fork(self) -> Callable[[int], list[Witness]]:
        """``fork(k)``: ``k`` witnesses of the driver's ``k`` forks, filing into this one's lists
        (only where the driver forks: otherwise a witness drives in one shard)."""
        if not hasattr(self.driver, "fork"):
            raise AttributeError(f"{type(self.driver).__name__} does not fork")

        def fork(k: int) -> list[Witness]:
            out = [Witness(d, self.period_s, self.every) for d in self.driver.fork(k)]
            for w in out:
                w._filed, w._ordinary = self._filed, self._ordinary
            return out

        return fork

    def seed_cars(self, cars: np.ndarray) -> None:
        self._cars = np.asarray(cars, dtype=np.int64).copy()
        if hasattr(self.driver, "seed_cars"):
            self.driver.seed_cars(cars)

    def reset(self, n_worlds: int) -> None:
        self.driver.reset(n_worlds)
        self.buffers: list[deque[Moment]] = [deque(maxlen=self.history) for _ in range(n_worlds)]
        self.steps = np.zeros(n_worlds, dtype=np.int64)
        unseeded = self._cars is None or len(self._cars) != n_worlds
        self.cars = np.arange(n_worlds) if unseeded else self._cars  # their indices in the drive
        self._cars = None  # (seeded anew for each drive)
        self.phase = (self.cars * PHASE_STRIDE) % self.every

    def act(self, obs: Observation) -> Actuation:
        active = np.ones(len(obs.worlds), dtype=bool) if obs.active is None else obs.active
        if obs.collided is not None:
            for i in np.flatnonzero(obs.collided & active).tolist():
                self._file(i)
        act = self.driver.act(obs)
        last = getattr(self.driver, "last", {})
        plans, modes, weights = last.get("points"), last.get("modes"), last.get("weights")
        read = last.get("affordances")
        steer, accel = np.asarray(act.steer_rad), np.asarray(act.accel_mps2)
        for i in np.flatnonzero(active).tolist():
            if obs.respawned[i]:
                self.buffers[i].clear()
            world, plan = obs.worlds[i], None if plans is None else np.array(plans[i])
            seg = int(world.track.segment_index(float(obs.s[i])))
            command = (float(steer[i]), float(accel[i]))
            moment = Moment(obs.state[i].copy(), seg, world, plan, command)
            if modes is not None and weights is not None:
                moment.mode_ends = np.array(modes[i][:, -1, :], dtype=float)
                moment.weights = np.array(weights[i], dtype=float)
            if read is not None:
                moment.gap_read_m = float(read[i][GAP_AHEAD])
            self.buffers[i].append(moment)
            if self.steps[i] % self.every == self.phase[i]:
                self._ordinary.append((int(self.steps[i]), int(self.cars[i]), moment))
        self.steps += 1
        return act

    def _file(self, i: int) -> None:
        """Car ``i`` collided since its last decision: file its moments."""
        moments = list(self.buffers[i])
        if moments:
            step, car = int(self.steps[i]), int(self.cars[i])
            self._filed.append((step, car, Collision(car, step, moments)))


def witnessed_to_dict(witness: Witness) -> dict[str, Any]:
    """What a :class:`Witness` kept, as JSON-able lists: each moment's world by its track's id
    (the world is rebuilt from it: :func:`witnessed_from_dict`), its arrays as lists of floats."""

    def moment(m: Moment) -> dict[str, Any]:
        plan = None if m.plan is None else m.plan.tolist()
        track = list(m.world.track.track_id)
        out = {
            "state": m.state.tolist(),
            "seg": m.seg,
            "track": track,
            "plan": plan,
            "command": list(m.command),
        }
        if m.mode_ends is not None and m.weights is not None:
            out["mode_ends"], out["weights"] = m.mode_ends.tolist(), m.weights.tolist()
        if m.gap_read_m is not None:
            out["gap_read_m"] = m.gap_read_m
        return out

    return {
        "collisions": [
            {"car": c.car, "step": c.step, "moments": [moment(m) for m in c.moments]}
            for c in witness.collisions
        ],
        "ordinary": [moment(m) for m in witness.ordinary],
    }


def witnessed_from_dict(
    stored: dict[str, Any], world_cfg: WorldConfig
) -> tuple[list[Collision], list[Moment]]:
    """:func:`witnessed_to_dict`'s collisions and ordinary moments back, each moment in a fresh
    copy of its world (one per track: a world's parked cars are a function of its track's id)."""
    worlds: dict[tuple[str, int], World] = {}

    def moment(m: dict[str, Any]) -> Moment:
        key = (str(m["track"][0]), int(m["track"][1]))
        if key not in worlds:
            worlds[key] = make_world(world_cfg, *key)
        world = worlds[key]
        plan = None if m["plan"] is None else np.array(m["plan"], dtype=float)
        state = np.array(m["state"], dtype=float)
        out = Moment(state, int(m["seg"]), world, plan, tuple(m["command"]))
        if "weights" in m:
            out.mode_ends = np.array(m["mode_ends"], dtype=float)
            out.weights = np.array(m["weights"], dtype=float)
        out.gap_read_m = m.get("gap_read_m")
        return out

    collisions = [
        Collision(c["car"], c["step"], [moment(m) for m in c["moments"]])
        for c in stored["collisions"]
    ]
    return collisions, [moment(m) for m in stored["ordinary"]]


def save_witnessed(path: Path, stored: dict[str, Any], key: str) -> None:
    """Write :func:`witnessed_to_dict`'s dict with its key (for :func:`~e2e_lite.artifacts.cached`)."""
    save_json(path, {"key": key, **stored})


def load_witnessed(path: Path) -> tuple[dict[str, Any], str]:
    """:func:`save_witnessed`'s dict and key back."""
    stored = load_json(path)
    return stored, stored.pop("key")
