"""Shares into a record: :func:`pool` checks that every share belongs (:func:`check_shares`) and
merges their rows (:func:`pool_row`) into the :class:`~e2e_lite.record.rows.Record` that the report
renders, and :func:`status` says in one sentence what it holds. Which roads each training seed
drives is here too (:func:`seed_run`): a share drives them, and a pool checks it did.
"""

from __future__ import annotations

from collections.abc import Sequence

from ..config import FULL, QUICK, Profile
from ..driving.roads import SEALED_BLOCK
from ..driving.rollout import EvalConfig, disjoint_runs
from ..simulation.world import WorldConfig
from .ablation import BY_KEY, PAPER_MPH, UNTRAINED
from .rows import SHARE_FORMAT, Block, Record, Row, SeedRun, Share, ShareRef, ShareRow

#: the fields every share of one record must have alike
ALIKE = ("profile", "recipes_commit", "settings_key", "miles_per_seed", "family")


def record_block(profile: Profile) -> str:
    """The block of test roads the record drives: the sealed one, which is for the record alone;
    the open one in the quick profile's smoke run."""
    return "open" if profile.quick else SEALED_BLOCK


def seed_run(
    profile: Profile, seed: int, miles_per_seed: float, block: str | None = None
) -> EvalConfig:
    """Training seed ``seed``'s own run of the record's block (``block``: another record's, as a
    pool checks it): ``miles_per_seed`` on tracks no other seed drives, the same whatever share
    (and whatever count of seeds) holds it (the run ``seed`` of
    :func:`~e2e_lite.driving.rollout.disjoint_runs`, whose runs do not depend on how many there
    are)."""
    ev = EvalConfig(
        miles=miles_per_seed * (seed + 1),
        n_worlds=profile.ablation_worlds,
        block=block or record_block(profile),
    )
    return disjoint_runs(ev, WorldConfig.for_profile(profile), seed + 1)[seed]


class ShareRefused(ValueError):
    """A share that does not belong in a pool (the message names its file and why)."""


def _refuse(name: str, why: str) -> ShareRefused:
    return ShareRefused(f"{name}: {why}; not pooled")


def check_shares(shares: Sequence[tuple[str, Share]]) -> list[str]:
    """The machines of ``shares`` (``[(file name, share), ...]``), in order of first appearance,
    once each share is found to belong with the first.

    Raises :class:`ShareRefused` naming the file for: a share edited after it was written (its
    digest), another format, profile, recipes commit, settings key, family or miles per seed than
    the first share's, a training seed in two shares, or a seed's roads off its own run of the
    block (:func:`seed_run`)."""
    first_name, first = shares[0]
    seen: dict[int, str] = {}
    machines: list[str] = []
    for name, share in shares:
        if share.format != SHARE_FORMAT:
            raise _refuse(name, f"not a record share (format {share.format!r})")
        if share.digest != share.content_digest():
            raise _refuse(
                name, "its content does not match its digest: edited after it was written"
            )
        for field in ALIKE:
            mine, theirs = getattr(share, field), getattr(first, field)
            if mine != theirs:
                why = f"its {field} {_shown(mine)!r} differs from {first_name}'s {_shown(theirs)!r}"
                raise _refuse(name, why)
        profile = QUICK if share.profile == QUICK.name else FULL
        for seed in share.seeds:
            if seed in seen:
                raise _refuse(name, f"training seed {seed} is in {seen[seed]} too")
            seen[seed] = name
            expected = seed_run(profile, seed, share.miles_per_seed, share.block.name).first_track
            drove = {r.first_track for row in share.rows for r in row.runs if r.seed == seed}
            if drove != {expected}:
                why = (
                    f"seed {seed} drove from tracks {sorted(drove)}, not its own run of the block"
                    f" (from track {expected})"
                )
                raise _refuse(name, why)
        if share.machine not in machines:
            machines.append(share.machine)
    return machines


def _shown(value: object) -> object:
    """A share's field as a refusal names it (its JSON, for a typed one)."""
    return value.to_json() if hasattr(value, "to_json") else value


def pool_row(parts: list[tuple[ShareRow, int]], single: bool, commit: str) -> Row:
    """One row of the record from its parts in each share (``[(row, machine index), ...]``):
    every seed's run in order of seed, or, for a row that one network (or none) drove on every
    seed's roads (``single``), one run of all their miles."""
    runs = sorted(((r, m) for row, m in parts for r in row.runs), key=lambda rm: rm[0].seed)
    miles = sum(r.miles for r, _ in runs)
    hours = sum(r.miles / r.mph for r, _ in runs if r.mph > 0)
    mph = round(miles / hours, 2) if hours else 0.0
    stalls = sum(r.stalls for r, _ in runs)
    car, rail = sum(r.car for r, _ in runs), sum(r.rail for r, _ in runs)
    kept = [r.interventions for r, _ in runs]
    interventions = None if None in kept else sum(kept)  # (every share must have kept them)
    if single:
        seeds = (
            SeedRun(
                0, car + rail, round(miles, 3), mph=mph, stalls=stalls, interventions=interventions
            ),
        )
    else:
        seeds = tuple(
            SeedRun(
                r.seed,
                r.collisions,
                r.miles,
                mph=r.mph,
                stalls=r.stalls,
                machine=m,
                interventions=r.interventions,
            )
            for r, m in runs
        )
    row = parts[0][0]
    return Row(
        key=row.key,
        label=row.label,
        paper_per_100mi=row.paper_per_100mi,
        seeds=seeds,
        car=car,
        rail=rail,
        mph=mph,
        stalls=stalls,
        commit=commit,
        control=row.control,
    )


def status(shares: Sequence[tuple[str, Share]], machines: list[str]) -> str:
    """The record's first sentence: its seeds, miles, shares, machines and kinds."""
    first = shares[0][1]
    seeds = sorted(k for _, s in shares for k in s.seeds)
    mps, n = first.miles_per_seed, len(seeds)
    kinds = {m.split(",")[0] for m in machines}
    alone = " and ".join(BY_KEY[k].label for k in first.single_seed_rows)
    # (each share trains its own seed 0 for these rows: one network per machine, not one in all)
    each = ", trained on each machine" if len(machines) > 1 else ""
    single = f" ({alone}: seed 0 alone{each}, {mps * n:g} mi)" if alone else ""

    def counted(k: int, what: str) -> str:
        return f"{k} {what}{'s' * (k > 1)}"

    return (
        f"Of record: {n} training seeds per learned row (seeds {seeds[0]}-{seeds[-1]}), "
        f"{mps:g} mi each{single}, pooled from "
        f"{counted(len(shares), 'share')} on {counted(len(machines), 'machine')} of "
        f"{counted(len(kinds), 'kind')}"
    )


def pool(shares: Sequence[tuple[str, Share]]) -> Record:
    """The record from ``shares`` (``[(file name, share), ...]``, checked by
    :func:`check_shares`): each row's runs of every seed (rows without training seeds,
    :data:`~e2e_lite.record.ablation.UNTRAINED`, and the single-seed rows as one pooled run), each
    seed's machine, and how many machines and kinds the record holds."""
    if not shares:
        raise ValueError("pool: no share to pool")
    machines = check_shares(shares)
    first = shares[0][1]
    single = set(first.single_seed_rows) | set(UNTRAINED)
    rows = tuple(
        pool_row(
            [(s.rows[i], machines.index(s.machine)) for _, s in shares],
            row.key in single,
            first.recipes_commit,
        )
        for i, row in enumerate(first.rows)
    )
    kinds = sorted({m.split(",")[0] for m in machines})
    where = machines[0] if len(machines) == 1 else f"{len(machines)} machines ({', '.join(kinds)})"
    seeds = len({k for _, s in shares for k in s.seeds})
    block = first.block
    return Record(
        title=f"Table 1 of record ({first.profile} profile, {seeds} training seeds)",
        status=status(shares, machines),
        machine=where,
        machines=machines,
        torch=", ".join(sorted({s.torch for _, s in shares})),
        precision=first.precision,
        roads="test",
        block=Block(block.name, block.range, first.recipes_commit, block.name != "open"),
        commits={first.recipes_commit: "every row"},
        miles_note="each seed drove its miles on test roads of its own (record.seed_run)",
        single_seed_rows=first.single_seed_rows,
        family=first.family,
        shares=tuple(ShareRef(name, s.seeds, s.digest) for name, s in shares),
        paper_mph=PAPER_MPH,
        rows=rows,
    )
