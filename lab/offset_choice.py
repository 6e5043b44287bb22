"""Does an off-centre car choose its lane change late on the expert's own states too? (issue 88,
item 3)

``lab/own_states.py`` found the start networks' late lane changes, on the states they drive into,
mostly in approaches first seen with the car 0.2 m or more off its lane's centre (a declared test
on fresh roads). Is that the offset itself, which the network would read late on any state, or
what the network's own drive brings with it? This reads the start networks (GMM + affordance +
CVaR, chapter 10's seeds) on chapter 04's validation frames, the expert's states: every frame
with a parked car 45-80 m ahead in the car's lane (the true gap, as ``lab/trigger_gap.py``) whose
label changes lanes (its 1.5 s point more than ``CHANGING_M`` from the lane's centre), but those
where the expert's overtake is already under way (moved ``CHANGE_START_M`` or more towards its
side): the frames where a plan has to choose the change. Per seed: the share whose followed plan
changes lanes too, for frames with the car 0.2 m or more off its lane's centre and within 0.2 m.

Declared before the run (the verdict the script prints):

* offset-sensitive on the expert's states: on every seed the off-centre share is at least 10
  points below the centred one;
* not on the expert's states: on every seed the off-centre share is no lower than the centred;
* mixed otherwise.

    python lab/offset_choice.py [--quick]

Writes docs/results/lab/offset_choice.json (full profile).
"""

from __future__ import annotations

import argparse

import numpy as np
from trigger_gap import approaches, choice_frames, write_result

from e2e_lite.config import FULL, QUICK
from e2e_lite.driving.witness import CHANGING_M
from e2e_lite.imitation import recipes
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.learning.dataset import CHANGE_START_M
from e2e_lite.learning.labels import AFFORDANCE_INDEX, CHANGE
from e2e_lite.simulation.world import WorldConfig

GAPS_M = (45.0, 80.0)  # the true gaps ahead read [m]
OFF_M = 0.2  # off centre: this far or farther from the lane's centre [m]
MARGIN_POINTS = 10.0  # how much lower the off-centre share must be on every seed [points]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    profile = QUICK if ap.parse_args().quick else FULL
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    world_cfg = WorldConfig.for_profile(profile)
    a = val.arrays
    offset = a["affordances"][:, AFFORDANCE_INDEX["center_offset_m"]]
    moved = offset * a["change_side"]  # towards the change's side [m]
    under_way = (a["expert_state"] == CHANGE) & a["overtaking"] & (moved >= CHANGE_START_M)
    v = choice_frames(val, world_cfg, "val", np.flatnonzero(~under_way))
    near = (v["gap"] >= GAPS_M[0]) & (v["gap"] < GAPS_M[1])
    label = np.abs(v["lane_offset"](val.trajectory[v["rows"]][:, -1])) > CHANGING_M
    take = near & label
    off = np.abs(offset[v["rows"]]) >= OFF_M
    groups = {"off centre": take & off, "centred": take & ~off}
    weight = recipes.affordance_weight(profile, train, val)
    out: dict = {"gaps_m": GAPS_M, "off_m": OFF_M, "groups": {}, "seeds": {}}
    for name, m in groups.items():
        out["groups"][name] = {"frames": int(m.sum()), "approaches": approaches(v, m)}
        print(f"{name}: {int(m.sum())} frames from {approaches(v, m)} approaches")
    for k in range(profile.ablation_seeds):
        agent = TrajectoryAgent(recipes.gmm_affordance_cvar(profile, train, val, weight, k)[0])
        plan = np.zeros(len(v["rows"]), bool)
        idx = np.flatnonzero(take)
        for c in np.array_split(idx, max(1, len(idx) // 256)):
            if len(c):
                rows = v["rows"][c]
                ends = agent.trajectories_from(val.images[rows], val.speed[rows])[:, -1]
                plan[c] = np.abs(v["lane_offset"](ends, c)) > CHANGING_M
        shares = {n: 100 * float(plan[m].mean()) if m.any() else None for n, m in groups.items()}
        out["seeds"][k] = shares
        print(
            f"seed {k}: the plan changes with the label on "
            + ", ".join(f"{n} {_pct(x)}" for n, x in shares.items())
        )
    pairs = [(s["off centre"], s["centred"]) for s in out["seeds"].values()]
    if any(None in p for p in pairs):
        verdict = "no verdict: a group has no frame"
    elif all(c - o >= MARGIN_POINTS for o, c in pairs):
        verdict = "offset-sensitive on the expert's states: lower off centre on every seed"
    elif all(o >= c for o, c in pairs):
        verdict = "not on the expert's states: no lower off centre on any seed"
    else:
        verdict = "mixed: the seeds disagree"
    out["verdict"] = verdict
    print(f"verdict (declared): {verdict}")
    write_result(out, "offset_choice.json", profile)


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f} %"


if __name__ == "__main__":
    main()
