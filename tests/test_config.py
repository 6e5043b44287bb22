"""Settings validation, profiles and artifacts."""

from __future__ import annotations

import dataclasses
import json
import os
from typing import ClassVar

import numpy as np
import pytest
import torch

from e2e_lite import artifacts
from e2e_lite.config import FULL, QUICK, Profile, active_profile
from e2e_lite.simulation.geometry import RoadConfig, track_rng
from e2e_lite.simulation.vehicle import VehicleParams
from e2e_lite.simulation.world import SimConfig, TrafficConfig


@pytest.mark.parametrize(
    ("factory", "field"),
    [
        (lambda: RoadConfig(n_lanes=1), "RoadConfig.n_lanes"),
        (lambda: RoadConfig(n_lanes=2.5), "RoadConfig.n_lanes"),
        (lambda: RoadConfig(lane_width_m=0.0), "RoadConfig.lane_width_m"),
        (lambda: RoadConfig(lane_width_m=-3.0), "RoadConfig.lane_width_m"),
        (lambda: RoadConfig(radius_m=(5.0, 10.0)), "RoadConfig.radius_m"),
        (lambda: RoadConfig(arc_deg=(10.0, 80.0)), "RoadConfig.arc_deg"),
        (lambda: VehicleParams(max_speed_mps=-1.0), "VehicleParams.max_speed_mps"),
        (lambda: VehicleParams(wheelbase_m=0.0), "VehicleParams.wheelbase_m"),
        (lambda: SimConfig(dt_s=0.0), "SimConfig.dt_s"),
        (lambda: SimConfig(dt_s=-0.02), "SimConfig.dt_s"),
        (lambda: SimConfig(dt_s=0.02, policy_period_s=0.05), "SimConfig.policy_period_s"),
        (lambda: TrafficConfig(car_length_m=0.0), "TrafficConfig.car_length_m"),
        (lambda: Profile("medium", 1000.0, 1, 1.0, 1, 1, 10, 10, 1, 1), "Profile.name"),
        (lambda: dataclasses.replace(QUICK, n_train_samples=0), "Profile.n_train_samples"),
    ],
)
def test_bad_settings_raise_a_clear_error(factory, field):
    with pytest.raises(ValueError) as err:
        factory()
    msg = str(err.value)
    assert field in msg and ("must be" in msg)


def test_error_names_value_and_range():
    with pytest.raises(
        ValueError, match=r"RoadConfig.n_lanes=1 is invalid: must be an integer in \[2, 8\]"
    ):
        RoadConfig(n_lanes=1)
    with pytest.raises(ValueError, match=r"whole number of physics steps"):
        SimConfig(policy_period_s=0.07)
    assert SimConfig().steps_per_policy == 5


def test_profile_switch():
    assert active_profile([], {}) is FULL
    assert active_profile(["--quick"], {}) is QUICK
    assert active_profile([], {"E2E_LITE_QUICK": "1"}) is QUICK
    assert active_profile([], {"E2E_LITE_QUICK": "0"}) is FULL
    with pytest.raises(ValueError, match="E2E_LITE_QUICK"):
        active_profile([], {"E2E_LITE_QUICK": "maybe"})
    assert QUICK.eval_miles < FULL.eval_miles and QUICK.track_length_m < FULL.track_length_m


def test_bad_split_is_refused():
    with pytest.raises(ValueError, match="split"):
        track_rng(0, "validation", 0)


def test_outputs_dir_follows_the_environment(tmp_path):
    assert artifacts.outputs_dir() == tmp_path / "outputs"
    p = artifacts.write_metrics("99_demo", {"headline": {"x": 1.5}})
    assert p == tmp_path / "outputs" / "metrics" / "99_demo.json"
    schema = {"schema": artifacts.METRICS_SCHEMA}
    assert artifacts.read_metrics("99_demo") == {**schema, "headline": {"x": 1.5}}
    artifacts.write_metrics("97_full", {"profile": "full"})
    assert artifacts.read_metrics("97_full", "full") == {**schema, "profile": "full"}
    assert artifacts.read_metrics("97_full", "quick") is None
    assert artifacts.read_metrics("98_missing") is None
    # a chapter's figures are stored relative to the outputs folder, missing ones skipped
    fig = artifacts.artifact_path("figures", "99_demo.png")
    artifacts.write_metrics("99_demo", {"headline": {}}, figures=(fig, None))
    assert artifacts.read_metrics("99_demo")["figures"] == ["figures/99_demo.png"]


def test_settings_key_is_stable_and_sensitive():
    a = artifacts.settings_key(RoadConfig(), {"n": 3})
    assert a == artifacts.settings_key(RoadConfig(), {"n": 3})
    assert a != artifacts.settings_key(RoadConfig(n_lanes=4), {"n": 3})
    assert a != artifacts.settings_key(RoadConfig(), {"n": 4})


@dataclasses.dataclass(frozen=True)
class _Inner:
    a: int = 1
    b: tuple[float, float] = (1.0, 2.0)  # came later: at its default it leaves the keys alone
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = ("b",)


@dataclasses.dataclass(frozen=True)
class _Outer:
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    items: tuple[_Inner, ...] = (_Inner(),)
    n: int = 3


def test_settings_key_omits_later_fields_at_their_default_at_every_level():
    # the keys the settings had before `b` existed: nested dataclasses as plain dicts
    before = {"a": 1}
    old = {"__type__": "_Outer", "inner": before, "items": [before], "n": 3}
    assert artifacts.settings_key(_Outer()) == artifacts.settings_key(old)
    moved = _Inner(b=(1.0, 3.0))
    assert artifacts.settings_key(_Outer(inner=moved)) != artifacts.settings_key(old)
    assert artifacts.settings_key(_Outer(items=(moved,))) != artifacts.settings_key(old)
    # what is written (not a key) keeps every field
    assert json.loads(artifacts.to_json(_Outer()))["inner"]["b"] == [1.0, 2.0]


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "data.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with artifacts.atomic_write(target) as f:
            f.write(b"half-written")
            raise RuntimeError("interrupted")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["data.bin"]


def _save(path, value, key):
    np.savez(open(path, "wb"), value=value, key=key)


def _load(path):
    with np.load(path) as z:
        return z["value"], str(z["key"])


def test_cached_reuses_rebuilds_on_mismatch_and_on_corruption(tmp_path, capsys):
    path = tmp_path / "thing.npz"
    calls = []

    def build():
        calls.append(1)
        return np.arange(5)

    v = artifacts.cached(path, "k1", build, _save, _load)
    assert np.array_equal(v, np.arange(5)) and len(calls) == 1
    artifacts.cached(path, "k1", build, _save, _load)
    assert len(calls) == 1  # reused
    artifacts.cached(path, "k2", build, _save, _load)
    assert len(calls) == 2 and "other settings" in capsys.readouterr().out
    path.write_bytes(b"garbage")
    artifacts.cached(path, "k2", build, _save, _load)
    assert len(calls) == 3 and "does not match its digest" in capsys.readouterr().out
    artifacts.seal_path(path).unlink()  # a file from before seals: read as before
    path.write_bytes(b"garbage")
    artifacts.cached(path, "k2", build, _save, _load)
    assert len(calls) == 4 and "unreadable" in capsys.readouterr().out
    # no temporary files left; the artifact and its digest
    assert sorted(os.listdir(tmp_path)) == ["thing.npz", "thing.npz.sha256"]


def test_metrics_keep_their_order_and_keys_ignore_it():
    artifacts.write_metrics("97_order", {"headline": {"zeta": 1, "alpha": 2}})
    assert list(artifacts.read_metrics("97_order")["headline"]) == ["zeta", "alpha"]
    assert artifacts.settings_key({"a": 1, "b": 2}) == artifacts.settings_key({"b": 2, "a": 1})


def test_quick_profile_writes_to_its_own_folder(tmp_path, monkeypatch):
    """A quick smoke run must never replace the full profile's checkpoints or metrics."""
    monkeypatch.setenv("E2E_LITE_QUICK", "1")
    assert artifacts.outputs_dir() == tmp_path / "outputs" / "quick"
    monkeypatch.setenv("E2E_LITE_QUICK", "0")
    assert artifacts.outputs_dir() == tmp_path / "outputs"


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_honour_the_umask(tmp_path, monkeypatch, umask, mode):
    """Artifacts are shared (a teacher's outputs/ folder): the temporary file must not stay 0600."""
    monkeypatch.setattr(artifacts, "_UMASK", umask)
    artifacts.save_json(tmp_path / "m.json", {"a": 1})
    with artifacts.atomic_write(tmp_path / "f.bin") as f:
        f.write(b"x")
    artifacts.cached(tmp_path / "c.npz", "k", lambda: np.arange(3), _save, _load)
    for name in ("m.json", "f.bin", "c.npz"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode, name


def test_the_umask_read_at_import_is_the_process_umask():
    current = os.umask(0o022)
    os.umask(current)
    assert artifacts._UMASK == current


def test_settings_are_checked_where_they_are_defined_types_as_well_as_ranges(tmp_path):
    """Issue 51: each of these was accepted, or failed far from its owner, before."""
    from e2e_lite.driving.rollout import EvalConfig
    from e2e_lite.learning.cvar import CVaRObjective, cvar, cvar_loss
    from e2e_lite.learning.losses import Objective

    with pytest.raises(ValueError, match=r"cvar\.alpha='0\.9' is invalid"):
        cvar(np.arange(5.0), "0.9")
    with pytest.raises(ValueError, match=r"cvar_loss\.alpha=1\.5 is invalid"):
        cvar_loss(torch.arange(5.0), 1.5)
    with pytest.raises(ValueError, match=r"cvar_loss\.min_tail=-5 is invalid"):
        cvar_loss(torch.arange(50.0), 0.9, min_tail=-5)
    with pytest.raises(ValueError, match=r"CVaRObjective\.min_tail"):
        CVaRObjective(Objective("trajectory"), 0.9, min_tail=0)
    with pytest.raises(
        ValueError, match=r"EvalConfig\.n_worlds=2\.0 is invalid: must be an integer"
    ):
        EvalConfig(n_worlds=2.0)
    EvalConfig(n_worlds=np.int64(2))  # a numpy count is a count


def test_the_gmm_loss_and_the_model_must_agree_on_k_at_the_first_batch():
    from e2e_lite.learning.dataset import DrivingDataset, synthetic_data
    from e2e_lite.learning.losses import GMMObjective
    from e2e_lite.learning.models import ModelConfig, build_model
    from e2e_lite.learning.training import model_stats

    data = synthetic_data(8)
    model = build_model(ModelConfig(head="gmm", gmm_modes=3, fusion_width=16))
    model.set_normalisation(model_stats(model.cfg, data, GMMObjective(n_modes=3)))
    batch = DrivingDataset(data).batch(np.arange(8))
    out = model(batch["image"], batch["speed"])
    assert GMMObjective(n_modes=3).per_sample(out, batch, model).shape == (8,)
    with pytest.raises(ValueError, match="n_modes=2, but the model's head has 3 modes"):
        GMMObjective(n_modes=2).per_sample(out, batch, model)


def test_a_checkpoint_of_other_settings_names_only_the_fields_that_differ():
    from e2e_lite.learning.checkpoints import CheckpointMismatch, load_checkpoint, save_checkpoint
    from e2e_lite.learning.losses import Objective
    from e2e_lite.learning.models import ModelConfig, build_model
    from e2e_lite.learning.training import TrainConfig

    model = build_model(ModelConfig(head="trajectory", fusion_width=16))
    path = artifacts.artifact_path("checkpoints", "m.pt")
    save_checkpoint(path, model, TrainConfig(epochs=1), Objective("trajectory"), "data")
    with pytest.raises(CheckpointMismatch) as err:
        load_checkpoint(path, ModelConfig(head="trajectory", fusion_width=32))
    assert str(err.value).count("fusion_width") == 1 and "16 (asked: 32)" in str(err.value)
    assert len(str(err.value)) < 200 and "head=" not in str(err.value)


def test_workers_default_to_the_cores_this_process_may_use_with_an_override():
    from e2e_lite.config import WORKERS_ENV, available_cores, default_workers

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert available_cores() == cores
    assert default_workers({}) == cores and default_workers({WORKERS_ENV: " "}) == cores
    assert default_workers({WORKERS_ENV: "3"}) == 3
    for bad in ("0", "-1", "2.5", "many"):
        with pytest.raises(ValueError, match=WORKERS_ENV):
            default_workers({WORKERS_ENV: bad})


def test_tf32_is_off_unless_asked_in_this_process_and_in_a_fresh_worker(monkeypatch):
    """Issue 56: torch lets cuDNN convolutions run in TF32 by default; the course turns it off
    where the networks are built (a worker process imports the same module), and the precision
    is part of a checkpoint's key."""
    import subprocess
    import sys

    from e2e_lite.config import TF32_ENV, precision
    from e2e_lite.learning.checkpoints import checkpoint_key
    from e2e_lite.learning.losses import Objective
    from e2e_lite.learning.models import ModelConfig
    from e2e_lite.learning.training import TrainConfig

    assert not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
    code = "import e2e_lite.learning.models, torch; print(torch.backends.cudnn.allow_tf32)"
    env = {k: v for k, v in os.environ.items() if k != TF32_ENV}
    fresh = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert fresh.stdout.strip() == "False", fresh.stderr
    asked = subprocess.run(
        [sys.executable, "-c", code], env={**env, TF32_ENV: "1"}, capture_output=True, text=True
    )
    assert asked.stdout.strip() == "True", asked.stderr
    assert precision({}) == "fp32" and precision({TF32_ENV: "yes"}) == "tf32"
    with pytest.raises(ValueError, match=TF32_ENV):
        precision({TF32_ENV: "maybe"})
    args = (ModelConfig(), TrainConfig(), Objective("trajectory"), "data")
    fp32 = checkpoint_key(*args)
    monkeypatch.setenv(TF32_ENV, "1")
    assert checkpoint_key(*args) != fp32
