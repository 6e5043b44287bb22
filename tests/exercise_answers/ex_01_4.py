"""The reference answer of exercise 01.4 (the suite checks that it passes and the stub
does not; keep it from students)."""


def miles() -> float:
    """The miles [mi]."""
    import math

    return 100.0 * -math.log(0.025)  # the exact interval's upper end at 0: -ln(0.025) / exposure
