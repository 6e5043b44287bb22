"""Do the course's last networks begin their lane changes late on the states they drive into
themselves? (issue 88, item 3)

On the expert's own states the start networks begin a lane change close to where the expert's
labels do (lab note "Neither the trigger gap nor the side coin, as tested, makes the choice
late"); the deciding collisions' plans began 25-30 m after the expert's from states the networks
drove into. This lab measures the choice on those states: each start network (GMM + affordance
+ CVaR, chapter 10's seeds) drives its own validation roads inside a ``Witness`` that keeps every
decision, and at each decision the expert's label is computed from the same state
(``anatomy.expert_label``, a function of the state alone).

An approach: the decisions of one car in one lane behind one parked car (the first parked car
ahead in the car's lane, within 80 m of its front bumper), first seen at 75 m or more with the car
within 0.5 m of its lane's centre (so settled in its lane); approaches that end in a collision are
the anatomy's and are left out (``Witness.ordinary``). In each: the gap at the first decision whose
label changes lanes (its 1.5 s point more than ``CHANGING_M`` from the lane's centre, read along
the road) and at the first whose plan does. The lateness: the label's gap minus the plan's [m]
(positive: the plan began nearer the car); a plan that never changes while its label did counts
as beginning at the approach's last gap. Approaches whose label never changes (the expert follows)
are counted apart.

Declared before the run (the verdict the script prints), over the approaches of each seed:

* late on its own states: on every seed the median approach's plan begins more than 10 m after
  its label;
* on time on its own states: on every seed the median lateness is 5 m or less;
* mixed otherwise.

Beside it: the share of approaches more than 15 m late, and for those against the rest, the
car's lane, offset from its lane's centre and heading to the road at the label's start (medians);
and (added after the run, not part of the verdict) where the plans began: the 5th percentile and
median of the plan's start gap, how many began nearer than the expert's nearest trigger gap
(45 m, ``ExpertConfig.trigger_m``), the lateness's quartiles, and how many began within 5 m of
their label and 5-15 m after it. Also added after a review, outside the verdict: the same
measure over every approach first seen at 75 m or more, settled or not, those ending in a
collision included (the declared filter leaves out exactly the late approaches that collide),
approaches cut by the end of a car's miles before their plan began counted as unknown, how
many are more than 15 m and 25 m or more late, by the car's offset from its lane's centre at
first sight, and the lateness of each approach that ends in a collision. A label that changes
at the first decision seen makes the lateness a lower bound (counted).

A second, declared test of the association the first run found after its verdict (late starts
with the car off its lane's centre), on fresh validation roads (``--fresh``: those of training
seeds 4-7, which chapter 12 does not drive; the same four networks), over every approach first
seen at 75 m or more with its lateness known: the approaches first seen 0.2 m or more off the
lane's centre against those within 0.2 m, by the share begun 25 m or more after the label.
Declared before that run:

* shown: pooled over the seeds, the off-centre share is larger (Fisher's exact test, one-sided,
  p < 0.05, approaches as units) and larger on at least three of the four seeds;
* not shown: the pooled off-centre share is no larger;
* unsettled otherwise.

A third, declared after the first run found it too and before its own run on the fresh roads
(at 5ab00bb's run of the first roads: 7 of 189 approaches first seen within 5 s of the car's last
lane change began 25 m or more late, against 7 of 486 seen later or with no change before them
on their road): approaches first seen within 5 s of the car's last lane change against the
rest, by the same share, the same test and rule (``--fresh``; its power is low: at those rates
about half of such records would show it).

    python lab/own_states.py [--quick] [--fresh]

Writes docs/results/lab/own_states.json, or with ``--fresh`` own_states_fresh.json (full
profile).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path

import numpy as np
from scipy.stats import fisher_exact

from e2e_lite import artifacts
from e2e_lite.config import FULL, QUICK
from e2e_lite.control.expert import Expert
from e2e_lite.control.rules import car_ahead
from e2e_lite.driving import anatomy
from e2e_lite.driving.evaluation import evaluate
from e2e_lite.driving.witness import CHANGING_M, Collision, Moment, Witness
from e2e_lite.imitation import dagger, recipes
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.simulation.world import WorldConfig

RANGE_M = 80.0  # an approach: a parked car ahead in the car's lane within this [m]
FIRST_SEEN_M = 75.0  # an approach counts when first seen this far or farther [m]
SETTLED_M = 0.5  # ... with the car this near its lane's centre [m]
LATE_M, ON_TIME_M, VERY_LATE_M = 10.0, 5.0, 15.0  # the verdict's and the description's [m]
NEAR_M = 45.0  # a plan that begins nearer than the expert's nearest trigger gap [m]
FAR_LATE_M = 25.0  # as late as the deciding collisions' plans [m]
OFFSET_BINS_M = (0.0, 0.2, 0.5, 2.0)  # the car's offset from its lane's centre at first sight [m]
#: the time from the car's last lane change to the first sight [s] ((None, None): none on the road)
CHANGE_BINS = ((0.0, 5.0), (5.0, 10.0), (10.0, math.inf), (None, None))


def where(m: Moment, front_m: float) -> tuple[int, float, float, float, int]:
    """``(lane, offset from its centre [m], heading to the road [rad], gap [m], parked car)`` of
    the car at ``m`` (gap ``inf`` and car ``-1``: none within :data:`RANGE_M`)."""
    track = m.world.track
    s, d = (float(np.ravel(v)[0]) for v in track.to_frenet(m.state[0], m.state[1]))
    lane = int(track.lane_index(d))
    gap, j = car_ahead(m.world, s + front_m, lane, RANGE_M)
    heading = float(m.state[2]) - float(track.heading(s))
    heading = (heading + np.pi) % (2 * np.pi) - np.pi
    return lane, d - float(track.lane_center(lane)), heading, gap, j


def approaches(
    kept: list[tuple[int, int, Moment]],
    world_cfg: WorldConfig,
    collisions: list[Collision] = (),
    settled: bool = True,
) -> list[dict]:
    """The approaches in ``kept`` (``Witness.kept``'s ``(decision, car, moment)``, in the order of
    the drive), each with its label's and plan's start, its first sight and how it ended:
    ``"collision"`` (the car collided within a decision of its last), ``"went on"`` (the car
    decided again, out of the approach: another lane, or past the car) or ``"cut"`` (the car's
    miles ended). ``settled``: only approaches first seen with the car within :data:`SETTLED_M`
    of its lane's centre (the declared verdict's)."""
    front, expert = (
        world_cfg.vehicle.rear_to_front_m,
        Expert(vehicle=world_cfg.vehicle, sim=world_cfg.sim),
    )
    decided = {(car, step) for step, car, _ in kept}
    collided = {(c.car, c.step) for c in collisions}
    runs: dict[tuple, list[tuple[int, Moment, tuple]]] = {}
    lane_of: dict[int, tuple] = {}  # car -> (its track, its lane, the decision it changed lane)
    changed: dict[tuple, int | None] = {}  # approach -> the car's last lane change before it
    for step, car, m in kept:
        at = where(m, front)
        track = m.world.track.track_id
        was = lane_of.get(car)
        if was is None or was[0] != track:
            lane_of[car] = (track, at[0], None)  # (a new road: no lane change on it yet)
        elif was[1] != at[0]:
            lane_of[car] = (track, at[0], step)
        if at[4] >= 0 and at[3] < RANGE_M:
            key = (car, track, at[0], at[4])
            changed.setdefault(key, lane_of[car][2])
            runs.setdefault(key, []).append((step, m, at))
    out = []
    period = world_cfg.sim.policy_period_s
    for (car, track, lane, parked), run in runs.items():
        first, last = run[0][2], run[-1][0]
        since = changed[(car, track, lane, parked)]
        if first[3] < FIRST_SEEN_M or (settled and abs(first[1]) > SETTLED_M):
            continue
        label_at = plan_at = None
        for k, (_, m, at) in enumerate(run):
            if label_at is None:
                end = anatomy.expert_label(m, world_cfg, expert)[-1]
                if abs(off := m.lane_offset(end)[0]) > CHANGING_M:
                    label_at, label_first, label_side = at, k == 0, 1 if off > 0 else -1
            if plan_at is None and m.plan_changing:
                plan_at = at
            if label_at is not None and plan_at is not None:
                break
        if (car, last + 1) in collided:
            ended = "collision"
        else:
            ended = "went on" if (car, last + 1) in decided else "cut"
        out.append(
            {
                "car": car,
                "track": list(track),
                "parked": parked,
                "first_seen": list(first[:4]),
                "label_start": None if label_at is None else list(label_at[:4]),
                "label_at_first_sight": None if label_at is None else label_first,
                "label_side": None if label_at is None else label_side,
                "plan_start": None if plan_at is None else list(plan_at[:4]),
                "last_gap_m": run[-1][2][3],
                "ended": ended,
                "since_lane_change_s": None if since is None else (run[0][0] - since) * period,
            }
        )
    return out


def lateness(a: dict, censor: bool = False) -> float | None:
    """How much nearer the car the plan began than the label [m] (None: the label never did;
    with ``censor``, also a plan that never began in an approach cut by the end of the car's
    miles: its lateness is unknown). The declared verdict reads a plan that never began as
    beginning at the approach's last gap."""
    if a["label_start"] is None:
        return None
    if a["plan_start"] is None and censor and a["ended"] == "cut":
        return None
    plan_gap = a["last_gap_m"] if a["plan_start"] is None else a["plan_start"][3]
    return a["label_start"][3] - plan_gap


def tail(found: list[dict]) -> dict:
    """Every approach first seen at :data:`FIRST_SEEN_M` or more, settled or not, those ending in
    a collision included (added after the declared run, outside its verdict): how many are late
    by more than :data:`VERY_LATE_M` and by :data:`FAR_LATE_M` or more, by the car's offset from
    its lane's centre at first sight (:data:`OFFSET_BINS_M`), and the collisions' approaches."""
    known = [(a, x) for a in found if (x := lateness(a, censor=True)) is not None]
    by_offset = []
    for lo, hi in itertools.pairwise(OFFSET_BINS_M):
        group = [x for a, x in known if lo <= abs(a["first_seen"][1]) < hi]
        by_offset.append(
            {
                "first_offset_m": [lo, hi],
                "approaches": len(group),
                "late_over_15_m": sum(x > VERY_LATE_M for x in group),
                "late_25_m_or_more": sum(x >= FAR_LATE_M for x in group),
            }
        )
    by_change = []
    for lo, hi in CHANGE_BINS:
        group = [x for a, x in known if _since_in(a["since_lane_change_s"], lo, hi)]
        by_change.append(
            {
                "since_lane_change_s": [lo, hi],
                "approaches": len(group),
                "late_25_m_or_more": sum(x >= FAR_LATE_M for x in group),
            }
        )
    return {
        "approaches": len(found),
        "label_changes": len(known),
        "by_since_lane_change": by_change,
        "cut_unknown": sum(a["label_start"] is not None for a in found) - len(known),
        "label_at_first_sight": sum(bool(a["label_at_first_sight"]) for a, _ in known),
        "late_over_15_m": sum(x > VERY_LATE_M for _, x in known),
        "late_25_m_or_more": sum(x >= FAR_LATE_M for _, x in known),
        "by_first_offset": by_offset,
        "off_centre_by_side": {
            side: {
                "approaches": len(group := [x for a, x in known if _off_side(a) == side]),
                "late_25_m_or_more": sum(x >= FAR_LATE_M for x in group),
            }
            for side in ("towards the change", "away from it")
        },
        "collisions": [
            {
                "lateness_m": x,
                "label_gap_m": a["label_start"][3],
                "first_offset_m": a["first_seen"][1],
            }
            for a, x in known
            if a["ended"] == "collision"
        ],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--fresh", action="store_true", help="other validation roads: the second test")
    args = ap.parse_args()
    profile, fresh = (QUICK if args.quick else FULL), args.fresh
    miles = 2.0 if profile.quick else 40.0  # validation miles per seed
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    world_cfg = WorldConfig.for_profile(profile)
    weight = recipes.affordance_weight(profile, train, val)
    out: dict = {"miles_per_seed": miles, "seeds": {}}
    for k in range(profile.ablation_seeds):
        net = recipes.gmm_affordance_cvar(profile, train, val, weight, k)[0]
        witness = Witness(TrajectoryAgent(net), world_cfg.sim.policy_period_s, every=1)
        roads = dagger.val_run(profile, k + profile.ablation_seeds * fresh, miles)
        evaluate(witness, world_cfg, roads, desc=f"seed {k}")
        ordinary = {id(m) for m in witness.ordinary}  # (the declared run's moments)
        declared = [x for x in witness.kept if id(x[2]) in ordinary]
        found = approaches(declared, world_cfg)
        late = [x for x in (lateness(a) for a in found) if x is not None]
        never = sum(a["label_start"] is not None and a["plan_start"] is None for a in found)
        very = [a for a in found if (lateness(a) or 0.0) > VERY_LATE_M]
        rest = [a for a in found if a["label_start"] is not None and a not in very]

        def medians(group: list[dict]) -> dict[str, float | None]:
            starts = np.array([a["label_start"] for a in group], dtype=float).reshape(-1, 4)
            names = ("lane", "offset_m", "heading_rad", "gap_m")
            if not len(starts):
                return dict.fromkeys(names)
            return {n: float(np.median(starts[:, i])) for i, n in enumerate(names)}

        began = np.array(
            [
                a["last_gap_m"] if a["plan_start"] is None else a["plan_start"][3]
                for a in found
                if a["label_start"] is not None
            ]
        )
        seed = {
            "approaches": len(found),
            "plan_start_gap_m": {
                "p5": float(np.percentile(began, 5)) if len(began) else None,
                "median": float(np.median(began)) if len(began) else None,
                f"nearer_than_{NEAR_M:g}": int((began < NEAR_M).sum()),
            },
            "label_never_changes": len(found) - len(late),
            "plan_never_changes": never,
            "median_lateness_m": float(np.median(late)) if late else None,
            "lateness_quartiles_m": np.percentile(late, [25, 75]).tolist() if late else None,
            "within_5_m": sum(abs(x) <= ON_TIME_M for x in late),
            "later_5_to_15_m": sum(ON_TIME_M < x <= VERY_LATE_M for x in late),
            "very_late_share": len(very) / len(late) if late else None,
            "at_the_label_start": {"very late": medians(very), "the rest": medians(rest)},
            "collisions": len(witness.collisions),
            "approaches_each": found,
        }
        out["seeds"][k] = seed
        print(
            f"seed {k}: {seed['approaches']} approaches ({seed['label_never_changes']} where the "
            f"label never changes, {never} where only the label does); median lateness "
            f"{_m(seed['median_lateness_m'])}, more than {VERY_LATE_M:g} m late "
            f"{_pct(seed['very_late_share'])}"
        )
        if late:
            q1, q3 = seed["lateness_quartiles_m"]
            print(
                f"  lateness quartiles {q1:.1f} and {q3:.1f} m; within {ON_TIME_M:g} m "
                f"{seed['within_5_m']} of {len(late)}, {ON_TIME_M:g}-{VERY_LATE_M:g} m late "
                f"{seed['later_5_to_15_m']}"
            )
        began_at = seed["plan_start_gap_m"]
        print(
            f"  the plans began at {_m(began_at['median'])} (median; 5th percentile "
            f"{_m(began_at['p5'])}), nearer than {NEAR_M:g} m in "
            f"{began_at[f'nearer_than_{NEAR_M:g}']} approaches"
        )
        for name, at in seed["at_the_label_start"].items():
            print(
                f"  {name} at the label's start: lane {_m(at['lane'], '')}, offset "
                f"{_m(at['offset_m'])}, heading {_m(at['heading_rad'], ' rad', 3)}, gap "
                f"{_m(at['gap_m'])}"
            )
        every = tail(approaches(witness.kept, world_cfg, witness.collisions, settled=False))
        seed["every_approach"] = every
        print(
            f"  every approach (outside the verdict): {every['label_changes']} whose label "
            f"changes and whose end is known ({every['cut_unknown']} cut), "
            f"{every['late_over_15_m']} more than {VERY_LATE_M:g} m late, "
            f"{every['late_25_m_or_more']} {FAR_LATE_M:g} m or more; ending in a collision: "
            + (", ".join(f"{_m(c['lateness_m'])} late" for c in every["collisions"]) or "none")
        )
    print("every approach, all seeds (outside the verdict), by the last lane change before it:")
    for n, (lo, hi) in enumerate(CHANGE_BINS):
        rows = [s["every_approach"]["by_since_lane_change"][n] for s in out["seeds"].values()]
        when = "none on this road" if lo is None else f"{lo:g}-{hi:g} s"
        print(
            f"  {when} before the first sight: "
            f"{sum(r['approaches'] for r in rows)} approaches, "
            f"{sum(r['late_25_m_or_more'] for r in rows)} {FAR_LATE_M:g} m or more late"
        )
    print("every approach first seen off centre, all seeds (outside the verdict), by its side:")
    for side in ("towards the change", "away from it"):
        rows = [s["every_approach"]["off_centre_by_side"][side] for s in out["seeds"].values()]
        print(
            f"  {side}: {sum(r['approaches'] for r in rows)} approaches, "
            f"{sum(r['late_25_m_or_more'] for r in rows)} {FAR_LATE_M:g} m or more late"
        )
    print("every approach, all seeds (outside the verdict), by the offset at first sight:")
    for n, (lo, hi) in enumerate(itertools.pairwise(OFFSET_BINS_M)):
        rows = [s["every_approach"]["by_first_offset"][n] for s in out["seeds"].values()]
        total = {key: sum(r[key] for r in rows) for key in rows[0] if key != "first_offset_m"}
        print(
            f"  {lo:g}-{hi:g} m: {total['approaches']} approaches, {total['late_over_15_m']} more "
            f"than {VERY_LATE_M:g} m late, {total['late_25_m_or_more']} {FAR_LATE_M:g} m or more"
        )
    found = [s["median_lateness_m"] for s in out["seeds"].values()]
    if None in found:
        verdict = "no verdict: a seed has no approach whose label changes lanes"
    elif all(x > LATE_M for x in found):
        verdict = f"late on its own states: median lateness over {LATE_M:g} m on every seed"
    elif all(x <= ON_TIME_M for x in found):
        verdict = (
            f"on time on its own states: median lateness {ON_TIME_M:g} m or less on every seed"
        )
    else:
        verdict = "mixed: the seeds' medians fall on both sides or between the thresholds"
    out["verdict"] = verdict
    print(f"verdict (declared): {verdict}")
    if fresh:
        out["off_centre_test"] = off_centre_test(out["seeds"])
        print(f"the off-centre test (declared for --fresh): {out['off_centre_test']['verdict']}")
        out["lane_change_test"] = lane_change_test(out["seeds"])
        print(f"the lane-change test (declared for --fresh): {out['lane_change_test']['verdict']}")
    out["commit"] = artifacts.code_commit(Path(__file__).parent)
    if not profile.quick:
        name = "own_states_fresh.json" if fresh else "own_states.json"
        path = Path(__file__).resolve().parents[1] / "docs/results/lab" / name
        path.write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {path}")


def lane_change_test(seeds: dict) -> dict:
    """The third declared test of ``--fresh``: approaches first seen within 5 s of the car's
    last lane change against the rest, by the share begun 25 m or more late."""
    per_seed = []
    for seed in seeds.values():
        bins = seed["every_approach"]["by_since_lane_change"]  # (CHANGE_BINS' order)
        per_seed.append(
            (
                bins[0]["late_25_m_or_more"],
                bins[0]["approaches"],
                sum(b["late_25_m_or_more"] for b in bins[1:]),
                sum(b["approaches"] for b in bins[1:]),
            )
        )
    return _fisher_verdict(per_seed, ("within 5 s", "later or none"))


def off_centre_test(seeds: dict) -> dict:
    """The declared test of ``--fresh``: approaches first seen 0.2 m or more off the lane's
    centre against those within 0.2 m, by the share begun 25 m or more late."""
    per_seed = []
    for seed in seeds.values():
        bins = seed["every_approach"]["by_first_offset"]
        per_seed.append(
            (
                sum(b["late_25_m_or_more"] for b in bins[1:]),
                sum(b["approaches"] for b in bins[1:]),
                bins[0]["late_25_m_or_more"],
                bins[0]["approaches"],
            )
        )
    return _fisher_verdict(per_seed, ("off centre", "centred"))


def _fisher_verdict(per_seed: list[tuple[int, int, int, int]], names: tuple[str, str]) -> dict:
    """A declared test of ``--fresh``: per seed ``(late, approaches)`` of the group ``names[0]``
    and of ``names[1]``; shown where, pooled, the first's share of late approaches is larger
    (Fisher's exact test, one-sided, p < 0.05) and larger on at least three seeds; not shown
    where it is no larger; else unsettled."""
    late_a, n_a, late_b, n_b = (sum(c[i] for c in per_seed) for i in range(4))
    table = [[late_a, n_a - late_a], [late_b, n_b - late_b]]
    p = float(fisher_exact(table, alternative="greater").pvalue) if n_a and n_b else None
    larger = sum(a / b > c / d for a, b, c, d in per_seed if b and d)
    counted = f"{names[0]} {late_a} of {n_a}, {names[1]} {late_b} of {n_b}"
    if p is None:
        verdict = "no verdict: a group has no approach"
    elif p < 0.05 and larger >= 3:
        verdict = f"shown: {counted} (p {p:.2g})"
    elif late_a / n_a <= late_b / n_b:
        verdict = f"not shown: {counted}"
    else:
        verdict = f"unsettled: {counted} (p {p:.2g}, larger on {larger} of {len(per_seed)} seeds)"
    return {
        names[0].replace(" ", "_"): [late_a, n_a],
        names[1].replace(" ", "_"): [late_b, n_b],
        "p_one_sided": p,
        "seeds_larger": larger,
        "verdict": verdict,
    }


def _off_side(a: dict) -> str | None:
    """For an approach first seen :data:`OFFSET_BINS_M`'s 0.2 m or more off its lane's centre:
    was the car off towards the side its label changes to, or away from it (None: centred, or
    a label that never changed)."""
    offset = a["first_seen"][1]
    if a["label_side"] is None or abs(offset) < OFFSET_BINS_M[1]:
        return None
    return "towards the change" if offset * a["label_side"] > 0 else "away from it"


def _since_in(since: float | None, lo: float | None, hi: float | None) -> bool:
    """Whether a time since the last lane change [s] (None: none) lies in the bin ``[lo, hi)``
    (``lo`` None: the bin of no lane change)."""
    if lo is None or since is None:
        return lo is None and since is None
    return lo <= since < hi


def _m(x: float | None, unit: str = " m", digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}{unit}"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


if __name__ == "__main__":
    main()
