# %% [markdown]
# # 12 · Beyond the paper: DAgger, the learner's own states
#
# The course's best learned drivers still collide far more often than the **oracle**, the same
# LQR tracker following the expert's own 5-point plans on the same roads with the same camera
# (chapter 10 and the record print both). The gap is the network's plans in the states it visits,
# and chapter 04 named the usual cause: **covariate shift**. The network was trained on the
# states the expert drives into; a small error takes it into states the expert never showed, where
# it errs more.
#
# Ross, Gordon and Bagnell (AISTATS 2011) made this precise. If a cloned policy errs with
# probability `eps` on the expert's states, then over `T` decisions its expected cost can grow as
# `eps T^2`: each mistake moves it off the expert's distribution, where nothing bounds its errors.
# **DAgger** (dataset aggregation) trains on the learner's own states instead: the learner drives,
# the expert labels every state it visits, the data is aggregated, and the network is trained
# again; its cost then grows as `eps T` (their Theorem 3.1). In their kart-racing task a cloned
# driver kept leaving the track however much expert data it had; after a few DAgger rounds it
# almost never did.
#
# This chapter runs DAgger on the course's best learned driver and asks two questions, each with
# a test: does the driver collide less after the rounds than before (**the step**), and does it
# collide less than **the control**, the same rounds with as many samples from the expert's own
# driving on the same fresh roads and the same fine-tunes (**is it the learner's states**, or just
# more data and more epochs?). What you will learn: why cloning compounds, how to label a
# learner's states, how to measure covariate shift, and why a data method needs a data control.
#
# Run it with `python chapters/12_dagger.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course import start_chapter

profile = start_chapter(12)  # flags, profile, outputs folder: checked before any work

import numpy as np
from matplotlib.figure import Figure

from e2e_lite import ablation, artifacts
from e2e_lite.control.expert import Expert
from e2e_lite.control.oracle import Oracle
from e2e_lite.driving.evaluation import EvalConfig, compare_seeds, power, result_dict, seed_counts
from e2e_lite.learning import dagger, recipes
from e2e_lite.learning.agents import TrajectoryAgent
from e2e_lite.learning.checkpoints import train_or_load, training_data_key
from e2e_lite.learning.collector import DataConfig, OnPolicy, collect, load_or_collect
from e2e_lite.record.stats import record_dispersion
from e2e_lite.report import load
from e2e_lite.simulation.world import WorldConfig
from e2e_lite.viz import save_figure

world_cfg = WorldConfig.for_profile(profile)
seeds = list(range(profile.ablation_seeds))  # chapter 10's training seeds

# %% [markdown]
# ## 1. The start network, and the rounds
#
# The start is **GMM + affordance + CVaR** (chapter 09), one network per training seed: the
# paper's final row, and the lowest pooled rate among the paper's rows (tied with its control,
# the mean fine-tune) in the first record (seeds 0-9), the one this recipe was chosen on. A
# round (`dagger.DaggerConfig`) adds a sixth of the training data:
#
# * the current network drives fresh **training** roads (never validation or test roads), the
#   expert executing a share `beta` of the decisions. Ross et al.'s first round (`beta = 1`,
#   pure expert) is chapter 04's data, so every round here lets the learner drive alone;
# * an expert labels every state visited, in chapter 04's schema: one that plans afresh at each
#   state, so that a state's label depends on the state alone, as DAgger assumes (the collector's
#   expert remembers its plans: exercise 3); a collision or a stall re-places the car as the
#   evaluator does;
# * the samples join the aggregate, and the network is fine-tuned on them plus as many replayed
#   from the earlier data: chapter 09's control fine-tune (the chapter-08 loss with the mean,
#   one epoch, its Adam carried at a tenth of the rate), so DAgger adds data, not a new loss.

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
weight = recipes.affordance_weight(profile, train, val)
cfg = dagger.DaggerConfig.for_profile(profile)
print(
    f"{len(seeds)} training seeds, {cfg.rounds} rounds of {cfg.samples:,} samples, betas "
    f"{cfg.betas}, {cfg.replay:g} replayed sample per new one"
)

# %% [markdown]
# ## 2. One round, written out
#
# The library's round (`dagger.run`) is these lines for seed 0's first round: the learner drives
# and the expert labels (`collect` with a learner: each decision the expert computes its label
# at the car's state, and the learner's command is executed unless it is the expert's turn),
# the round's samples are measured against the data the network saw, and the network is
# fine-tuned from its parent on the new samples plus replayed old ones.

# %%
start0, _, _ = recipes.gmm_affordance_cvar(profile, train, val, weight, 0)
drive = dagger.RoundSpec(profile, cfg, 0, 0, "dagger").data()  # fresh training roads, no noise
learner = OnPolicy(TrajectoryAgent(start0), beta=cfg.betas[0], fresh=cfg.fresh)
visited = collect(drive, progress=False, on_policy=learner)
shift = dagger.covariate_shift(visited, [train])  # outside the data's 1-99 % range
ft_data = dagger.finetune_set([train], visited, cfg.replay, 0, 0)  # new + replayed old
objective, tcfg = recipes.finetune_settings(profile, weight, 0, "mean")
by_hand, _ = train_or_load(
    "12_by_hand",
    recipes.AFFORDANCE_CFG,
    tcfg,
    objective,
    ft_data,
    val,
    init_from="09_gmm_affordance_cvar",
    parent_data_key=training_data_key(train, val),
    carry_optimizer=True,
    progress=False,
)
print(
    f"round 1 by hand: {len(visited):,} samples, aggregate {len(train) + len(visited):,}; "
    f"outside the data's range: {shift['any']:.1%}"
)

# %% [markdown]
# Now the library's rounds, for every seed and both arms: DAgger, and the control whose samples
# come from the expert's own noisy driving (chapter 04's collector, take-overs and all) on the
# same fresh roads, fine-tuned the same way from the same parent. The first round of seed 0 must
# be the one written out above: the same samples, to the byte, and the same weights (to the bit
# on a CPU; a GPU's kernels are not deterministic).

# %%
runs = {k: dagger.run(profile, train, val, weight, k, cfg) for k in seeds}
first = runs[0][1]["dagger"][0]
library_visited = dagger.RoundSpec(profile, cfg, 0, 0, "dagger").samples(start0, progress=False)
assert all(np.array_equal(visited.arrays[f], library_visited.arrays[f]) for f in visited.arrays)
mine, theirs = by_hand.state_dict(), first.model.state_dict()
apart = max(float((mine[n].float() - theirs[n].float()).abs().max()) for n in mine)
assert apart < 1e-2, apart  # (0 on a CPU; a GPU's kernels are not deterministic)
print(f"the round written out and dagger.run agree: the same samples, weights {apart:.1g} apart")
for k, (_, arms) in runs.items():
    for arm, rounds in arms.items():
        for r in rounds:
            drove = r.collection.get("collisions_per_100mi", float("nan"))
            print(
                f"seed {k} {arm:7s} round {r.round}: +{r.samples:,} samples -> "
                f"{r.aggregate:,}; visited outside the data {r.shift['any']:.1%}; while "
                f"collecting {r.collection.get('miles', float('nan')):.1f} mi, "
                f"{drove:.1f} collisions per 100 mi"
            )

# %% [markdown]
# ## 3. Covariate shift, measured
#
# Each DAgger round's samples are the states the network of the round before visited, driving
# alone. How far do they lie from the data that network was trained on? Per feature (lateral
# offset, heading error, speed, gap ahead), the share of visited states outside the training
# data's 1st to 99th percentiles; "any" counts a state outside in at least one. States drawn like
# the data leave that range rarely, by its construction. If DAgger works, the share falls round
# by round: the network's states move towards its data, and its data towards its states.

# %%
names = [*dagger.SHIFT_FEATURES, "any"]
shift_by_round = np.array(
    [[[r.shift[n] for n in names] for r in arms["dagger"]] for _, arms in runs.values()]
)  # (seeds, rounds, features)
print("| round | " + " | ".join(names) + " |")
print("|---|" + "---:|" * len(names))
for j in range(cfg.rounds):
    cells = " | ".join(
        f"{100 * np.median(shift_by_round[:, j, f]):.1f} %" for f in range(len(names))
    )
    print(f"| {j + 1} (the network of round {j}) | {cells} |")

# %% [markdown]
# ## 4. Round by round, on validation roads
#
# Each network (the start, and each round of both arms) drives the validation roads, every
# training seed on roads of its own, beside the expert and the oracle (the LQR tracker on the
# expert's plans). This is the figure Berkeley's CS285 asks of its students: round on the x axis,
# each seed a point, the median a line. Rounds are chosen on these roads, so the verdicts of
# section 5 drive the test roads instead.

# %%
on_val = dagger.val_roads(profile.eval_miles, profile.ablation_worlds)
nets = {"start": [start for start, _ in runs.values()]}
for arm in dagger.ARMS:
    for j in range(cfg.rounds):
        nets[f"{arm} round {j + 1}"] = [arms[arm][j].model for _, arms in runs.values()]
drivers = {f"12_{k.replace(' ', '_')}": [TrajectoryAgent(m) for m in v] for k, v in nets.items()}
driven = ablation.evaluate_drivers(drivers, world_cfg, on_val)
ceilings = ablation.evaluate_drivers(
    {"12_expert": Expert(), "12_oracle": Oracle()}, world_cfg, on_val
)
per_seed = {k: 100.0 * np.divide(*seed_counts(r)) for k, r in zip(nets, driven.values())}
for k, rates in per_seed.items():
    print(f"{k:18s} per seed {' / '.join(f'{x:.1f}' for x in rates)} per 100 mi (validation)")
line = {k: result_dict(r)["collisions_per_100mi"] for k, r in ceilings.items()}
print(f"expert {line['12_expert']:.1f}, oracle {line['12_oracle']:.1f} per 100 mi (validation)")

# %%
fig = Figure(figsize=(10, 3.8), layout="constrained")
ax, ax_shift = fig.subplots(1, 2, gridspec_kw={"width_ratios": [3, 2]})
x = np.arange(cfg.rounds + 1)
for arm, color, dx in (("dagger", "C0", -0.06), ("control", "C1", 0.06)):
    keys = ["start", *(f"{arm} round {j + 1}" for j in range(cfg.rounds))]
    rates = np.array([per_seed[k] for k in keys])  # (rounds + 1, seeds)
    for col in rates.T:
        ax.scatter(x + dx, col, color=color, s=14, alpha=0.6)
    ax.plot(x + dx, np.median(rates, axis=1), color=color, lw=2, label=f"{arm}: median of seeds")
ax.axhline(np.median(per_seed["start"]), color="0.3", ls=":", label="start network")
ax.axhline(line["12_oracle"], color="0.5", ls="--", label="oracle")
ax.axhline(line["12_expert"], color="C2", ls="--", label="expert")
ax.set(xticks=x, xlabel="round (0: the start network)", ylabel="collisions per 100 mi, validation")
ax.legend(fontsize=8)
for f, name in enumerate(names):
    ax_shift.plot(
        np.arange(1, cfg.rounds + 1),
        100 * np.median(shift_by_round[:, :, f], axis=0),
        marker="o",
        label=name,
    )
ax_shift.set(xlabel="round", ylabel="visited states outside the data [%]", xticks=x[1:])
ax_shift.legend(fontsize=7)
fig.suptitle(f"DAgger and its control, {len(seeds)} training seeds", fontsize=11)
png = save_figure(fig, artifacts.artifact_path("figures", "12_dagger.png"))
print(f"saved {png}")

# %% [markdown]
# ## 5. The verdicts, on test roads
#
# The start network, the last DAgger round and the last control round drive the test roads
# (chapter 10's: seed `k` of each on the same roads), and two paired sign-flip tests by seed read
# them: **the step** (last round against its start network) and **the control** (DAgger against
# its control, which shares its parent, its roads and its fine-tunes, but not its labeller:
# exercise 7). The power line says what these seeds can find: a true 2x step at the start's
# rate, with the record's seed spread.

# %%
ev = EvalConfig(miles=profile.ablation_miles, n_worlds=profile.ablation_worlds)
last = f"round_{cfg.rounds}"
rows = {
    "start": "gmm_affordance_cvar",
    "dagger": f"12_dagger_{last}",
    "control": f"12_control_{last}",
}
nets_of = {"start": "12_start", "dagger": f"12_dagger_{last}", "control": f"12_control_{last}"}
on_test = ablation.evaluate_drivers(
    {rows[k]: drivers[n] for k, n in nets_of.items()}, world_cfg, ev
)
test = {k: on_test[v] for k, v in rows.items()}
counts, per_mi = seed_counts(test["start"])
start_rate = max(0.5, float(np.median(counts)) * 100.0 / per_mi)
spread_k = record_dispersion(load())["dispersion"]
reach = power(len(seeds), per_mi, start_rate, dispersion=spread_k, test="sign-flip")
print(
    f"{len(seeds)} seeds x {per_mi:.3g} mi: a true 2x step at {start_rate:.1f} per 100 mi is "
    f"found in {reach['power']:.0%} of records (paired, the record's seed spread "
    f"{spread_k:.2f}); smallest reachable p {reach['min_p']:.2g}"
)
pairs = {
    "the step: DAgger's last round vs its start": ("dagger", "start"),
    "the control: DAgger vs its control": ("dagger", "control"),
    "the control's step: control vs the start": ("control", "start"),
}
verdicts = {what: compare_seeds(test[a], test[b], paired=True) for what, (a, b) in pairs.items()}
for what, v in verdicts.items():
    print(f"{what}: {v['verdict']}")
rate = {k: result_dict(r)["collisions_per_100mi"] for k, r in test.items()}
mph = {k: result_dict(r)["mean_speed_mph"] for k, r in test.items()}
print("test roads: " + ", ".join(f"{k} {rate[k]:.1f} per 100 mi at {mph[k]:.1f} mph" for k in rate))

# %% [markdown]
# ## Headline figures

# %%
shift_first, shift_last = (float(np.median(shift_by_round[:, j, -1])) for j in (0, -1))
headline = {
    "start collisions/100mi": rate["start"],
    "DAgger collisions/100mi": rate["dagger"],
    "control collisions/100mi": rate["control"],
    "DAgger mph": mph["dagger"],
    "visited outside the data, round 1": shift_first,
    f"visited outside the data, round {cfg.rounds}": shift_last,
}
config = {k: getattr(cfg, k) for k in ("rounds", "samples", "betas", "replay")} | {
    "seeds": len(seeds)
}


def round_entry(r: dagger.Round) -> dict:
    return {k: getattr(r, k) for k in ("round", "samples", "aggregate", "shift", "collection")}


rounds = {
    k: {a: [round_entry(r) for r in rs] for a, rs in arms.items()} for k, (_, arms) in runs.items()
}
tested = {
    k: {"verdict": v["verdict"], "p": v["p_fewer"], "ratio": v["ratio"]}
    for k, v in verdicts.items()
}
# %%
metrics = {
    "profile": profile.name,
    "headline": headline,
    "config": config,
    "rounds": rounds,
    "train_samples": len(train),
    "validation_per_seed": {k: v.tolist() for k, v in per_seed.items()},
    "ceilings_validation": line,
    "test": {k: {**result_dict(r), "events": None} for k, r in test.items()},
    "verdicts": tested,
    "power": {**reach, "dispersion": spread_k, "rate_per_100mi": start_rate},
}
artifacts.write_metrics("12_dagger", metrics, figures=(png,))

# %% [markdown]
# ## Summary
#
# * Cloning trains on the expert's states; a learner that errs drifts into others, where its
#   errors compound (`eps T^2`). DAgger labels the learner's own states with the expert and
#   aggregates them (`eps T`).
# * A round is a collection with the learner driving (`collect(..., on_policy=OnPolicy(...))`): the
#   expert labels every state, whoever drives; the network is fine-tuned on the new samples
#   plus replayed old ones.
# * Covariate shift can be measured: the share of visited states outside the training data's
#   range, round by round.
# * A data method needs a data control: the same number of samples from the expert's own
#   driving, on the same roads, with the same fine-tunes. Only a step that beats it is the
#   learner's states; the verdict lines above say whether this run's did. A control must differ
#   in one thing: this one's labels come from the collector's expert, DAgger's from the fresh
#   one (exercise 7 holds the labeller fixed).
# * DAgger can only label the states a round visits. Compare the miles one round drove (section
#   2) with the miles between the start network's collisions (section 5): the states that end in
#   a collision are rare, and a round of this size may visit none of them (exercise 6).
# * DAgger assumes an expert whose label depends on the state alone: the course's labels come
#   from an expert planning afresh at each state. A planner that remembers its plan labels a
#   learner that lagged it with the rest of that plan: a swerve (exercise 3).
#
# ## Exercises
#
# 1. The beta schedule: run the rounds with `betas=(0.5, 0.0)` and `(1.0, 0.0)`
#    (`dagger.DaggerConfig.for_profile(profile, betas=...)`). How does the first round's
#    covariate shift change, and the driving after it?
# 2. More rounds: `rounds=4` with four betas. Does the shift keep falling, and the collisions?
#    Prakash et al. (2020) saw plain DAgger get worse after its second round: does ours?
# 3. Labels with memory: run the rounds with `labels="expert"` (the collector's expert, which
#    remembers its plans). How often do its labels ask for a swerve, against the fresh expert's,
#    and how do the rounds drive (lab note "Who labels DAgger's states")?
# 4. No aggregation: set `replay=0.0`, so each round fine-tunes on its new samples alone. What
#    does the network forget (drive it, and compare the shift)?
# 5. DAgger from the GMM (chapter 07) instead of the final network: does a worse start gain more?
# 6. Rare states: how many collisions should a round of `cfg.samples` meet at the start's rate on
#    test roads? Run one round of six times the samples (`samples=6 * cfg.samples`): how many
#    collisions did its collection meet, and does the fine-tune on them drive better?
# 7. The control's labeller: run the control with `control_labels="fresh"` (its very states,
#    labelled by the fresh expert). Does it still drive as the course's control does? Which of
#    DAgger's two differences from its control, states or labels, moves the collisions?
