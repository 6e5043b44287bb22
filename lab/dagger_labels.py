"""Who should label DAgger's states (chapter 12): the collector's expert, whose plans remember
where it meant the car to be, or an expert planning afresh at every state? Runs the DAgger arm
with fresh labels for chapter 12's seeds and drives each round on chapter 12's validation roads
(the expert-labelled rounds' drives are chapter 12's, reused), and counts how often each
variant's labels ask for more than 1.5 m of sideways motion at 1.5 s.

    python lab/dagger_labels.py [--quick]      (after chapter 12; writes docs/results/lab/)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from dagger_setup import setup

from e2e_lite import ablation
from e2e_lite.driving.evaluation import seed_counts
from e2e_lite.learning import dagger
from e2e_lite.learning.agents import TrajectoryAgent


def main() -> None:
    profile, world_cfg, train, val, weight, seeds = setup(__doc__)
    on_val = dagger.val_roads(profile.eval_miles, profile.ablation_worlds)
    out = {"profile": profile.name, "variants": {}}
    for labels in dagger.LABELS:
        cfg = dagger.DaggerConfig.for_profile(profile, labels=labels)
        runs = {k: dagger.run(profile, train, val, weight, k, cfg, arms=("dagger",)) for k in seeds}
        variant = {}
        for j in range(cfg.rounds):
            models = [arms["dagger"][j].model for _, arms in runs.values()]
            key = f"12_dagger_round_{j + 1}" + ("" if labels == "expert" else "_fresh")
            res = ablation.evaluate_drivers(
                {key: [TrajectoryAgent(m) for m in models]}, world_cfg, on_val
            )[key]
            counts, budget = seed_counts(res)
            swerve = []
            for k in seeds:  # the learner of round j is the start, or round j - 1's network
                learner = runs[k][0] if j == 0 else runs[k][1]["dagger"][j - 1].model
                spec = dagger.RoundSpec(profile, cfg, k, j, "dagger")
                ends_y = spec.samples(learner, progress=False).arrays["trajectory"][:, -1, 1]
                swerve.append(float(np.mean(np.abs(ends_y) > 1.5)))
            variant[f"round {j + 1}"] = {
                "validation per seed, per 100 mi": (100.0 * counts / budget).tolist(),
                "labels over 1.5 m sideways": swerve,
                "visited outside the data": [arms["dagger"][j].shift["any"] for _, arms in runs.values()],
            }  # fmt: skip
            print(labels, j + 1, json.dumps(variant[f"round {j + 1}"]))
        out["variants"][labels] = variant
    if not profile.quick:
        path = (
            Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "dagger_labels.json"
        )
        path.write_text(json.dumps(out, indent=1))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
