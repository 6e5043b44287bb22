"""Where does the expert's lateral acceleration peak? The expert (its note ran the state expert,
the course's expert at a73c5b7) drives the roads of the lab note "Does the labeller drive?"
(validation, first track 5,000, 32 cars, the full profile's world; its script is at e4eddca),
and every decision whose commanded lateral acceleration, less the road's, exceeds a threshold is
kept with its state and its decision (which branch of the state table chose it).

    python lab/lateral_outliers.py [--miles 300] [--over 5.0]

Writes docs/results/lab/lateral_outliers.json (lab note "Does the labeller drive?").
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from labellers import Lateral, drive

from e2e_lite.config import FULL
from e2e_lite.control.expert import Expert
from e2e_lite.driving.evaluation import EvalConfig
from e2e_lite.learning.labels import STATE_NAMES as NAMES
from e2e_lite.simulation.world import WorldConfig

OUT = Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "lateral_outliers.json"


class Outliers(Lateral):
    """:class:`Lateral`, keeping each decision over ``over`` [m/s^2] with its car's state."""

    def __init__(self, expert: Expert, over: float) -> None:
        super().__init__(expert)
        self.over, self.kept, self.before = over, [], None

    def act(self, obs):
        before = self.before or self.expert.decisions
        act = super().act(obs)
        for i in np.flatnonzero(self.a_lat[-1] > self.over):
            now = self.expert.decisions[i]
            self.kept.append(
                {
                    "lateral_m_s2": float(self.a_lat[-1][i]),
                    "time_s": round(obs.time_s, 1),
                    "car": int(i),
                    "speed_m_s": float(obs.speed[i]),
                    "lane": int(obs.lane[i]),
                    "offset_from_lane_centre_m": float(
                        obs.d[i] - obs.worlds[i].track.lane_center(int(obs.lane[i]))
                    ),
                    "heading_error_deg": math.degrees(obs.heading_error[i]),
                    "steer_deg_before_after": [
                        math.degrees(obs.state[i, 4]),
                        math.degrees(act.steer_rad[i]),
                    ],
                    "decision_before": [NAMES[before[i].state], before[i].target],
                    "decision": [NAMES[now.state], now.target],
                }
            )
        self.before = list(self.expert.decisions)
        return act


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--miles", type=float, default=300.0)
    parser.add_argument("--over", type=float, default=5.0, help="threshold [m/s^2]")
    args = parser.parse_args()
    world = WorldConfig.for_profile(FULL)
    ev = EvalConfig(miles=args.miles, n_worlds=32, split="val", first_track=5_000)
    probe = Outliers(Expert(sim=world.sim), args.over)
    out = {"roads": "validation, first track 5,000, 32 cars, the full profile's world"}
    out["drive"] = drive(probe, world, ev, workers=1)
    a = np.concatenate(probe.a_lat)
    out["decisions"], out["over_m_s2"] = int(a.size), args.over
    out["kept"] = sorted(probe.kept, key=lambda k: -k["lateral_m_s2"])
    OUT.write_text(json.dumps(out, indent=1) + "\n")
    print(f"{len(probe.kept)} of {a.size} decisions over {args.over} m/s^2; wrote {OUT}")


if __name__ == "__main__":
    main()
