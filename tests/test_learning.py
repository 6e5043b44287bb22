"""Models, training, checkpoints and agents on small synthetic data (fast, CPU)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from e2e_lite.artifacts import artifact_path, seal, settings_key
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.driving.parallel import processes_ok
from e2e_lite.imitation.agents import (
    SPEED_SOURCES,
    ActuatorAgent,
    CruiseControl,
    SteeringAgent,
    TrajectoryAgent,
)
from e2e_lite.imitation.collector import DrivingDataset, synthetic_data
from e2e_lite.learning.checkpoints import (
    CheckpointMismatch,
    load_checkpoint,
    refit_or_load,
    save_checkpoint,
    train_or_load,
)
from e2e_lite.learning.losses import GMMObjective, Objective, target
from e2e_lite.learning.models import (
    TRUNK_FEATURES,
    DrivingModel,
    FusionNet,
    ModelConfig,
    Normalise,
    PilotNet,
    PilotNetTrunk,
    build_model,
    count_parameters,
    prepare,
)
from e2e_lite.learning.probes import (
    HeadRefit,
    layer_features,
    probe_affordances,
    refit_affordance_head,
)
from e2e_lite.learning.training import (
    DECISIVE,
    TrainConfig,
    decisive_errors,
    evaluate_loss,
    fit,
    model_stats,
)
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.vehicle import VehicleParams
from e2e_lite.simulation.world import TrafficConfig, WorldConfig


def test_trunk_and_heads_shapes_and_parameter_counts():
    x = torch.zeros(2, 3, 66, 200, dtype=torch.uint8)
    assert PilotNetTrunk()(x).shape == (2, TRUNK_FEATURES) == (2, 1152)
    pilot = PilotNet(ModelConfig(kind="pilotnet", head="steer"))
    assert pilot(x)["main"].shape == (2, 1)
    assert 240_000 < count_parameters(pilot) < 260_000  # seed 003: ~250K
    speed = torch.full((2, 1), 20.0)
    for head, size in (("actuators", 2), ("trajectory", 10), ("gmm", 42)):
        net = FusionNet(ModelConfig(head=head, affordance=True)).eval()
        out = net(x, speed)
        assert out["main"].shape == (2, size) and out["affordance"].shape == (2, 9)
    assert "affordance" not in FusionNet(ModelConfig())(x, speed)


def test_normalisation_layer_is_fixed():
    layer = Normalise()
    assert not list(layer.parameters())
    out = layer(torch.tensor([0, 255], dtype=torch.uint8))
    assert out.tolist() == [-1.0, 1.0]
    # bit for bit the formula, on uint8 and float input; a float input is left as it was
    pixels = torch.randint(0, 256, (2, 3, 66, 200), dtype=torch.uint8)
    assert torch.equal(layer(pixels), pixels.float() / 127.5 - 1.0)
    floats = pixels.float()
    assert torch.equal(layer(floats), pixels.float() / 127.5 - 1.0)
    assert torch.equal(floats, pixels.float())
    net = build_model(ModelConfig(kind="pilotnet", head="steer"))
    names = [n for n, _ in net.named_parameters()]
    assert not any("normalise" in n or "mean" in n or "std" in n for n in names)


def test_bad_model_settings_raise():
    with pytest.raises(ValueError, match=r"ModelConfig\.head"):
        ModelConfig(head="throttle")
    with pytest.raises(ValueError, match=r"ModelConfig\.affordance"):
        ModelConfig(kind="pilotnet", head="steer", affordance=True)


def test_model_overfits_sixteen_samples():
    data = synthetic_data(16)
    ds = DrivingDataset(data)
    torch.manual_seed(0)
    cfg = ModelConfig(kind="pilotnet", head="actuators")
    model = build_model(cfg)
    objective = Objective("actuators")
    model.set_normalisation(model_stats(cfg, data, objective))
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    batch = ds.batch(np.arange(16))
    losses = []
    for _ in range(200):
        loss = objective.per_sample(model(batch["image"], batch["speed"]), batch, model).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < losses[0] / 10


def small_train_cfg(**kw) -> TrainConfig:
    return TrainConfig(**{"epochs": 2, "batch_size": 16, "device": "cpu", **kw})


def test_training_is_seeded_and_keeps_the_best_epoch():
    data, val = synthetic_data(48, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="actuators", fusion_width=32)
    obj = Objective("actuators")
    runs = []
    for _ in range(2):
        model, hist = train_or_load(
            "seeded", cfg, small_train_cfg(), obj, data, val, progress=False
        )
        runs.append(model.state_dict())
        artifact_path("checkpoints", "seeded.pt").unlink()  # force a second training
    for k in runs[0]:
        assert torch.equal(runs[0][k], runs[1][k]), k
    best = min(range(len(hist.epochs)), key=lambda e: hist.epochs[e]["val_loss"])
    assert hist.best_epoch == best


def test_train_or_load_reuses_a_valid_checkpoint(capsys):
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="trajectory", fusion_width=32)
    obj = Objective("trajectory")
    first, _ = train_or_load(
        "reuse", cfg, small_train_cfg(epochs=1), obj, data, val, progress=False
    )
    again, hist = train_or_load("reuse", cfg, small_train_cfg(epochs=1), obj, data, val)
    assert "reusing" in capsys.readouterr().out and len(hist.epochs) == 1
    x = DrivingDataset(val).batch(np.arange(4))
    with torch.inference_mode():
        np.testing.assert_array_equal(
            first(x["image"], x["speed"])["main"].numpy(),
            again(x["image"], x["speed"])["main"].numpy(),
        )
    # other training settings: retrained, with a message
    train_or_load("reuse", cfg, small_train_cfg(epochs=1, lr=5e-4), obj, data, val)
    assert "other settings" in capsys.readouterr().out


def test_a_reused_and_a_trained_model_are_scored_alike_and_the_warm_up_is_an_argument():
    """The GMM's warm-up is the epoch its loss is given, not the objective's state: a reused and
    a trained model get the same held-out NLL (it once depended on which path ran)."""
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="gmm", fusion_width=16)
    trained_obj = GMMObjective(sigma_warmup_epochs=1)
    assert trained_obj.sigma_fixed(0) and not trained_obj.sigma_fixed(1)
    assert not trained_obj.sigma_fixed(None)  # scored after training: the warm-up is over
    model, _ = train_or_load(
        "state", cfg, small_train_cfg(epochs=2), trained_obj, data, val, progress=False
    )
    reused_obj = GMMObjective(sigma_warmup_epochs=1)
    again, _ = train_or_load(
        "state", cfg, small_train_cfg(epochs=2), reused_obj, data, val, progress=False
    )
    a, _ = evaluate_loss(model, trained_obj, DrivingDataset(val))
    b, _ = evaluate_loss(again, reused_obj, DrivingDataset(val))
    np.testing.assert_allclose(a, b)
    # the same model scored as in its warm-up epoch: sigma held at 1, another NLL
    warm, _ = evaluate_loss(model, trained_obj, DrivingDataset(val), epoch=0)
    assert not np.allclose(warm, a)


def test_fine_tune_starts_from_its_parent_and_follows_it(capsys):
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="trajectory", fusion_width=32)
    obj = Objective("trajectory")
    with pytest.raises(CheckpointMismatch, match="train it first"):
        train_or_load("child", cfg, small_train_cfg(epochs=1), obj, data, val, init_from="nope")
    parent, _ = train_or_load("parent", cfg, small_train_cfg(epochs=1), obj, data, val)
    tiny_lr = small_train_cfg(epochs=1, lr=1e-12)  # so the child stays (almost) the parent
    child, _ = train_or_load("child", cfg, tiny_lr, obj, data, val, init_from="parent")
    fresh, _ = train_or_load("fresh", cfg, tiny_lr, obj, data, val)
    for (name, p), c, f in zip(
        parent.named_parameters(), child.parameters(), fresh.parameters(), strict=True
    ):  # the weights (not batch-norm statistics) come from the parent, not a fresh start
        torch.testing.assert_close(c, p, msg=name)
        assert not torch.allclose(f, p) or p.numel() == 0 or torch.all(p == 0)
    capsys.readouterr()
    train_or_load("child", cfg, tiny_lr, obj, data, val, init_from="parent")
    assert "reusing" in capsys.readouterr().out
    # a retrained parent makes the child stale
    train_or_load("parent", cfg, small_train_cfg(epochs=1, lr=5e-4), obj, data, val)
    capsys.readouterr()
    train_or_load("child", cfg, tiny_lr, obj, data, val, init_from="parent")
    assert "other settings" in capsys.readouterr().out


def test_checkpoint_round_trip_and_refusals(tmp_path):
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="actuators", fusion_width=32)
    obj = Objective("actuators")
    model, hist = train_or_load(
        "ck", cfg, small_train_cfg(epochs=1), obj, data, val, progress=False
    )
    path = save_checkpoint(tmp_path / "m.pt", model, small_train_cfg(epochs=1), obj, "data-A", hist)
    loaded, meta = load_checkpoint(path, cfg, "data-A", model.normalisation())
    x = DrivingDataset(val).batch(np.arange(8))
    with torch.inference_mode():
        a = model(x["image"], x["speed"])["main"]
        b = loaded(x["image"], x["speed"])["main"]
    assert torch.equal(a, b) and meta["data_key"] == "data-A"
    with pytest.raises(CheckpointMismatch, match="normalis"):
        other = model_stats(cfg, synthetic_data(32, 7), obj)
        load_checkpoint(path, cfg, "data-A", other)
    with pytest.raises(CheckpointMismatch, match="settings"):
        load_checkpoint(path, dataclasses.replace(cfg, fusion_width=64))
    with pytest.raises(CheckpointMismatch, match="dataset"):
        load_checkpoint(path, cfg, "data-B")


def test_freezing_keeps_parameters_fixed_for_its_epochs():
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    torch.manual_seed(0)
    cfg = ModelConfig(head="actuators", fusion_width=32)
    model = prepare(build_model(cfg), torch.device("cpu"))
    model.set_normalisation(model_stats(cfg, data, Objective("actuators")))
    before = model.trunk.convs[0].weight.detach().clone()
    head_before = model.head.weight.detach().clone()
    hist = fit(
        model,
        Objective("actuators"),
        DrivingDataset(data),
        DrivingDataset(val),
        small_train_cfg(epochs=1, freeze=(("trunk.", 0, 1),)),
        name="freeze",
        progress=False,
    )
    assert torch.equal(model.trunk.convs[0].weight, before)
    assert not torch.equal(model.head.weight, head_before)
    assert hist.epochs[0]["frozen"] == ["trunk."]
    assert all(p.requires_grad for p in model.parameters())


def test_bad_train_settings_raise():
    with pytest.raises(ValueError, match=r"TrainConfig\.freeze"):
        TrainConfig(freeze=(("trunk.", 3, 1),))
    with pytest.raises(ValueError, match=r"TrainConfig\.device"):
        TrainConfig(device="tpu")


def test_steering_target_is_curvature():
    batch = {"actuators": torch.tensor([[0.1, 0.0]])}
    assert float(target("steer", batch, 2.7)) == pytest.approx(np.tan(0.1) / 2.7)


class Spy:
    """Wraps an agent, checks the frames it gets and keeps its commands."""

    def __init__(self, agent, seen: list) -> None:
        self.agent, self.seen, self.camera = agent, seen, agent.camera

    def reset(self, n: int) -> None:
        self.agent.reset(n)

    def act(self, obs):
        a = self.agent.act(obs)
        assert obs.images.shape == (len(obs.s), 66, 200, 3)
        self.seen.append((a.steer_rad.copy(), a.accel_mps2.copy()))
        return a


def test_agents_give_valid_commands_in_closed_loop():
    """An untrained model with absurd output scales still yields commands within the car's limits."""
    world_cfg = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(5, 5)))
    veh = VehicleParams()
    seen = []
    for cfg, agent_cls in (
        (ModelConfig(head="actuators", fusion_width=16), ActuatorAgent),
        (ModelConfig(kind="pilotnet", head="steer"), SteeringAgent),
        (ModelConfig(head="trajectory", fusion_width=16), TrajectoryAgent),
        (ModelConfig(head="gmm", gmm_modes=3, fusion_width=16), TrajectoryAgent),
    ):
        torch.manual_seed(0)
        model = prepare(build_model(cfg), torch.device("cpu")).eval()
        model.target_std.fill_(100.0)
        agent = agent_cls(model)
        evaluate(
            Spy(agent, seen),
            world_cfg,
            EvalConfig(miles=0.05, n_worlds=3, n_tracks=2),
            progress=False,
        )
    steer = np.concatenate([s for s, _ in seen])
    accel = np.concatenate([a for _, a in seen])
    assert np.all(np.abs(steer) <= veh.max_steer_rad + 1e-9)
    assert np.all((accel >= -veh.max_brake_mps2 - 1e-9) & (accel <= veh.max_accel_mps2 + 1e-9))
    assert np.ptp(steer) > 0  # the commands come from the frames, not a constant


def test_network_agents_fork_into_parallel_shards_reproducibly():
    """Two shards share one model; the result repeats, in threads or processes; torch's thread
    count comes back."""
    world_cfg = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(5, 5)))
    torch.manual_seed(0)
    model = prepare(build_model(ModelConfig(head="gmm", fusion_width=16)), torch.device("cpu"))
    agent = TrajectoryAgent(model)
    forks = agent.fork(2)
    assert forks[0].model is model and forks[0] is not agent and forks[0].last is not agent.last
    threads = torch.get_num_threads()
    cfg = EvalConfig(miles=0.2, n_worlds=4, n_tracks=2)
    a = evaluate(agent, world_cfg, cfg, progress=False, workers=2)
    b = evaluate(agent, world_cfg, cfg, progress=False, workers=2)
    assert torch.get_num_threads() == threads
    assert a.events == b.events and a.miles == b.miles and a.miles >= 0.2
    assert a.timing_s["frames"] >= a.sim_time_s / 0.1 - 1e-6 and a.timing_s["render"] > 0
    # the shards may run in worker processes (the default): the same drive
    assert processes_ok(agent)
    t = evaluate(agent, world_cfg, cfg, progress=False, workers=2, parallel="threads")
    p = evaluate(agent, world_cfg, cfg, progress=False, workers=2, parallel="processes")
    assert t.events == p.events == a.events and t.miles == p.miles
    assert torch.get_num_threads() == threads


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_a_network_on_the_gpu_drives_the_same_in_threads_and_processes():
    """On a GPU machine the shards go to worker processes too (each loads the network onto the
    device): the same events as two threads sharing it in this process."""
    world_cfg = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(5, 5)))
    torch.manual_seed(0)
    model = prepare(build_model(ModelConfig(head="gmm", fusion_width=16)), torch.device("cuda"))
    agent = TrajectoryAgent(model)
    assert processes_ok(agent)
    cfg = EvalConfig(miles=0.2, n_worlds=4, n_tracks=2)
    t = evaluate(agent, world_cfg, cfg, progress=False, workers=2, parallel="threads")
    p = evaluate(agent, world_cfg, cfg, progress=False, workers=2, parallel="processes")
    assert t.events == p.events and t.miles == p.miles and t.miles >= 0.2


def test_cruise_control_targets_the_road_speed_limit():
    from conftest import straight_world

    from e2e_lite.driving.evaluation import observe
    from e2e_lite.simulation.world import Fleet

    fleet = Fleet([straight_world([], [])], WorldConfig())
    fleet.place(0, 100.0, 0.0, 10.0)
    accel = CruiseControl().accel(observe(fleet, True))
    assert accel[0] > 0  # below the 25 m/s limit of a straight


def test_trajectory_agent_keeps_every_mode():
    from conftest import straight_world

    from e2e_lite.driving.evaluation import observe
    from e2e_lite.simulation.world import Fleet

    torch.manual_seed(0)
    model = prepare(
        build_model(ModelConfig(head="gmm", gmm_modes=2, fusion_width=16)), torch.device("cpu")
    )
    agent = TrajectoryAgent(model.eval())
    fleet = Fleet([straight_world([], []), straight_world([], [])], WorldConfig())
    for i in range(2):
        fleet.place(i, 100.0, 0.0, 20.0)
    obs = observe(fleet, True, images=np.zeros((2, 66, 200, 3), np.uint8))
    pts = agent.trajectories(obs)
    last = agent.last
    assert (
        pts.shape == (2, 5, 2)
        and last["modes"].shape == (2, 2, 5, 2)
        and last["weights"].shape == (2, 2)
    )
    top = last["weights"].argmax(axis=1)
    np.testing.assert_allclose(pts, last["modes"][np.arange(2), top])
    assert np.all(last["sigmas"] > 0) and "affordances" not in last
    # the diagnostic decoding follows the mixture's mean, the modes' weighted average
    mean_agent = TrajectoryAgent(model, decode="mean")
    averaged = mean_agent.trajectories(obs)
    expected = np.einsum("bk,bkpc->bpc", last["weights"], last["modes"])
    np.testing.assert_allclose(averaged, expected, rtol=1e-5, atol=1e-6)  # float32 maths
    np.testing.assert_allclose(mean_agent.last["modes"], last["modes"])
    with pytest.raises(ValueError, match="decode"):
        TrajectoryAgent(model, decode="median")
    from e2e_lite.record.stored import fingerprint

    assert fingerprint(mean_agent) != fingerprint(agent)
    with_aff = prepare(
        build_model(ModelConfig(head="gmm", affordance=True, fusion_width=16)), torch.device("cpu")
    ).eval()
    with_aff.affordance_mean.fill_(30.0)
    agent = TrajectoryAgent(with_aff)
    agent.trajectories(obs)
    assert agent.last["affordances"].shape == (2, 9)
    assert 20.0 < agent.last["affordances"].mean() < 40.0  # de-normalised
    with pytest.raises(ValueError, match="trajectory or gmm"):
        TrajectoryAgent(build_model(ModelConfig(kind="pilotnet", head="steer")))


def test_trajectory_agent_speed_sources():
    """Same steering from every speed source; the speed command follows the chosen source."""
    from conftest import straight_world

    from e2e_lite.control.tracker import trajectory_reference
    from e2e_lite.driving.evaluation import observe
    from e2e_lite.simulation.world import Fleet

    torch.manual_seed(0)
    model = prepare(
        build_model(ModelConfig(head="trajectory", fusion_width=16)), torch.device("cpu")
    ).eval()
    t = 0.3 * np.arange(1, 6)  # the net proposes ~ a straight at 10 m/s speeding up at 1 m/s^2
    plan = np.stack([10.0 * t + 0.5 * t**2, np.zeros(5)], axis=1).ravel()
    model.target_mean.copy_(torch.as_tensor(plan, dtype=torch.float32))
    model.target_std.fill_(0.01)
    fleet = Fleet([straight_world([], [])], WorldConfig())
    fleet.place(0, 100.0, 0.0, 10.0)
    obs = observe(fleet, True, images=np.full((1, 66, 200, 3), 90, np.uint8))
    acts = {s: TrajectoryAgent(model, speed=s).act(obs) for s in SPEED_SOURCES}
    steer = {s: float(a.steer_rad[0]) for s, a in acts.items()}
    assert len(set(steer.values())) == 1
    agent = TrajectoryAgent(model)
    _, _, _, v_ref, a_ref = trajectory_reference(agent.trajectories(obs))
    no_ff = agent.tracker.accel(obs.speed, v_ref, np.zeros(1))
    with_ff = agent.tracker.accel(obs.speed, v_ref, a_ref)
    assert abs(with_ff[0] - no_ff[0]) > 1e-3  # the two trajectory sources are distinguishable
    assert acts["trajectory"].accel_mps2[0] == pytest.approx(with_ff[0])
    assert acts["trajectory_no_ff"].accel_mps2[0] == pytest.approx(no_ff[0])
    assert acts["cruise"].accel_mps2[0] == pytest.approx(CruiseControl().accel(obs)[0])
    with pytest.raises(ValueError, match="is invalid: must be one of"):
        TrajectoryAgent(model, speed="fast")


def test_recorder_keeps_one_row_per_decision_and_passes_the_camera():
    from e2e_lite.control.drivers import LaneKeeper
    from e2e_lite.imitation.agents import Recorder

    rec = Recorder(LaneKeeper(), lambda obs, agent: obs.time_s)
    assert rec.camera is None
    world_cfg = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(0, 0)))
    evaluate(rec, world_cfg, EvalConfig(miles=0.05, n_worlds=2, n_tracks=1), progress=False)
    assert len(rec.rows) > 10 and rec.rows == sorted(rec.rows) and rec.rows[0] == 0.0
    torch.manual_seed(0)
    model = prepare(
        build_model(ModelConfig(head="trajectory", fusion_width=16)), torch.device("cpu")
    )
    assert Recorder(TrajectoryAgent(model.eval()), lambda o, a: None).camera is not None


def test_decisive_errors_and_selection_by_them():
    ade = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    masks = {
        "overtake_start": np.array([True, True, False, False, False]),
        "slow": np.array([False, False, True, False, False]),
        "curve": np.zeros(5, dtype=bool),  # none: left out
    }
    out = decisive_errors(ade, masks)
    assert out == {"ADE overtake_start [m]": 1.5, "ADE slow [m]": 3.0, DECISIVE: 2.25}
    with pytest.raises(ValueError, match="decisive"):
        decisive_errors(ade, {"curve": np.zeros(5, dtype=bool)})
    # the kept epoch is the one with the lowest decisive error, recorded every epoch
    data, val = synthetic_data(48, 0), synthetic_data(32, 1)
    val.arrays["curvature"][:10] = 0.01  # some curves among the validation frames
    cfg = ModelConfig(head="gmm", fusion_width=32)
    _, hist = train_or_load(
        "decisive",
        cfg,
        small_train_cfg(epochs=3, select_by="decisive_ade"),
        GMMObjective(sigma_warmup_epochs=0),
        data,
        val,
        progress=False,
    )
    scores = [e[DECISIVE] for e in hist.epochs]
    assert hist.best_epoch == int(np.argmin(scores))
    assert all("ADE curve [m]" in e and "ADE slow [m]" in e for e in hist.epochs)
    with pytest.raises(ValueError, match="select_by"):
        TrainConfig(select_by="nll")
    with pytest.raises(ValueError, match="trajectory head"):
        train_or_load(
            "decisive_steer",
            ModelConfig(head="actuators", fusion_width=32),
            small_train_cfg(epochs=1, select_by="decisive_ade"),
            Objective("actuators"),
            data,
            val,
            progress=False,
        )


def test_a_fine_tune_continues_its_parents_optimiser(capsys):
    """``carry_optimizer``: the fine-tune's first step is the step the parent's training would
    have taken next (same Adam moments and step count), not a fresh Adam's."""
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="trajectory", fusion_width=32, dropout=0.0)
    obj = Objective("trajectory")
    one_step = small_train_cfg(epochs=1, batch_size=32)  # one batch: the whole set
    _, hist = train_or_load("parent", cfg, one_step, obj, data, val, progress=False)
    assert hist.optimizer_state is not None
    _, meta = load_checkpoint(artifact_path("checkpoints", "parent.pt"))
    assert meta["optimizer"]["state"]  # Adam's moments are in the checkpoint
    child, _ = train_or_load(
        "child", cfg, one_step, obj, data, val, init_from="parent", carry_optimizer=True
    )
    fresh, _ = train_or_load("fresh_adam", cfg, one_step, obj, data, val, init_from="parent")
    # the uninterrupted run's next step, by hand: the parent, its Adam state, one more batch
    model, _ = load_checkpoint(artifact_path("checkpoints", "parent.pt"))
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=one_step.lr)
    opt.load_state_dict(meta["optimizer"])
    order = np.random.default_rng([one_step.seed, 0]).permutation(len(data))  # fit's epoch 0
    batch = DrivingDataset(data).batch(order)
    loss = obj.reduce(obj.per_sample(model(batch["image"], batch["speed"]), batch, model))
    opt.zero_grad()
    loss.backward()
    opt.step()
    moved_apart = 0
    for (name, want), got, other in zip(
        model.named_parameters(), child.parameters(), fresh.parameters(), strict=True
    ):
        torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5, msg=name)
        moved_apart += not torch.allclose(other, want, atol=1e-6, rtol=1e-5)
    assert moved_apart > 0  # a fresh Adam takes another step: the test can tell them apart


def test_carrying_the_optimiser_needs_a_parent_that_kept_it(capsys):
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="trajectory", fusion_width=32)
    obj, tcfg = Objective("trajectory"), small_train_cfg(epochs=1)
    train_or_load("old", cfg, tcfg, obj, data, val, progress=False)
    path = artifact_path("checkpoints", "old.pt")
    blob = torch.load(path, weights_only=False)
    blob["optimizer"] = None  # as saved before the course kept optimiser states
    torch.save(blob, path)
    seal(path)  # (a file the course wrote: sealed)
    with pytest.raises(CheckpointMismatch, match="no optimiser state"):
        train_or_load("kid", cfg, tcfg, obj, data, val, init_from="old", carry_optimizer=True)
    with pytest.raises(ValueError, match="needs init_from"):
        train_or_load("kid", cfg, tcfg, obj, data, val, carry_optimizer=True)
    train_or_load("old", cfg, tcfg, obj, data, val)  # still reused without the request
    assert "reusing" in capsys.readouterr().out
    train_or_load("old", cfg, tcfg, obj, data, val, keep_optimizer=True)
    assert "no optimiser state kept" in capsys.readouterr().out
    train_or_load("kid", cfg, tcfg, obj, data, val, init_from="old", carry_optimizer=True)


def test_features_are_what_the_heads_read():
    torch.manual_seed(0)
    cfg = ModelConfig(head="trajectory", affordance=True)
    model = prepare(build_model(cfg), torch.device("cpu")).eval()
    ds_val = DrivingDataset(synthetic_data(16, 1))
    batch = ds_val.batch(np.arange(8))
    with torch.inference_mode():
        feats = model.features(batch["image"], batch["speed"])
        out = model(batch["image"], batch["speed"])
        main, affordance = model.head(feats["fused"]), model.affordance_head(feats["fused"])
    assert feats["trunk"].shape == (8, 1152) and feats["fused"].shape == (8, cfg.fusion_width)
    torch.testing.assert_close(main, out["main"])
    torch.testing.assert_close(affordance, out["affordance"])
    np.testing.assert_allclose(  # the same features, batched by the dataset
        layer_features(model, ds_val, "fused")[:8], feats["fused"].numpy(), rtol=1e-5, atol=1e-6
    )
    with pytest.raises(ValueError, match="layer"):
        layer_features(model, ds_val, "head")


class _SeesBrightness(torch.nn.Module):
    """A stand-in network whose "trunk" is each frame's mean brightness per channel and per image
    quarter (12 numbers) and whose "fused" layer is noise: what a probe can and cannot read."""

    def __init__(self) -> None:
        super().__init__()
        self.unused = torch.nn.Parameter(torch.zeros(1))

    def features(self, image: torch.Tensor, speed: torch.Tensor) -> dict[str, torch.Tensor]:
        quarters = image.float().unflatten(3, (4, 50)).mean(dim=(2, 4))  # (B, 3, 4)
        noise = torch.randn(len(image), 12, generator=torch.Generator().manual_seed(len(image)))
        return {"trunk": quarters.flatten(1) / 255.0, "fused": noise}


def test_a_probe_reads_what_a_layer_holds_and_not_what_it_lacks():
    train, val = synthetic_data(256, 0), synthetic_data(64, 1)
    for data, seed in ((train, 0), (val, 1)):
        gain = np.random.default_rng(seed).uniform(0.1, 1.0, len(data))
        images = data.arrays["images"] * gain[:, None, None, None]
        data.arrays["images"][:] = images.astype(np.uint8)
        data.arrays["affordances"][:] = np.outer(gain, np.linspace(-2.0, 2.0, 9) + 0.1)
    net, ds_train, ds_val = _SeesBrightness(), DrivingDataset(train), DrivingDataset(val)
    true = val.arrays["affordances"].astype(np.float64)
    floor = np.sqrt(((train.arrays["affordances"].mean(0) - true) ** 2).mean(0))  # the mean's
    seen = probe_affordances(net, ds_train, ds_val, "trunk", epochs=60)
    unseen = probe_affordances(net, ds_train, ds_val, "fused", epochs=60)
    assert np.all(np.sqrt(((seen - true) ** 2).mean(0)) < 0.25 * floor)
    assert np.all(np.sqrt(((unseen - true) ** 2).mean(0)) > 0.8 * floor)
    np.testing.assert_array_equal(
        seen, probe_affordances(net, ds_train, ds_val, "trunk", epochs=60)
    )


def test_the_affordance_head_reads_where_it_is_told_and_old_keys_stand():
    torch.manual_seed(0)
    cfg = ModelConfig(head="gmm", affordance=True, affordance_from="trunk")
    model = prepare(build_model(cfg), torch.device("cpu")).eval()
    batch = DrivingDataset(synthetic_data(4, 1)).batch(np.arange(4))
    with torch.inference_mode():
        feats = model.features(batch["image"], batch["speed"])
        out = model(batch["image"], batch["speed"])
        from_trunk = model.affordance_head(feats["trunk"])
    torch.testing.assert_close(out["affordance"], from_trunk)
    # fields that came after checkpoints existed: at their defaults they leave the keys as they were
    paper = ModelConfig(head="gmm", affordance=True)
    later = ("affordance_from", "sigma_floor", "sigma_floor_m")
    without_field = {
        "__type__": "ModelConfig",
        **{k: v for k, v in dataclasses.asdict(paper).items() if k not in later},
    }
    assert settings_key(paper) == settings_key(without_field)
    assert settings_key(cfg) != settings_key(paper)
    assert settings_key(dataclasses.replace(paper, sigma_floor_m=0.1)) != settings_key(paper)
    with pytest.raises(ValueError, match="affordance_from"):
        ModelConfig(affordance=True, affordance_from="speed")


def _brightness_data(n: int, seed: int):
    """Synthetic samples whose affordances are a linear function of each frame's brightness (a
    random gain on the image): something a network's trunk can see."""
    data = synthetic_data(n, seed)
    gain = np.random.default_rng(seed).uniform(0.1, 1.0, n)
    data.arrays["images"][:] = (data.arrays["images"] * gain[:, None, None, None]).astype(np.uint8)
    data.arrays["affordances"][:] = np.outer(gain, np.linspace(-2.0, 2.0, 9) + 0.1)
    return data


def _affordance_net(train) -> DrivingModel:
    torch.manual_seed(0)
    cfg = ModelConfig(head="gmm", affordance=True, affordance_from="trunk")
    model = build_model(cfg)
    model.set_normalisation(model_stats(cfg, train, GMMObjective()))
    return prepare(model, torch.device("cpu")).eval()


def _outputs(model: DrivingModel, data) -> dict[str, torch.Tensor]:
    batch = DrivingDataset(data).batch(np.arange(len(data.arrays["speed"])))
    with torch.inference_mode():
        return model(batch["image"], batch["speed"])


def test_a_refit_head_learns_from_frozen_features_and_leaves_the_driving_to_the_bit():
    train, val = _brightness_data(256, 0), _brightness_data(64, 1)
    model = _affordance_net(train)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    refit = refit_affordance_head(model, DrivingDataset(train), HeadRefit(epochs=60))
    for k, v in model.state_dict().items():  # the original is left as it was
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    old, new = _outputs(model, val), _outputs(refit, val)
    torch.testing.assert_close(new["main"], old["main"], rtol=0, atol=0)  # drives the same
    for k, v in refit.state_dict().items():
        if not k.startswith("affordance_head."):
            torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    # the refit head beats the untrained one and the mean predictor, in normalised units
    true = (
        torch.from_numpy(val.arrays["affordances"]).float() - model.affordance_mean
    ) / model.affordance_std
    floor = (true**2).mean()  # the mean predictor: the training mean is 0 in normalised units
    assert ((new["affordance"] - true) ** 2).mean() < 0.3 * floor
    assert ((old["affordance"] - true) ** 2).mean() > 0.8 * floor  # untrained: the mean, or worse
    again = refit_affordance_head(model, DrivingDataset(train), HeadRefit(epochs=60))
    torch.testing.assert_close(
        _outputs(again, val)["affordance"], new["affordance"], rtol=0, atol=0
    )


def test_a_refit_of_no_epochs_is_the_same_head_after_the_standardisation_folds_back():
    train = _brightness_data(64, 0)
    model = _affordance_net(train)
    same = refit_affordance_head(model, DrivingDataset(train), HeadRefit(epochs=0))
    torch.testing.assert_close(
        _outputs(same, train)["affordance"], _outputs(model, train)["affordance"],
        rtol=1e-4, atol=1e-5,
    )  # fmt: skip
    with pytest.raises(ValueError, match="epochs"):
        HeadRefit(epochs=-1)
    with pytest.raises(ValueError, match="no affordance head"):
        refit_affordance_head(build_model(ModelConfig(head="gmm")), DrivingDataset(train))


def test_a_refit_head_is_stored_and_refit_only_for_another_network(capsys):
    train = _brightness_data(64, 0)
    model, settings = _affordance_net(train), HeadRefit(epochs=2)
    first = refit_or_load("net", model, train, settings)
    assert artifact_path("checkpoints", "net_head.pt").exists()
    again = refit_or_load("net", model, train, settings)
    assert "reusing the refit head" in capsys.readouterr().out
    for k, v in first.state_dict().items():
        torch.testing.assert_close(again.state_dict()[k], v, rtol=0, atol=0)
    with torch.no_grad():  # another network (a retrained trunk): its head is refit
        model.trunk.convs[0].weight.mul_(1.01)
    refit_or_load("net", model, train, settings)
    assert "refitting" in capsys.readouterr().out


def test_on_epoch_sees_each_epoch_in_eval_mode_and_its_numbers_join_the_record():
    """``on_epoch`` (what lab/epochs_on_the_road.py keeps each epoch's weights with) is called
    once per epoch after validation, with the model in eval mode; what it returns joins that
    epoch's record; a stored checkpoint calls it no more."""
    data, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="gmm", fusion_width=16)
    seen: list[tuple[int, bool, float]] = []

    def hook(epoch: int, model) -> dict[str, float]:
        seen.append((epoch, model.training, float(next(model.parameters()).detach().sum())))
        return {"probe": 10.0 + epoch}

    obj = GMMObjective(sigma_warmup_epochs=1)
    _, hist = train_or_load(
        "hook", cfg, small_train_cfg(epochs=2), obj, data, val, progress=False, on_epoch=hook
    )
    assert [(e, training) for e, training, _ in seen] == [(0, False), (1, False)]
    assert seen[0][2] != seen[1][2]  # the weights after each epoch, not one copy
    assert [r["probe"] for r in hist.epochs] == [10.0, 11.0]
    train_or_load("hook", cfg, small_train_cfg(epochs=2), obj, data, val, progress=False,
                  on_epoch=hook)  # fmt: skip
    assert len(seen) == 2


def test_selection_by_validation_roads_keeps_the_epoch_that_collides_least():
    """``select_by="val_roads"``: the epoch with the fewest collisions per 100 mi on validation
    roads (what ``on_epoch`` returns) is kept, ties to the lower decisive ADE; without the drive,
    or without its miles, the settings are refused; the miles are part of the checkpoint key, and
    a configuration without them keeps the key it had before the option existed."""
    from e2e_lite.learning.checkpoints import checkpoint_key
    from e2e_lite.learning.training import VAL_ROADS

    data, val = synthetic_data(48, 0), synthetic_data(32, 1)
    val.arrays["curvature"][:10] = 0.01
    cfg = ModelConfig(head="gmm", fusion_width=32)
    obj = GMMObjective(sigma_warmup_epochs=0)
    for rates in ([30.0, 5.0, 40.0], [10.0, 10.0, 10.0]):

        def drive(epoch: int, model, rates=rates) -> dict[str, float]:
            return {VAL_ROADS: rates[epoch]}

        train_cfg = small_train_cfg(epochs=3, select_by="val_roads", select_miles=20.0)
        _, hist = train_or_load(
            f"roads{rates[0]:g}", cfg, train_cfg, obj, data, val, progress=False, on_epoch=drive
        )
        ties = [e for e, r in enumerate(rates) if r == min(rates)]
        expected = min(ties, key=lambda e: hist.epochs[e][DECISIVE])
        assert hist.best_epoch == expected
        assert [r[VAL_ROADS] for r in hist.epochs] == rates
    assert hist.best_epoch == int(np.argmin([e[DECISIVE] for e in hist.epochs]))  # all tied
    with pytest.raises(ValueError, match="on_epoch"):
        train_or_load("roads_nohook", cfg, small_train_cfg(select_by="val_roads", select_miles=1.0),
                      obj, data, val, progress=False)  # fmt: skip
    with pytest.raises(ValueError, match="select_miles"):
        TrainConfig(select_by="val_roads")
    with pytest.raises(ValueError, match="select_miles"):
        TrainConfig(select_miles=20.0)
    key = checkpoint_key(cfg, TrainConfig(), obj, "data")
    old = dataclasses.asdict(TrainConfig())
    del old["select_miles"]
    expected = settings_key("checkpoint-v3", cfg, {**old, "device": None}, obj.name, "data", "fp32")
    assert key == expected  # (select_miles left out when unused; the precision is in)
    miles = [TrainConfig(select_by="val_roads", select_miles=m) for m in (10.0, 20.0)]
    assert len({checkpoint_key(cfg, c, obj, "data") for c in miles}) == 2


def test_the_road_scorer_drives_each_epoch_on_validation_roads_alike():
    """The selection drive: the network's driver (by its head) on the validation split, the same
    roads and start lanes for every epoch, so the same weights score the same; the caller's own
    hook still runs."""
    from e2e_lite.config import QUICK
    from e2e_lite.imitation import selection
    from e2e_lite.learning.training import VAL_ROADS

    torch.manual_seed(0)
    model = prepare(
        build_model(ModelConfig(head="actuators", fusion_width=16)), torch.device("cpu")
    )
    assert isinstance(selection.driver_for(model), ActuatorAgent)
    assert isinstance(selection.driver_for(build_model(ModelConfig(head="gmm"))), TrajectoryAgent)
    assert isinstance(
        selection.driver_for(build_model(ModelConfig(kind="pilotnet", head="steer"))),
        SteeringAgent,
    )
    model.train()
    seen = []
    score = selection.road_scorer(
        WorldConfig.for_profile(QUICK), 0.3, also=lambda e, m: seen.append(e), workers=1
    )
    first, again = score(0, model), score(1, model)
    assert first == again and set(first) == {VAL_ROADS, "val roads mph", "val roads stalls"}
    assert seen == [0, 1] and first["val roads mph"] > 0
    assert model.training  # the drive took a copy: the training's model is left as it was


def test_equal_collision_counts_tie_and_a_stored_epoch_the_rule_would_not_keep_is_retrained(
    monkeypatch, capsys
):
    """Drives of one budget end a few metres apart, so 3 collisions give 15.02 or 14.98 per
    100 mi: the rule counts whole collisions, and equal counts go to the lower decisive ADE (the
    bug of f3ded4a's record kept two networks by the third digit of such rates). A checkpoint
    whose kept epoch the rule would not keep is retrained, and so is its fine-tune (whose key
    holds its parent's weights)."""
    from e2e_lite.learning import training
    from e2e_lite.learning.training import VAL_ROADS, kept_epoch, selection_score

    roads = small_train_cfg(select_by="val_roads", select_miles=20.0)
    near = [
        {VAL_ROADS: 15.02, DECISIVE: 0.40, "val_loss": 1.0},
        {VAL_ROADS: 14.98, DECISIVE: 0.60, "val_loss": 1.0},
        {VAL_ROADS: 20.0, DECISIVE: 0.10, "val_loss": 1.0},
    ]
    assert [selection_score(r, roads)[0] for r in near] == [3, 3, 4]
    assert kept_epoch(near, roads) == 0  # the tie, to the lower decisive ADE; not epoch 1
    assert kept_epoch(near, small_train_cfg(select_by="decisive_ade")) == 2

    data, val = synthetic_data(48, 0), synthetic_data(32, 1)
    val.arrays["curvature"][:10] = 0.01
    cfg = ModelConfig(head="gmm", fusion_width=32)
    obj = GMMObjective(sigma_warmup_epochs=0)

    def drive(epoch: int, model) -> dict[str, float]:
        return {VAL_ROADS: 10.0}  # every epoch ties

    # a parent kept by another rule (the highest decisive ADE), and its fine-tune
    def worst(record: dict, cfg: TrainConfig) -> tuple[float, ...]:
        return (-record[DECISIVE],) if cfg.select_by == "val_roads" else (record["val_loss"],)

    with monkeypatch.context() as m:
        m.setattr(training, "selection_score", worst)
        _, old = train_or_load("par", cfg, roads, obj, data, val, progress=False, on_epoch=drive,
                               keep_optimizer=True)  # fmt: skip
        train_or_load("kid", cfg, small_train_cfg(epochs=1), obj, data, val, progress=False,
                      init_from="par", carry_optimizer=True)  # fmt: skip
    assert old.best_epoch == int(np.argmax([e[DECISIVE] for e in old.epochs]))
    _, new = train_or_load("par", cfg, roads, obj, data, val, on_epoch=drive, keep_optimizer=True)
    assert "which train_cfg's rule would not keep" in capsys.readouterr().out
    assert new.best_epoch == int(np.argmin([e[DECISIVE] for e in new.epochs])) != old.best_epoch
    train_or_load("kid", cfg, small_train_cfg(epochs=1), obj, data, val,
                  init_from="par", carry_optimizer=True)  # fmt: skip
    assert "kid: trained with other settings; retraining" in capsys.readouterr().out
    train_or_load("par", cfg, roads, obj, data, val, on_epoch=drive, keep_optimizer=True)
    assert "reusing" in capsys.readouterr().out
