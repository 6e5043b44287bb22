"""The record's tests, declared before it runs: which rows are compared (:data:`STEPS`), in
which family each is Holm-adjusted (:data:`FAMILIES`), the outcome each gets on the seeds' counts
(:func:`steps`, one :class:`StepResult` each), and the record's power under its seeds' fitted
spread (:func:`record_power`). :mod:`e2e_lite.record.run` writes the families into the shares it
runs; :mod:`e2e_lite.record.words` says each outcome in words and :mod:`e2e_lite.record.report` renders
them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.stats import spearmanr

from ..stats.power import Dispersion, fit_dispersion, holm, power
from ..stats.seeds import SeedTest, compare_seeds, seed_counts
from .rows import Family, Record, Row, slow


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
    "data": "does new data beat the same fine-tunes on none?",
}
#: why the tests are grouped so, written where they are declared: a family is one question a
#: reader takes as one claim, so Holm within it holds the chance that any of its answers is
#: false at 0.05; the Holm p over every test of the record says what survives when the whole
#: record is read as one claim
FAMILY_REASON = (
    "a family is one question, read as one claim, so Holm's adjustment within it holds the"
    " chance that any of its answers is false at 0.05; the Holm p over every test of the record"
    " is beside it, for a reader who takes the whole record as one claim"
)
#: the outcomes a step is tested on: collisions, and off-centre episodes (the interventions
#: that were neither collisions nor stalls); an off-centre test is declared under its step's
#: name with this suffix
OUTCOMES = ("collisions", "off_centre")
OFF_CENTRE_SUFFIX = " (off-centre)"
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
    Step(
        "dagger_no_new_data", "dagger", "DAgger against its fine-tunes on no new data", True, "data"
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

#: a step's outcome, read at its p-values: the later row collides less, more, neither (these
#: seeds could not have shown it), or neither (they could have)
FEWER, MORE, UNDECIDABLE, NOT_SHOWN = "fewer", "more", "undecidable", "not shown"


def outcome(p_fewer: float, p_more: float, min_p: float, level: float = 0.95) -> str:
    """A step's outcome (:data:`FEWER`, :data:`MORE`, :data:`UNDECIDABLE`, :data:`NOT_SHOWN`)
    from its one-sided p-values (Holm-adjusted, in a family) and the smallest p-value its seeds
    could give."""
    cut = 1.0 - level - 1e-9
    if p_fewer < cut:
        return FEWER
    if p_more < cut:
        return MORE
    return UNDECIDABLE if min_p >= cut else NOT_SHOWN


#: the steps declared after the record of 28eba5c ran: a record that declared no families is
#: read without them
LATER_STEPS = ("DAgger against its fine-tunes on no new data",)


def family(declared: str, outcomes: tuple[str, ...] = OUTCOMES) -> Family:
    """The families of :data:`STEPS` as a record holds them, with when they were ``declared``:
    every step on each of ``outcomes`` (an off-centre test named with
    :data:`OFF_CENTRE_SUFFIX`), in its step's family, and, with both outcomes, why the tests
    are grouped so (:data:`FAMILY_REASON`)."""
    tests = {st.what: st.family for st in STEPS}
    if "off_centre" in outcomes:
        tests |= {st.what + OFF_CENTRE_SUFFIX: st.family for st in STEPS}
    reason = FAMILY_REASON if "off_centre" in outcomes else None
    return Family(dict(FAMILIES), tests, "holm", declared, reason)


def declares_off_centre(record: Record) -> bool:
    """Whether the record declared its steps' off-centre tests before it ran."""
    return record.family is not None and any(
        t.endswith(OFF_CENTRE_SUFFIX) for t in record.family.tests
    )


def declared_family(record: Record) -> Family:
    """The record's families of tests: as it declares them, or (a record from before the
    declaration) :func:`family`, marked as declared after it ran."""
    if record.family is not None:
        return record.family
    read = family("after this record ran, so its Holm p is a reading, not a plan", OUTCOMES[:1])
    tests = {t: f for t, f in read.tests.items() if t not in LATER_STEPS}
    return dataclasses.replace(read, tests=tests)


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
        slow_mph: the later row's speed when it drove slow beside the expert (else None).
        outcome: read at the adjusted p (:func:`outcome`; words: :mod:`e2e_lite.record.words`).
        measure: the count compared, one of :data:`OUTCOMES`.
        p_holm_all_fewer, p_holm_all_more: Holm-adjusted over every declared test of the record
            (NaN where it declared no such reading).
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
    slow_mph: float | None = None
    p_holm_fewer: float = float("nan")
    p_holm_more: float = float("nan")
    outcome: str = ""
    measure: str = "collisions"
    p_holm_all_fewer: float = float("nan")
    p_holm_all_more: float = float("nan")

    @property
    def opposite(self) -> bool:
        """Whether the outcome is the other direction (more collisions)."""
        return self.outcome == MORE

    @property
    def verdict_p(self) -> float:
        """The Holm-adjusted p the verdict reads: for more collisions when it is the opposite of
        the step's direction, else for fewer."""
        return self.p_holm_more if self.opposite else self.p_holm_fewer

    @property
    def verdict_p_all(self) -> float:
        """:attr:`verdict_p`'s twin adjusted over every test of the record (NaN: none)."""
        return self.p_holm_all_more if self.opposite else self.p_holm_all_fewer

    @property
    def paper_inside(self) -> bool | None:
        """Whether the paper's ratio lies inside this step's 95 % interval (None: the paper has
        no ratio for it, or the interval is undefined)."""
        lo, hi = self.ratio_ci
        if self.paper_ratio is None or np.isnan(lo) or np.isnan(hi):
            return None
        return bool(lo <= self.paper_ratio <= hi)

    @property
    def p_read(self) -> tuple[float, float, str]:
        """The p-value the verdict reads, its Holm-adjusted twin, and its direction: for more
        collisions when the verdict is the opposite, else for fewer."""
        if self.opposite:
            return self.p_more, self.p_holm_more, "more"
        return self.p_fewer, self.p_holm_fewer, "fewer"


def test_step(
    st: Step, test: SeedTest, paper_ratio: float | None = None, slow_mph: float | None = None
) -> StepResult:
    """:data:`STEPS`' ``st`` from its seed-level test (:func:`~e2e_lite.stats.seeds.compare_seeds`
    of the later row against the earlier: a record's rows, or a chapter's pooled results), its
    outcome read at its own p-values (:func:`steps` reads a record's at Holm's)."""
    return StepResult(
        step=st.what,
        family=st.family,
        credits=st.credits,
        p_fewer=test.p_fewer,
        p_more=test.p_more,
        min_p=test.min_p,
        test=test.test,
        p_unpaired=test.p_unpaired,
        p_paired=test.p_paired,
        ratio=test.ratio,
        ratio_ci=test.ratio_ci,
        paper_ratio=paper_ratio,
        seeds=(len(test.counts_a), len(test.counts_b)),
        slow_mph=slow_mph,
        p_holm_fewer=test.p_fewer,
        p_holm_more=test.p_more,
        outcome=outcome(test.p_fewer, test.p_more, test.min_p),
    )


def _tested(
    record: Record, st: Step, family_of: dict[str, str], measure: str = "collisions"
) -> StepResult:
    """:data:`STEPS`' ``st`` tested on ``record``'s seeds' ``measure`` (before Holm)."""
    after, before = record.row(st.after), record.row(st.before)
    paper_a, paper_b = after.paper_per_100mi, before.paper_per_100mi
    paper = (
        paper_a / paper_b if paper_a is not None and paper_b and measure == OUTCOMES[0] else None
    )
    test = compare_seeds(after, before, paired=st.paired, outcome=measure)
    result = test_step(st, test, paper, slow(after.mph, record.expert_mph))
    name = st.what + (OFF_CENTRE_SUFFIX if measure == "off_centre" else "")
    return dataclasses.replace(result, family=family_of.get(name, st.family), measure=measure)


def _kept_interventions(record: Record, st: Step) -> bool:
    """Whether both of ``st``'s rows recorded their seeds' interventions (the off-centre test
    needs them)."""
    rows = (record.row(st.after), record.row(st.before))
    return all(r is not None and r.interventions is not None for r in rows)


def _declared_tests(record: Record) -> list[StepResult]:
    """Every declared test whose rows the record holds (a record that declared its families
    tests only what it declared; one from before the declaration every step on collisions),
    Holm-adjusted within its family and, where the record declared its off-centre tests, over
    every test too."""
    declared = declared_family(record).tests
    held = [st for st in STEPS if record.row(st.before) and record.row(st.after)]
    tested = []
    for measure in OUTCOMES if declares_off_centre(record) else OUTCOMES[:1]:
        suffix = OFF_CENTRE_SUFFIX if measure == "off_centre" else ""
        for st in held:
            kept = measure == "collisions" or _kept_interventions(record, st)
            if st.what + suffix in declared and kept:
                tested.append(_tested(record, st, declared, measure))
    out = []
    for fam in dict.fromkeys(r.family for r in tested):
        out += _read_at_holm([r for r in tested if r.family == fam])
    if declares_off_centre(record):
        fewer, more = holm([r.p_fewer for r in out]), holm([r.p_more for r in out])
        out = [
            dataclasses.replace(r, p_holm_all_fewer=f, p_holm_all_more=m)
            for r, f, m in zip(out, fewer, more)
        ]
    order = [(r.measure, r.step) for r in tested]
    return sorted(out, key=lambda r: order.index((r.measure, r.step)))


def steps(record: Record) -> list[StepResult]:
    """Each declared test of :data:`STEPS` on collisions whose rows the record holds, tested on
    the seeds' counts, its p-values Holm-adjusted within its declared family
    (:func:`declared_family`, and over every test where the record declared that), its outcome
    read at the adjusted p."""
    return [r for r in _declared_tests(record) if r.measure == "collisions"]


#: the family of the off-centre tests of a record whose families did not declare them: read
#: after it ran, Holm-adjusted together
OFF_CENTRE_READING = "off-centre, read after the record"


def off_centre_steps(record: Record) -> list[StepResult]:
    """Each of :data:`STEPS` tested on the seeds' off-centre episodes (the interventions that
    were neither collisions nor stalls), where both rows recorded them: the second outcome of
    every step. A record that declared them reads them in their declared families (as
    :func:`steps`); one that did not reads them after it ran, all in one family
    (:data:`OFF_CENTRE_READING`), Holm-adjusted together; [] where none was recorded."""
    if declares_off_centre(record):
        return [r for r in _declared_tests(record) if r.measure == "off_centre"]
    declared = declared_family(record).tests
    kept = [st for st in STEPS if st.what in declared and _kept_interventions(record, st)]
    tested = [_tested(record, st, {}, "off_centre") for st in kept]
    return _read_at_holm([dataclasses.replace(r, family=OFF_CENTRE_READING) for r in tested])


def _read_at_holm(family: list[StepResult]) -> list[StepResult]:
    """One family's steps with their p-values Holm-adjusted together and each outcome read at
    the adjusted p. A step is undecidable when even its smallest reachable p, adjusted with the
    family's (Holm's adjustment only rises with any p of the family), cannot go below 0.05."""
    fewer = holm([r.p_fewer for r in family])
    more = holm([r.p_more for r in family])
    reach = holm([r.min_p for r in family])
    return [
        dataclasses.replace(r, p_holm_fewer=p_f, p_holm_more=p_m, outcome=outcome(p_f, p_m, lo))
        for r, p_f, p_m, lo in zip(family, fewer, more, reach)
    ]


def record_dispersion(record: Record, near: str | None = None) -> Dispersion | None:
    """The negative-binomial dispersion of the record's seeds
    (:func:`~e2e_lite.stats.power.fit_dispersion` over its rows of two or more seeds, each
    seed's count at its row's common budget); with ``near``, over the rows whose median rate is
    within :data:`POWER_RATES_WITHIN` of that row's only. None without such a row."""
    rows = [r for r in record.rows if len(r.seeds) >= 2]
    if near is not None and record.row(near) is not None:
        centre = median_rate(record.row(near))
        rows = [r for r in rows if _within(median_rate(r), centre, POWER_RATES_WITHIN)]
    counts = [seed_counts(r).counts for r in rows]
    return fit_dispersion(counts) if counts else None


def median_rate(row: Row) -> float:
    """A row's median seed rate [per 100 mi]."""
    counts, budget = seed_counts(row)
    return float(np.median(counts)) * 100.0 / budget


def _within(rate: float, centre: float, factor: float) -> bool:
    """Whether ``rate`` lies within ``factor`` of ``centre`` (either way; 0.5 per 100 mi floors
    both, a median of no collision is not infinitely far)."""
    a, b = max(rate, 0.5), max(centre, 0.5)
    return max(a, b) / min(a, b) <= factor


#: the largest shared spread the power simulates (a pair sharing all of it is one seed)
SHARED_MAX = 0.95


def shared_spread(record: Record, level: float = 0.95) -> tuple[float, float, float]:
    """How much of a seed's spread :data:`POWER_ROW` and :data:`POWER_PAIR` share: the Spearman
    rank correlation of their seeds' counts, and the range the data allow for it (Fisher's z
    with Bonett and Wright's standard error for Spearman's rho, ``sqrt((1 + rho^2 / 2) /
    (n - 3))``), each within 0 and :data:`SHARED_MAX` (all 0 without both rows or with fewer
    than three seeds; with three, the range is all of it)."""
    from scipy.stats import norm

    a, b = record.row(POWER_ROW), record.row(POWER_PAIR)
    if a is None or b is None or len(a.seeds) != len(b.seeds) or len(a.seeds) < 3:
        return 0.0, 0.0, 0.0
    n = len(a.seeds)
    rho = float(np.nan_to_num(spearmanr(seed_counts(a).counts, seed_counts(b).counts).statistic))
    rho = float(np.clip(rho, -0.999, 0.999))
    if n < 4:  # (three seeds allow any shared spread)
        return float(np.clip(rho, 0.0, SHARED_MAX)), 0.0, SHARED_MAX
    half = norm.ppf(0.5 + level / 2.0) * np.sqrt((1.0 + rho * rho / 2.0) / (n - 3))
    ends = np.tanh(np.arctanh(rho) + np.array([-half, 0.0, half]))
    low, mid, high = (float(np.clip(x, 0.0, SHARED_MAX)) for x in ends)
    return mid, low, high


@dataclass(frozen=True)
class RecordPower:
    """What :func:`record_power` found.

    Attributes:
        seeds, miles_per_seed: the record's seeds per row and each seed's budget [mi].
        rate_per_100mi, label: the median seed's rate of :data:`POWER_ROW` and that row's name.
        power, power_paired, power_poisson: the share of records that find the step (rank test,
            paired sign-flip test, both under the fitted spread; rank test without spread).
        min_p: the smallest p-value its seeds can reach.
        dispersion: the spread fitted to the rows near :data:`POWER_ROW`'s rate.
        shared: the share of that spread a pair shares (:func:`shared_spread`), and
            ``shared_range`` the range the data allow for it, with ``power_paired_range`` the
            paired test's power at its two ends.
    """

    seeds: int
    miles_per_seed: float
    rate_per_100mi: float
    label: str
    power: float
    power_paired: float
    power_poisson: float
    min_p: float
    dispersion: Dispersion
    shared: float
    shared_range: tuple[float, float] = (0.0, 0.0)
    power_paired_range: tuple[float, float] = (0.0, 0.0)


def record_power(record: Record) -> RecordPower | None:
    """The record's power to find a :data:`POWER_STEP`-fold step at its own :data:`POWER_ROW`
    rate (the median seed's), with its seeds and miles per seed: under the seeds' spread fitted
    to the record (:func:`record_dispersion`) with the rank test (``power``) and the paired
    sign-flip test (``power_paired``), and without spread (``power_poisson``, an upper bound);
    and the smallest p-value its seeds can reach (:func:`~e2e_lite.stats.power.power`).
    None without that row."""
    row = record.row(POWER_ROW)
    if row is None or len(row.seeds) < 2:
        return None
    counts, budget = seed_counts(row)
    rate = max(median_rate(row), 0.5)  # (a zero rate has no step)
    fitted = record_dispersion(record, near=POWER_ROW)
    k, (rho, rho_low, rho_high) = fitted.k, shared_spread(record)
    spread_rank = power(len(counts), budget, rate, POWER_STEP, dispersion=k)

    def paired(shared: float) -> float:
        return power(
            len(counts), budget, rate, POWER_STEP, dispersion=k, test="sign-flip", shared=shared
        ).power

    poisson = power(len(counts), budget, rate, POWER_STEP)
    return RecordPower(
        seeds=len(counts),
        miles_per_seed=budget,
        rate_per_100mi=rate,
        label=row.label,
        power=spread_rank.power,
        power_paired=paired(rho),
        power_poisson=poisson.power,
        min_p=poisson.min_p,
        dispersion=fitted,
        shared=rho,
        shared_range=(rho_low, rho_high),
        power_paired_range=(paired(rho_low), paired(rho_high)),
    )


#: the spread a paper row's seeds may show: its worst seed's rate at most this many times the
#: median's
SPREAD_GOAL = 3.0
