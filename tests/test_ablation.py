"""The ablation's helpers: every driver in the table, the paper beside it, seeded, reusable."""

from __future__ import annotations

import pytest
import torch

from e2e_lite import ablation
from e2e_lite.agents import SteeringAgent, TrajectoryAgent
from e2e_lite.config import QUICK
from e2e_lite.drivers import LaneKeeper
from e2e_lite.evaluation import EvalConfig, EvalResult
from e2e_lite.expert import Expert, Oracle
from e2e_lite.geometry import RoadConfig
from e2e_lite.models import ModelConfig, build_model, prepare
from e2e_lite.world import TrafficConfig, WorldConfig

WORLD = WorldConfig(road=RoadConfig(length_m=1_500.0), traffic=TrafficConfig(n_cars=(8, 8)))
CFG = EvalConfig(miles=0.4, n_worlds=4, n_tracks=2)


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


def test_same_seeds_give_the_same_table_and_a_stored_result_is_reused():
    first = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=True, progress=False)
    assert all(isinstance(r, EvalResult) for r in first.values())
    again = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=False, progress=False)
    table = ablation.ablation_table(first)
    assert table == ablation.ablation_table(again)
    reused = ablation.evaluate_drivers(_drivers(), WORLD, CFG, reuse=True, progress=False)
    assert all(isinstance(r, dict) for r in reused.values())  # read back, not driven
    assert ablation.ablation_table(reused) == table
    # other weights are another driver: evaluated again
    other = {"gmm": TrajectoryAgent(_tiny("gmm", seed=1))}
    fresh = ablation.evaluate_drivers(other, WORLD, CFG, progress=False)
    assert isinstance(fresh["gmm"], EvalResult)


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
    assert ablation.fingerprint(a) == ablation.fingerprint(b)
    with torch.no_grad():
        next(b.model.parameters()).add_(1e-3)
    assert ablation.fingerprint(a) != ablation.fingerprint(b)
    cruise = TrajectoryAgent(_tiny("gmm"), speed="cruise")
    assert ablation.fingerprint(a) != ablation.fingerprint(cruise)
    assert ablation.fingerprint(Expert()) != ablation.fingerprint(Oracle())


def test_unknown_driver_is_refused():
    with pytest.raises(ValueError, match="unknown drivers"):
        ablation.build_drivers(QUICK, ["pilotnet", "nonsense"])
