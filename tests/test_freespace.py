"""The free-space profile: its labels on hand-made roads, its head, and the rule that reads it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import straight_world

from e2e_lite.experiments.freespace_rule import check_profile, nearest_car
from e2e_lite.experiments.safety import SafetyConfig, check
from e2e_lite.learning.agents import TrajectoryAgent
from e2e_lite.learning.data import affordances
from e2e_lite.learning.dataset import DrivingData, synthetic_data
from e2e_lite.learning.freespace import (
    N_STRIPS,
    PROFILE_CAP_M,
    STRIP_CENTRES_M,
    ProfileFit,
    ProfileHead,
    fit_profile_head,
    free_profile,
    free_profiles,
    in_view,
    load_or_label,
    profile_head_or_load,
)
from e2e_lite.learning.models import ModelConfig, build_model
from e2e_lite.learning.recipes import gmm_config

CENTRE = int(np.flatnonzero(STRIP_CENTRES_M == 0.0)[0])
FREE = np.full(N_STRIPS, PROFILE_CAP_M - 0.5)
T = 0.3 * np.arange(1, 6)


def test_a_car_ahead_is_read_from_the_front_bumper_in_the_strips_its_body_covers():
    world = straight_world([100.0], [1])  # the middle lane, centred at d = 0
    p = free_profile(world, 50.0, 0.0, 0.0)
    # its rear at 100 - 2.25; our front bumper 3.6 m ahead of the rear axle at 50
    expected = 100.0 - 2.25 - 53.6
    covered = np.abs(STRIP_CENTRES_M) <= 1.0  # its body spans +-0.9 m: strips -1, 0, 1
    assert p[covered] == pytest.approx(expected, abs=1e-9)
    assert np.all(p[~covered] == PROFILE_CAP_M)
    # behind the rear bumper it is gone; beyond the cap it is not seen
    assert np.all(free_profile(world, 110.0, 0.0, 0.0) == PROFILE_CAP_M)
    assert np.all(free_profile(world, 30.0, 0.0, 0.0) == PROFILE_CAP_M)
    # turned left, the car ahead moves to the right-hand strips
    turned = free_profile(world, 50.0, 0.0, 0.05)
    assert STRIP_CENTRES_M[np.argmin(turned)] < -1.0


def test_a_car_alongside_reads_zero_and_one_in_the_next_lane_reads_in_its_strips():
    world = straight_world([51.0, 80.0], [2, 0])  # alongside on the left; ahead on the right
    p = free_profile(world, 50.0, 0.0, 0.0)
    lane = world.track.lane_width  # 3.7 m: the cars' bodies span +-0.9 m about +-3.7 m
    left = np.abs(STRIP_CENTRES_M - lane) <= 1.4  # strips 3, 4, 5
    right = np.abs(STRIP_CENTRES_M + lane) <= 1.4
    assert np.all(p[left] == 0.0)
    assert p[right] == pytest.approx(80.0 - 2.25 - 53.6)
    assert np.all(p[~left & ~right] == PROFILE_CAP_M)


def test_on_a_straight_road_the_centre_strip_is_the_lane_gap_ahead():
    rng = np.random.default_rng(0)
    world = straight_world(sorted(rng.uniform(60.0, 1500.0, 40)), list(rng.integers(0, 3, 40)))
    s = rng.uniform(50.0, 1400.0, 200)
    d = np.zeros_like(s)  # centred in the middle lane, along the road
    profiles = free_profiles([world] * len(s), s, d, np.zeros_like(s))
    gaps = affordances([world] * len(s), s, d, np.zeros_like(s))[:, 6]
    assert np.any(gaps < 60.0) and np.any(gaps == 60.0)
    assert profiles[:, CENTRE] == pytest.approx(gaps, abs=1e-9)


def test_the_rule_reads_the_strips_the_body_sweeps():
    cfg = SafetyConfig()
    profile = FREE + 0.5

    def verdict(points, centres, distance):
        p = profile.copy()
        p[np.isin(STRIP_CENTRES_M, centres)] = distance
        return check_profile(points, p, FREE, 0.0, cfg)[0]

    ahead = np.stack([25.0 * T, 0.0 * T], axis=1)
    u = T / T[-1]
    change = np.stack([25.0 * T, 3.5 * u * u * (3 - 2 * u)], axis=1)
    assert verdict(ahead, [], 0.0) == ""  # nothing seen
    assert verdict(ahead, [0.0], 30.0) == "collision course"
    assert verdict(ahead, [0.0], 50.0) == "cannot stop"  # 12.5 m left at 25 m/s: 57 m needed
    slow = np.stack([10.0 * T, 0.0 * T], axis=1)  # 35 m left at 10 m/s: 10.3 m needed
    assert verdict(slow, [0.0], 50.0) == ""
    assert verdict(ahead, [-3.0, -4.0], 30.0) == ""  # the next lane's car
    assert verdict(change, [0.0], 50.0) == ""  # changed out of its strips before reaching it
    assert verdict(change, [3.0, 4.0], 50.0) != ""  # into a car in the lane it enters
    # a strip read at its threshold or above is free
    assert verdict(ahead, [0.0], FREE[CENTRE]) == ""
    near = nearest_car(profile, FREE, np.array([-0.9, 2.0]), np.array([0.9, 2.1]))
    assert np.all(np.isinf(near))


def test_check_with_a_profile_ignores_the_lane_gaps_and_keeps_the_road_edges():
    aff = np.array([0.0, 0.0, 1.75, 1.75, 5.25, 5.25, 10.0, 10.0, 10.0])  # every lane "blocked"
    ahead = np.stack([25.0 * T, 0.0 * T], axis=1)
    assert not check(ahead, aff, 25.0, 0.0).ok
    assert check(ahead, aff, 25.0, 0.0, profile=(FREE + 0.5, FREE)).ok
    profile = FREE + 0.5
    profile[CENTRE] = 30.0
    v = check(ahead, aff, 25.0, 0.0, profile=(profile, FREE))
    assert not v.ok and v.kind == "collision course" and "30 m" in v.reason
    off_road = np.stack([25.0 * T, 8.0 * T / T[-1]], axis=1)
    v = check(off_road, aff, 25.0, 0.0, profile=(FREE + 0.5, FREE))
    assert not v.ok and v.kind == "road edge"


def _frames(n: int = 80) -> tuple[DrivingData, np.ndarray]:
    """Frames whose profile the image shows: dark frames read a car 20 m ahead in every strip,
    bright ones nothing; tracks 0-9 (0 and 5 held out)."""
    data = synthetic_data(n, seed=3)
    bright = np.arange(n) % 2 == 0
    data.arrays["images"][:] = np.where(bright, 200, 30).astype(np.uint8)[:, None, None, None]
    data.arrays["track"][:] = np.arange(n) % 10
    labels = np.where(bright[:, None], PROFILE_CAP_M, 20.0).repeat(N_STRIPS, 1)
    return data, labels.astype(np.float32)


def _model() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_model(gmm_config(affordance=True)).eval()


def test_the_head_learns_what_the_trunk_shows_and_calibrates_on_held_out_tracks():
    data, labels = _frames()
    model = _model()
    settings = ProfileFit(epochs=40, lr=3e-3, batch_size=16)
    head = fit_profile_head(model, data, labels, settings, progress=False)
    again = fit_profile_head(model, data, labels, settings, progress=False)
    for a, b in zip(head.state_dict().values(), again.state_dict().values()):
        assert torch.equal(a, b)  # seeded
    with torch.inference_mode():
        trunk = model(torch.from_numpy(data.arrays["images"]).permute(0, 3, 1, 2),
                      torch.from_numpy(data.arrays["speed"])[:, None], with_trunk=True)["trunk"]  # fmt: skip
        reads = head(trunk).numpy()
    assert np.abs(reads - labels).mean() < 3.0
    held = data.arrays["track"] % 5 == 0
    free = labels[held, 0] == PROFILE_CAP_M
    expected = np.quantile(reads[held][free], 0.02, axis=0)
    assert head.free_m.numpy() == pytest.approx(expected, abs=1e-4)
    with pytest.raises(ValueError, match="label rows"):
        fit_profile_head(model, data, labels[:-1], settings, progress=False)
    data.arrays["track"][:] = 1  # nothing held out
    with pytest.raises(ValueError, match="held out"):
        fit_profile_head(model, data, labels, settings, progress=False)
    with pytest.raises(ValueError, match="free_quantile"):
        ProfileFit(free_quantile=0.0)


def test_the_driver_reads_the_profile_in_its_own_pass_and_the_head_is_stored():
    data, labels = _frames(40)
    model = _model()
    settings = ProfileFit(epochs=2, batch_size=16)
    head = profile_head_or_load("t", model, data, labels, settings, progress=False)
    stored = profile_head_or_load("t", model, data, labels, settings, progress=False)
    for a, b in zip(head.state_dict().values(), stored.state_dict().values()):
        assert torch.equal(a, b)
    agent = TrajectoryAgent(model, profile_head=head)
    images, speed = data.arrays["images"][:8], data.arrays["speed"][:8]
    agent.trajectories_from(images, speed)
    plain = TrajectoryAgent(model)
    plain.trajectories_from(images, speed)
    assert np.array_equal(agent.last["modes"], plain.last["modes"])  # it drives the same
    with torch.inference_mode():
        trunk = model.features(torch.from_numpy(images).permute(0, 3, 1, 2),
                               torch.from_numpy(speed)[:, None])["trunk"]  # fmt: skip
        expected = head(trunk).double().numpy()
    assert agent.last["profile"] == pytest.approx(expected, abs=1e-5)
    assert np.array_equal(agent.last["profile_free_m"], head.free_m.double().numpy())
    with pytest.raises(ValueError, match="fusion model"):
        TrajectoryAgent(build_model(ModelConfig(kind="pilotnet", head="trajectory")),
                        profile_head=ProfileHead())  # fmt: skip


def test_labels_are_stored_and_read_back(monkeypatch):
    from e2e_lite.learning import freespace
    from e2e_lite.learning.data import DataConfig

    calls = []
    monkeypatch.setattr(
        freespace, "profile_labels", lambda d, c, p: calls.append(1) or np.ones((len(d), N_STRIPS))
    )
    data = synthetic_data(8)
    cfg = DataConfig()
    first = load_or_label(data, cfg, progress=False)
    second = load_or_label(data, cfg, progress=False)
    assert np.array_equal(first, second) and len(calls) == 1


def test_strips_beside_the_car_are_out_of_the_cameras_view():
    near = in_view(np.full(N_STRIPS, 2.0), 50.0, 1.5)  # 4.1 m ahead of the lens: +-1.9 m seen
    assert near[CENTRE] and near[CENTRE - 2] and near[CENTRE + 2]
    assert not near[CENTRE + 3] and not near[0]
    assert in_view(np.full(N_STRIPS, 20.0), 50.0, 1.5).all()  # 22.1 m ahead: +-10.3 m seen
    assert not in_view(np.full(N_STRIPS, 0.0), 10.0, 1.5)[CENTRE + 1]  # a narrow lens
