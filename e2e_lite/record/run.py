"""Running the record: one share of training seeds (:func:`record_share`), every row trained
and driven for them, each seed on its own run of the sealed block (:func:`seed_run`: the same
roads whatever share holds it); what a share costs (:func:`record_work`); and the plan, the seeds
and miles that reach the record's power (:func:`plan`). Trainings and drives are stored as the
chapters store theirs, so a cut run goes on where it stopped.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from ..artifacts import code_commit, profile_outputs, seeded, settings_key
from ..config import FULL, Profile, check_range, default_workers, precision
from ..course.estimate import Work, cpu_name, estimate_s, plan_text
from ..driving.roads import ROAD_BLOCKS
from ..driving.rollout import EvalConfig
from ..imitation.collector import DataConfig, load_or_collect
from ..imitation.dagger import DaggerConfig
from ..imitation.recipes import SELECT_MILES
from ..learning.models import pick_device
from ..simulation.world import WorldConfig
from ..stats.power import seeds_for_power
from .ablation import BEYOND, BY_KEY, CONTROLS, DRIVERS, UNTRAINED, build_drivers
from .pool import record_block, seed_run
from .rows import SHARE_FORMAT, Block, Record, SeedRun, Share, ShareRow
from .stats import POWER_ROW, family, median_rate, record_dispersion, record_power
from .stored import evaluate_stored

#: every row of the record: the paper's, DAgger's (chapter 12) and the controls
ROWS = (*DRIVERS, *BEYOND, *CONTROLS)
#: the first training seed no choice and no earlier record saw (0-3: the course's own networks;
#: 10-23, 24-37 and 38-57: the records of 321f6a9, 28eba5c and 7a36b30)
FRESH_SEEDS_FROM = 58
#: the rows a record drives with seed 0's network alone: none. Every learned row trains every
#: seed of the record on one machine, so no row pools networks trained on different machines
#: (the record of 28eba5c drove PilotNet and L2 with each machine's seed 0: ablation's
#: SEED_ZERO_ONLY, which chapter 10 still uses for its own run)
RECORD_SINGLE: tuple[str, ...] = ()


def record_work(
    profile: Profile, seeds: int, miles_per_seed: float, single: Sequence[str] = RECORD_SINGLE
) -> Work:
    """What a share of ``seeds`` seeds (:func:`record_share`) does from an empty outputs folder,
    in the parts the benchmarks measure: the data, chapter 08's weight grid (5 weights, 2 epochs,
    a quarter of the data), every training (from scratch: the profile's epochs and a selection
    drive per epoch; the two fine-tunes: one epoch; the rows of ``single``: seed 0 alone),
    DAgger's three arms (their drives, fine-tunes and every iterate's validation drive), and
    every seed's run of every row."""

    learned = [d.key for d in (*DRIVERS, *CONTROLS) if d.key not in UNTRAINED]
    tuned = sum(k in ("gmm_affordance_cvar", "gmm_affordance_control") for k in learned)
    trainings = sum(1 if k in single else seeds for k in learned)  # (no fine-tune is single)
    scratch = trainings - seeds * tuned
    epochs = profile.train_epochs
    dag = DaggerConfig.for_profile(profile)
    driven = seeds * dag.rounds * dag.samples * (2 * dag.drive + 0.25)  # two arms, DART's pilot
    iterates = seeds * (1 + len(BEYOND) * dag.rounds) * dag.val_miles
    return Work(
        collect_samples=profile.n_train_samples + profile.n_val_samples + driven,
        train_samples=profile.n_train_samples * (scratch * epochs + seeds * tuned)
        + 5 * 2 * profile.n_train_samples / 4
        + seeds * len(BEYOND) * dag.rounds * dag.steps_samples,
        drive_miles=scratch * epochs * SELECT_MILES + miles_per_seed * seeds * len(ROWS) + iterates,
    )


def parse_seeds(text: str) -> list[int]:
    """``"N"``: training seeds ``0 .. N-1`` (the whole record on one machine); ``"A-B"``: seeds
    ``A .. B`` (one share of it)."""
    try:
        if "-" in text:
            first, last = (int(x) for x in text.split("-"))
        else:
            first, last = 0, int(text) - 1
    except ValueError:
        raise ValueError(f"--seeds {text!r} is invalid: give N (seeds 0 .. N-1) or A-B") from None
    if first < 0 or last < first:
        raise ValueError(f"--seeds {text!r} is invalid: give N >= 1, or A-B with 0 <= A <= B")
    return list(range(first, last + 1))


def _commit() -> str:
    """The code that trains and drives: the commit at the start (a run takes hours); every recipe
    choice is frozen in it before the sealed roads are driven (:func:`~e2e_lite.artifacts.code_commit`
    of this package's checkout)."""
    return code_commit(Path(__file__).resolve().parent)


def record_share(
    profile: Profile,
    seeds: Sequence[int],
    miles_per_seed: float = 100.0,
    *,
    single: Sequence[str] = RECORD_SINGLE,
    progress: bool = True,
) -> Share:
    """One share of the record: every row of :data:`ROWS` (the paper's, DAgger's and the
    controls) for training ``seeds``, each seed driving ``miles_per_seed`` on its own run of the
    block (:func:`seed_run`; the sealed block of test roads, or open roads in the quick profile's
    smoke run), storing its networks and drives in the profile's outputs folder. Each learned row
    trains the share's seeds (:data:`RECORD_SINGLE`: every one); the rows of ``single``, if any,
    drive seed 0's network on each seed's run, as the expert and the oracle do. Returns the share,
    its digest written."""
    seeds = sorted(int(k) for k in seeds)
    if not seeds or seeds[0] < 0 or len(set(seeds)) != len(seeds):
        raise ValueError(f"record_share: seeds {seeds} must be distinct and >= 0")
    if not profile.quick and seeds[0] < FRESH_SEEDS_FROM:
        raise ValueError(
            f"record_share: seeds {seeds[0]}-{FRESH_SEEDS_FROM - 1} trained the course's networks "
            f"or an earlier record: a record of the fresh block takes seeds {FRESH_SEEDS_FROM} and up"
        )
    check_range("record_share", "miles_per_seed", miles_per_seed, 0.0, lo_open=True)
    commit, keys = _commit(), [d.key for d in ROWS]
    with profile_outputs(profile.quick):  # (also when called from Python, not the command)
        world_cfg = WorldConfig.for_profile(profile)
        workers, device = default_workers(), pick_device()
        if progress:
            work = record_work(profile, len(seeds), miles_per_seed, single)
            print(
                plan_text(f"the record's seeds {seeds[0]}-{seeds[-1]}", work, workers, device.type)
            )
        train = load_or_collect(DataConfig.for_profile(profile, "train"), progress)
        val = load_or_collect(DataConfig.for_profile(profile, "val"), progress)
        learned = [k for k in keys if k not in UNTRAINED and k not in single]
        fixed = build_drivers(profile, [k for k in keys if k not in learned], train, val, seed=0)
        runs: dict[str, list[SeedRun]] = {k: [] for k in keys}
        for seed in seeds:
            run = seed_run(profile, seed, miles_per_seed)
            mine = {**fixed, **build_drivers(profile, learned, train, val, seed=seed)}
            for key in keys:
                label = f"{BY_KEY[key].label} (seed {seed})"
                name = seeded(key, seed)
                result = evaluate_stored(name, label, mine[key], world_cfg, run, progress=progress)
                runs[key].append(SeedRun.of(result, seed, run.first_track))
    block = record_block(profile)
    template = EvalConfig(miles=miles_per_seed, n_worlds=profile.ablation_worlds, block=block)
    data_keys = (train.info["key"], val.info["key"])
    settings = settings_key(
        profile, world_cfg, template, *data_keys, precision(), keys, list(single)
    )
    controls = {d.key for d in CONTROLS}
    rows = tuple(
        ShareRow(k, BY_KEY[k].label, BY_KEY[k].paper_per_100mi, k in controls, tuple(runs[k]))
        for k in keys
    )
    return Share(
        format=SHARE_FORMAT,
        profile=profile.name,
        seeds=seeds,
        miles_per_seed=miles_per_seed,
        recipes_commit=commit,
        settings_key=settings,
        data=dict(zip(("train", "val"), data_keys)),
        precision=precision(),
        torch=torch.__version__,
        machine=f"{cpu_name()}, {os.cpu_count()} cores, {workers} workers, {device.type}",
        block=Block(block, list(ROAD_BLOCKS[block])),
        single_seed_rows=list(single),
        family=family(f"before this record ran, in the recipes of {commit}"),
        rows=rows,
    ).sealed()


def low_rate_row(record: Record) -> str:
    """The learned row of two or more seeds whose median seed collides least: the rows whose
    steps are the hardest to find (issue 88: the record's seeds are planned for them too)."""
    learned = [r for r in record.rows if r.key not in UNTRAINED and len(r.seeds) >= 2]
    return min(learned, key=median_rate).key


def plan(
    record: Record,
    target: float = 0.8,
    most: int = 30,
    miles_options: Sequence[float] = (100.0, 150.0, 200.0, 300.0),
    n_sim: int = 500,
    row: str | None = None,
) -> dict[str, Any]:
    """The record's plan: for each budget of miles per seed, the fewest training seeds
    (10 to ``most``) whose verdicts find a true 2x step at the record's own + affordance rate with
    at least ``target`` power under the seeds' spread fitted to ``record``
    (:func:`~e2e_lite.record.stats.record_power`), and what each plan costs on 2 cores and on a
    16-core machine with a GPU (:func:`record_work`); the chosen plan is the cheapest on 2 cores
    that reaches ``target`` (else the most powerful at ``most`` seeds). With ``row``, the step
    is at that row's median rate, under the spread fitted to the rows near it (a low-rate row's
    own, :func:`low_rate_row`)."""

    found = record_power(record)
    k, rate = found.dispersion.k, found.rate_per_100mi
    if row is not None:
        rate = max(median_rate(record.row(row)), 0.5)  # (a zero rate has no step)
        k = record_dispersion(record, near=row).k
    options = []
    for miles in miles_options:
        need = seeds_for_power(miles, rate, target, most=most, least=10, n_sim=n_sim, dispersion=k)
        work = record_work(FULL, need.seeds, miles)
        hours = {
            "hours_2_cores": estimate_s(work, 2) / 3600.0,
            "hours_16_cores_gpu": estimate_s(work, 16, "cuda") / 3600.0,
        }
        options.append({"seeds": need.seeds, "power": need.power, "miles_per_seed": miles, **hours})
    reaching = [o for o in options if o["power"] >= target]
    chosen = (
        min(reaching, key=lambda o: o["hours_2_cores"])
        if reaching
        else max(options, key=lambda o: o["power"])
    )
    return {
        "row": row or POWER_ROW,
        "dispersion": k,
        "rate_per_100mi": rate,
        "target": target,
        "options": options,
        "chosen": chosen,
    }


def plan_lines(found: dict[str, Any]) -> list[str]:
    """:func:`plan` as the lines ``python -m e2e_lite.record --plan`` prints."""
    lines = [
        f"{found['row']}: seeds' spread (dispersion) {found['dispersion']:.2f}; a 2x step at "
        f"{found['rate_per_100mi']:.1f} per 100 mi, power {found['target']:.0%}:"
    ]
    for o in found["options"]:
        lines.append(
            f"  {o['miles_per_seed']:5.0f} mi per seed: {o['seeds']:2d} seeds, power "
            f"{o['power']:.2f}, about {o['hours_2_cores']:.1f} h on 2 cores, "
            f"{o['hours_16_cores_gpu']:.1f} h on 16 cores and a GPU"
        )
    c = found["chosen"]
    lines.append(
        f"plan: {c['seeds']} seeds x {c['miles_per_seed']:.0f} mi (power {c['power']:.2f})"
    )
    return lines
