"""Chapter 01's exercises 1 and 3, measured: the lane changer's collisions as its trigger_m falls,
and both scripted drivers on tight arcs (``RoadConfig(radius_m=(60, 100))``), with the largest
road-wheel angle each commanded, against the bicycle's limit (docs/solutions.md 01.1, 01.3).

    python lab/scripted_exercises.py [--miles 20]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from e2e_lite.control.drivers import LaneChanger, LaneKeeper
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.simulation.world import WorldConfig, make_world


class Widest:
    """Wraps a driver and keeps the largest |steering| [rad] it commands (the scripted drivers
    have no ``fork``: one shard drives every car through this wrapper)."""

    def __init__(self, driver, widest: list[float] | None = None):
        self.driver, self.widest = driver, widest if widest is not None else [0.0]

    def __getattr__(self, name):
        return getattr(self.driver, name)

    def act(self, obs):
        act = self.driver.act(obs)
        self.widest[0] = max(self.widest[0], float(np.max(np.abs(act.steer_rad))))
        return act


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--miles", type=float, default=20.0)
    args = parser.parse_args()
    cfg = WorldConfig()
    ev = EvalConfig(miles=args.miles, n_worlds=16)
    print(
        f"bicycle: max_steer_rad {cfg.vehicle.max_steer_rad}, wheelbase {cfg.vehicle.wheelbase_m} m"
    )
    for trigger in (70.0, 50.0, 45.0, 40.0, 35.0, 30.0):
        r = evaluate(LaneChanger(trigger_m=trigger), cfg, ev, progress=False, workers=1)
        print(f"lane changer trigger_m {trigger:4.0f} m: {r.summary()}")
    tight = dataclasses.replace(cfg, road=dataclasses.replace(cfg.road, radius_m=(60.0, 100.0)))
    for name, driver in (("lane keeper", LaneKeeper()), ("lane changer", LaneChanger())):
        wrapped = Widest(driver)
        r = evaluate(wrapped, tight, ev, progress=False, workers=1)
        print(
            f"radius 60-100 m, {name}: {r.summary()}; widest wheel angle {wrapped.widest[0]:.3f} rad"
        )
    tracks = [make_world(tight, "test", i).track for i in range(16)]
    kappa = max(float(np.max(np.abs(t.curvature(np.linspace(0, t.length, 4000))))) for t in tracks)
    print(
        f"tightest centre-line radius on those tracks {1 / kappa:.1f} m: wheel angle "
        f"L / R = {cfg.vehicle.wheelbase_m * kappa:.3f} rad (the limit: {cfg.vehicle.max_steer_rad})"
    )


if __name__ == "__main__":
    main()
