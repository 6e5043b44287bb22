"""Exercise 01.1: what look-ahead does the lane changer need at 25 m/s with its steering law?
The smallest ``trigger_m`` (the gap from its front bumper to a parked car's rear in its lane) at
which it still passes the car: time its lateral move (chapter 01's lane keeper is a second-order
law, ``wn_radps`` and ``zeta``) until its side clears the parked car's side.

Check: ``python -m e2e_lite.exercises check 01.1``
"""


def lookahead_m() -> float:
    """The look-ahead [m]."""
    raise NotImplementedError("your answer")
