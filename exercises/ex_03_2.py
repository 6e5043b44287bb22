"""Exercise 03.2: remove the feed-forward (``atan(L kappa)``) from ``LQRTracker.steer``. What
steady lateral error does the tracker keep on the 300 m curve at 20 m/s, and why can't the
two-state LQR remove it? Answer the size here; the why in words.

Check: ``python -m e2e_lite.exercises check 03.2``
"""


def steady_error_m() -> float:
    """The steady lateral error's size [m]."""
    raise NotImplementedError("your answer")
