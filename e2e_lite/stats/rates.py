"""Rates of collisions over miles, read as Poisson counts: a rate's exact interval
(:func:`poisson_ci`) and the exact test of two pooled rates (:func:`compare_rates`), which treats
each row's miles as one draw (the seed-level tests of :mod:`.seeds` do not)."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import check_range
from .seeds import Driven


def poisson_ci(count: int, exposure: float, level: float = 0.95) -> tuple[float, float]:
    """Exact (Garwood) confidence interval of a Poisson rate: ``count`` events over ``exposure``.

    lower = chi2.ppf(a/2, 2k) / 2 / exposure,  upper = chi2.ppf(1 - a/2, 2k + 2) / 2 / exposure,
    with a = 1 - level. For k = 0 the lower bound is 0 and the upper is -ln(a/2) / exposure
    (3.69 per 100 miles over 100 miles at 95 %).
    """
    check_range("poisson_ci", "count", count, 0, integer=True)
    check_range("poisson_ci", "exposure", exposure, 0.0, lo_open=True)
    check_range("poisson_ci", "level", level, 0.0, 1.0, lo_open=True, hi_open=True)
    from scipy.stats import chi2  # (here: scipy.stats costs evaluation workers 0.4 s to import)

    a = 1.0 - level
    lo = 0.0 if count == 0 else chi2.ppf(a / 2, 2 * count) / 2.0
    hi = chi2.ppf(1 - a / 2, 2 * count + 2) / 2.0
    return float(lo / exposure), float(hi / exposure)


@dataclass(frozen=True)
class RateTest:
    """Two pooled rates compared (:func:`compare_rates`).

    Attributes:
        rate_a, rate_b: each row's collisions per 100 miles.
        ratio: ``rate_a / rate_b`` (None when b never collided).
        p_value: the two-sided p-value of the exact conditional test.
        different: whether ``p_value`` is below ``1 - level``.
    """

    rate_a: float
    rate_b: float
    ratio: float | None
    p_value: float
    different: bool


def compare_rates(a: Driven, b: Driven, level: float = 0.95) -> RateTest:
    """Is driver a's collision rate different from b's beyond chance?

    The exact conditional test of two Poisson rates: given ``n = k_a + k_b`` collisions in
    ``m_a`` and ``m_b`` miles, ``k_a ~ Binomial(n, m_a / (m_a + m_b))`` when the rates are equal;
    the two-sided p-value of that binomial test: twice the smaller tail, at most 1 (the central
    definition: scipy's default, which sums the outcomes no likelier than the one observed, jumps
    when the miles differ by a metre and the share crosses 1/2, as two drives of one budget do).
    """
    ka, kb, ma, mb = a.collisions, b.collisions, a.miles, b.miles
    n = ka + kb
    from scipy.stats import binom  # (here: see poisson_ci)

    share = ma / (ma + mb)
    tails = (binom.cdf(ka, n, share), binom.sf(ka - 1, n, share))
    p = 1.0 if n == 0 else float(min(1.0, 2.0 * min(tails)))
    rate_a, rate_b = 100.0 * ka / ma, 100.0 * kb / mb
    return RateTest(
        rate_a=rate_a,
        rate_b=rate_b,
        ratio=None if kb == 0 else rate_a / rate_b,
        p_value=p,
        different=p < 1.0 - level,
    )
