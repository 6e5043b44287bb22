"""Why L2 passes chapter 07's overtake scenes (issue 64): where L2's and the GMM's predicted end
points fall as the parked car nears, which side each driver and the expert pass on, and the
expert's side shares in training samples of the same situation.

    python lab/l2_scenes.py [--quick]

Writes docs/results/lab/l2_scenes.json (full profile) and outputs/figures/lab_l2_scenes.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from e2e_lite import artifacts
from e2e_lite.config import FULL, QUICK
from e2e_lite.control.expert import Expert
from e2e_lite.driving.figures import save_figure
from e2e_lite.imitation import recipes
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.learning.labels import AFFORDANCE_INDEX, GAP_CAP_M
from e2e_lite.simulation.scenarios import START_S_M, ScenarioConfig, overtake_scenes, run_scenarios
from e2e_lite.simulation.world import WorldConfig

DISTANCES_M = (90.0, 70.0, 55.0, 45.0, 35.0, 25.0)  # rear axle to the parked car's centre [m]
SIDE_M = 1.0  # an end point more than this left (right) of the lane centre goes left (right) [m]


class Recorder:
    """Wraps a trajectory agent: after each decision keeps every car's (s, d, end point's y)."""

    def __init__(self, agent: TrajectoryAgent) -> None:
        self.agent, self.rows = agent, []

    def __getattr__(self, name: str):
        return getattr(self.agent, name)

    def reset(self, n: int) -> None:
        self.agent.reset(n)
        self.rows.append([])  # one list per batch of scenes

    def act(self, obs):
        act = self.agent.act(obs)
        end_y = np.asarray(self.agent.last["points"])[:, -1, 1]  # (B,) [m], car frame, left +
        self.rows[-1].append((obs.s.copy(), obs.d.copy(), end_y))
        return act


def side(y: float) -> str:
    return "left" if y > SIDE_M else "right" if y < -SIDE_M else "ahead"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument(
        "--offset", type=float, default=None,
        help="the scenes' lateral jitter [m] (default: chapter 07's); 0: every car on the centre",
    )  # fmt: skip
    args = parser.parse_args()
    profile = QUICK if args.quick else FULL
    world_cfg = WorldConfig.for_profile(profile)
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    nets = {
        "L2": recipes.trajectory_l2(profile, train, val)[0],
        "GMM": recipes.gmm(profile, train, val)[0],
    }
    cfg = ScenarioConfig(n_scenes=8 if profile.quick else 200)
    if args.offset is not None:
        cfg = dataclasses.replace(cfg, offset_m=args.offset)
    scenes = overtake_scenes(cfg)
    mid = 0.0  # the middle lane's centre (of three) is the road's centre line, d = 0
    out: dict = {"profile": profile.name, "scenes": len(scenes), "drivers": {}}
    passed_side = {}
    for name in ("expert", *nets):
        policy = Expert() if name == "expert" else Recorder(TrajectoryAgent(nets[name]))
        result = run_scenarios(policy, cfg, world_cfg, desc=name, progress=False)
        sides = []
        for path, sc in zip(result.paths, scenes):
            car_s = START_S_M + sc.ahead_m
            at = np.argmin(np.abs(path[:, 0] - car_s)) if path[-1, 0] >= car_s - 5 else -1
            sides.append(side(path[at, 1] - mid))
        passed_side[name] = sides
        entry = {"outcomes": {o: result.count(o) for o in ("passed", "collided", "stuck")},
                 "sides": {s: sides.count(s) for s in ("left", "right", "ahead")}}  # fmt: skip
        if name != "expert":
            # end point per scene at each distance: the first decision at or inside it
            ends = np.full((len(scenes), len(DISTANCES_M)), np.nan)
            for b, batch in enumerate(policy.rows):
                for k in range(len(batch[0][0])):
                    i = b * cfg.batch + k
                    car_s = START_S_M + scenes[i].ahead_m
                    dist = np.array([car_s - s[k] for s, _, _ in batch])
                    for j, dmax in enumerate(DISTANCES_M):
                        hit = np.flatnonzero(dist <= dmax)
                        if len(hit):
                            ends[i, j] = batch[hit[0]][2][k] + batch[hit[0]][1][k] - mid
            entry["end_y_m"] = {
                f"{d:g} m": {"median": float(np.nanmedian(ends[:, j])),
                             "abs_median": float(np.nanmedian(np.abs(ends[:, j]))),
                             "within_1m": float(np.nanmean(np.abs(ends[:, j]) <= SIDE_M)),
                             "left": float(np.nanmean(ends[:, j] > SIDE_M))}
                for j, d in enumerate(DISTANCES_M)
            }  # fmt: skip
            entry["agrees_with_expert"] = float(
                np.mean([a == b for a, b in zip(sides, passed_side["expert"])])
            )
            out.setdefault("_ends", {})[name] = ends
        out["drivers"][name] = entry
        print(name, json.dumps(entry))
    # the expert's labels in the same situation in the training data: the middle of three lanes,
    # a straight road, about cruise speed, a car ahead in the ego lane, both neighbours free
    a = train.arrays
    aff = a["affordances"]
    gap, left, right = (
        aff[:, AFFORDANCE_INDEX[g]] for g in ("gap_ego_m", "gap_left_m", "gap_right_m")
    )
    near = (
        (a["lane"] == world_cfg.road.n_lanes // 2)
        & (np.abs(a["curvature"]) < 1e-3)
        & (np.abs(a["speed"] - 25.0) < 2.0)
        & (left >= GAP_CAP_M - 1e-3)
        & (right >= GAP_CAP_M - 1e-3)
    )
    end_y = a["trajectory"][:, -1, 1] + a["d"]  # the label's end point from the lane's centre
    data = {}
    for lo, hi in ((0, 15), (15, 25), (25, 35), (35, 45), (45, 59.9), (59.9, 61)):
        m = near & (gap >= lo) & (gap < hi)
        ys = end_y[m]
        data[f"gap {lo:g}-{hi:g} m"] = {"samples": int(m.sum()),
                                         **{s: float(np.mean([side(y) == s for y in ys])) if len(ys) else None
                                            for s in ("left", "right", "ahead")}}  # fmt: skip
    out["training_labels"] = data
    # per scene: its jitter and the side each driver passed on (does a side follow a cue?)
    out["per_scene"] = [
        {"ahead_m": round(sc.ahead_m, 2), "offset_m": round(sc.offset_m, 3),
         "speed_mps": round(sc.speed_mps, 2), **{n: passed_side[n][i] for n in passed_side}}
        for i, sc in enumerate(scenes)
    ]  # fmt: skip
    for name in nets:
        for cue in ("offset_m", "ahead_m", "speed_mps"):
            x = np.array([r[cue] for r in out["per_scene"]])
            left = np.array([r[name] == "left" for r in out["per_scene"]])
            if left.all() or not left.any():
                continue
            print(
                f"{name}: scenes passed left have {cue} {x[left].mean():.3f}, right {x[~left].mean():.3f}"
            )
    print(json.dumps(data, indent=1))
    ends = out.pop("_ends")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.4), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    for ax, (name, e) in zip(axes, ends.items()):
        colors = [
            "C0" if s == "left" else "C3" if s == "right" else "0.5" for s in passed_side["expert"]
        ]
        for i in range(len(e)):
            ax.plot(DISTANCES_M, e[i], color=colors[i], alpha=0.25, lw=0.8)
        ax.axhspan(-SIDE_M, SIDE_M, color="0.9")
        ax.invert_xaxis()
        ax.set_title(f"{name}: predicted end point per scene", fontsize=10)
        ax.set_xlabel("distance to the parked car [m]")
    axes[0].set_ylabel("end point's lateral offset [m] (left +)\ncolour: the expert's side")
    tag = "" if args.offset is None else f"_offset_{args.offset:g}"
    png = save_figure(fig, artifacts.artifact_path("figures", f"lab_l2_scenes{tag}.png"))
    print(f"saved {png}")
    if not profile.quick:
        tag = "" if args.offset is None else f"_offset_{args.offset:g}"
        path = (
            Path(__file__).resolve().parents[1]
            / "docs"
            / "results"
            / "lab"
            / f"l2_scenes{tag}.json"
        )
        path.write_text(json.dumps(out, indent=1))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
