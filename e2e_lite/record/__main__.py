"""``python -m e2e_lite.record``: run a share of the record, pool shares, plan the record, or
record a course run (see :mod:`e2e_lite.record`). Rendering is ``python -m e2e_lite.record.report``'s."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

import e2e_lite.record

from ..artifacts import atomic_write, outputs_dir
from ..config import FULL, QUICK
from . import COURSE_RUN, QUICK_RUN, RECORD, ROOT, report
from .course_run import course_run_record, quick_run_record
from .pool import ShareRefused, pool
from .rows import Record, Share, dump, load_record
from .run import FRESH_SEEDS_FROM, low_rate_row, parse_seeds, plan, plan_lines, record_share


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m e2e_lite.record",
        description=e2e_lite.record.__doc__.split("\n\n")[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    jobs = parser.add_subparsers(dest="job", required=True, metavar="JOB")
    run = jobs.add_parser(
        "run",
        help="train and drive every row for some training seeds (hours in the full profile; stop "
        "and run again to go on: trainings and drives are stored)",
    )
    run.add_argument(
        "--seeds",
        required=True,
        metavar="N|A-B",
        help="N: training seeds 0 .. N-1, pooled here (the quick smoke run); A-B: one share of "
        "the record, written to <outputs>/shares/ for the pool (the full profile: seeds from "
        f"{FRESH_SEEDS_FROM})",
    )
    run.add_argument(
        "--miles",
        type=float,
        default=150.0,
        help="test-road miles per seed (the record of 7a36b30: 150; that of 28eba5c drove 200)",
    )
    run.add_argument(
        "--quick",
        action="store_true",
        help="the quick profile (a smoke test on open roads, written to the outputs folder, "
        "never to docs/)",
    )
    pool = jobs.add_parser(
        "pool",
        help="pool shares (from run --seeds A-B, on any machines) into docs/results/table1.json "
        "and render it; a share that does not belong is refused, naming its file",
    )
    pool.add_argument("shares", nargs="+", type=Path, metavar="SHARE")
    jobs.add_parser(
        "plan",
        help="the seeds and miles per seed that find a 2x step with power 0.8 under the "
        "committed record's seed spread, and what each costs",
    )
    course = jobs.add_parser(
        "course-run",
        help="record what a full-profile course run printed (docs/results/course_run.json, "
        "rendered into docs/teaching.md)",
    )
    quick = jobs.add_parser(
        "quick-run",
        help="record what a quick-profile course run printed (docs/results/quick_run.json, "
        "rendered into docs/teaching.md: what a class sees live)",
    )
    quick.add_argument("outputs", type=Path, metavar="OUTPUTS")
    course.add_argument("outputs", type=Path, metavar="OUTPUTS")
    course.add_argument("--time-log", type=Path, help="the run's '/usr/bin/time -v' output")
    course.add_argument("--quick-outputs", type=Path, help="a quick course run's outputs folder")
    course.add_argument("--venv", type=Path, help="the venv the run used")
    course.add_argument(
        "--downloads", type=Path, help="a folder of what 'pip download' fetched for the install"
    )
    return parser


def _write_record(record: Record, quick: bool) -> int:
    """Write a pooled record: the record of record (rendered), or a quick smoke test's (printed,
    never written to docs/)."""

    path = outputs_dir(quick=True) / "table1.json" if quick else RECORD
    with atomic_write(path, "w") as f:
        f.write(dump(record))
    print(f"wrote {path}")
    if quick:
        print(report.table1(record))
    else:
        report.render(record)
    return 0


def _run(seeds_text: str, miles: float, quick: bool) -> int:
    profile = QUICK if quick else FULL
    seeds = parse_seeds(seeds_text)
    share = record_share(profile, seeds, miles)
    if "-" not in seeds_text:  # the whole record on this machine: pooled at once
        return _write_record(pool([("this run", share)]), quick)
    path = outputs_dir(quick=quick) / "shares" / f"share-seeds-{seeds[0]}-{seeds[-1]}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        f.write(dump(share))
    print(f"wrote {path}: pool it with python -m e2e_lite.record pool SHARE...")
    return 0


def _pool(files: Sequence[Path]) -> int:
    shares = [(p.name, Share.from_json(json.loads(p.read_text()))) for p in files]
    try:
        record = pool(shares)
    except ShareRefused as err:
        print(err, file=sys.stderr)
        return 2
    return _write_record(record, quick=shares[0][1].profile == QUICK.name)


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.job == "run":
        return _run(args.seeds, args.miles, args.quick)
    if args.job == "pool":
        return _pool(args.shares)
    if args.job == "plan":
        record = load_record(RECORD)
        for row in (None, low_rate_row(record)):
            print("\n".join(plan_lines(plan(record, row=row))))
        return 0

    if args.job == "quick-run":
        with atomic_write(QUICK_RUN, "w") as f:
            json.dump(quick_run_record(args.outputs, ROOT), f, indent=1)
        print(
            f"wrote {QUICK_RUN.relative_to(ROOT)}: render it with python -m e2e_lite.record.report"
        )
        return 0
    with atomic_write(COURSE_RUN, "w") as f:
        needs = {k: getattr(args, k) for k in ("time_log", "quick_outputs", "venv", "downloads")}
        json.dump(course_run_record(args.outputs, **needs), f, indent=1)
    print(f"wrote {COURSE_RUN.relative_to(ROOT)}: render it with python -m e2e_lite.record.report")
    return 0


if __name__ == "__main__":
    sys.exit(main())
