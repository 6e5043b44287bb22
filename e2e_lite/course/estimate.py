"""How long a run should take on this machine: the parts the benchmarks measure (:class:`Work`),
their rates on the reference machine (:data:`RATES`, from docs/benchmarks.md), and the line a long
run prints first (:func:`plan_text`: the workers, the device, the precision and the estimate).
``python -m e2e_lite.course`` and ``python -m e2e_lite.record run`` print it.
"""

from __future__ import annotations

import platform
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

from ..config import WORKERS_ENV, Profile, available_cores, precision
from ..imitation.dagger import DaggerConfig
from ..imitation.recipes import SELECT_MILES


class Work(NamedTuple):
    """What a run does, in the parts ``python -m e2e_lite.course.bench`` measures (for estimates).

    Attributes:
        collect_samples: expert samples collected (chapter 04's data).
        train_samples: samples passed through training (samples x epochs, every network).
        drive_miles: closed-loop miles (evaluations and the selection drives).
        other_s: everything else, as timed on the reference machine [s].
    """

    collect_samples: float
    train_samples: float
    drive_miles: float
    other_s: float = 0.0


#: Per-part rates on the reference machine (the project's 2-core AMD EPYC, torch 2.13 on CPU;
#: docs/benchmarks.md, "Every core"): closed-loop miles per second of one worker process driving
#: chapter 10's 64 cars (``bench scaling``: 1.46, two workers 2.72 once started), expert samples
#: per second of one collecting process (1,177), training samples per second (about 600 on the
#: machine's threads; on a GPU, a lent H100's training loop in float32: 13,907), and the share of
#: the ideal speed-up each further worker adds (0.86 for the second here; 0.80-0.98 up to 16
#: workers on the lent H100's cores, which drive as fast as these).
RATES = {
    "drive_mi_per_s_per_worker": 1.46,
    "collect_samples_per_s_per_worker": 1_177.0,
    "train_samples_per_s": {"cpu": 600.0, "cuda": 14_000.0},
    "worker_efficiency": 0.86,
}


def estimate_s(work: Work, workers: int, device: str = "cpu") -> float:
    """Seconds ``work`` should take with ``workers`` worker processes and training on ``device``
    (``"cpu"`` or ``"cuda"``), from :data:`RATES`: each part's amount over its rate, the workers
    counted at :data:`RATES`' efficiency beyond the first, at most one per group of cars to share
    (the full profile's 64 cars in groups of 8 for driving, its 16 cars for collecting). An
    estimate: the networks, the roads' traffic and the machine's cores all move it."""

    def effective(most: int) -> float:
        return 1.0 + RATES["worker_efficiency"] * (min(max(1, workers), most) - 1)

    train_rate = RATES["train_samples_per_s"].get(device, RATES["train_samples_per_s"]["cpu"])
    return (
        work.collect_samples / (RATES["collect_samples_per_s_per_worker"] * effective(16))
        + work.drive_miles / (RATES["drive_mi_per_s_per_worker"] * effective(8))
        + work.train_samples / train_rate
        + work.other_s
    )


def scaled_estimate_s(reference_s: float, work: Work, workers: int, device: str = "cpu") -> float:
    """A run measured at ``reference_s`` on the reference machine (2 workers, CPU), on this one:
    the parts of ``work`` are timed with :data:`RATES` at 2 workers and at ``workers`` on
    ``device``, and the measured time is scaled by their ratio (the rates set the shares, the
    measurement the scale)."""
    return reference_s * estimate_s(work, workers, device) / estimate_s(work, 2, "cpu")


def plan_text(
    what: str, work: Work, workers: int, device: str, reference_s: float | None = None
) -> str:
    """The line a long run prints first: the workers and device it will use, and its estimate
    (from :data:`RATES`, or scaled from ``reference_s`` measured on the reference machine)."""

    seconds = (
        estimate_s(work, workers, device)
        if reference_s is None
        else scaled_estimate_s(reference_s, work, workers, device)
    )
    minutes = seconds / 60.0
    return (
        f"{what}: {workers} worker processes ({available_cores()} cores; {WORKERS_ENV} to change),"
        f" training on {device} in {precision()}; estimate about {minutes:.0f} min "
        f"({work.drive_miles:,.0f} mi driven, {work.train_samples / 1e6:.1f} M training samples,"
        f" {work.collect_samples:,.0f} samples collected; docs/benchmarks.md's rates)"
    )


def chapter_work(profile: Profile) -> dict[int, Work]:
    """What each chapter does from the outputs of the chapters before it, in :class:`Work`'s
    parts (counted from the chapters): chapter 04's data and its two ceilings' drives; chapters
    05-08's networks (05: three, 07: two), chapter 08's weight grid; chapters 09-10's further
    seeds (09: + affordance, 10: the Baseline E2E and the GMM; PilotNet and L2 keep seed 0; the
    w = 0 control is the record's) and chapter 09's fine-tunes; chapter 12's anatomy and DAgger's
    three arms (collections, fine-tunes, every iterate on validation roads); every evaluation and
    selection drive.
    Chapters 01-03, the figures and the replays are ``other_s`` (about 300 s in all)."""

    s, n, epochs = profile.ablation_seeds, profile.n_train_samples, profile.train_epochs
    select = epochs * SELECT_MILES if epochs > 1 else 0.0  # the selection drives of a training
    ev, rows = profile.eval_miles, profile.ablation_miles  # one evaluation, one ablation row
    other = 31.0  # a chapter's figures, replays and imports [s]

    def trains(scratch: int, evaluations: float, tuned: int = 0, grid: float = 0.0) -> Work:
        return Work(
            0.0, n * (scratch * epochs + tuned) + grid, scratch * select + evaluations, other
        )

    dagger = DaggerConfig.for_profile(profile)
    driven = dagger.rounds * dagger.samples * (2 * dagger.drive + 0.25)  # two arms, DART's pilot
    collected = s * driven  # every seed
    return {
        1: Work(0.0, 0.0, 0.0, 10.0),
        2: Work(0.0, 0.0, 0.0, 5.0),
        3: Work(0.0, 0.0, 0.0, 5.0),
        4: Work(profile.n_train_samples + profile.n_val_samples, 0.0, 2 * ev, other),
        5: trains(3, 3 * ev),
        6: trains(1, ev),
        7: trains(2, 2 * ev),
        8: trains(1, ev, grid=5 * 2 * n / 4),  # 5 weights, 2 epochs, a quarter of the data
        9: trains(s - 1, 3 * rows, tuned=2 * s),  # the CVaR fine-tune and its control
        10: trains(2 * (s - 1), 2 * rows + 4 * ev),  # + the ceilings, PilotNet and L2
        11: trains(0, 3 * rows),  # three variants of the safety module
        # the anatomy's drive, the labeller's two drives (the expert, the oracle); validation:
        # the start and every round of the three arms; test: four rows; the fine-tunes draw
        # steps_samples per round and arm
        12: Work(
            collected,
            s * 3 * dagger.rounds * dagger.steps_samples,
            s * (1.5 * ev + (1 + 3 * dagger.rounds) * dagger.val_miles) + 0.3 * ev + 4 * rows,
            other,
        ),
    }


def course_work(profile: Profile, chapters: Sequence[int] | None = None) -> Work:
    """What the full course (or its ``chapters``) does from an empty outputs folder: the sum of
    :func:`chapter_work` over them."""
    each = chapter_work(profile)
    parts = [each[k] for k in (each if chapters is None else chapters) if k in each]
    return Work(*(sum(w[i] for w in parts) for i in range(len(Work._fields))))


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what ``platform`` says), for records."""

    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    return next(
        (ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
        platform.processor() or platform.machine(),
    )
