"""Do networks learn the state expert as well as the course's expert? The same recipe (chapter
07's GMM), the same training seeds and the same validation roads, on chapter 04's data labelled
(and driven) by the state expert, whose plan is read off the state (`control/state_expert.py`;
the course's expert at 21afcad, so ``--labeller expert`` here), or by the course's expert, which
carries its plan (`control/expert.py`; ``--labeller remembering``, its name at 21afcad). Each
labeller's run keeps its own outputs folder (chapter 04's data and the GMMs are stored there and
reused, so a cut run goes on where it stopped); `--compare` reads both and tests them with the
training seed as the unit: a rank test, declared before the runs, the state expert's seeds
against the course's expert's.

    python lab/labels_learned.py --labeller expert --outputs DIR_A
    python lab/labels_learned.py --labeller remembering --outputs DIR_B
    python lab/labels_learned.py --compare DIR_A DIR_B

Writes ``labels_learned.json`` in each outputs folder and, with ``--compare``,
docs/results/lab/labels_learned.json (lab note "Do networks learn the labeller?"), whose keys keep
21afcad's names: "course's expert" is the state expert, "first expert" the one that carries its
plan.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
from pathlib import Path

OUT = Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "labels_learned.json"


def run(labeller: str, outputs: Path, seeds: int, miles: float, quick: bool) -> None:
    os.environ["E2E_LITE_OUTPUTS"] = str(outputs)
    from e2e_lite.config import FULL, QUICK
    from e2e_lite.driving.evaluation import EvalConfig
    from e2e_lite.imitation import collector, recipes
    from e2e_lite.imitation.agents import TrajectoryAgent
    from e2e_lite.record import ablation
    from e2e_lite.simulation.world import WorldConfig

    profile = QUICK if quick else FULL
    driver = "state" if labeller == "expert" else "expert"  # (the names of 21afcad, see above)
    train = collector.load_or_collect(
        collector.DataConfig.for_profile(profile, "train", driver=driver)
    )
    val = collector.load_or_collect(collector.DataConfig.for_profile(profile, "val", driver=driver))
    models = [
        recipes.gmm(profile, train, val, seed=k, name=recipes.seeded_name("07_gmm", k))[0]
        for k in range(seeds)
    ]
    world_cfg = WorldConfig.for_profile(profile)
    ev = EvalConfig(miles=miles * seeds, n_worlds=profile.ablation_worlds, split="val")
    drivers = {f"labels_{labeller}_gmm": [TrajectoryAgent(m) for m in models]}
    found = ablation.evaluate_drivers(drivers, world_cfg, ev)[next(iter(drivers))]
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    found = {
        **found.to_dict(with_events=False),
        "events": None,
        "labeller": labeller,
        "commit": commit.stdout.strip(),
    }
    found["train_data"] = {k: v for k, v in train.info.items() if k != "key"}
    (outputs / ("quick" if quick else "") / "labels_learned.json").write_text(
        json.dumps(found, indent=1, default=str) + "\n"
    )
    print(
        f"{labeller}: {found['collisions_per_100mi']:.1f} per 100 mi over {found['miles']:.0f} mi"
    )


def compare(a: Path, b: Path) -> None:
    from dataclasses import asdict

    from e2e_lite.driving.metrics import EvalResult
    from e2e_lite.record import words
    from e2e_lite.stats.seeds import compare_seeds

    course, first = (json.loads((p / "labels_learned.json").read_text()) for p in (a, b))
    test = compare_seeds(EvalResult.from_dict(course), EvalResult.from_dict(first))
    said = words.seeds(test)
    out = {
        "course's expert": course,
        "first expert": first,
        "test": {**asdict(test), "verdict": said},
    }
    OUT.write_text(json.dumps(out, indent=1, default=str) + "\n")
    print(said)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--labeller", choices=("expert", "remembering"))
    parser.add_argument("--outputs", type=Path)
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("COURSE", "FIRST"))
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--miles", type=float, default=100.0, help="per seed")
    parser.add_argument("--quick", action="store_true", help="a smoke test of the script")
    args = parser.parse_args()
    if args.compare:
        compare(*args.compare)
    elif args.labeller and args.outputs:
        run(args.labeller, args.outputs, args.seeds, args.miles, args.quick)
    else:
        parser.error("give --labeller and --outputs, or --compare")


if __name__ == "__main__":
    main()
