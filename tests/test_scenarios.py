"""The overtake scene set: seeded scenes, outcomes of known drivers."""

from __future__ import annotations

import pytest

from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.control.expert import Expert
from e2e_lite.control.oracle import Oracle
from e2e_lite.simulation.scenarios import ScenarioConfig, overtake_scenes, run_scenarios


def test_scenes_are_seeded_and_jittered_within_their_ranges():
    cfg = ScenarioConfig(n_scenes=30, seed=4)
    a, b = overtake_scenes(cfg), overtake_scenes(cfg)
    assert a == b
    assert overtake_scenes(ScenarioConfig(n_scenes=30, seed=5)) != a
    assert all(70.0 <= sc.ahead_m <= 100.0 and abs(sc.offset_m) <= 0.2 for sc in a)
    assert len({sc.ahead_m for sc in a}) == 30


def test_expert_and_oracle_pass_and_a_lane_keeper_hits_the_car():
    cfg = ScenarioConfig(n_scenes=12, batch=6, seed=1)
    expert = run_scenarios(Expert(), cfg, progress=False)
    assert expert.count("passed") == 12, expert.summary()
    # both sides are taken: the scene has two right answers
    sides = {round(float(p[-1, 1]) / 3.7) for p in expert.paths}
    assert sides == {-1, 1}
    assert run_scenarios(Oracle(), cfg, progress=False).pass_rate == 1.0
    keeper = run_scenarios(LaneKeeper(), cfg, progress=False)
    assert keeper.count("collided") == 12 and keeper.pass_rate == 0.0
    # the same seed gives the same outcomes and paths
    again = run_scenarios(Expert(), cfg, progress=False)
    assert again.outcomes == expert.outcomes
    assert all((p == q).all() for p, q in zip(again.paths, expert.paths))


def test_bad_scenario_settings_raise():
    with pytest.raises(ValueError, match="ahead_m"):
        ScenarioConfig(ahead_m=(100.0, 70.0))
    with pytest.raises(ValueError, match="n_scenes"):
        ScenarioConfig(n_scenes=0)
