"""The course's recipes: the settings rules that chapters share."""

from e2e_lite.imitation.recipes import choose_affordance_weight, sigma_warmup


def test_sigma_warmup_is_a_third_of_the_schedule():
    assert [sigma_warmup(e) for e in (1, 2, 3, 6, 15)] == [0, 1, 1, 2, 5]


def test_affordance_weight_is_chosen_on_trajectory_nll_then_on_perception():
    scores = {
        0.0: {"trajectory_nll": 3.0, "affordance_rel_mae": 0.9},
        0.3: {"trajectory_nll": 2.0, "affordance_rel_mae": 0.8},
        1.0: {"trajectory_nll": 2.5, "affordance_rel_mae": 0.4},
    }
    assert choose_affordance_weight(scores)[0] == 0.3
    # w = 0 winning is reported, and the w > 0 whose head perceives best is trained instead
    scores[0.0]["trajectory_nll"] = 1.0
    w, why = choose_affordance_weight(scores)
    assert w == 1.0 and "did not help" in why and "affordance error" in why


def test_a_gmm_recipe_with_one_mode_and_a_mismatch_refused():
    """K = 1 (chapter 07's control: the same NLL, no choice of modes) builds a one-mode head."""
    import numpy as np
    import pytest

    from e2e_lite.config import QUICK
    from e2e_lite.imitation.recipes import gmm, gmm_config, gmm_objective
    from e2e_lite.learning.dataset import DrivingDataset, synthetic_data
    from e2e_lite.learning.models import build_model
    from e2e_lite.learning.training import model_stats

    with pytest.raises(ValueError, match="modes"):
        gmm(QUICK, None, None, objective=gmm_objective(QUICK), modes=1)
    # the one-mode recipe's network and loss agree, and the loss is the one-mode NLL
    one, two = gmm_objective(QUICK, n_modes=1), gmm_objective(QUICK)
    model = build_model(gmm_config(modes=1, fusion_width=16))
    data = synthetic_data(8)
    model.set_normalisation(model_stats(model.cfg, data, one))
    batch = DrivingDataset(data).batch(np.arange(8))
    out = model(batch["image"], batch["speed"])
    assert out["main"].shape[1] == model.cfg.out_size == 21  # 10 means, 10 sigmas, 1 weight
    assert one.per_sample(out, batch, model).shape == (8,) and "K1" in one.name
    with pytest.raises(ValueError, match="n_modes=2, but the model's head has 1 modes"):
        two.per_sample(out, batch, model)


def test_the_course_holds_every_sigma_at_one_and_the_paper_s_sigmas_open_after_the_warm_up():
    """The course's GMM (``GMM_SIGMA = "held"``) trains the means and weights with sigma = 1 and
    the log-sigma layer frozen in every epoch, and is scored so after training; the paper's
    learned sigmas open after the warm-up. The recipe refuses an objective given beside
    ``sigma``, and an unknown value names its owner."""
    from types import SimpleNamespace

    import pytest
    import torch

    from e2e_lite.config import FULL
    from e2e_lite.imitation.recipes import GMM_SIGMA, gmm, gmm_objective
    from e2e_lite.learning.heads import LOG_2PI
    from e2e_lite.learning.losses import GMMObjective

    assert GMM_SIGMA == "held"  # the course's choice (lab note "Every epoch on the road")
    fixed = gmm_objective(FULL)
    learned = gmm_objective(FULL, sigma="learned")
    for epoch in range(FULL.train_epochs):
        assert fixed.sigma_fixed(epoch) and fixed.frozen_prefixes(epoch) == ["head.log_sigma"]
    assert fixed.sigma_fixed(None)  # scored after training as it trained
    assert learned.sigma_fixed(0) and learned.frozen_prefixes(0) == ["head.log_sigma"]
    assert not learned.sigma_fixed(FULL.train_epochs - 1) and not learned.sigma_fixed(None)
    assert learned.frozen_prefixes(FULL.train_epochs - 1) == []
    assert fixed.name != learned.name  # a different checkpoint key
    with pytest.raises(ValueError, match="GMMObjective: sigma='fixed'"):
        GMMObjective(sigma="fixed")
    with pytest.raises(ValueError, match="gmm_objective: sigma='open'"):
        gmm_objective(FULL, sigma="open")
    # held at 1: the NLL is a soft mixture of squared errors whatever the raw log-sigmas say
    y, means = torch.zeros(3, 10), torch.randn(3, 2, 10)
    raw = torch.cat([means.reshape(3, -1), torch.full((3, 20), -5.0), torch.zeros(3, 2)], 1)
    from e2e_lite.learning.heads import Mixture

    model = SimpleNamespace(
        normalise_target=lambda t: t,
        mixture=lambda out, fixed=False: Mixture.from_output(out, 2, 0.01, fixed),
    )
    nll = fixed.per_sample({"main": raw}, {"trajectory": y}, model, epoch=FULL.train_epochs - 1)
    sq = 0.5 * ((y[:, None] - means) ** 2).sum(-1) + 5 * LOG_2PI
    expected = -torch.logsumexp(torch.log(torch.tensor(0.5)) - sq, dim=1)
    assert torch.allclose(nll, expected, atol=1e-5)
    with pytest.raises(ValueError, match="not both"):
        gmm(FULL, None, None, objective=learned, sigma="learned")


def test_the_affordance_weight_is_scored_once_per_data_and_grid(tmp_path, monkeypatch):
    """Chapters that build several seeds ask for ``w`` once per seed: the grid is scored once, and
    again when a grid checkpoint changes or the data has no settings key."""
    from types import SimpleNamespace

    from e2e_lite import artifacts
    from e2e_lite.config import QUICK
    from e2e_lite.imitation import recipes

    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path))
    monkeypatch.setattr(recipes, "_CHOSEN_WEIGHTS", {})
    scored = []

    def fake_grid(profile, train, val, **kw):
        scored.append(train.info.get("key"))
        return {0.0: {"trajectory_nll": 2.0, "affordance_rel_mae": 0.9},
                1.0: {"trajectory_nll": 1.0, "affordance_rel_mae": 0.5}}  # fmt: skip

    monkeypatch.setattr(recipes, "affordance_grid", fake_grid)
    train, val = SimpleNamespace(info={"key": "t"}), SimpleNamespace(info={"key": "v"})
    assert [recipes.affordance_weight(QUICK, train, val) for _ in range(3)] == [1.0] * 3
    assert scored == ["t"]
    # another training set is scored
    recipes.affordance_weight(QUICK, SimpleNamespace(info={"key": "t2"}), val)
    assert scored == ["t", "t2"]
    # a grid checkpoint written (or retrained) since: scored again, then remembered
    artifacts.artifact_path("checkpoints", "08_grid_w1.pt").write_bytes(b"retrained")
    recipes.affordance_weight(QUICK, train, val)
    recipes.affordance_weight(QUICK, train, val)
    assert scored == ["t", "t2", "t"]
    # data without a settings key is never remembered
    keyless = SimpleNamespace(info={})
    recipes.affordance_weight(QUICK, keyless, val)
    recipes.affordance_weight(QUICK, keyless, val)
    assert scored == ["t", "t2", "t", None, None]
