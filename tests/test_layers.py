"""The layers: the learning side loads without the simulator, the dataset's schema is the one
place that says what a sample holds, and settings that must agree are derived, not defaulted."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import e2e_lite.data
import e2e_lite.dataset
from e2e_lite.agents import CruiseControl, SteeringAgent, TrajectoryAgent
from e2e_lite.dataset import FIELDS, SCHEMA, allocate, synthetic_data
from e2e_lite.evaluation import EvalConfig, evaluate
from e2e_lite.expert import Expert
from e2e_lite.models import ModelConfig, build_model
from e2e_lite.tracker import default_tracker
from e2e_lite.world import SimConfig, WorldConfig

SIMULATOR = ("pymunk", "cv2", "control")


def test_the_learning_modules_import_without_the_simulator() -> None:
    code = (
        "import sys\n"
        "import e2e_lite.labels, e2e_lite.dataset, e2e_lite.models, e2e_lite.losses\n"
        "import e2e_lite.training, e2e_lite.recipes, e2e_lite.cvar, e2e_lite.heldout\n"
        "import e2e_lite.checkpoints, e2e_lite.probes\n"
        f"print(sorted(m for m in {SIMULATOR!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
    # and the check itself can fail: the collector does pull the simulator in
    code = f"import sys, e2e_lite.data; print(sorted(m for m in {SIMULATOR!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(sorted(SIMULATOR))


def test_the_schema_makes_the_field_list_the_arrays_the_synthetic_data_and_the_docs() -> None:
    assert FIELDS == tuple(n for n in SCHEMA if n != "images")
    arrays = allocate(3, (4, 5), fill=0)
    assert set(arrays) == set(SCHEMA)
    assert arrays["images"].shape == (3, 4, 5, 3)
    assert arrays["trajectory"].shape == (3, 5, 2) and arrays["speed"].shape == (3,)
    syn = synthetic_data(8)
    for name, (_, dtype, meaning) in SCHEMA.items():
        assert arrays[name].dtype == dtype and syn.arrays[name].dtype == dtype, name
        assert (
            f"``{name}``" in e2e_lite.dataset.__doc__ and meaning[:20] in e2e_lite.dataset.__doc__
        )
    assert syn.images.shape == (8, 66, 200, 3)
    # the collector's module re-exports the dataset's names (the chapters read them there)
    assert e2e_lite.data.DrivingData is e2e_lite.dataset.DrivingData


def _gains(tracker) -> np.ndarray:
    return tracker.gains


def test_the_trackers_are_discretised_at_the_worlds_policy_period() -> None:
    slow = SimConfig(policy_period_s=0.2)
    base, changed = Expert(), Expert(sim=slow)
    assert base.tracker.cfg.period_s == 0.1 and changed.tracker.cfg.period_s == 0.2
    assert not np.allclose(_gains(base.tracker), _gains(changed.tracker))
    model = build_model(ModelConfig(head="trajectory", fusion_width=16))
    agent = TrajectoryAgent(model, sim=slow)
    assert agent.tracker.cfg.period_s == 0.2
    assert np.allclose(_gains(agent.tracker), _gains(changed.tracker))
    steer = SteeringAgent(build_model(ModelConfig(kind="pilotnet", head="steer")), sim=slow)
    assert steer.cruise.tracker.cfg.period_s == 0.2
    assert CruiseControl(sim=slow).tracker.cfg.period_s == 0.2
    assert default_tracker().cfg.period_s == SimConfig().policy_period_s


def test_a_driver_built_for_another_policy_period_is_refused() -> None:
    world_cfg = WorldConfig()
    with pytest.raises(ValueError, match=r"sim=world_cfg\.sim"):
        evaluate(Expert(sim=SimConfig(policy_period_s=0.2)), world_cfg, EvalConfig(miles=0.01))
    # the same driver built for the world's steps drives
    res = evaluate(
        Expert(sim=world_cfg.sim), world_cfg, EvalConfig(miles=0.01, n_worlds=1), progress=False
    )
    assert res.miles > 0


def test_models_still_run_on_synthetic_batches_after_the_move() -> None:
    data = synthetic_data(4)
    batch = e2e_lite.dataset.DrivingDataset(data).batch(np.arange(4))
    out = build_model(ModelConfig(head="gmm", fusion_width=16))(batch["image"], batch["speed"])
    assert torch.isfinite(out["main"]).all()


def test_recovery_views_re_express_the_labels_in_the_shifted_cars_frame() -> None:
    from e2e_lite.recovery import to_car_frame

    pts = np.array([[[7.5, 0.0], [15.0, 0.5]]])
    pose = np.array([[10.0, 2.0, 0.3]])
    assert np.allclose(to_car_frame(pts, pose, pose), pts)  # same pose: unchanged
    left = np.array([[0.0, 0.0, 0.0]])
    shifted = np.array([[0.0, 1.0, 0.0]])  # the same car 1 m to the left
    assert np.allclose(to_car_frame(pts, left, shifted), pts - [0.0, 1.0])
    turned = np.array([[0.0, 0.0, np.pi / 2]])  # turned 90 degrees left: ahead becomes right
    assert np.allclose(to_car_frame(np.array([[[1.0, 0.0]]]), left, turned), [[[0.0, -1.0]]])
    # and back again
    there = to_car_frame(pts, pose, shifted)
    assert np.allclose(to_car_frame(there, shifted, pose), pts)
