"""How likely a record is to find a step, and the spread it is stated under.

* :func:`power`: how often a record of its seeds and miles finds a true step of a given size
  (simulated under the seeds' spread), and the smallest p-value it can reach at all (3 seeds
  against 3: 0.05, never below it); :func:`seeds_for_power`, the fewest seeds that reach a power.
* :func:`fit_dispersion`: the seeds' spread beyond Poisson, a negative binomial's dispersion
  fitted to rows of per-seed counts (Cox-Reid adjusted), with its likelihood interval;
  :func:`chi_square_spread`, one row's chi-square against a shared rate.
* :func:`holm`: Holm's step-down adjustment of a family of p-values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..config import check_range
from .seeds import rank_test, sign_flip_test


@dataclass(frozen=True)
class Power:
    """What :func:`power` found: the share of simulated records that find the step, and the
    smallest p-value these seeds can reach."""

    power: float
    min_p: float


@dataclass(frozen=True)
class SeedsNeeded:
    """What :func:`seeds_for_power` found: the fewest seeds per row and the power they reach."""

    seeds: int
    power: float


@dataclass(frozen=True)
class Dispersion:
    """A negative binomial's dispersion fitted to rows of seeds (:func:`fit_dispersion`).

    Attributes:
        k: the dispersion (``Var = mu + k mu^2``; 0 is Poisson), the maximum of the Cox-Reid
            adjusted profile likelihood.
        low, high: its interval from that likelihood.
        rows, seeds: how many rows of two or more seeds it was fitted to, and their seeds.
    """

    k: float
    low: float
    high: float
    rows: int
    seeds: int


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
) -> Power:
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
    the pair's log-rates correlate about ``shared``. Returns :class:`Power`: the share of simulated
    records that find it, and the smallest p-value these seeds can reach."""
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
                cache[key] = rank_test(a, b, exact=False).p_fewer < cut
        else:
            key = tuple(sorted((a - b).tolist()))
            if key not in cache:
                cache[key] = sign_flip_test(a, b).p_fewer < cut
        found += cache[key]
    min_p = 1.0 / math.comb(2 * seeds, seeds) if test == "rank" else 0.5**seeds
    return Power(found / n_sim, min_p)


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
) -> SeedsNeeded:
    """The fewest seeds per row, from ``least``, whose record finds a ``step`` with at least
    ``target`` power (:func:`power`, under the seeds' ``dispersion``), up to ``most`` (returned
    when none reaches it)."""
    for n in range(least, most + 1):
        found = power(
            n, miles_per_seed, rate_per_100mi, step, n_sim=n_sim, dispersion=dispersion, test=test
        )
        if found.power >= target or n == most:
            return SeedsNeeded(n, found.power)
    raise ValueError(f"seeds_for_power: most={most} is below least={least}")


def _nb_loglik(counts: Sequence[np.ndarray], dispersion: float) -> float:
    """Cox-Reid adjusted log-likelihood of rows of counts under a negative binomial with each
    row's own mean (its maximum-likelihood estimate, the row's mean count) and one shared
    ``dispersion`` k: ``log P(y) = lnG(y + r) - lnG(r) - lnG(y + 1) + r ln(r / (r + mu)) +
    y ln(mu / (r + mu))``, ``r = 1/k``, less half the log of each row's information on its
    mean's log, ``n mu / (1 + k mu)``. The adjustment pays for each row's mean being fitted
    from its own few seeds: without it the fit underestimates k (a review's simulation, 8 rows
    of 4 seeds at k = 0.3: 0.16 on average; adjusted 0.30)."""
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
            - 0.5 * math.log(len(y) * mu / (1.0 + mu / r))
        )
    return total


def fit_dispersion(counts: Sequence[Sequence[float]], level: float = 0.95) -> Dispersion:
    """The seeds' spread beyond Poisson, fitted to rows of per-seed counts (each row one
    recipe, its seeds driving one common budget): the dispersion k of a negative binomial
    (``Var = mu + k mu^2``, each row its own mean, every row one k) at the maximum of the
    Cox-Reid adjusted profile likelihood (:func:`_nb_loglik`), and its interval from that
    likelihood (``2 (l_max - l(k)) <=`` the chi-square quantile of 1 df);
    k = 0 is Poisson. A grid brackets the maximum and the interval's ends, which are then
    solved for to 1e-6 (the digits a sentence prints are the fit's, not the grid's)."""
    rows = [np.asarray(c, dtype=float) for c in counts if len(c) >= 2]
    if not rows:
        raise ValueError("fit_dispersion: needs a row of at least two seeds")
    from scipy.optimize import brentq, minimize_scalar  # (an evaluation worker never loads scipy)
    from scipy.stats import chi2

    grid = np.concatenate([[0.0], np.geomspace(1e-3, 20.0, 400)])
    ll = np.array([_nb_loglik(rows, k) for k in grid])
    best = int(np.argmax(ll))
    lo_k, hi_k = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    k = float(grid[best])
    if hi_k > lo_k:
        found = minimize_scalar(
            lambda x: -_nb_loglik(rows, x),
            bounds=(lo_k, hi_k),
            method="bounded",
            options={"xatol": 1e-7},
        )
        if -found.fun >= ll[best]:
            k = float(found.x)
    top = max(float(ll[best]), _nb_loglik(rows, k))
    cut = top - chi2.ppf(level, 1) / 2.0
    inside = np.flatnonzero(ll >= cut)

    def end(i: int, j: int) -> float:
        """The interval's end between grid points ``i`` (inside) and ``j`` (outside)."""
        if not 0 <= j < len(grid):
            return float(grid[i])
        return float(brentq(lambda x: _nb_loglik(rows, x) - cut, grid[j], grid[i], xtol=1e-7))

    low = end(int(inside.min()), int(inside.min()) - 1)
    high = end(int(inside.max()), int(inside.max()) + 1)
    return Dispersion(
        k=k,
        low=min(low, k),
        high=max(high, k),
        rows=len(rows),
        seeds=int(sum(len(r) for r in rows)),
    )


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


def chi_square_spread(collisions: Sequence[int], miles: Sequence[float]) -> float | None:
    """One row's seeds against one shared rate: the chi-square of their collisions (degrees of
    freedom: seeds - 1); far above its degrees of freedom, the seeds do not drive alike. ``None``
    for one seed."""
    if len(collisions) < 2:
        return None
    k = np.asarray(collisions, dtype=float)
    m = np.asarray(miles, dtype=float)
    expected = m * k.sum() / m.sum()
    return float(np.sum((k - expected) ** 2 / np.maximum(expected, 1e-12)))
