"""The GMM loss against direct computations, its numerical safety, mode selection, sigma warm-up."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import multivariate_normal

from e2e_lite.imitation.collector import DrivingDataset, synthetic_data
from e2e_lite.learning.heads import Mixture, gmm_nll, log_sigma, split_gmm
from e2e_lite.learning.heldout import mode_split, side_shares
from e2e_lite.learning.losses import GMMObjective, Objective
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.learning.training import TrainConfig, fit, model_stats


def direct_nll(y, weights, means, sigmas):
    """-log sum_k w_k N(y; mu_k, diag(sigma_k^2)) with scipy densities."""
    dens = sum(
        w * multivariate_normal(mean=m, cov=np.diag(s**2)).pdf(y)
        for w, m, s in zip(weights, means, sigmas)
    )
    return -math.log(dens)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_gmm_nll_equals_scipy(k):
    rng = np.random.default_rng(k)
    y = rng.normal(size=10)
    means = rng.normal(size=(k, 10))
    sigmas = rng.uniform(0.5, 2.0, size=(k, 10))
    logits = rng.normal(size=k)
    weights = np.exp(logits) / np.exp(logits).sum()
    ours = gmm_nll(
        torch.tensor(y)[None],
        torch.tensor(logits)[None],
        torch.tensor(means)[None],
        torch.tensor(np.log(sigmas))[None],
    )
    assert float(ours[0]) == pytest.approx(direct_nll(y, weights, means, sigmas), rel=1e-9)


def test_one_mode_with_unit_sigma_is_scaled_mse_plus_constant():
    rng = np.random.default_rng(0)
    y, mu = torch.tensor(rng.normal(size=(6, 10))), torch.tensor(rng.normal(size=(6, 1, 10)))
    nll = gmm_nll(y, torch.zeros(6, 1, dtype=torch.float64), mu, torch.zeros_like(mu))
    mse = ((y - mu[:, 0]) ** 2).mean(dim=1)
    torch.testing.assert_close(nll, 5.0 * mse + 5.0 * math.log(2 * math.pi))


@settings(max_examples=60, deadline=None)
@given(
    mean_scale=st.floats(1e-3, 1e4),
    raw_sigma=st.floats(-60.0, 10.0),
    logit=st.floats(-50.0, 50.0),
    k=st.integers(1, 4),
)
def test_loss_and_gradients_stay_finite_for_extreme_inputs(mean_scale, raw_sigma, logit, k):
    out = torch.zeros(3, k * 21)
    out[:, : k * 10] = mean_scale * torch.linspace(-1, 1, k * 10)
    out[:, k * 10 : k * 20] = raw_sigma
    out[:, k * 20 :] = torch.linspace(-logit, logit, k)
    out.requires_grad_(True)
    logits, means, raw = split_gmm(out, k)
    loss = gmm_nll(torch.zeros(3, 10), logits, means, log_sigma(raw, 0.01)).mean()
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(out.grad).all()


def test_sigma_floor_is_smooth_and_respected():
    raw = torch.tensor([-100.0, 0.0, 5.0])
    ls = log_sigma(raw, 0.01)
    assert ls[0] == pytest.approx(math.log(0.01), abs=1e-6)
    assert ls[1] == pytest.approx(math.log(1.01)) and ls[2] == pytest.approx(
        math.log(0.01 + math.exp(5))
    )


def test_most_likely_mode_and_shapes():
    weights = torch.tensor([[0.2, 0.8], [0.9, 0.1]])
    means = torch.arange(40.0).reshape(2, 2, 10)
    mix = Mixture(torch.log(weights), means, torch.zeros_like(means))
    torch.testing.assert_close(mix.followed("top"), torch.stack([means[0, 1], means[1, 0]]))
    for k in (1, 2, 5):
        logits, mu, raw = split_gmm(torch.zeros(4, k * 21), k)
        assert logits.shape == (4, k) and mu.shape == raw.shape == (4, k, 10)


def test_bad_sizes_raise():
    with pytest.raises(ValueError, match="n_modes"):
        split_gmm(torch.zeros(2, 21), 0)
    with pytest.raises(ValueError, match="columns"):
        split_gmm(torch.zeros(2, 40), 2)
    with pytest.raises(ValueError, match="mismatched"):
        gmm_nll(torch.zeros(2, 9), torch.zeros(2, 2), torch.zeros(2, 2, 10), torch.zeros(2, 2, 10))
    with pytest.raises(ValueError, match=r"GMMObjective\.n_modes"):
        GMMObjective(n_modes=0)


def test_sigma_is_frozen_during_warmup_and_opened_after():
    train, val = synthetic_data(32, 0), synthetic_data(16, 1)
    cfg = ModelConfig(head="gmm", fusion_width=32)
    torch.manual_seed(0)
    model = prepare(build_model(cfg), torch.device("cpu"))
    model.set_normalisation(model_stats(cfg, train, GMMObjective()))
    tcfg = TrainConfig(epochs=1, batch_size=16, device="cpu")
    before = {n: p.detach().clone() for n, p in model.named_parameters()}
    hist = fit(
        model,
        GMMObjective(sigma_warmup_epochs=1),
        DrivingDataset(train),
        DrivingDataset(val),
        tcfg,
        progress=False,
    )
    assert hist.epochs[0]["frozen"] == ["head.log_sigma"]
    after = dict(model.named_parameters())
    assert torch.equal(after["head.log_sigma.weight"], before["head.log_sigma.weight"])
    assert not torch.equal(after["head.means.weight"], before["head.means.weight"])
    fit(
        model,
        GMMObjective(sigma_warmup_epochs=0),
        DrivingDataset(train),
        DrivingDataset(val),
        tcfg,
        progress=False,
    )
    assert not torch.equal(model.head.log_sigma.weight, before["head.log_sigma.weight"])


def test_normalisation_round_trip():
    data = synthetic_data(16)
    cfg = ModelConfig(head="gmm")
    model = build_model(cfg)
    model.set_normalisation(model_stats(cfg, data, GMMObjective()))
    x = torch.from_numpy(data.trajectory.reshape(16, 10))
    torch.testing.assert_close(
        model.denormalise(model.normalise_target(x)), x, rtol=1e-6, atol=1e-5
    )
    assert model.normalise_target(x).mean(dim=0).abs().max() < 1e-4  # the stats are this data's


@pytest.mark.parametrize(
    "objective_of",
    [
        lambda n: GMMObjective(normalise_targets=n),
        lambda n: Objective("trajectory", normalise_targets=n),
    ],
)
def test_target_normalisation_is_a_switch(objective_of):
    """Off: the model carries the identity and the loss sees metres; the two runs get
    different checkpoint names (so one never reuses the other's)."""
    data = synthetic_data(16)
    cfg = ModelConfig(head="gmm" if isinstance(objective_of(True), GMMObjective) else "trajectory")
    on, off = objective_of(True), objective_of(False)
    assert on.name != off.name
    stats = model_stats(cfg, data, off)
    assert np.all(stats["target_mean"] == 0) and np.all(stats["target_std"] == 1)
    assert np.any(model_stats(cfg, data, on)["target_std"] != 1)
    model = build_model(cfg)
    model.set_normalisation(stats)
    x = torch.from_numpy(data.trajectory.reshape(16, 10))
    torch.testing.assert_close(model.normalise_target(x), x)
    model.eval()
    batch = DrivingDataset(data).batch(np.arange(16))
    with torch.no_grad():
        out = model(batch["image"], batch["speed"])
        loss = off.per_sample(out, batch, model, epoch=0)  # (a GMM in its warm-up)
    if isinstance(off, GMMObjective):
        logits, means, _ = split_gmm(out["main"], 2)
        expected = gmm_nll(x, logits, means, torch.zeros_like(means))  # warm-up: sigma = 1 m
    else:
        expected = ((out["main"] - x) ** 2).mean(dim=1)
    torch.testing.assert_close(loss, expected)


def test_mode_split_on_hand_made_mixtures():
    modes = np.zeros((2, 3, 5, 2))
    modes[0, 0, -1] = (37.0, 1.5)  # sample 0: left and right modes, 0.4 m apart in x
    modes[0, 1, -1] = (37.4, -1.8)
    modes[0, 2, -1] = (10.0, 0.0)  # the least likely: ignored
    modes[1, 0, -1] = (30.0, 0.1)  # sample 1: a slow and a fast keep-lane mode
    modes[1, 2, -1] = (36.0, 0.1)
    weights = np.array([[0.5, 0.4, 0.1], [0.6, 0.1, 0.3]])
    lateral, longitudinal = mode_split(modes, weights)
    np.testing.assert_allclose(lateral, [3.3, 0.0], atol=1e-12)
    np.testing.assert_allclose(longitudinal, [0.4, 6.0], atol=1e-12)
    with pytest.raises(ValueError, match="mode_split"):
        mode_split(modes[:, :1], weights[:, :1])


def test_side_shares_on_hand_made_offsets():
    y = np.array([2.0, 1.0, -1.5, 0.2, -2.0, 0.5])
    side = np.array([1, 1, 1, 1, -1, -1])  # the expert goes left, left, left, left, right, right
    shares = side_shares(y, side)
    assert shares == pytest.approx({"expert_side": 3 / 6, "other_side": 1 / 6, "keep": 2 / 6})
    assert side_shares(y, side, committed_m=1.2)["expert_side"] == pytest.approx(2 / 6)
    with pytest.raises(ValueError, match="side_shares"):
        side_shares(y, side[:3])


def test_axis_scale_and_a_floor_in_metres():
    """Per axis: every x shares one scale and every y another; the model's floor in metres
    becomes floor / scale per coordinate, and the NLL (and an agent reading the sigmas)
    respects it."""
    data = synthetic_data(32)
    data.arrays["trajectory"][:, :, 1] *= np.arange(1, 6) / 5.0  # lateral spread grows with time
    from e2e_lite.imitation.collector import dataset_stats

    data.stats.update(dataset_stats(data.arrays))
    obj = GMMObjective(target_scale="axis")
    assert obj.name == "gmm-nll-K2-warmup1-axis"
    cfg = ModelConfig(head="gmm", fusion_width=16, sigma_floor_m=0.1)
    model = build_model(cfg)
    model.set_normalisation(model_stats(cfg, data, obj))
    std = model.target_std.reshape(5, 2)
    assert torch.all(std[:, 0] == std[0, 0]) and torch.all(std[:, 1] == std[0, 1])
    per_coord = data.stats["trajectory_std"].astype(np.float64)
    assert float(std[0, 1]) == pytest.approx(np.sqrt(np.mean(per_coord[:, 1] ** 2)), rel=1e-5)
    torch.testing.assert_close(model.sigma_floor(), 0.1 / model.target_std)
    out = {"main": torch.zeros(4, 42)}
    out["main"][:, 20:40] = -50.0  # raw log-sigma far below the floor
    _, _, log_sig = obj.modes(out, model)
    torch.testing.assert_close(torch.exp(log_sig[0, 0]) * model.target_std, torch.full((10,), 0.1))
    # the model without a floor in metres: the default 0.01 standard deviations
    plain = build_model(ModelConfig(head="gmm", fusion_width=16))
    plain.set_normalisation(model_stats(cfg, data, obj))
    _, _, log_sig = obj.modes(out, plain)
    torch.testing.assert_close(torch.exp(log_sig[0, 0]), torch.full((10,), 0.01))
    with pytest.raises(ValueError, match="sigma_floor_m"):
        ModelConfig(head="gmm", sigma_floor_m=0.0)
    with pytest.raises(ValueError, match="target_scale"):
        GMMObjective(target_scale="pixel")


def test_the_mixture_object_reads_the_heads_output_like_the_functions_it_wraps():
    gen = torch.Generator().manual_seed(3)
    out = torch.randn(5, 2 * 21, generator=gen, dtype=torch.float64)
    mix = Mixture.from_output(out, 2, 0.05)
    logits, means, raw = split_gmm(out, 2)
    assert torch.equal(mix.logits, logits) and torch.equal(mix.means, means)
    assert torch.equal(mix.log_sigma, log_sigma(raw, 0.05))
    assert torch.allclose(mix.weights.sum(dim=-1), torch.ones(5, dtype=torch.float64))
    y = torch.randn(5, 10, generator=gen, dtype=torch.float64)
    assert torch.equal(mix.nll(y), gmm_nll(y, logits, means, log_sigma(raw, 0.05)))
    held = Mixture.from_output(out, 2, 0.05, sigma_fixed=True)
    assert torch.equal(held.log_sigma, torch.zeros_like(raw))  # the warm-up: every sigma 1
    top = mix.followed("top")
    for b in range(5):  # the heaviest mode's mean, sample by sample
        assert torch.equal(top[b], means[b, int(torch.argmax(logits[b]))])
    w = torch.softmax(logits, dim=-1)
    assert torch.allclose(mix.followed("mean"), (w[..., None] * means).sum(dim=1))
    metres = means * 2.0 + 1.0  # the same modes in other units
    assert torch.allclose(mix.followed("top", metres), top * 2.0 + 1.0)
