"""The expert, under each home-lane rule: collision-free driving, random sides, clean labels that
depend on the state alone, the oracle."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import straight_world

from e2e_lite.control import rules
from e2e_lite.control.expert import Expert, expert_labels
from e2e_lite.control.oracle import Oracle
from e2e_lite.control.rules import ExpertConfig, SpeedLimits, car_ahead, lane_clear, speed_profile
from e2e_lite.driving.evaluation import EvalConfig, evaluate, observe
from e2e_lite.learning.labels import CHANGE, KEEP, PASS
from e2e_lite.simulation.geometry import RoadConfig, Track
from e2e_lite.simulation.world import Fleet, TrafficConfig, World, WorldConfig, make_world

#: the expert under every home-lane rule (the course's is ``ExpertConfig().home``)
HOMES = pytest.mark.parametrize("home", rules.HOMES)


def expert_of(home: str, **kw) -> Expert:
    return Expert(ExpertConfig(home=home), **kw)


def small_world_cfg() -> WorldConfig:
    return WorldConfig(road=RoadConfig(length_m=2_000.0), traffic=TrafficConfig())


@HOMES
def test_expert_drives_seeded_tracks_without_collision(home):
    cfg = small_world_cfg()
    expert = expert_of(home)
    res = evaluate(expert, cfg, EvalConfig(miles=6.0, n_worlds=4, n_tracks=4), progress=False)
    assert res.collisions == 0 and res.stalls == 0
    assert expert.manoeuvres["left"] > 0 and expert.manoeuvres["right"] > 0
    assert res.mean_speed_mph > 45.0


@pytest.mark.parametrize("home", ("own", "middle"))
def test_both_sides_occur_when_both_are_free(home):
    """A parked car in the middle lane of a straight road: over many seeds the expert overtakes
    on the left in some runs and on the right in others (keeping right, it prefers the right)."""
    world = straight_world([300.0], [1], length=1_000.0)
    cfg = WorldConfig()
    sides = []
    for seed in range(16):
        fleet = Fleet([world], cfg)
        fleet.place(0, 100.0, 0.0, 25.0)
        expert = expert_of(home, seed=seed)
        expert.reset(1)
        side = 0
        for k in range(120):
            act = expert.act(observe(fleet, respawned=k == 0))
            decision = expert.decisions[0]
            if decision.state == CHANGE and side == 0:
                side = decision.side
            contacts = fleet.step(act.steer_rad, act.accel_mps2)
            assert not contacts[0]
        sides.append(side)
    assert sides.count(1) >= 3 and sides.count(-1) >= 3
    assert 0 not in sides


@HOMES
def test_trigger_distance_is_drawn_in_its_range(home):
    lane = 0 if home == "right" else 1  # (in its home lane, the car ahead in it)
    world = straight_world([400.0], [lane], length=1_000.0)
    starts = []
    for seed in range(10):
        fleet = Fleet([world], WorldConfig())
        fleet.place(0, 100.0, float(world.track.lane_center(lane)), 25.0)
        expert = expert_of(home, seed=seed)
        expert.reset(1)
        for k in range(200):
            obs = observe(fleet, respawned=k == 0)
            act = expert.act(obs)
            if expert.decisions[0].state == CHANGE:
                front = obs.s[0] + 3.6
                starts.append(400.0 - 2.25 - front)
                break
            fleet.step(act.steer_rad, act.accel_mps2)
    lo, hi = ExpertConfig().trigger_m
    assert len(starts) == 10
    assert min(starts) >= lo - 3.0 and max(starts) <= hi
    assert max(starts) - min(starts) > 5.0  # randomised, not one fixed distance


@HOMES
def test_blocked_expert_stops_behind_the_car(home):
    """Cars in all three lanes side by side: nothing is free, so it must stop, not crash."""
    world = straight_world([300.0, 302.0, 304.0], [0, 1, 2], length=1_000.0)
    fleet = Fleet([world], WorldConfig())
    fleet.place(0, 150.0, 0.0, 25.0)
    expert = expert_of(home)
    expert.reset(1)
    for k in range(300):
        act = expert.act(observe(fleet, respawned=k == 0))
        assert not fleet.step(act.steer_rad, act.accel_mps2)[0]
    s, _, _, _ = fleet.lane_frame()
    assert fleet.state[0, 3] < 0.5 and s[0] < 300.0 - 2.25 - 3.6


@HOMES
def test_label_on_a_straight_empty_road_is_constant_speed_points(home):
    world = straight_world([], [], length=1_000.0)
    fleet = Fleet([world], WorldConfig())
    v = ExpertConfig().top_speed_mps
    d = float(world.track.lane_center(0 if home == "right" else 1))  # (its home lane)
    fleet.place(0, 100.0, d, v)
    expert = expert_of(home)
    expert.reset(1)
    label = expert.trajectory_label(observe(fleet, respawned=True))
    expected = np.stack([v * 0.3 * np.arange(1, 6), np.zeros(5)], axis=-1)
    np.testing.assert_allclose(label[0], expected, atol=1e-6)


@HOMES
def test_label_is_the_clean_rollout_not_the_noisy_future(home):
    """Drive 1.5 s with a steering offset: the label taken at the start equals a noise-free
    replay, and differs from where the noisy car actually went."""
    world = straight_world([], [], length=1_000.0)
    cfg = WorldConfig()
    fleet = Fleet([world], cfg)
    fleet.place(0, 100.0, 0.0, 22.0)
    expert = expert_of(home)
    expert.reset(1)
    obs0 = observe(fleet, respawned=True)
    label = expert.trajectory_label(obs0)[0]
    # noise-free replay with the real machinery
    replay_fleet = Fleet([world], cfg)
    replay_fleet.place(0, 100.0, 0.0, 22.0)
    replay = expert_of(home)
    replay.reset(1)
    noisy_xy, clean_xy = [], []
    for k in range(15):
        act = expert.act(observe(fleet, respawned=k == 0))
        fleet.step(act.steer_rad + 0.02, act.accel_mps2)
        ract = replay.act(observe(replay_fleet, respawned=k == 0))
        replay_fleet.step(ract.steer_rad, ract.accel_mps2)
        if (k + 1) % 3 == 0:
            noisy_xy.append(fleet.state[0, :2] - obs0.state[0, :2])
            clean_xy.append(replay_fleet.state[0, :2] - obs0.state[0, :2])
    np.testing.assert_allclose(label, np.array(clean_xy), atol=1e-6)
    assert np.abs(label[:, 1] - np.array(noisy_xy)[:, 1]).max() > 0.5


def test_expert_labels_with_kept_speed_limits_are_the_same_and_profile_each_track_once(monkeypatch):
    """The safety module's audits ask the expert at every intervention; with the speed limits
    kept across calls they get the same labels, and each track's profile is computed once."""
    cfg = small_world_cfg()
    worlds = [make_world(cfg, "test", k) for k in range(2)]
    fleet = Fleet([worlds[0], worlds[0], worlds[1], worlds[1]], cfg)
    for i, (s, lane, v) in enumerate(((150.0, 0, 24.0), (600.0, 1, 18.0), (300.0, 2, 26.0),
                                       (900.0, 1, 12.0))):  # fmt: skip
        world = fleet.worlds[i]
        fleet.place(i, s, float(world.track.lane_center(lane)), v)
    obs = observe(fleet, respawned=True)
    calls = []
    real = rules.speed_profile
    monkeypatch.setattr(rules, "speed_profile", lambda *a, **k: calls.append(1) or real(*a, **k))
    plain = [expert_labels(obs, idx) for idx in ([0, 1], [2, 3], [0, 3])]
    assert len(calls) == 4  # a new expert computes every track it meets again
    calls.clear()
    limits = SpeedLimits(ExpertConfig())
    kept = [expert_labels(obs, idx, limits=limits) for idx in ([0, 1], [2, 3], [0, 3])]
    assert len(calls) == 2  # once per track
    for a, b in zip(plain, kept):
        np.testing.assert_array_equal(a, b)
    assert np.abs(plain[0][:, -1, 0]).min() > 10.0  # (the cars drive: a real label)


@HOMES
def test_a_label_depends_on_the_state_alone(home):
    """The same state, reached after two different histories (the expert's own drive, and a car
    placed there by hand before a new expert's first decision), gets the same label and the same
    decision: mid-overtake, and in the lane it overtook into (``pass``, or ``keep`` where that
    lane is its home), whatever its home lane."""
    world = straight_world([300.0, 600.0], [1, 1], length=1_000.0)
    cfg = WorldConfig()
    fleet = Fleet([world], cfg)
    fleet.place(0, 100.0, 0.0, 25.0)
    expert = expert_of(home, seed=3)
    expert.reset(1)
    seen = {}
    for k in range(200):
        obs = observe(fleet, respawned=k == 0)
        label = expert.trajectory_label(obs)
        act = expert.act(obs)
        state = expert.decisions[0].state
        kind = "change" if state == CHANGE else "after" if "change" in seen else None
        if kind and kind not in seen:
            seen[kind] = (fleet.state[0].copy(), int(fleet.seg[0]), label, expert.decisions[0])
        fleet.step(act.steer_rad, act.accel_mps2)
    assert set(seen) == {"change", "after"}
    assert seen["after"][3].state in (PASS, KEEP) and seen["after"][3].target != 1
    for car_state, seg, label, decision in seen.values():
        other = Fleet([world], cfg)
        other.state[0], other.seg[0] = car_state, seg
        fresh = expert_of(home, seed=3)
        fresh.reset(1)
        obs = observe(other, respawned=True)
        np.testing.assert_array_equal(fresh.trajectory_label(obs), label)
        fresh.act(obs)
        assert fresh.decisions[0] == decision


def test_the_experts_home_lane_is_its_own_the_middle_or_the_rightmost():
    """In a side lane with nothing ahead, the expert heads home to the middle lane (a return:
    a change, not an overtake); with ``home="own"`` it keeps the lane it is in; with
    ``home="right"`` it keeps the rightmost lane and heads there from the leftmost one lane at a
    time. Each drives validation roads without a collision when the tracker follows its labels."""
    world = straight_world([900.0], [2], length=1_000.0)
    found = {}
    for lane in (0, 2):
        fleet = Fleet([world], WorldConfig())
        fleet.place(0, 100.0, float(world.track.lane_center(lane)), 25.0)
        for home in rules.HOMES:
            expert = expert_of(home, seed=3)
            expert.reset(1)
            expert.act(observe(fleet, respawned=True))
            found[home, lane] = expert.decisions[0]
    assert found["middle", 0].state == CHANGE and found["middle", 0].target == 1
    assert not found["middle", 0].overtaking
    assert found["own", 0].state == KEEP and found["own", 0].target == 0
    assert found["own", 2].state == KEEP and found["own", 2].target == 2
    assert found["right", 0].state == KEEP and found["right", 0].target == 0
    assert found["right", 2].state == CHANGE and found["right", 2].target == 1
    assert not found["right", 2].overtaking
    ev = EvalConfig(miles=4.0, n_worlds=8, split="val")
    for home in ("own", "right"):
        res = evaluate(Oracle(expert_of(home)), small_world_cfg(), ev, progress=False)
        assert res.collisions == 0, home
    with pytest.raises(ValueError, match=r"ExpertConfig\.home"):
        ExpertConfig(home="left")


def test_the_oracle_on_the_experts_labels_drives_as_the_expert():
    """A label is a driver: the tracker following the expert's labels at every decision (the
    oracle) drives validation roads without a collision, as the expert does."""
    cfg = small_world_cfg()
    ev = EvalConfig(miles=4.0, n_worlds=8, split="val")
    expert = evaluate(Expert(), cfg, ev, progress=False, workers=1)
    oracle = evaluate(Oracle(Expert()), cfg, ev, progress=False, workers=1)
    assert expert.collisions == 0 and oracle.collisions == 0


def test_oracle_follows_the_labels_without_collision():
    cfg = small_world_cfg()
    res = evaluate(Oracle(), cfg, EvalConfig(miles=2.0, n_worlds=4, n_tracks=4), progress=False)
    assert res.collisions == 0 and res.mean_speed_mph > 45.0


def test_oracle_with_point_noise_and_a_preview_is_seeded_and_still_drives():
    cfg = small_world_cfg()
    ev = EvalConfig(miles=1.0, n_worlds=4, n_tracks=4)
    clean = evaluate(Oracle(), cfg, ev, progress=False)
    noisy = [
        evaluate(Oracle(preview_s=0.3, point_noise_m=0.2, seed=3), cfg, ev, progress=False)
        for _ in range(2)
    ]
    assert noisy[0].to_dict() == {
        **noisy[1].to_dict(),
        "wall_time_s": noisy[0].wall_time_s,
        "sim_miles_per_wall_s": noisy[0].sim_miles_per_wall_s,
        "timing_s": noisy[0].timing_s,
    }
    assert noisy[0].speed_hist != clean.speed_hist  # the noise changed the drive
    assert noisy[0].collisions == 0  # 20 cm of noise per point, read 0.3 s ahead, is harmless
    with pytest.raises(ValueError, match="preview_s"):
        Oracle(preview_s=-0.1)


def test_speed_profile_respects_the_friction_limit_and_brakes_ahead():
    # only the curvature matters here: a straight, a 100 m radius arc, a straight
    track = Track([0.0, 500.0, 600.0], [0.0] * 3, [0.0] * 3, [0.0, 1 / 100, 0.0], [500, 100, 500])
    cfg = ExpertConfig()
    v = speed_profile(track, cfg, step_m=5.0)
    assert v.max() == pytest.approx(cfg.top_speed_mps)
    assert np.all(v <= cfg.top_speed_mps + 1e-9)
    # consecutive speeds never need more than the planned deceleration
    assert np.all(v[:-1] ** 2 - v[1:] ** 2 <= 2 * cfg.curve_brake_mps2 * 5.0 + 1e-6)


def test_gap_helpers_on_a_constructed_scene():
    world: World = straight_world([100.0, 160.0], [1, 2], length=500.0)
    gap, j = car_ahead(world, 50.0, 1, 100.0)
    assert gap == pytest.approx(100.0 - 2.25 - 50.0) and j == 0
    assert car_ahead(world, 50.0, 0, 200.0) == (np.inf, -1)
    assert not lane_clear(world, 2, 150.0, 158.0) and lane_clear(world, 2, 150.0, 157.0)
    assert lane_clear(world, 0, 0.0, 400.0)


def test_bad_expert_settings_raise():
    with pytest.raises(ValueError, match=r"ExpertConfig\.trigger_m"):
        ExpertConfig(trigger_m=(60.0, 40.0))
    with pytest.raises(ValueError, match=r"ExpertConfig\.top_speed_mps"):
        ExpertConfig(top_speed_mps=0.0)


def test_the_expert_and_the_oracle_drive_alike_in_any_shards_and_count_their_manoeuvres():
    """Every car's draws are its own (seeded by its index), so the expert and the oracle drive the
    same events in one shard or in three worker processes; the manoeuvres started in the workers come back
    through the results' info."""
    from e2e_lite.driving.evaluation import close_shard_workers

    world = WorldConfig(road=RoadConfig(length_m=3_000.0))
    ev = EvalConfig(miles=3.0, n_worlds=24, n_tracks=6)
    for policy in (Expert(), Oracle(point_noise_m=0.3)):
        one = evaluate(policy, world, ev, progress=False, workers=1)
        three = evaluate(policy, world, ev, progress=False, workers=3, parallel="processes")
        assert one.events == three.events and one.miles == three.miles
        assert one.mean_speed_mph == three.mean_speed_mph
    close_shard_workers()
    expert = Expert()
    res = evaluate(expert, world, ev, progress=False, workers=3, parallel="processes")
    close_shard_workers()
    alone = evaluate(Expert(), world, ev, progress=False, workers=1)
    assert res.info["manoeuvres"] == alone.info["manoeuvres"]
    assert res.info["manoeuvres"]["left"] + res.info["manoeuvres"]["right"] > 0


def test_a_return_is_recorded_with_the_side_it_moves_to():
    """What the data records of the expert's decisions (home: the middle lane): the overtake's
    side, then the return's, which moves the other way."""
    world = straight_world([300.0], [1], length=1_000.0)
    fleet = Fleet([world], WorldConfig())
    fleet.place(0, 100.0, 0.0, 25.0)
    expert = expert_of("middle", seed=1)
    expert.reset(1)
    changes = []
    for k in range(400):
        act = expert.act(observe(fleet, respawned=k == 0))
        decision = expert.decisions[0]
        if decision.state == CHANGE and (decision.side, decision.overtaking) not in changes:
            changes.append((decision.side, decision.overtaking))
        fleet.step(act.steer_rad, act.accel_mps2)
    (side, overtake), (back, ret) = changes
    assert overtake and not ret and side in (1, -1) and back == -side
