"""The course's recipes: the settings rules that chapters share."""

from e2e_lite.recipes import choose_affordance_weight, sigma_warmup


def test_sigma_warmup_is_a_third_of_the_schedule():
    assert [sigma_warmup(e) for e in (1, 2, 3, 6, 15)] == [0, 1, 1, 2, 5]


def test_affordance_weight_is_chosen_on_trajectory_nll():
    scores = {
        0.0: {"trajectory_nll": 3.0},
        0.3: {"trajectory_nll": 2.0},
        1.0: {"trajectory_nll": 2.5},
    }
    assert choose_affordance_weight(scores)[0] == 0.3
    # w = 0 winning is reported, and the best w > 0 is trained instead
    scores[0.0]["trajectory_nll"] = 1.0
    w, why = choose_affordance_weight(scores)
    assert w == 0.3 and "did not help" in why


def test_a_gmm_recipe_with_one_mode_and_a_mismatch_refused():
    """K = 1 (chapter 07's control: the same NLL, no choice of modes) builds a one-mode head."""
    import pytest

    from e2e_lite.config import QUICK
    from e2e_lite.recipes import gmm, gmm_objective

    with pytest.raises(ValueError, match="modes"):
        gmm(QUICK, None, None, objective=gmm_objective(QUICK), modes=1)
    assert gmm_objective(QUICK, n_modes=1).n_modes == 1
