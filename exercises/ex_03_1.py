"""Exercise 03.1: double ``steer_max_rad`` in ``TrackerConfig`` (a cheaper control effort). How do
the settling distance and the overshoot of section 3 change (answer in words)? Where do the
poles move: give the modulus of the closed-loop poles at 20 m/s with the doubled setting.

Check: ``python -m e2e_lite.exercises check 03.1``
"""


def pole_radius() -> float:
    """The largest modulus of the closed-loop poles (discrete, per policy period) at 20 m/s."""
    raise NotImplementedError("your answer")
