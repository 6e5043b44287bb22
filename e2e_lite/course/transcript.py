"""A chapter run cell by cell, with a transcript: each cell's source, what it printed and the
figures it saved, written to ``<outputs>/transcripts/<chapter>.json`` (the book, ``python -m
e2e_lite.course.book``, renders them). The course's full profile runs every chapter this way
(``python -m e2e_lite.course.transcript chapters/NN_name.py``); the cells share one namespace, as the
script's top-level code does, so a chapter runs the same as with plain ``python``.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from ..artifacts import atomic_write, code_commit, outputs_dir

#: a cell's first line: ``# %%`` (code) or ``# %% [markdown]`` (prose)
CELL = re.compile(r"^# %%( \[markdown\])?\s*$", re.M)


def cells(source: str) -> list[tuple[str, str]]:
    """A percent-format script as ``[(kind, text), ...]``: ``"markdown"`` cells with the comment
    marks taken off, ``"code"`` cells as they are (blank lines at their ends trimmed); a script
    without cell marks is one code cell."""
    marks = list(CELL.finditer(source))
    if not marks:
        return [("code", source.strip("\n"))] if source.strip() else []
    out = []
    for k, m in enumerate(marks):
        end = marks[k + 1].start() if k + 1 < len(marks) else len(source)
        body = source[m.end() + 1 : end].strip("\n")
        if m.group(1):
            text = "\n".join(re.sub(r"^# ?", "", ln) for ln in body.splitlines())
            out.append(("markdown", text))
        elif body.strip():
            out.append(("code", body))
    return out


class _Tee(io.TextIOBase):
    """Writes to the real stream and keeps a copy."""

    def __init__(self, stream: Any) -> None:
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text: str) -> int:
        self.stream.write(text)
        self.copy.write(text)
        return len(text)

    def flush(self) -> None:
        self.stream.flush()


def _figures(root: Path) -> dict[str, float]:
    """Every picture under ``root/figures`` and its modification time."""
    folder = root / "figures"
    if not folder.exists():
        return {}
    return {str(p.relative_to(root)): p.stat().st_mtime for p in folder.rglob("*.png")}


def run(path: Path, flags: list[str]) -> int:
    """Run chapter ``path`` cell by cell as ``__main__`` with ``flags`` as its arguments, and
    write its transcript; returns the exit code (1 after an error, whose traceback is printed
    and kept in the transcript)."""

    source = path.read_text()
    sys.argv = [str(path), *flags]
    namespace: dict[str, Any] = {"__name__": "__main__", "__file__": str(path)}
    record: list[dict[str, Any]] = []
    code = 0
    root = None
    for kind, text in cells(source):
        if kind == "markdown":
            record.append({"kind": kind, "text": text})
            continue
        root = outputs_dir()
        before = _figures(root)
        tee, saved = _Tee(sys.stdout), sys.stdout
        sys.stdout = tee
        t0 = time.perf_counter()
        try:
            exec(compile(text, str(path), "exec"), namespace)
        except SystemExit as exit_:  # as the interpreter would: a message goes to stderr, code 1
            code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
            if exit_.code is not None and not isinstance(exit_.code, int):
                print(exit_.code, file=sys.stderr)
        except Exception:
            traceback.print_exc(file=tee)
            code = 1
        finally:
            sys.stdout = saved
        after = _figures(root)
        new = sorted(p for p, t in after.items() if before.get(p) != t)
        cell = {"kind": kind, "text": text, "output": tee.copy.getvalue(), "figures": new}
        record.append({**cell, "seconds": round(time.perf_counter() - t0, 1)})
        if code:
            break
    root = root or outputs_dir()
    repo = path.resolve().parent.parent
    transcript = {
        "chapter": path.stem,
        "commit": code_commit(repo),
        "source_sha256": hashlib.sha256(source.encode()).hexdigest(),
        "flags": flags,
        "exit_code": code,
        "date": time.strftime("%Y-%m-%d"),
        "cells": record,
    }
    out = root / "transcripts" / f"{path.stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out, "w") as f:
        json.dump(transcript, f, indent=1)
    return code


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: python -m e2e_lite.course.transcript chapters/NN_name.py [--quick]")
    sys.exit(run(Path(sys.argv[1]), sys.argv[2:]))
