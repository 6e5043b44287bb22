"""The reference answer of exercise 02.1 (the suite checks that it passes and the stub
does not; keep it from students)."""


def car_width_px() -> float:
    """The car's width in the image [px]."""
    import math

    f = (200 / 2) / math.tan(math.radians(90.0) / 2)  # 100 px
    return f * 1.8 / 60.0  # a 1.8 m car 60 m ahead: 3 px
