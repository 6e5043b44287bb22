"""The course's numbers of record, rendered: Table 1 in the README and ``docs/results.md``, from
the committed JSON under ``docs/results/`` (``python -m e2e_lite.report``; ``--check`` exits 1
when either file differs from the render, which a test runs).

The training seed is the unit of replication. Each row holds its seeds' collisions and miles; the
table shows each seed's rate per 100 miles, their median and range, and the pooled Poisson
interval as a secondary column (it treats the seeds' miles as one draw, which three networks are
not). Each of the paper's steps is tested on the per-seed rates with an exact one-sided
Mann-Whitney test (:func:`seed_level_test`): with 3 seeds against 3 the smallest possible p is
0.05, so no step of a 3-seed table can be called reproduced; 5 against 5 can reach 0.004. A row
driven more than 10 % slower than the expert is marked, and its verdict names its speed.

The record itself is one resumable command: ``python -m e2e_lite.report --record [--seeds 5]
[--miles 100]`` trains every paper row, L2 and the two controls with that many training seeds,
drives each seed on test roads of its own (:func:`record_table1`), writes
``docs/results/table1.json`` and renders it. Trainings and drives are stored as the chapters store
theirs, so a cut run goes on where it stopped. It takes longer than the course's full profile
(five seeds instead of three, and every row), which keeps to its own budget.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .artifacts import atomic_write, save_figure
from .config import Profile, check_range
from .driving.metrics import compare_seeds, poisson_ci, result_dict, seed_rates

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "docs" / "results" / "table1.json"
RESULTS_MD = ROOT / "docs" / "results.md"
FIGURE = ROOT / "docs" / "figures" / "table1.png"
README = ROOT / "README.md"
#: the README's rendered blocks lie between these pairs of lines
BEGIN, END = "<!-- table1: rendered by python -m e2e_lite.report -->", "<!-- /table1 -->"
CHAPTERS_BEGIN = "<!-- chapters: rendered by python -m e2e_lite.report -->"
CHAPTERS_END = "<!-- /chapters -->"
#: the paper's steps: (before, after, what); each goes "better" in the paper (seed 000)
STEPS = (
    ("actuators", "gmm", "Baseline E2E -> trajectory GMM"),
    ("gmm", "gmm_affordance", "GMM -> + affordance"),
    ("gmm_affordance", "gmm_affordance_cvar", "+ affordance -> + CVaR"),
    ("gmm_affordance_control", "gmm_affordance_cvar", "CVaR against its control (the mean)"),
    ("gmm_affordance_w0", "gmm_affordance", "affordance loss against its control (w = 0)"),
)
#: a row slower than this share of the expert's speed is marked
SLOW_SHARE = 0.9


def load(path: Path = RECORD) -> dict[str, Any]:
    """A record of ``docs/results/`` (rows with per-seed collisions and miles), checked."""
    record = json.loads(path.read_text())
    for row in record["rows"]:
        if not row["seeds"] or any(s["miles"] <= 0 or s["collisions"] < 0 for s in row["seeds"]):
            raise ValueError(f"{path.name}: row {row['key']!r} needs seeds with miles > 0")
        if sum(s["collisions"] for s in row["seeds"]) != row["car"] + row["rail"]:
            raise ValueError(f"{path.name}: row {row['key']!r}: seeds do not add up to car + rail")
    return record


def pooled(row: dict[str, Any]) -> tuple[float, float, float]:
    """The pooled rate per 100 miles and its exact 95 % Poisson interval (secondary)."""
    k = sum(s["collisions"] for s in row["seeds"])
    miles = sum(s["miles"] for s in row["seeds"])
    lo, hi = poisson_ci(k, miles / 100.0)
    return 100.0 * k / miles, lo, hi


def dispersion(row: dict[str, Any]) -> float | None:
    """The seeds' chi-square against one shared rate (degrees of freedom: seeds - 1); far above
    its degrees of freedom, the seeds do not drive alike. ``None`` for one run."""
    if len(row["seeds"]) < 2:
        return None
    k = np.array([s["collisions"] for s in row["seeds"]], dtype=float)
    m = np.array([s["miles"] for s in row["seeds"]], dtype=float)
    expected = m * k.sum() / m.sum()
    return float(np.sum((k - expected) ** 2 / np.maximum(expected, 1e-12)))


#: the spread a paper row's seeds may show: its worst seed's rate at most this many times the
#: median's (issue 50)
SPREAD_GOAL = 3.0


def spread(row: dict[str, Any]) -> float | None:
    """The worst seed's rate over the median seed's (``inf`` when the median is 0 and the worst
    is not; ``None`` for one run, e.g. an evaluation's result of a driver with no seeds): how far
    one training seed strays from the recipe's typical."""
    if len(row.get("seeds") or []) < 2:
        return None
    rates = seed_rates(row)
    median, worst = float(np.median(rates)), float(rates.max())
    if median == 0.0:
        return 1.0 if worst == 0.0 else float("inf")
    return worst / median


def seed_level_test(before: np.ndarray, after: np.ndarray) -> float:
    """Exact one-sided p-value that ``after``'s per-seed rates are lower than ``before``'s: the
    Mann-Whitney test of :func:`~e2e_lite.driving.metrics.compare_seeds`, on bare rates."""
    as_result = lambda rates: {"seeds": [{"collisions": r, "miles": 100.0} for r in rates]}  # noqa: E731
    return compare_seeds(as_result(after), as_result(before))["p_fewer"]


def verdict(test: dict[str, Any], slow_mph: float | None) -> str:
    """A step's verdict from its seed-level test (:func:`~e2e_lite.driving.metrics.compare_seeds`
    of the later row against the earlier), with the later row's speed when it is slow."""
    if test["fewer"]:
        text = "reproduces"
    elif test["more"]:
        text = "the opposite"
    else:
        text = f"not shown at the seed level (p = {test['p_fewer']:.2g})"
    return text + (f", at {slow_mph:.1f} mph" if slow_mph is not None else "")


def steps(record: dict[str, Any]) -> list[dict[str, Any]]:
    """Each of :data:`STEPS` present in the record, tested on the per-seed rates."""
    rows = {r["key"]: r for r in record["rows"]}
    expert_mph = rows["expert"]["mph"] if "expert" in rows else None
    out = []
    for before, after, what in STEPS:
        if before not in rows or after not in rows:
            continue
        test = compare_seeds(rows[after], rows[before])  # (a record's rows hold their seeds)
        mph = rows[after]["mph"]
        slow = mph if expert_mph and mph < SLOW_SHARE * expert_mph else None
        out.append(
            {"step": what, "p_better": test["p_fewer"], "p_worse": test["p_more"],
             "verdict": verdict(test, slow)}
        )  # fmt: skip
    return out


def _row_cells(row: dict[str, Any], expert_mph: float | None) -> list[str]:
    rates = seed_rates(row)
    rate, lo, hi = pooled(row)
    seeds = " / ".join(f"{r:.1f}" for r in rates) if len(rates) > 1 else "-"
    spread = (
        f"{np.median(rates):.1f} [{rates.min():.1f}-{rates.max():.1f}]" if len(rates) > 1 else "-"
    )
    slow = " (slow)" if expert_mph and row["mph"] < SLOW_SHARE * expert_mph else ""
    paper = "-" if row["paper_per_100mi"] is None else f"{row['paper_per_100mi']:g}"
    stalls = "-" if row["stalls"] is None else f"{row['stalls']:,}"
    return [row["label"], seeds, spread, f"{rate:.1f} [{lo:.1f}-{hi:.1f}]",
            f"{row['mph']:.1f}{slow}", stalls, _between(row), paper]  # fmt: skip


def _between(row: dict[str, Any]) -> str:
    """The mean driving time between two collisions [min] ("-" without a collision)."""
    k, miles = row["car"] + row["rail"], sum(s["miles"] for s in row["seeds"])
    return f"{60.0 * miles / row['mph'] / k:.1f}" if k else "-"


def table1(record: dict[str, Any]) -> str:
    """The README's Table 1: the paper's rows and the two controls, each seed's rate."""
    rows = {r["key"]: r for r in record["rows"]}
    expert_mph = rows["expert"]["mph"] if "expert" in rows else None
    lines = [
        "| driver | per seed, per 100 mi | median [range] | pooled [95 % CI] | mph | stalls "
        "| min between collisions | paper |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    for row in record["rows"]:
        lines.append("| " + " | ".join(_row_cells(row, expert_mph)) + " |")
    lines.append("")
    lines.append("| the paper's step | seed-level verdict (one-sided exact Mann-Whitney) |")
    lines.append("|---|---|")
    lines += [f"| {s['step']} | {s['verdict']} |" for s in steps(record)]
    lines.append("")
    lines.append(
        f"*{record['status']}. Measured on {record['machine']}, torch {record['torch']} on "
        f"{record['torch_threads']} threads: "
        + "; ".join(f"{what} at {c}" for c, what in record["commits"].items())
        + f". Slow: more than {100 * (1 - SLOW_SHARE):.0f} % slower than the expert. The paper's"
        f" drivers averaged {record['paper_mph']:g} mph.*"
    )
    return "\n".join(lines)


def results_md(record: dict[str, Any]) -> str:
    """``docs/results.md``: Table 1 and, per row, what a reader needs to judge it."""
    rows = record["rows"]
    detail = [
        "| driver | collisions (car / rail) | miles | stalls | minutes between collisions "
        "| seeds' chi-square (df) | worst seed / median |",
        "|---|---:|---:|---:|---:|---|---:|",
    ]
    for row in rows:
        k, miles = row["car"] + row["rail"], sum(s["miles"] for s in row["seeds"])
        between = _between(row)
        chi = dispersion(row)
        chi_text = "-" if chi is None else f"{chi:.1f} ({len(row['seeds']) - 1})"
        stalls = "-" if row["stalls"] is None else str(row["stalls"])
        ratio = spread(row)
        ratio_text = "-" if ratio is None else f"{ratio:.1f}"
        if ratio is not None and row["paper_per_100mi"] is not None and ratio > SPREAD_GOAL:
            ratio_text += " (over the goal)"
        detail.append(f"| {row['label']} | {k} ({row['car']} / {row['rail']}) | {miles:.0f} | "
                      f"{stalls} | {between} | {chi_text} | {ratio_text} |")  # fmt: skip
    return "\n".join([
        "# Results",
        "",
        "Rendered by `python -m e2e_lite.report` from `docs/results/table1.json`; do not edit by"
        " hand. Every chapter prints its own numbers when it runs; the findings of the"
        " investigations behind the course's recipes are in [lab-notes.md](lab-notes.md).",
        "",
        f"## {record['title']}",
        "",
        table1(record),
        "",
        *(line for note in record.get("notes", []) for line in (note, "")),
        "## Per row",
        "",
        "A seeds' chi-square far above its degrees of freedom says the training seeds do not drive"
        " alike: read the per-seed rates before the pooled one. The course's goal for a paper"
        f" row: its worst seed at most {SPREAD_GOAL:g} times its median. Stalls: a car under"
        " 0.5 m/s for 20 s, re-placed ('-': not recorded by that run).",
        "",
        *detail,
        "",
        f"*{record['miles_note']}.*",
        "",
    ])  # fmt: skip


def figure(record: dict[str, Any]):
    """Table 1 as a picture: each training seed's rate (grey dots), their median (a black bar)
    and the paper's figure (a red diamond), on a symmetric-log axis (the rates span decades)."""
    from matplotlib.figure import Figure

    rows = record["rows"]
    fig = Figure(figsize=(8.5, 0.45 * len(rows) + 1.4), layout="constrained")
    ax = fig.subplots()
    for y, row in enumerate(rows):
        rates = seed_rates(row)
        ax.scatter(rates, np.full(len(rates), y), color="0.55", s=22, zorder=2)
        ax.plot([np.median(rates)] * 2, [y - 0.3, y + 0.3], color="black", lw=2.5, zorder=3)
        if row["paper_per_100mi"] is not None:
            ax.scatter([row["paper_per_100mi"]], [y], marker="D", color="C3", s=40, zorder=4)
    ax.set_yticks(range(len(rows)), [r["label"] for r in rows], fontsize=9)
    ax.invert_yaxis()
    ax.set_xscale("symlog", linthresh=1.0)
    top = max(max(seed_rates(r).max(), r["paper_per_100mi"] or 0.0) for r in rows)
    ax.set_xlim(0.0, 2.0 * top)
    ax.grid(axis="x", alpha=0.3)
    ax.set_xlabel("collisions per 100 miles: grey, each training seed; black, their median; "
                  "red, the paper", fontsize=9)  # fmt: skip
    ax.set_title(record["title"], fontsize=10)
    return fig


def chapters_table() -> str:
    """The README's chapter list, one line each, from :data:`e2e_lite.course.CHAPTERS` (the same
    times ``--help`` prints)."""
    from .course import CHAPTERS, QUICK_COURSE_S, find_chapters

    paths = dict(find_chapters(ROOT / "chapters"))
    lines = [
        "| # | chapter | the idea | paper | quick | full |",
        "|---|---|---|---|---:|---:|",
    ]
    for n, info in CHAPTERS.items():
        path = paths[n].relative_to(ROOT)
        name = path.stem[3:].replace("_", " ")
        paper = f"§{info.paper}" if info.paper[:1].isdigit() else info.paper or "-"
        lines.append(f"| {n:02d} | [{name}]({path}) | {info.purpose} | {paper} | "
                     f"{info.quick_s} s | {info.full_min} min |")  # fmt: skip
    total = sum(i.full_min for i in CHAPTERS.values())
    lines.append(f"| | **the course**, in order | | | {QUICK_COURSE_S} s | {total} min |")
    return "\n".join(lines)


def _replace(text: str, begin: str, end: str, block: str) -> str:
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise ValueError(f"README.md has no block between {begin!r} and {end!r}")
    return pattern.sub(lambda _: f"{begin}\n{block}\n{end}", text)


def readme_with(readme: str, table: str, chapters: str | None = None) -> str:
    """``readme`` with its Table 1 block replaced by ``table`` and its chapters block by
    ``chapters`` (default: :func:`chapters_table`)."""
    readme = _replace(readme, BEGIN, END, table)
    return _replace(readme, CHAPTERS_BEGIN, CHAPTERS_END, chapters or chapters_table())


def record_table1(
    profile: Profile,
    seeds: int = 5,
    miles_per_seed: float = 100.0,
    *,
    progress: bool = True,
) -> dict[str, Any]:
    """Table 1 of record: every row of :data:`DRIVERS` and :data:`CONTROLS`, each learned row
    trained with ``seeds`` training seeds, each seed driving ``miles_per_seed`` on test roads of
    its own (:func:`evaluate_drivers`; trainings and evaluations are stored, so a cut run goes on
    where it stopped). Returns the record :mod:`e2e_lite.report` renders (per row: each seed's
    collisions, miles, mph and stalls; the code's commit, the CPU, torch and its threads)."""
    import platform
    import subprocess

    import torch

    from . import ablation
    from .driving.parallel import EVAL_TORCH_THREADS
    from .driving.rollout import EvalConfig
    from .simulation.world import WorldConfig

    check_range("record_table1", "seeds", seeds, 1, integer=True)
    check_range("record_table1", "miles_per_seed", miles_per_seed, 0.0, lo_open=True)
    # the code that trains and drives: the commit at the start (a run takes hours)
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    keys = [d.key for d in (*ablation.DRIVERS, *ablation.CONTROLS)]
    world_cfg = WorldConfig.for_profile(profile)
    ev = EvalConfig(miles=miles_per_seed * seeds, n_worlds=profile.ablation_worlds)
    drivers = ablation.build_seeded_drivers(profile, keys, seeds=seeds, progress=progress)
    results = ablation.evaluate_drivers(
        drivers, world_cfg, ev, progress=progress, workers=profile.ablation_workers
    )
    cpu = next(
        (ln.split(":", 1)[1].strip() for ln in _cpuinfo() if ln.startswith("model name")),
        platform.processor() or platform.machine(),
    )
    rows = []
    for key in keys:
        r = result_dict(results[key])
        parts = r.get("seeds") or [r]
        rows.append({
            "key": key,
            "label": ablation.BY_KEY[key].label,
            "paper_per_100mi": ablation.BY_KEY[key].paper_per_100mi,
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
            "control": key in {d.key for d in ablation.CONTROLS},
        })  # fmt: skip
    return {
        "title": f"Table 1 of record ({profile.name} profile, {seeds} training seeds)",
        "status": (
            f"Of record: {seeds} training seeds per learned row, {miles_per_seed:g} mi each on "
            "test roads no choice has seen"
        ),
        "machine": f"{cpu}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "torch_threads": EVAL_TORCH_THREADS,
        "roads": ev.split,
        "commits": {commit: "every row"},
        "miles_note": "each seed drove its miles on test roads of its own (evaluation.disjoint_runs)",
        "paper_mph": ablation.PAPER_MPH,
        "rows": rows,
    }


def _cpuinfo() -> list[str]:
    """The lines of ``/proc/cpuinfo`` (empty where there is none)."""
    try:
        return Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return []


def main(argv: list[str] | None = None) -> int:
    """Render the committed record (``--check``: only compare), or drive a new one first
    (``--record``)."""
    parser = argparse.ArgumentParser(prog="python -m e2e_lite.report", description=__doc__)
    parser.add_argument("--check", action="store_true", help="exit 1 if a file differs")
    parser.add_argument(
        "--record",
        action="store_true",
        help="train and drive Table 1 of record first (hours in the full profile; stop and run "
        "again to go on: trainings and drives are stored), then write docs/results/table1.json",
    )
    parser.add_argument("--seeds", type=int, default=5, help="training seeds per learned row")
    parser.add_argument("--miles", type=float, default=100.0, help="test-road miles per seed")
    parser.add_argument(
        "--quick", action="store_true", help="with --record: the quick profile (a smoke test; "
        "written to the outputs folder, never to docs/)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.record:
        from .artifacts import outputs_dir
        from .config import FULL, QUICK

        profile = QUICK if args.quick else FULL
        record = record_table1(profile, args.seeds, args.miles)
        path = outputs_dir(quick=True) / "table1.json" if args.quick else RECORD
        with atomic_write(path, "w") as f:
            json.dump(record, f, indent=1)
        print(f"wrote {path}")
        if args.quick:
            print(table1(record))
            return 0
    record = load()
    wanted = {
        README: readme_with(README.read_text(), table1(record)),
        RESULTS_MD: results_md(record),
    }
    stale = [p for p, text in wanted.items() if not p.exists() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"{p.relative_to(ROOT)} differs from the render: run python -m e2e_lite.report")
        return 1 if stale else 0
    for p in stale:
        with atomic_write(p, "w") as f:
            f.write(wanted[p])
        print(f"wrote {p.relative_to(ROOT)}")
    save_figure(figure(record), FIGURE)
    print(f"wrote {FIGURE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
