"""The perceived safety module's "nothing seen" thresholds, calibrated on training frames
(chapter 11): a learned head answers around the 60 m cap with noise, so a threshold that suits
the true gaps sees parked cars that are not there."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..control.labels import AFFORDANCE_INDEX as _A
from ..control.labels import GAP_CAP_M, GAP_NAMES
from .safety import SafetyConfig

#: The share of training frames with nothing within the cap on which a calibrated
#: ``gap_free_m`` may still see a car (:func:`calibrate_gap_free`).
GHOST_SHARE = 0.01
_GAPS = [_A[n] for n in GAP_NAMES]


def calibrate_gap_free(
    cfg: SafetyConfig, predicted: np.ndarray, true: np.ndarray, ghost_share: float = GHOST_SHARE
) -> SafetyConfig:
    """``cfg`` with the "nothing seen" thresholds set for a perception whose gaps are noisy at
    the cap: ``gap_free_m`` for the ego lane, ``gap_free_side_m`` for the left and right lanes.

    A free lane's true gap is exactly :data:`~e2e_lite.control.labels.GAP_CAP_M`; a learned head
    answers around it (chapter 11 prints how widely), so a threshold just under the cap sees a
    parked car on the free frames whose answer falls under it, and "cannot stop" brakes for it.
    Each calibrated threshold is the ``ghost_share`` quantile of the predicted gaps on frames
    whose true gap is at the cap (the ego lane's alone; the left and right lanes' pooled): with
    it, at most that share of those frames sees a car that is not there. The price: a car
    between the threshold and the cap counts as not seen until it comes nearer (at 25 m/s,
    2.5 m per decision). The lanes are calibrated apart because a head may see its own lane
    more sharply than its neighbours (a pooled quantile would then blind the ego lane to the
    cars the network overtakes).

    Args:
        cfg: the settings to start from; its ``gap_free_m`` bounds both thresholds.
        predicted, true: (N, 9) affordances of the same frames, predicted and true (training
            frames: the thresholds must not be chosen on the evaluation's tracks).
        ghost_share: the share of free frames allowed to see a car, in (0, 1).

    Returns:
        The settings with each threshold ``min(cfg.gap_free_m, quantile)`` (at least 1 m); a
        threshold whose lanes are never free in the frames is left as it was.
    """
    p, t = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    if p.shape != t.shape or p.ndim != 2 or p.shape[1] != len(_A):
        raise ValueError(
            f"calibrate_gap_free needs (N, {len(_A)}) predictions and truths; got {p.shape}, "
            f"{t.shape}"
        )
    if not 0.0 < ghost_share < 1.0:
        raise ValueError(f"calibrate_gap_free: ghost_share={ghost_share} must lie in (0, 1)")

    def threshold(columns: list[int], current: float | None) -> float | None:
        free = t[:, columns] >= GAP_CAP_M
        if not free.any():
            return current
        quantile = float(np.quantile(p[:, columns][free], ghost_share))
        return max(1.0, min(cfg.gap_free_m, quantile))

    ego, side = _GAPS[:1], _GAPS[1:]
    return replace(
        cfg,
        gap_free_m=threshold(ego, cfg.gap_free_m),
        gap_free_side_m=threshold(side, cfg.gap_free_side_m),
    )
