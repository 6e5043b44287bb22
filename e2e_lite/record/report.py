"""The course's numbers, rendered: Table 1 in the README and ``docs/results.md`` from the
committed record (``docs/results/table1.json``), the README's chapter table from
:data:`e2e_lite.course.run.CHAPTERS`, and ``docs/teaching.md``'s table of a full-profile course run
(``docs/results/course_run.json``). ``python -m e2e_lite.record.report`` writes them; ``--check`` exits 1
when a file differs from its render (a test runs it). It renders and does nothing else: running,
pooling and planning the record are ``python -m e2e_lite.record``'s.

The training seed is the unit of replication. Each row holds its seeds' collisions and miles; the
table shows each seed's rate per 100 miles, their median and range, and the pooled Poisson
interval as a secondary column (it treats the seeds' miles as one draw, which a few networks are
not). Each step is tested on the seeds' counts (:func:`~e2e_lite.record.stats.steps`), with the
record's power to find a 2x step beside the verdicts, so a "not shown" reads as what it is. A row
driven more than 10 % slower than the expert is marked, and its verdict names its speed.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..artifacts import atomic_write, save_figure
from ..course.run import CHAPTERS, QUICK_COURSE_S, duration, find_chapters
from ..driving.roads import SPENT_BLOCKS
from ..driving.rollout import EvalConfig
from ..stats.power import chi_square_spread
from ..stats.seeds import seed_rates, spread
from . import COURSE_RUN, QUICK_RUN, RECORD, ROOT, words
from .kit import replace_block, teaching_with
from .rows import SLOW_SHARE, Record, Row, load_record
from .stats import OFF_CENTRE_READING, SPREAD_GOAL, StepResult, off_centre_steps, steps

RESULTS_MD = ROOT / "docs" / "results.md"
FIGURE = ROOT / "docs" / "figures" / "table1.png"
README = ROOT / "README.md"
TEACHING = ROOT / "docs" / "teaching.md"
#: the rendered blocks lie between these pairs of lines
BEGIN, END = "<!-- table1: rendered by python -m e2e_lite.record.report -->", "<!-- /table1 -->"
CHAPTERS_BEGIN = "<!-- chapters: rendered by python -m e2e_lite.record.report -->"
CHAPTERS_END = "<!-- /chapters -->"


def load(path: Path = RECORD) -> Record:
    """A record of ``docs/results/`` (default: the record of record), checked."""
    return load_record(path)


def _roads_text(record: Record) -> str:
    block = record.block
    if block and not block.sealed:  # the quick profile's smoke run
        return f"the open block of test roads (a smoke run, recipes at {block.recipes_commit})"
    if block:
        lo, hi = block.range
        driven = (
            "spent since: driven by the records of 321f6a9 and 28eba5c, with a redesign between"
            " them; the next record drives a fresh one"
            if block.name in SPENT_BLOCKS
            else "driven by nothing else"
        )
        return (
            f"the sealed block '{block.name}' of test roads (tracks {lo:,}-{hi - 1:,}, {driven};"
            f" recipes frozen at {block.recipes_commit})"
        )
    return (
        "open test roads, not sealed: some recipe choices were made while looking at them; the"
        " next record drives a sealed block"
    )


def _row_cells(row: Row, expert_mph: float | None) -> list[str]:
    """One line of Table 1: the driver, its seeds' rates, their median and range, the pooled
    rate, its speed, stalls, minutes between collisions and the paper's figure."""
    rates = seed_rates(row)
    rate, lo, hi = row.pooled()
    several = len(rates) > 1
    per_seed = " / ".join(f"{r:.1f}" for r in rates) if several else "-"
    median = f"{np.median(rates):.1f} [{rates.min():.1f}-{rates.max():.1f}]" if several else "-"
    slow = " (slow)" if row.slow_beside(expert_mph) else ""
    paper = "-" if row.paper_per_100mi is None else f"{row.paper_per_100mi:g}"
    stalls = "-" if row.stalls is None else f"{row.stalls:,}"
    pooled = f"{rate:.1f} [{lo:.1f}-{hi:.1f}]"
    return [
        row.label,
        per_seed,
        median,
        pooled,
        f"{row.mph:.1f}{slow}",
        stalls,
        _between(row),
        paper,
    ]


def _off_centre(row: Row) -> str:
    """Off-centre episodes per 100 miles: the autonomy metric's interventions that were neither
    collisions nor stalls (the car farther from every lane centre than ``EvalConfig.offcentre_m`` for longer
    than ``EvalConfig.offcentre_grace_s``, as :func:`_off_centre_line` says; "-": not recorded)."""
    episodes = row.off_centre
    return "-" if episodes is None else f"{100.0 * episodes / row.miles:.1f}"


def _kept_interventions(record: Record) -> bool:
    """Whether any row of ``record`` kept its interventions (records before 2026-11-29 did not:
    their tables have no off-centre column)."""
    return any(row.interventions is not None for row in record.rows)


def _between(row: Row) -> str:
    """The mean driving time between two collisions [min] ("-" without a collision)."""
    minutes = row.minutes_between()
    return "-" if minutes is None else f"{minutes:.1f}"


def _steps_table(record: Record) -> list[str]:
    """The table of steps under Table 1: each test's family, seeds, p, Holm p, rate ratio, the
    paper's ratio and its verdict."""
    off = {st.step: st for st in off_centre_steps(record)}
    head = (
        "| step, or method against control | family | seeds | p, one-sided: direction (test) |"
        " Holm p | rate ratio [95 % CI] | the paper's ratio | seed-level verdict |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|"]
    if off:
        lines = [
            head + " off-centre episodes: Holm p, verdict | a better driver? |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
    for st in steps(record):
        lo, hi = st.ratio_ci
        ratio = "-" if np.isnan(st.ratio) else f"{st.ratio:.2f} [{lo:.2f}, {hi:.2f}]"
        paper = "-" if st.paper_ratio is None else f"{st.paper_ratio:.2g}"
        p, p_holm, direction = st.p_read
        holm_p = f"{p_holm:.2g}" + _all(st)
        cells = (
            f"| {st.step} | {st.family} | {st.seeds[0]} vs {st.seeds[1]} | "
            f"{p:.2g}: {direction} ({st.test}) | {holm_p} | {ratio} | {paper} | {words.cell(st)} |"
        )
        if off:
            second = off.get(st.step)
            read = (
                "-"
                if second is None
                else f"{second.verdict_p:.2g}{_all(second)}, {words.off_centre(second)}"
            )
            cells += f" {read} | {words.better_driver(st, second)} |"
        lines.append(cells)
    return lines


def _all(st: StepResult) -> str:
    """`` (all: p)``, the test's Holm p over every test of the record, where it was declared."""
    return "" if np.isnan(st.verdict_p_all) else f" (all: {st.verdict_p_all:.2g})"


def _table_note(record: Record) -> str:
    """The italic paragraph under Table 1: what the record holds, where it was measured, how its
    tests are read and what they can find."""
    where = f"torch {record.torch}"
    if record.torch_threads:
        where += f" on {record.torch_threads} threads"
    where += f", {record.precision or 'fp32'}"
    commits = "; ".join(f"{what} at {c}" for c, what in (record.commits or {}).items())
    return (
        f"*{record.status}, on {_roads_text(record)}. Measured on {record.machine}, {where}: "
        f"{commits}. Ties are ties: a seed's count is its collisions over the row's common budget."
        f" A rate ratio below 1: the later row collides less.{words.families(record)}"
        f"{words.power(record)} Slow: more than {100 * (1 - SLOW_SHARE):.0f} % slower than the"
        f" expert.{_off_centre_line(record)} The paper's drivers averaged {record.paper_mph:g}"
        " mph.*"
    )


def _off_centre_line(record: Record) -> str:
    """What the off-centre column counts, when the table has one."""
    if not _kept_interventions(record):
        return ""
    cfg = EvalConfig()
    read = off_centre_steps(record)
    declared = read and read[0].family != OFF_CENTRE_READING
    tests = (
        ""
        if not read or declared
        else f" The steps' off-centre tests were read after this record ran ({len(read)} tests,"
        f" Holm-adjusted together) and were not declared: they can show a step is not a better"
        f" driver, not that it is one."
    )
    return (
        f" Off-centre: the autonomy metric's interventions that were neither collisions nor stalls,"
        f" the car more than {cfg.offcentre_m:g} m from every lane centre for more than"
        f" {cfg.offcentre_grace_s:g} s.{tests}"
    )


def table1(record: Record) -> str:
    """The README's Table 1: every row with each seed's rate, then the table of steps, what the
    controls found, and the note on what the record holds."""
    off = _kept_interventions(record)
    lines = [
        "| driver | per seed, per 100 mi | median [range] | pooled [95 % CI] | mph | stalls "
        "| min between collisions | paper |" + (" off-centre per 100 mi |" if off else ""),
        "|---|---|---|---|---:|---:|---:|---:|" + ("---:|" if off else ""),
    ]
    expert_mph = record.expert_mph
    for row in record.rows:
        cells = _row_cells(row, expert_mph) + ([_off_centre(row)] if off else [])
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", *_steps_table(record)]
    controls = words.controls(steps(record))
    if controls:
        lines += ["", controls]
    lines += ["", _table_note(record)]
    return "\n".join(lines)


def _detail_line(row: Row) -> str:
    """One line of docs/results.md's table per row."""
    chi = chi_square_spread([s.collisions for s in row.seeds], [s.miles for s in row.seeds])
    chi_text = "-" if chi is None else f"{chi:.1f} ({len(row.seeds) - 1})"
    stalls = "-" if row.stalls is None else str(row.stalls)
    ratio = spread(row)
    ratio_text = "-" if ratio is None else f"{ratio:.1f}"
    if ratio is not None and row.paper_per_100mi is not None and ratio > SPREAD_GOAL:
        ratio_text += " (over the goal)"
    return (
        f"| {row.label} | {row.collisions} ({row.car} / {row.rail}) | {row.miles:.0f} | "
        f"{stalls} | {_between(row)} | {chi_text} | {ratio_text} |"
    )


def results_md(record: Record, table: str | None = None) -> str:
    """``docs/results.md``: Table 1 (``table``, the README's, when already rendered) and, per row,
    what a reader needs to judge it."""
    head = [
        "# Results",
        "",
        "Rendered by `python -m e2e_lite.record.report` from `docs/results/table1.json`; do not edit by"
        " hand. Every chapter prints its own numbers when it runs; the findings of the"
        " investigations behind the course's recipes are in [lab-notes.md](lab-notes.md).",
        "",
        f"## {record.title}",
        "",
        table1(record) if table is None else table,
        "",
    ]
    notes = [line for note in record.notes or [] for line in (note, "")]
    per_row = [
        "## Per row",
        "",
        "A seeds' chi-square far above its degrees of freedom says the training seeds do not drive"
        " alike: read the per-seed rates before the pooled one. The course's goal for a paper"
        f" row: its worst seed at most {SPREAD_GOAL:g} times its median. Stalls: a car under"
        " 0.5 m/s for 20 s, re-placed ('-': not recorded by that run).",
        "",
        "| driver | collisions (car / rail) | miles | stalls | minutes between collisions "
        "| seeds' chi-square (df) | worst seed / median |",
        "|---|---:|---:|---:|---:|---|---:|",
        *(_detail_line(row) for row in record.rows),
        "",
        f"*{record.miles_note}.*",
        "",
    ]
    return "\n".join(head + notes + per_row)


def figure(record: Record):
    """Table 1 as a picture, both outcomes per row: each training seed's collisions per 100 mi
    (grey dots), their median (a black bar) and the paper's figure (a red diamond); beside them,
    where the record kept them, each seed's off-centre episodes per 100 mi. Symmetric-log axes
    (the rates span decades)."""
    rows = record.rows
    off = _kept_interventions(record)
    fig = Figure(figsize=(11.5 if off else 8.5, 0.45 * len(rows) + 1.4), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True, width_ratios=(3, 2)) if off else [fig.subplots()]
    panels = [(axes[0], seed_rates, "collisions per 100 miles")]
    if off:
        panels.append((axes[1], _off_centre_rates, "off-centre episodes per 100 miles"))
    for ax, rates_of, what in panels:
        top = 1.0
        for y, row in enumerate(rows):
            rates = rates_of(row)
            if rates is None:
                continue
            ax.scatter(rates, np.full(len(rates), y), color="0.55", s=22, zorder=2)
            ax.plot([np.median(rates)] * 2, [y - 0.3, y + 0.3], color="black", lw=2.5, zorder=3)
            paper = row.paper_per_100mi if rates_of is seed_rates else None
            if paper is not None:
                ax.scatter([paper], [y], marker="D", color="C3", s=40, zorder=4)
            top = max(top, rates.max(), paper or 0.0)
        ax.set_xscale("symlog", linthresh=1.0)
        ax.set_xlim(0.0, 2.0 * top)
        ax.grid(axis="x", alpha=0.3)
        ax.set_xlabel(what, fontsize=9)
    axes[0].set_yticks(range(len(rows)), [r.label for r in rows], fontsize=9)
    axes[0].invert_yaxis()
    key = "grey, each training seed; black, their median; red, the paper"
    fig.suptitle(f"{record.title}: {key}", fontsize=10)
    return fig


def _off_centre_rates(row: Row) -> np.ndarray | None:
    """Each seed's off-centre episodes per 100 mi (None: not recorded)."""
    counts = [s.off_centre for s in row.seeds]
    if None in counts:
        return None
    return np.array([100.0 * c / s.miles for c, s in zip(counts, row.seeds)])


def chapters_table() -> str:
    """The README's chapter list, one line each, from :data:`e2e_lite.course.run.CHAPTERS` (the same
    times ``--help`` prints)."""

    paths = dict(find_chapters(ROOT / "chapters"))
    lines = [
        "| # | chapter | the idea | paper | quick | full |",
        "|---|---|---|---|---:|---:|",
    ]
    for n, info in CHAPTERS.items():
        path = paths[n].relative_to(ROOT)
        name = path.stem[3:].replace("_", " ")
        paper = f"§{info.paper}" if info.paper[:1].isdigit() else info.paper or "-"
        times = f"{info.quick_s} s | {duration(info.full_s)}"
        lines.append(f"| {n:02d} | [{name}]({path}) | {info.purpose} | {paper} | {times} |")
    total = duration(sum(i.full_s for i in CHAPTERS.values()))
    lines.append(f"| | **the course**, in order | | | {QUICK_COURSE_S} s | {total} |")
    return "\n".join(lines)


def readme_with(readme: str, table: str, chapters: str | None = None) -> str:
    """``readme`` with its Table 1 block replaced by ``table`` and its chapters block by
    ``chapters`` (default: :func:`chapters_table`)."""
    readme = replace_block(readme, BEGIN, END, table)
    return replace_block(readme, CHAPTERS_BEGIN, CHAPTERS_END, chapters or chapters_table())


def renders(record: Record) -> dict[Path, str]:
    """Each rendered file and the text it should hold, from ``record``."""
    table = table1(record)
    wanted = {
        README: readme_with(README.read_text(), table),
        RESULTS_MD: results_md(record, table),
    }
    if TEACHING.exists():
        run = json.loads(COURSE_RUN.read_text()) if COURSE_RUN.exists() else None
        quick = json.loads(QUICK_RUN.read_text()) if QUICK_RUN.exists() else None
        wanted[TEACHING] = teaching_with(TEACHING.read_text(), run, record, quick)
    return wanted


def render(record: Record | None = None, check: bool = False) -> list[Path]:
    """Write every file whose text differs from its render (and Table 1's figure); with
    ``check``, only say which differ. Returns the files that differed."""
    record = record or load()
    wanted = renders(record)
    stale = [p for p, text in wanted.items() if not p.exists() or p.read_text() != text]
    if check:
        for p in stale:
            print(
                f"{p.relative_to(ROOT)} differs from the render: run python -m e2e_lite.record.report"
            )
        return stale
    for p in stale:
        with atomic_write(p, "w") as f:
            f.write(wanted[p])
        print(f"wrote {p.relative_to(ROOT)}")
    save_figure(figure(record), FIGURE)
    print(f"wrote {FIGURE.relative_to(ROOT)}")
    return stale


def main(argv: Sequence[str] | None = None) -> int:
    """Render the committed record (``--check``: only compare)."""
    parser = argparse.ArgumentParser(prog="python -m e2e_lite.record.report", description=__doc__)
    parser.add_argument("--check", action="store_true", help="exit 1 if a file differs")
    args = parser.parse_args(argv)
    stale = render(check=args.check)
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
