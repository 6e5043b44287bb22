"""The numbers of record: every paper row, L2 and the two controls, each learned row trained with
several seeds, every seed driving its miles on the sealed block of test roads
(:data:`~e2e_lite.driving.roads.SEALED_BLOCK` of :data:`~e2e_lite.driving.roads.ROAD_BLOCKS`),
which nothing else drives (a quick smoke run of the record drives open roads).

The record is a **pool of shares** (issue 65). ``python -m e2e_lite.report --record --seeds A-B``
runs :func:`record_share` for training seeds ``A .. B``: every row trained and driven for those
seeds, each seed on its own run of the block (:func:`seed_run`: the same roads whatever share holds
it), written as one share file with what a pool needs to check that it belongs (the recipes'
commit, a key of the settings, the profile, precision, torch, the machine, each seed's first
track, and a digest of its content). ``python -m e2e_lite.report --pool SHARE...`` merges shares
(:func:`pool_shares`, which refuses a share that does not belong, naming its file) into the record
that the report renders. A class, or a cluster's job array, runs one share each; one machine runs
them all (``--record --seeds N``: seeds ``0 .. N-1`` as one share, pooled).

Every run says first what it will use (workers, device, precision) and how long it should take
(:func:`~e2e_lite.estimate.estimate_s`). Trainings and drives are stored as the chapters store
theirs, so a cut run goes on where it stopped.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from .ablation import (
    BEYOND,
    BY_KEY,
    CONTROLS,
    DRIVERS,
    PAPER_MPH,
    SEED_ZERO_ONLY,
    UNTRAINED,
    build_drivers,
    evaluate_stored,
)
from .artifacts import settings_key
from .config import FULL, QUICK, Profile, check_range, default_workers, precision
from .driving.metrics import result_dict
from .driving.roads import ROAD_BLOCKS, SEALED_BLOCK
from .driving.rollout import EvalConfig, disjoint_runs
from .estimate import Work, cpu_name, plan_text
from .learning.data import DataConfig, load_or_collect
from .learning.models import pick_device
from .record_tests import family
from .simulation.world import WorldConfig

#: every row of the record: the paper's, DAgger's (chapter 12) and the controls
ROWS = (*DRIVERS, *BEYOND, *CONTROLS)


def record_work(
    profile: Profile, seeds: int, miles_per_seed: float, single: Sequence[str] = SEED_ZERO_ONLY
) -> Work:
    """What :func:`record_table1` does from an empty outputs folder, in the parts the benchmarks
    measure: the data, chapter 08's weight grid (5 weights, 2 epochs, a quarter of the data),
    every training (from scratch: the profile's epochs and a selection drive per epoch; the two
    fine-tunes: one epoch; the rows of ``single``: seed 0 alone), DAgger's rounds and their
    control (a collection and a fine-tune each), and every seed's run of every row."""
    from .learning.dagger import DaggerConfig
    from .learning.recipes import SELECT_MILES

    learned = [d.key for d in (*DRIVERS, *CONTROLS) if d.key not in UNTRAINED]
    tuned = sum(k in ("gmm_affordance_cvar", "gmm_affordance_control") for k in learned)
    trainings = sum(1 if k in single else seeds for k in learned)  # (no fine-tune is single)
    scratch = trainings - seeds * tuned
    epochs = profile.train_epochs
    rounds = DaggerConfig.for_profile(profile)
    dagger_samples = seeds * len(BEYOND) * rounds.rounds * rounds.samples  # collected
    return Work(
        collect_samples=profile.n_train_samples + profile.n_val_samples + dagger_samples,
        train_samples=profile.n_train_samples * (scratch * epochs + seeds * tuned)
        + 5 * 2 * profile.n_train_samples / 4
        + dagger_samples * (1.0 + rounds.replay),
        drive_miles=scratch * epochs * SELECT_MILES + miles_per_seed * seeds * len(ROWS),
    )


#: what a share file says it is
SHARE_FORMAT = "e2e-lite record share"


class ShareRefused(ValueError):
    """A share that does not belong in a pool (the message names its file and why)."""


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


def _block(profile: Profile) -> str:
    # the sealed roads are for the record alone: a quick smoke run drives open roads
    return "open" if profile.quick else SEALED_BLOCK


def seed_run(profile: Profile, seed: int, miles_per_seed: float) -> EvalConfig:
    """Training seed ``seed``'s own run of the record's block: ``miles_per_seed`` on tracks no
    other seed drives, the same whatever share (and whatever count of seeds) holds it (the run
    ``seed`` of :func:`~e2e_lite.driving.rollout.disjoint_runs`, whose runs do not depend on how
    many there are)."""
    ev = EvalConfig(
        miles=miles_per_seed * (seed + 1), n_worlds=profile.ablation_worlds, block=_block(profile)
    )
    return disjoint_runs(ev, WorldConfig.for_profile(profile), seed + 1)[seed]


def _commit() -> str:
    """The code that trains and drives: the commit at the start (a run takes hours); every recipe
    choice is frozen in it before the sealed roads are driven. A copy without git's history (a
    zip, a lent machine's copy of the tree) says its commit in ``$E2E_LITE_COMMIT``."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return os.environ.get("E2E_LITE_COMMIT", "unknown")


def share_digest(share: dict[str, Any]) -> str:
    """A SHA-256 digest of a share's content (everything but the digest itself)."""
    body = {k: v for k, v in share.items() if k != "digest"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def record_share(
    profile: Profile,
    seeds: Sequence[int],
    miles_per_seed: float = 100.0,
    *,
    single: Sequence[str] = SEED_ZERO_ONLY,
    progress: bool = True,
) -> dict[str, Any]:
    """One share of the record: every row of :data:`ROWS` (the paper's, DAgger's and the
    controls) for training
    ``seeds``, each seed driving ``miles_per_seed`` on its own run of the block (:func:`seed_run`;
    the sealed block of test roads, or open roads in the quick profile's smoke run). Each
    learned row trains the share's seeds; the rows of ``single`` (PilotNet and L2: no step of the
    paper is theirs) drive seed 0's network on each seed's run, as the expert and the oracle do.
    Returns the share: its rows' runs and what a pool checks (:func:`pool_shares`)."""
    seeds = sorted(int(k) for k in seeds)
    if not seeds or seeds[0] < 0 or len(set(seeds)) != len(seeds):
        raise ValueError(f"record_share: seeds {seeds} must be distinct and >= 0")
    check_range("record_share", "miles_per_seed", miles_per_seed, 0.0, lo_open=True)
    commit, keys = _commit(), [d.key for d in ROWS]
    world_cfg = WorldConfig.for_profile(profile)
    workers, device = default_workers(), pick_device()
    if progress:
        work = record_work(profile, len(seeds), miles_per_seed, single)
        print(plan_text(f"the record's seeds {seeds[0]}-{seeds[-1]}", work, workers, device.type))
    train = load_or_collect(DataConfig.for_profile(profile, "train"), progress)
    val = load_or_collect(DataConfig.for_profile(profile, "val"), progress)
    learned = [k for k in keys if k not in UNTRAINED and k not in single]
    fixed = build_drivers(profile, [k for k in keys if k not in learned], train, val, seed=0)
    runs: dict[str, list[dict[str, Any]]] = {k: [] for k in keys}
    for seed in seeds:
        run = seed_run(profile, seed, miles_per_seed)
        mine = {**fixed, **build_drivers(profile, learned, train, val, seed=seed)}
        for key in keys:
            label = f"{BY_KEY[key].label} (seed {seed})"
            r = result_dict(evaluate_stored(f"{key}_seed{seed}", label, mine[key], world_cfg, run,
                                            progress=progress))  # fmt: skip
            runs[key].append({"seed": seed, "first_track": run.first_track,
                              "collisions": r["collisions"], "car": r["car_collisions"],
                              "rail": r["rail_collisions"], "miles": round(r["miles"], 3),
                              "mph": round(r["mean_speed_mph"], 2), "stalls": r["stalls"]})  # fmt: skip
    template = EvalConfig(
        miles=miles_per_seed, n_worlds=profile.ablation_worlds, block=_block(profile)
    )
    share = {
        "format": SHARE_FORMAT,
        "profile": profile.name,
        "seeds": seeds,
        "miles_per_seed": miles_per_seed,
        "recipes_commit": commit,
        "settings_key": settings_key(
            profile,
            world_cfg,
            template,
            train.info["key"],
            val.info["key"],
            precision(),
            keys,
            list(single),
        ),
        "data": {"train": train.info["key"], "val": val.info["key"]},
        "precision": precision(),
        "torch": torch.__version__,
        "machine": f"{cpu_name()}, {os.cpu_count()} cores, {workers} workers, {device.type}",
        "block": {"name": template.block, "range": list(ROAD_BLOCKS[template.block])},
        "single_seed_rows": list(single),
        "family": family(f"before this record ran, in the recipes of {commit}"),
        "rows": [
            {
                "key": k,
                "label": BY_KEY[k].label,
                "paper_per_100mi": BY_KEY[k].paper_per_100mi,
                "control": k in {d.key for d in CONTROLS},
                "runs": runs[k],
            }
            for k in keys
        ],
    }
    share["digest"] = share_digest(share)
    return share


def _refuse(name: str, why: str) -> ShareRefused:
    return ShareRefused(f"{name}: {why}; not pooled")


def pool_shares(shares: Sequence[tuple[str, dict[str, Any]]]) -> dict[str, Any]:
    """The record from shares ``[(file name, share), ...]``: each row's runs of every seed (rows
    without training seeds, :data:`UNTRAINED` and the single-seed rows, as one pooled run), each
    seed's machine, and how many machines and kinds the record holds.

    Raises :class:`ShareRefused` naming the file for: a share edited after it was written (its
    digest), another format, profile, recipes commit, settings key, family or miles per seed
    than the first share's, a training seed in two shares, or a seed's roads off its own run of
    the block (:func:`seed_run`)."""
    if not shares:
        raise ValueError("pool_shares: no share to pool")
    first_name, first = shares[0]
    seen: dict[int, str] = {}
    machines: list[str] = []
    for name, share in shares:
        if share.get("format") != SHARE_FORMAT:
            raise _refuse(name, f"not a record share (format {share.get('format')!r})")
        if share.get("digest") != share_digest(share):
            raise _refuse(
                name, "its content does not match its digest: edited after it was written"
            )
        for field in ("profile", "recipes_commit", "settings_key", "miles_per_seed", "family"):
            if share[field] != first[field]:
                raise _refuse(name, f"its {field} {share[field]!r} differs from {first_name}'s "
                                    f"{first[field]!r}")  # fmt: skip
        profile = QUICK if share["profile"] == QUICK.name else FULL
        for seed in share["seeds"]:
            if seed in seen:
                raise _refuse(name, f"training seed {seed} is in {seen[seed]} too")
            seen[seed] = name
            expected = seed_run(profile, seed, share["miles_per_seed"]).first_track
            drove = {
                r["first_track"] for row in share["rows"] for r in row["runs"] if r["seed"] == seed
            }
            if drove != {expected}:
                raise _refuse(name, f"seed {seed} drove from tracks {sorted(drove)}, not its own "
                                    f"run of the block (from track {expected})")  # fmt: skip
        if share["machine"] not in machines:
            machines.append(share["machine"])
    single = set(first["single_seed_rows"]) | set(UNTRAINED)
    seeds = sorted(seen)
    rows = []
    for i, row in enumerate(first["rows"]):
        runs = sorted(
            ({**r, "machine": machines.index(share["machine"])}
             for _, share in shares for r in share["rows"][i]["runs"]), key=lambda r: r["seed"],
        )  # fmt: skip
        miles = sum(r["miles"] for r in runs)
        hours = sum(r["miles"] / r["mph"] for r in runs if r["mph"] > 0)
        mph, stalls = round(miles / hours, 2) if hours else 0.0, sum(r["stalls"] for r in runs)
        car, rail = sum(r["car"] for r in runs), sum(r["rail"] for r in runs)
        if row["key"] in single:  # one network (or none) drove every seed's run: one entry
            runs = [{"seed": 0, "collisions": car + rail, "miles": round(miles, 3), "mph": mph,
                     "stalls": stalls}]  # fmt: skip
        rows.append({
            "key": row["key"], "label": row["label"], "paper_per_100mi": row["paper_per_100mi"],
            "seeds": [{k: r[k] for k in ("seed", "collisions", "miles", "mph", "stalls", "machine")
                       if k in r} for r in runs],
            "car": car, "rail": rail, "mph": mph, "stalls": stalls,
            "commit": first["recipes_commit"],
            "control": row["control"],
        })  # fmt: skip
    mps, n = first["miles_per_seed"], len(seeds)
    kinds = sorted({m.split(",")[0] for m in machines})
    where = machines[0] if len(machines) == 1 else f"{len(machines)} machines ({', '.join(kinds)})"
    alone = " and ".join(BY_KEY[k].label for k in first["single_seed_rows"])
    return {
        "title": f"Table 1 of record ({first['profile']} profile, {n} training seeds)",
        "status": (
            f"Of record: {n} training seeds per learned row (seeds {seeds[0]}-{seeds[-1]}), "
            f"{mps:g} mi each ({alone}: seed 0 alone, {mps * n:g} mi), "
            f"pooled from {len(shares)} share{'s' * (len(shares) > 1)} on {len(machines)} "
            f"machine{'s' * (len(machines) > 1)} of {len(kinds)} kind{'s' * (len(kinds) > 1)}"
        ),
        "machine": where,
        "machines": machines,
        "torch": ", ".join(sorted({s["torch"] for _, s in shares})),
        "precision": first["precision"],
        "roads": "test",
        "block": {
            **first["block"],
            "recipes_commit": first["recipes_commit"],
            "sealed": first["block"]["name"] == SEALED_BLOCK,
        },
        "commits": {first["recipes_commit"]: "every row"},
        "miles_note": "each seed drove its miles on test roads of its own (record.seed_run)",
        "single_seed_rows": first["single_seed_rows"],
        "family": first["family"],
        "shares": [
            {"file": name, "seeds": s["seeds"], "digest": s["digest"]} for name, s in shares
        ],
        "paper_mph": PAPER_MPH,
        "rows": rows,
    }


def record_table1(
    profile: Profile,
    seeds: int = 10,
    miles_per_seed: float = 100.0,
    *,
    single: Sequence[str] = SEED_ZERO_ONLY,
    progress: bool = True,
) -> dict[str, Any]:
    """Table 1 of record on one machine: the share of training seeds ``0 .. seeds-1``
    (:func:`record_share`), pooled (:func:`pool_shares`)."""
    check_range("record_table1", "seeds", seeds, 1, integer=True)
    share = record_share(profile, range(seeds), miles_per_seed, single=single, progress=progress)
    return pool_shares([("this run", share)])


def plan(
    record: dict[str, Any],
    target: float = 0.8,
    most: int = 30,
    miles_options: Sequence[float] = (100.0, 150.0, 200.0, 300.0),
    n_sim: int = 500,
) -> dict[str, Any]:
    """The record's plan (issue 65): for each budget of miles per seed, the fewest training seeds
    (10 to ``most``) whose verdicts find a true 2x step at the record's own + affordance rate with
    at least ``target`` power under the seeds' spread fitted to ``record``
    (:func:`~e2e_lite.record_tests.record_power`), and what each plan costs on 2 cores and on a
    16-core machine with a GPU (:func:`record_work`); the chosen plan is the cheapest on 2 cores
    that reaches ``target`` (else the most powerful at ``most`` seeds)."""
    from .driving.verdicts import seeds_for_power
    from .estimate import estimate_s
    from .record_tests import record_power

    found = record_power(record)
    k, rate = found["dispersion"]["dispersion"], found["rate_per_100mi"]
    options = []
    for miles in miles_options:
        need = seeds_for_power(miles, rate, target, most=most, least=10, n_sim=n_sim, dispersion=k)
        work = record_work(FULL, need["seeds"], miles)
        options.append({**need, "miles_per_seed": miles,
                        "hours_2_cores": estimate_s(work, 2) / 3600.0,
                        "hours_16_cores_gpu": estimate_s(work, 16, "cuda") / 3600.0})  # fmt: skip
    reaching = [o for o in options if o["power"] >= target]
    chosen = (
        min(reaching, key=lambda o: o["hours_2_cores"])
        if reaching
        else max(options, key=lambda o: o["power"])
    )
    return {"dispersion": k, "rate_per_100mi": rate, "target": target, "options": options,
            "chosen": chosen}  # fmt: skip


def plan_lines(found: dict[str, Any]) -> list[str]:
    """:func:`plan` as the lines ``python -m e2e_lite.report --plan`` prints."""
    lines = [
        f"seeds' spread (dispersion) {found['dispersion']:.2f}; a 2x step at "
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
