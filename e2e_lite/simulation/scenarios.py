"""The paper's claim in one closed-loop scene: a parked car dead ahead, both side lanes free.

Aggregate collision counts mix many causes (curves, restarts, speed). This scene isolates the one
the GMM is for (seed 000, Fig. 3): the ego drives at cruise speed on the centre of the middle lane
of a straight road, a parked car stands in that lane ahead, and both side lanes are free. Going
left and going right are both right; the average of the two is the parked car. A scene is
*passed* when the ego's rear axle gets 10 m past the parked car's centre without any collision
within the time limit; *collided* when it touches a car or a rail; *stuck* otherwise (it stopped
or crawled behind the car).

Every scene is seeded (:func:`overtake_scenes`): the distance to the car, a small lateral offset
and the speed are jittered, so the same seed gives the same scenes and, for a deterministic
driver, the same outcomes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import check_pair, check_range, tqdm
from .camera import Camera
from .geometry import Track
from .policy import Policy, observe
from .world import Fleet, ParkedCars, World, WorldConfig

START_S_M = 50.0  # the ego's rear axle at the start [m]
PASSED_M = 10.0  # past the parked car's centre by this much counts as passed [m]
ROAD_M = 600.0  # length of the straight road [m]


@dataclass(frozen=True)
class ScenarioConfig:
    """Settings of the overtake scene set.

    Attributes:
        n_scenes: how many scenes.
        ahead_m: (min, max) distance from the ego's rear axle to the parked car's centre [m].
        offset_m: the ego starts uniformly within +-this of the middle lane's centre [m].
        speed_mps: (min, max) start speed [m/s] (the roads' cruise speed is 25 m/s).
        seconds: time limit of a scene [s].
        batch: scenes driven in lockstep.
        seed: seeds the jitter.
    """

    n_scenes: int = 200
    ahead_m: tuple[float, float] = (70.0, 100.0)
    offset_m: float = 0.2
    speed_mps: tuple[float, float] = (24.0, 26.0)
    seconds: float = 12.0
    batch: int = 50
    seed: int = 0

    def __post_init__(self) -> None:
        o = "ScenarioConfig"
        check_range(o, "n_scenes", self.n_scenes, 1, 100_000, integer=True)
        check_pair(o, "ahead_m", self.ahead_m, lo=20.0)
        check_range(o, "ahead_m[1]", self.ahead_m[1], 20.0, ROAD_M - START_S_M - 100.0)
        check_range(o, "offset_m", self.offset_m, 0.0, 1.0)
        check_pair(o, "speed_mps", self.speed_mps, lo=1.0)
        check_range(o, "seconds", self.seconds, 0.1, 120.0)
        check_range(o, "batch", self.batch, 1, 4096, integer=True)
        check_range(o, "seed", self.seed, 0, integer=True)


@dataclass(frozen=True)
class Scene:
    """One scene: the parked car ``ahead_m`` ahead [m], the ego ``offset_m`` left of the lane
    centre [m] at ``speed_mps`` [m/s]."""

    ahead_m: float
    offset_m: float
    speed_mps: float


def overtake_scenes(cfg: ScenarioConfig) -> list[Scene]:
    """The seeded scenes of ``cfg`` (the same seed gives the same scenes)."""
    rng = np.random.default_rng([cfg.seed, 41])
    ahead = rng.uniform(*cfg.ahead_m, cfg.n_scenes)
    offset = rng.uniform(-cfg.offset_m, cfg.offset_m, cfg.n_scenes)
    speed = rng.uniform(*cfg.speed_mps, cfg.n_scenes)
    return [Scene(float(a), float(o), float(v)) for a, o, v in zip(ahead, offset, speed)]


def scene_world(scene: Scene, world_cfg: WorldConfig) -> World:
    """A straight 3-lane road (the course's cross-section) with one parked car in the middle
    lane, ``scene.ahead_m`` ahead of the start."""
    road = world_cfg.road
    track = Track(
        [0.0],
        [0.0],
        [0.0],
        [0.0],
        [ROAD_M],
        n_lanes=road.n_lanes,
        lane_width_m=road.lane_width_m,
        shoulder_m=road.shoulder_m,
        track_id=("scene", 0),
    )
    middle = road.n_lanes // 2
    cars = ParkedCars.on_track(
        track,
        np.array([START_S_M + scene.ahead_m]),
        np.array([float(track.lane_center(middle))]),
    )
    return World(track, cars, world_cfg.vehicle)


#: Chapters 04, 06 and 07's frame with two right answers: on a straight 900 m road, one parked
#: car in the middle lane at 300 m, the ego centred in that lane behind it.
TWO_ANSWERS_ROAD_M = 900.0
TWO_ANSWERS_CAR_S_M = 300.0


def two_answers_scene(
    world_cfg: WorldConfig, gap_m: float = 44.0, speed_mps: float = 25.0
) -> tuple[World, Fleet]:
    """The frame with two right answers (pass left or right), as a world and a placed fleet of
    one car: the ego's front bumper ``gap_m`` behind the parked car's rear [m] (44 m: nearer than
    any of the expert's overtake triggers), at ``speed_mps`` [m/s]."""
    straight = Track([0.0], [0.0], [0.0], [0.0], [TWO_ANSWERS_ROAD_M])
    cars = ParkedCars.on_track(straight, np.array([TWO_ANSWERS_CAR_S_M]), np.array([0.0]))
    world = World(straight, cars, world_cfg.vehicle)
    fleet = Fleet([world], world_cfg)
    veh = world_cfg.vehicle
    # rear axle = the car's centre - half its length - our front bumper's reach - the gap
    rear_axle_s = TWO_ANSWERS_CAR_S_M - cars.length_m / 2 - veh.rear_to_front_m
    fleet.place(0, rear_axle_s - gap_m, 0.0, speed_mps)
    return world, fleet


@dataclass
class ScenarioResult:
    """Outcomes of a scene set: one of ``"passed"``, ``"collided"``, ``"stuck"`` per scene,
    and every scene's rear-axle path in the lane frame, ``paths[k]`` (T, 2) ``(s, d)`` [m]
    (recorded until the scene ends)."""

    outcomes: list[str]
    paths: list[np.ndarray] = field(default_factory=list)

    def count(self, outcome: str) -> int:
        """How many scenes ended so."""
        return sum(o == outcome for o in self.outcomes)

    @property
    def pass_rate(self) -> float:
        """Share of scenes passed without a collision."""
        return self.count("passed") / len(self.outcomes)

    def summary(self) -> str:
        """One readable line."""
        n = len(self.outcomes)
        return (
            f"{self.count('passed')}/{n} passed ({100 * self.pass_rate:.1f} %), "
            f"{self.count('collided')} collided, {self.count('stuck')} stuck"
        )


def run_scenarios(
    policy: Policy,
    cfg: ScenarioConfig | None = None,
    world_cfg: WorldConfig | None = None,
    *,
    progress: bool = True,
    desc: str = "overtake scenes",
) -> ScenarioResult:
    """Drive ``policy`` through every scene of ``cfg``, ``cfg.batch`` scenes in lockstep.

    The policy sees what the evaluator shows it (camera frames when it has a ``camera``), is
    ``reset`` per batch, and every car is frozen when its scene ends (passed or collided).
    """
    cfg = cfg or ScenarioConfig()
    world_cfg = world_cfg or WorldConfig()
    scenes = overtake_scenes(cfg)
    cam_cfg = getattr(policy, "camera", None)
    camera = None if cam_cfg is None else Camera(cam_cfg)
    period = world_cfg.sim.policy_period_s
    outcomes: list[str] = []
    paths: list[np.ndarray] = []
    bar = tqdm(total=len(scenes), desc=desc, unit="scene", disable=not progress, leave=False)
    for first in range(0, len(scenes), cfg.batch):
        batch = scenes[first : first + cfg.batch]
        worlds = [scene_world(sc, world_cfg) for sc in batch]
        fleet = Fleet(worlds, world_cfg)
        mid = float(worlds[0].track.lane_center(world_cfg.road.n_lanes // 2))
        for i, sc in enumerate(batch):
            fleet.place(i, START_S_M, mid + sc.offset_m, sc.speed_mps)
        goal = np.array([START_S_M + sc.ahead_m + PASSED_M for sc in batch])
        policy.reset(len(batch))
        n = len(batch)
        ended = np.full(n, "", dtype=object)
        track_path: list[list[tuple[float, float]]] = [[] for _ in range(n)]
        images = None if camera is None else np.empty((n, *camera.shape), dtype=np.uint8)
        for k in range(round(cfg.seconds / period)):
            active = ended == ""
            if not active.any():
                break
            s, d, road_h, kappa = fleet.lane_frame()
            for i in np.flatnonzero(active).tolist():
                track_path[i].append((float(s[i]), float(d[i])))
            if camera is not None:
                tracks, cars = [w.track for w in worlds], [w.cars for w in worlds]
                camera.render_batch(tracks, cars, fleet.state[:, :3], s, out=images)
            act = policy.act(observe(fleet, k == 0, k * period, images, (s, d, road_h, kappa)))
            contacts = fleet.step(np.asarray(act.steer_rad), np.asarray(act.accel_mps2), active)
            s_after = fleet.lane_frame()[0]
            for i in np.flatnonzero(active).tolist():
                if contacts[i]:
                    ended[i] = "collided"
                elif s_after[i] >= goal[i]:
                    ended[i] = "passed"
        ended[ended == ""] = "stuck"
        outcomes += ended.tolist()
        paths += [np.array(p) for p in track_path]
        bar.update(n)
    bar.close()
    return ScenarioResult(outcomes, paths)
