"""The reference answer of exercise 03.2 (the suite checks that it passes and the stub
does not; keep it from students)."""


def steady_error_m() -> float:
    """The steady lateral error's size [m]."""
    import math

    from e2e_lite.control.tracker import LQRTracker
    from e2e_lite.simulation.vehicle import VehicleParams

    # psi = 0 at steady state: the feedback k_e e must give the curve's steering, atan(L / R)
    return math.atan(VehicleParams().wheelbase_m / 300.0) / LQRTracker().gain(20.0)[0]
