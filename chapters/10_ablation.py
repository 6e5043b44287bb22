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
# Two drivers frame the learned ones: the **expert** (privileged: it reads the parked cars from
# the simulator; the ceiling) and the **oracle** (the LQR tracker following the expert's own
# 5-point trajectories: the ceiling of any network that predicts such a trajectory).
#
# Every trained driver comes from `e2e_lite/learning/recipes.py`, and **every learned row is
# trained with several seeds** (`profile.ablation_seeds`: four in the full profile, two in the
# quick one): two trainings of one recipe can differ by more than two recipes do, so the
# verdicts compare seeds. Seed 0 is the checkpoint of chapters 05-09; the others are trained
# here or in chapter 09. PilotNet and L2, not rows of the paper's Table 1, drive with their
# chapter's network alone (`ablation.SEED_ZERO_ONLY`), and they and the two ceilings drive the
# chapters' own budget (`profile.eval_miles`): the course's 2 h on 2 cores has room for the
# seeds of the paper's rows only; the record (`docs/results.md`) drives every row over ten
# seeds' miles, on roads of its own. Seed k of every row drives the same roads; each result is
# stored under a key of the driver's weights and the settings, and reused. Run it with
# `python chapters/10_ablation.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course import start_chapter

profile = start_chapter(10)  # flags, profile, outputs folder: checked before any work

import numpy as np

from e2e_lite import ablation, artifacts
from e2e_lite.driving import replay
from e2e_lite.driving.evaluation import (
    COLLISION_KINDS,
    EvalConfig,
    collision_kinds,
    compare_rates,
    compare_seeds,
    miles_text,
    power,
    result_dict,
    results_table,
    seed_counts,
)
from e2e_lite.learning.data import DataConfig, load_or_collect
from e2e_lite.report import SPREAD_GOAL, spread
from e2e_lite.simulation.world import WorldConfig, make_world
from e2e_lite.viz import collision_chart, save_figure

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
    runs = len(policy) if isinstance(policy, list) else 1
    print(f"{key:22s} {ablation.BY_KEY[key].label} ({runs} training run{'s' * (runs > 1)})")

# %% [markdown]
# ## 2. Closed loop: the same tracks, the same seeds
#
# `evaluate` drives 64 cars in lockstep (in the full profile), each on roads no other car and no
# earlier lap drove (car `i` on tracks `i, i + 64, ...`), each from start lanes drawn by its own
# seeded generator, until the budget is spent; a collision is counted once and the car is put
# back 15 m past the obstacle. Every driver meets exactly the same parked cars from the same
# starts; only what it does differs. The cars are shared out over one worker process per core
# (in groups of eight, whose frames the network sees together): the events are the same on a
# laptop of 2 cores and on a machine of 16.

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
# The paper's claim is a sequence of improvements. For each step: do the training seeds of the
# later row collide less than those of the earlier one (`compare_seeds`: an exact one-sided
# permutation test on the seeds' counts, ties kept as ties; paired where a fine-tune shares its
# parent), by how much (the rate ratio, with a bootstrap interval over the seeds), and the
# paper's way? The pooled Poisson test (`compare_rates`, secondary) treats a row's miles as one
# draw. A row more than 10 % slower than the expert is marked: it is not the same claim.
#
# First, what these seeds and miles can show at all: the smallest p-value the seeds can reach,
# and how often a record of this size finds a true 2x step at the + affordance row's rate
# (`power`: Poisson seeds, no seed-to-seed spread, so an upper bound). A "not shown" from a
# record that finds a true 2x step half the time says little.

# %%
aff_counts, per_seed_mi = seed_counts(results["gmm_affordance"])
base_rate = max(0.5, float(np.median(aff_counts)) * 100.0 / per_seed_mi)
reach = power(profile.ablation_seeds, per_seed_mi, base_rate)
print(
    f"{profile.ablation_seeds} seeds x {per_seed_mi:.3g} mi: smallest reachable p "
    f"{reach['min_p']:.2g}; power to find a true 2x step at {base_rate:.1f} per 100 mi: "
    f"{reach['power']:.0%}"
)
# %%
# (before, after, what, paired: the later row is a fine-tune of the earlier, seed by seed; each
# step is the paper's "fewer collisions". PilotNet and L2 have one seed: chapters 05-07 compare
# them, the record tests them)
STEPS = (
    ("actuators", "gmm", "Baseline E2E -> trajectory GMM (seed 000: 183.3 -> 12.7)", False),
    ("gmm", "gmm_affordance", "GMM -> + affordance (seed 000: 12.7 -> 0.83)", False),
    ("gmm_affordance", "gmm_affordance_cvar", "+ affordance -> + CVaR (seed 000: 0.83 -> 0)", True),
)
steps = []
expert_mph = result_dict(results["expert"])["mean_speed_mph"]
for before, after, what, paired in STEPS:
    seeds = compare_seeds(results[after], results[before], paired=paired)
    pooled = compare_rates(results[after], results[before])
    if not (seeds["fewer"] or seeds["more"]):
        outcome = "not shown at the seed level"
    else:
        outcome = "reproduces" if seeds["fewer"] else "the opposite"
    mph = result_dict(results[after])["mean_speed_mph"]
    slow = f", at {mph:.1f} mph (slow)" if mph < 0.9 * expert_mph else ""
    steps.append(
        {
            "step": what,
            "before": before,
            "after": after,
            "seed_level": seeds,
            "pooled_p_value": pooled["p_value"],
            "outcome": outcome + slow,
        }
    )
    print(f"{what}: {seeds['verdict']}; pooled p = {pooled['p_value']:.2g}: {outcome}{slow}")

# %% [markdown]
# ## 3b. Controls: which part of a step did it?
#
# A control changes one thing, with the same seeds on the same roads. Chapter 09 trained the CVaR
# row's: **the fine-tune with the mean** (same parent, epoch, batches, rate, carried optimiser
# and sigmas held at 1) reducing each batch by its mean: is the CVaR step CVaR's, or one more
# epoch's? It shares its parent with the CVaR row, seed by seed, so the tests are paired.
#
# The seeds' spread in each row (the table's "per seed" column, the chart's grey dots) says how
# large training noise is: the course's goal is a worst seed at most `SPREAD_GOAL` times its
# row's median (what brought the GMM within it: lab notes "Every epoch on the road" and "Keeping
# the epoch that drives"). The lines below say whether each row meets the goal. The stalls (a car
# under 0.5 m/s for 20 s, re-placed) say whether a row bought its rate by not driving.
#
# The affordance step has a control too, **w = 0** (`ablation.CONTROLS`: the same network and
# recipe with the auxiliary loss off; chapter 08). It is **the test of the affordance loss**: if
# + affordance does not beat it seed by seed, the step from the GMM is not shown to be the
# loss's. Its four trainings do not fit the course's 2 h on 2 cores: the record trains it with
# every seed, and its verdict is in the record's table (`docs/results.md`); exercise 7 drives it
# here.

# %%
controls = ablation.build_seeded_drivers(profile, ["gmm_affordance_control"], train=train, val=val)
control_results = ablation.evaluate_drivers(controls, world_cfg, ev)
control_table = results_table(
    [(ablation.BY_KEY[k].label, r) for k, r in control_results.items()],
    extra=[
        ("per seed, per 100 mi", [ablation.per_seed(r) for r in control_results.values()]),
        ("stalls", [f"{result_dict(r)['stalls']:,}" for r in control_results.values()]),
    ],
)
print(control_table + profile.caveat)
spreads = {k: spread(result_dict(r)) for k, r in {**results, **control_results}.items()}
for k, ratio in spreads.items():
    if ratio is not None:
        over = "over the goal" if ratio > SPREAD_GOAL else "within the goal"
        print(f"{ablation.BY_KEY[k].label}: worst seed / median {ratio:.1f} ({over})")
control_tests = {}
for control, base, what, paired in (
    ("gmm_affordance_cvar", "gmm_affordance_control", "CVaR fine-tune vs the same with the mean",
     True),
    ("gmm_affordance_control", "gmm_affordance", "the fine-tune with the mean vs its base", True),
):  # fmt: skip
    both = {**results, **control_results}
    verdict = compare_seeds(both[control], both[base], paired=paired)["verdict"]
    control_tests[what] = verdict
    print(f"{what}: {verdict}")

# %% [markdown]
# ## 3c. Where the collisions are
#
# Each collision by kind (`evaluation.collision_kinds`): a guard rail; a parked car in the
# driver's own lane while it is centred in that lane (it neither left the lane nor stopped); a
# parked car hit off centre (changing lanes, or clipped beside). Pooled over the seeds.

# %%
every = {**results, **control_results}
kinds = {k: collision_kinds(r, world_cfg) for k, r in every.items() if k not in ablation.UNTRAINED}
print("| driver | collisions | " + " | ".join(COLLISION_KINDS) + " |")
print("|---|---:|" + "---:|" * len(COLLISION_KINDS))
for k, c in kinds.items():
    cells = " | ".join(str(c[kind]) for kind in COLLISION_KINDS)
    print(f"| {ablation.BY_KEY[k].label} | {result_dict(every[k])['collisions']} | {cells} |")
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
        f"seeds each), {miles_text(reference_ev.miles)} for the others; the same roads",
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
# stretch (test track 0, middle lane, from 30 m) alone, for up to the replay length or until
# its first collision. `e2e_lite.driving.replay` writes each drive as a **standalone 3D page** (meshcat's viewer
# and the scene in one HTML file, no server: open it from disk) with the car's declared intent
# at every decision: the 5 proposed points, one colour per GMM mode, bigger for heavier modes.
# The same drive as a GIF of the camera view with the proposal drawn on it is next to it.

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
    r = result_dict(results[key])
    caption = f"{r['collisions_per_100mi']:.1f} collisions per 100 miles over {miles_text(round(r['miles'], 1))}"
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
# The lines below are computed from this run's numbers; the quick profile's few miles decide
# nothing. The full profile's numbers of record are rendered in `docs/results.md` from committed
# JSON, and the investigations behind the course's recipes (why the data takes the car over, why
# the GMM's targets are scaled per axis, why the GMM holds its sigmas at 1, the controls this
# chapter no longer drives) are in `docs/lab-notes.md`.
#
# What our world lacks that the paper had: 10 times the data, a ResNet-34 instead of a PilotNet
# trunk, moving traffic, and many more epochs. What it adds: every number comes with its
# interval, each training seed's rate and a test, so the reader can see which differences are
# real.

# %%
res_d = {k: result_dict(r) for k, r in results.items()}
learned = [k for k in results if k not in ("expert", "oracle")]
best = min(learned, key=lambda k: res_d[k]["collisions_per_100mi"])
lines = [
    f"best learned driver: {ablation.BY_KEY[best].label} "
    f"({res_d[best]['collisions_per_100mi']:.1f} per 100 mi)",
    f"ceilings: expert {res_d['expert']['collisions_per_100mi']:.1f}, oracle "
    f"{res_d['oracle']['collisions_per_100mi']:.1f} per 100 mi",
    "steps that reproduce the paper's direction: "
    + (", ".join(s["step"] for s in steps if s["outcome"].startswith("reproduces")) or "none"),
    "steps that go the other way: "
    + (", ".join(s["step"] for s in steps if s["outcome"].startswith("the opposite")) or "none"),
    "steps not shown at the seed level: "
    + (", ".join(s["step"] for s in steps if s["outcome"].startswith("not shown")) or "none"),
    "mean speeds [mph]: "
    + ", ".join(f"{k} {res_d[k]['mean_speed_mph']:.1f}" for k in results)
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
        "headline": {f"{k} collisions/100mi": res_d[k]["collisions_per_100mi"] for k in results},
        "miles_per_driver": ev.miles,
        "reference_miles": reference_ev.miles,
        "eval": {
            "n_worlds": ev.n_worlds,
            "n_tracks": ev.n_tracks,
            "first_track": ev.first_track,
            "seed": ev.seed,
        },
        "results": {k: {**res_d[k], "events": None} for k in results},
        "paper": {
            d.key: {"per_100mi": d.paper_per_100mi, "ttc_s": d.paper_ttc_s}
            for d in ablation.DRIVERS
        },
        "paper_mph": ablation.PAPER_MPH,
        "steps": steps,
        "power": {
            "seeds": profile.ablation_seeds,
            "miles_per_seed": per_seed_mi,
            "rate_per_100mi": base_rate,
            **reach,
        },
        "controls": {k: {**result_dict(r), "events": None} for k, r in control_results.items()},
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
# * Every driver of the course drove the same test tracks from the same starts; the table
#   puts our rates, with their 95 % intervals, beside the paper's.
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
# 2. With `evaluation.power`, find the seeds and miles per seed that would find a 1.5x step (not
#    2x) at the + affordance row's rate nine times in ten. What would that record cost in
#    training time on your machine (`python -m e2e_lite.bench train`)?
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
# 7. Train and drive the w = 0 control with this chapter's seeds
#    (`ablation.build_seeded_drivers(profile, ["gmm_affordance_w0"], train=train, val=val)`, then
#    `evaluate_drivers` on `ev`) and test + affordance against it with `compare_seeds`. Does the
#    affordance loss beat its control here? Does your verdict agree with the record's?
