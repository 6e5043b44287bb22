"""Every epoch of the course's GMM, driven: is the seeds' spread the kept epoch's, or the
learned sigma's? (issue 50, item 3; the lab note "Every epoch on the road" cites its output)

    python lab/epochs_on_the_road.py [--quick] [--seeds 5] [--val-miles 20] [--test-miles 50]
                                     [--jobs N] [--json PATH] [--recipe gmm|gmm_affordance]

Trains chapter 07's GMM (recipes.gmm, the course's settings) with its sigmas learned and with
them held at 1 (``sigma``), ``--seeds`` training seeds each, in a scratch outputs folder,
keeping each epoch's weights; then drives every epoch ``--val-miles`` on validation roads and
``--test-miles`` on test roads (64 cars, one shard, one torch thread, ``--jobs`` drives at a
time), and prints per epoch: the validation loss, the decisive ADE, whether the recipe kept it
(since f3ded4a by its own validation-road drive, before by the decisive ADE) and both roads'
collisions per 100 mi. Not a chapter: an investigation's script, kept so that
its lab note's numbers come from code in the repository. ``--recipe gmm_affordance``: chapter
08's network instead (its sigmas as the course holds them, at chapter 08's chosen weight).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any


def _drive(job: tuple) -> dict[str, Any]:
    """One epoch's drive on one split: ``(tag, model_cfg, state, split, miles, quick)``."""
    import torch

    from e2e_lite.config import FULL, QUICK
    from e2e_lite.driving.evaluation import evaluate
    from e2e_lite.driving.rollout import EvalConfig
    from e2e_lite.imitation.agents import TrajectoryAgent
    from e2e_lite.learning.models import build_model
    from e2e_lite.simulation.world import WorldConfig

    tag, model_cfg, state, split, miles, quick = job
    torch.set_num_threads(1)
    model = build_model(model_cfg)
    model.load_state_dict(state)
    model.eval()
    profile = QUICK if quick else FULL
    ev = EvalConfig(miles=miles, n_worlds=64, split=split)
    res = evaluate(TrajectoryAgent(model), WorldConfig.for_profile(profile), ev, progress=False)
    return {
        **tag,
        "split": split,
        "collisions": res.collisions,
        "rail": res.rail_collisions,
        "miles": res.miles,
        "per_100mi": res.collisions_per_100mi,
        "mph": res.mean_speed_mph,
        "stalls": res.stalls,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python lab/epochs_on_the_road.py")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--val-miles", type=float, default=20.0)
    parser.add_argument("--test-miles", type=float, default=50.0)
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--json", default=None, help="write the rows here")
    parser.add_argument("--data", default=None, help="outputs folder holding chapter 04's data")
    parser.add_argument("--recipe", choices=["gmm", "gmm_affordance"], default="gmm")
    parser.add_argument("--only-seeds", type=int, nargs="+", default=None, help="these seeds")
    parser.add_argument("--variants", nargs="+", choices=["learned", "held"], default=None)
    args = parser.parse_args(argv)

    scratch = tempfile.mkdtemp(prefix="epochs-on-the-road-")
    if args.data:  # reuse chapter 04's datasets: link them into the scratch folder
        sub = "quick" if args.quick else ""
        src = os.path.join(args.data, sub, "data")
        dst = os.path.join(scratch, sub, "data")
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        if os.path.isdir(src):
            os.symlink(os.path.abspath(src), dst)
    os.environ["E2E_LITE_OUTPUTS"] = scratch
    if args.quick:
        os.environ["E2E_LITE_QUICK"] = "1"

    from e2e_lite.config import FULL, QUICK
    from e2e_lite.imitation import recipes
    from e2e_lite.imitation.collector import DataConfig, load_or_collect

    profile = QUICK if args.quick else FULL
    t0 = time.perf_counter()
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    print(
        f"data: {len(train)} + {len(val)} samples in {time.perf_counter() - t0:.0f} s", flush=True
    )

    jobs, trainings = [], []
    affordance = args.recipe == "gmm_affordance"
    weight = recipes.affordance_weight(profile, train, val, progress=False) if affordance else 0.0
    variants = ("held",) if affordance else tuple(args.variants or ("learned", "held"))
    for variant in variants:
        for seed in args.only_seeds or range(args.seeds):
            states: list[dict] = []

            def keep(epoch: int, model: Any, states: list[dict] = states) -> None:
                states.append({k: v.detach().cpu().clone() for k, v in model.state_dict().items()})

            t1 = time.perf_counter()
            name = f"lab_{args.recipe}_{variant}_seed{seed}"
            if affordance:
                _, _, hist = recipes.gmm_affordance(
                    profile, train, val, weight, name=name, seed=seed, on_epoch=keep,
                    progress=False,
                )  # fmt: skip
                cfg = recipes.AFFORDANCE_CFG
            else:
                _, _, hist = recipes.gmm(
                    profile, train, val, seed=seed, name=name, sigma=variant, on_epoch=keep,
                    progress=False,
                )  # fmt: skip
                cfg = recipes.gmm_config()
            print(
                f"{variant} seed {seed}: trained in {time.perf_counter() - t1:.0f} s, "
                f"kept epoch {hist.best_epoch + 1}",
                flush=True,
            )
            for e, rec in enumerate(hist.epochs):
                tag = {
                    "variant": variant, "seed": seed, "epoch": e + 1,
                    "kept": e == hist.best_epoch, "sigma_frozen": bool(rec["frozen"]),
                    "val_loss": rec["val_loss"], "decisive_ade": rec.get("decisive ADE [m]"),
                    "ade": rec.get("ADE [m]"),
                }  # fmt: skip
                trainings.append(tag)
                state = states[e]  # (a copy already, on the CPU)
                jobs.append((tag, cfg, state, "val", args.val_miles, args.quick))
                jobs.append((tag, cfg, state, "test", args.test_miles, args.quick))
    t2 = time.perf_counter()
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        rows = list(pool.map(_drive, jobs))
    print(f"{len(jobs)} drives in {time.perf_counter() - t2:.0f} s", flush=True)

    by = {}
    for r in rows:
        by.setdefault((r["variant"], r["seed"], r["epoch"]), {})[r["split"]] = r
    print(
        "| sigma | seed | epoch | kept | sigma frozen | val loss | decisive ADE [m] "
        "| val roads /100mi | test roads /100mi (rail) | test mph |"
    )
    print("|---|---:|---:|---|---|---:|---:|---:|---:|---:|")
    for t in trainings:
        d = by[(t["variant"], t["seed"], t["epoch"])]
        v, s = d["val"], d["test"]
        print(
            f"| {t['variant']} | {t['seed']} | {t['epoch']} | {'kept' if t['kept'] else ''} | "
            f"{'yes' if t['sigma_frozen'] else ''} | {t['val_loss']:.3f} | "
            f"{t['decisive_ade'] or float('nan'):.3f} | {v['per_100mi']:.1f} | "
            f"{s['per_100mi']:.1f} ({s['rail']}) | {s['mph']:.1f} |"
        )
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "weight": weight, "trainings": trainings, "drives": rows}, f,
                  indent=1)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
