"""The reference answer of exercise 07.3 (the suite checks that it passes and the stub
does not; keep it from students)."""

import numpy as np


def mixture_mean(weights: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """The mixture's mean (B, D) from its weights (B, K), summing to 1, and modes (B, K, D)."""
    return (weights[..., None] * modes).sum(axis=1)
