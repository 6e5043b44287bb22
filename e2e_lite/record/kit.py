"""The teacher's kit's rendered blocks (``docs/teaching.md``): what each chapter printed in the
recorded full-profile course run (``docs/results/course_run.json``) and the minutes it took, what
a machine needs, and each session's findings: its chapters' headline figures beside the record's
verdicts on the steps it teaches. :mod:`e2e_lite.record.report` writes them with the README's tables.
"""

from __future__ import annotations

import re
from typing import Any

from ..course.run import CHAPTERS
from . import words
from .rows import Record
from .stats import StepResult, off_centre_steps, steps

RUN_BEGIN = "<!-- course run: rendered by python -m e2e_lite.record.report -->"
RUN_END = "<!-- /course run -->"
FINDINGS_BEGIN = "<!-- sessions' findings: rendered by python -m e2e_lite.record.report -->"
FINDINGS_END = "<!-- /sessions' findings -->"
NEEDS_BEGIN = "<!-- machine needs: rendered by python -m e2e_lite.record.report -->"
NEEDS_END = "<!-- /machine needs -->"
LIVE_BEGIN = "<!-- quick run: rendered by python -m e2e_lite.record.report -->"
LIVE_END = "<!-- /quick run -->"
#: each session's chapters and the record's steps it teaches (teaching.md's sessions)
SESSIONS = {
    1: (("01", "02", "03"), ()),
    2: (("04", "05"), ()),
    3: (("06", "07"), ("Baseline E2E -> trajectory GMM",)),
    4: (("08", "09"), ("GMM -> + affordance", "+ affordance -> + CVaR")),
    5: (
        ("10", "11"),
        ("CVaR against its control (the mean)", "affordance loss against its control (w = 0)"),
    ),
    6: (
        ("12",),
        (
            "+ CVaR -> + DAgger",
            "DAgger against its control (the expert's samples)",
            "DAgger's control against its fine-tunes on no new data",
            "DAgger against its fine-tunes on no new data",
        ),
    ),
}


def replace_block(text: str, begin: str, end: str, block: str) -> str:
    """``text`` with what lies between the lines ``begin`` and ``end`` replaced by ``block``."""
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise ValueError(f"the text has no block between {begin!r} and {end!r}")
    return pattern.sub(lambda _: f"{begin}\n{block}\n{end}", text)


def _figure(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.3g}" if abs(value) < 100 else f"{value:,.0f}"
    return str(value)


def course_run_table(run: dict[str, Any] | None, record: Record | None = None) -> str:
    """docs/teaching.md's table of what each chapter printed in a full-profile run, and (with
    ``record``) what the record of many seeds says of the same rows."""

    if run is None:
        return (
            "*No full-profile run is recorded yet: run `python -m e2e_lite.course`, then "
            "`python -m e2e_lite.record course-run outputs` to record it and "
            "`python -m e2e_lite.record.report` to render it.*"
        )
    lines = ["| chapter | minutes | what it printed (its headline figures) |", "|---|---:|---|"]
    for stem, ch in run["chapters"].items():
        figures = "; ".join(f"{k}: {_figure(v)}" for k, v in ch["headline"].items()) or "-"
        cut = "" if ch["complete"] else " (cut)"
        lines.append(f"| {stem} | {ch['minutes']:g}{cut} | {figures} |")
    done = [stem[:2] for stem, ch in run["chapters"].items() if ch["complete"]]
    total = sum(ch["minutes"] for ch in run["chapters"].values() if ch["complete"])
    if len(done) == len(CHAPTERS):
        what = f"The full course, {total:.0f} min"
    else:
        last = done[-1] if done else "-"
        what = (
            f"A run cut after chapter {last} (chapters {', '.join(done)} complete, {total:.0f} min)"
        )
    note = "; " + run["note"] if run.get("note") else ""
    lines += ["", f"*{what} on {run['machine']}, torch {run['torch']}{note}.*"]
    if record is not None:
        lines += ["", _one_run_against_the_record(record)]
    return "\n".join(lines)


def machine_needs_list(run: dict[str, Any] | None) -> str:
    """docs/teaching.md's list of what a machine needs, as the recorded course run measured it
    (only what was measured is said)."""
    if run is None:
        return "*No full-profile run is recorded yet.*"
    needs = run.get("needs", {})
    gb = {k: f"{v / 1e9:.2f} GB" for k, v in needs.items() if k.endswith("_bytes")}
    items = []
    if "download_bytes" in gb:
        items.append(
            f"**Download**: {gb['download_bytes']} of packages (torch's CPU wheel, the project "
            "and its test extras, as `pip download` fetched them)."
        )
    if "venv_bytes" in gb:
        items.append(f"**The venv** on disk: {gb['venv_bytes']}.")
    sizes = []
    if "outputs_bytes" in run:
        sizes.append(f"{run['outputs_bytes'] / 1e9:.2f} GB after the full course")
    if "quick_outputs_bytes" in gb:
        sizes.append(f"{gb['quick_outputs_bytes']} after the quick one")
    if sizes:
        items.append(f"**`outputs/`** on disk: {', '.join(sizes)}.")
    if "peak_memory_kib" in needs:
        items.append(
            f"**Memory**: the largest process in the run's GNU `time -v` reports (a "
            f"chapter or one of its workers) held {needs['peak_memory_kib'] / 2**20:.1f} GiB "
            "resident (docs/benchmarks.md says which chapters they cover)."
        )
    done = [ch for ch in run["chapters"].values() if ch["complete"]]
    minutes = sum(ch["minutes"] for ch in done)
    items.append(f"**Time**: {minutes:.0f} min for the {len(done)} chapters on {run['machine']}.")
    if "system" in needs:
        items.append(
            f"**Systems**: the course and its tests ran on {needs['system']}, Python "
            f"{needs['python']}; no other system is tested here."
        )
    return "\n".join(f"- {item}" for item in items)


def _one_run_against_the_record(record: Record) -> str:
    """What one course run's seed 0 is worth beside the record: each paper row's pooled rate of
    record and the verdicts of the controls, so a single run's "CVaR 2, control 5" is not read
    as a result."""
    keys = ("gmm_affordance", "gmm_affordance_cvar", "gmm_affordance_control")
    rows = [row for row in map(record.row, keys) if row]
    rates = ", ".join(f"{r.label} {r.pooled()[0]:.1f}" for r in rows)
    controls = "; ".join(
        f"{st.step}: {words.verdict(st)} (Holm p = {st.verdict_p:.2g})"
        for st in steps(record)
        if st.credits is not None
    )
    seeds = len(record.row("gmm").seeds)
    commit = _recipes(record)
    recipes = f"recipes {commit}; " if commit else ""
    return (
        "*One run: chapters 05-08 train each network on one seed; the learned rows of chapters"
        f" 09-12 pool chapter 10's few training seeds. The record ({recipes}{seeds} seeds per row,"
        " docs/results.md),"
        f" pooled per 100 mi: {rates}; {controls}.*"
    )


def _recipes(record: Record) -> str | None:
    """The commit of the recipes ``record`` drove, where it names one (a course run's chapters may
    be newer than the recipes the record drove)."""
    return record.block.recipes_commit if record.block else None


def _second(off: StepResult) -> str:
    """A step's off-centre verdict as a clause after its collisions' (``words.off_centre``)."""
    said = words.off_centre(off)
    return said if said.endswith("off-centre episodes") else f"off-centre episodes {said}"


def session_findings(run: dict[str, Any] | None, record: Record) -> str:
    """docs/teaching.md's list of what each session's full-profile run should show: the headline
    figures its chapters printed in the recorded course run, and the record's verdicts on the
    steps it teaches, on both outcomes (many seeds: what one student's seed is a draw from)."""
    tested = {st.step: st for st in steps(record)}
    off = {st.step: st for st in off_centre_steps(record)}
    commit = _recipes(record)
    the_record = f"The record (recipes {commit})" if commit else "The record"
    lines = []
    for session, (chapters, step_names) in SESSIONS.items():
        shown = []
        for stem, ch in (run or {}).get("chapters", {}).items():
            if stem[:2] in chapters:
                figures = list(ch["headline"].items())[:4]
                shown += [f"{k} {_figure(v)}" for k, v in figures]
        verdicts = [
            f"{name}: {words.cell(tested[name])}, ratio {tested[name].ratio:.2f}"
            + ("" if name not in off else f", {_second(off[name])}")
            + f" ({words.better_driver(tested[name], off.get(name))})"
            for name in step_names
            if name in tested
        ]
        run_text = "; ".join(shown) if shown else "no full-profile run recorded"
        record_text = f" {the_record}: {'; '.join(verdicts)}." if verdicts else ""
        lines.append(
            f"- **Session {session}** (chapters {', '.join(chapters)}). One run: {run_text}.{record_text}"
        )
    return "\n".join(lines)


def quick_run_lines(quick: dict[str, Any] | None) -> str:
    """docs/teaching.md's list of what each chapter prints in the quick profile (the headline
    figures of the recorded quick run): what a class sees live."""
    if quick is None:
        return (
            "*No quick run is recorded yet: run `python -m e2e_lite.course --quick`, then "
            "`python -m e2e_lite.record quick-run outputs/quick`.*"
        )
    lines = [
        f"- **{stem}**: " + ("; ".join(f"{k} {_figure(v)}" for k, v in figures.items()) or "-")
        for stem, figures in quick["chapters"].items()
    ]
    at = f" at commit {quick['commit']}" if quick.get("commit") else ""
    lines += [
        "",
        f"*The quick profile{at} on {quick['machine']}, torch {quick['torch']}: tiny data,"
        " networks trained for a few steps, a few miles each; it shows that every path runs, not"
        " how a method drives (another CPU prints other trained figures; the scripted drivers'"
        " and the expert's are the same everywhere).*",
    ]
    return "\n".join(lines)


def teaching_with(
    text: str, run: dict[str, Any] | None, record: Record, quick: dict[str, Any] | None = None
) -> str:
    """``docs/teaching.md``'s ``text`` with its rendered blocks made from ``run`` (the recorded
    course run, or None), ``record`` and ``quick`` (the recorded quick run, or None)."""
    text = replace_block(text, RUN_BEGIN, RUN_END, course_run_table(run, record))
    text = replace_block(text, FINDINGS_BEGIN, FINDINGS_END, session_findings(run, record))
    if LIVE_BEGIN in text:
        text = replace_block(text, LIVE_BEGIN, LIVE_END, quick_run_lines(quick))
    return replace_block(text, NEEDS_BEGIN, NEEDS_END, machine_needs_list(run))
