"""Every sentence a verdict prints, in one place: the statistics (:mod:`e2e_lite.stats`) and the
record's tests (:mod:`.stats`) return numbers, and these functions say them.

* the chapters' lines: two pooled rates compared (:func:`rates`), two rows seed by seed
  (:func:`seeds`);
* the record's: a step's verdict (:func:`verdict`) and its cell in the steps table
  (:func:`cell`), what the controls found (:func:`controls`), the families of tests
  (:func:`families`) and the power (:func:`power`) under Table 1.
"""

from __future__ import annotations

import math

from ..stats.rates import RateTest
from ..stats.seeds import SeedTest
from .rows import Record
from .stats import (
    FEWER,
    MORE,
    OFF_CENTRE_READING,
    POWER_RATES_WITHIN,
    POWER_STEP,
    UNDECIDABLE,
    StepResult,
    declared_family,
    declares_off_centre,
    record_power,
)

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


def rates(test: RateTest) -> str:
    """Two pooled rates compared (:func:`~e2e_lite.stats.rates.compare_rates`), in one line."""
    head = f"{test.rate_a:.1f} vs {test.rate_b:.1f} per 100 mi"
    if not test.different:
        return f"{head}: a difference not shown (p = {test.p_value:.2f})"
    word = "fewer" if test.rate_a < test.rate_b else "more"
    return f"{head}: {word} collisions beyond chance (p = {test.p_value:.2g})"


def seeds(test: SeedTest) -> str:
    """Two rows compared seed by seed (:func:`~e2e_lite.stats.seeds.compare_seeds`), in one
    line: the medians, the pooled ratio, and what the primary test found (or why it could not)."""
    ratio, (lo, hi) = test.ratio, test.ratio_ci
    ratio_text = (
        "no collision in either" if math.isnan(ratio) else f"{ratio:.2f} [{lo:.2f}, {hi:.2f}]"
    )
    med_a, med_b = test.median_rates()
    med = (
        f"median {med_a:.1f} vs {med_b:.1f} per 100 mi "
        f"({len(test.counts_a)} vs {len(test.counts_b)} seeds), pooled ratio {ratio_text}"
    )
    if test.fewer:
        return f"{med}: fewer collisions, seed by seed ({test.test} p = {test.p_fewer:.2g})"
    if test.more:
        return f"{med}: more collisions, seed by seed ({test.test} p = {test.p_more:.2g})"
    p = min(test.p_fewer, test.p_more)
    reach = "" if test.reachable else f"; these seeds cannot reach p < {1 - test.level:.2g}"
    text = f"{med}: not shown at the seed level ({test.test} p = {p:.2g}{reach})"
    if test.narrow:
        text += (
            f"; the interval, bootstrapped over {len(test.counts_a)} seeds, is too narrow to read"
        )
    return text


def verdict(st: StepResult) -> str:
    """A step's verdict, read at its family's Holm-adjusted p-values, in the words of its family
    (:data:`FOUND`), with the later row's speed when it drove slow."""
    if st.outcome == FEWER:
        text = FOUND.get(st.family, FOUND["paper"])
    elif st.outcome == MORE:
        text = OPPOSITE
    elif st.outcome == UNDECIDABLE:
        text = "cannot be decided with these seeds"
    else:
        text = "not shown at the seed level"
    return text + (f", at {st.slow_mph:.1f} mph" if st.slow_mph is not None else "")


def paper_ratio(st: StepResult, test: SeedTest) -> str:
    """The paper's ratio and where it lies against a step's interval: inside, outside, no
    interval, or one too narrow to read (:attr:`~e2e_lite.stats.seeds.SeedTest.narrow`)."""
    where = {None: "no CI", True: "inside the CI", False: "outside the CI"}[st.paper_inside]
    where = "an interval too narrow to read" if test.narrow else where
    return (
        "the paper: no ratio"
        if st.paper_ratio is None
        else f"the paper's ratio {st.paper_ratio:.2g}: {where}"
    )


def off_centre(st: StepResult) -> str:
    """A step's second outcome, its off-centre episodes (:func:`~.stats.off_centre_steps`)."""
    return {
        FEWER: "fewer off-centre episodes",
        MORE: "more off-centre episodes",
        UNDECIDABLE: "cannot be decided with these seeds",
    }.get(st.outcome, "not shown at the seed level")


def better_driver(collisions: StepResult, off: StepResult | None) -> str:
    """Whether a step makes a better driver: fewer collisions and not more off-centre episodes,
    each at the seed level. Where it wins one and loses the other, it says so in those words;
    an off-centre test read after the record ran can refute the claim but not make it."""
    if off is None:
        return "off-centre episodes not recorded"
    declared = off.family != OFF_CENTRE_READING
    if collisions.outcome == FEWER and off.outcome == MORE:
        return "fewer collisions, more off-centre episodes: not a better driver"
    if collisions.outcome == MORE and off.outcome == FEWER:
        return "more collisions, fewer off-centre episodes: not a better driver"
    if collisions.outcome == MORE or off.outcome == MORE:
        return "a worse driver"
    if collisions.outcome == FEWER:
        return "a better driver" if declared else "not shown: its off-centre test was not declared"
    return "not shown to be a better driver"


def cell(st: StepResult) -> str:
    """The verdict as the steps table shows it, with what it says of the paper's size: a step
    in the paper's direction whose interval holds the paper's ratio reproduces its size too;
    one that does not, its direction only; a step not shown whose interval excludes the
    paper's ratio excludes a step of that size."""
    said = verdict(st)
    if st.opposite:
        return f"{said}: more collisions"
    inside = st.paper_inside
    if inside is None:
        return said
    if said.startswith(FOUND["paper"]):
        size = "the paper's size too" if inside else "the direction only, not the paper's size"
        return f"{said}: {size}"
    if not inside and said.startswith(("not shown", "cannot be decided")):
        return f"{said}; a step of the paper's size is excluded"
    return said


def controls(tested: list[StepResult]) -> str:
    """One sentence per control among the ``tested`` steps (:func:`~.stats.steps`): what its
    test found, and so whether the step it tests is credited to its method ("" without a
    control)."""
    found = []
    for st in tested:
        if st.credits is None:
            continue
        credited = verdict(st).startswith(FOUND["controls"])
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


def power(record: Record) -> str:
    """The sentence under Table 1 that says what the record's seeds can find
    (:func:`~.stats.record_power`); "" without the row it is stated at."""
    found = record_power(record)
    if found is None:
        return ""
    k = found.dispersion
    (lo, hi), (p_lo, p_hi) = found.shared_range, found.power_paired_range
    return (
        f" Power: {found.seeds} seeds x {found.miles_per_seed:.0f} mi find a true"
        f" {POWER_STEP:g}x step at {found.label}'s median rate"
        f" ({found.rate_per_100mi:.1f} per 100 mi) in {100 * found.power:.0f} % of records"
        f" under the seeds' spread (rank test; paired sign-flip"
        f" {100 * found.power_paired:.0f} %, its pairs sharing {found.shared:.2f} of the"
        f" spread, the rank correlation of the seeds of {found.label} and its fine-tune, which"
        f" the data allow from {lo:.2f} to {hi:.2f}: power {100 * p_lo:.0f}-{100 * p_hi:.0f} %), a"
        f" negative binomial of dispersion {k.k:.2f} [{k.low:.2f}-{k.high:.2f}]"
        f" fitted to this record's {k.rows} rows of seeds whose rates lie within"
        f" {POWER_RATES_WITHIN:g}x of it; {100 * found.power_poisson:.0f} % if seeds did not"
        f" differ (Poisson: an upper bound); at p < 0.05 before Holm's adjustment, which only"
        f" lowers it. The smallest reachable p is {found.min_p:.2g}."
    )


def families(record: Record) -> str:
    """The sentence under Table 1 that names the record's families of tests and when they were
    declared."""
    fam = declared_family(record)
    parts = []
    for key, text in fam.families.items():
        n = sum(f == key for f in fam.tests.values())
        parts.append(f"{text} ({n} test{'s' * (n != 1)})")
    both = (
        " Every step is tested on both outcomes, collisions and off-centre episodes, in its"
        " family; the Holm p over every test of the record is beside each family's ('all')."
        if declares_off_centre(record)
        else ""
    )
    why = f" Why: {fam.reason}." if fam.reason else ""
    return (
        f" The families of tests, declared {fam.declared}: " + "; ".join(parts) + f".{both}{why}"
        " Each family's p-values are Holm-adjusted together, and the verdict reads the adjusted p"
        " at 0.05; 'reproduces' means the direction of the paper's step, whose own ratio is beside"
        " ours ('beats its control', 'fewer collisions': the same for a control, a step beyond)."
    )
