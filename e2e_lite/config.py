"""Profiles (quick / full) and the validation helper every settings dataclass uses.

One place decides the active profile: :func:`active_profile`. The quick profile is on when the
environment variable ``E2E_LITE_QUICK`` is ``1`` (or ``true``/``yes``) or when the running
script was given ``--quick``. Chapters ask this module; they never read the switch themselves.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm.std import tqdm as text_tqdm

QUICK_ENV = "E2E_LITE_QUICK"
QUICK_FLAG = "--quick"
#: how many worker processes drive and collect (default: every core this process may use)
WORKERS_ENV = "E2E_LITE_WORKERS"
#: ``1`` lets a GPU's convolutions and matrix products run in TF32 (off by default: fp32)
TF32_ENV = "E2E_LITE_TF32"


def check_range(
    owner: str,
    name: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    integer: bool = False,
) -> None:
    """Raise ``ValueError`` naming ``owner.name``, the value and the allowed range.

    ``lo``/``hi`` are inclusive bounds unless ``lo_open``/``hi_open``; ``None`` means unbounded.
    ``integer`` also requires a whole number (bool is refused).
    """
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    rng = f"{'(' if lo_open or lo is None else '['}{lo_s}, {hi_s}{')' if hi_open or hi is None else ']'}"
    kind = "an integer" if integer else "a number"
    msg = f"{owner}.{name}={value!r} is invalid: must be {kind} in {rng}"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(msg)
    if integer and not isinstance(value, (int, np.integer)):  # (2.0 is a float, not a count)
        raise ValueError(msg)
    if not math.isfinite(float(value)) and not (hi is None and value == math.inf):
        raise ValueError(msg)
    if lo is not None and (value < lo or (lo_open and value == lo)):
        raise ValueError(msg)
    if hi is not None and (value > hi or (hi_open and value == hi)):
        raise ValueError(msg)


def check_pair(owner: str, name: str, pair: Sequence[float], lo: float | None = None) -> None:
    """Check a ``(low, high)`` range setting: two numbers, ``low <= high``, both ``>= lo``."""
    if len(pair) != 2:
        raise ValueError(f"{owner}.{name}={pair!r} is invalid: must be a (low, high) pair")
    check_range(owner, f"{name}[0]", pair[0], lo)
    check_range(owner, f"{name}[1]", pair[1], lo)
    if pair[0] > pair[1]:
        raise ValueError(f"{owner}.{name}={tuple(pair)!r} is invalid: low must be <= high")


@dataclass(frozen=True)
class Profile:
    """Every size the course depends on, in one place.

    Attributes:
        name: ``"quick"`` or ``"full"``.
        track_length_m: length of each procedural track [m].
        n_val_tracks: how many validation tracks closed-loop evaluation cycles through.
        eval_miles: closed-loop distance budget per driver in the chapters [mi].
        n_worlds: worlds driven in lockstep by the evaluator (the batch B). The evaluator shares
            them out in groups of 8 (``policy.FORWARD_GROUP``), so B / 8 cores at most drive
            one evaluation: 64 in the full profile, for 8 cores; 16 in the quick one, for 2.
        collect_worlds: cars the data collector drives in lockstep (each records its share of
            the samples, so few samples need few cars).
        n_train_samples: expert samples collected on training tracks (chapter 04).
        n_val_samples: expert samples collected on validation tracks (for validation losses).
        n_train_tracks: how many training tracks the collector cycles through.
        train_epochs: epochs of every network's training (chapters 05-09).
        ablation_miles: closed-loop distance per driver in chapter 10's ablation [mi] (the
            paper: more than 480).
        replay_s: length of chapter 10's replays [s].
        ablation_worlds: cars driven in lockstep in chapters 09-11 and by the record.
        ablation_seeds: training seeds per learned driver in chapters 09-11; a row's miles are
            shared among them and the verdicts compare seeds (one training run cannot separate
            the methods). Four in the full profile: 4 seeds against 4 can reach p = 1/70, where
            3 against 3 never go below 0.05; a fifth seed would add about 20 min to the course
            on the slower of the reference 2-core machines (docs/benchmarks.md).
    """

    name: str
    track_length_m: float
    n_val_tracks: int
    eval_miles: float
    n_worlds: int
    collect_worlds: int
    n_train_samples: int
    n_val_samples: int
    n_train_tracks: int
    train_epochs: int
    ablation_miles: float = 300.0
    replay_s: float = 30.0
    ablation_worlds: int = 64
    ablation_seeds: int = 4

    def __post_init__(self) -> None:
        if self.name not in ("quick", "full"):
            raise ValueError(f"Profile.name={self.name!r} is invalid: must be 'quick' or 'full'")
        check_range("Profile", "track_length_m", self.track_length_m, 500.0)
        check_range("Profile", "n_val_tracks", self.n_val_tracks, 1, integer=True)
        check_range("Profile", "eval_miles", self.eval_miles, 0.0, lo_open=True)
        check_range("Profile", "n_worlds", self.n_worlds, 1, integer=True)
        check_range("Profile", "collect_worlds", self.collect_worlds, 1, integer=True)
        check_range("Profile", "n_train_samples", self.n_train_samples, 1, integer=True)
        check_range("Profile", "n_val_samples", self.n_val_samples, 1, integer=True)
        check_range("Profile", "n_train_tracks", self.n_train_tracks, 1, integer=True)
        check_range("Profile", "train_epochs", self.train_epochs, 1, integer=True)
        check_range("Profile", "ablation_miles", self.ablation_miles, 0.0, lo_open=True)
        check_range("Profile", "replay_s", self.replay_s, 0.0, lo_open=True)
        check_range("Profile", "ablation_worlds", self.ablation_worlds, 1, integer=True)
        check_range("Profile", "ablation_seeds", self.ablation_seeds, 1, 100, integer=True)

    @property
    def quick(self) -> bool:
        """True in the quick profile."""
        return self.name == "quick"

    @property
    def caveat(self) -> str:
        """A line to print under every table of results: empty in the full profile."""
        if not self.quick:
            return ""
        return (
            "\n(quick profile: a smoke test of the code, networks trained for seconds on "
            f"{self.n_train_samples} samples and {self.ablation_miles:g}-{self.eval_miles:g} miles "
            "driven per row; these numbers are not results)"
        )


QUICK = Profile(
    name="quick",
    track_length_m=2_000.0,
    n_val_tracks=4,
    eval_miles=1.0,
    n_worlds=16,
    collect_worlds=8,
    n_train_samples=400,
    n_val_samples=160,
    n_train_tracks=4,
    train_epochs=1,
    ablation_miles=0.4,
    replay_s=2.0,
    ablation_worlds=8,
    ablation_seeds=2,
)
# The full profile's tracks hold the paper's 20-80 parked cars, 50-200 m apart (mean 125 m).
# 48,000 training samples (the paper had 500K) are 80 minutes of expert driving, ~120 km.
FULL = Profile(
    name="full",
    track_length_m=8_000.0,
    n_val_tracks=16,
    eval_miles=100.0,
    n_worlds=64,
    collect_worlds=16,
    n_train_samples=48_000,
    n_val_samples=8_000,
    n_train_tracks=32,
    train_epochs=3,
    ablation_miles=300.0,
    replay_s=30.0,
    ablation_worlds=64,
    ablation_seeds=4,
)


QUICK_ON = ("1", "true", "yes")
QUICK_OFF = ("", "0", "false", "no")


def in_notebook() -> bool:
    """True inside a Jupyter kernel (where ``sys.argv`` is the kernel's, not the chapter's)."""
    if "ipykernel" not in sys.modules:
        return False
    try:
        from IPython import get_ipython  # (here: the notebook extra's, maybe not installed)
    except ImportError:
        return False
    shell = get_ipython()
    return shell is not None and getattr(shell, "kernel", None) is not None


def quick_requested(argv: Sequence[str] | None = None, environ: dict | None = None) -> bool:
    """Whether the quick profile is asked for, by ``--quick`` in ``argv`` or ``E2E_LITE_QUICK``.

    ``argv`` defaults to the script's arguments, and to none inside a notebook (the kernel's own
    arguments are not the chapter's); there, set the variable in the first cell instead
    (``%env E2E_LITE_QUICK=1``). A value of the variable outside 1/true/yes/0/false/no (any case)
    raises ``ValueError`` naming them.
    """
    if argv is None:
        argv = [] if in_notebook() else sys.argv[1:]
    environ = os.environ if environ is None else environ
    raw = environ.get(QUICK_ENV, "")
    flag = raw.strip().lower()
    if flag not in QUICK_ON + QUICK_OFF:
        accepted = ", ".join(v for v in QUICK_ON + QUICK_OFF if v)
        raise ValueError(
            f"{QUICK_ENV}={raw!r} is invalid: must be one of {accepted} (any case) or empty"
        )
    return QUICK_FLAG in argv or flag in QUICK_ON


def available_cores() -> int:
    """The cores this process may run on (``os.sched_getaffinity`` where the system has it: a
    container or ``taskset`` may allow fewer than ``os.cpu_count``)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def default_workers(environ: dict | None = None) -> int:
    """Worker processes for driving and collecting: ``E2E_LITE_WORKERS`` when set (a whole number
    >= 1; anything else raises ``ValueError`` naming it), else :func:`available_cores`. Results
    do not depend on it (see :mod:`e2e_lite.driving.parallel`), only the time they take."""
    environ = os.environ if environ is None else environ
    raw = environ.get(WORKERS_ENV, "").strip()
    if not raw:
        return available_cores()
    if not raw.isdigit() or int(raw) < 1:
        raise ValueError(f"{WORKERS_ENV}={raw!r} is invalid: must be a whole number >= 1")
    return int(raw)


def tf32_allowed(environ: dict | None = None) -> bool:
    """Whether TF32 is asked for (``E2E_LITE_TF32`` in 1/true/yes; 0/false/no/empty: not)."""
    environ = os.environ if environ is None else environ
    raw = environ.get(TF32_ENV, "")
    flag = raw.strip().lower()
    if flag not in QUICK_ON + QUICK_OFF:
        accepted = ", ".join(v for v in QUICK_ON + QUICK_OFF if v)
        raise ValueError(f"{TF32_ENV}={raw!r} is invalid: must be one of {accepted} or empty")
    return flag in QUICK_ON


def precision(environ: dict | None = None) -> str:
    """The arithmetic the networks train and drive in: ``"fp32"`` (the default, on every device)
    or ``"tf32"`` (a GPU's tensor cores round inputs to 10 bits of mantissa; asked for with
    ``E2E_LITE_TF32=1``). Part of every checkpoint's and evaluation's key: on an H100, five GMM
    seeds trained in TF32 drove worse than the same seeds in fp32 (as issue 56 reports)."""
    return "tf32" if tf32_allowed(environ) else "fp32"


def apply_precision(torch: Any) -> None:
    """Set torch's TF32 switches (cuDNN convolutions and CUDA matrix products) to
    :func:`precision`. Called where torch is first used: the learning layer and every worker."""
    allow = precision() == "tf32"
    torch.backends.cudnn.allow_tf32 = allow
    torch.backends.cuda.matmul.allow_tf32 = allow


def _progress_bar() -> type:
    """tqdm's notebook bar inside a kernel with ipywidgets, else the text bar (which also works in
    a notebook: ``tqdm.auto`` would warn "IProgress not found" there and still fall back)."""
    if in_notebook():
        try:
            import ipywidgets  # noqa: F401 (here: the notebook bar needs it; maybe not installed)
            from tqdm.notebook import tqdm as notebook_tqdm  # (here: imports ipywidgets' parts)

            return notebook_tqdm
        except ImportError:
            pass

    return text_tqdm


tqdm = _progress_bar()


def active_profile(argv: Sequence[str] | None = None, environ: dict | None = None) -> Profile:
    """The profile the current process runs under (see module docstring)."""
    return QUICK if quick_requested(argv, environ) else FULL
