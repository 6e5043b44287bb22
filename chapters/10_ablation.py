# %% [markdown]
# # 10 · The ablation: every driver on the same roads, beside the paper's Table 1
#
# Chapters 05-09 each added one idea of the paper (seed 000) and drove it on its own. This
# chapter is the course's result: **every driver on the same unseen test tracks, with the same
# seeds, over several training seeds each**, in one table beside the paper's Table 1:
#
# | method (seed 000, TORCS) | collisions per 100 miles |
# |---|---:|
# | Baseline E2E (actuators) | 183.3 |
# | Trajectory GMM | 12.7 |
# | GMM + affordance | 0.83 |
# | GMM + affordance + CVaR | 0 |
#
# at an average of 48 mph; and seed 002's times to collision in CARLA: PilotNet (steering only)
# 10.2 s, the modified PilotNet that also outputs throttle and brake 1.1 s.
#
# Two drivers frame the learned ones: the **expert** (privileged: it reads the parked cars; the
# ceiling) and the **oracle** (the LQR tracker following the expert's own 5-point trajectories).
#
# Every trained driver comes from `e2e_lite/imitation/recipes.py`, and **every row of the paper
# is trained with several seeds** (`profile.ablation_seeds`): two trainings of one recipe can
# differ by more than two recipes do, so the verdicts compare seeds. Seed 0 is the checkpoint of
# chapters 05-09. PilotNet, L2 and the ceilings, no step of the paper, drive their chapter's
# network and budget alone (`ablation.SEED_ZERO_ONLY`, `profile.eval_miles`); the record
# (`docs/results.md`) drives every row on roads of its own. Seed k of every row drives the same
# roads; each result is stored under a key of the weights and settings, and reused.

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(10)  # flags, profile, outputs folder: checked before any work

import numpy as np

from e2e_lite import artifacts
from e2e_lite.driving import replay
from e2e_lite.driving.evaluation import (
    COLLISION_KINDS,
    EvalConfig,
    collision_kinds,
    miles_text,
    results_table,
)
from e2e_lite.driving.figures import collision_chart, save_figure
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.record import ablation, words
from e2e_lite.record.report import load
from e2e_lite.record.stats import SPREAD_GOAL, STEPS, record_dispersion, slow, test_step
from e2e_lite.simulation.world import WorldConfig, make_world
from e2e_lite.stats.power import power
from e2e_lite.stats.rates import compare_rates
from e2e_lite.stats.seeds import compare_seeds, rank_test, seed_counts, sign_flip_test, spread

world_cfg = WorldConfig.for_profile(profile)
print(
    f"{miles_text(profile.ablation_miles)} per row of the paper, "
    f"{profile.ablation_seeds} training seeds each; {miles_text(profile.eval_miles)} for the others"
)

# %% [markdown]
# ## 1. The drivers
#
# The network drivers see the same 66 x 200 camera frame through the same PilotNet trunk; they
# differ in head and loss (chapter 05: steering or actuators; 06: a 5-point trajectory with L2;
# 07: a 2-mode GMM; 08: plus the affordance auxiliary loss; 09: plus one epoch of CVaR-90).

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
drivers = ablation.build_seeded_drivers(
    profile, train=train, val=val, single=ablation.SEED_ZERO_ONLY
)
for key, policy in drivers.items():
    print(f"{key:22s} {ablation.BY_KEY[key].label} (training runs: {len(np.atleast_1d(policy))})")

# %% [markdown]
# ## 2. Closed loop: the same tracks, the same seeds
#
# `evaluate` drives 64 cars in lockstep (full profile), car `i` on tracks `i, i + 64, ...` from
# start lanes of its own seeded generator, until the budget is spent; a collision is counted once
# and the car put back 15 m past the obstacle. Seed k of every row meets the same parked cars from
# the same starts; a row of one run starts on seed 0's roads. The cars are shared out over one
# worker per core in groups of eight: the events are the same on 2 cores and on 16.

# %%
ev = EvalConfig(miles=profile.ablation_miles, n_worlds=profile.ablation_worlds)
reference_ev = EvalConfig(miles=profile.eval_miles, n_worlds=profile.ablation_worlds)
REFERENCE = ("expert", "oracle", *ablation.SEED_ZERO_ONLY)  # the rows that are no paper step
driven = {
    **ablation.evaluate_drivers(
        {k: p for k, p in drivers.items() if k in REFERENCE}, world_cfg, reference_ev
    ),
    **ablation.evaluate_drivers(
        {k: p for k, p in drivers.items() if k not in REFERENCE}, world_cfg, ev
    ),
}
results = {k: driven[k] for k in drivers}  # (in the table's order)
table = ablation.ablation_table(results)
print(table + profile.caveat)

# %% [markdown]
# ## 3. The paper's steps, tested
#
# The paper's claim is a sequence of improvements. For each step: do the later row's training
# seeds collide less (`compare_seeds`: an exact one-sided permutation test on the seeds' counts,
# ties kept as ties; paired where a fine-tune shares its parent), by how much (the rate ratio,
# bootstrapped over the seeds) beside the paper's ratio? The pooled Poisson test is secondary.
# Each step is read at its own p here; the record reads the three as one family (Holm). A row
# more than 10 % slower than the expert is marked; the off-centre line tests the second outcome:
# a better driver has fewer collisions and not more off-centre episodes.
#
# First, what these seeds and miles can show at all: the smallest p-value the seeds can reach,
# and how often a record of this size finds a true 2x step at the + affordance row's rate
# (`power`), with seeds that spread as the record's seeds do (a negative binomial fitted to its
# rows, `record.stats.record_dispersion`) and, as an upper bound, seeds that do not differ at all.

# %%
aff_counts, per_seed_mi = seed_counts(results["gmm_affordance"])
base_rate = max(0.5, float(np.median(aff_counts)) * 100.0 / per_seed_mi)
spread_k = record_dispersion(load(), near="gmm_affordance").k  # its seeds' spread
reach = power(profile.ablation_seeds, per_seed_mi, base_rate, dispersion=spread_k)
flat = power(profile.ablation_seeds, per_seed_mi, base_rate)
print(
    f"{profile.ablation_seeds} seeds x {per_seed_mi:.3g} mi: smallest reachable p "
    f"{reach.min_p:.2g} (paired: {0.5**profile.ablation_seeds:.2g}, every seed one way); "
    f"power to find a true 2x step at {base_rate:.1f} per 100 mi: "
    f"{reach.power:.0%} with the record's seed spread (dispersion {spread_k:.2f}), "
    f"{flat.power:.0%} if seeds did not differ (an upper bound)"
)

# %% [markdown]
# Both tests fit in a few lines. The rank test pools the two rows' counts, gives tied counts the
# mean of their ranks, and counts the splits of the pooled seeds into two rows of the same sizes
# whose first row's rank sum is at most the one observed. The paired test flips the sign of each
# seed's difference in every way (a zero difference flips to itself). The library counts the
# same without listing them (by subset sums), as the record's many seeds need.

# %%
from itertools import combinations, product


def rank_p(a, b):  # P(a's rank sum <= observed), every split of the seeds equally likely
    pooled = np.concatenate([a, b])
    ranks = np.array([np.sum(pooled < v) + (np.sum(pooled == v) + 1) / 2 for v in pooled])
    sums = [ranks[list(c)].sum() for c in combinations(range(len(pooled)), len(a))]
    return np.mean(np.array(sums) <= ranks[: len(a)].sum() + 1e-9)


def flip_p(a, b):  # P(sum of the flipped differences <= observed), every pattern equally likely
    d = np.asarray(a) - np.asarray(b)
    sums = [np.dot(signs, np.abs(d)) for signs in product((-1, 1), repeat=len(d))]
    return np.mean(np.array(sums) <= d.sum() + 1e-9)


gmm_counts, cvar_counts = (seed_counts(results[k])[0] for k in ("gmm", "gmm_affordance_cvar"))
rec = {r.key: seed_counts(r).counts[:6] for r in load().rows}  # 6 of the record's seeds
ours = (aff_counts, gmm_counts, cvar_counts)
for a, b, c in (ours, (rec["gmm_affordance"], rec["gmm"], rec["gmm_affordance_cvar"])):
    assert np.isclose(rank_p(a, b), rank_test(a, b).p_fewer)
    assert np.isclose(flip_p(c, a), sign_flip_test(c, a).p_fewer)
by_hand = f"rank p {rank_p(a, b):.3g}, sign-flip p {flip_p(c, a):.3g}"
print(f"by hand, the record's 6: {by_hand}, as e2e_lite.stats.seeds gives")
# %%
# the paper's three steps (record.stats.STEPS); PilotNet and L2, one seed each, are no step
steps, pooled = [], {}
expert_mph = results["expert"].mean_speed_mph
for st in (st for st in STEPS if st.family == "paper"):
    after, before = results[st.after], results[st.before]
    seeds = compare_seeds(after, before, paired=st.paired)
    paper = ablation.BY_KEY[st.after].paper_per_100mi / ablation.BY_KEY[st.before].paper_per_100mi
    tested = test_step(st, seeds, paper, slow(after.mean_speed_mph, expert_mph))
    off = test_step(st, compare_seeds(after, before, paired=st.paired, outcome="off_centre"))
    steps.append(tested)
    pooled[st.what] = compare_rates(after, before).p_value
    tail = f"verdict: {words.verdict(tested)} ({words.paper_ratio(tested, seeds)})"
    print(f"{st.what}: {words.seeds(seeds)}; {tail}; pooled p = {pooled[st.what]:.2g}")
    print(f"  off-centre: {words.off_centre(off)}; {words.better_driver(tested, off)}")

# %% [markdown]
# ## 3b. Controls: which part of a step did it?
#
# A control changes one thing, with the same seeds on the same roads. Chapter 09 trained the CVaR
# row's: **the fine-tune with the mean** (same parent, epoch, batches and rate, each batch
# reduced by its mean): is the CVaR step CVaR's, or one more epoch's? It shares its parent with
# the CVaR row, seed by seed, so the tests are paired. The affordance step's control, **w = 0**
# (the same head, its loss off), is exercise 7's (four trainings) and the record's, of its recipes.
#
# The seeds' spread measures training noise (goal: a worst seed at most `SPREAD_GOAL` times its
# row's median); the stalls (a car under 0.5 m/s for 20 s, re-placed), a rate bought by stopping.

# %%
controls = ablation.build_seeded_drivers(profile, ["gmm_affordance_control"], train=train, val=val)
control_results = ablation.evaluate_drivers(controls, world_cfg, ev)
control_table = results_table(
    [(ablation.BY_KEY[k].label, r) for k, r in control_results.items()],
    extra=[
        ("per seed, per 100 mi", [ablation.per_seed(r) for r in control_results.values()]),
        ("stalls", [f"{r.stalls:,}" for r in control_results.values()]),
    ],
)
print(control_table + profile.caveat)
spreads = {k: spread(r) for k, r in {**results, **control_results}.items()}
for k, ratio in spreads.items():
    if ratio is not None:
        over = "over the goal" if ratio > SPREAD_GOAL else "within the goal"
        print(f"{ablation.BY_KEY[k].label}: worst seed / median {ratio:.1f} ({over})")
both = {**results, **control_results}
control_tests = {  # (paired: each fine-tune and its parent share a seed)
    what: words.seeds(compare_seeds(both[a], both[b], paired=True))
    for a, b, what in (
        (
            "gmm_affordance_cvar",
            "gmm_affordance_control",
            "CVaR fine-tune vs the same with the mean",
        ),
        ("gmm_affordance_control", "gmm_affordance", "the fine-tune with the mean vs its base"),
    )
}
print("\n".join(f"{what}: {text}" for what, text in control_tests.items()))

# %% [markdown]
# ## 3c. Where the collisions are
#
# Each collision by kind (`evaluation.collision_kinds`): a guard rail; a parked car in the
# driver's own lane while it is centred in that lane (it neither left the lane nor stopped); a
# parked car hit off centre (changing lanes, or clipped beside). Pooled over the seeds.

# %%
kinds = {k: collision_kinds(r, world_cfg) for k, r in both.items() if k not in ablation.UNTRAINED}
print("| driver | collisions | " + " | ".join(COLLISION_KINDS) + " |")
print("|---|---:|" + "---:|" * len(COLLISION_KINDS))
for k, c in kinds.items():
    cells = " | ".join(str(c[kind]) for kind in COLLISION_KINDS)
    print(f"| {ablation.BY_KEY[k].label} | {both[k].collisions} | {cells} |")
print(profile.caveat.strip())

# %% [markdown]
# ## 4. The chart
#
# Bars: our pooled rates with their 95 % intervals; grey dots: each training seed's own rate and
# interval; diamonds: the paper's figure for the same method (seed 000's Table 1). The axis is
# logarithmic above one per 100 miles: the rates span decades.

# %%
rows = [(ablation.BY_KEY[k].label, r) for k, r in results.items()]
marks = [ablation.BY_KEY[k].paper_per_100mi for k in results]
chart_png = save_figure(
    collision_chart(
        rows,
        title=f"{miles_text(ev.miles)} per row of the paper ({profile.ablation_seeds} training "
        f"seeds each), {miles_text(reference_ev.miles)} for the others (seed 0's roads)",
        marks=marks,
        marks_label="seed 000, Table 1",
        log=True,
    ),
    artifacts.artifact_path("figures", "10_ablation.png"),
)
print(f"saved {chart_png}")

# %% [markdown]
# ## 5. Replays
#
# Numbers say how often; a replay shows how. Each driver (its training seed 0) drives the same
# stretch (test track 0, middle lane, from 30 m) alone, for up to the replay length or until its
# first collision. `e2e_lite.driving.replay` writes each drive as a **standalone 3D page**
# (meshcat's viewer and the scene in one HTML file: open it from disk) with the car's declared
# intent at every decision: the 5 proposed points, one colour per GMM mode, bigger for heavier
# modes; beside it, the same drive as a GIF of the camera view with the proposal drawn on it.

# %%
replay_dir = artifacts.artifact_path("replays")
entries = []
for key, policy in drivers.items():
    ep = replay.record(
        ablation.first(policy),
        make_world(world_cfg, "test", 0),
        world_cfg,
        ablation.BY_KEY[key].label,
        s_m=30.0,
        lane=1,
        seconds=profile.replay_s,
    )
    r = results[key]
    r0 = (r.seeds or [r])[0]  # the replay's own network: seed 0
    caption = f"seed 0: {r0.collisions} collisions in {r0.miles:.0f} mi; all seeds: "
    caption += f"{r.collisions_per_100mi:.1f} per 100 mi over {miles_text(round(r.miles, 1))}"
    page = replay.export_html(ep, replay_dir / f"{key}.html", caption)
    gif = replay.export_gif(ep, replay_dir / f"{key}.gif")
    ending = f"collided with a {ep.contact}" if ep.contact else "no collision"
    entries.append((ep.name, page.name, f"{ep.seconds:.1f} s, {ending}; {caption}"))
    print(f"{key:22s} {ep.seconds:5.1f} s, {ending:22s} -> {page.name}, {gif.name}")
index = replay.write_index(entries, replay_dir / "index.html", "e2e-lite: closed-loop replays")
print(f"open {index} in a browser")

# %% [markdown]
# ## 6. What reproduces, what does not
#
# The lines below are computed from this run's numbers (the quick profile's few miles decide
# nothing); the numbers of record are in `docs/results.md`, the investigations behind the
# recipes in `docs/lab-notes.md`. What our world lacks that the paper had (seed 000, section 4):
# 500K samples, a ResNet-34 trunk on 320x640 images, many more epochs. What it adds: every number
# with its interval, each training seed's rate and a test.

# %%
rate = {k: r.collisions_per_100mi for k, r in results.items()}
best = min((k for k in results if k not in ablation.UNTRAINED), key=rate.get)
lines = [
    f"lowest pooled rate: {ablation.BY_KEY[best].label} ({rate[best]:.1f}"
    " per 100 mi; which differences the seeds show, the steps below say)",
    f"references: expert {rate['expert']:.1f}, oracle "
    f"{rate['oracle']:.1f} per 100 mi (intervals: the table)",
    *(
        f"{s.step}: {words.verdict(s)}; ratio {s.ratio:.2f} (the paper's {s.paper_ratio:.2g})"
        for s in steps
    ),
    *(f"control: {what}: {text}" for what, text in control_tests.items()),
    "the affordance loss against w = 0 is the record's test (exercise 7 drives it here)",
    "mean speeds [mph]: "
    + ", ".join(f"{k} {r.mean_speed_mph:.1f}" for k, r in results.items())
    + f" (the paper: {ablation.PAPER_MPH:g})",
]
print("\n".join(lines))

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "10_ablation",
    {
        "profile": profile.name,
        "headline": {f"{k} collisions/100mi": rate[k] for k in results},
        "miles_per_driver": ev.miles,
        "reference_miles": reference_ev.miles,
        "eval": {k: getattr(ev, k) for k in ("n_worlds", "n_tracks", "first_track", "seed")},
        "results": {k: r.to_dict(with_events=False) for k, r in results.items()},
        "paper": {
            d.key: {"per_100mi": d.paper_per_100mi, "ttc_s": d.paper_ttc_s}
            for d in ablation.DRIVERS
        },
        "paper_mph": ablation.PAPER_MPH,
        "steps": [
            {**vars(s), "verdict": words.verdict(s), "pooled_p_value": pooled[s.step]}
            for s in steps
        ],
        "power": {
            "seeds": profile.ablation_seeds,
            "miles_per_seed": per_seed_mi,
            "rate_per_100mi": base_rate,
            "dispersion": spread_k,
            "power_poisson": flat.power,
            **vars(reach),
        },
        "controls": {k: r.to_dict(with_events=False) for k, r in control_results.items()},
        "collision_kinds": kinds,
        "control_tests": control_tests,
        "worst_seed_over_median": spreads,
        "discussion": lines,
        "table_md": table,
        "replays": [
            str((replay_dir / f).relative_to(artifacts.outputs_dir())) for _, f, _ in entries
        ],
    },
    figures=(chart_png,),
)

# %% [markdown]
# ## Summary
#
# * Seed k of every row drove the same test tracks from the same starts; the table puts our
#   rates, with their 95 % intervals, beside the paper's.
# * Each of the paper's steps is tested, not eyeballed: a difference counts only when the exact
#   test on the training seeds' counts (ties kept as ties; paired for a fine-tune) says it is
#   beyond chance, and the power printed before the verdicts says what a "not shown" is worth.
# * The replays (`outputs/replays/index.html`) show what the numbers count: where each driver
#   meant to go, and where it went.
#
# ## Exercises
#
# 1. Evaluate every driver with a second evaluation seed (`EvalConfig(seed=1)`, other start
#    lanes): which rows move beyond their intervals? What does that say about a verdict's miles?
# 2. With `stats.power.power`, find the seeds and miles per seed that would find a 1.5x step (not
#    2x) at the + affordance row's rate nine times in ten. What would that record cost in
#    training time on your machine (`python -m e2e_lite.course.bench train`)?
# 3. Drive the exercises' drivers (`ablation.DIAGNOSTICS`: the mixture's mean, K = 1, the
#    paper's learned sigmas, the head on the fused features) beside the GMM rows, seed by seed.
#    Which of them changes the GMM row's spread (lab note "Every epoch on the road")?
# 4. Drive the GMM drivers with `TrajectoryAgent(model, speed="cruise")` (the speed from the
#    road's curve limits, as PilotNet's cruise control; the network only steers): which of the
#    paper's steps reproduce once the network no longer sets the speed?
# 5. Open two replays side by side at a collision: did the network propose the collision, or
#    did the tracker fail to follow a safe proposal? (Chapter 11 builds a check for the first.)
# 6. Drive every epoch of a GMM seed on test roads too (`lab/epochs_on_the_road.py` keeps each
#    epoch's weights with `recipes.gmm(..., on_epoch=...)`). Does the epoch that validation roads
#    keep drive best on test roads? Change `recipes.SELECT_MILES` (5, 20, 80): when is the choice
#    more than chance, and what does it cost per training?
# 7. Train and drive the w = 0 control with this chapter's seeds (`ablation.build_seeded_drivers(
#    profile, ["gmm_affordance_w0"], train=train, val=val)`, then `evaluate_drivers` on `ev`) and
#    test + affordance against it with `compare_seeds`: does your verdict agree with the record's?
