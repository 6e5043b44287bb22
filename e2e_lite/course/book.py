"""The course as a book a class can read before it runs (``docs/book/``): one page per chapter
with its prose, its code, what each cell printed and the figures it saved, from the transcripts
of one full-profile run (:mod:`e2e_lite.course.transcript`), and an index with the chapter table, the
machine, the commit and the date of the run.

    python -m e2e_lite.course.book OUTPUTS      # OUTPUTS: the full run's outputs folder

Pages are Markdown a repository host shows as it is; figures are copied as PNGs scaled to at most
:data:`WIDTH_PX` wide, the whole kept under :data:`BUDGET_BYTES`. A page whose chapter source
changed since its run says so at its top.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import sys
from pathlib import Path
from typing import Any

from PIL import Image

from .estimate import cpu_name
from .run import CHAPTERS, TIMES_FILE, duration, find_chapters

ROOT = Path(__file__).resolve().parents[2]
BOOK = ROOT / "docs" / "book"
#: the widest a figure is shown [px], and the most the book's images may weigh [bytes]
WIDTH_PX, BUDGET_BYTES = 900, 15_000_000
#: a cell's printed output longer than this many lines is cut: its head and its tail are shown
HEAD_LINES, TAIL_LINES = 40, 10


def cut(output: str) -> str:
    """A cell's output, its middle cut (and said so) when it is long."""
    lines = output.rstrip("\n").splitlines()
    if len(lines) <= HEAD_LINES + TAIL_LINES:
        return "\n".join(lines)
    hidden = len(lines) - HEAD_LINES - TAIL_LINES
    return "\n".join([*lines[:HEAD_LINES], f"... ({hidden} lines cut) ...", *lines[-TAIL_LINES:]])


def shrink(png: Path, width_px: int = WIDTH_PX) -> bytes:
    """A figure as PNG bytes at most ``width_px`` wide, its colours quantised (the course's
    figures are line art: 256 colours lose nothing a reader sees)."""

    img = Image.open(png).convert("RGB")
    if img.width > width_px:
        img = img.resize((width_px, round(img.height * width_px / img.width)), Image.LANCZOS)
    buf = io.BytesIO()
    img.quantize(256).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


#: the line at the top of a page whose chapter changed since the book's run
CHANGED = (
    "> **This chapter's source has changed since this run**: the prose and code below are the"
    " run's, and may differ from the chapter's today."
)


def mark_changed(book: Path | None = None, chapters: Path | None = None) -> list[str]:
    """Give each committed page the :data:`CHANGED` line when its chapter differs today from
    the chapter at the commit the page names (read with ``git show``), and take it away when
    not: the book's run stays as it was, its pages say whether the code moved since. Returns
    the pages it changed."""
    import re
    import subprocess

    book, chapters = book or BOOK, chapters or ROOT / "chapters"
    changed = []
    for path in sorted(book.glob("[0-9][0-9]_*.md")):
        text = path.read_text()
        found = re.search(r"at commit `([0-9a-f]+)`", text)
        chapter = chapters / f"{path.stem}.py"
        if found is None or not chapter.exists():
            continue
        then = subprocess.run(
            ["git", "show", f"{found.group(1)}:chapters/{chapter.name}"],
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        if then.returncode != 0:
            continue  # (no history here: leave the page as it is)
        moved = then.stdout != chapter.read_text()
        marked = text.startswith(CHANGED)
        if moved and not marked:
            path.write_text(f"{CHANGED}\n\n{text}")
        elif marked and not moved:
            path.write_text(text[len(CHANGED) :].lstrip("\n"))
        else:
            continue
        changed.append(path.name)
    return changed


def page(
    transcript: dict[str, Any], source: str, figures: dict[str, str], outputs: str = ""
) -> str:
    """One chapter's page from its ``transcript``; ``source``: the chapter's current text (a
    page whose source changed since the run says so); ``figures``: each saved figure's path in
    the outputs and its file name in the book; ``outputs``: the run's outputs folder, shown in
    printed lines as ``outputs`` (the folder a reader's own run writes to)."""
    profile = "quick" if "--quick" in transcript.get("flags", []) else "full"
    lines = [
        f"*Rendered from the {profile}-profile run at commit `{transcript['commit']}` on"
        f" {transcript['date']} (the book's [index](README.md) names the machine). The code"
        f" is [chapters/{transcript['chapter']}.py](../../chapters/{transcript['chapter']}.py).*",
        "",
    ]
    if hashlib.sha256(source.encode()).hexdigest() != transcript["source_sha256"]:
        lines[:0] = [CHANGED, ""]
    for cell in transcript["cells"]:
        if cell["kind"] == "markdown":
            lines += [cell["text"], ""]
            continue
        lines += ["```python", cell["text"], "```", ""]
        output = cell.get("output", "")
        if outputs:
            root = outputs.rstrip("/")
            output = output.replace(root + "/", "outputs/").replace(root, "outputs/")
        if output.strip():
            lines += ["```text", cut(output), "```", ""]
        for fig in cell.get("figures", []):
            if fig in figures:
                lines += [f"![{Path(fig).stem}](figures/{figures[fig]})", ""]
    if transcript.get("exit_code"):
        lines += [f"*The run stopped here with exit code {transcript['exit_code']}.*", ""]
    return "\n".join(lines).rstrip() + "\n"


def render(outputs: Path, book: Path = BOOK, note: str = "") -> dict[str, Any]:
    """Write the book from the full run in ``outputs``: a page per transcript, its figures, the
    index (``note``: a line under the run's, for what the run's files cannot say). A chapter of
    the course with no transcript yet is listed as not in the run. Returns what it wrote: the
    chapters, the commit(s) and the images' bytes."""

    transcripts = sorted((outputs / "transcripts").glob("*.json"))
    if not transcripts:
        raise SystemExit(f"{outputs}/transcripts holds no transcript: run the full course first")
    (book / "figures").mkdir(parents=True, exist_ok=True)
    for old in (book / "figures").glob("*.png"):
        old.unlink()
    paths = dict(find_chapters(ROOT / "chapters"))
    times = (
        json.loads((outputs / TIMES_FILE).read_text()) if (outputs / TIMES_FILE).exists() else {}
    )
    rows, commits, image_bytes, total, dates = [], {}, 0, 0.0, []
    for path in transcripts:
        t = json.loads(path.read_text())
        dates.append(t["date"])
        figures = {}
        for cell in t["cells"]:
            for fig in cell.get("figures", []):
                name = f"{Path(fig).stem}.png"
                data = shrink(outputs / fig)
                (book / "figures" / name).write_bytes(data)
                image_bytes += len(data)
                figures[fig] = name
        number = int(t["chapter"][:2])
        source = paths[number].read_text() if number in paths else ""
        (book / f"{t['chapter']}.md").write_text(page(t, source, figures, str(outputs)))
        seconds = (times.get(t["chapter"]) or {}).get("seconds", 0.0)
        info = CHAPTERS.get(number)
        purpose = info.purpose if info else ""
        link = f"[{t['chapter'][3:].replace('_', ' ')}]({t['chapter']}.md)"
        rows.append(f"| {number:02d} | {link} | {purpose} | {duration(seconds)} |")
        commits.setdefault(t["commit"], []).append(f"{number:02d}")
        total += seconds
    for number in sorted(set(CHAPTERS) - {int(p.stem[:2]) for p in transcripts}):
        name = paths[number].stem[3:].replace("_", " ") if number in paths else ""
        rows.append(f"| {number:02d} | {name} | {CHAPTERS[number].purpose} | not in this run yet |")
    rows.sort(key=lambda row: row[2:4])
    if image_bytes > BUDGET_BYTES:
        raise SystemExit(f"the book's images weigh {image_bytes:,} bytes, over {BUDGET_BYTES:,}")
    date = max(dates)
    index = [
        "# The course as a book",
        "",
        "Every chapter's prose, code, printed output and figures from **one full-profile run**, so"
        " a class can read the course before (or instead of) running it, and a teaching assistant"
        " can check a student's run against it (another CPU trains other networks: compare the"
        " verdicts and their power, not the last digit). Rendered by `python -m e2e_lite.course.book`"
        " from the run's transcripts; do not edit by hand.",
        "",
        f"*The run: {date}, on {cpu_name()}, at {at_commits(commits)}; each chapter's time as"
        " that run took it.*",
        "",
        *([note, ""] if note else []),
        "| # | chapter | the idea | time |",
        "|---|---|---|---:|",
        *rows,
        f"| | **the course** | | {duration(total)} |",
        "",
    ]
    (book / "README.md").write_text("\n".join(index))
    return {"chapters": len(transcripts), "commits": sorted(commits), "image_bytes": image_bytes}


def at_commits(chapters: dict[str, list[str]]) -> str:
    """Which chapters ran at which commit: ``"commit `abc1234`"`` for one, else ``"commits
    `abc1234` (chapters 01-06) and `def5678` (07-12)"``."""
    if len(chapters) == 1:
        return f"commit `{next(iter(chapters))}`"
    parts = [
        f"`{c}` ({'chapters ' if k == 0 else ''}{', '.join(_ranges(ns))})"
        for k, (c, ns) in enumerate(sorted(chapters.items(), key=lambda kv: min(kv[1])))
    ]
    return "commits " + ", ".join(parts[:-1]) + " and " + parts[-1]


def _ranges(numbers: list[str]) -> list[str]:
    """``["01", "02", "03", "05"]`` -> ``["01-03", "05"]``."""
    out: list[list[int]] = []
    for n in sorted(int(x) for x in numbers):
        if out and n == out[-1][-1] + 1:
            out[-1].append(n)
        else:
            out.append([n])
    return [f"{r[0]:02d}-{r[-1]:02d}" if len(r) > 1 else f"{r[0]:02d}" for r in out]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m e2e_lite.course.book", description=__doc__)
    parser.add_argument(
        "outputs", type=Path, nargs="?", help="the full-profile run's outputs folder"
    )
    parser.add_argument("--note", default="", help="a line for the index, under the run's")
    parser.add_argument(
        "--mark-changed",
        action="store_true",
        help="only mark the pages whose chapter changed since the book's run (git)",
    )
    args = parser.parse_args(argv)
    if args.mark_changed:
        print(f"marked or unmarked: {', '.join(mark_changed()) or 'none'}")
        return 0
    if args.outputs is None:
        parser.error("give the run's outputs folder, or --mark-changed")
    wrote = render(args.outputs, note=args.note)
    print(f"wrote {BOOK.relative_to(ROOT)}: {wrote}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
