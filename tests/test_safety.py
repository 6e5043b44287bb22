"""The safety module: the rule on hand-made cases, the fallback order, and fewer collisions."""

from __future__ import annotations

import copy
import json
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from e2e_lite.control.tracker import LQRTracker, trajectory_reference
from e2e_lite.driving.evaluation import Actuation, EvalConfig, Observation, evaluate
from e2e_lite.driving.metrics import add_info
from e2e_lite.imitation.collector import AFFORDANCE_NAMES, affordances
from e2e_lite.learning.labels import GAP_NAMES
from e2e_lite.safety.agent import IMPACT_CAUSES, SafeAgent, SafetyStats, impact_cause
from e2e_lite.safety.rule import (
    SafetyConfig,
    brake_along,
    brake_to_lane,
    calibrate_gap_free,
    check,
    choose,
    end_lateral,
    keep_lane_brake,
)
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig

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
    lane_only = SafetyConfig(fallback="keep-lane")
    c = choose(np.stack([unsafe, unsafe]), np.array([0.5, 0.5]), a, 25.0, 0.0, lane_only)
    assert c.source == "fallback" and len(c.verdicts) == 2
    assert np.allclose(c.points, keep_lane_brake(a, 25.0, 0.0))


def test_the_path_fallback_brakes_for_a_parked_car_on_the_networks_own_path():
    """The perceived module's fallback (chapter 11): the heaviest mode heads for a car 30 m
    ahead; the lanes beside look free, but the lane fallback would steer by perceived geometry.
    With ``fallback="path"`` the mode's own path is driven, braking."""
    along = SafetyConfig(fallback="path")
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
    with pytest.raises(ValueError, match="fallback"):
        SafetyConfig(fallback="swerve")


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
    from dataclasses import fields

    assert len(fields(SafetyConfig)) <= 12  # the course's lesson, not one switch per experiment
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
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2, split="val")
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    guarded = SafeAgent(StraightOn(), ground_truth=True)
    safe = evaluate(guarded, world, cfg, progress=False, workers=2)
    assert alone.car_collisions >= 3  # the scripted driver is unsafe (4-5 on the machines tried)
    assert safe.collisions < alone.collisions / 2
    stats = SafetyStats.from_info(safe.info).to_dict()
    assert stats["interventions"] > 0 and stats["sources"]["fallback"] > 0
    # one decision per car per period while it drives; both cars share a shard (one group of
    # FORWARD_GROUP), so the car that finished first is still asked until the other one ends
    periods = round(safe.sim_time_s / 0.1)  # the two cars' driven periods, summed
    assert periods <= stats["decisions"] <= 2 * periods
    # every collision is told to the policy with the next decision: who drove into it
    assert sum(stats["at_impact"].values()) == safe.collisions
    assert set(stats["at_impact"]) <= set(IMPACT_CAUSES)


def test_a_collision_is_classified_by_who_drove_and_how_long_after_an_intervention():
    """Issue 64: the module's own manoeuvre, the network within 2 s of a hand-back, or the
    network with the module silent (never intervened, or long ago)."""
    assert impact_cause("fallback", 0.0) == "fallback"
    assert impact_cause("other mode", 5.0) == "other mode"
    assert impact_cause("network", 20.0, 0.1) == "network after a hand-back"  # 2.0 s
    assert impact_cause("network", 21.0, 0.1) == "network, module silent"
    assert impact_cause("network", np.inf) == "network, module silent"


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
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2, split="val")
    runs = {}
    for emergency in (None, 8.0):
        how = SafetyConfig(gap_free_m=28.0, fallback="keep-lane", emergency_brake_mps2=emergency)
        agent = Watched(StraightOn(), how, ground_truth=True)
        runs[emergency] = (evaluate(agent, world, cfg, progress=False), agent.seen)
    tracker_brake, emergency = runs[None][0], runs[8.0][0]
    assert tracker_brake.car_collisions >= 3 and emergency.collisions == 0  # (4 and 0 here)
    for sources, accel in runs[8.0][1]:  # the fallback's cars at -8, every other as tracked
        fallback = np.array(sources) == "fallback"
        assert np.all(accel[fallback] == -8.0) and np.all(accel[~fallback] >= -6.0)
    assert any("fallback" in sources for sources, _ in runs[8.0][1])
    with pytest.raises(ValueError, match="emergency_brake_mps2"):
        SafetyConfig(emergency_brake_mps2=0.0)


def test_the_rollout_tells_the_policy_of_each_collision_with_its_next_decision():
    class Counting(StraightOn):
        told = 0

        def act(self, obs: Observation) -> Actuation:
            assert obs.collided is not None and np.all(obs.respawned[obs.collided])
            Counting.told += int(obs.collided.sum())
            return super().act(obs)

    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    res = evaluate(
        Counting(),
        world,
        EvalConfig(miles=1.0, n_worlds=2, n_tracks=2, split="val"),
        progress=False,
    )
    assert res.collisions >= 3 and Counting.told == res.collisions


def test_a_guarded_evaluation_is_stored_with_what_the_module_reported(
    tmp_path, monkeypatch, drives
):
    from e2e_lite.record.stored import evaluate_stored, fingerprint

    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path))
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=0.3, n_worlds=2, n_tracks=2, split="val")
    guarded = SafeAgent(StraightOn(), ground_truth=True)
    first = evaluate_stored("guarded", "guarded", guarded, world, cfg, progress=False, workers=1)
    again = evaluate_stored("guarded", "guarded", guarded, world, cfg, progress=False, workers=1)
    assert len(drives) == 1 and again.collisions == first.collisions  # read back, typed
    stored = SafetyStats.from_info(again.info).to_dict()
    assert stored == SafetyStats.from_info(first.info).to_dict() and stored["interventions"] > 0
    assert again.info["examples"] == first.info["examples"]
    # the module's settings and audits are part of the driver's identity
    other = SafeAgent(StraightOn(), SafetyConfig(fallback="keep-lane"), ground_truth=True)
    assert fingerprint(other) != fingerprint(guarded)
    assert fingerprint(SafeAgent(StraightOn(), ground_truth=True, audit_every=4)) != fingerprint(
        guarded
    )
    # and so is the module's results version: a change to what it computes bumps it
    before = fingerprint(guarded)
    monkeypatch.setattr(SafeAgent, "RESULTS_VERSION", SafeAgent.RESULTS_VERSION + 1)
    assert fingerprint(guarded) != before


class BlindToCars(StraightOn):
    """StraightOn with an affordance "head" that is exact but sees no parked car (every gap at the
    cap)."""

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        seen[:, [AFFORDANCE_NAMES.index(g) for g in GAP_NAMES]] = 60.0
        self.last["affordances"] = seen
        return pts


class Exact(StraightOn):
    """StraightOn with an exact affordance head."""

    def trajectories(self, obs: Observation) -> np.ndarray:
        pts = super().trajectories(obs)
        self.last["affordances"] = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        return pts


def test_the_perceived_module_is_as_good_as_what_it_perceives():
    """An exact affordance head drives exactly as the ground-truth module; a head blind to parked
    cars lets the unsafe driver collide as it does alone."""
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=1.0, n_worlds=2, n_tracks=2, split="val")
    alone = evaluate(StraightOn(), world, cfg, progress=False)
    truth = evaluate(SafeAgent(StraightOn(), ground_truth=True), world, cfg, progress=False)
    exact = evaluate(SafeAgent(Exact()), world, cfg, progress=False)
    blind = evaluate(SafeAgent(BlindToCars()), world, cfg, progress=False)
    assert exact.events == truth.events and truth.collisions < alone.collisions
    assert blind.collisions == alone.collisions >= 3  # (blind, it never intervenes)
    assert SafetyStats.from_info(blind.info).interventions == 0


def test_the_perceived_check_needs_predicted_affordances():
    world = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(2, 2)))
    with pytest.raises(ValueError, match="affordances"):
        evaluate(SafeAgent(StraightOn()), world, EvalConfig(miles=0.01, n_worlds=1, n_tracks=1))


def test_the_module_counts_the_same_in_threads_and_in_processes():
    world = WorldConfig(road=RoadConfig(length_m=2_500.0), traffic=TrafficConfig(n_cars=(12, 12)))
    cfg = EvalConfig(miles=0.5, n_worlds=2, n_tracks=2, split="val")
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
