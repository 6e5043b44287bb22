"""Does the fine-tunes' drift off the lane centre come with the state expert's home lane? Chapter
12's arm with no new data fine-tunes each seed's CVaR network, round after round, on chapter 04's
data relabelled by the state expert, and its iterates drift off the lane centre (lab note "The
lingering comes with the state expert's labels"); most of the states where that labeller and the
course's expert part are the expert keeping to a side lane, where the state expert heads for the
middle lane, its home (lab note "The two experts part over the home lane"). This script runs the
same fine-tunes twice, differing in one thing, the labeller's home lane: ``middle`` (the course's)
and ``own`` (the lane it is in: it never returns), and drives every iterate on the seed's own
validation roads (the roads chapter 12's iterates drive), with each labeller followed by the
tracker as a check that both drive.

    E2E_LITE_OUTPUTS=<outputs holding chapter 09/10's CVaR networks> python lab/home_lane.py \\
        [--rounds 2] [--weight 3] [--workers 16] [--out FILE]

Both arms start from the same stored networks (``09_gmm_affordance_cvar`` and chapter 10's
seeds, read as stored: they may have been trained on another machine); the own-home datasets are
stored as ``<split>-<n>-home-own`` beside chapter 04's, the drives as ``lab12_home_...`` (the
fine-tunes are not stored). ``--weight``: chapter 08's chosen affordance weight (read from
its stored grid when not given). Declared before the run: one paired sign-flip test over the
seeds, the off-centre episodes of the middle-home arm's last iterate against the own-home arm's
(more with the middle home). Off-centre episodes: the autonomy metric's interventions that were
not collisions (:attr:`~e2e_lite.driving.metrics.EvalResult.off_centre`).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import torch

from e2e_lite.artifacts import artifact_path
from e2e_lite.config import FULL, QUICK, Profile
from e2e_lite.control.oracle import Oracle
from e2e_lite.control.state_expert import StateExpert
from e2e_lite.driving.evaluation import evaluate
from e2e_lite.imitation import dagger, recipes
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.imitation.collector import DataConfig, collect, load_or_collect
from e2e_lite.learning.checkpoints import load_checkpoint
from e2e_lite.learning.dataset import DrivingData, DrivingDataset, relabelled
from e2e_lite.learning.models import DrivingModel, pick_device
from e2e_lite.learning.training import fit
from e2e_lite.record.stored import evaluate_stored
from e2e_lite.simulation.world import WorldConfig
from e2e_lite.stats.seeds import sign_flip_test

OUT = Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "home_lane.json"
HOMES = StateExpert.HOMES  # ("middle", "own"): the course's first


def data(profile: Profile, split: str, home: str, workers: int | None, store: bool) -> DrivingData:
    """Chapter 04's ``split`` with the state expert of ``home`` beside the expert's labels (the
    middle home's is chapter 04's own file; the other is stored beside it), collected on
    ``workers`` processes when it is not stored; ``store=False``: neither read nor written."""
    cfg = DataConfig.for_profile(profile, split, home_lane=home)
    if not store:
        return collect(cfg, workers=workers)
    return load_or_collect(cfg, workers=workers)


def drive(name: str, model: DrivingModel, profile: Profile, seed: int, miles: float) -> dict:
    """``model``'s drive of training seed ``seed``'s validation roads: off-centre episodes and
    collisions (counts), miles [mi]."""
    res = evaluate_stored(
        f"{name}_val",
        f"{name} on validation roads",
        TrajectoryAgent(model),
        WorldConfig.for_profile(profile),
        dagger.val_run(profile, seed, miles),
    )
    return res.brief()


def start(seed: int) -> tuple[DrivingModel, dict[str, Any]]:
    """Training seed ``seed``'s CVaR network as stored (chapter 09's for seed 0, chapter 10's for
    the others) and its checkpoint's metadata (its kept Adam state among them)."""
    name = recipes.seeded_name("09_gmm_affordance_cvar", seed)
    return load_checkpoint(artifact_path("checkpoints", f"{name}.pt"), device=pick_device())


def arm(
    profile: Profile,
    home: str,
    old: DrivingData,
    val: DrivingData,
    seed: int,
    rounds: int,
    weight: float,
) -> list[dict]:
    """The arm with no new data on chapter 04's data ``old`` and ``val`` relabelled by the state
    expert of ``home``: each round fine-tunes the last
    iterate on rows drawn from chapter 04's relabelled data as :func:`~e2e_lite.imitation.dagger.
    run` does (one epoch, its Adam state carried on), then drives; the drives of iterates 1 ..
    ``rounds``. Trained as :func:`~e2e_lite.learning.checkpoints.train_or_load` trains a
    fine-tune, keeping the start network's normalisation, but neither stored nor checked against
    the data's statistics (data collected on another machine may differ in the last digits)."""
    cfg = dagger.DaggerConfig.for_profile(profile)
    objective, tcfg = recipes.finetune_settings(profile, weight, seed, "mean")
    model, meta = start(seed)
    state = meta["optimizer"]
    if state is None:  # (as train_or_load refuses: a fresh Adam would be another fine-tune)
        raise SystemExit(f"the start network of seed {seed} kept no Adam state to carry on")
    drives = []
    for r in range(rounds):
        name = f"lab12_home_{home}_round{r + 1}_seed{seed}"
        rows = dagger.aggregate_draw([old], cfg.steps_samples, seed, r)
        torch.manual_seed(tcfg.seed)
        history = fit(
            model,
            objective,
            DrivingDataset(rows),
            DrivingDataset(val),
            tcfg,
            name=name,
            optimizer_state=state,
        )
        model.eval()
        state = history.optimizer_state
        drives.append(drive(name, model, profile, seed, cfg.val_miles))
    return drives


def labellers(profile: Profile, miles: float) -> dict[str, dict[str, float]]:
    """Each home's state expert followed by the tracker on chapter 12's section-2 roads:
    collisions and off-centre episodes (counts), miles [mi]."""
    world = WorldConfig.for_profile(profile)
    out = {}
    for home in HOMES:
        res = evaluate(
            Oracle(StateExpert(sim=world.sim, home=home)), world, dagger.val_roads(miles, 32)
        )
        out[home] = res.brief()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=4, help="training seeds 0 .. N-1")
    ap.add_argument("--rounds", type=int, default=2, help="fine-tunes per arm and seed")
    ap.add_argument("--weight", type=float, default=None, help="chapter 08's affordance weight")
    ap.add_argument("--workers", type=int, default=None, help="collection processes")
    ap.add_argument("--miles", type=float, default=20.0, help="each labeller's check drive [mi]")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--no-store", action="store_true", help="collect the data, store none of it")
    ap.add_argument("--quick", action="store_true", help="the quick profile (tests the script)")
    args = ap.parse_args()
    profile = QUICK if args.quick else FULL
    t0 = time.perf_counter()
    result: dict[str, Any] = {
        "profile": profile.name,
        "machine": f"{platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{'cuda ' + torch.cuda.get_device_name() if torch.cuda.is_available() else 'cpu'}",
        "labellers_driven": labellers(profile, args.miles),
    }
    print(result, flush=True)
    sets = {
        home: [
            data(profile, split, home, args.workers, not args.no_store)
            for split in ("train", "val")
        ]
        for home in HOMES
    }
    weight = args.weight
    if weight is None:
        weight = recipes.affordance_weight(profile, *sets["middle"])
    relabel = {home: [relabelled(d) for d in pair] for home, pair in sets.items()}
    print(f"data ready, {time.perf_counter() - t0:.0f} s", flush=True)
    off: dict[str, list[list[int]]] = {h: [] for h in HOMES}
    collisions: dict[str, list[list[int]]] = {h: [] for h in HOMES}
    cfg = dagger.DaggerConfig.for_profile(profile)
    for k in range(args.seeds):
        first = drive(
            recipes.seeded_name("09_gmm_affordance_cvar", k), start(k)[0], profile, k, cfg.val_miles
        )
        for home in HOMES:
            drives = [first, *arm(profile, home, *relabel[home], k, args.rounds, weight)]
            off[home].append([d["off_centre"] for d in drives])
            collisions[home].append([d["collisions"] for d in drives])
            print(
                f"seed {k}, home {home}: off-centre by iterate (0: the start) {off[home][-1]}"
                f" ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
        result.update(off_centre_by_iterate=off, collisions_by_iterate=collisions)
        args.out.write_text(json.dumps(result, indent=1) + "\n")  # (each seed, as it lands)
    last = {h: [per[-1] for per in off[h]] for h in HOMES}
    test = sign_flip_test(last["middle"], last["own"])
    result.update(
        config={
            "rounds": args.rounds,
            "steps_samples": cfg.steps_samples,
            "val_miles": cfg.val_miles,
            "weight": weight,
        },
        declared_test="paired sign-flip, last iterate's off-centre episodes: middle home vs own",
        p_more_with_middle_home=test.p_more,
        min_p=test.min_p,
        wall_s=round(time.perf_counter() - t0, 1),
    )
    print(json.dumps(result, indent=1))
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
