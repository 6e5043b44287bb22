"""DAgger's round (issue 63): the learner drives, the expert labels the states it visits, the
data is aggregated, the samples do not depend on the worker count, a round never drives a
validation or test road, and the fine-tune's key holds what made it. (The quick course's chapter
12 checks that a round grows the aggregate by exactly its samples: tests/test_chapters.py.)"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from e2e_lite.config import QUICK
from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.control.expert import Expert
from e2e_lite.learning import dagger
from e2e_lite.learning.agents import TrajectoryAgent
from e2e_lite.learning.collector import DataConfig, NoiseConfig, OnPolicy, collect
from e2e_lite.learning.dataset import synthetic_data
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig

WORLD = WorldConfig(road=RoadConfig(length_m=1_500.0), traffic=TrafficConfig(n_cars=(8, 8)))


def small(n_worlds: int = 8, n_samples: int = 160, **changes) -> DataConfig:
    return DataConfig(
        n_samples=n_samples, n_tracks=2, n_worlds=n_worlds, world=WORLD, **changes
    )  # fmt: skip


class Shadow(LaneKeeper):
    """A learner that keeps its lane at 20 m/s whatever is parked in it (the expert cruises at
    25), and keeps a copy of every observation it was given (the states the cars were in)."""

    def __init__(self) -> None:
        super().__init__(target_speed_mps=20.0)
        self.seen = []

    def act(self, obs):
        self.seen.append(dataclasses.replace(
            obs, state=obs.state.copy(), s=obs.s.copy(), d=obs.d.copy(),
            heading_error=obs.heading_error.copy(), curvature=obs.curvature.copy(),
            lane=obs.lane.copy(), respawned=obs.respawned.copy(), images=None,
            collided=None if obs.collided is None else obs.collided.copy(),
        ))  # fmt: skip
        return super().act(obs)


def test_on_policy_samples_are_the_experts_labels_of_the_states_the_learner_visited():
    cfg = small(noise=NoiseConfig(rate_per_s=0.0), restart_rate_per_s=0.0)
    learner = Shadow()
    data = collect(cfg, progress=False, workers=1, on_policy=OnPolicy(learner, beta=0.0))
    # a fresh expert of the same seed, shown the same states in the same order, labels them so
    expert = Expert(cfg.expert, vehicle=cfg.world.vehicle, sim=cfg.world.sim, seed=cfg.seed)
    expert.seed_cars(np.arange(cfg.n_worlds))
    expert.reset(cfg.n_worlds)
    quota = cfg.n_samples // cfg.n_worlds
    for k, obs in enumerate(learner.seen[:quota]):
        traj = expert.trajectory_label(obs)
        act = expert.act(obs)
        rows = np.arange(cfg.n_worlds) * quota + k  # car after car, decision k of each
        np.testing.assert_allclose(data.arrays["trajectory"][rows], traj, atol=1e-5)
        np.testing.assert_allclose(data.arrays["actuators"][rows, 0], act.steer_rad, atol=1e-6)
        np.testing.assert_allclose(data.arrays["s"][rows], obs.s, atol=1e-3)
    # the learner drove: the states are not those the expert drives into
    expert_only = collect(cfg, progress=False, workers=1)
    assert data.arrays["speed"][-1] < expert_only.arrays["speed"][-1] - 1.0


def test_beta_one_drives_exactly_the_experts_states():
    cfg = small()  # with the collector's noise and take-overs: only who drives may differ
    mixed = collect(cfg, progress=False, workers=1, on_policy=OnPolicy(Shadow(), beta=1.0))
    alone = collect(cfg, progress=False, workers=1)
    for name in alone.arrays:
        assert np.array_equal(mixed.arrays[name], alone.arrays[name]), name
    # the control with fresh labels (DaggerConfig.control_labels): the same states, each labelled
    # by an expert planning afresh there
    from e2e_lite.control.expert import fresh_labels

    shadow = Shadow()
    fresh = collect(cfg, progress=False, workers=1, on_policy=OnPolicy(shadow, fresh=True))
    for name in alone.arrays:
        if name != "trajectory":
            assert np.array_equal(fresh.arrays[name], alone.arrays[name]), name
    quota = cfg.n_samples // cfg.n_worlds
    for k, obs in enumerate(shadow.seen[:quota]):
        want = fresh_labels(obs, list(range(cfg.n_worlds)), cfg.world.sim)
        rows = np.arange(cfg.n_worlds) * quota + k
        np.testing.assert_allclose(fresh.arrays["trajectory"][rows], want, atol=1e-5)


def test_a_networks_round_gives_the_same_bytes_for_one_and_two_workers():
    torch.manual_seed(0)
    model = build_model(ModelConfig(head="trajectory", fusion_width=16))
    model = prepare(model, torch.device("cpu")).eval()
    cfg = small(n_worlds=16, n_samples=320, noise=NoiseConfig(rate_per_s=0.0))
    one = collect(cfg, progress=False, workers=1, on_policy=OnPolicy(TrajectoryAgent(model), 0.5))
    two = collect(cfg, progress=False, workers=2, on_policy=OnPolicy(TrajectoryAgent(model), 0.5))
    for name in one.arrays:
        assert np.array_equal(one.arrays[name], two.arrays[name]), name


def test_a_round_drives_fresh_training_roads_and_never_a_validation_or_test_road():
    cfg = dagger.DaggerConfig.for_profile(QUICK)
    firsts = set()
    for seed in range(4):
        for r in range(cfg.rounds):
            both = [dagger.RoundSpec(QUICK, cfg, seed, r, arm).data() for arm in dagger.ARMS]
            assert all(d.split == "train" for d in both)
            assert both[0].first_track == both[1].first_track >= dagger.FIRST_TRACK  # paired
            firsts.add(both[0].first_track)
    assert len(firsts) == 4 * cfg.rounds  # every seed and round on roads of its own
    data = collect(dagger.RoundSpec(QUICK, cfg, 1, 1, "control").data(), progress=False, workers=1)
    first = dagger.RoundSpec(QUICK, cfg, 1, 1, "control").data().first_track
    assert data.arrays["track"].min() >= first
    assert data.arrays["track"].max() < first + dagger.TRACK_STRIDE
    with pytest.raises(ValueError, match="split"):
        DataConfig(split="test")
    with pytest.raises(ValueError, match="one beta per round"):
        dagger.DaggerConfig(rounds=2, betas=(0.5,))
    with pytest.raises(ValueError, match="arm"):
        dagger.RoundSpec(QUICK, cfg, 0, 0, "oracle").data()


def test_the_finetunes_key_holds_the_parent_the_round_the_beta_and_the_data():
    torch.manual_seed(0)
    net = build_model(ModelConfig(head="trajectory", fusion_width=16))
    other = build_model(ModelConfig(head="trajectory", fusion_width=16))
    cfg = dagger.DaggerConfig(rounds=2, samples=64, betas=(0.5, 0.0))
    key = dagger.RoundSpec(QUICK, cfg, 0, 0, "dagger").samples_key(net)
    assert key != dagger.RoundSpec(QUICK, cfg, 0, 1, "dagger").samples_key(net)  # the round
    assert key != dagger.RoundSpec(QUICK, cfg, 1, 0, "dagger").samples_key(net)  # the seed
    assert key != dagger.RoundSpec(QUICK, cfg, 0, 0, "dagger").samples_key(other)  # the learner
    other_beta = dataclasses.replace(cfg, betas=(0.7, 0.0))
    assert key != dagger.RoundSpec(QUICK, other_beta, 0, 0, "dagger").samples_key(net)  # the beta
    with pytest.raises(ValueError, match="learner"):
        dagger.RoundSpec(QUICK, cfg, 0, 0, "dagger").samples_key(None)
    # the fine-tune's data: its new samples, every earlier part and the rows replayed
    base, new = synthetic_data(40, seed=1), synthetic_data(16, seed=2)
    ft = dagger.finetune_set([base], new, 1.0, 0, 0)
    assert len(ft) == 32 and ft.stats["speed_mean"] == base.stats["speed_mean"]
    assert np.array_equal(ft.arrays["images"][16:], new.arrays["images"])
    assert (
        ft.info["key"]
        != dagger.finetune_set([base], synthetic_data(16, seed=3), 1.0, 0, 0).info["key"]
    )
    assert ft.info["key"] != dagger.finetune_set([base], new, 1.0, 0, 1).info["key"]
    assert len(dagger.finetune_set([base, new], new, 0.5, 0, 1)) == 24
    # a beta schedule stores its samples and networks under names of its own, beside the course's
    course = dagger.DaggerConfig(rounds=2, samples=64)
    assert dagger.RoundSpec(QUICK, course, 0, 0, "dagger").stem == "12_dagger_fresh"
    assert dagger.RoundSpec(QUICK, cfg, 0, 0, "dagger").stem == "12_dagger_fresh_beta0.5-0"
    assert (
        dagger.RoundSpec(QUICK, cfg, 0, 0, "control").stem
        == dagger.RoundSpec(QUICK, course, 0, 0, "control").stem
        == "12_control"
    )
    relabelled = dataclasses.replace(course, control_labels="fresh")
    assert dagger.RoundSpec(QUICK, relabelled, 0, 0, "control").stem == "12_control_fresh"
    assert dagger.RoundSpec(QUICK, relabelled, 0, 0, "control").samples_key(
        None
    ) != dagger.RoundSpec(QUICK, course, 0, 0, "control").samples_key(None)
    with pytest.raises(ValueError, match="control_labels"):
        dagger.DaggerConfig(control_labels="oracle")


def test_covariate_shift_counts_the_visits_outside_the_datas_range():
    data = synthetic_data(400, seed=1)
    same = dagger.covariate_shift(synthetic_data(400, seed=2), [data])
    assert 0.0 <= same["any"] < 0.15  # about 2 % per feature
    far = synthetic_data(400, seed=3)
    far.arrays["speed"][:] = 40.0  # nothing in the data drives that fast
    assert dagger.covariate_shift(far, [data])["speed [m/s]"] == 1.0


def test_fresh_labels_come_from_an_expert_without_memory_of_its_plans():
    """Issue 63's lab: with ``labels="fresh"`` each state's trajectory label is what a fresh
    expert (no plans) drives from it; the key and the stored names say which labels they hold."""
    from e2e_lite.control.expert import fresh_labels

    cfg = small(n_samples=80, noise=NoiseConfig(rate_per_s=0.0), restart_rate_per_s=0.0)
    learner = Shadow()
    data = collect(cfg, progress=False, workers=1, on_policy=OnPolicy(learner, 0.0, fresh=True))
    quota = cfg.n_samples // cfg.n_worlds
    for k, obs in enumerate(learner.seen[:quota]):
        rows = np.arange(cfg.n_worlds) * quota + k
        want = fresh_labels(obs, list(range(cfg.n_worlds)), cfg.world.sim)
        np.testing.assert_allclose(data.arrays["trajectory"][rows], want, atol=1e-5)
    with pytest.raises(ValueError, match="labels"):
        dagger.DaggerConfig(labels="oracle")
    torch.manual_seed(0)
    net = build_model(ModelConfig(head="trajectory", fusion_width=16))
    expert = dagger.DaggerConfig.for_profile(QUICK, labels="expert")
    fresh = dagger.DaggerConfig.for_profile(QUICK)  # the course's labels
    assert fresh.labels == "fresh"
    assert dagger.RoundSpec(QUICK, expert, 0, 0, "dagger").samples_key(net) != dagger.RoundSpec(
        QUICK, fresh, 0, 0, "dagger"
    ).samples_key(net)
