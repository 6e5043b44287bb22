"""The safety module: the rule on hand-made cases, the fallback order, and fewer collisions."""

from __future__ import annotations

import copy
import json
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from e2e_lite.control.labels import GAP_NAMES
from e2e_lite.control.tracker import LQRTracker, trajectory_reference
from e2e_lite.driving.evaluation import Actuation, EvalConfig, Observation, evaluate
from e2e_lite.driving.metrics import EvalResult, add_info
from e2e_lite.experiments.calibration import calibrate_gap_free
from e2e_lite.experiments.safe_agent import (
    GYRO_FULL_SPEED_MPS,
    GYRO_MIN_CAMERA_WEIGHT,
    SafeAgent,
    SafetyStats,
    fuse_heading,
)
from e2e_lite.experiments.safety import (
    SafetyConfig,
    brake_along,
    brake_to_lane,
    cap_speed,
    check,
    choose,
    end_lateral,
    keep_lane_brake,
)
from e2e_lite.learning.data import AFFORDANCE_NAMES, affordances
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig, make_world

T = 0.3 * np.arange(1, 6)


def aff(gap_ego=60.0, gap_left=60.0, gap_right=60.0, offset=0.0, heading=0.0) -> np.ndarray:
    """Affordances of a car in the middle lane of a 3 x 3.5 m road (edges 5.25 m away)."""
    values = {
        "heading_rad": heading,
        "center_offset_m": offset,
        "left_marking_m": 1.75 - offset,
        "right_marking_m": 1.75 + offset,
        "left_edge_m": 5.25 - offset,
        "right_edge_m": 5.25 + offset,
        "gap_ego_m": gap_ego,
        "gap_left_m": gap_left,
        "gap_right_m": gap_right,
    }
    return np.array([values[name] for name in AFFORDANCE_NAMES])


def straight(speed=25.0, y_end=0.0) -> np.ndarray:
    """Points at constant speed, moving sideways to ``y_end`` along a smooth curve."""
    u = T / T[-1]
    return np.stack([speed * T, y_end * u**2 * (3 - 2 * u)], axis=1)


def test_a_trajectory_into_a_parked_car_is_rejected_at_a_short_gap_and_accepted_at_a_long_one():
    short = check(straight(25.0), aff(gap_ego=30.0), 25.0, 0.0)
    assert not short.ok and short.lane == "ego" and short.kind == "collision course"
    # beyond what the car perceives: nothing seen, nothing to fear
    assert check(straight(25.0), aff(gap_ego=60.0), 25.0, 0.0).ok
    # a car 50 m ahead is not reached in 1.5 s, but the car could not stop for it afterwards
    late = check(straight(25.0), aff(gap_ego=50.0), 25.0, 0.0)
    assert not late.ok and late.kind == "cannot stop"
    # the same gap at walking pace is fine
    assert check(straight(5.0), aff(gap_ego=50.0), 5.0, 0.0).ok


def test_changing_into_a_blocked_lane_is_rejected_and_into_a_free_one_accepted():
    to_left = straight(25.0, y_end=3.5)
    assert check(to_left, aff(gap_ego=40.0, gap_left=60.0), 25.0, 0.0).ok
    blocked = check(to_left, aff(gap_ego=40.0, gap_left=25.0), 25.0, 0.0)
    assert not blocked.ok and blocked.lane == "left"


def test_the_calibrated_gap_free_thresholds_are_each_lanes_noise_quantile_on_free_lanes_only():
    rng = np.random.default_rng(0)
    n = 4000
    true = np.stack([aff() for _ in range(n)])
    ego, left, right = (AFFORDANCE_NAMES.index(g) for g in GAP_NAMES)
    true[: n // 2, ego] = 20.0  # a car ahead: not a free lane
    true[: n // 4, left] = 0.0  # no lane there
    pred = true.copy()
    pred[:, ego] = np.where(true[:, ego] >= 60.0, rng.uniform(55.0, 60.0, n), 5.0)
    side_noise = rng.uniform(40.0, 60.0, (n, 2))
    free_side = true[:, [left, right]] >= 60.0
    pred[:, [left, right]] = np.where(free_side, side_noise, 3.0)  # blocked lanes: ignored
    cfg = calibrate_gap_free(SafetyConfig(), pred, true, ghost_share=0.05)
    assert cfg.gap_free_m == pytest.approx(np.quantile(pred[n // 2 :, ego], 0.05))
    assert 55.1 < cfg.gap_free_m < 55.4  # the 5 % point of U(55, 60)
    assert cfg.gap_free_side_m == pytest.approx(np.quantile(side_noise[free_side], 0.05))
    assert 40.6 < cfg.gap_free_side_m < 41.4  # the 5 % point of U(40, 60)
    # only the thresholds change; the check reads each lane's own
    assert cfg == SafetyConfig(gap_free_m=cfg.gap_free_m, gap_free_side_m=cfg.gap_free_side_m)
    assert "gap_free_side_m" in repr(cfg) and "gap_free_side_m" not in repr(SafetyConfig())
    assert (
        cfg.free_from_m("ego") == cfg.gap_free_m and cfg.free_from_m("left") == cfg.gap_free_side_m
    )
    assert not check(straight(25.0), aff(gap_ego=56.0), 25.0, 0.0).ok
    assert check(straight(25.0), aff(gap_ego=56.0), 25.0, 0.0, cfg).ok
    assert not check(straight(25.0), aff(gap_ego=50.0), 25.0, 0.0, cfg).ok  # ego sees at 50 m
    into_left = straight(25.0, y_end=3.5)
    assert not check(into_left, aff(gap_left=50.0), 25.0, 0.0).ok
    assert check(into_left, aff(gap_left=50.0), 25.0, 0.0, cfg).ok  # 50 m: beyond the side's
    # never above the setting it starts from; unchanged where no lane is free
    exact = calibrate_gap_free(SafetyConfig(), true, true)
    assert exact.gap_free_m == exact.gap_free_side_m == SafetyConfig().gap_free_m
    blocked = true.copy()
    blocked[:, [ego, left, right]] = 10.0
    assert calibrate_gap_free(SafetyConfig(), pred, blocked) == SafetyConfig()
    with pytest.raises(ValueError, match="ghost_share"):
        calibrate_gap_free(SafetyConfig(), pred, true, ghost_share=1.0)
    with pytest.raises(ValueError, match="predictions and truths"):
        calibrate_gap_free(SafetyConfig(), pred[:, :8], true[:, :8])
    with pytest.raises(ValueError, match="gap_free_side_m"):
        SafetyConfig(gap_free_side_m=0.0)


def test_a_trajectory_leaving_the_road_is_rejected():
    off_road = check(straight(25.0, y_end=-5.0), aff(), 25.0, 0.0)
    assert not off_road.ok and off_road.kind == "road edge" and off_road.lane == "right"
    # the same points are on the road when the road bends the same way (radius 100 m)
    bend = -1 / 100.0
    pts = straight(25.0)
    pts[:, 1] = bend * pts[:, 0] ** 2 / 2
    assert check(pts, aff(), 25.0, bend).ok
    assert not check(pts, aff(), 25.0, 0.0).ok  # ... and leave it on a straight road


def test_fallback_order_heaviest_passing_mode_then_keep_lane_braking():
    safe, unsafe = straight(25.0, y_end=3.5), straight(25.0)
    a = aff(gap_ego=30.0, gap_left=60.0)
    c = choose(np.stack([unsafe, safe]), np.array([0.3, 0.7]), a, 25.0, 0.0)
    assert c.source == "network" and np.array_equal(c.points, safe)
    c = choose(np.stack([unsafe, safe]), np.array([0.7, 0.3]), a, 25.0, 0.0)
    assert c.source == "other mode" and np.array_equal(c.points, safe)
    assert [v.ok for v in c.verdicts] == [False, True]
    # no mode passes: without the neighbouring lanes, the keep-lane brake, unchecked
    lane_only = SafetyConfig(fallback_lanes=False)
    c = choose(np.stack([unsafe, unsafe]), np.array([0.5, 0.5]), a, 25.0, 0.0, lane_only)
    assert c.source == "fallback" and len(c.verdicts) == 2
    assert np.allclose(c.points, keep_lane_brake(a, 25.0, 0.0))
    # checked, it meets the car 30 m ahead later than either mode, and is still driven
    checked = SafetyConfig(fallback_lanes=False, check_fallback=True)
    c = choose(np.stack([unsafe, unsafe]), np.array([0.5, 0.5]), a, 25.0, 0.0, checked)
    assert c.source == "fallback" and len(c.verdicts) == 3
    assert c.verdicts[-1].kind == "collision course"
    assert c.verdicts[-1].t_s > max(v.t_s for v in c.verdicts[:2])
    # a brake that only "cannot stop" is driven: it already brakes as hard as the rule assumes
    c = choose(np.stack([unsafe]), np.array([1.0]), aff(gap_ego=50.0), 25.0, 0.0, checked)
    assert c.source == "fallback" and c.verdicts[-1].kind == "cannot stop"


def test_modes_only_re_ranks_the_modes_and_never_brakes():
    safe, unsafe, worse = straight(25.0, y_end=3.5), straight(25.0), straight(25.0, y_end=-0.2)
    a = aff(gap_ego=30.0, gap_left=60.0)
    only = SafetyConfig(modes_only=True, brake_along_path=True)  # (no fallback of any kind)
    c = choose(np.stack([unsafe, safe]), np.array([0.7, 0.3]), a, 25.0, 0.0, only)
    assert c.source == "other mode" and np.array_equal(c.points, safe)  # as without the option
    # no mode passes: the heaviest, as proposed (its verdicts kept: the alarm rang)
    c = choose(np.stack([worse, unsafe]), np.array([0.4, 0.6]), a, 25.0, 0.0, only)
    assert c.source == "network" and np.array_equal(c.points, unsafe)
    assert [v.ok for v in c.verdicts] == [False, False]
    braked = choose(np.stack([worse, unsafe]), np.array([0.4, 0.6]), a, 25.0, 0.0)
    assert braked.source == "fallback" and braked.points[-1, 0] < unsafe[-1, 0] - 5.0


def test_half_way_through_a_lane_change_the_fallback_brakes_on_into_the_lane_being_entered():
    """Chapter 11's ground-truth collisions: a car 1.5 m right of its lane centre, passing a
    parked car 32 m ahead at 24.6 m/s, the network's mode turning back. Braking back to the lane
    centre cannot stop in time; braking on into the free right lane passes the check."""
    a = aff(gap_ego=32.0, gap_right=60.0, offset=-1.5)
    back = straight(24.6, y_end=1.0)  # the heaviest mode: back into the blocked lane
    assert not check(back, a, 24.6, 0.0).ok
    assert not check(keep_lane_brake(a, 24.6, 0.0), a, 24.6, 0.0).ok
    c = choose(back[None], np.array([1.0]), a, 24.6, 0.0)
    assert c.source == "fallback" and c.verdicts[-1].ok
    assert np.allclose(c.points, brake_to_lane(a, 24.6, 0.0, -1))
    assert end_lateral(c.points, a, 0.0) == pytest.approx(-3.5)  # the right lane's centre
    # the mode still heading right: the right lane is tried first
    on = choose(straight(24.6, y_end=-1.0)[None], np.array([1.0]), a, 24.6, 0.0)
    assert len(on.verdicts) == 2 and np.allclose(on.points, c.points)
    # the right lane blocked too: no brake passes, the last resort is the keep-lane brake
    both = aff(gap_ego=32.0, gap_right=20.0, gap_left=20.0, offset=-1.5)
    c = choose(back[None], np.array([1.0]), both, 24.6, 0.0)
    assert c.source == "fallback" and len(c.verdicts) == 1
    assert np.allclose(c.points, keep_lane_brake(both, 24.6, 0.0))
    # braking in the lane stops in time (15 m/s, a car 25 m ahead): it comes first, although
    # the lanes beside are free
    slow = aff(gap_ego=25.0)
    c = choose(straight(15.0)[None], np.array([1.0]), slow, 15.0, 0.0)
    assert c.verdicts[0].kind == "cannot stop" and len(c.verdicts) == 2
    assert np.allclose(c.points, keep_lane_brake(slow, 15.0, 0.0))


def test_with_brake_along_path_a_parked_car_is_braked_for_on_the_networks_own_path():
    """The perceived module's fallback (chapter 11): the heaviest mode heads for a car 30 m
    ahead; the lanes beside look free, but the lane fallback would steer by perceived geometry.
    With ``brake_along_path`` the mode's own path is driven, braking."""
    along = SafetyConfig(brake_along_path=True)
    a = aff(gap_ego=30.0)
    drift = straight(25.0, y_end=0.4)  # the network's path, drifting a little left
    c = choose(drift[None], np.array([1.0]), a, 25.0, 0.0, along)
    assert c.source == "fallback" and np.allclose(c.points, brake_along(drift, 25.0, along))
    assert not c.verdicts[0].ok and len(c.verdicts) == 1  # its brake fails too: the last resort
    # without the option, the lane fallback brakes into the left lane's centre
    lanes = choose(drift[None], np.array([1.0]), a, 25.0, 0.0)
    assert np.allclose(lanes.points, brake_to_lane(a, 25.0, 0.0, 1))
    # a passing braked path is taken from the modes heaviest first: 40 m ahead at 15 m/s, the
    # mode's own path cannot stop, braking along it can
    b = aff(gap_ego=40.0)
    c = choose(straight(15.0)[None], np.array([1.0]), b, 15.0, 0.0, along)
    assert c.verdicts[0].kind == "cannot stop" and c.verdicts[-1].ok
    # a road-edge rejection keeps the lane fallback: the path itself leaves the road
    off = straight(25.0, y_end=8.0)
    edge = choose(off[None], np.array([1.0]), aff(), 25.0, 0.0, along)
    assert edge.verdicts[0].kind == "road edge"
    assert np.allclose(edge.points, choose(off[None], np.array([1.0]), aff(), 25.0, 0.0).points)
    # stored keys: the option shows in the settings' text only when set
    assert "brake_along_path" in repr(along) and "brake_along_path" not in repr(SafetyConfig())


@settings(max_examples=60, deadline=None)
@given(speed=st.floats(0.0, 40.0), y_end=st.floats(-4.0, 4.0), pace=st.floats(0.5, 1.5))
def test_braking_along_a_path_stays_on_it_and_slows_down(speed, y_end, pace):
    path = straight(pace * max(speed, 1.0), y_end=y_end)
    pts = brake_along(path, speed)
    assert pts.shape == (5, 2) and np.all(np.isfinite(pts))
    whole = np.concatenate([np.zeros((1, 2)), pts])
    steps = np.hypot(*np.diff(whole, axis=0).T)
    assert np.all(np.diff(steps) <= 1e-9)  # never faster
    assert steps.sum() <= speed * 1.5 + 1e-9  # never further than at the speed now
    # every point lies on the proposed path: on the segment between two of its points
    dense = np.concatenate([np.zeros((1, 2)), path])
    u = np.linspace(0.0, 1.0, 2001)[:, None, None]
    on_path = (dense[:-1] + u * np.diff(dense, axis=0)).reshape(-1, 2)
    nearest = np.min(np.hypot(*(pts[:, None] - on_path[None]).transpose(2, 0, 1)), axis=1)
    step = np.max(np.hypot(*np.diff(dense, axis=0).T)) / 2000
    assert np.all(nearest <= step + 1e-6)


@settings(max_examples=60, deadline=None)
@given(free=st.floats(5.0, 120.0), reaction=st.floats(0.0, 1.0), brake=st.floats(1.0, 10.0))
def test_the_sight_speed_stops_exactly_within_the_sight(free, reaction, brake):
    cfg = SafetyConfig(gap_free_m=free, reaction_s=reaction, brake_mps2=brake)
    v = cfg.sight_speed_mps()
    assert v >= 0.0 and cfg.stopping_m(v) == pytest.approx(max(free, cfg.margin_m), abs=1e-6)
    # the true affordances' threshold (59.5 m) allows the roads' cruise speed, barely
    assert 25.0 < SafetyConfig().sight_speed_mps() < 25.2


@settings(max_examples=60, deadline=None)
@given(speed=st.floats(1.0, 40.0), y_end=st.floats(-4.0, 4.0), cap=st.floats(0.0, 40.0))
def test_capping_the_speed_keeps_the_path_and_never_exceeds_the_cap(speed, y_end, cap):
    path = straight(speed, y_end=y_end)
    pts = cap_speed(path, cap)
    assert pts.shape == (5, 2) and np.all(np.isfinite(pts))
    whole = np.concatenate([np.zeros((1, 2)), pts])
    along = np.cumsum(np.hypot(*np.diff(whole, axis=0).T))
    assert np.all(along <= cap * T + 1e-6)  # never further along than the cap allows
    own = np.cumsum(np.hypot(*np.diff(np.concatenate([np.zeros((1, 2)), path]), axis=0).T))
    if np.all(own <= cap * T):  # a proposal under the cap (along its path) is driven as proposed
        assert np.array_equal(pts, path)
    # on the proposed path (as braking along it), and a batch of them capped at once
    dense = np.concatenate([np.zeros((1, 2)), path])
    u = np.linspace(0.0, 1.0, 2001)[:, None, None]
    on_path = (dense[:-1] + u * np.diff(dense, axis=0)).reshape(-1, 2)
    nearest = np.min(np.hypot(*(pts[:, None] - on_path[None]).transpose(2, 0, 1)), axis=1)
    assert np.all(nearest <= np.max(np.hypot(*np.diff(dense, axis=0).T)) / 2000 + 1e-6)
    batch = cap_speed(np.stack([path, straight(0.5 * speed)])[None], cap)
    assert batch.shape == (1, 2, 5, 2) and np.array_equal(batch[0, 0], pts)


def swerve_left(speed=25.0, t_across=0.6) -> np.ndarray:
    """Points at constant speed, one lane (3.5 m) to the left within ``t_across`` seconds."""
    return np.stack([speed * T, 3.5 * np.minimum(1.0, T / t_across)], axis=1)


def test_when_braking_cannot_avoid_the_car_the_latest_violation_is_driven():
    # a car 20 m ahead at 25 m/s: braking meets it at about 0.8 s; the sharp swerve leaves the
    # lane in time and meets the car 30 m ahead in the left lane only at about 1.1 s
    a = aff(gap_ego=20.0, gap_left=30.0)
    straight_on, swerve = straight(25.0), swerve_left()
    checked = SafetyConfig(check_fallback=True)
    c = choose(np.stack([straight_on, swerve]), np.array([0.7, 0.3]), a, 25.0, 0.0, checked)
    t_straight, t_swerve, t_brake = (v.t_s for v in c.verdicts)
    assert t_straight < t_brake < t_swerve and c.verdicts[1].lane == "left"
    assert c.source == "other mode" and np.array_equal(c.points, swerve)
    # by default the brake is driven unchecked
    old = choose(np.stack([straight_on, swerve]), np.array([0.7, 0.3]), a, 25.0, 0.0)
    assert old.source == "fallback" and len(old.verdicts) == 2


@settings(max_examples=60, deadline=None)
@given(
    speed=st.floats(0.0, 40.0),
    offset=st.floats(-2.0, 2.0),
    heading=st.floats(-0.3, 0.3),
    curvature=st.floats(-0.01, 0.01),
)
def test_keep_lane_braking_is_always_a_valid_trajectory(speed, offset, heading, curvature):
    cfg = SafetyConfig()
    pts = keep_lane_brake(aff(offset=offset, heading=heading), speed, curvature, cfg)
    assert pts.shape == (5, 2) and np.all(np.isfinite(pts))
    x = np.r_[0.0, pts[:, 0]]
    assert np.all(np.diff(x) >= -1e-12)  # never backwards
    steps = np.diff(x)
    assert np.all(np.diff(steps) <= 1e-9)  # never faster
    assert x[-1] <= speed * 1.5 + 1e-9
    # it ends on the lane centre: the lateral offset it removes is the car's
    delta = pts[-1, 1] + heading * pts[-1, 0] - curvature * pts[-1, 0] ** 2 / 2
    assert delta == pytest.approx(-offset, abs=1e-9)
    # braking into the lane to the left ends on that lane's centre, one lane width over
    a = aff(offset=offset, heading=heading)
    left = brake_to_lane(a, speed, curvature, 1, cfg)
    assert np.allclose(left[:, 0], pts[:, 0])  # the same braking along the road
    assert end_lateral(left, a, curvature) == pytest.approx(3.5, abs=1e-9)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="brake_mps2"):
        SafetyConfig(brake_mps2=0.0)
    with pytest.raises(ValueError, match="reaction_s"):
        SafetyConfig(reaction_s=-1.0)
    assert SafetyConfig().stopping_m(0.0) == SafetyConfig().margin_m
    assert not check(np.full((5, 2), np.nan), aff(), 10.0, 0.0).ok


class StraightOn:
    """A scripted unsafe driver: proposes to hold its lane at 20 m/s whatever is ahead."""

    camera = None

    def __init__(self) -> None:
        self.tracker = LQRTracker()
        self.last: dict = {}

    def reset(self, n_worlds: int) -> None:
        pass

    def fork(self, k: int) -> list:
        return [copy.copy(self) for _ in range(k)]

    def trajectories(self, obs: Observation) -> np.ndarray:
        lane_d = np.array([w.track.lane_center(int(k)) for w, k in zip(obs.worlds, obs.lane)])
        x = 20.0 * T[None, :].repeat(len(obs.s), 0)
        u = T / T[-1]
        delta = -(obs.d - lane_d)[:, None] * (u * u * (3 - 2 * u))[None]
        y = delta - obs.heading_error[:, None] * x + obs.curvature[:, None] * x**2 / 2
        pts = np.stack([x, y], axis=-1)
        self.last = {"points": pts}
        return pts

    def follow(self, points: np.ndarray, obs: Observation) -> Actuation:
        e, psi, kappa, v_ref, a_ref = trajectory_reference(points)
        steer = self.tracker.steer(e, psi, kappa, obs.speed)
        return Actuation(steer, self.tracker.accel(obs.speed, v_ref, a_ref))

    def act(self, obs: Observation) -> Actuation:
        return self.follow(self.trajectories(obs), obs)


def test_the_module_makes_a_scripted_unsafe_driver_collide_less():
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    guarded = SafeAgent(StraightOn(), ground_truth=True)
    safe = evaluate(guarded, world, cfg, progress=False, workers=2)
    assert alone.car_collisions >= 3  # the scripted driver is unsafe (4-5 on the machines tried)
    assert safe.collisions < alone.collisions / 2
    stats = SafetyStats.from_info(safe.info).to_dict()
    assert stats["interventions"] > 0 and stats["sources"]["fallback"] > 0
    assert stats["decisions"] == round(safe.sim_time_s / 0.1)
    # every collision is told to the policy with the next decision: who drove into it
    assert sum(stats["at_impact"].values()) == safe.collisions
    # and how many of its last 30 decisions the module overrode
    assert sum(stats["before_impact"].values()) == safe.collisions
    assert all(0 <= int(n) <= 30 for n in stats["before_impact"])
    assert sum(int(n) * c for n, c in stats["before_impact"].items()) <= stats["interventions"]
    assert set(stats["at_impact"]) <= {"network", "other mode", "fallback"}


class Watched(SafeAgent):
    """The module, keeping each decision's sources and commanded accelerations."""

    def act(self, obs: Observation) -> Actuation:
        out = super().act(obs)
        self.__dict__.setdefault("seen", []).append((list(self.last["sources"]), out.accel_mps2))
        return out


def test_an_emergency_brake_stops_where_the_trackers_brake_cannot():
    """Parked cars seen from 28 m only, at 20 m/s: braking at the tracker's 6 m/s^2 needs
    4 + 33 + 2 m to stop, the car's full 8 m/s^2 4 + 25 + 2 m."""
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    runs = {}
    for emergency in (None, 8.0):
        how = SafetyConfig(gap_free_m=28.0, fallback_lanes=False, emergency_brake_mps2=emergency)
        agent = Watched(StraightOn(), how, ground_truth=True)
        runs[emergency] = (evaluate(agent, world, cfg, progress=False), agent.seen)
    tracker_brake, emergency = runs[None][0], runs[8.0][0]
    assert tracker_brake.car_collisions >= 3 and emergency.collisions == 0  # (4 and 0 here)
    for sources, accel in runs[8.0][1]:  # the fallback's cars at -8, every other as tracked
        fallback = np.array(sources) == "fallback"
        assert np.all(accel[fallback] == -8.0) and np.all(accel[~fallback] >= -6.0)
    assert any("fallback" in sources for sources, _ in runs[8.0][1])
    assert "emergency_brake_mps2=8.0" in repr(SafetyConfig(emergency_brake_mps2=8.0))
    assert "emergency" not in repr(SafetyConfig())  # stored results keep their keys
    with pytest.raises(ValueError, match="emergency_brake_mps2"):
        SafetyConfig(emergency_brake_mps2=0.0)


def test_the_speed_cap_alone_slows_the_driver_and_unchecked_it_is_the_driver_alone():
    """``check_proposals=False`` is the control: without ``sight_speed`` it drives exactly what
    the driver alone drives; with it, the same paths no faster than the sight allows."""
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    off = SafetyConfig(check_proposals=False)
    unchecked = evaluate(SafeAgent(StraightOn(), off, ground_truth=True), world, cfg,
                         progress=False)  # fmt: skip
    assert unchecked.events == alone.events and unchecked.collisions == alone.collisions >= 3
    assert SafetyStats.from_info(unchecked.info).interventions == 0
    short = SafetyConfig(gap_free_m=25.0, sight_speed=True, check_proposals=False)
    assert 15.0 < short.sight_speed_mps() < 16.0  # StraightOn proposes 20 m/s
    capped = evaluate(SafeAgent(StraightOn(), short, ground_truth=True), world, cfg,
                      progress=False)  # fmt: skip
    assert SafetyStats.from_info(capped.info).interventions == 0
    assert capped.mean_speed_mph < 0.85 * alone.mean_speed_mph
    # (about 0.2 m/s over the cap: each placed car starts at 20 m/s and takes a second to slow)
    assert capped.mean_speed_mph * 0.44704 <= short.sight_speed_mps() + 0.5
    assert "sight_speed=True" in repr(short) and "check_proposals=False" in repr(short)
    assert "sight_speed" not in repr(SafetyConfig())  # stored results keep their keys


def test_the_rollout_tells_the_policy_of_each_collision_with_its_next_decision():
    class Counting(StraightOn):
        told = 0

        def act(self, obs: Observation) -> Actuation:
            assert obs.collided is not None and np.all(obs.respawned[obs.collided])
            Counting.told += int(obs.collided.sum())
            return super().act(obs)

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    res = evaluate(Counting(), world, EvalConfig(miles=1.0, n_worlds=2, n_tracks=2), progress=False)
    assert res.collisions >= 3 and Counting.told == res.collisions


def test_a_guarded_evaluation_is_stored_with_what_the_module_reported(tmp_path, monkeypatch):
    from e2e_lite.driving.metrics import result_info
    from e2e_lite.experiments.ablation import evaluate_stored, fingerprint

    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path))
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=0.3, n_worlds=2, n_tracks=2)
    guarded = SafeAgent(StraightOn(), ground_truth=True)
    first = evaluate_stored("guarded", "guarded", guarded, world, cfg, progress=False, workers=1)
    again = evaluate_stored("guarded", "guarded", guarded, world, cfg, progress=False, workers=1)
    assert not isinstance(again, type(first)) and again["collisions"] == first.collisions
    stored = SafetyStats.from_info(result_info(again)).to_dict()
    assert stored == SafetyStats.from_info(first.info).to_dict() and stored["interventions"] > 0
    assert result_info(again)["examples"] == first.info["examples"]
    # the module's settings and audits are part of the driver's identity
    other = SafeAgent(StraightOn(), SafetyConfig(fallback_lanes=False), ground_truth=True)
    assert fingerprint(other) != fingerprint(guarded)
    assert fingerprint(SafeAgent(StraightOn(), ground_truth=True, audit_every=4)) != fingerprint(
        guarded
    )


class BlindToCars(StraightOn):
    """StraightOn with an affordance "head" that is exact but sees no parked car (every gap at the
    cap)."""

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        seen[:, [AFFORDANCE_NAMES.index(g) for g in GAP_NAMES]] = 60.0
        self.last["affordances"] = seen
        return pts


class Ghosts(StraightOn):
    """StraightOn with an exact affordance head that sees a car 10 m ahead in its own lane on
    every decision (``every=1``) or on every other one (``every=2``: a flickering false alarm)."""

    def __init__(self, every: int) -> None:
        super().__init__()
        self.every, self.calls = every, 0

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        if self.calls % self.every == 0:
            seen[:, AFFORDANCE_NAMES.index("gap_ego_m")] = 10.0
        self.calls += 1
        self.last["affordances"] = seen
        return pts


#: an empty straight road, driven by :class:`Ghosts` under the module (the filter and hold tests)
GHOST_WORLD = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(0, 0)))
GHOST_RUN = EvalConfig(miles=0.3, n_worlds=2, n_tracks=2)


def drive_ghosts(settings: SafetyConfig) -> dict[int, EvalResult]:
    """The module with ``settings`` over a lasting ghost (key 1) and a flickering one (key 2)."""
    return {
        every: evaluate(
            SafeAgent(Ghosts(every), settings, audit=False), GHOST_WORLD, GHOST_RUN, progress=False
        )
        for every in (1, 2)
    }


def test_a_persistence_filter_ignores_flickering_alarms_and_acts_on_lasting_ones():
    alone = evaluate(StraightOn(), GHOST_WORLD, GHOST_RUN, progress=False)
    twice = SafetyConfig(confirm_decisions=2)
    runs = {how.confirm_decisions: drive_ghosts(how) for how in (SafetyConfig(), twice)}
    n = {
        (every, confirm): SafetyStats.from_info(res.info).interventions
        for confirm, by_ghost in runs.items()
        for every, res in by_ghost.items()
    }
    # every alarm alone: the driver drives
    assert runs[2][2].events == alone.events and runs[2][2].miles == alone.miles
    assert n[2, 1] > 0 and n[2, 2] == 0  # flickering: heeded at once, ignored when confirmed
    # lasting: heeded either way, from the second decision on when confirmed
    assert 0 < n[1, 2] < n[1, 1]
    assert "confirm_decisions" not in repr(SafetyConfig()) and "confirm_decisions=2" in repr(twice)
    with pytest.raises(ValueError, match="confirm_decisions"):
        SafetyConfig(confirm_decisions=0)


def test_a_hold_after_an_alarm_brakes_through_a_flickering_one():
    held = SafetyConfig(release_decisions=3)
    stats = {
        (every, how.release_decisions): (res, SafetyStats.from_info(res.info))
        for how in (SafetyConfig(), held)
        for every, res in drive_ghosts(how).items()
    }
    # flickering: heeded every other decision, then held in between (braking on its own path)
    flicker, flicker_held = stats[2, 1][1], stats[2, 3][1]
    assert flicker.sources["network"] > 0 and "hold" not in flicker.sources
    assert flicker_held.sources["hold"] == flicker_held.kinds["hold"] > 0
    assert flicker_held.sources["network"] < flicker.sources["network"] / 10
    assert stats[2, 3][0].mean_speed_mph < stats[2, 1][0].mean_speed_mph
    # lasting: never a pass, so never a hold: the same drive
    assert stats[1, 3][0].events == stats[1, 1][0].events
    assert stats[1, 3][1].to_dict() == stats[1, 1][1].to_dict()
    # no alarm, no hold: the driver alone
    alone = evaluate(StraightOn(), GHOST_WORLD, GHOST_RUN, progress=False)
    quiet = evaluate(SafeAgent(Exact(), held, audit=False), GHOST_WORLD, GHOST_RUN, progress=False)
    assert quiet.events == alone.events and quiet.miles == alone.miles
    assert SafetyStats.from_info(quiet.info).interventions == 0
    assert "release_decisions" not in repr(SafetyConfig()) and "release_decisions=3" in repr(held)
    with pytest.raises(ValueError, match="release_decisions"):
        SafetyConfig(release_decisions=0)


def test_the_decisions_before_each_collision_are_traced_without_changing_the_drive():
    from e2e_lite.experiments.ablation import fingerprint

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    plain = evaluate(SafeAgent(BlindToCars(), audit=False), world, cfg, progress=False)
    traced_agent = SafeAgent(BlindToCars(), audit=False, trace_before_impact=5)
    traced = evaluate(traced_agent, world, cfg, progress=False)
    assert traced.events == plain.events and traced.collisions >= 3
    traces = traced.info["traces"]
    # one trace per collision (one on the very last decision may go unreported), 5 decisions
    assert traced.collisions - cfg.n_worlds <= len(traces) <= traced.collisions
    assert all(1 <= len(t) <= 5 for t in traces) and sum(len(t) == 5 for t in traces) > 0
    speeds = sorted(e["speed_mps"] for e in traced.events)
    for trace in traces:
        times = [r["time_s"] for r in trace]
        assert times == sorted(times) and len(set(times)) == len(times)
        last = trace[-1]
        # blind to cars: the perceived check passes; the rule on the truth sees the car
        assert all(r["perceived"] == "ok" and r["source"] == "network" for r in trace)
        assert last["rule_on_truth"] in ("cannot stop", "collision course")
        gap = AFFORDANCE_NAMES.index("gap_ego_m")
        assert last["seen"][gap] == 60.0 and last["true"][gap] < 20.0
        assert min(speeds) - 1.0 <= last["speed_mps"]
        # where the car was: its own world again, the same road position
        w = make_world(world, *last["track_id"])
        x, y, _ = last["pose"]
        assert abs(float(w.track.to_frenet(x, y)[0]) - last["s"]) < 0.1
    assert "traces" not in plain.info
    assert fingerprint(traced_agent) != fingerprint(SafeAgent(BlindToCars(), audit=False))
    with pytest.raises(ValueError, match="trace_before_impact"):
        SafeAgent(BlindToCars(), trace_before_impact=-1)


class Exact(StraightOn):
    """StraightOn with an exact affordance head."""

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        self.last["affordances"] = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        return pts


class Seer(StraightOn):
    """A perception network's stand-in: exact affordances (``blind``: every gap at the cap), and
    a trajectory that swerves 3 m left (never to be driven)."""

    def __init__(self, blind: bool = False) -> None:
        super().__init__()
        self.blind = blind

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs) + np.array([0.0, 3.0])
        seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        if self.blind:
            seen[:, [AFFORDANCE_NAMES.index(g) for g in GAP_NAMES]] = 60.0
        self.last = {"points": pts, "affordances": seen}
        return pts


def test_a_separate_perception_network_feeds_the_check_and_never_drives():
    from e2e_lite.experiments.ablation import fingerprint
    from e2e_lite.simulation.camera import CameraConfig

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    truth = evaluate(SafeAgent(StraightOn(), ground_truth=True, audit=False), world, cfg,
                     progress=False)  # fmt: skip
    # a driver blind to cars, checked on an exact seer's affordances: the ground-truth module
    seeing = SafeAgent(BlindToCars(), seer=Seer(), audit=False)
    seen = evaluate(seeing, world, cfg, progress=False)
    assert seen.events == truth.events and seen.collisions < alone.collisions
    assert SafetyStats.from_info(seen.info).interventions == (
        SafetyStats.from_info(truth.info).interventions
    )
    # a seer blind to cars: never an intervention, the driver alone (not the seer's swerve)
    blind = evaluate(SafeAgent(StraightOn(), seer=Seer(blind=True), audit=False), world, cfg,
                     progress=False)  # fmt: skip
    assert blind.events == alone.events and blind.collisions == alone.collisions >= 3
    assert SafetyStats.from_info(blind.info).interventions == 0
    assert fingerprint(seeing) != fingerprint(SafeAgent(BlindToCars(), audit=False))
    # the vote: the driver's own head must agree; blind to cars, it never does
    vetoed = evaluate(SafeAgent(BlindToCars(), seer=Seer(), vote=SafetyConfig(), audit=False), world, cfg,
                      progress=False)  # fmt: skip
    assert vetoed.events == alone.events
    assert SafetyStats.from_info(vetoed.info).interventions == 0
    # an exact head agrees with an exact seer: the ground-truth module again
    agreed = evaluate(SafeAgent(Exact(), seer=Seer(), vote=SafetyConfig(), audit=False), world, cfg,
                      progress=False)  # fmt: skip
    assert agreed.events == truth.events
    with_vote = SafeAgent(Exact(), seer=Seer(), vote=SafetyConfig())
    assert fingerprint(with_vote) != fingerprint(SafeAgent(Exact(), seer=Seer()))
    with pytest.raises(ValueError, match="vote needs a seer"):
        SafeAgent(Exact(), vote=SafetyConfig())
    other_camera = Seer()
    other_camera.camera = CameraConfig(width_px=100)
    with pytest.raises(ValueError, match="same frame"):
        SafeAgent(StraightOn(), seer=other_camera)


def test_true_affordances_replace_only_the_named_predictions():
    from e2e_lite.experiments.ablation import fingerprint

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    blind = evaluate(SafeAgent(BlindToCars(), audit=False), world, cfg, progress=False)
    truth = evaluate(SafeAgent(StraightOn(), ground_truth=True, audit=False), world, cfg,
                     progress=False)  # fmt: skip
    mended = SafeAgent(BlindToCars(), true_affordances=GAP_NAMES, audit=False)
    fixed = evaluate(mended, world, cfg, progress=False)
    # blind to cars, the module never intervenes: the driver alone, collision for collision
    assert blind.collisions == alone.collisions >= 3
    assert SafetyStats.from_info(blind.info).interventions == 0
    assert SafetyStats.from_info(blind.info).before_impact == {"0": blind.collisions}
    # given the true gaps (the rest was exact already), it is the ground-truth module
    assert fixed.collisions == truth.collisions < alone.collisions
    assert (
        SafetyStats.from_info(fixed.info).to_dict() == SafetyStats.from_info(truth.info).to_dict()
    )
    assert fingerprint(mended) != fingerprint(SafeAgent(BlindToCars(), audit=False))
    with pytest.raises(ValueError, match="not affordances"):
        SafeAgent(BlindToCars(), true_affordances=("gap_ahead",))


def test_the_fused_heading_is_the_cameras_at_cruise_and_the_gyros_when_slow():
    one = np.ones(3)
    last, camera, turned = 0.10 * one, np.array([0.0, 0.0, 0.3]), 0.02 * one
    speed, kappa = np.array([GYRO_FULL_SPEED_MPS, 0.0, 30.0]), np.array([0.0, 0.0, 0.01])
    fused = fuse_heading(last, camera, turned, speed, kappa, 0.1)
    assert fused[0] == camera[0] and fused[2] == camera[2]  # at and above cruise: the camera
    g = GYRO_MIN_CAMERA_WEIGHT  # at standstill: mostly the gyro's prediction
    assert fused[1] == pytest.approx((1 - g) * (0.10 + 0.02) + g * 0.0)
    # the road turning under a moving car turns the heading to the lane the other way
    half = GYRO_FULL_SPEED_MPS / 2
    at_half = fuse_heading(last[:1], camera[:1], turned[:1], np.array([half]), kappa[2:], 0.1)
    assert at_half[0] == pytest.approx(0.75 * (0.12 - 0.01 * half * 0.1))
    # a fixed camera weight: the same blend at every speed, cruise included
    fixed = fuse_heading(last, camera, turned, speed, kappa, 0.1, camera_weight=0.1)
    predicted = last + turned - kappa * speed * 0.1
    assert fixed == pytest.approx(0.9 * predicted + 0.1 * camera)
    assert fused[0] != pytest.approx(fixed[0])
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="gyro_camera_weight"):
            SafetyConfig(gyro_heading=True, gyro_camera_weight=bad)
    assert "gyro_camera_weight" not in repr(SafetyConfig(gyro_heading=True))  # keys kept


class NoisyHeading(StraightOn):
    """StraightOn with exact affordances except the heading, misread by N(0, 0.05 rad) each
    decision (independently: what a gyro can average away)."""

    def __init__(self) -> None:
        super().__init__()
        self.rng = np.random.default_rng(0)

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        seen[:, AFFORDANCE_NAMES.index("heading_rad")] += self.rng.normal(0.0, 0.05, len(seen))
        self.last["affordances"] = seen
        return pts


def test_the_gyro_heading_averages_away_a_noisy_camera_and_restarts_with_each_car():
    col = AFFORDANCE_NAMES.index("heading_rad")
    rows = []

    class Recording(SafeAgent):
        def act(self, obs: Observation) -> Actuation:
            out = super().act(obs)
            truth = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)[:, col]
            camera, fused = self.agent.last["affordances"][:, col], self.last["seen"][:, col]
            rows.append((camera - truth, fused - truth, obs.respawned.copy(), camera, fused))
            return out

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=0.5, n_worlds=2, n_tracks=2)
    agent = Recording(NoisyHeading(), SafetyConfig(gyro_heading=True), audit=False)
    evaluate(agent, world, cfg, progress=False)
    cam_err, fused_err = (np.concatenate([r[k] for r in rows]) for k in (0, 1))
    rmse = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rmse(fused_err) < 0.8 * rmse(cam_err)  # about 0.7 at 20 m/s (g = 0.64)
    respawned = np.concatenate([r[2] for r in rows])
    assert respawned.sum() >= 2  # (the start, at least)
    camera, fused = (np.concatenate([r[k] for r in rows]) for k in (3, 4))
    assert np.array_equal(fused[respawned], camera[respawned])  # a placed car starts afresh
    assert not np.array_equal(fused[~respawned], camera[~respawned])
    from e2e_lite.experiments.ablation import fingerprint

    plain = SafeAgent(NoisyHeading(), audit=False)
    assert fingerprint(agent) != fingerprint(plain)
    assert "gyro_heading" not in repr(SafetyConfig())  # stored results keep their keys
    # trusting the camera a tenth at every speed averages more of its noise away
    rows.clear()
    steady = SafetyConfig(gyro_heading=True, gyro_camera_weight=0.1)
    evaluate(Recording(NoisyHeading(), steady, audit=False), world, cfg, progress=False)
    steady_err = np.concatenate([r[1] for r in rows])
    assert rmse(steady_err) < 0.6 * rmse(fused_err)


def test_the_perceived_check_needs_predicted_affordances():
    world = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(2, 2)))
    with pytest.raises(ValueError, match="affordances"):
        evaluate(SafeAgent(StraightOn()), world, EvalConfig(miles=0.01, n_worlds=1, n_tracks=1))


def test_the_module_counts_the_same_in_threads_and_in_processes():
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=0.5, n_worlds=2, n_tracks=2)
    runs = {}
    for parallel in ("threads", "processes"):
        guarded = SafeAgent(StraightOn(), ground_truth=True)
        res = evaluate(guarded, world, cfg, progress=False, workers=2, parallel=parallel)
        runs[parallel] = (res, SafetyStats.from_info(res.info).to_dict())
    (r_t, s_t), (r_p, s_p) = runs["threads"], runs["processes"]
    assert r_t.events == r_p.events and s_t == s_p and s_p["interventions"] > 0
    # a second evaluation of the same agent counts its own decisions, and the examples come
    # home from the worker processes, JSON-able, up to keep_examples per shard
    again = evaluate(guarded, world, cfg, progress=False, workers=2, parallel="processes")
    assert SafetyStats.from_info(again.info).to_dict() == s_p
    examples = again.info["examples"]
    assert 0 < len(examples) <= 2 * guarded.keep_examples and "info" not in again.to_dict()
    assert json.loads(json.dumps(examples)) == examples
    assert examples == r_t.info["examples"]  # the same in threads
    # the decisions' info adds up: numbers and Counters summed, lists concatenated
    total = add_info({}, {"n": 1, "sources": Counter(a=1), "examples": [1]})
    add_info(total, {"n": 2, "sources": Counter(a=1, b=1), "examples": [2]})
    assert total == {"n": 3, "sources": Counter(a=2, b=1), "examples": [1, 2]}
    with pytest.raises(TypeError, match="cannot add up"):
        add_info(total, {"n": "x"})


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), cap=st.floats(0.0, 40.0))
def test_capping_a_batch_equals_np_interp_on_each_path_to_the_bit(seed, cap):
    """The batched re-timing answers what np.interp answers per path, repeated points included."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform(0.0, 4.0, (6, 5, 2)) * rng.choice([0.0, 1.0], (6, 5, 1), p=[0.2, 0.8])
    paths = np.round(np.cumsum(steps * np.array([8.0, 0.5]), axis=1), int(rng.integers(0, 3)))
    limit = cap * 0.3 * np.arange(1, 6)  # (as cap_speed computes it: the same bits)
    for path, got in zip(paths, cap_speed(paths, cap)):
        poly = np.concatenate([np.zeros((1, 2)), path])
        along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poly, axis=0).T))])
        covered = np.minimum(np.minimum(along[1:], limit), along[-1])
        want = np.stack([np.interp(covered, along, poly[:, c]) for c in (0, 1)], axis=1)
        moved = np.any(np.abs(covered - along[1:]) > 1e-9)
        np.testing.assert_array_equal(got, want if moved else path)


class ProfileReader(BlindToCars):
    """BlindToCars (no lane gap ever short) with a free-space "head": the exact profile, or
    (``blind``) every strip at the cap."""

    profile_head = "exact"

    def __init__(self, blind: bool = False) -> None:
        super().__init__()
        self.blind = blind

    def trajectories(self, obs: Observation) -> np.ndarray:
        from e2e_lite.learning.freespace import N_STRIPS, free_profiles

        pts = super().trajectories(obs)
        exact = free_profiles(obs.worlds, obs.s, obs.d, obs.heading_error)
        self.last["profile"] = np.full_like(exact, 60.0) if self.blind else exact
        self.last["profile_free_m"] = np.full(N_STRIPS, 59.5)
        return pts


def test_the_module_can_read_parked_cars_from_a_free_space_profile():
    from e2e_lite.experiments.ablation import fingerprint

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2)
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    true = evaluate(SafeAgent(StraightOn(), ground_truth=True, audit=False, profile="true"), world,
                    cfg, progress=False)  # fmt: skip
    assert alone.collisions >= 3 and true.collisions < alone.collisions / 2
    assert SafetyStats.from_info(true.info).kinds  # it intervened for the cars it saw
    # an exact profile read by the driver drives as the true one; the lane gaps play no part
    # (the driver's own gaps see nothing)
    read = evaluate(SafeAgent(ProfileReader(), audit=False, profile="perceived"), world, cfg,
                    progress=False)  # fmt: skip
    assert read.events == true.events
    # a profile blind to cars: no intervention, the driver alone
    blind = evaluate(SafeAgent(ProfileReader(blind=True), audit=False, profile="perceived"),
                     world, cfg, progress=False)  # fmt: skip
    assert blind.events == alone.events
    assert SafetyStats.from_info(blind.info).interventions == 0
    plain = SafeAgent(StraightOn(), ground_truth=True, audit=False)
    assert fingerprint(plain) != fingerprint(
        SafeAgent(StraightOn(), ground_truth=True, audit=False, profile="true")
    )
    with pytest.raises(ValueError, match="profile_head"):
        SafeAgent(StraightOn(), ground_truth=True, profile="perceived")
    with pytest.raises(ValueError, match="profile="):
        SafeAgent(StraightOn(), ground_truth=True, profile="lidar")
