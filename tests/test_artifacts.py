"""What the course guarantees after a crash: every stored artifact is sealed by a digest and
rebuilt when its bytes change (a flipped bit, a truncation), a killed write leaves its target
intact and its temporary is removed by the next run, and metrics of older code are not read."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from e2e_lite import artifacts
from e2e_lite.config import QUICK
from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.driving.evaluation import EvalConfig
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.learning.checkpoints import refit_or_load, train_or_load
from e2e_lite.learning.dataset import synthetic_data
from e2e_lite.learning.losses import GMMObjective, Objective
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.learning.probes import HeadRefit
from e2e_lite.learning.training import TrainConfig, model_stats
from e2e_lite.record.stored import evaluate_stored
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig


def flip_a_bit(path: Path, at: float = 0.6) -> None:
    """Flip one bit of ``path`` at the given share of its length (inside the payload)."""
    raw = bytearray(path.read_bytes())
    raw[int(at * len(raw))] ^= 0x10
    path.write_bytes(bytes(raw))


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])


DAMAGE = {"bit flipped": flip_a_bit, "truncated": truncate}


def test_a_sealed_file_is_checked_and_an_old_unsealed_one_is_sealed_on_first_read(tmp_path):
    path = tmp_path / "x.bin"
    with artifacts.atomic_write(path, sealed=True) as f:
        f.write(b"0123456789" * 100)
    assert artifacts.check_seal(path) == "ok"
    flip_a_bit(path)
    with pytest.raises(artifacts.CorruptArtifact, match=r"x\.bin does not match its digest"):
        artifacts.check_seal(path)
    old = tmp_path / "old.bin"  # written before seals existed
    old.write_bytes(b"abc")
    assert artifacts.check_seal(old) == "unsealed" and artifacts.check_seal(old) == "ok"


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_checkpoint_is_retrained_not_reused(damage, capsys):
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg, obj = ModelConfig(head="trajectory", fusion_width=32), Objective("trajectory")
    train_cfg = TrainConfig(epochs=1, batch_size=16, device="cpu")
    first, _ = train_or_load("ckpt", cfg, train_cfg, obj, data, val, progress=False)
    path = artifacts.artifact_path("checkpoints", "ckpt.pt")
    DAMAGE[damage](path)
    again, _ = train_or_load("ckpt", cfg, train_cfg, obj, data, val)
    out = capsys.readouterr().out
    assert "retraining" in out and "reusing" not in out
    for k, v in first.state_dict().items():  # retrained, seeded: the same weights
        assert torch.equal(v, again.state_dict()[k]), k
    assert artifacts.check_seal(path) == "ok"


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_refit_head_is_refit_not_reused(damage, capsys):
    train = synthetic_data(32, 0)
    cfg = ModelConfig(head="gmm", affordance=True, fusion_width=16)
    torch.manual_seed(0)
    model = build_model(cfg)
    model.set_normalisation(model_stats(cfg, train, GMMObjective()))
    model = prepare(model, torch.device("cpu")).eval()
    settings = HeadRefit(epochs=1)
    first = refit_or_load("head", model, train, settings, progress=False)
    path = artifacts.artifact_path("checkpoints", "head_head.pt")
    DAMAGE[damage](path)
    again = refit_or_load("head", model, train, settings)
    out = capsys.readouterr().out
    assert "refitting" in out and "reusing" not in out
    for k, v in first.affordance_head.state_dict().items():
        assert torch.equal(v, again.affordance_head.state_dict()[k]), k


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_dataset_is_collected_again(damage, capsys):
    cfg = DataConfig.for_profile(QUICK, n_samples=48, n_worlds=4)
    first = load_or_collect(cfg, progress=False)
    path = next(artifacts.outputs_dir().glob("data/*.npz"))
    DAMAGE[damage](path)
    again = load_or_collect(cfg, progress=False)
    assert "rebuilding" in capsys.readouterr().out
    np.testing.assert_array_equal(first.images, again.images)


@pytest.mark.parametrize("damage", DAMAGE)
def test_a_damaged_evaluation_is_driven_again(damage, capsys, drives):
    world = WorldConfig(road=RoadConfig(length_m=1_500.0), traffic=TrafficConfig(n_cars=(4, 4)))
    cfg = EvalConfig(miles=0.1, n_worlds=2, n_tracks=2)
    first = evaluate_stored("keeper", "keeper", LaneKeeper(), world, cfg, workers=1)
    path = next(artifacts.outputs_dir().glob("evaluations/keeper-*.json"))
    DAMAGE[damage](path)
    again = evaluate_stored("keeper", "keeper", LaneKeeper(), world, cfg, workers=1)
    out = capsys.readouterr().out
    assert "rebuilding" in out and len(drives) == 2  # driven, not read back
    assert again.events == first.events


def test_metrics_of_older_code_or_a_flipped_bit_are_not_read(capsys):
    artifacts.write_metrics("05_x", {"profile": "full", "headline": {"a": 1.0}})
    assert artifacts.read_metrics("05_x", "full")["headline"] == {"a": 1.0}
    path = artifacts.metrics_path("05_x")
    stored = json.loads(path.read_text())
    stored["schema"] = artifacts.METRICS_SCHEMA - 1
    artifacts.save_json(path, stored, sealed=True)
    assert artifacts.read_metrics("05_x", "full") is None
    said = capsys.readouterr().out
    assert "written by older code" in said and "run chapter 05_x again" in said
    artifacts.write_metrics("05_x", {"profile": "full", "headline": {"a": 1.0}})
    text = path.read_text().replace('"a": 1.0', '"a": 7.0')  # a changed byte, same length
    path.write_text(text)
    assert artifacts.read_metrics("05_x", "full") is None
    assert "does not match its digest" in capsys.readouterr().out


KILLED_WRITE = """
import os, signal, sys
from e2e_lite import artifacts
target = sys.argv[1]
with artifacts.atomic_write(target) as f:
    f.write(b"new bytes that never land")
    f.flush()
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_a_killed_write_leaves_the_target_intact_and_the_next_run_removes_its_temporary(tmp_path):
    target = tmp_path / "outputs" / "x.json"
    artifacts.save_json(target, {"old": True}, sealed=True)
    proc = subprocess.run([sys.executable, "-c", KILLED_WRITE, str(target)], timeout=60)
    assert proc.returncode == -9  # killed inside the write
    left = [p for p in target.parent.iterdir() if p.name.startswith(".x.json.")]
    assert len(left) == 1 and json.loads(target.read_text()) == {"old": True}
    assert artifacts.check_seal(target) == "ok"
    # a live write (fresh modification time) is left alone; a stale one is removed
    assert artifacts.remove_stale_temporaries(target.parent) == 0
    old = time.time() - 2 * artifacts.STALE_AFTER_S
    os.utime(left[0], (old, old))
    assert artifacts.remove_stale_temporaries(target.parent) == 1
    assert not left[0].exists() and json.loads(target.read_text()) == {"old": True}
    assert (target.parent / "x.json.sha256").exists()  # (not a temporary: kept)


def test_profile_outputs_pins_the_profiles_folder_for_its_block_and_gives_the_setting_back(
    monkeypatch, tmp_path
):
    """Inside the block the outputs folder is the asked profile's, whatever ``E2E_LITE_QUICK``
    said before (the variable set for the processes the block starts too); after it, as before."""
    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path))
    monkeypatch.delenv("E2E_LITE_QUICK", raising=False)
    with artifacts.profile_outputs(True) as root:
        assert root == artifacts.outputs_dir() == tmp_path / "quick"
        assert os.environ["E2E_LITE_QUICK"] == "1"
    assert "E2E_LITE_QUICK" not in os.environ and artifacts.outputs_dir() == tmp_path
    monkeypatch.setenv("E2E_LITE_QUICK", "yes")
    with artifacts.profile_outputs(False) as root:
        assert root == artifacts.outputs_dir() == tmp_path
    assert os.environ["E2E_LITE_QUICK"] == "yes"
