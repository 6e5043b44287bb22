"""The book: a chapter run cell by cell keeps each cell's output and figures, and the book's page
shows them, names its commit, and says when the chapter changed since its run."""

from __future__ import annotations

import json

from e2e_lite.course import book, transcript

CHAPTER = """# %% [markdown]
# # 99 · A test chapter
#
# It prints and saves a figure.

# %%
from e2e_lite import artifacts

print("hello from the first cell")

# %% [markdown]
# Then a long output.

# %%
from PIL import Image

for k in range(80):
    print(f"line {k}")
Image.new("RGB", (1200, 300), (200, 30, 30)).save(artifacts.artifact_path("figures", "99_t.png"))
"""


def test_a_chapter_runs_cell_by_cell_and_its_page_shows_each_cells_output(tmp_path, monkeypatch):
    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path / "out"))
    chapters = tmp_path / "chapters"
    chapters.mkdir()
    path = chapters / "99_test.py"
    path.write_text(CHAPTER)
    assert [kind for kind, _ in transcript.cells(CHAPTER)] == [
        "markdown",
        "code",
        "markdown",
        "code",
    ]
    assert transcript.run(path, []) == 0
    outputs = tmp_path / "out"
    t = json.loads((outputs / "transcripts" / "99_test.json").read_text())
    code = [c for c in t["cells"] if c["kind"] == "code"]
    assert code[0]["output"] == "hello from the first cell\n" and code[0]["figures"] == []
    assert code[1]["figures"] == ["figures/99_t.png"] and t["exit_code"] == 0
    page = book.page(t, CHAPTER, {"figures/99_t.png": "99_t.png"})
    assert f"`{t['commit']}`" in page and "hello from the first cell" in page
    assert "(30 lines cut)" in page and "line 79" in page and "line 45" not in page
    assert "![99_t](figures/99_t.png)" in page and "has changed since this run" not in page
    assert "has changed since this run" in book.page(t, CHAPTER + "\n# edited\n", {})
    data = book.shrink(outputs / "figures" / "99_t.png")
    from io import BytesIO

    from PIL import Image

    assert Image.open(BytesIO(data)).width == book.WIDTH_PX
    # an error stops the run there, its traceback kept
    path.write_text(CHAPTER.replace('print("hello', 'raise RuntimeError("boom")\nprint("hello'))
    assert transcript.run(path, []) == 1
    t = json.loads((outputs / "transcripts" / "99_test.json").read_text())
    assert "RuntimeError: boom" in t["cells"][1]["output"] and t["exit_code"] == 1


def test_the_index_says_which_chapters_ran_at_which_commit_and_times_read_as_times():
    """A run across commits names each commit with its chapters; a printed path into the run's
    outputs folder reads as the reader's own ``outputs``."""
    assert book.at_commits({"abc1234": ["01", "02"]}) == "commit `abc1234`"
    ran = {"def5678": ["07", "08", "10"], "abc1234": ["01", "02", "03", "05"]}
    assert (
        book.at_commits(ran) == "commits `abc1234` (chapters 01-03, 05) and `def5678` (07-08, 10)"
    )
    assert [book.duration(s) for s in (2.7, 1006.0, 7500.0)] == ["3 s", "16.8 min", "2 h 05 min"]
    t = {"chapter": "99_t", "commit": "abc1234", "date": "2026-11-29", "source_sha256": ""}
    printed = "outputs in /runs/x\nsaved /runs/x/figures/a.png\n"
    t["cells"] = [{"kind": "code", "text": "print(p)", "output": printed}]
    shown = book.page(t, "", {}, "/runs/x/")
    assert "outputs in outputs/\nsaved outputs/figures/a.png" in shown and "/runs" not in shown


def test_the_index_lists_a_chapter_not_yet_run_and_carries_a_note(tmp_path):
    """A run cut before its last chapter makes a book of the chapters it ran; the index lists
    the others as not in the run, and a note says what the run's files cannot."""
    from e2e_lite.course.run import CHAPTERS

    out = tmp_path / "out"
    (out / "transcripts").mkdir(parents=True)
    cell = {"kind": "code", "text": "print(1)", "output": "1\n"}
    t = {"chapter": "01_highway", "commit": "abc1234", "date": "2026-11-29"}
    t |= {"source_sha256": "", "cells": [cell], "exit_code": 0}
    (out / "transcripts" / "01_highway.json").write_text(json.dumps(t))
    wrote = book.render(out, tmp_path / "book", note="*A note.*")
    index = (tmp_path / "book" / "README.md").read_text()
    assert wrote["chapters"] == 1 and "*A note.*" in index
    rows = [r for r in index.splitlines() if r[:4].strip("| ").isdigit()]
    assert [r[2:4] for r in rows] == [f"{n:02d}" for n in sorted(CHAPTERS)]
    assert sum("not in this run yet" in r for r in rows) == len(CHAPTERS) - 1


def test_each_committed_page_says_whether_its_chapter_changed_since_the_books_run():
    """A page of docs/book/ carries the "source has changed" line exactly when its chapter today
    differs from the chapter at the commit the page names (``course.book --mark-changed``); a
    page whose commit this clone does not hold is not judged."""
    import re
    import subprocess

    for path in sorted(book.BOOK.glob("[0-9][0-9]_*.md")):
        text = path.read_text()
        commit = re.search(r"at commit `([0-9a-f]+)`", text).group(1)
        then = subprocess.run(
            ["git", "show", f"{commit}:chapters/{path.stem}.py"],
            capture_output=True,
            text=True,
            cwd=book.ROOT,
        )
        if then.returncode != 0:
            continue
        moved = then.stdout != (book.ROOT / "chapters" / f"{path.stem}.py").read_text()
        assert text.startswith(book.CHANGED) == moved, path.name
