"""The pymunk world: collisions counted once, no tunnelling, rails, range queries, determinism."""

from __future__ import annotations

import numpy as np
import pymunk
import pytest
from conftest import straight_world

from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import CAT_CAR, Fleet, TrafficConfig, WorldConfig, make_world

CFG = WorldConfig()


def drive(fleet: Fleet, periods: int, steer: float = 0.0, accel: float = 0.0) -> list:
    """Drive until the first collision event (or ``periods`` policy periods); return the events."""
    for _ in range(periods):
        ev = [e for e in fleet.step(np.full(len(fleet), steer), np.full(len(fleet), accel)) if e]
        if ev:
            return ev
    return []


def test_driving_into_a_parked_car_counts_exactly_once():
    world = straight_world([100.0], [1])
    fleet = Fleet([world], CFG)
    fleet.place(0, 0.0, 0.0, 15.0)
    first = drive(fleet, 80)  # 8 s at 15 m/s would pass 100 m: it must stop at the car
    assert first == [[("car", 0)]]
    # driving on while still touching does not begin a new contact: one contact, one event
    for _ in range(3):
        assert fleet.step(np.zeros(1), np.zeros(1)) == [[]]


def test_contact_at_the_right_place():
    world = straight_world([100.0], [1])
    fleet = Fleet([world], CFG)
    fleet.place(0, 0.0, 0.0, 10.0)
    drive(fleet, 200)
    front = fleet.state[0, 0] + CFG.vehicle.length_m - CFG.vehicle.rear_overhang_m
    rear_of_parked = 100.0 - 2.25
    assert rear_of_parked <= front <= rear_of_parked + 10.0 * CFG.sim.dt_s + 1e-9


def test_no_tunnelling_at_40_mps():
    world = straight_world([300.0], [1])
    fleet = Fleet([world], CFG)
    fleet.place(0, 0.0, 0.0, 40.0)
    events = drive(fleet, 100)
    assert len(events) == 1 and events[0][0] == ("car", 0)
    assert fleet.state[0, 0] < 300.0


def test_hitting_the_rail_counts():
    world = straight_world([], [])
    fleet = Fleet([world], CFG)
    fleet.place(0, 10.0, 0.0, 20.0)
    events = drive(fleet, 100, steer=0.05)  # a slow left turn into the left rail
    assert events[0] == [("rail", 1)]
    fleet.place(0, 10.0, 0.0, 20.0)
    events = drive(fleet, 100, steer=-0.05)
    assert events[0] == [("rail", 0)]


def test_no_obstacles_no_collisions():
    world = straight_world([500.0], [0])  # a car in another lane
    fleet = Fleet([world], CFG)
    fleet.place(0, 0.0, 0.0, 30.0)
    assert drive(fleet, 300) == []


def test_ego_box_follows_the_bicycle_state():
    world = straight_world([], [])
    fleet = Fleet([world], CFG)
    fleet.place(0, 0.0, 0.0, 20.0)
    drive(fleet, 20, steer=0.02)
    assert world.ego.position.x == pytest.approx(fleet.state[0, 0], abs=1e-9)
    assert world.ego.position.y == pytest.approx(fleet.state[0, 1], abs=1e-9)
    assert world.ego.angle == pytest.approx(fleet.state[0, 2], abs=1e-12)


def test_gap_ahead_on_a_straight_and_a_curve():
    world = straight_world([120.0, 200.0], [1, 2])
    assert world.gap_ahead(50.0, 1, 100.0) == pytest.approx(120.0 - 2.25 - 50.0, abs=1e-6)
    assert world.gap_ahead(50.0, 2, 200.0) == pytest.approx(200.0 - 2.25 - 50.0, abs=1e-6)
    assert world.gap_ahead(50.0, 0, 300.0) == np.inf
    assert world.gap_ahead(50.0, 1, 50.0) == np.inf  # out of range
    # on a generated (curvy) track every car is found at its own lane and distance
    w = make_world(WorldConfig(road=RoadConfig(length_m=4_000.0)), "val", 1)
    for s, lane, d in zip(w.cars.s, w.cars.lane, w.cars.d):
        gap = w.gap_ahead(s - 30.0, int(lane), 60.0)
        assert 30.0 - 2.25 - 0.5 <= gap <= 30.0 - 2.25 + 0.5, (s, lane, d, gap)


def test_gap_ahead_shrinks_with_every_step_towards_a_car_as_pymunk_sees_it():
    """Approaching a parked car, the gap falls by exactly the distance moved, down to the rear of
    the car's pymunk shape inside the lane band (found here by point queries on a fine grid). The
    old piece-wise segment query jumped by up to 9.9 m, or lost the car, near its pieces' starts."""
    w = make_world(WorldConfig(road=RoadConfig(length_m=4_000.0)), "val", 1)
    track, cars = w.track, w.cars
    band = track.lane_width / 2.0 - 0.3
    only_cars = pymunk.ShapeFilter(mask=CAT_CAR)
    for k in range(0, len(cars), max(1, len(cars) // 6)):
        lane, s_car = int(cars.lane[k]), float(cars.s[k])
        centre = float(track.lane_center(lane))
        grid = np.arange(s_car - 4.0, s_car + 1.0, 0.01)
        seen = np.zeros(len(grid), dtype=bool)
        for dd in centre + np.linspace(-band, band, 15):
            for j, p in enumerate(np.asarray(track.position(grid, dd)).reshape(-1, 2)):
                if not seen[j]:
                    seen[j] = w.space.point_query_nearest(tuple(p), 0.0, only_cars) is not None
        rear = float(grid[np.argmax(seen)])  # the shape's first point in the band
        assert seen.any() and rear < s_car
        for s0 in np.arange(rear - 45.0, rear - 0.5, 0.37):
            assert w.gap_ahead(float(s0), lane, 60.0) == pytest.approx(rear - s0, abs=0.06), (k, s0)
        assert w.gap_ahead(rear - 61.0, lane, 60.0) == np.inf  # out of range
        assert w.gap_ahead(s_car, lane, 60.0) == 0.0  # the body reaches past s_from


def test_parked_cars_follow_the_paper():
    cfg = WorldConfig(road=RoadConfig(length_m=20_000.0))
    for i in range(5):
        w = make_world(cfg, "train", i)
        assert 20 <= len(w.cars) <= 80
        gaps = np.diff(w.cars.s)
        assert np.all(gaps >= 50.0) and np.all(gaps <= 200.0)
        # never every lane blocked at one place: within any 50 m window at most one car
        assert np.all(gaps >= 50.0)


def test_same_seed_same_world_different_seed_different_world():
    a, b = make_world(CFG, "val", 4), make_world(CFG, "val", 4)
    assert np.array_equal(a.cars.x, b.cars.x) and np.array_equal(a.track.k, b.track.k)
    c = make_world(WorldConfig(road=RoadConfig(seed=1)), "val", 4)
    assert not np.array_equal(a.cars.s, c.cars.s)


def test_respawn_is_past_the_obstacle_on_a_free_lane():
    world = straight_world([100.0, 150.0], [1, 0])
    s, lane = world.respawn_pose(102.25, 0.0)
    assert s == pytest.approx(117.25)
    assert world.lane_free(s, lane, 20.0, 40.0)
    assert lane == 2  # lane 1 holds the obstacle, lane 0 a car 33 m ahead; lane 2 is as near
    world_free = straight_world([100.0], [1])
    assert world_free.respawn_pose(102.25, -1.0) == (pytest.approx(117.25), 0)  # nearest free


def test_traffic_config_validation():
    with pytest.raises(ValueError, match="spacing_m"):
        TrafficConfig(spacing_m=(200.0, 50.0))
    with pytest.raises(ValueError, match="n_cars"):
        TrafficConfig(n_cars=(-1, 5))
