"""The dataset: affordances, clean labels under noise, determinism, storage, torch view."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import straight_world

from e2e_lite.config import QUICK
from e2e_lite.control.rules import ExpertConfig
from e2e_lite.driving.evaluation import EvalConfig
from e2e_lite.imitation.collector import (
    AFFORDANCE_NAMES,
    GAP_CAP_M,
    DataConfig,
    DrivingDataset,
    NoiseConfig,
    affordances,
    car_quotas,
    collect,
    dataset_path,
    load_or_collect,
    road_lateral,
    situations,
    throttle_brake,
)
from e2e_lite.learning.dataset import oversampled
from e2e_lite.learning.labels import CHANGE
from e2e_lite.simulation.geometry import generate_track
from e2e_lite.simulation.vehicle import VehicleParams


def small_cfg(**kw) -> DataConfig:
    base = DataConfig.for_profile(QUICK, n_samples=96, n_worlds=4)
    return dataclasses.replace(base, **kw)


def test_affordances_on_a_constructed_scene():
    # ego rear axle at s=100, 0.3 m left of the middle lane's centre; cars ahead in the middle
    # lane (centre s=140) and the left lane (s=130); the right lane is empty
    world = straight_world([140.0, 130.0], [1, 2], length=500.0)
    aff = affordances([world], np.array([100.0]), np.array([0.3]), np.array([0.02]))[0]
    named = dict(zip(AFFORDANCE_NAMES, aff))
    veh = VehicleParams()
    front = 100.0 + veh.length_m - veh.rear_overhang_m
    assert named["heading_rad"] == pytest.approx(0.02)
    assert named["center_offset_m"] == pytest.approx(0.3)
    assert named["left_marking_m"] == pytest.approx(1.85 - 0.3)
    assert named["right_marking_m"] == pytest.approx(1.85 + 0.3)
    assert named["left_edge_m"] == pytest.approx(5.55 - 0.3)
    assert named["right_edge_m"] == pytest.approx(5.55 + 0.3)
    assert named["gap_ego_m"] == pytest.approx(140.0 - 2.25 - front, abs=1e-3)
    assert named["gap_left_m"] == pytest.approx(130.0 - 2.25 - front, abs=1e-3)
    assert named["gap_right_m"] == GAP_CAP_M


def test_affordances_encode_missing_lanes_and_cars_alongside():
    # ego in the left lane; a car alongside in the middle lane
    world = straight_world([101.0], [1], length=500.0)
    aff = affordances([world], np.array([100.0]), np.array([3.7]), np.array([0.0]))[0]
    named = dict(zip(AFFORDANCE_NAMES, aff))
    assert named["gap_left_m"] == 0.0  # no lane there
    assert named["gap_right_m"] == 0.0  # a car alongside
    assert named["gap_ego_m"] == GAP_CAP_M


def test_collection_is_deterministic_and_labels_are_clean():
    cfg = small_cfg(noise=NoiseConfig(rate_per_s=2.0))
    a, b = collect(cfg, progress=False), collect(cfg, progress=False)
    for name in a.arrays:
        np.testing.assert_array_equal(a.arrays[name], b.arrays[name], err_msg=name)
    assert len(a) == 96 and a.images.shape == (96, 66, 200, 3) and a.images.dtype == np.uint8
    assert a.noise.mean() > 0.3
    # under noise, the label still starts where the expert's clean plan goes: the first point
    # is ahead of the car at about the speed times 0.3 s
    first = a.trajectory[:, 0]
    np.testing.assert_allclose(first[:, 0], a.speed * 0.3, rtol=0.1, atol=0.3)
    # the actuator label is the clean command, within the car's limits
    assert np.all(np.abs(a.actuators[:, 0]) <= VehicleParams().max_steer_rad)


def test_one_and_two_collecting_processes_make_the_same_bytes():
    """Issue 56: each car records its own quota from its own draws, car after car, so the arrays
    do not depend on how many processes collect them."""
    from e2e_lite.driving.evaluation import close_shard_workers

    cfg = small_cfg(n_samples=150, n_worlds=5, noise=NoiseConfig(rate_per_s=1.0))
    one, two = collect(cfg, progress=False, workers=1), collect(cfg, progress=False, workers=2)
    close_shard_workers()
    for name in one.arrays:
        np.testing.assert_array_equal(one.arrays[name], two.arrays[name], err_msg=name)
    assert one.info["manoeuvres"] == two.info["manoeuvres"]
    assert one.info["collection"]["miles"] == two.info["collection"]["miles"]
    assert car_quotas(cfg).tolist() == [30] * 5 and car_quotas(small_cfg(n_samples=7)).tolist() == [
        2,
        2,
        2,
        1,
    ]
    with pytest.raises(ValueError, match="workers"):
        collect(cfg, progress=False, workers=0)


def test_noise_changes_the_states_but_not_what_labels_mean():
    quiet = collect(small_cfg(noise=NoiseConfig(rate_per_s=0.0)), progress=False)
    noisy = collect(small_cfg(noise=NoiseConfig(rate_per_s=2.0)), progress=False)
    assert not quiet.noise.any()
    off_quiet = np.abs(quiet.affordances[:, 1])[quiet.expert_state != CHANGE]
    off_noisy = np.abs(noisy.affordances[:, 1])[noisy.expert_state != CHANGE]
    assert off_noisy.mean() > off_quiet.mean()


def test_train_and_validation_tracks_never_overlap():
    cfg = small_cfg()
    train = [generate_track(cfg.world.road, "train", i) for i in range(8)]
    val = [generate_track(cfg.world.road, "val", i) for i in range(8)]
    train_sig = {tuple(np.round(t.seg_len, 6)) for t in train}
    assert not train_sig & {tuple(np.round(t.seg_len, 6)) for t in val}
    data = collect(cfg, progress=False)
    assert data.info["split"] == "train" and set(np.unique(data.track)) <= set(range(cfg.n_tracks))
    assert DataConfig.for_profile(QUICK, "val").key != DataConfig.for_profile(QUICK, "train").key
    # the expert's home lane keys a dataset, and changes its labels where a car is in a side lane
    own = DataConfig.for_profile(QUICK, "train")
    middle = DataConfig.for_profile(QUICK, "train", expert=ExpertConfig(home="middle"))
    assert own.expert.home == "own" and middle.key != own.key
    mid = collect(dataclasses.replace(cfg, expert=ExpertConfig(home="middle")), progress=False)
    returns = [(d.expert_state == CHANGE) & ~d.overtaking for d in (data, mid)]
    assert not returns[0].any() and returns[1].any()  # keeping its own lane, it never returns


def test_dataset_is_saved_reused_and_rebuilt_on_other_settings(capsys):
    cfg = small_cfg()
    first = load_or_collect(cfg, progress=False)
    assert dataset_path(cfg).exists()
    again = load_or_collect(cfg, progress=False)
    np.testing.assert_array_equal(first.images, again.images)
    for name, value in first.stats.items():
        np.testing.assert_array_equal(value, again.stats[name])
    assert again.info["shares"] == first.info["shares"]
    assert "rebuilding" not in capsys.readouterr().out
    load_or_collect(dataclasses.replace(cfg, seed=5), progress=False)
    assert "other settings" in capsys.readouterr().out


def test_a_saved_dataset_is_compressed_and_a_raw_one_still_loads(tmp_path):
    from e2e_lite.learning.dataset import load_dataset, save_dataset, synthetic_data

    data = synthetic_data(32)
    data.arrays["images"][:] = 90  # the camera's flat colours (random noise would not deflate)
    save_dataset(tmp_path / "d.npz", data, key="k")
    raw = sum(a.nbytes for a in data.arrays.values())
    assert (tmp_path / "d.npz").stat().st_size < raw / 10
    back, key = load_dataset(tmp_path / "d.npz")
    assert key == "k"
    for name, array in data.arrays.items():
        np.testing.assert_array_equal(array, back.arrays[name])
    np.savez(tmp_path / "raw.npz", **np.load(tmp_path / "d.npz"))  # as earlier versions wrote
    np.testing.assert_array_equal(load_dataset(tmp_path / "raw.npz")[0].images, data.images)


def test_stats_and_shares():
    data = collect(small_cfg(), progress=False)
    assert data.stats["trajectory_mean"].shape == (5, 2)
    assert data.stats["affordances_std"].shape == (len(AFFORDANCE_NAMES),)
    assert np.all(data.stats["trajectory_std"] > 0)
    shares = data.info["shares"]
    assert all(0.0 <= v <= 1.0 for v in shares.values())
    assert shares["overtake_left"] + shares["overtake_right"] + shares["return"] == pytest.approx(
        shares["lane_change"]
    )
    # the lines a chapter prints leave out what the course's expert never does (returns,
    # passing) while it is 0, and show it when a dataset has some
    from e2e_lite.imitation.collector import describe

    none = {**data.info, "shares": {**shares, "return": 0.0, "pass": 0.0}}
    some = {**data.info, "shares": {**shares, "return": 0.02, "pass": 0.05}}
    quiet, told = (
        describe(dataclasses.replace(data, info=none)),
        describe(dataclasses.replace(data, info=some)),
    )
    assert "return" not in quiet and "passing" not in quiet and "following" in quiet
    assert "return 2.0%" in told and "passing 5.0%" in told


def test_torch_view_shapes():
    data = collect(small_cfg(), progress=False)
    ds = DrivingDataset(data, np.arange(10, 20))
    item = ds[3]
    assert len(ds) == 10
    assert item["image"].shape == (3, 66, 200) and str(item["image"].dtype) == "torch.uint8"
    assert item["trajectory"].shape == (10,) and item["affordances"].shape == (9,)
    np.testing.assert_array_equal(item["image"].numpy(), data.images[13].transpose(2, 0, 1))
    batch = ds.batch(np.array([0, 5]))
    assert batch["speed"].shape == (2, 1) and batch["actuators"].shape == (2, 2)


def test_throttle_brake_recovered_from_acceleration():
    veh = VehicleParams()
    thr, brk = throttle_brake(np.array([1.5, -4.0, 0.0]), veh)
    np.testing.assert_allclose(thr, [1.5 / veh.max_accel_mps2, 0, 0])
    np.testing.assert_allclose(brk, [0, 4.0 / veh.max_brake_mps2, 0])


def test_bad_data_settings_raise():
    with pytest.raises(ValueError, match=r"DataConfig\.split"):
        DataConfig(split="test")
    with pytest.raises(ValueError, match=r"NoiseConfig\.duration_s"):
        NoiseConfig(duration_s=(2.0, 1.0))


def test_collector_starts_and_restarts_cars_with_the_evaluators_rule(monkeypatch):
    """Every (re)start of the collector is placed by the evaluator's own functions, and the
    recorded samples hold those states (position, lane centre, 20 m/s)."""
    from e2e_lite.driving import rollout

    placed: dict[str, list[tuple[float, float, float]]] = {"start": [], "restart": []}
    for kind, name in (("start", "start_state"), ("restart", "restart_state")):
        original = getattr(rollout, name)

        def spy(*args, _original=original, _kind=kind):
            state = _original(*args)
            placed[_kind].append(state)
            return state

        monkeypatch.setattr(rollout, name, spy)
    data = collect(small_cfg(restart_rate_per_s=0.5, n_samples=400), progress=False)
    assert len(placed["start"]) == 4  # one per car
    assert len(placed["restart"]) >= 5  # 0.5 per second over 10 s of driving per car
    ev = EvalConfig()
    recorded = np.stack([data.s, data.d, data.speed], axis=1)
    found = 0
    for s, d, v in placed["start"] + placed["restart"]:
        assert v == ev.start_speed_mps
        found += bool((np.abs(recorded - np.array([s, d, v])).max(axis=1) < 1e-3).any())
    # each is the car's next sample, except where the sample budget ended first (one per car)
    assert found >= len(placed["start"]) + len(placed["restart"]) - 4


def test_restarts_and_braking_bursts_put_slow_samples_in_the_data():
    quiet = small_cfg(n_samples=800, restart_rate_per_s=0.0, noise=NoiseConfig(brake_share=0.0))
    busy = small_cfg(n_samples=800, restart_rate_per_s=0.2, noise=NoiseConfig(brake_share=1.0))
    slow = [np.mean(collect(c, progress=False).speed < 22.0) for c in (quiet, busy)]
    assert slow[1] > 2 * slow[0]


def test_deep_braking_bursts_show_slow_speeds_and_leave_the_default_data_alone():
    base = small_cfg(n_samples=800, restart_rate_per_s=0.0, noise=NoiseConfig(brake_share=1.0))
    deep = dataclasses.replace(base, noise=NoiseConfig(brake_share=1.0, slow_share=1.0))
    plain, slow = collect(base, progress=False), collect(deep, progress=False)
    assert plain.speed.min() > 15.0  # braking bursts take 1-6 m/s off (these cars start at 20)
    assert np.mean(slow.speed < 15.0) > 0.1  # braked to 6-18 m/s, then the expert's recovery
    assert slow.speed.min() >= 6.0 - 0.5  # (one decision's braking past the target at most)
    # the labels stay the expert's: back to speed from the slow states
    rows = (slow.speed < 15.0) & ~slow.arrays["noise"]
    assert rows.any() and (slow.arrays["actuators"][rows, 1] > 0).mean() > 0.9
    # at its default the option changes neither the data nor its key
    explicit = dataclasses.replace(base, noise=NoiseConfig(brake_share=1.0, slow_share=0.0))
    assert explicit.key == base.key
    np.testing.assert_array_equal(collect(explicit, progress=False).speed, plain.speed)
    with pytest.raises(ValueError, match=r"NoiseConfig\.slow_share"):
        NoiseConfig(slow_share=1.5)


def test_situation_masks_on_hand_made_rows():
    arrays = {
        "expert_state": np.array([CHANGE, CHANGE, 0, 0]),
        "overtaking": np.array([True, True, False, False]),
        "affordances": np.zeros((4, len(AFFORDANCE_NAMES))),
        "speed": np.array([25.0, 25.0, 21.0, 25.0]),
        "curvature": np.array([0.0, 0.0, 0.0, 0.002]),
        "change_side": np.array([1, -1, 0, 0]),
    }
    # row 1 is near the end of a change to the right: left of its new lane's centre
    arrays["affordances"][1, AFFORDANCE_NAMES.index("center_offset_m")] = 0.3
    masks = situations(arrays)
    assert masks["overtake_start"].tolist() == [True, False, False, False]
    assert masks["slow"].tolist() == [False, False, True, False]
    assert masks["curve"].tolist() == [False, False, False, True]
    assert situations(arrays, np.array([2, 3]))["slow"].tolist() == [True, False]
    # a recipe's rows that draw the overtake starts 4 times as often (issue 88, item 3's lab)
    assert oversampled(arrays, "overtake_start", 4).tolist() == [0, 1, 2, 3, 0, 0, 0]
    assert oversampled(arrays, "slow", 1).tolist() == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="at least 1"):
        oversampled(arrays, "slow", 0)


def test_road_lateral_removes_heading_and_curve():
    x = np.arange(1, 6) * 7.5
    straight = np.stack([x, np.zeros(5)], axis=1)[None]
    # heading 0.02 rad left of the road: the road ahead appears to the right by 0.02 x
    turned = np.stack([x, -0.02 * x], axis=1)[None]
    bend = np.stack([x, 0.002 * x**2 / 2], axis=1)[None]  # a left curve, keeping the lane
    np.testing.assert_allclose(road_lateral(straight, np.zeros(1), np.zeros(1)), [0.0])
    np.testing.assert_allclose(road_lateral(turned, np.array([0.02]), np.zeros(1)), [0.0])
    np.testing.assert_allclose(road_lateral(bend, np.zeros(1), np.array([0.002])), [0.0])
    np.testing.assert_allclose(road_lateral(straight, np.array([0.02]), np.zeros(1)), [0.75])


def test_a_standing_car_gets_no_recovery_view():
    """Recovery views (chapter 05) are made of moving cars only: a car standing behind a parked
    one has no steering that "brings it back within 2 s", and the tracker's gains at a standstill
    gave labels of half a radian. Every view's speed is at least the floor, and every moving
    sample gets one at fraction 1."""
    from e2e_lite.imitation.recovery import RecoveryConfig, recovery_views

    cfg = small_cfg(n_samples=120)
    data = collect(cfg, progress=False)
    data.arrays["speed"][:30] = 0.0  # 30 cars standing, their plans standing too:
    data.arrays["trajectory"][:30] = 0.0  # (without the floor their views' labels reach 0.4 rad)
    views = recovery_views(data, cfg, RecoveryConfig(fraction=1.0), progress=False)
    floor = RecoveryConfig().min_speed_mps
    assert len(views) == int((data.speed >= floor).sum()) and views.speed.min() >= floor
    assert np.abs(views.actuators[:, 0]).max() < 0.1  # (a highway correction, not a swerve)
