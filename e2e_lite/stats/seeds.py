"""Seed-level tests: does one recipe collide less than another, with the training seed as the
unit of replication?

Every seed of a row drives the same budget of miles (:func:`~e2e_lite.driving.rollout.disjoint_runs`),
so a seed's result is a whole number of collisions. Two rows are compared on those counts:

* :func:`rank_test`: the exact permutation test of the midrank sum (Mann-Whitney with ties
  kept as ties): every split of the pooled seeds into two rows of the same sizes is equally
  likely under "no difference", and the p-value counts the splits whose rank sum is at least as
  extreme. Equal counts share their rank: a step that rests on ties is not claimed.
* :func:`sign_flip_test`: the paired version, where seed ``k`` of both rows drove the same
  roads and start lanes and (for a fine-tune and its control) grew from the same parent network:
  the per-seed differences' signs are flipped in every way.
* :func:`ratio_interval`: the effect size, the rows' pooled rate ratio, with a bootstrap
  interval over the seeds (and, where a row never collided, the pooled counts' exact interval).
* :func:`compare_seeds`: both tests and the ratio on two rows' seeds, one :class:`SeedTest`.

Counts of seeds whose miles differ (a drive ends a few metres after its budget) are first
brought to the row's common budget and rounded (:func:`seed_counts`), so a tie stays a tie.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np


class Driven(Protocol):
    """What a test reads of a drive: its collisions and its miles [mi]."""

    @property
    def collisions(self) -> int: ...

    @property
    def miles(self) -> float: ...


class Seeded(Driven, Protocol):
    """A row of training seeds: each seed's drive (empty: one drive, the row itself)."""

    @property
    def seeds(self) -> Sequence[Driven]: ...


class SeedCounts(NamedTuple):
    """Each training seed's collisions at the row's common budget, and that budget [mi]."""

    counts: np.ndarray
    budget: float


@dataclass(frozen=True)
class Tails:
    """One-sided p-values of an exact test: the first row collides less (``p_fewer``), more
    (``p_more``), and the smallest p-value these data could give in either tail (``min_p``)."""

    p_fewer: float
    p_more: float
    min_p: float


def seed_counts(row: Seeded, outcome: str = "collisions") -> SeedCounts:
    """Each training seed's collisions (or another count its seeds hold, ``outcome``: e.g.
    ``"off_centre"``) over the row's common budget, and that budget [mi].

    The budget is the median of the seeds' miles; a seed's count is its rate at that budget,
    rounded to a whole collision (a seed that drove 100.004 mi and collided 6 times counts 6, as
    one that drove 99.998 mi and collided 6 times), so equal counts stay equal."""
    seeds = row.seeds or [row]
    miles = np.array([s.miles for s in seeds], dtype=float)
    budget = float(np.median(miles))
    counts = np.array([getattr(s, outcome) for s in seeds], dtype=float)
    return SeedCounts(np.rint(counts * budget / np.maximum(miles, 1e-9)), budget)


def seed_rates(row: Seeded) -> np.ndarray:
    """Each training seed's collisions per 100 miles (one drive: its rate alone)."""
    return np.array([100.0 * s.collisions / s.miles for s in (row.seeds or [row])])


def _midranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..N with tied values sharing the mean of their ranks, doubled (integers)."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values), dtype=np.int64)
    sorted_v = values[order]
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and sorted_v[j + 1] == sorted_v[i]:
            j += 1
        ranks[order[i : j + 1]] = (i + 1) + (j + 1)  # twice the mean of ranks i+1 .. j+1
        i = j + 1
    return ranks


def _subset_sum_counts(weights: np.ndarray, k: int | None, exact: bool = True) -> np.ndarray:
    """``out[s]``: how many subsets of the non-negative integer ``weights`` sum to ``s``; of
    exactly ``k`` of them, or of any size with ``k=None`` (the ``2^n`` sign patterns of a paired
    test). ``exact``: Python integers (C(60, 30) and beyond, exact); else float64 (relative
    error about 1e-16, for the thousands of draws of :func:`power`)."""
    weights = np.asarray(weights, dtype=np.int64)
    total = int(weights.sum())
    rows = 1 if k is None else k + 1
    dp = np.zeros((rows, total + 1), dtype=object if exact else np.float64)
    dp[0, 0] = 1
    for w in weights.tolist():
        # 0/1 knapsack: the right side is evaluated from the counts before this weight
        if k is None:
            dp[0, w:] = dp[0, w:] + dp[0, : total + 1 - w]
        else:
            dp[1:, w:] = dp[1:, w:] + dp[:-1, : total + 1 - w]
    return dp[-1] if k is not None else dp[0]


def _tails(dist: np.ndarray, observed: int, total: float) -> Tails:
    """One-sided p-values of ``observed`` under the exact distribution ``dist`` (counts per
    value, ``total`` in all), and the smallest p-value these data could give in either tail."""
    support = np.flatnonzero(dist != 0)
    return Tails(
        p_fewer=float(sum(dist[: observed + 1]) / total),
        p_more=float(sum(dist[observed:]) / total),
        min_p=float(min(dist[support[0]], dist[support[-1]]) / total),
    )


def rank_test(a: Sequence[float], b: Sequence[float], exact: bool = True) -> Tails:
    """Exact one-sided permutation tests of the midrank sum of ``a`` against ``b``.

    Returns :class:`Tails`: ``p_fewer`` = P(a's rank sum <= observed), ``p_more`` = P(>=
    observed), ``min_p`` the smallest p-value these values can reach, under every split of the pooled values into
    groups of ``len(a)`` and ``len(b)`` being equally likely (ties kept: tied values share a
    rank, so a split that only moves tied seeds changes nothing, and ``min_p`` grows with the
    ties). ``exact=False`` counts in float64 (for :func:`power`)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ranks = _midranks(np.concatenate([a, b]))
    observed = int(ranks[: len(a)].sum())
    dist = _subset_sum_counts(ranks, len(a), exact)
    return _tails(dist, observed, math.comb(len(a) + len(b), len(a)))


def sign_flip_test(a: Sequence[float], b: Sequence[float]) -> Tails:
    """Exact one-sided sign-flip tests on the paired differences ``d[k] = a[k] - b[k]``.

    Under "no difference" each seed's difference is as likely negative as positive; the p-value
    counts the ``2^n`` sign patterns whose sum is at least as extreme. A zero difference flips
    to itself: a tie counts for neither row, and ``min_p`` (the smallest p-value these
    differences can give) is ``2^-(n - zeros)``, not ``2^-n``. Returns :class:`Tails`.

    The sum of a sign pattern is ``2 P - A``, with ``A = sum |d|`` and ``P`` the sum of the
    ``|d|`` given a plus sign, so whole-number differences are counted by subset sums of
    ``|d|`` (30 seeds in milliseconds); others by listing the patterns (up to 20 seeds)."""
    if len(np.asarray(a)) != len(np.asarray(b)):  # (before numpy broadcasts one row of 1)
        raise ValueError("sign_flip_test: both rows need the same seeds (paired)")
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    observed, n = float(d.sum()), len(d)
    if np.all(d == np.rint(d)):
        size = np.abs(d).astype(np.int64)
        dist = _subset_sum_counts(size, None, exact=True)
        # S = 2 P - A <= observed  <=>  P <= (observed + A) / 2 (a whole number: S and A agree
        # in parity); the tails of S are those of P
        plus = round((observed + int(size.sum())) / 2)
        return _tails(dist, plus, 2**n)
    if n > 20:
        raise ValueError(f"sign_flip_test: {n} seeds of fractional differences (at most 20)")
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=n)))  # (2^n, n)
    sums = signs @ np.abs(d)
    eps = 1e-9 * max(1.0, float(np.abs(d).sum()))
    nonzero = int(np.sum(np.abs(d) > eps))
    return Tails(
        p_fewer=float(np.mean(sums <= observed + eps)),
        p_more=float(np.mean(sums >= observed - eps)),
        min_p=0.5**nonzero,
    )


def ratio_interval(
    a: Sequence[float],
    b: Sequence[float],
    level: float = 0.95,
    paired: bool = False,
    n_boot: int = 4_000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """The rate ratio ``mean(a) / mean(b)`` of two rows' counts (equal budgets per seed; with
    equal numbers of seeds ``sum(a) / sum(b)``) with a percentile bootstrap interval over the
    training seeds: ``(ratio, low, high)`` (all NaN when neither row collided).

    The seeds of each row are resampled with replacement (``paired``: seed pairs together); a
    resample whose ``b`` row never collided gives ``inf``. A ratio below 1: ``a`` collides less.

    When one row never collided its seeds have no spread to resample (every resample of a row of
    zeros gives 0, so the bootstrap alone would say ``[0, 0]``, or ``[1, inf]`` the other way):
    the interval then also holds the exact conditional one of the pooled counts (Clopper-Pearson
    on ``sum(a)`` of ``sum(a) + sum(b)``, :func:`pooled_ratio_interval`), which treats a row's
    miles as one draw: the least uncertainty the counts allow. So does an interval whose every
    resample gives the same ratio (paired rows equal seed by seed: ``[1, 1]`` alone), which
    would say the counts fix the ratio exactly."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if paired and len(a) != len(b):
        raise ValueError("ratio_interval: paired rows need the same seeds")
    rng = np.random.default_rng(seed)
    ia = rng.integers(0, len(a), (n_boot, len(a)))
    ib = ia if paired else rng.integers(0, len(b), (n_boot, len(b)))
    if a.sum() == 0 and b.sum() == 0:  # 0 / 0: no ratio to estimate
        return math.nan, math.nan, math.nan
    # (each sum times the other row's number of seeds: the rates per seed, in one division)
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = (a[ia].sum(1) * len(b)) / (b[ib].sum(1) * len(a))
        ratio = (a.sum() * len(b)) / (b.sum() * len(a)) if b.sum() else math.inf
    boot = np.where(np.isnan(boot), 1.0, boot)  # a resample of 0 / 0: no evidence either way
    tail = (1.0 - level) / 2.0 * 100.0
    # interpolating between two infinite ratios gives NaN: with any, read the order statistics
    method = "linear" if np.isfinite(boot).all() else "inverted_cdf"
    low, high = np.percentile(boot, [tail, 100.0 - tail], method=method)
    if a.sum() == 0 or b.sum() == 0 or low == high:
        exact_low, exact_high = pooled_ratio_interval(a, b, level)
        low, high = min(low, exact_low), max(high, exact_high)
    return float(ratio), float(low), float(high)


def pooled_ratio_interval(
    a: Sequence[float], b: Sequence[float], level: float = 0.95
) -> tuple[float, float]:
    """The exact conditional (Clopper-Pearson) interval of the rate ratio of two rows' pooled
    counts, each seed of either row driving the same budget: given ``n = sum(a) + sum(b)``,
    ``sum(a) ~ Binomial(n, p)`` with ``p = r m_a / (r m_a + m_b)`` for the ratio ``r`` and the
    rows' miles ``m_a, m_b`` (here their numbers of seeds). ``(low, high)``; ``high`` is ``inf``
    when ``b`` never collided; NaN when neither did."""
    from scipy.stats import beta  # (here: an evaluation worker never loads scipy.stats)

    k_a, k_b = float(np.sum(a)), float(np.sum(b))
    if k_a + k_b == 0:
        return math.nan, math.nan
    tail = (1.0 - level) / 2.0
    p_low = float(beta.ppf(tail, k_a, k_b + 1)) if k_a > 0 else 0.0
    p_high = float(beta.ppf(1.0 - tail, k_a + 1, k_b)) if k_b > 0 else 1.0
    exposure = len(b) / len(a)  # m_b / m_a
    low = p_low / (1.0 - p_low) * exposure
    high = math.inf if p_high >= 1.0 else p_high / (1.0 - p_high) * exposure
    return low, high


@dataclass(frozen=True)
class SeedTest:
    """Two rows compared seed by seed (:func:`compare_seeds`): does row a collide less than b?

    Attributes:
        p_fewer, p_more, min_p: the primary test's one-sided p-values and the smallest p-value
            these seeds could give (:class:`Tails`).
        fewer, more: whether ``p_fewer`` (``p_more``) is below ``1 - level``.
        test: the primary test, ``"rank"`` or ``"paired sign-flip"``.
        p_unpaired, p_paired: the p-value for fewer of either test (None: the rows' seeds differ
            in number, so no pairs).
        ratio, ratio_ci: the pooled rate ratio a / b and its bootstrap interval
            (:func:`ratio_interval`; NaN when neither row collided).
        counts_a, counts_b: each seed's count at its row's common budget (:func:`seed_counts`).
        budget: row a's common budget per seed [mi].
        level: the confidence level the test was read at.
    """

    p_fewer: float
    p_more: float
    min_p: float
    fewer: bool
    more: bool
    test: str
    p_unpaired: float
    p_paired: float | None
    ratio: float
    ratio_ci: tuple[float, float]
    counts_a: tuple[int, ...]
    counts_b: tuple[int, ...]
    budget: float
    level: float = 0.95

    @property
    def cut(self) -> float:
        """The p-value a verdict must be below (3 seeds against 3 give exactly 0.05, not below)."""
        return 1.0 - self.level - 1e-9

    @property
    def reachable(self) -> bool:
        """Whether these seeds could have reached a p-value below the cut at all."""
        return self.min_p < self.cut

    @property
    def narrow(self) -> bool:
        """Not shown at the seed level while the bootstrap interval excludes 1: a percentile
        bootstrap over a few seeds is too narrow to read."""
        lo, hi = self.ratio_ci
        return not (self.fewer or self.more) and (hi < 1.0 or lo > 1.0)

    def median_rates(self) -> tuple[float, float]:
        """Each row's median seed rate [per 100 mi], both at row a's budget."""
        scale = 100.0 / self.budget if self.budget > 0 else 0.0
        return float(np.median(self.counts_a)) * scale, float(np.median(self.counts_b)) * scale


def compare_seeds(
    a: Seeded, b: Seeded, level: float = 0.95, paired: bool = False, outcome: str = "collisions"
) -> SeedTest:
    """Does row ``a`` collide less than ``b``, or more, with the training seed as the unit?

    The primary test is :func:`rank_test` on the seeds' counts (:func:`seed_counts`), or with
    ``paired`` (seed ``k`` of both rows drove the same roads, and a fine-tune shares its parent's
    seed) :func:`sign_flip_test`; the other is reported beside it. The pooled Poisson test
    (:func:`~e2e_lite.stats.rates.compare_rates`) treats a row's miles as one draw and is
    secondary. ``fewer`` (``more``) when its p-value is below ``1 - level``; ``min_p`` is the
    smallest p-value these seeds could give, so a verdict that could not have been reached can
    say so. ``outcome``: the count compared (:func:`seed_counts`)."""
    ca, budget_a = seed_counts(a, outcome)
    cb, _ = seed_counts(b, outcome)
    paired = paired and len(ca) == len(cb)
    unpaired = rank_test(ca, cb)
    flip = sign_flip_test(ca, cb) if len(ca) == len(cb) else None
    main = flip if paired and flip is not None else unpaired
    cut = 1.0 - level - 1e-9
    ratio, lo, hi = ratio_interval(ca, cb, level, paired=paired)
    return SeedTest(
        p_fewer=main.p_fewer,
        p_more=main.p_more,
        min_p=main.min_p,
        fewer=bool(main.p_fewer < cut),
        more=bool(main.p_more < cut),
        test="paired sign-flip" if main is flip else "rank",
        p_unpaired=unpaired.p_fewer,
        p_paired=None if flip is None else flip.p_fewer,
        ratio=ratio,
        ratio_ci=(lo, hi),
        counts_a=tuple(ca.astype(int).tolist()),
        counts_b=tuple(cb.astype(int).tolist()),
        budget=budget_a,
        level=level,
    )


def spread(row: Seeded) -> float | None:
    """The worst seed's rate over the median seed's (``inf`` when the median is 0 and the worst
    is not; ``None`` for one drive): how far one training seed strays from the recipe's
    typical."""
    if len(row.seeds) < 2:
        return None
    rates = seed_rates(row)
    median, worst = float(np.median(rates)), float(rates.max())
    if median == 0.0:
        return 1.0 if worst == 0.0 else float("inf")
    return worst / median
