"""The record's statistics, declared before it runs: which rows are compared (:data:`STEPS`), in
which family each is Holm-adjusted (:data:`FAMILIES`), the verdict each gets on the seeds' counts
(:func:`steps`, one :class:`StepResult` each), what the controls found (:func:`controls_line`),
and the record's power under its seeds' fitted spread (:func:`record_power`).
:mod:`e2e_lite.record.run` writes the families into the shares it runs; :mod:`e2e_lite.report`
renders the verdicts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from ..driving.metrics import seed_rates
from ..driving.verdicts import compare_seeds, fit_dispersion, holm, power, seed_counts
from .rows import Family, Record, Row


class Step(NamedTuple):
    """A test of the record: does row ``after`` collide less than row ``before``?

    Attributes:
        before, after: row keys.
        what: its name in the table.
        paired: the rows share a parent network seed by seed (a fine-tune, its control and their
            parent), so the paired sign-flip test is the primary one.
        family: the key in :data:`FAMILIES` whose p-values are Holm-adjusted together.
        credits: for a control's test, the paper's step whose method it tests (``what`` of it).
    """

    before: str
    after: str
    what: str
    paired: bool
    family: str
    credits: str | None = None


#: the families of tests, declared before a record runs: the p-values of one family are
#: Holm-adjusted together and the verdict reads the adjusted p
FAMILIES = {
    "paper": "the paper's steps: does each reproduce?",
    "beyond": "beyond the paper: does DAgger's step hold?",
    "controls": "each method against its control: is the step the method's?",
    "data": "does new data from the expert's states beat the same fine-tunes on none?",
}
_CVAR_STEP = "+ affordance -> + CVaR"
_AFFORDANCE_STEP = "GMM -> + affordance"
_DAGGER_STEP = "+ CVaR -> + DAgger"
#: the record's tests; the paper's steps each go "fewer" in the paper (seed 000)
STEPS = (
    Step("actuators", "gmm", "Baseline E2E -> trajectory GMM", False, "paper"),
    Step("gmm", "gmm_affordance", _AFFORDANCE_STEP, False, "paper"),
    Step("gmm_affordance", "gmm_affordance_cvar", _CVAR_STEP, True, "paper"),
    Step(
        "gmm_affordance_control",
        "gmm_affordance_cvar",
        "CVaR against its control (the mean)",
        True,
        "controls",
        _CVAR_STEP,
    ),
    Step(
        "gmm_affordance_w0",
        "gmm_affordance",
        "affordance loss against its control (w = 0)",
        False,
        "controls",
        _AFFORDANCE_STEP,
    ),
    Step("gmm_affordance_cvar", "dagger", _DAGGER_STEP, True, "beyond"),
    Step(
        "dagger_control",
        "dagger",
        "DAgger against its control (the expert's samples)",
        True,
        "controls",
        _DAGGER_STEP,
    ),
    Step(
        "dagger_no_new_data",
        "dagger_control",
        "DAgger's control against its fine-tunes on no new data",
        True,
        "data",
    ),
)
#: the row whose rate the record's power is stated at, and the step it must find
POWER_ROW, POWER_STEP = "gmm_affordance", 2.0
#: the paired row whose seeds share their parent with :data:`POWER_ROW`'s (the paired power's
#: shared spread is read from their rank correlation)
POWER_PAIR = "gmm_affordance_cvar"
#: the rows whose spread the power is stated under: those whose median rate is within this
#: factor of :data:`POWER_ROW`'s (the rows its steps compare; a row far above, whose seeds
#: spread otherwise, would set another spread)
POWER_RATES_WITHIN = 4.0

#: what a verdict says when the later row collides less, per family: a step beyond the paper
#: has nothing to reproduce, and a method that beats its control is credited
FOUND = {
    "paper": "reproduces",
    "controls": "beats its control",
    "beyond": "fewer collisions",
    "data": "fewer collisions",
}
#: what a verdict says when the later row collides more, in every family
OPPOSITE = "the opposite"


def verdict(
    test: dict[str, Any],
    slow_mph: float | None,
    family: str = "paper",
    holm_p: tuple[float, float] | None = None,
) -> str:
    """A step's verdict from its seed-level test (:func:`~e2e_lite.driving.verdicts.compare_seeds`
    of the later row against the earlier), read at its family's Holm-adjusted p-values
    ``holm_p = (fewer, more)`` (the test's own where None), with the later row's speed when it is
    slow; in the words of its ``family`` (:data:`FOUND`)."""
    p_fewer, p_more = holm_p or (test["p_fewer"], test["p_more"])
    if p_fewer < 0.05 - 1e-9:
        text = FOUND.get(family, FOUND["paper"])
    elif p_more < 0.05 - 1e-9:
        text = OPPOSITE
    elif test["min_p"] >= 0.05:
        text = "cannot be decided with these seeds"
    else:
        text = "not shown at the seed level"
    return text + (f", at {slow_mph:.1f} mph" if slow_mph is not None else "")


def family(declared: str) -> Family:
    """The families of :data:`STEPS` as a record holds them, with when they were ``declared``."""
    tests = {st.what: st.family for st in STEPS}
    return Family(dict(FAMILIES), tests, "holm", declared)


def declared_family(record: Record) -> Family:
    """The record's families of tests: as it declares them, or (a record from before the
    declaration) :func:`family`, marked as declared after it ran."""
    if record.family is not None:
        return record.family
    return family("after this record ran, so its Holm p is a reading, not a plan")


@dataclass(frozen=True)
class StepResult:
    """One of :data:`STEPS` tested on a record's seeds (:func:`steps`).

    Attributes:
        step, family, credits: the :class:`Step`'s ``what``, its declared family and ``credits``.
        p_fewer, p_more: the primary test's one-sided p-values (the later row collides less;
            more), and their Holm-adjusted twins ``p_holm_fewer``, ``p_holm_more``.
        min_p: the smallest p-value these seeds could give.
        test: the primary test, ``"rank"`` or ``"paired sign-flip"``.
        p_unpaired, p_paired: the p-value for fewer of either test (None: not paired).
        ratio, ratio_ci: the rate ratio (after / before) and its 95 % bootstrap interval.
        paper_ratio: the paper's ratio of the same rows (None: it has no figure for one).
        seeds: how many seeds each row has (after, before).
        verdict: one phrase, read at the adjusted p (:func:`verdict`).
    """

    step: str
    family: str
    credits: str | None
    p_fewer: float
    p_more: float
    min_p: float
    test: str
    p_unpaired: float
    p_paired: float | None
    ratio: float
    ratio_ci: tuple[float, float]
    paper_ratio: float | None
    seeds: tuple[int, int]
    p_holm_fewer: float = float("nan")
    p_holm_more: float = float("nan")
    verdict: str = ""

    @property
    def opposite(self) -> bool:
        """Whether the verdict reads the other direction (more collisions)."""
        return self.verdict.startswith(OPPOSITE)

    @property
    def verdict_p(self) -> float:
        """The Holm-adjusted p the verdict reads: for more collisions when it is the opposite of
        the step's direction, else for fewer."""
        return self.p_holm_more if self.opposite else self.p_holm_fewer

    @property
    def paper_inside(self) -> bool | None:
        """Whether the paper's ratio lies inside this step's 95 % interval (None: the paper has
        no ratio for it, or the interval is undefined)."""
        lo, hi = self.ratio_ci
        if self.paper_ratio is None or np.isnan(lo) or np.isnan(hi):
            return None
        return bool(lo <= self.paper_ratio <= hi)

    @property
    def cell(self) -> str:
        """The verdict as the steps table shows it, with what it says of the paper's size: a step
        in the paper's direction whose interval holds the paper's ratio reproduces its size too;
        one that does not, its direction only; a step not shown whose interval excludes the
        paper's ratio excludes a step of that size."""
        if self.opposite:
            return f"{self.verdict}: more collisions"
        inside = self.paper_inside
        if inside is None:
            return self.verdict
        if self.verdict.startswith(FOUND["paper"]):
            size = "the paper's size too" if inside else "the direction only, not the paper's size"
            return f"{self.verdict}: {size}"
        if not inside and self.verdict.startswith(("not shown", "cannot be decided")):
            return f"{self.verdict}; a step of the paper's size is excluded"
        return self.verdict

    @property
    def p_read(self) -> tuple[float, float, str]:
        """The p-value the verdict reads, its Holm-adjusted twin, and its direction: for more
        collisions when the verdict is the opposite, else for fewer."""
        if self.opposite:
            return self.p_more, self.p_holm_more, "more"
        return self.p_fewer, self.p_holm_fewer, "fewer"


def _tested(record: Record, st: Step, family_of: dict[str, str]) -> tuple[StepResult, float]:
    """:data:`STEPS`' ``st`` tested on ``record``'s seeds (before Holm), and the later row's
    speed when it is slow (else None)."""
    after, before = record.row(st.after), record.row(st.before)
    test = compare_seeds(after.as_result(), before.as_result(), paired=st.paired)
    paper_a, paper_b = after.paper_per_100mi, before.paper_per_100mi
    result = StepResult(
        step=st.what,
        family=family_of.get(st.what, st.family),
        credits=st.credits,
        p_fewer=test["p_fewer"],
        p_more=test["p_more"],
        min_p=test["min_p"],
        test=test["test"],
        p_unpaired=test["p_unpaired"],
        p_paired=test["p_paired"],
        ratio=test["ratio"],
        ratio_ci=test["ratio_ci"],
        paper_ratio=paper_a / paper_b if paper_a is not None and paper_b else None,
        seeds=(len(test["counts_a"]), len(test["counts_b"])),
    )
    return result, after.mph if after.slow_beside(record.expert_mph) else None


def steps(record: Record) -> list[StepResult]:
    """Each of :data:`STEPS` whose rows the record holds, tested on the seeds' counts, its
    p-values Holm-adjusted within its declared family (:func:`declared_family`), and its verdict
    read at the adjusted p."""
    family_of = declared_family(record).tests
    present = [st for st in STEPS if record.row(st.before) and record.row(st.after)]
    tested = [_tested(record, st, family_of) for st in present]
    out = []
    for fam in {r.family for r, _ in tested}:
        members = [(r, slow) for r, slow in tested if r.family == fam]
        fewer = holm([r.p_fewer for r, _ in members])
        more = holm([r.p_more for r, _ in members])
        for (r, slow), p_f, p_m in zip(members, fewer, more):
            test = {"p_fewer": r.p_fewer, "p_more": r.p_more, "min_p": r.min_p}
            words = verdict(test, slow, fam, (p_f, p_m))
            out.append(dataclasses.replace(r, p_holm_fewer=p_f, p_holm_more=p_m, verdict=words))
    order = [st.what for st in present]
    return sorted(out, key=lambda r: order.index(r.step))


def controls_line(tested: list[StepResult]) -> str:
    """One sentence per control among the ``tested`` steps (:func:`steps`): what its test found,
    and so whether the step it tests is credited to its method ("" without a control)."""
    found = []
    for st in tested:
        if st.credits is None:
            continue
        credited = st.verdict.startswith(FOUND["controls"])
        what = (
            "beaten" if credited else "the control collides less" if st.opposite else "not beaten"
        )
        credit = (
            "credited to its method"
            if credited
            else "not its method's: the control does better"
            if st.opposite
            else "not credited to its method"
        )
        found.append(
            f"{st.step}: {what} (Holm p = {st.verdict_p:.2g}, ratio {st.ratio:.2f}), so"
            f" '{st.credits}' is {credit}"
        )
    return "" if not found else "**What the controls found.** " + "; ".join(found) + "."


def record_dispersion(record: Record, near: str | None = None) -> dict[str, float] | None:
    """The negative-binomial dispersion of the record's seeds
    (:func:`~e2e_lite.driving.verdicts.fit_dispersion` over its rows of two or more seeds, each
    seed's count at its row's common budget); with ``near``, over the rows whose median rate is
    within :data:`POWER_RATES_WITHIN` of that row's only. None without such a row."""
    rows = [r for r in record.rows if len(r.seeds) >= 2]
    if near is not None and record.row(near) is not None:
        centre = _median_rate(record.row(near))
        rows = [r for r in rows if _within(_median_rate(r), centre, POWER_RATES_WITHIN)]
    counts = [seed_counts(r.as_result())[0] for r in rows]
    return fit_dispersion(counts) if counts else None


def _median_rate(row: Row) -> float:
    """A row's median seed rate [per 100 mi]."""
    counts, budget = seed_counts(row.as_result())
    return float(np.median(counts)) * 100.0 / budget


def _within(rate: float, centre: float, factor: float) -> bool:
    """Whether ``rate`` lies within ``factor`` of ``centre`` (either way; 0.5 per 100 mi floors
    both, a median of no collision is not infinitely far)."""
    a, b = max(rate, 0.5), max(centre, 0.5)
    return max(a, b) / min(a, b) <= factor


def shared_spread(record: Record) -> float:
    """How much of a seed's spread :data:`POWER_ROW` and :data:`POWER_PAIR` share: the Spearman
    rank correlation of their seeds' counts, at least 0 (0 without both rows)."""
    a, b = record.row(POWER_ROW), record.row(POWER_PAIR)
    if a is None or b is None or len(a.seeds) != len(b.seeds) or len(a.seeds) < 3:
        return 0.0
    from scipy.stats import spearmanr

    rho = spearmanr(seed_counts(a.as_result())[0], seed_counts(b.as_result())[0]).statistic
    return float(np.clip(np.nan_to_num(rho), 0.0, 0.95))


def record_power(record: Record) -> dict[str, Any] | None:
    """The record's power to find a :data:`POWER_STEP`-fold step at its own :data:`POWER_ROW`
    rate (the median seed's), with its seeds and miles per seed: under the seeds' spread fitted
    to the record (:func:`record_dispersion`) with the rank test (``power``) and the paired
    sign-flip test (``power_paired``), and without spread (``power_poisson``, an upper bound);
    and the smallest p-value its seeds can reach (:func:`~e2e_lite.driving.verdicts.power`).
    None without that row."""
    row = record.row(POWER_ROW)
    if row is None or len(row.seeds) < 2:
        return None
    counts, budget = seed_counts(row.as_result())
    rate = max(float(np.median(counts)) * 100.0 / budget, 0.5)  # (a zero rate has no step)
    fitted = record_dispersion(record, near=POWER_ROW)
    k, rho = fitted["dispersion"], shared_spread(record)
    spread_rank = power(len(counts), budget, rate, POWER_STEP, dispersion=k)
    spread_pair = power(
        len(counts), budget, rate, POWER_STEP, dispersion=k, test="sign-flip", shared=rho
    )
    poisson = power(len(counts), budget, rate, POWER_STEP)
    return {
        "seeds": len(counts),
        "miles_per_seed": budget,
        "rate_per_100mi": rate,
        "label": row.label,
        "power": spread_rank["power"],
        "power_paired": spread_pair["power"],
        "power_poisson": poisson["power"],
        "min_p": poisson["min_p"],
        "dispersion": fitted,
        "shared": rho,
    }


def power_line(record: Record) -> str:
    """The sentence under Table 1 that says what the record's seeds can find
    (:func:`record_power`); "" without the row it is stated at."""
    found = record_power(record)
    if found is None:
        return ""
    k = found["dispersion"]
    return (
        f" Power: {found['seeds']} seeds x {found['miles_per_seed']:.0f} mi find a true"
        f" {POWER_STEP:g}x step at {found['label']}'s median rate"
        f" ({found['rate_per_100mi']:.1f} per 100 mi) in {100 * found['power']:.0f} % of records"
        f" under the seeds' spread (rank test; paired sign-flip"
        f" {100 * found['power_paired']:.0f} %, its pairs sharing {found['shared']:.2f} of the"
        f" spread, the rank correlation of the seeds of {found['label']} and its fine-tune), a"
        f" negative binomial of dispersion {k['dispersion']:.2f} [{k['low']:.2f}-{k['high']:.2f}]"
        f" fitted to this record's {k['rows']} rows of seeds whose rates lie within"
        f" {POWER_RATES_WITHIN:g}x of it; {100 * found['power_poisson']:.0f} % if seeds did not"
        f" differ (Poisson: an upper bound); at p < 0.05 before Holm's adjustment, which only"
        f" lowers it. The smallest reachable p is {found['min_p']:.2g}."
    )


def family_line(record: Record) -> str:
    """The sentence under Table 1 that names the record's families of tests and when they were
    declared."""
    fam = declared_family(record)
    parts = []
    for key, text in fam.families.items():
        n = sum(f == key for f in fam.tests.values())
        parts.append(f"{text} ({n} test{'s' * (n != 1)})")
    return (
        f" The families of tests, declared {fam.declared}: " + "; ".join(parts) + ". Each"
        " family's p-values are Holm-adjusted together, and the verdict reads the adjusted p at"
        " 0.05; 'reproduces' means the direction of the paper's step, whose own ratio is beside"
        " ours ('beats its control', 'fewer collisions': the same for a control, a step beyond)."
    )


def _seeds_of(row: Row | dict[str, Any]) -> dict[str, Any]:
    """A record's row, or an evaluation's pooled result, as the seed-level functions read it."""
    return row.as_result() if isinstance(row, Row) else row


def dispersion(row: Row) -> float | None:
    """The seeds' chi-square against one shared rate (degrees of freedom: seeds - 1); far above
    its degrees of freedom, the seeds do not drive alike. ``None`` for one run."""
    if len(row.seeds) < 2:
        return None
    k = np.array([s.collisions for s in row.seeds], dtype=float)
    m = np.array([s.miles for s in row.seeds], dtype=float)
    expected = m * k.sum() / m.sum()
    return float(np.sum((k - expected) ** 2 / np.maximum(expected, 1e-12)))


#: the spread a paper row's seeds may show: its worst seed's rate at most this many times the
#: median's
SPREAD_GOAL = 3.0


def spread(row: Row | dict[str, Any]) -> float | None:
    """The worst seed's rate over the median seed's (``inf`` when the median is 0 and the worst
    is not; ``None`` for one run, e.g. an evaluation's result of a driver with no seeds): how far
    one training seed strays from the recipe's typical. ``row``: a record's row, or a pooled
    evaluation's result (a dict with ``"seeds"``)."""
    seeds = _seeds_of(row)
    if len(seeds.get("seeds") or []) < 2:
        return None
    rates = seed_rates(seeds)
    median, worst = float(np.median(rates)), float(rates.max())
    if median == 0.0:
        return 1.0 if worst == 0.0 else float("inf")
    return worst / median
