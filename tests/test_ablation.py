"""The ablation's helpers: every driver in the table, the paper beside it, seeded, reusable."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from e2e_lite.config import QUICK
from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.control.expert import Expert
from e2e_lite.control.oracle import Oracle
from e2e_lite.driving.evaluation import EvalConfig, EvalResult
from e2e_lite.imitation.agents import SteeringAgent, TrajectoryAgent
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.record import ablation
from e2e_lite.record.stored import fingerprint
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig

WORLD = WorldConfig(road=RoadConfig(length_m=1_500.0), traffic=TrafficConfig(n_cars=(8, 8)))
CFG = EvalConfig(miles=0.2, n_worlds=4, n_tracks=2)


def _tiny(head: str, seed: int = 0):
    torch.manual_seed(seed)
    kind = "pilotnet" if head == "steer" else "fusion"
    cfg = ModelConfig(kind=kind, head=head, fusion_width=16)
    return prepare(build_model(cfg), torch.device("cpu"))


def _drivers() -> dict:
    return {
        "expert": Expert(),
        "oracle": Oracle(),
        "pilotnet": SteeringAgent(_tiny("steer")),
        "gmm": TrajectoryAgent(_tiny("gmm")),
    }


def test_same_seeds_give_the_same_table_and_a_stored_result_is_reused(drives):
    first = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=True, progress=False)
    assert all(isinstance(r, EvalResult) for r in first.values())
    again = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=False, progress=False)
    table = ablation.ablation_table(first)
    assert table == ablation.ablation_table(again)
    driven = len(drives)
    reused = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=True, progress=False)
    assert len(drives) == driven  # read back, not driven
    assert all(isinstance(r, EvalResult) for r in reused.values())  # as the type it was saved
    assert ablation.ablation_table(reused) == table
    # other weights are another driver: evaluated again
    other = {"gmm": TrajectoryAgent(_tiny("gmm", seed=1))}
    fresh = ablation.evaluate_drivers(other, WORLD, CFG, progress=False)
    assert len(drives) == driven + 1 and isinstance(fresh["gmm"], EvalResult)


def test_evaluations_with_other_settings_are_kept_side_by_side(drives):
    """Chapter 11 drives chapter 10's network over other miles: neither replaces the other."""
    keeper = {"side_by_side": LaneKeeper()}
    short = replace(CFG, miles=CFG.miles / 2)
    assert isinstance(ablation.evaluate_drivers(keeper, WORLD, CFG)["side_by_side"], EvalResult)
    assert isinstance(ablation.evaluate_drivers(keeper, WORLD, short)["side_by_side"], EvalResult)
    long_again = ablation.evaluate_drivers(keeper, WORLD, CFG, progress=False)["side_by_side"]
    short_again = ablation.evaluate_drivers(keeper, WORLD, short, progress=False)["side_by_side"]
    assert len(drives) == 2  # both read back
    assert long_again.miles > short_again.miles


def test_table_has_every_driver_with_the_papers_figures():
    r = ablation.evaluate_drivers({"keeper": LaneKeeper()}, WORLD, CFG, reuse=False, progress=False)
    rows = {d.key: r["keeper"] for d in ablation.DRIVERS}
    lines = ablation.ablation_table(rows).splitlines()
    assert len(lines) == 2 + len(ablation.DRIVERS)
    row = {d.key: line for d, line in zip(ablation.DRIVERS, lines[2:])}
    for d in ablation.DRIVERS:
        assert row[d.key].startswith(f"| {d.label} |"), d.label
    # seed 000's Table 1 and seed 002's times sit in the rows of the same methods
    assert row["actuators"].endswith("| 183.3 | 1.1 s |")
    assert row["gmm"].endswith("| 12.7 | - |") and row["gmm_affordance"].endswith("| 0.83 | - |")
    assert row["gmm_affordance_cvar"].endswith("| 0 | - |")
    assert row["pilotnet"].endswith("| - | 10.2 s |") and row["expert"].endswith("| - | - |")


def test_fingerprint_follows_weights_and_settings():
    a, b = TrajectoryAgent(_tiny("gmm")), TrajectoryAgent(_tiny("gmm"))
    assert fingerprint(a) == fingerprint(b)
    with torch.no_grad():
        next(b.model.parameters()).add_(1e-3)
    assert fingerprint(a) != fingerprint(b)
    cruise = TrajectoryAgent(_tiny("gmm"), speed="cruise")
    assert fingerprint(a) != fingerprint(cruise)
    assert fingerprint(Expert()) != fingerprint(Oracle())


def test_every_driver_declares_its_identity_and_settings_that_drive_differently_key_apart():
    """Issue 87: each driver says what decides its behaviour (``identity()``), and a stored drive
    is keyed by it: the expert's home lane, an oracle's expert and a lane keeper's speed each
    change the key (they shared one before), while the course's stored drivers keep theirs (a
    setting added later is left out at its default: artifacts.added_later)."""
    from e2e_lite.control.drivers import LaneChanger
    from e2e_lite.control.rules import ExpertConfig
    from e2e_lite.imitation.agents import Recorder
    from e2e_lite.safety.agent import SafeAgent

    drivers = [Expert(), Oracle(), LaneKeeper(), LaneChanger()]
    drivers += [SteeringAgent(_tiny("steer")), TrajectoryAgent(_tiny("gmm"))]
    drivers += [SafeAgent(TrajectoryAgent(_tiny("gmm")), ground_truth=True)]
    drivers += [Recorder(Expert(), lambda obs, agent: None)]
    for d in drivers:
        assert isinstance(d.identity(), list), type(d).__name__
    middle = Expert(ExpertConfig(home="middle"))
    assert fingerprint(Expert()) != fingerprint(middle)
    assert fingerprint(Oracle(middle)) != fingerprint(Oracle())
    assert fingerprint(LaneKeeper(target_speed_mps=30.0)) != fingerprint(LaneKeeper())
    assert fingerprint(LaneChanger(trigger_m=50.0)) != fingerprint(LaneChanger())
    gmm = _tiny("gmm")
    top, mean = TrajectoryAgent(gmm), TrajectoryAgent(gmm, decode="mean")
    assert fingerprint(top) != fingerprint(mean) and "top" not in top.identity()


def test_unknown_driver_is_refused():
    with pytest.raises(ValueError, match="unknown drivers"):
        ablation.build_drivers(QUICK, ["pilotnet", "nonsense"])


def test_a_row_of_seeds_shares_the_miles_and_pools_the_counts():
    seeds = [TrajectoryAgent(_tiny("gmm", seed=k)) for k in range(2)]
    out = ablation.evaluate_drivers({"gmm": seeds}, WORLD, CFG, progress=False)
    pooled = out["gmm"]
    assert len(pooled.seeds) == 2
    assert pooled.miles == pytest.approx(CFG.miles, rel=0.05)
    assert all(s.miles == pytest.approx(CFG.miles / 2, rel=0.1) for s in pooled.seeds)
    assert pooled.collisions == sum(s.collisions for s in pooled.seeds)
    rates = " / ".join(f"{s.collisions_per_100mi:.1f}" for s in pooled.seeds)
    assert f"| {rates} |" in ablation.ablation_table(out)
    # each seed is stored on its own and read back
    again = ablation.evaluate_drivers({"gmm": seeds}, WORLD, CFG, progress=False)
    assert again["gmm"].collisions_per_100mi == pooled.collisions_per_100mi


def test_seeded_names_keep_the_chapters_checkpoint_for_seed_zero():
    from e2e_lite.imitation.recipes import seeded_name

    assert seeded_name("07_gmm", 0) == "07_gmm"
    assert seeded_name("07_gmm", 2) == "10_gmm_seed2"
    assert seeded_name("09_gmm_affordance_cvar", 1) == "10_gmm_affordance_cvar_seed1"


def test_the_exercises_drivers_are_drivers_but_not_chapter_10_rows():
    keys = [d.key for d in ablation.DIAGNOSTICS]
    assert "gmm_affordance_cvar_open" in keys and "gmm_sigma_learned" in keys
    assert all(k in ablation.BY_KEY for k in keys)
    assert [d.key for d in ablation.CONTROLS] == ["gmm_affordance_w0", "gmm_affordance_control"]
    table_keys = {d.key for d in (*ablation.DRIVERS, *ablation.CONTROLS)}
    assert not table_keys & set(keys)
