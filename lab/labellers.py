"""Does the labeller drive? The state expert (its plan read off the state; the course's expert at
e4eddca, named "expert" here) and the course's expert (its plan carried; "remembering" here),
each driving, each followed by the tracker at every decision (the oracle on its labels), and the
course's expert's labels with its plans wiped before every label
(chapter 12's old DAgger labeller), on validation roads of the full profile's world: collisions,
speed, manoeuvres and the lateral acceleration of the expert's own driving.

    python lab/labellers.py [--miles 300] [--wiped-miles 100]

Writes docs/results/lab/labellers.json (lab note "Does the labeller drive?").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from e2e_lite.config import FULL
from e2e_lite.control.expert import Expert, WipedExpert
from e2e_lite.control.oracle import Oracle
from e2e_lite.control.state_expert import StateExpert
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.simulation.world import WorldConfig

OUT = Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "labellers.json"


class Lateral:
    """Drives ``expert`` and keeps |lateral acceleration - the road's| of every command [m/s^2]."""

    camera = None

    def __init__(self, expert) -> None:
        self.expert, self.sim, self.a_lat = expert, expert.sim, []

    def seed_cars(self, cars):
        self.expert.seed_cars(cars)

    def reset(self, n):
        self.expert.reset(n)

    def act(self, obs):
        act = self.expert.act(obs)
        v = obs.speed
        wheelbase = obs.worlds[0].vehicle.wheelbase_m
        self.a_lat.append(np.abs(v * v * np.tan(act.steer_rad) / wheelbase - v * v * obs.curvature))
        return act


def drive(policy, world, ev, workers=None):
    t = time.perf_counter()
    res = evaluate(policy, world, ev, progress=True, workers=workers)
    r = res.to_dict(with_events=False)
    keep = ("collisions", "car_collisions", "rail_collisions", "miles", "mean_speed_mph", "stalls")
    return {
        **{k: r[k] for k in keep},
        "manoeuvres": dict(res.info.get("manoeuvres", {})),
        "wall_s": round(time.perf_counter() - t, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--miles", type=float, default=300.0)
    parser.add_argument("--wiped-miles", type=float, default=100.0)
    args = parser.parse_args()
    world = WorldConfig.for_profile(FULL)
    ev = EvalConfig(miles=args.miles, n_worlds=32, split="val", first_track=5_000)
    out = {"roads": "validation, first track 5,000, 32 cars, the full profile's world"}
    for name, kind in (("expert", StateExpert), ("remembering", Expert)):
        lateral = Lateral(kind(sim=world.sim))
        out[name] = drive(lateral, world, ev, workers=1)
        a = np.concatenate(lateral.a_lat)
        out[name]["lateral_m_s2_p50_p99_p999_max"] = np.percentile(a, [50, 99, 99.9, 100]).tolist()
        out[f"oracle on {name}"] = drive(Oracle(kind(sim=world.sim)), world, ev)
        print(name, out[name], out[f"oracle on {name}"], flush=True)
    wiped_ev = dataclasses.replace(ev, miles=args.wiped_miles)
    out["oracle on wiped"] = drive(Oracle(WipedExpert(sim=world.sim)), world, wiped_ev)
    print(out["oracle on wiped"])
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
