"""The numbers of record: every paper row, L2 and the two controls, each learned row trained with
several seeds, every seed driving its miles on the sealed block of test roads
(:data:`~e2e_lite.driving.roads.SEALED_BLOCK` of :data:`~e2e_lite.driving.roads.ROAD_BLOCKS`),
which nothing else drives (a quick smoke run of the record drives open roads).

``python -m e2e_lite.report --record`` runs :func:`record_table1`, writes
``docs/results/table1.json`` and renders it; it says first what it will use (workers, device,
precision) and how long it should take (:func:`~e2e_lite.estimate.estimate_s`, from the per-part
rates measured in docs/benchmarks.md). Trainings and drives are stored as the chapters store
theirs, so a cut run goes on where it stopped.
"""

from __future__ import annotations

import os
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from .ablation import (
    BY_KEY,
    CONTROLS,
    DRIVERS,
    PAPER_MPH,
    SEED_ZERO_ONLY,
    UNTRAINED,
    build_seeded_drivers,
    evaluate_drivers,
)
from .config import Profile, check_range, default_workers, precision
from .driving.metrics import result_dict
from .driving.roads import ROAD_BLOCKS, SEALED_BLOCK
from .driving.rollout import EvalConfig
from .estimate import Work, cpu_name, plan_text
from .learning.models import pick_device
from .record_tests import FAMILIES, STEPS
from .simulation.world import WorldConfig


def record_work(
    profile: Profile, seeds: int, miles_per_seed: float, single: Sequence[str] = SEED_ZERO_ONLY
) -> Work:
    """What :func:`record_table1` does from an empty outputs folder, in the parts the benchmarks
    measure: the data, chapter 08's weight grid (5 weights, 2 epochs, a quarter of the data),
    every training (from scratch: the profile's epochs and a selection drive per epoch; the two
    fine-tunes: one epoch; the rows of ``single``: seed 0 alone), and every row's drive."""
    from .learning.recipes import SELECT_MILES

    learned = [d.key for d in (*DRIVERS, *CONTROLS) if d.key not in UNTRAINED]
    tuned = sum(k in ("gmm_affordance_cvar", "gmm_affordance_control") for k in learned)
    trainings = sum(1 if k in single else seeds for k in learned)  # (no fine-tune is single)
    scratch = trainings - seeds * tuned
    epochs = profile.train_epochs
    return Work(
        collect_samples=profile.n_train_samples + profile.n_val_samples,
        train_samples=profile.n_train_samples * (scratch * epochs + seeds * tuned)
        + 5 * 2 * profile.n_train_samples / 4,
        drive_miles=scratch * epochs * SELECT_MILES
        + miles_per_seed * seeds * (len(learned) + len(UNTRAINED)),
    )


def record_table1(
    profile: Profile,
    seeds: int = 10,
    miles_per_seed: float = 100.0,
    *,
    single: Sequence[str] = SEED_ZERO_ONLY,
    progress: bool = True,
) -> dict[str, Any]:
    """Table 1 of record: every row of :data:`DRIVERS` and :data:`CONTROLS`, each learned row
    trained with ``seeds`` training seeds (those of ``single``: one), each seed driving
    ``miles_per_seed`` on test roads of its own inside the sealed block of test roads
    (:data:`~e2e_lite.driving.roads.SEALED_BLOCK`: no chapter, lab script, selection, benchmark
    or test drives it; the quick profile's smoke run drives open roads). The rows of ``single``
    (PilotNet and L2: no step of the paper's Table 1 is theirs) train seed 0 alone, which drives
    every seed's miles in one run; the verdicts' rows train every seed. Trainings and
    evaluations are stored, so a cut run goes on where it stopped. Returns the record
    :mod:`e2e_lite.report` renders (per row: each seed's collisions, miles, mph and stalls; the
    recipes' commit, the CPU, torch, the precision, the workers and the block).

    The default, 10 seeds x 100 mi, finds a true 2x step at 3 collisions per 100 mi about 90 %
    of the time (:func:`~e2e_lite.driving.verdicts.power`; 5 x 100 mi: about 60 %)."""
    check_range("record_table1", "seeds", seeds, 1, integer=True)
    check_range("record_table1", "miles_per_seed", miles_per_seed, 0.0, lo_open=True)
    # the code that trains and drives: the commit at the start (a run takes hours); every recipe
    # choice is frozen in it before the sealed roads are driven
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    # the family of tests, declared before anything is trained or driven (issue 64)
    family = {
        "families": FAMILIES,
        "tests": {st.what: st.family for st in STEPS},
        "adjustment": "holm",
        "declared": f"before this record ran, in the recipes of {commit}",
    }
    keys = [d.key for d in (*DRIVERS, *CONTROLS)]
    world_cfg = WorldConfig.for_profile(profile)
    # the sealed roads are for the record alone: a quick smoke run drives open roads
    block = "open" if profile.quick else SEALED_BLOCK
    ev = EvalConfig(miles=miles_per_seed * seeds, n_worlds=profile.ablation_worlds, block=block)
    workers, device = default_workers(), pick_device()
    if progress:
        work = record_work(profile, seeds, miles_per_seed, single)
        print(plan_text("the record", work, workers, device.type), flush=True)
    drivers = build_seeded_drivers(profile, keys, seeds=seeds, single=single, progress=progress)
    results = evaluate_drivers(drivers, world_cfg, ev, progress=progress)
    cpu = cpu_name()
    rows = []
    for key in keys:
        r = result_dict(results[key])
        parts = r.get("seeds") or [r]
        rows.append({
            "key": key,
            "label": BY_KEY[key].label,
            "paper_per_100mi": BY_KEY[key].paper_per_100mi,
            "seeds": [
                {"seed": k, "collisions": p["collisions"], "miles": round(p["miles"], 3),
                 "mph": round(p["mean_speed_mph"], 2), "stalls": p["stalls"]}
                for k, p in enumerate(parts)
            ],
            "car": r["car_collisions"],
            "rail": r["rail_collisions"],
            "mph": round(r["mean_speed_mph"], 2),
            "stalls": r["stalls"],
            "commit": commit,
            "control": key in {d.key for d in CONTROLS},
        })  # fmt: skip
    return {
        "title": f"Table 1 of record ({profile.name} profile, {seeds} training seeds)",
        "status": (
            f"Of record: {seeds} training seeds per learned row, {miles_per_seed:g} mi each"
            + (
                f" ({', '.join(single)}: seed 0 alone, {miles_per_seed * seeds:g} mi)"
                if single
                else ""
            )
        ),
        "machine": f"{cpu}, {os.cpu_count()} cores, {workers} workers, {device.type}",
        "torch": torch.__version__,
        "precision": precision(),
        "roads": ev.split,
        "block": {"name": ev.block, "range": list(ROAD_BLOCKS[ev.block]), "recipes_commit": commit},
        "commits": {commit: "every row"},
        "miles_note": "each seed drove its miles on test roads of its own (evaluation.disjoint_runs)",
        "single_seed_rows": list(single),
        "family": family,
        "paper_mph": PAPER_MPH,
        "rows": rows,
    }
