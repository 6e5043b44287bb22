"""The record's tests, declared before it runs: which rows are compared (:data:`STEPS`), in which
family each is Holm-adjusted (:data:`FAMILIES`), the verdict each gets on the seeds' counts
(:func:`steps`), what the controls found (:func:`controls_line`), and the record's power under its
seeds' fitted spread (:func:`record_power`). :mod:`e2e_lite.record` writes the families into the
record it runs; :mod:`e2e_lite.report` renders the verdicts. Both import this module, which imports
neither of them.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from .driving.verdicts import compare_seeds, fit_dispersion, holm, power, seed_counts


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


#: the families of tests, declared before a record runs (issue 64): the p-values of one family
#: are Holm-adjusted together and the verdict reads the adjusted p. Two questions, two families:
#: does each of the paper's steps reproduce, and is each step the method's rather than the extra
#: training it came with?
FAMILIES = {
    "paper": "the paper's steps: does each reproduce?",
    "beyond": "beyond the paper: does DAgger's step hold?",
    "controls": "each method against its control: is the step the method's?",
}
#: the record's tests; the paper's steps each go "better" in the paper (seed 000)
STEPS = (
    Step("actuators", "gmm", "Baseline E2E -> trajectory GMM", False, "paper"),
    Step("gmm", "gmm_affordance", "GMM -> + affordance", False, "paper"),
    Step("gmm_affordance", "gmm_affordance_cvar", "+ affordance -> + CVaR", True, "paper"),
    Step("gmm_affordance_control", "gmm_affordance_cvar", "CVaR against its control (the mean)",
         True, "controls", "+ affordance -> + CVaR"),
    Step("gmm_affordance_w0", "gmm_affordance", "affordance loss against its control (w = 0)",
         False, "controls", "GMM -> + affordance"),
    Step("gmm_affordance_cvar", "dagger", "+ CVaR -> + DAgger", True, "beyond"),
    Step("dagger_control", "dagger", "DAgger against its control (the expert's samples)",
         True, "controls", "+ CVaR -> + DAgger"),
)  # fmt: skip
#: the row whose rate the record's power is stated at (issue 57), and the step it must find
POWER_ROW, POWER_STEP = "gmm_affordance", 2.0
#: a row slower than this share of the expert's speed is marked
SLOW_SHARE = 0.9


#: what a verdict says when the later row collides less, per family: a step beyond the paper
#: has nothing to reproduce, and a method that beats its control is credited
FOUND = {"paper": "reproduces", "controls": "beats its control", "beyond": "fewer collisions"}
#: what a verdict says when the later row collides more, in every family
OPPOSITE = "the opposite"


def verdict(test: dict[str, Any], slow_mph: float | None, family: str = "paper") -> str:
    """A step's verdict from its seed-level test (:func:`~e2e_lite.driving.verdicts.compare_seeds`
    of the later row against the earlier), read at its family's Holm-adjusted p-values
    (``p_holm_fewer``, ``p_holm_more``; the raw ones where absent), with the later row's speed
    when it is slow; in the words of its ``family`` (:data:`FOUND`)."""
    fewer = test.get("p_holm_fewer", test["p_fewer"]) < 0.05 - 1e-9
    more = test.get("p_holm_more", test["p_more"]) < 0.05 - 1e-9
    if fewer:
        text = FOUND.get(family, FOUND["paper"])
    elif more:
        text = OPPOSITE
    elif test["min_p"] >= 0.05:
        text = "cannot be decided with these seeds"
    else:
        text = "not shown at the seed level"
    return text + (f", at {slow_mph:.1f} mph" if slow_mph is not None else "")


def family(declared: str) -> dict[str, Any]:
    """The families of :data:`STEPS` as a record holds them, with when they were ``declared``."""
    tests = {st.what: st.family for st in STEPS}
    return {"families": FAMILIES, "tests": tests, "adjustment": "holm", "declared": declared}


def declared_family(record: dict[str, Any]) -> dict[str, Any]:
    """The record's families of tests: as its JSON declares them, or (a record from before the
    declaration, issue 64) :func:`family`, marked as declared after it ran."""
    if "family" in record:
        return record["family"]
    return family("after this record ran (issue 64), so its Holm p is a reading, not a plan")


def steps(record: dict[str, Any]) -> list[dict[str, Any]]:
    """Each of :data:`STEPS` present in the record, tested on the seeds' counts: the primary
    p-value and its test, the unpaired and paired p-values, the p-value Holm-adjusted within its
    declared family (:func:`declared_family`), the rate ratio (after / before) with its 95 %
    bootstrap interval, the paper's ratio, and the verdict (read at the adjusted p)."""
    rows = {r["key"]: r for r in record["rows"]}
    expert_mph = rows["expert"]["mph"] if "expert" in rows else None
    family_of = declared_family(record)["tests"]
    out = []
    for st in STEPS:
        if st.before not in rows or st.after not in rows:
            continue
        test = compare_seeds(rows[st.after], rows[st.before], paired=st.paired)
        mph = rows[st.after]["mph"]
        paper_a, paper_b = rows[st.after]["paper_per_100mi"], rows[st.before]["paper_per_100mi"]
        out.append(
            {"step": st.what, "family": family_of.get(st.what, st.family),
             "credits": st.credits, "p_better": test["p_fewer"], "p_worse": test["p_more"],
             "min_p": test["min_p"], "test": test["test"], "p_unpaired": test["p_unpaired"],
             "p_paired": test["p_paired"], "ratio": test["ratio"], "ratio_ci": test["ratio_ci"],
             "paper_ratio": paper_a / paper_b if paper_a is not None and paper_b else None,
             "seeds": (len(test["counts_a"]), len(test["counts_b"])),
             "slow_mph": mph if expert_mph and mph < SLOW_SHARE * expert_mph else None}
        )  # fmt: skip
    for family in {o["family"] for o in out}:
        members = [o for o in out if o["family"] == family]
        for key, adjusted in (("p_better", "p_holm"), ("p_worse", "p_holm_worse")):
            for o, p in zip(members, holm([o[key] for o in members])):
                o[adjusted] = p
    for o in out:
        test = {"p_fewer": o["p_better"], "p_more": o["p_worse"], "min_p": o["min_p"],
                "p_holm_fewer": o["p_holm"], "p_holm_more": o["p_holm_worse"]}  # fmt: skip
        o["verdict"] = verdict(test, o.pop("slow_mph"), o["family"])
    return out


def verdict_p(step: dict[str, Any]) -> float:
    """The Holm-adjusted p a tested step's verdict (:func:`steps`) reads: the one for more
    collisions when the verdict is the opposite of the step's direction, else the one for fewer."""
    return step["p_holm_worse"] if step["verdict"].startswith(OPPOSITE) else step["p_holm"]


def verdict_cell(step: dict[str, Any]) -> str:
    """A tested step's verdict as the steps table shows it: the opposite of the step's direction
    with the p it reads, since the table's p-values are those for fewer collisions."""
    if step["verdict"].startswith(OPPOSITE):
        return f"{step['verdict']}: more collisions, Holm p {verdict_p(step):.2g}"
    return step["verdict"]


def controls_line(tested: list[dict[str, Any]]) -> str:
    """One sentence per control among the ``tested`` steps (:func:`steps`): what its test found,
    and so whether the step it tests is credited to its method ("" without a control)."""
    found = []
    for st in tested:
        if st["credits"] is None:
            continue
        credited = st["verdict"].startswith(FOUND["controls"])
        worse = st["verdict"].startswith(OPPOSITE)
        what = "beaten" if credited else "the control collides less" if worse else "not beaten"
        found.append(
            f"{st['step']}: {what} (Holm p = {verdict_p(st):.2g}, ratio {st['ratio']:.2f}), so"
            f" '{st['credits']}' is "
            + ("credited to its method" if credited else "not credited to its method")
        )
    return "" if not found else "**What the controls found.** " + "; ".join(found) + "."


def record_dispersion(record: dict[str, Any]) -> dict[str, float] | None:
    """The negative-binomial dispersion of the record's seeds
    (:func:`~e2e_lite.driving.verdicts.fit_dispersion` over every row of two or more seeds, each
    seed's count at its row's common budget); None without such a row."""
    counts = [seed_counts(r)[0] for r in record["rows"] if len(r["seeds"]) >= 2]
    return fit_dispersion(counts) if counts else None


def record_power(record: dict[str, Any]) -> dict[str, Any] | None:
    """The record's power to find a :data:`POWER_STEP`-fold step at its own :data:`POWER_ROW`
    rate (the median seed's), with its seeds and miles per seed: under the seeds' spread fitted
    to the record (:func:`record_dispersion`) with the rank test (``power``) and the paired
    sign-flip test (``power_paired``), and without spread (``power_poisson``, an upper bound);
    and the smallest p-value its seeds can reach (:func:`~e2e_lite.driving.verdicts.power`).
    None without that row."""
    row = next((r for r in record["rows"] if r["key"] == POWER_ROW), None)
    if row is None or len(row["seeds"]) < 2:
        return None
    counts, budget = seed_counts(row)
    rate = max(float(np.median(counts)) * 100.0 / budget, 0.5)  # (a zero rate has no step)
    fitted = record_dispersion(record)
    k = fitted["dispersion"]
    spread_rank = power(len(counts), budget, rate, POWER_STEP, dispersion=k)
    spread_pair = power(len(counts), budget, rate, POWER_STEP, dispersion=k, test="sign-flip")
    poisson = power(len(counts), budget, rate, POWER_STEP)
    return {"seeds": len(counts), "miles_per_seed": budget, "rate_per_100mi": rate,
            "label": row["label"], "power": spread_rank["power"],
            "power_paired": spread_pair["power"], "power_poisson": poisson["power"],
            "min_p": poisson["min_p"], "dispersion": fitted}  # fmt: skip


def power_line(record: dict[str, Any]) -> str:
    found = record_power(record)
    if found is None:
        return ""
    k = found["dispersion"]
    return (
        f" Power: {found['seeds']} seeds x {found['miles_per_seed']:.0f} mi find a true"
        f" {POWER_STEP:g}x step at {found['label']}'s median rate"
        f" ({found['rate_per_100mi']:.1f} per 100 mi) in {100 * found['power']:.0f} % of records"
        f" under the seeds' spread (rank test; paired sign-flip"
        f" {100 * found['power_paired']:.0f} %), a negative binomial of dispersion"
        f" {k['dispersion']:.2f} [{k['low']:.2f}-{k['high']:.2f}] fitted to this record's"
        f" {k['rows']} rows of seeds; {100 * found['power_poisson']:.0f} % if seeds did not"
        f" differ (Poisson: an upper bound); at p < 0.05 before Holm's adjustment, which only"
        f" lowers it. The smallest reachable p is {found['min_p']:.2g}."
    )


def family_line(record: dict[str, Any]) -> str:
    fam = declared_family(record)
    tests = fam["tests"]
    parts = []
    for key, text in fam["families"].items():
        n = sum(f == key for f in tests.values())
        parts.append(f"{text} ({n} test{'s' * (n != 1)})")
    return (
        f" The families of tests, declared {fam['declared']}: " + "; ".join(parts) + ". Each"
        " family's p-values are Holm-adjusted together, and the verdict reads the adjusted p at"
        " 0.05; 'reproduces' means the direction of the paper's step, whose own ratio is beside"
        " ours ('beats its control', 'fewer collisions': the same for a control, a step beyond)."
    )
