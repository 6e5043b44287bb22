"""The course reads as a course: each chapter within its line budget, short code cells and
summaries, and no result typed into prose (results are printed from a run's metrics)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CHAPTERS = sorted((ROOT / "chapters").glob("[0-9][0-9]_*.py"))
#: the most lines a chapter may have (issue 49); the chapters not named: 450
BUDGET = {"07": 500, "08": 400, "09": 450, "10": 400, "11": 600}
#: a typed collision count or rate: a number followed by "collision(s)" or "per 100 mi(les)"
TYPED_RATE = re.compile(r"\b\d[\d,]*(?:\.\d+)?\s*(?:collisions?\b|(?:per|/)\s*100\s*mi)", re.I)
#: a line that names the papers' figures (allowed: they are the papers', not ours)
PAPERS = re.compile(r"paper|seed 00[0-3]", re.I)


def cells(path: Path) -> list[tuple[str, str]]:
    """The percent-format cells of a chapter: ``(kind, text)``, kind "markdown" or "code"."""
    parts = re.split(r"^# %%", path.read_text(), flags=re.M)[1:]
    return [("markdown" if p.startswith(" [markdown]") else "code", p) for p in parts]


def typed_rates(markdown: str) -> list[str]:
    """The lines of a markdown cell that type a collision count or rate of ours."""
    return [ln for ln in markdown.splitlines() if TYPED_RATE.search(ln) and not PAPERS.search(ln)]


def test_the_scan_finds_a_typed_rate_and_spares_the_papers() -> None:
    assert typed_rates("# the GMM drove 12.7 per 100 mi on these roads")
    assert typed_rates("# with the module: 8 collisions against 21")
    assert not typed_rates("# the paper reports 12.7 per 100 miles")
    assert not typed_rates("# the rate is printed below, per 100 mi")


@pytest.mark.parametrize("path", CHAPTERS, ids=[p.stem for p in CHAPTERS])
def test_a_chapter_teaches_within_its_budget(path: Path) -> None:
    lines = len(path.read_text().splitlines())
    assert lines <= BUDGET.get(path.name[:2], 450), f"{path.name}: {lines} lines"
    long = [len(t.strip("\n").splitlines()) for k, t in cells(path) if k == "code"]
    assert max(long) <= 60, f"{path.name}: a code cell of {max(long)} lines"
    summary = re.search(r"^# ## Summary\n(.*?)(?=^# ## |\Z)", path.read_text(), re.M | re.S)
    assert summary, f"{path.name} has no Summary"
    bullets = len(re.findall(r"^# \* ", summary.group(1), flags=re.M))
    assert 1 <= bullets <= 8, f"{path.name}: {bullets} summary bullets"


@pytest.mark.parametrize("path", CHAPTERS, ids=[p.stem for p in CHAPTERS])
def test_no_chapter_types_a_collision_rate_into_its_prose(path: Path) -> None:
    typed = [ln for kind, text in cells(path) if kind == "markdown" for ln in typed_rates(text)]
    assert not typed, f"{path.name} types results the run prints:\n" + "\n".join(typed)
