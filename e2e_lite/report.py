"""The course's numbers of record, rendered: Table 1 in the README and ``docs/results.md``, from
the committed JSON under ``docs/results/`` (``python -m e2e_lite.report``; ``--check`` exits 1
when either file differs from the render, which a test runs).

The training seed is the unit of replication. Each row holds its seeds' collisions and miles; the
table shows each seed's rate per 100 miles, their median and range, and the pooled Poisson
interval as a secondary column (it treats the seeds' miles as one draw, which a few networks are
not). Each of the paper's steps is tested on the seeds' counts (:func:`steps`, with
:func:`~e2e_lite.driving.verdicts.compare_seeds`): an exact permutation test that keeps ties as
ties, the rate ratio with a bootstrap interval over the seeds, and the paired sign-flip test
(seed ``k`` of every row drove the same roads; where rows share a parent network, the paired test
is the primary one). Beside the verdicts, the record's power to find a 2x step
(:func:`~e2e_lite.driving.verdicts.power`), so a "not shown" reads as what it is. A row driven
more than 10 % slower than the expert is marked, and its verdict names its speed.

The record itself is one resumable command, ``python -m e2e_lite.report --record``, which runs
:func:`e2e_lite.ablation.record_table1` (the layer that trains and drives), writes
``docs/results/table1.json`` and renders it.
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
from .driving.metrics import poisson_ci, seed_rates
from .record_tests import (  # noqa: F401 (re-exported: chapter 10 and the tests read them here)
    FAMILIES,
    POWER_ROW,
    POWER_STEP,
    SLOW_SHARE,
    STEPS,
    Step,
    controls_line,
    declared_family,
    family_line,
    power_line,
    record_dispersion,
    record_power,
    steps,
    verdict,
    verdict_cell,
    verdict_p,
)

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "docs" / "results" / "table1.json"
RESULTS_MD = ROOT / "docs" / "results.md"
FIGURE = ROOT / "docs" / "figures" / "table1.png"
README = ROOT / "README.md"
#: the README's rendered blocks lie between these pairs of lines
BEGIN, END = "<!-- table1: rendered by python -m e2e_lite.report -->", "<!-- /table1 -->"
CHAPTERS_BEGIN = "<!-- chapters: rendered by python -m e2e_lite.report -->"
CHAPTERS_END = "<!-- /chapters -->"
#: what the chapters printed in a full-profile run (``--course-run``), and the page it renders into
COURSE_RUN = ROOT / "docs" / "results" / "course_run.json"
TEACHING = ROOT / "docs" / "teaching.md"
RUN_BEGIN = "<!-- course run: rendered by python -m e2e_lite.report -->"
RUN_END = "<!-- /course run -->"


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


def _roads_text(record: dict[str, Any]) -> str:
    block = record.get("block")
    if block and not block.get("sealed", True):  # the quick profile's smoke run
        return f"the open block of test roads (a smoke run, recipes at {block['recipes_commit']})"
    if block:
        return (
            f"the sealed block '{block['name']}' of test roads (tracks {block['range'][0]:,}-"
            f"{block['range'][1] - 1:,}, driven by nothing else; recipes frozen at "
            f"{block['recipes_commit']})"
        )
    return (
        "open test roads, not sealed: some recipe choices were made while looking at them "
        "(issue 57); the next record drives a sealed block"
    )


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
    lines.append(
        "| step, or method against control | family | seeds | p, one-sided (test) | Holm p"
        " | rate ratio [95 % CI] | the paper's ratio | seed-level verdict |"
    )
    lines.append("|---|---|---|---|---|---|---|---|")
    tested = steps(record)
    for st in tested:
        lo, hi = st["ratio_ci"]
        ratio = "-" if np.isnan(st["ratio"]) else f"{st['ratio']:.2f} [{lo:.2f}, {hi:.2f}]"
        paper = "-" if st["paper_ratio"] is None else f"{st['paper_ratio']:.2g}"
        lines.append(
            f"| {st['step']} | {st['family']} | {st['seeds'][0]} vs {st['seeds'][1]} | "
            f"{st['p_better']:.2g} ({st['test']}) | {st['p_holm']:.2g} | {ratio} | {paper} | "
            f"{verdict_cell(st)} |"
        )
    controls = controls_line(tested)
    if controls:
        lines += ["", controls]
    threads = record.get("torch_threads")
    where = f"torch {record['torch']}" + (f" on {threads} threads" if threads else "")
    where += f", {record.get('precision', 'fp32')}"
    lines.append("")
    lines.append(
        f"*{record['status']}, on {_roads_text(record)}. Measured on {record['machine']}, "
        f"{where}: "
        + "; ".join(f"{what} at {c}" for c, what in record["commits"].items())
        + f". Ties are ties: a seed's count is its collisions over the row's common budget. A"
        f" rate ratio below 1: the later row collides less.{family_line(record)}"
        f"{power_line(record)} Slow: more than {100 * (1 - SLOW_SHARE):.0f} % slower than the"
        f" expert. The paper's drivers averaged {record['paper_mph']:g} mph.*"
    )
    return "\n".join(lines)


def results_md(record: dict[str, Any], table: str | None = None) -> str:
    """``docs/results.md``: Table 1 (``table``, the README's, when already rendered) and, per row,
    what a reader needs to judge it."""
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
        table1(record) if table is None else table,
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


def course_run_record(outputs: Path) -> dict[str, Any]:
    """A full-profile run of the course, read from its outputs folder: each chapter's wall time
    (``course_times.json``) and the headline figures it wrote (``metrics/<chapter>.json``), with
    the machine and torch (the record of ``--course-run``, rendered into docs/teaching.md)."""
    import torch

    from .course import TIMES_FILE
    from .estimate import cpu_name

    times = json.loads((outputs / TIMES_FILE).read_text())
    chapters = {}
    for stem, entry in sorted(times.items()):
        path = outputs / "metrics" / f"{stem}.json"
        metrics = json.loads(path.read_text()) if path.exists() else {}
        if metrics.get("profile") not in (None, "full"):
            raise ValueError(f"{path}: not a full-profile run ({metrics.get('profile')})")
        headline = {k: v for k, v in metrics.get("headline", {}).items() if v is not None}
        chapters[stem] = {
            "minutes": round(entry["seconds"] / 60.0, 1),
            "complete": entry.get("complete", False),
            "headline": headline,
        }
    return {"machine": f"{cpu_name()}, {os.cpu_count()} cores", "torch": torch.__version__,
            "chapters": chapters}  # fmt: skip


def _figure(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.3g}" if abs(value) < 100 else f"{value:,.0f}"
    return str(value)


def course_run_table(run: dict[str, Any] | None, record: dict[str, Any] | None = None) -> str:
    """docs/teaching.md's table of what each chapter printed in a full-profile run, and (with
    ``record``) what the record of many seeds says of the same rows."""
    from .course import CHAPTERS

    if run is None:
        return (
            "*No full-profile run is recorded yet: run `python -m e2e_lite.course`, then "
            "`python -m e2e_lite.report --course-run outputs` to record and render it.*"
        )
    lines = ["| chapter | minutes | what it printed (its headline figures) |", "|---|---:|---|"]
    for stem, ch in run["chapters"].items():
        figures = "; ".join(f"{k}: {_figure(v)}" for k, v in ch["headline"].items()) or "-"
        cut = "" if ch["complete"] else " (cut)"
        lines.append(f"| {stem} | {ch['minutes']:g}{cut} | {figures} |")
    done = [stem[:2] for stem, ch in run["chapters"].items() if ch["complete"]]
    total = sum(ch["minutes"] for ch in run["chapters"].values() if ch["complete"])
    what = (
        f"The full course, {total:.0f} min"
        if len(done) == len(CHAPTERS)
        else f"A run cut after chapter {done[-1] if done else '-'} (chapters {', '.join(done)} "
        f"complete, {total:.0f} min)"
    )
    lines += ["", f"*{what} on {run['machine']}, torch {run['torch']}"
              f"{'; ' + run['note'] if run.get('note') else ''}.*"]  # fmt: skip
    if record is not None:
        lines += ["", _one_run_against_the_record(record)]
    return "\n".join(lines)


def _one_run_against_the_record(record: dict[str, Any]) -> str:
    """What one course run's seed 0 is worth beside the record: each paper row's pooled rate of
    record and the verdicts of the controls, so a single run's "CVaR 2, control 5" is not read
    as a result."""
    rows = {r["key"]: r for r in record["rows"]}
    rates = ", ".join(
        f"{rows[k]['label']} {pooled(rows[k])[0]:.1f}"
        for k in ("gmm_affordance", "gmm_affordance_cvar", "gmm_affordance_control")
        if k in rows
    )
    controls = "; ".join(
        f"{st['step']}: {st['verdict']} (Holm p = {verdict_p(st):.2g})"
        for st in steps(record)
        if st["credits"] is not None
    )
    return (
        f"*One run is one training seed. The record ({len(rows['gmm']['seeds'])} seeds per row,"
        f" docs/results.md), pooled per 100 mi: {rates}; {controls}.*"
    )


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
    parser.add_argument(
        "--seeds", default="10", metavar="N|A-B",
        help="with --record: N, training seeds 0 .. N-1 (the whole record, pooled here), or A-B, "
        "one share of the record (written to <outputs>/shares/ for --pool)",
    )  # fmt: skip
    parser.add_argument(
        "--pool", nargs="+", type=Path, metavar="SHARE",
        help="pool record shares (from --record --seeds A-B, on any machines) into the record "
        "and render it; a share that does not belong is refused, naming its file",
    )  # fmt: skip
    parser.add_argument("--miles", type=float, default=100.0, help="test-road miles per seed")
    parser.add_argument(
        "--plan", action="store_true",
        help="print the record's plan: the seeds and miles per seed that find a 2x step with "
        "power 0.8 under the committed record's seed spread, and what each costs",
    )  # fmt: skip
    parser.add_argument(
        "--quick", action="store_true", help="with --record: the quick profile (a smoke test; "
        "written to the outputs folder, never to docs/)",
    )  # fmt: skip
    parser.add_argument(
        "--course-run", type=Path, metavar="OUTPUTS",
        help="record what a full-profile course run in OUTPUTS printed (docs/results/"
        "course_run.json, rendered into docs/teaching.md)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.course_run:
        with atomic_write(COURSE_RUN, "w") as f:
            json.dump(course_run_record(args.course_run), f, indent=1)
        print(f"wrote {COURSE_RUN.relative_to(ROOT)}")
    if args.plan:
        from .record import plan, plan_lines

        print("\n".join(plan_lines(plan(load()))))
        return 0
    if args.record or args.pool:
        from .artifacts import outputs_dir
        from .config import FULL, QUICK
        from .record import ShareRefused, parse_seeds, pool_shares, record_share

        if args.record:
            profile = QUICK if args.quick else FULL
            seeds = parse_seeds(args.seeds)
            share = record_share(profile, seeds, args.miles)
            if "-" in args.seeds:  # one share of the record: its file, to pool with the others
                path = (
                    outputs_dir(quick=profile.quick)
                    / "shares"
                    / (f"share-seeds-{seeds[0]}-{seeds[-1]}.json")
                )
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_write(path, "w") as f:
                    json.dump(share, f, indent=1)
                print(f"wrote {path}: pool it with python -m e2e_lite.report --pool SHARE...")
                return 0
            shares = [("this run", share)]
        else:
            shares = [(p.name, json.loads(p.read_text())) for p in args.pool]
        try:
            record = pool_shares(shares)
        except ShareRefused as err:
            print(err, file=sys.stderr)
            return 2
        quick = record["title"].startswith("Table 1 of record (quick")
        # a quick-profile pool is a smoke test, never a record of record
        path = outputs_dir(quick=True) / "table1.json" if quick else RECORD
        with atomic_write(path, "w") as f:
            json.dump(record, f, indent=1)
        print(f"wrote {path}")
        if quick:
            print(table1(record))
            return 0
    record = load()
    table = table1(record)
    wanted = {
        README: readme_with(README.read_text(), table),
        RESULTS_MD: results_md(record, table),
    }
    if TEACHING.exists():
        run = json.loads(COURSE_RUN.read_text()) if COURSE_RUN.exists() else None
        wanted[TEACHING] = _replace(
            TEACHING.read_text(), RUN_BEGIN, RUN_END, course_run_table(run, record)
        )
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
