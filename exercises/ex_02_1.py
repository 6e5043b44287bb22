"""Exercise 02.1: set ``hfov_deg=90`` and look at the "car ahead" scene at 66 x 200. How many
pixels does a parked car 60 m ahead cover across the image? (What that does to a network that
must decide when to overtake, answer in words.)

Check: ``python -m e2e_lite.exercises check 02.1``
"""


def car_width_px() -> float:
    """The car's width in the image [px]."""
    raise NotImplementedError("your answer")
