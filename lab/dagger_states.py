"""DAgger's states or its labeller? Chapter 12's DAgger rounds (the learner drives, a fresh
expert labels) drove worse than their start network, while their control (the collector's noisy
expert drives and labels) moved less. The two arms differ in whose states (the learner's, or the
noisy expert's) and in who labels them (an expert planning afresh at each state, or the
collector's expert, which remembers its plans). Two more arms separate them: the control's very
states labelled by the fresh expert (``control_labels="fresh"``), and the rounds at beta = 1 (the
noise-free expert drives every decision, the fresh expert labels). Every arm starts from chapter
09's CVaR network per seed and drives chapter 12's test roads (the same roads per seed in every
arm; the course's arms' drives are chapter 12's, reused).

    python lab/dagger_states.py [--quick]      (after chapter 12; writes docs/results/lab/)
"""

from __future__ import annotations

import json
from pathlib import Path

from dagger_setup import setup

from e2e_lite import ablation
from e2e_lite.driving.evaluation import EvalConfig, compare_seeds, seed_counts
from e2e_lite.learning import dagger
from e2e_lite.learning.agents import TrajectoryAgent


def main() -> None:
    profile, world_cfg, train, val, weight, seeds = setup(__doc__)
    course = dagger.DaggerConfig.for_profile(profile)
    expert_states = dagger.DaggerConfig.for_profile(profile, betas=(1.0,) * course.rounds)
    relabelled = dagger.DaggerConfig.for_profile(profile, control_labels="fresh")
    runs = {k: dagger.run(profile, train, val, weight, k, course) for k in seeds}
    beta1 = {k: dagger.run(profile, train, val, weight, k, expert_states, arms=("dagger",))
             for k in seeds}  # fmt: skip
    fresh = {k: dagger.run(profile, train, val, weight, k, relabelled, arms=("control",))
             for k in seeds}  # fmt: skip
    last = course.rounds - 1
    nets = {
        "gmm_affordance_cvar": [runs[k][0] for k in seeds],  # chapter 12's keys: its drives reused
        f"12_dagger_round_{last + 1}": [runs[k][1]["dagger"][last].model for k in seeds],
        f"12_control_round_{last + 1}": [runs[k][1]["control"][last].model for k in seeds],
        f"12_dagger_beta1_round_{last + 1}": [beta1[k][1]["dagger"][last].model for k in seeds],
        f"12_control_fresh_round_{last + 1}": [fresh[k][1]["control"][last].model for k in seeds],
    }
    ev = EvalConfig(miles=profile.ablation_miles, n_worlds=profile.ablation_worlds)
    drivers = {k: [TrajectoryAgent(m) for m in v] for k, v in nets.items()}
    test = dict(zip(("start", "dagger", "control", "beta 1", "control, fresh"), ablation.evaluate_drivers(
        drivers, world_cfg, ev).values()))  # fmt: skip
    out: dict = {"profile": profile.name, "test roads": {}, "paired": {}, "shift": {}}
    for name, res in test.items():
        counts, per_mi = seed_counts(res)
        out["test roads"][name] = {"collisions per seed": counts.tolist(), "miles per seed": per_mi}
        print(f"{name:8s} collisions per seed {counts.tolist()} in {per_mi:.3g} mi each")
    pairs = (("control, fresh", "control"), ("dagger", "control, fresh"), ("beta 1", "control, fresh"),
             ("dagger", "beta 1"), ("control, fresh", "start"))  # fmt: skip
    for a, b in pairs:
        v = compare_seeds(test[a], test[b], paired=True)
        out["paired"][f"{a} vs {b}"] = {k: v[k] for k in ("p_fewer", "p_more", "ratio", "verdict")}
        print(f"{a} vs {b}: {v['verdict']}")
    for name, rounds, arm in (("dagger", runs, "dagger"), ("control", runs, "control"),
                              ("beta 1", beta1, "dagger")):  # fmt: skip
        out["shift"][name] = [[r.shift["any"] for r in rounds[k][1][arm]] for k in seeds]
    print("visited outside the data, per seed and round:", json.dumps(out["shift"]))
    if not profile.quick:
        path = Path(__file__).resolve().parents[1] / "docs/results/lab/dagger_states.json"
        path.write_text(json.dumps(out, indent=1))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
