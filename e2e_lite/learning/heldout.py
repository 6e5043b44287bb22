"""Held-out measures of what the networks predict, beside their losses: how a mixture's modes
split (:func:`mode_split`), which side the followed trajectory takes at an overtake start
(:func:`side_shares`), and the affordance head's errors against the floor of always answering
the training mean (:func:`affordance_errors`, with chapter 08's goals :data:`AFFORDANCE_GOALS` and
:func:`goal_ratios`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .labels import AFFORDANCE_NAMES, GAP_CAP_M


def mode_split(modes_m: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How the two most likely modes of each sample differ at the last point (1.5 s):
    ``(lateral |dy| [m], longitudinal |dx| [m])``, each (B,).

    Args:
        modes_m: (B, K, 5, 2) mode means in metres (car frame), K >= 2.
        weights: (B, K) mixing weights.
    """
    modes_m, weights = np.asarray(modes_m), np.asarray(weights)
    if modes_m.ndim != 4 or modes_m.shape[1] < 2 or weights.shape != modes_m.shape[:2]:
        raise ValueError(
            f"mode_split needs modes (B, K>=2, 5, 2) and weights (B, K); got {modes_m.shape}, "
            f"{weights.shape}"
        )
    order = np.argsort(-weights, axis=1, kind="stable")[:, :2]
    rows = np.arange(len(modes_m))[:, None]
    first, second = modes_m[rows, order][:, 0, -1], modes_m[rows, order][:, 1, -1]  # (B, 2)
    gap = np.abs(first - second)
    return gap[:, 1], gap[:, 0]


def side_shares(
    followed_end_y_m: np.ndarray, expert_side: np.ndarray, committed_m: float = 0.9
) -> dict[str, float]:
    """Which way a followed trajectory goes where the expert changes lanes: the shares of samples
    whose lateral offset at 1.5 s is past ``committed_m`` towards the expert's side
    (``"expert_side"``), past it towards the other side (``"other_side"``), or neither
    (``"keep"``).

    Args:
        followed_end_y_m: (N,) lateral offset of the followed trajectory at 1.5 s [m], left > 0.
        expert_side: (N,) +1 when the expert goes left, -1 right.
        committed_m: offset that counts as going to a side [m] (default a quarter lane).
    """
    y, side = np.asarray(followed_end_y_m, float), np.asarray(expert_side, float)
    if y.shape != side.shape or not len(y):
        raise ValueError(
            f"side_shares needs two equal, non-empty arrays; got {y.shape}, {side.shape}"
        )
    towards = y * np.sign(side)
    expert = float(np.mean(towards > committed_m))
    other = float(np.mean(towards < -committed_m))
    return {"expert_side": expert, "other_side": other, "keep": 1.0 - expert - other}


#: Chapter 08's goals for the affordance head on held-out frames: the error that must be at most
#: half the mean predictor's: MAE of the gap on frames with a car ahead, RMSE of the
#: lane-centre offset and the heading.
AFFORDANCE_GOALS = (
    ("gap_ego_m_car_ahead", "mae"),
    ("center_offset_m", "rmse"),
    ("heading_rad", "rmse"),
)


def affordance_errors(
    pred: np.ndarray, true: np.ndarray, train_mean: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Held-out errors of predicted affordances against the floor to beat: always answering the
    training set's mean.

    Args:
        pred, true: (N, 9) predicted and true affordances (units of :data:`AFFORDANCE_NAMES`).
        train_mean: (9,) the training set's mean of each.

    Returns:
        ``{name: {"model": {"mae", "rmse"}, "mean_predictor": {"mae", "rmse"}, "frames": n}}``
        for each affordance, plus ``"gap_ego_m_car_ahead"``: the gap on the frames with a parked
        car ahead in the own lane (true gap below :data:`~e2e_lite.learning.labels.GAP_CAP_M`), where
        knowing the gap matters (elsewhere the answer is the cap).
    """
    pred, true = np.asarray(pred, np.float64), np.asarray(true, np.float64)
    train_mean = np.asarray(train_mean, np.float64).reshape(-1)
    n_aff = len(AFFORDANCE_NAMES)
    if pred.shape != true.shape or pred.ndim != 2 or pred.shape[1] != n_aff or not len(pred):
        raise ValueError(
            f"affordance_errors needs (N, {n_aff}) predictions and truths, N >= 1; got "
            f"{pred.shape}, {true.shape}"
        )

    def errors(p: np.ndarray, t: np.ndarray, mean: float) -> dict[str, Any]:
        return {
            "model": {
                "mae": float(np.abs(p - t).mean()),
                "rmse": float(np.sqrt(((p - t) ** 2).mean())),
            },
            "mean_predictor": {
                "mae": float(np.abs(mean - t).mean()),
                "rmse": float(np.sqrt(((mean - t) ** 2).mean())),
            },
            "frames": len(t),
        }

    out = {n: errors(pred[:, j], true[:, j], train_mean[j]) for j, n in enumerate(AFFORDANCE_NAMES)}
    gap = AFFORDANCE_NAMES.index("gap_ego_m")
    ahead = true[:, gap] < GAP_CAP_M
    if ahead.any():
        out["gap_ego_m_car_ahead"] = errors(pred[ahead, gap], true[ahead, gap], train_mean[gap])
    return out


def goal_ratios(errors: dict[str, dict[str, Any]]) -> dict[str, float]:
    """Each of :data:`AFFORDANCE_GOALS`' errors as a share of the mean predictor's (the goal: at
    most 0.5), keyed ``"<name> <mae|rmse>"``, from :func:`affordance_errors`' answer (a goal
    whose frames are absent, e.g. no car ahead, is left out)."""
    return {
        f"{name} {kind}": errors[name]["model"][kind] / errors[name]["mean_predictor"][kind]
        for name, kind in AFFORDANCE_GOALS
        if name in errors
    }
