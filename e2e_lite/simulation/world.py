"""The world: a pymunk 7 space per track with guard rails, parked cars and the ego car.

* Guard rails are static segments along both road edges (a shoulder beyond the outer lane
  markings), so leaving the road is a collision.
* Parked cars are static boxes on the lane centres (20-80 per track, 50-200 m apart, random lane,
  as the paper). Consecutive cars are at least 50 m apart, so no place ever has every lane blocked.
* The ego is a KINEMATIC body moved by the bicycle model (:mod:`e2e_lite.simulation.vehicle`): each physics
  step sets its velocity to the model's chord velocity and pymunk integrates it, landing exactly
  on the model's pose. Kinematic bodies have infinite mass, so contacts never fling anything.
* Collisions are detected by pymunk's collision callbacks (``Space.on_collision``), not by
  hand-written overlap tests. The callback only records the contact; :class:`Fleet` turns all
  contacts of one physics step into exactly one collision event and then re-spawns the ego (the
  rule is in :meth:`World.respawn_pose`), so one physical collision is counted once whatever its
  duration, and driving goes on.

:class:`Fleet` steps B worlds in lockstep with one vectorised bicycle update per physics step.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import pymunk

from ..config import Profile, check_pair, check_range
from .geometry import RoadConfig, Track, generate_track, track_rng
from .vehicle import STATE_SIZE, STEER, V, VehicleParams, bicycle_step

# collision types and query categories
EGO, CAR, RAIL = 1, 2, 3
CAT_EGO, CAT_CAR, CAT_RAIL = 0b001, 0b010, 0b100
RAIL_RADIUS_M = 0.15  # half thickness of a guard rail [m]
CAR_HEIGHT_M = 1.5  # parked cars' height, for the camera [m]
# pymunk wraps attribute assignment in a typo check that costs more than the physics step;
# the hot loop calls the property setters directly.
_SET_VELOCITY = pymunk.Body.velocity.fset
_SET_ANGULAR_VELOCITY = pymunk.Body.angular_velocity.fset


@dataclass(frozen=True)
class TrafficConfig:
    """Parked cars on a track (the paper: 20 to 80 per track, 50 to 200 m apart).

    Attributes:
        n_cars: (min, max) number of cars drawn per track; fewer if the track is too short.
        spacing_m: (min, max) gap between consecutive cars along the road [m].
        first_car_m: arc length of the first possible car, leaving the start free [m].
        end_margin_m: no car within this distance of the track's end [m].
        car_length_m, car_width_m: size of a parked car [m].
        lateral_jitter_m: a car's centre is up to this far off its lane centre [m].
        heading_jitter_rad: a car's heading is up to this far off the road's [rad].
    """

    n_cars: tuple[int, int] = (20, 80)
    spacing_m: tuple[float, float] = (50.0, 200.0)
    first_car_m: float = 150.0
    end_margin_m: float = 150.0
    car_length_m: float = 4.5
    car_width_m: float = 1.8
    lateral_jitter_m: float = 0.2
    heading_jitter_rad: float = 0.03

    def __post_init__(self) -> None:
        o = "TrafficConfig"
        check_pair(o, "n_cars", self.n_cars, lo=0)
        for i, n in enumerate(self.n_cars):
            check_range(o, f"n_cars[{i}]", n, 0, integer=True)
        check_pair(o, "spacing_m", self.spacing_m, lo=self.car_length_m + 1.0)
        check_range(o, "first_car_m", self.first_car_m, 0.0)
        check_range(o, "end_margin_m", self.end_margin_m, 0.0)
        check_range(o, "car_length_m", self.car_length_m, 0.0, 20.0, lo_open=True)
        check_range(o, "car_width_m", self.car_width_m, 0.0, 5.0, lo_open=True)
        check_range(o, "lateral_jitter_m", self.lateral_jitter_m, 0.0, 1.0)
        check_range(o, "heading_jitter_rad", self.heading_jitter_rad, 0.0, 0.5)


@dataclass(frozen=True)
class SimConfig:
    """Time steps: physics at ``1 / dt_s`` Hz, the policy every ``policy_period_s``.

    Attributes:
        dt_s: physics step [s] (the paper's simulator ran at 50 fps: 0.02 s).
        policy_period_s: time between policy decisions [s] (the paper: 100 ms); must be a whole
            number of physics steps.
    """

    dt_s: float = 0.02
    policy_period_s: float = 0.1

    def __post_init__(self) -> None:
        check_range("SimConfig", "dt_s", self.dt_s, 0.0, 0.1, lo_open=True)
        check_range("SimConfig", "policy_period_s", self.policy_period_s, self.dt_s, 1.0)
        ratio = self.policy_period_s / self.dt_s
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"SimConfig.policy_period_s={self.policy_period_s!r} is invalid: must be a whole "
                f"number of physics steps (dt_s={self.dt_s!r}); got {ratio:.4g} steps"
            )

    @property
    def steps_per_policy(self) -> int:
        """Physics steps per policy decision."""
        return round(self.policy_period_s / self.dt_s)


@dataclass(frozen=True)
class WorldConfig:
    """Everything that defines a world: road, traffic, car and time steps."""

    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    sim: SimConfig = field(default_factory=SimConfig)

    @classmethod
    def for_profile(cls, profile: Profile, **road_overrides: object) -> WorldConfig:
        """The default world with the profile's track length (and any road overrides)."""
        return cls(road=RoadConfig(length_m=profile.track_length_m, **road_overrides))


@dataclass(frozen=True)
class ParkedCars:
    """Parked cars of one track, sorted by arc length. Arrays of shape (N,).

    Attributes:
        s, d: centre of each car in the lane frame [m].
        lane: lane index of each car.
        x, y, heading: centre pose in the world [m, m, rad].
        length_m, width_m: size shared by all cars [m].
    """

    s: np.ndarray
    d: np.ndarray
    lane: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    length_m: float
    width_m: float

    def __len__(self) -> int:
        return len(self.s)

    @classmethod
    def on_track(
        cls,
        track: Track,
        s: np.ndarray,
        d: np.ndarray,
        length_m: float = 4.5,
        width_m: float = 1.8,
        heading_offset: np.ndarray | float = 0.0,
    ) -> ParkedCars:
        """Cars centred at lane coordinates ``(s, d)`` [m], aligned with the road (plus
        ``heading_offset`` [rad]); sorted by ``s``. Their lane is the nearest lane centre."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        order = np.argsort(s, kind="stable")
        s = s[order]
        d = np.broadcast_to(np.asarray(d, dtype=np.float64), order.shape)[order]
        offset = np.broadcast_to(np.asarray(heading_offset, dtype=np.float64), order.shape)[order]
        xy = track.position(s, d).reshape(-1, 2)
        return cls(
            s=s,
            d=d.copy(),
            lane=np.atleast_1d(track.lane_index(d)),
            x=xy[:, 0],
            y=xy[:, 1],
            heading=np.asarray(track.heading(s) + offset, dtype=np.float64).reshape(-1),
            length_m=length_m,
            width_m=width_m,
        )

    def corners(self) -> np.ndarray:
        """World corners of every car, counter-clockwise; (N, 4, 2) [m]."""
        hl, hw = self.length_m / 2, self.width_m / 2
        local = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
        c, s = np.cos(self.heading)[:, None], np.sin(self.heading)[:, None]
        x = self.x[:, None] + c * local[:, 0] - s * local[:, 1]
        y = self.y[:, None] + s * local[:, 0] + c * local[:, 1]
        return np.stack([x, y], axis=-1)

    @functools.cached_property
    def box_corners_3d(self) -> np.ndarray:
        """World corners of every car as a box of height ``CAR_HEIGHT_M``: bottom ring, then top
        ring, counter-clockwise from rear-right; (N, 8, 3) [m]. Computed once (cars never move)."""
        ring = self.corners()
        bottom = np.concatenate([ring, np.zeros((*ring.shape[:2], 1))], axis=-1)
        top = bottom.copy()
        top[..., 2] = CAR_HEIGHT_M
        return np.concatenate([bottom, top], axis=1)

    def between(self, s_lo: float, s_hi: float) -> slice:
        """The slice of cars with centre ``s`` in ``[s_lo, s_hi)``."""
        return slice(int(self.s.searchsorted(s_lo)), int(self.s.searchsorted(s_hi)))


def place_parked_cars(track: Track, cfg: TrafficConfig, rng: np.random.Generator) -> ParkedCars:
    """Draw a count from ``cfg.n_cars``, then cars ``cfg.spacing_m`` apart in random lanes."""
    n_target = int(rng.integers(cfg.n_cars[0], cfg.n_cars[1] + 1))
    s_list, lanes = [], []
    s = cfg.first_car_m + rng.uniform(0.0, cfg.spacing_m[0])
    while len(s_list) < n_target and s <= track.length - cfg.end_margin_m:
        s_list.append(s)
        lanes.append(int(rng.integers(0, track.n_lanes)))
        s += rng.uniform(*cfg.spacing_m)
    n = len(s_list)
    lane = np.array(lanes, dtype=np.int64)
    d = track.lane_center(lane) + rng.uniform(-cfg.lateral_jitter_m, cfg.lateral_jitter_m, n)
    yaw = rng.uniform(-cfg.heading_jitter_rad, cfg.heading_jitter_rad, n)
    return ParkedCars.on_track(track, np.array(s_list), d, cfg.car_length_m, cfg.car_width_m, yaw)


class World:
    """One track's pymunk space: guard rails, parked cars, the ego body and its contacts.

    Args:
        track: the road.
        cars: the parked cars on it.
        vehicle: the ego car's dimensions.

    Attributes:
        contacts: ``(kind, index)`` of every contact begun since the last :meth:`clear_contacts`;
            kind is ``"car"`` (index = parked car) or ``"rail"`` (index 0 right, 1 left).
    """

    def __init__(self, track: Track, cars: ParkedCars, vehicle: VehicleParams) -> None:
        self.track = track
        self.cars = cars
        self.vehicle = vehicle
        self.contacts: list[tuple[str, int]] = []
        space = pymunk.Space()  # gravity (0, 0): a top-down world
        self.space = space
        # guard rails: polylines beside both road edges
        self._rail_shape_side: dict[pymunk.Shape, int] = {}
        for side, d in enumerate((-track.rail_d, track.rail_d)):
            pts = track.polyline(d)
            for a, b in itertools.pairwise(pts):
                seg = pymunk.Segment(space.static_body, tuple(a), tuple(b), RAIL_RADIUS_M)
                seg.collision_type = RAIL
                seg.filter = pymunk.ShapeFilter(categories=CAT_RAIL)
                space.add(seg)
                self._rail_shape_side[seg] = side
        # parked cars: static boxes
        self._car_index: dict[pymunk.Shape, int] = {}
        for i, corners in enumerate(cars.corners()):
            poly = pymunk.Poly(space.static_body, [tuple(p) for p in corners])
            poly.collision_type = CAR
            poly.filter = pymunk.ShapeFilter(categories=CAT_CAR)
            space.add(poly)
            self._car_index[poly] = i
        # each box's half extents along and across the road, for gap_ahead
        psi = cars.heading - np.asarray(track.heading(cars.s)).reshape(-1)
        c, sn = np.abs(np.cos(psi)), np.abs(np.sin(psi))
        hl, hw = cars.length_m / 2.0, cars.width_m / 2.0
        self._car_half_s = hl * c + hw * sn
        self._car_half_d = hl * sn + hw * c
        # the ego: a kinematic body at the rear axle, its box offset forward
        self.ego = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        box = pymunk.Poly(self.ego, [tuple(p) for p in vehicle.box_corners()])
        box.collision_type = EGO
        box.filter = pymunk.ShapeFilter(categories=CAT_EGO)
        space.add(self.ego, box)
        space.on_collision(EGO, CAR, begin=self._on_car)
        space.on_collision(EGO, RAIL, begin=self._on_rail)

    # -------------------------------------------------------------- contacts
    def _on_car(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: dict) -> None:
        self.contacts.append(("car", self._car_index[arbiter.shapes[1]]))

    def _on_rail(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: dict) -> None:
        self.contacts.append(("rail", self._rail_shape_side[arbiter.shapes[1]]))

    def clear_contacts(self) -> None:
        """Forget recorded contacts."""
        self.contacts.clear()

    # ------------------------------------------------------------------ ego
    def place_ego(self, x: float, y: float, heading: float) -> None:
        """Teleport the ego's rear axle to ``(x, y)`` with ``heading`` [m, m, rad]; stops it."""
        self.ego.position = (x, y)
        self.ego.angle = heading
        self.ego.velocity = (0.0, 0.0)
        self.ego.angular_velocity = 0.0
        self.space.reindex_shapes_for_body(self.ego)

    def physics_step(self, vx: float, vy: float, omega: float, dt: float) -> None:
        """Move the ego with velocity ``(vx, vy)`` [m/s] and yaw rate ``omega`` [rad/s] for ``dt`` [s]."""
        _SET_VELOCITY(self.ego, (vx, vy))
        _SET_ANGULAR_VELOCITY(self.ego, omega)
        self.space.step(dt)

    # --------------------------------------------------------- range queries
    def gap_ahead(self, s_from: float, lane: int, max_range_m: float = 60.0) -> float:
        """Distance along the road from ``s_from`` to the rear of the first parked car in
        ``lane`` [m]: 0 when a car's body already reaches past ``s_from``, ``inf`` when no car's
        rear is within ``max_range_m``.

        A car counts when its body reaches into the band ``lane_width/2 - 0.3`` m either side of
        the lane centre. Each car is its box in the lane frame: centre ``(s, d)``, turned by its
        heading jitter ``psi`` (at most ``TrafficConfig.heading_jitter_rad``), so it spans
        ``+-(l/2 |cos psi| + w/2 |sin psi|)`` along the road and ``+-(l/2 |sin psi| + w/2 |cos psi|)``
        across it. (The whole box's rear stands for the rear of the part inside the band, and a
        curve's ``1 - kappa d`` stretch is left out: both under 0.05 m on these roads.)

        Why not a pymunk segment query along the lane: a query does not see a shape it starts
        inside, so a query cut into pieces (to follow curves) missed every car whose rear lay
        within the query's radius past a piece's start, and reported the next hit instead: on 4 %
        of the positions approaching a car the gap came out up to one piece (9.9 m) too long, or
        the car was not seen at all (``tests/test_world.py`` checks the boxes against pymunk's
        shapes).
        """
        cars = self.cars
        if not len(cars):
            return math.inf
        reach = float(self._car_half_s.max())
        sl = cars.between(s_from - reach, s_from + max_range_m + reach)
        band = max(0.1, self.track.lane_width / 2.0 - 0.3)
        centre = float(self.track.lane_center(lane))
        rear = cars.s[sl] - self._car_half_s[sl]
        hit = (
            (np.abs(cars.d[sl] - centre) < band + self._car_half_d[sl])
            & (cars.s[sl] + self._car_half_s[sl] > s_from)
            & (rear - s_from <= max_range_m)
        )
        if not hit.any():
            return math.inf
        return max(0.0, float(rear[hit].min()) - s_from)

    def lane_free(self, s: float, lane: int, behind_m: float, ahead_m: float) -> bool:
        """No parked car centre in ``lane`` within ``[s - behind_m, s + ahead_m]`` [m]."""
        sl = self.cars.between(s - behind_m, s + ahead_m)
        return not np.any(self.cars.lane[sl] == lane)

    # --------------------------------------------------------------- respawn
    def respawn_pose(self, s_obstacle: float, d_now: float) -> tuple[float, int]:
        """Where the ego restarts after a collision: ``(s, lane)``.

        The rule: 15 m past the obstacle's arc length, on the free lane centre nearest to where
        the ego was (free = no parked car from 20 m behind to 40 m ahead), aligned with the road.
        If no lane is free there, try 10 m further on.
        """
        lanes = sorted(
            range(self.track.n_lanes), key=lambda i: (abs(self.track.lane_center(i) - d_now), i)
        )
        s = s_obstacle + 15.0
        for _ in range(100):
            for lane in lanes:
                if self.lane_free(s, lane, 20.0, 40.0):
                    return s, lane
            s += 10.0
        raise RuntimeError("no free lane found within 1 km after the obstacle")


#: test tracks sealed for the numbers of record (the block "record-2" of
#: :data:`e2e_lite.driving.roads.ROAD_BLOCKS`): only a drive of that block may make their worlds
SEALED_TEST_TRACKS = range(2_000_000, 3_000_000)
#: test tracks spent: the block "record", which the records of 321f6a9 and 28eba5c drove while the
#: recipes changed between them; no drive makes their worlds again
SPENT_TEST_TRACKS = range(1_000_000, 2_000_000)


def make_world(cfg: WorldConfig, split: str, index: int, *, sealed: bool = False) -> World:
    """The world of track ``(split, index)``: deterministic in ``(cfg, split, index)``.

    A test track of :data:`SEALED_TEST_TRACKS` is made only with ``sealed=True``, which the
    record's drive of its sealed block alone passes (:class:`~e2e_lite.driving.roads.WorldPool`):
    any other code that reaches for one raises ``ValueError`` before a road exists. A test track
    of :data:`SPENT_TEST_TRACKS` is made by nobody."""
    if split == "test" and index in SPENT_TEST_TRACKS:
        raise ValueError(
            f"make_world: test track {index} lies in the spent block of test roads "
            f"[{SPENT_TEST_TRACKS.start}, {SPENT_TEST_TRACKS.stop}): two records drove it while "
            "the recipes changed, so no drive makes its roads again"
        )
    if split == "test" and index in SEALED_TEST_TRACKS and not sealed:
        raise ValueError(
            f"make_world: test track {index} lies in the sealed block of test roads "
            f"[{SEALED_TEST_TRACKS.start}, {SEALED_TEST_TRACKS.stop}): only the record's drive of "
            "that block makes its roads (e2e_lite.record)"
        )
    track = generate_track(cfg.road, split, index)
    cars = place_parked_cars(track, cfg.traffic, track_rng(cfg.road.seed, split, index, stream=1))
    return World(track, cars, cfg.vehicle)


def lane_frame(
    tracks: list[Track], state: np.ndarray, seg: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lane-frame ``(s, d)`` [m] of each car's rear axle, road heading [rad] and curvature [1/m].

    Args:
        tracks: car i's track.
        state: ``(B, 5)`` car states.
        seg: ``(B,)`` int segment hints, updated in place (a hinted lookup costs ~2 us per car).
    """
    n = len(tracks)
    s, d, h, k = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for i, track in enumerate(tracks):
        si, di, j = track.to_frenet_hint(state[i, 0], state[i, 1], int(seg[i]))
        s0, _, _, _, h0, kj, _, _ = track.seg_table[j]
        s[i], d[i], h[i], k[i] = si, di, h0 + kj * (si - s0), kj
        seg[i] = j
    return s, d, h, k


class Fleet:
    """B worlds stepped in lockstep: one vectorised bicycle update, then each world's physics.

    Args:
        worlds: one world per car (each has its own pymunk space).
        cfg: the world settings (vehicle and time steps are used here).

    Attributes:
        state: ``(B, 5)`` ego states (see :mod:`e2e_lite.simulation.vehicle`).
        seg: each car's current segment index (the hint for lane-frame lookups).
    """

    def __init__(self, worlds: list[World], cfg: WorldConfig) -> None:
        self.worlds = worlds
        self.cfg = cfg
        self.state = np.zeros((len(worlds), STATE_SIZE))
        self.seg = np.zeros(len(worlds), dtype=np.int64)

    def __len__(self) -> int:
        return len(self.worlds)

    def place(self, i: int, s: float, d: float, speed: float) -> None:
        """Put car ``i`` at lane coordinates ``(s, d)`` [m], aligned with the road, at ``speed`` [m/s]."""
        track = self.worlds[i].track
        x, y, h = track.pose(s, d)
        self.state[i] = (x, y, h, speed, 0.0)
        self.seg[i] = int(track.segment_index(s))
        self.worlds[i].place_ego(float(x), float(y), float(h))
        self.worlds[i].clear_contacts()

    def lane_frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every car's ``(s, d)`` [m] (rear axle), road heading [rad] and curvature [1/m] there.

        Uses and updates the per-car segment hints, so it costs a few microseconds per car.
        """
        return lane_frame([w.track for w in self.worlds], self.state, self.seg)

    def step(
        self, steer_cmd: np.ndarray, accel_cmd: np.ndarray, active: np.ndarray | None = None
    ) -> list[list[tuple[str, int]]]:
        """Run one policy period of physics with the given commands held.

        Args:
            steer_cmd: road-wheel angle commands [rad], (B,).
            accel_cmd: acceleration commands [m/s^2], (B,).
            active: which cars move (B,) bool; frozen cars keep their state. Default: all.

        Returns:
            For each car, the contacts of the **first** physics step that had any (empty if none).
            A car stops integrating for the rest of the period once it has collided, so the caller
            can re-spawn it: one collision, one event.
        """
        n = len(self.worlds)
        dt = self.cfg.sim.dt_s
        moving = np.ones(n, dtype=bool) if active is None else active.copy()
        events: list[list[tuple[str, int]]] = [[] for _ in range(n)]
        steer_cmd = np.asarray(steer_cmd, dtype=np.float64)
        accel_cmd = np.asarray(accel_cmd, dtype=np.float64)
        for _ in range(self.cfg.sim.steps_per_policy):
            idx = np.flatnonzero(moving)
            if idx.size == 0:
                break
            sub = self.state[idx]
            _, vx, vy, om = bicycle_step(sub, steer_cmd[idx], accel_cmd[idx], self.cfg.vehicle, dt)
            self.state[idx] = sub
            for j, i in enumerate(idx.tolist()):
                w = self.worlds[i]
                w.physics_step(float(vx[j]), float(vy[j]), float(om[j]), dt)
                if w.contacts:
                    events[i] = list(w.contacts)
                    w.clear_contacts()
                    moving[i] = False
        return events

    def stop(self, i: int) -> None:
        """Zero car ``i``'s speed and steering (used after a collision)."""
        self.state[i, V] = 0.0
        self.state[i, STEER] = 0.0
