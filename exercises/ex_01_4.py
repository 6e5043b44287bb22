"""Exercise 01.4: how many miles without a collision would you need to claim a rate below one per
100 miles with 95 % confidence (the exact interval chapter 01 prints beside every rate)?

Check: ``python -m e2e_lite.exercises check 01.4``
"""


def miles() -> float:
    """The miles [mi]."""
    raise NotImplementedError("your answer")
