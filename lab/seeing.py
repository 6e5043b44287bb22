"""Does the course's last driver see the parked car it overtakes late? (issue 88, item 3)

Chapter 12's start networks (GMM + affordance + CVaR, chapter 10's seeds) read every validation
frame with a parked car ahead in the car's lane. Per bin of the true gap ahead and per lane:
how often the affordance head reads the gap right (``anatomy.reads_right``: only below 50 m,
where a reading of a free lane, the 60 m cap, would not pass too), how often it reads a free
lane (at least 55 m where the car is nearer), and, on the frames where the expert changes lanes,
how often the network's followed plan changes with it (its 1.5 s point within 1 m of the
label's, sideways, in the car's frame: both plans are in it). A measurement, not a choice: it
says where the late lane change starts, seeing or deciding, over thousands of frames rather
than a run's few collisions.

    python lab/seeing.py [--quick]

Writes docs/results/lab/seeing.json (full profile).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from e2e_lite import artifacts
from e2e_lite.config import FULL, QUICK
from e2e_lite.driving.anatomy import READ_TOLERANCE, reads_right
from e2e_lite.imitation import recipes
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.learning.labels import AFFORDANCE_INDEX, CHANGE, GAP_CAP_M

BINS_M = (0.0, 15.0, 30.0, 45.0, 50.0, GAP_CAP_M)  # bins of the true gap ahead [m]
FREE_M = 55.0  # a reading at least this is a free lane [m]
WITH_M = 1.0  # a plan changes with the expert when its 1.5 s point is this near the label's [m]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    profile = QUICK if ap.parse_args().quick else FULL
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    weight = recipes.affordance_weight(profile, train, val)
    gap_i = AFFORDANCE_INDEX["gap_ego_m"]
    true_gap = val.affordances[:, gap_i].astype(np.float64)
    rows = np.flatnonzero(true_gap < GAP_CAP_M)
    lane, state = val.arrays["lane"][rows], val.arrays["expert_state"][rows]
    label_y = val.arrays["trajectory"][rows][:, -1, 1].astype(np.float64)
    gap = true_gap[rows]
    if not len(rows):
        print("no validation frame has a parked car ahead within the head's range")
        return
    metres = READ_TOLERANCE[0]
    out = {"frames_with_a_car_ahead": len(rows), "frames": len(val), "seeds": {}}
    for k in range(profile.ablation_seeds):
        net = recipes.gmm_affordance_cvar(profile, train, val, weight, k)[0]
        agent = TrajectoryAgent(net)
        read, end_y = [], []
        for c in np.array_split(rows, max(1, len(rows) // 256)):
            if not len(c):
                continue
            pts = agent.trajectories_from(val.images[c], val.speed[c])
            read.append(agent.last["affordances"][:, gap_i])
            end_y.append(pts[:, -1, 1])
        read, end_y = np.concatenate(read), np.concatenate(end_y)
        right, scored = reads_right(read, gap)
        free = (read >= FREE_M) & (gap < FREE_M - metres)
        changing = state == CHANGE
        took = np.abs(end_y - label_y) <= WITH_M
        table = []
        for lo, hi in itertools.pairwise(BINS_M):
            for ln in [*sorted(set(lane.tolist())), None]:
                m = (gap >= lo) & (gap < hi) & ((lane == ln) if ln is not None else True)
                ch, sc = m & changing, m & scored
                table.append(
                    {
                        "gap_m": [lo, hi],
                        "lane": "all" if ln is None else int(ln),
                        "frames": int(m.sum()),
                        "read_right": float(right[sc].mean()) if sc.any() else None,
                        "read_free": float(free[m].mean()) if m.any() else None,
                        "median_error_m": float(np.median(np.abs(read - gap)[m]))
                        if m.any()
                        else None,
                        "expert_changing": float(changing[m].mean()) if m.any() else None,
                        "plan_with_expert_change": float(took[ch].mean()) if ch.any() else None,
                    }
                )
        out["seeds"][k] = table
        print(f"seed {k}")
        for r in table:
            if r["frames"]:
                with_it, right = r["plan_with_expert_change"], r["read_right"]
                print(
                    f"  gap {r['gap_m'][0]:4.0f}-{r['gap_m'][1]:2.0f} m lane {r['lane']!s:3s}: "
                    f"{r['frames']:5d} frames, read right {'-' if right is None else f'{right:.2f}'}, read free "
                    f"{r['read_free']:.2f}, median error {r['median_error_m']:5.1f} m; expert "
                    f"changing {r['expert_changing']:.2f}, the plan with it "
                    f"{'-' if with_it is None else f'{with_it:.2f}'}"
                )
    out["commit"] = artifacts.code_commit(Path(__file__).parent)
    if not profile.quick:
        path = Path(__file__).resolve().parents[1] / "docs/results/lab/seeing.json"
        path.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
