"""The reference answer of exercise 01.1 (the suite checks that it passes and the stub does
not; keep it from students)."""


def lookahead_m() -> float:
    """The look-ahead [m]: the lateral error's second-order response to a lane's step, until the
    car has moved by the two cars' half widths, at 25 m/s."""
    wn, zeta, lane_m, clear_m, dt = 1.0, 0.9, 3.7, 1.8, 1e-3
    d = v = t = 0.0
    while d < clear_m:
        v += (-(wn**2) * (d - lane_m) - 2.0 * zeta * wn * v) * dt
        d += v * dt
        t += dt
    return 25.0 * t
