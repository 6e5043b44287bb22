"""Seed-level verdicts: does one recipe collide less than another, with the training seed as the
unit of replication, and how likely was the record to see it?

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
* :func:`power`: how often a record of its seeds and miles finds a true step of a given size,
  and the smallest p-value it can reach at all (3 seeds against 3: 0.05, never below it).

Counts of seeds whose miles differ (a drive ends a few metres after its budget) are first
brought to the row's common budget and rounded (:func:`seed_counts`), so a tie stays a tie.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..config import check_range
from .metrics import EvalResult, result_dict


def seed_counts(result: EvalResult | dict[str, Any]) -> tuple[np.ndarray, float]:
    """Each training seed's collisions over the row's common budget, and that budget [mi].

    The budget is the median of the seeds' miles; a seed's count is its rate at that budget,
    rounded to a whole collision (a seed that drove 100.004 mi and collided 6 times counts 6, as
    one that drove 99.998 mi and collided 6 times), so equal counts stay equal."""
    r = result_dict(result)
    seeds = r.get("seeds") or [r]
    miles = np.array([s["miles"] for s in seeds], dtype=float)
    budget = float(np.median(miles))
    counts = np.array([s["collisions"] for s in seeds], dtype=float)
    return np.rint(counts * budget / np.maximum(miles, 1e-9)), budget


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


def _tails(dist: np.ndarray, observed: int, total: float) -> dict[str, float]:
    """One-sided p-values of ``observed`` under the exact distribution ``dist`` (counts per
    value, ``total`` in all), and the smallest p-value these data could give in either tail."""
    support = np.flatnonzero(dist != 0)
    return {
        "p_fewer": float(sum(dist[: observed + 1]) / total),
        "p_more": float(sum(dist[observed:]) / total),
        "min_p": float(min(dist[support[0]], dist[support[-1]]) / total),
    }


def rank_test(a: Sequence[float], b: Sequence[float], exact: bool = True) -> dict[str, float]:
    """Exact one-sided permutation tests of the midrank sum of ``a`` against ``b``.

    Returns ``{"p_fewer": P(a's rank sum <= observed), "p_more": P(>= observed), "min_p": the
    smallest p-value these values can reach}`` under every split of the pooled values into
    groups of ``len(a)`` and ``len(b)`` being equally likely (ties kept: tied values share a
    rank, so a split that only moves tied seeds changes nothing, and ``min_p`` grows with the
    ties). ``exact=False`` counts in float64 (for :func:`power`)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    ranks = _midranks(np.concatenate([a, b]))
    observed = int(ranks[: len(a)].sum())
    dist = _subset_sum_counts(ranks, len(a), exact)
    return _tails(dist, observed, math.comb(len(a) + len(b), len(a)))


def sign_flip_test(a: Sequence[float], b: Sequence[float]) -> dict[str, float]:
    """Exact one-sided sign-flip tests on the paired differences ``d[k] = a[k] - b[k]``.

    Under "no difference" each seed's difference is as likely negative as positive; the p-value
    counts the ``2^n`` sign patterns whose sum is at least as extreme. A zero difference flips
    to itself: a tie counts for neither row, and ``min_p`` (the smallest p-value these
    differences can give) is ``2^-(n - zeros)``, not ``2^-n``. Returns ``{"p_fewer", "p_more",
    "min_p"}``.

    The sum of a sign pattern is ``2 P - A``, with ``A = sum |d|`` and ``P`` the sum of the
    ``|d|`` given a plus sign, so whole-number differences are counted by subset sums of
    ``|d|`` (30 seeds in milliseconds); others by listing the patterns (up to 20 seeds)."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    if len(d) != len(np.asarray(b)):
        raise ValueError("sign_flip_test: both rows need the same seeds (paired)")
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
    return {
        "p_fewer": float(np.mean(sums <= observed + eps)),
        "p_more": float(np.mean(sums >= observed - eps)),
        "min_p": 0.5**nonzero,
    }


def ratio_interval(
    a: Sequence[float],
    b: Sequence[float],
    level: float = 0.95,
    paired: bool = False,
    n_boot: int = 4_000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """The rate ratio ``sum(a) / sum(b)`` of two rows' counts (equal budgets per seed) with a
    percentile bootstrap interval over the training seeds: ``(ratio, low, high)`` (all NaN when
    neither row collided).

    The seeds of each row are resampled with replacement (``paired``: seed pairs together); a
    resample whose ``b`` row never collided gives ``inf``. A ratio below 1: ``a`` collides less.

    When one row never collided its seeds have no spread to resample (every resample of a row of
    zeros gives 0, so the bootstrap alone would say ``[0, 0]``, or ``[1, inf]`` the other way):
    the interval then also holds the exact conditional one of the pooled counts (Clopper-Pearson
    on ``sum(a)`` of ``sum(a) + sum(b)``, :func:`pooled_ratio_interval`), which treats a row's
    miles as one draw: the least uncertainty the counts allow."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    rng = np.random.default_rng(seed)
    ia = rng.integers(0, len(a), (n_boot, len(a)))
    ib = ia if paired else rng.integers(0, len(b), (n_boot, len(b)))
    if a.sum() == 0 and b.sum() == 0:  # 0 / 0: no ratio to estimate
        return math.nan, math.nan, math.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        boot = a[ia].sum(1) / b[ib].sum(1)
        ratio = a.sum() / b.sum() if b.sum() else math.inf
    boot = np.where(np.isnan(boot), 1.0, boot)  # a resample of 0 / 0: no evidence either way
    tail = (1.0 - level) / 2.0 * 100.0
    # interpolating between two infinite ratios gives NaN: with any, read the order statistics
    method = "linear" if np.isfinite(boot).all() else "inverted_cdf"
    low, high = np.percentile(boot, [tail, 100.0 - tail], method=method)
    if a.sum() == 0 or b.sum() == 0:
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


def compare_seeds(
    a: EvalResult | dict[str, Any],
    b: EvalResult | dict[str, Any],
    level: float = 0.95,
    paired: bool = False,
) -> dict[str, Any]:
    """Does driver ``a`` collide less than ``b``, or more, with the training seed as the unit?

    The primary test is :func:`rank_test` on the seeds' counts (:func:`seed_counts`), or with
    ``paired`` (seed ``k`` of both rows drove the same roads, and a fine-tune shares its parent's
    seed) :func:`sign_flip_test`; the other is reported beside it. The pooled Poisson test
    (:func:`~e2e_lite.driving.metrics.compare_rates`) treats a row's miles as one draw and is
    secondary.

    Returns:
        ``{"p_fewer", "p_more", "fewer", "more", "min_p", "test", "p_unpaired", "p_paired",
        "ratio", "ratio_ci", "counts_a", "counts_b", "verdict": one line}``. ``fewer``
        (``more``) when its p-value is below ``1 - level``; ``min_p`` is the smallest p-value
        these seeds could give, so a verdict that could not have been reached says so.
    """
    ca, budget_a = seed_counts(a)
    cb, _ = seed_counts(b)
    paired = paired and len(ca) == len(cb)
    unpaired = rank_test(ca, cb)
    flip = sign_flip_test(ca, cb) if len(ca) == len(cb) else None
    main = flip if paired and flip is not None else unpaired
    cut = 1.0 - level - 1e-9  # (3 seeds against 3 give exactly 0.05, which is not below 0.05)
    fewer, more = main["p_fewer"] < cut, main["p_more"] < cut
    ratio, lo, hi = ratio_interval(ca, cb, level, paired=paired)
    scale = 100.0 / budget_a if budget_a > 0 else 0.0
    ratio_text = (
        "no collision in either" if math.isnan(ratio) else f"{ratio:.2f} [{lo:.2f}, {hi:.2f}]"
    )
    med = (
        f"median {np.median(ca) * scale:.1f} vs {np.median(cb) * scale:.1f} per 100 mi "
        f"({len(ca)} vs {len(cb)} seeds), pooled ratio {ratio_text}"
    )
    test = "paired sign-flip" if main is flip else "rank"
    if fewer:
        verdict = f"{med}: fewer collisions, seed by seed ({test} p = {main['p_fewer']:.2g})"
    elif more:
        verdict = f"{med}: more collisions, seed by seed ({test} p = {main['p_more']:.2g})"
    else:
        p = min(main["p_fewer"], main["p_more"])
        reach = "" if main["min_p"] < cut else f"; these seeds cannot reach p < {1 - level:.2g}"
        verdict = f"{med}: not shown at the seed level ({test} p = {p:.2g}{reach})"
        if hi < 1.0 or lo > 1.0:  # a percentile bootstrap over a few seeds is too narrow
            verdict += f"; the interval, bootstrapped over {len(ca)} seeds, is too narrow to read"
    return {
        "p_fewer": main["p_fewer"],
        "p_more": main["p_more"],
        "fewer": bool(fewer),
        "more": bool(more),
        "min_p": main["min_p"],
        "test": test,
        "p_unpaired": unpaired["p_fewer"],
        "p_paired": None if flip is None else flip["p_fewer"],
        "ratio": ratio,
        "ratio_ci": (lo, hi),
        "counts_a": ca.astype(int).tolist(),
        "counts_b": cb.astype(int).tolist(),
        "verdict": verdict,
    }


def power(
    seeds: int,
    miles_per_seed: float,
    rate_per_100mi: float,
    step: float = 2.0,
    level: float = 0.95,
    n_sim: int = 2_000,
    seed: int = 0,
    *,
    dispersion: float = 0.0,
    test: str = "rank",
    shared: float = 0.0,
) -> dict[str, float]:
    """How often a record of ``seeds`` seeds per row, each driving ``miles_per_seed``, finds a
    true step: the better row colliding ``rate_per_100mi``, the worse ``step`` times that.

    Simulated with the seeds' spread: seed ``k``'s own rate is its row's rate times a gamma draw
    of mean 1 and variance ``dispersion``, and its count a Poisson draw of that rate (a negative
    binomial: ``Var = mu + dispersion mu^2``; :func:`fit_dispersion` fits it to a record's rows).
    ``dispersion=0``, no spread between seeds, is an upper bound. The record "finds" the step
    when ``test`` ("rank": :func:`rank_test`; "sign-flip": :func:`sign_flip_test` on seed pairs)
    gives ``p_fewer < 1 - level``. ``shared``: the share of a seed's spread its pair shares (a
    fine-tune and its parent, seed by seed): each seed's rate is then a shared gamma draw of
    variance ``shared x dispersion`` times one of its own of ``(1 - shared) x dispersion``, so
    the pair's log-rates correlate about ``shared``. Returns ``{"power", "min_p"}``: the share of
    simulated records that find it, and the smallest p-value these seeds can reach."""
    check_range("power", "dispersion", dispersion, 0.0)
    check_range("power", "shared", shared, 0.0, 1.0, hi_open=True)
    if test not in ("rank", "sign-flip"):
        raise ValueError(f"power: test must be 'rank' or 'sign-flip', got {test!r}")
    rng = np.random.default_rng(seed)
    lam = rate_per_100mi * miles_per_seed / 100.0

    def spread(k: float) -> np.ndarray:
        # (n_sim, seeds): gamma(shape 1/k, scale k) draws of mean 1 and variance k
        return np.ones((n_sim, seeds)) if k == 0.0 else rng.gamma(1.0 / k, k, (n_sim, seeds))

    common = spread(shared * dispersion)  # what a seed's pair shares
    own = (1.0 - shared) * dispersion
    better = rng.poisson(lam * common * spread(own))
    worse = rng.poisson(lam * step * common * spread(own))
    cut = 1.0 - level - 1e-9
    cache: dict[tuple, bool] = {}
    found = 0
    for a, b in zip(better, worse):
        if test == "rank":
            key = (tuple(sorted(a.tolist())), tuple(sorted(b.tolist())))
            if key not in cache:
                cache[key] = rank_test(a, b, exact=False)["p_fewer"] < cut
        else:
            key = tuple(sorted((a - b).tolist()))
            if key not in cache:
                cache[key] = sign_flip_test(a, b)["p_fewer"] < cut
        found += cache[key]
    min_p = 1.0 / math.comb(2 * seeds, seeds) if test == "rank" else 0.5**seeds
    return {"power": found / n_sim, "min_p": min_p}


def seeds_for_power(
    miles_per_seed: float,
    rate_per_100mi: float,
    target: float = 0.9,
    step: float = 2.0,
    most: int = 20,
    *,
    least: int = 2,
    n_sim: int = 1_000,
    dispersion: float = 0.0,
    test: str = "rank",
) -> dict[str, float]:
    """The fewest seeds per row, from ``least``, whose record finds a ``step`` with at least
    ``target`` power (:func:`power`, under the seeds' ``dispersion``), up to ``most`` (returned
    when none reaches it): ``{"seeds", "power"}``."""
    for n in range(least, most + 1):
        found = power(
            n, miles_per_seed, rate_per_100mi, step, n_sim=n_sim, dispersion=dispersion, test=test
        )
        if found["power"] >= target or n == most:
            return {"seeds": n, "power": found["power"]}
    raise ValueError(f"seeds_for_power: most={most} is below least={least}")


def _nb_loglik(counts: Sequence[np.ndarray], dispersion: float) -> float:
    """Log-likelihood of rows of counts under a negative binomial with each row's own mean (its
    maximum-likelihood estimate, the row's mean count) and one shared ``dispersion`` k:
    ``log P(y) = lnG(y + r) - lnG(r) - lnG(y + 1) + r ln(r / (r + mu)) + y ln(mu / (r + mu))``,
    ``r = 1/k``."""
    from scipy.special import gammaln  # (here: an evaluation worker never loads scipy)

    r = 1.0 / max(dispersion, 1e-8)
    total = 0.0
    for y in counts:
        mu = float(np.mean(y))
        if mu == 0.0:
            continue  # a row of zeros is as likely under every k
        total += float(
            np.sum(gammaln(y + r) - gammaln(r) - gammaln(y + 1.0))
            + np.sum(r * np.log(r / (r + mu)) + y * np.log(mu / (r + mu)))
        )
    return total


def fit_dispersion(counts: Sequence[Sequence[float]], level: float = 0.95) -> dict[str, float]:
    """The seeds' spread beyond Poisson, fitted to rows of per-seed counts (each row one
    recipe, its seeds driving one common budget): the maximum-likelihood dispersion k of a
    negative binomial (``Var = mu + k mu^2``, each row its own mean, every row one k) and its
    profile-likelihood interval (``2 (l_max - l(k)) <=`` the chi-square quantile of 1 df).
    Returns ``{"dispersion", "low", "high", "rows", "seeds"}``; k = 0 is Poisson."""
    rows = [np.asarray(c, dtype=float) for c in counts if len(c) >= 2]
    if not rows:
        raise ValueError("fit_dispersion: needs a row of at least two seeds")
    from scipy.stats import chi2  # (here: an evaluation worker never loads scipy.stats)

    grid = np.concatenate([[0.0], np.geomspace(1e-3, 20.0, 400)])
    ll = np.array([_nb_loglik(rows, k) for k in grid])
    best = int(np.argmax(ll))
    drop = chi2.ppf(level, 1) / 2.0
    inside = grid[ll >= ll[best] - drop]
    return {
        "dispersion": float(grid[best]),
        "low": float(inside.min()),
        "high": float(inside.max()),
        "rows": len(rows),
        "seeds": int(sum(len(r) for r in rows)),
    }


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjustment of a family of p-values (in their order): the ``i``-th
    smallest is multiplied by ``m - i`` (``i`` from 0), made non-decreasing, capped at 1.
    Reading each adjusted p at 0.05 keeps the chance of any false "reproduces" in the family at
    most 5 %."""
    p = np.asarray(p_values, dtype=float)
    order = np.argsort(p, kind="stable")
    adjusted = np.empty_like(p)
    running = 0.0
    for i, j in enumerate(order):
        running = max(running, min(1.0, (len(p) - i) * p[j]))
        adjusted[j] = running
    return adjusted.tolist()
