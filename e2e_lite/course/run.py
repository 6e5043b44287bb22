"""Run the course: every chapter script in order.

    python -m e2e_lite.course [--quick] [--only N ...] [--from N] [--chapters DIR]
                              [--processes auto|one|each]

The full profile runs each chapter in its own process with plain ``python`` (long work,
isolated); the quick profile runs them all in this one (``runpy``), so torch's and the other
imports are paid once instead of eleven times.

Shows which chapter runs and how long each took, stops at the first failure (the chapter's own
error is on screen above the message), and ends with a table of each chapter's headline figures,
read from ``<outputs>/metrics/<chapter>.json`` (the ``"headline"`` entry each chapter writes).

Each chapter's wall time is also kept in ``<outputs>/course_times.json`` (:class:`ChapterClock`),
across runs: a chapter cut short (a closed lid, a lost session, a failure) keeps the seconds it
had spent, and its next run adds to them, so a full course resumed with ``--from N`` over several
sittings still ends with its true total ("The whole course in this outputs folder took ...").

Each chapter starts with :func:`start_chapter`: it reads the chapter's flags (``--quick``,
``--help``; anything else stops with one line and exit code 2), picks the profile, checks that
the outputs folder can be written, and says what the quick profile's numbers are.
"""

from __future__ import annotations

import argparse
import gc
import os
import re
import runpy
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from types import TracebackType
from typing import Any, NamedTuple, NoReturn

from ..artifacts import (
    check_outputs_writable,
    load_json,
    outputs_dir,
    read_metrics,
    remove_stale_temporaries,
    save_json,
)
from ..config import (
    FULL,
    QUICK_ENV,
    Profile,
    active_profile,
    default_workers,
    in_notebook,
    quick_requested,
)

_REPO_ROOT = Path(__file__).resolve().parents[2]
_CHAPTER_RE = re.compile(r"^(\d{2})_[a-z0-9_]+\.py$")


class ChapterInfo(NamedTuple):
    """What ``--help`` and the README say about a chapter: its idea, where the paper has it, and
    its time on 2 CPU cores (``docs/benchmarks.md`` says how each was measured: the quick times
    on a 2-core AMD EPYC at cece423, the full ones the book's run on a 2-core Intel Xeon).

    Attributes:
        purpose: one line.
        paper: where the papers have it (seed 000 unless named), or "" for the course's own.
        quick_s: the quick profile, the chapter in its own process (imports included) after the
            chapters before it, from an empty outputs folder (``course --quick --processes each``)
            [s].
        full_s: the full profile, building everything it needs that earlier chapters did not
            [s] (the book's run: docs/book/README.md gives the same times).
    """

    purpose: str
    paper: str
    quick_s: int
    full_s: float


#: ``python -m e2e_lite.course --quick``, every chapter in one interpreter from an empty outputs
#: folder, on 2 cores with nothing else running [s] (``docs/benchmarks.md``)
QUICK_COURSE_S = 43
CHAPTERS: dict[int, ChapterInfo] = {
    1: ChapterInfo("the highway world, its lane frame and two scripted drivers", "4.1", 1, 6.7),
    2: ChapterInfo("the rasterised front camera the networks see", "4.1", 1, 1.3),
    3: ChapterInfo(
        "LQR tracking: following a trajectory with steering and acceleration", "3.1", 2, 3.6
    ),
    4: ChapterInfo("the rule-based expert and the driving dataset", "4.1", 6, 172.1),
    5: ChapterInfo("the PilotNet baselines: camera to actuators", "seeds 002, 003", 7, 735.6),
    6: ChapterInfo("trajectory regression with an L2 loss and LQR", "3.2", 5, 235.1),
    7: ChapterInfo("the Gaussian-mixture trajectory loss and what it changes", "3.3", 7, 482.1),
    8: ChapterInfo("the affordance auxiliary loss", "3.5", 8, 434.9),
    9: ChapterInfo("CVaR fine-tuning on the loss tail", "3.4", 8, 1395.5),
    10: ChapterInfo("the ablation: the paper's Table 1 in closed loop", "4.2", 9, 1402.5),
    11: ChapterInfo("a safety module that checks the proposed trajectory", "3.1, Fig. 1", 6, 517.1),
    12: ChapterInfo("where the last collisions come from, and DAgger aimed there", "", 18, 2787.6),
}


def duration(seconds: float) -> str:
    """``"3 s"`` under a minute, ``"16.8 min"`` under an hour, else ``"2 h 05 min"``."""
    if seconds < 60.0:
        return f"{seconds:.0f} s"
    if seconds < 3600.0:
        return f"{seconds / 60.0:.1f} min"
    hours, minutes = divmod(round(seconds / 60.0), 60)
    return f"{hours} h {minutes:02d} min"


class _ChapterParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``prog: error: ...``) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def start_chapter(number: int, argv: Sequence[str] | None = None) -> Profile:
    """What every chapter does first; returns the profile it runs under.

    As a script: parses ``argv`` (default ``sys.argv[1:]``). ``--quick`` picks the quick profile,
    ``--help`` prints the chapter's purpose and measured times and exits, anything else exits
    with one line and code 2 (a typo must not start hours of full-profile work). In a notebook
    the kernel's arguments are ignored; set ``%env E2E_LITE_QUICK=1`` in the first cell for the
    quick profile. A bad ``E2E_LITE_QUICK`` or an outputs folder that cannot be written stops
    here, with one line (exit code 2 in a script, an error in a notebook), before any work.
    """
    info = CHAPTERS[number]
    notebook = in_notebook()
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else f"chapter {number:02d}"
    if not notebook:
        parser = _ChapterParser(
            prog=prog,
            description=f"Chapter {number:02d}: {info.purpose}.",
            epilog=(
                f"Measured on 2 CPU cores: about {info.quick_s} s with --quick, about "
                f"{duration(info.full_s)} in the full profile (earlier chapters' artifacts reused)."
            ),
            allow_abbrev=False,
        )
        parser.add_argument(
            "--quick",
            action="store_true",
            help="the quick profile: a smoke test in seconds (tiny data, untrained networks)",
        )
        parser.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        profile = active_profile(argv=[] if notebook else argv)
        root = check_outputs_writable()
    except (ValueError, OSError) as err:
        if notebook:
            raise RuntimeError(str(err)) from None
        print(f"{prog}: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    print(f"Chapter {number:02d}, {profile.name} profile; outputs in {root}")
    if not notebook:
        sys.excepthook = _interrupted_in_one_line(sys.excepthook, prog)
    remove_stale_temporaries(root)  # what a killed run's writes left behind
    if profile.quick:
        print(profile.caveat.strip())
    return profile


def _interrupted_in_one_line(hook: Any, prog: str) -> Any:
    """``hook`` (``sys.excepthook``), except that Ctrl-C prints one line instead of a traceback:
    what the chapter stored is kept, and running it again resumes from there."""

    def excepthook(kind: type[BaseException], value: BaseException, tb: Any) -> None:
        if issubclass(kind, KeyboardInterrupt):
            print(
                f"{prog}: interrupted; what it stored is kept, run it again to go on",
                file=sys.stderr,
            )
            return
        hook(kind, value, tb)

    return excepthook


def find_chapters(directory: Path | None = None) -> list[tuple[int, Path]]:
    """``(number, path)`` of every ``NN_name.py`` chapter, in order.

    The folder is ``directory``, else ``./chapters`` if it exists, else the source checkout's.
    """
    if directory is None:
        directory = Path.cwd() / "chapters"
        if not directory.is_dir():
            directory = _REPO_ROOT / "chapters"
    if not directory.is_dir():
        raise FileNotFoundError(f"no chapters folder at {directory}; pass --chapters DIR")
    found = []
    for path in sorted(directory.iterdir()):
        m = _CHAPTER_RE.match(path.name)
        if m:
            found.append((int(m.group(1)), path))
    return found


def select(
    chapters: list[tuple[int, Path]], only: list[int] | None, start: int | None
) -> list[tuple[int, Path]]:
    """Filter chapters by ``--only`` numbers or a ``--from`` number; unknown numbers raise."""
    known = {n for n, _ in chapters}
    for n in (only or []) + ([start] if start is not None else []):
        if n not in known:
            raise ValueError(f"chapter {n} does not exist; chapters are {sorted(known)}")
    if only:
        return [(n, p) for n, p in chapters if n in set(only)]
    if start is not None:
        return [(n, p) for n, p in chapters if n >= start]
    return chapters


def _format_value(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    return str(value)


def summary_table(rows: list[tuple[str, float, dict | None]]) -> str:
    """A markdown table: chapter, seconds, headline figures."""
    lines = ["| chapter | time [s] | headline |", "|---|---:|---|"]
    for name, seconds, metrics in rows:
        head = (metrics or {}).get("headline") or {}
        text = "; ".join(f"{k}: {_format_value(v)}" for k, v in head.items()) or "(no metrics)"
        lines.append(f"| {name} | {seconds:.1f} | {text} |")
    return "\n".join(lines)


TIMES_FILE = "course_times.json"


def read_times(path: Path) -> dict[str, dict[str, Any]]:
    """The ledger's entries by chapter (``{}`` when there is none or it is unreadable): each has
    ``seconds`` (wall time [s], over every run that counted), ``complete`` (its last run ended
    without error), ``runs`` (how many runs counted) and ``updated`` (UTC, ISO 8601)."""
    try:
        times = load_json(path)
    except (OSError, ValueError):
        return {}
    return times if isinstance(times, dict) else {}


class ChapterClock:
    """Times one chapter into the ledger at ``path``, as a ``with`` block.

    A chapter whose last run did not complete starts from the seconds that run had spent (its next
    run reuses what the cut one stored, so only the two together are what it cost); a chapter
    that had completed starts from zero (its entry is replaced). While the block runs, a thread
    writes the elapsed time every ``heartbeat_s`` seconds, so a run killed without warning loses
    at most that much. The block's end writes the total and marks the entry complete unless the
    block raised or :meth:`failed` was called.
    """

    def __init__(self, path: Path, chapter: str, heartbeat_s: float = 10.0) -> None:
        self.path, self.chapter, self.heartbeat_s = path, chapter, heartbeat_s
        prior = read_times(path).get(chapter) or {}
        resumed = prior.get("complete") is False
        self.carried = float(prior.get("seconds", 0.0)) if resumed else 0.0
        self.runs = int(prior.get("runs", 0)) + 1 if resumed else 1
        self._ok = True
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._beat, daemon=True)
        self._t0 = 0.0

    def elapsed(self) -> float:
        """Seconds spent on the chapter so far, carried-over runs included [s]."""
        return self.carried + time.perf_counter() - self._t0

    def failed(self) -> None:
        """Mark this run as not complete (the chapter exited with an error code)."""
        self._ok = False

    def _write(self, complete: bool) -> None:
        with self._lock:  # the heartbeat and the block's end write the same file
            times = read_times(self.path)
            times[self.chapter] = {
                "seconds": round(self.elapsed(), 1),
                "complete": complete,
                "runs": self.runs,
                "updated": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            }
            save_json(self.path, times)

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            self._write(complete=False)

    def __enter__(self) -> ChapterClock:
        self._t0 = time.perf_counter()
        self._write(complete=False)
        self._thread.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stop.set()
        self._thread.join()
        self._write(complete=self._ok and exc_type is None)


def course_total(times: dict[str, dict[str, Any]], chapters: Sequence[str]) -> float | None:
    """The whole course's recorded time [s]: the sum over ``chapters``, or ``None`` while any of
    them has no complete entry."""
    if not all((times.get(c) or {}).get("complete") for c in chapters):
        return None
    return sum(float(times[c]["seconds"]) for c in chapters)


def run_in_process(path: Path, flags: list[str], env: dict[str, str]) -> int:
    """Run a chapter script in this interpreter (``runpy``, as ``__main__``, from the repository
    root, with ``flags`` as its arguments and ``env`` as the environment); returns its exit code
    (1 after printing the traceback of an error). The interpreter's imports (torch and its
    compiler, python-control, matplotlib: several seconds) are then paid once for the course."""
    saved_argv, saved_cwd, saved_env = sys.argv, os.getcwd(), dict(os.environ)
    sys.argv = [str(path), *flags]
    os.environ.clear()
    os.environ.update(env)
    os.chdir(path.parent.parent)
    try:
        runpy.run_path(str(path), run_name="__main__")
        return 0
    except SystemExit as exit_:  # as the interpreter would: a message goes to stderr, code 1
        if exit_.code is None or isinstance(exit_.code, int):
            return exit_.code or 0
        print(exit_.code, file=sys.stderr)
        return 1
    except Exception:
        traceback.print_exc()
        return 1
    finally:
        sys.argv = saved_argv
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        gc.collect()


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = argparse.ArgumentParser(
        prog="python -m e2e_lite.course", description=__doc__.split("\n")[0]
    )
    parser.add_argument(
        "--quick", action="store_true", help="the quick profile (seconds per chapter)"
    )
    parser.add_argument("--only", type=int, nargs="+", metavar="N", help="run only these chapters")
    parser.add_argument("--from", dest="start", type=int, metavar="N", help="start at chapter N")
    parser.add_argument("--chapters", type=Path, help="the chapters folder")
    parser.add_argument(
        "--processes",
        choices=("auto", "one", "each"),
        default="auto",
        help="run the chapters in this one process (imports paid once) or each in its own; "
        "auto: one for --quick, each otherwise",
    )
    args = parser.parse_args(argv)
    quick = args.quick or quick_requested([])
    in_process = args.processes == "one" or (args.processes == "auto" and quick)
    try:
        found = find_chapters(args.chapters)
        chapters = select(found, args.only, args.start)
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    env = dict(os.environ)
    if quick:
        env[QUICK_ENV] = "1"
    profile = "quick" if quick else "full"
    print(f"e2e-lite course: {len(chapters)} chapters, {profile} profile", flush=True)
    if not quick:
        from ..learning.models import pick_device  # (here: a chapter imports this module first,
        from .estimate import course_work, plan_text  # (to check its flags before torch loads)

        reference_s = sum(CHAPTERS[n].full_s for n, _ in chapters)
        work = course_work(FULL, [n for n, _ in chapters])
        line = plan_text("the course", work, default_workers(), pick_device().type, reference_s)
        print(line, flush=True)
    ledger = (outputs_dir(quick) / TIMES_FILE).resolve()  # (in-process chapters change the cwd)
    try:
        return _run(chapters, found, quick, in_process, env, profile, ledger)
    except KeyboardInterrupt:
        print(
            "\ninterrupted: what the chapters stored is kept; `python -m e2e_lite.course --from NN`"
            " goes on from chapter NN",
            file=sys.stderr,
            flush=True,
        )
        return 130


def _run(
    chapters: list[tuple[int, Path]],
    found: list[tuple[int, Path]],
    quick: bool,
    in_process: bool,
    env: dict[str, str],
    profile: str,
    ledger: Path,
) -> int:
    """Run ``chapters`` in order (see :func:`main`); returns the exit code."""
    rows: list[tuple[str, float, dict | None]] = []
    t_course = time.perf_counter()
    for k, (_, path) in enumerate(chapters, 1):
        print(f"\n==> [{k}/{len(chapters)}] {path.stem}", flush=True)
        flags = ["--quick"] if quick else []
        with ChapterClock(ledger, path.stem) as clock:
            if clock.carried:
                print(
                    f"(resuming: its earlier run was cut after {clock.carried:.1f} s; "
                    f"{ledger} adds them)",
                    flush=True,
                )
            if in_process:
                code = run_in_process(path, flags, env)
            else:
                # cell by cell, its transcript kept for the book (e2e_lite.course.transcript)
                run = [sys.executable, "-m", "e2e_lite.course.transcript", str(path), *flags]
                code = subprocess.run(run, env=env, cwd=path.parent.parent).returncode
            if code != 0:
                clock.failed()
        seconds = clock.elapsed() - clock.carried  # (this run's own)
        if code != 0:
            print(
                f"\n!! {path.stem} failed (exit code {code}) after {seconds:.1f} s; "
                f"its error is above. Fix it, then resume with --from {path.stem[:2]}",
                file=sys.stderr,
                flush=True,
            )
            return code
        print(f"<== {path.stem} done in {seconds:.1f} s", flush=True)
        rows.append((path.stem, seconds, read_metrics(path.stem)))
    print(
        f"\n{'The chapter' if len(rows) == 1 else f'All {len(rows)} chapters'} passed in "
        f"{time.perf_counter() - t_course:.1f} s "
        f"({profile} profile).\n"
    )
    print(summary_table(rows))
    total = course_total(read_times(ledger), [p.stem for _, p in found])
    if total is not None:
        print(
            f"\nThe whole course in this outputs folder took {total:.0f} s ({total / 3600:.2f} h): "
            f"each chapter's last complete run, with the time of the runs cut before it "
            f"(per chapter in {ledger})."
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
