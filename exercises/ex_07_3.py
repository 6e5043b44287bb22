"""Exercise 07.3: following the mixture's mean. Write the mean of a mixture's modes, each weighted
by its mixing weight (then draw it on chapter 07's parked-car frame and drive it, as the
chapter's exercise asks).

Check: ``python -m e2e_lite.exercises check 07.3``
"""

import numpy as np


def mixture_mean(weights: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """The mixture's mean (B, D) from its weights (B, K), summing to 1, and modes (B, K, D)."""
    raise NotImplementedError("your answer")
