# %% [markdown]
# # 11 · Beyond the paper: a safety module that checks the trajectory
#
# The paper's architecture (seed 000, Fig. 1) sends the predicted trajectory through a **safety
# module** before the controller follows it, and leaves the module unbuilt: "its implementation
# was beyond the scope of this work". A trajectory, unlike a steering angle, says where the car
# means to be in the next 1.5 s, so it can be checked. This chapter builds the check, runs the
# best affordance-predicting GMM driver of chapter 10 with and without it on the same tracks and
# seeds, and measures what it costs.
#
# ## The rule
#
# In the spirit of responsibility-sensitive safety (RSS, Shalev-Shwartz et al. 2017): keep a
# distance from which you can still stop, and do not cut into a lane without that distance.
# The module sees only what the driver perceives: its 5 proposed points `(x_i, y_i)`, its speed
# `v`, the road's curvature `kappa` from the map (as the cruise control knows it), and the 9
# **affordances its own network predicts** (chapter 08): heading to the road `h`, offset from
# the lane centre, distances to markings and road edges, and the free gap ahead in the ego, left
# and right lanes (60 m means "nothing seen").
#
# 1. Where the body goes: sideways in the lane frame, `Delta_i = y_i + h x_i - kappa x_i^2 / 2`,
#    the body spanning `Delta_i +- w/2`.
# 2. Lateral: stay on the road: `Delta_i + w/2 <= left edge + 0.3 m` (and on the right).
# 3. Lanes entered: the body more than 0.3 m across a marking occupies that lane.
# 4. Longitudinal, in every lane occupied, with `g` that lane's gap: (a) the body never reaches
#    the parked car `g` metres ahead within the 1.5 s; (b) if the 1.5 s end in that lane, the car
#    can still stop: `g - x_5 >= v_5 rho + v_5^2 / (2 beta) + margin` with reaction `rho = 0.2 s`,
#    braking `beta = 6 m/s^2` (the tracker's limit), margin 2 m.
#
# On a failed check: the network's other GMM mode if it passes, else a **keep-lane braking**
# trajectory (back to the lane centre, braking at `beta`). The **ground-truth variant** feeds the
# world's true affordances into the same rule: the upper bound that better perception would buy.
#
# Run it with `python chapters/11_safety_module.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course import start_chapter

profile = start_chapter(11)  # flags, profile, outputs folder: checked before any work

import textwrap

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from e2e_lite import ablation, artifacts, recipes
from e2e_lite.agents import TrajectoryAgent
from e2e_lite.camera import Camera, CameraConfig, draw_trajectory
from e2e_lite.data import AFFORDANCE_NAMES, DataConfig, load_or_collect
from e2e_lite.evaluation import EvalConfig, compare_rates, evaluate, result_dict, results_table
from e2e_lite.safety import SafeAgent, SafetyConfig, check
from e2e_lite.viz import save_figure
from e2e_lite.world import WorldConfig

world_cfg = WorldConfig.for_profile(profile)
cfg = SafetyConfig()
print(f"{cfg}")

# %% [markdown]
# ## 1. The rule on the expert's own trajectories
#
# Before trusting a check, run it on trajectories known to be safe: the expert's labels of the
# validation set (it never collides). With the **true** affordances, the share it rejects is the
# rule's own strictness; with the affordances the **network predicts** for the same frames, the
# extra rejections are what imperfect perception adds.

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
a = val.arrays
candidates = ("gmm_affordance", "gmm_affordance_cvar")  # the GMM drivers that predict affordances
ten = artifacts.read_metrics("10_ablation", profile.name)
if ten is not None:
    key = min(candidates, key=lambda k: ten["results"][k]["collisions_per_100mi"])
    print(f"chapter 10's best GMM driver with an affordance head: {key}")
else:
    key = "gmm_affordance"
    print("chapter 10 has not run in this profile: using GMM + affordance")
weight = recipes.affordance_weight(profile, train, val)
recipe = recipes.gmm_affordance if key == "gmm_affordance" else recipes.gmm_affordance_cvar
model = recipe(profile, train, val, weight)[0]
agent = TrajectoryAgent(model)

rows = np.arange(0, len(val), max(1, len(val) // 4000))  # up to ~4,000 samples
predicted = []
for i in range(0, len(rows), 256):
    batch = rows[i : i + 256]
    agent.trajectories_from(a["images"][batch], a["speed"][batch])  # fills agent.last
    predicted.append(agent.last["affordances"])
predicted = np.concatenate(predicted)
expert_ok = {"true": [], "predicted": []}
for j, r in enumerate(rows):
    args = (a["trajectory"][r], float(a["speed"][r]), float(a["curvature"][r]), cfg)
    expert_ok["true"].append(check(args[0], a["affordances"][r], *args[1:]).ok)
    expert_ok["predicted"].append(check(args[0], predicted[j], *args[1:]).ok)
accept = {k: 100.0 * float(np.mean(v)) for k, v in expert_ok.items()}
print(
    f"the expert's trajectories on {len(rows)} validation samples: accepted {accept['true']:.1f} % "
    f"with the true affordances, {accept['predicted']:.1f} % with the network's"
)
gap_i = AFFORDANCE_NAMES.index("gap_ego_m")
err = np.abs(predicted[:, gap_i] - a["affordances"][rows, gap_i])
print(
    f"the network's gap to the car ahead: mean |error| {err.mean():.1f} m; predicted range "
    f"{predicted[:, gap_i].min():.1f}-{predicted[:, gap_i].max():.1f} m, true range "
    f"{a['affordances'][rows, gap_i].min():.1f}-{a['affordances'][rows, gap_i].max():.1f} m"
)

# %% [markdown]
# ## 2. Closed loop: without, with (perceived), with (ground truth)
#
# Same validation tracks, same seeds and the same two shards of cars as chapter 10 (each shard
# sends the module's counters home). The row without the module is the same network (chapter
# 10's training seed 0) over the same miles, stored and reused. The module audits one
# intervention in four: would a fresh expert, from the same state, have driven what the network
# proposed (then the intervention was a **false alarm**)? And would the ground-truth rule have
# accepted it (then **perception alone** caused it)?

# %%
# (the quick profile's barely trained network makes the module crawl: a fifth of a mile is enough)
miles = 0.2 if profile.quick else profile.ablation_miles
ev = EvalConfig(miles=miles, n_worlds=profile.ablation_worlds)
stored = ablation.evaluate_drivers({key: agent}, world_cfg, ev, workers=profile.ablation_workers)
without = stored[key]
guarded = {}
stats = {}
variants = (("perceived", False), ("ground truth", True))
for name, gt in variants:
    safe = SafeAgent(TrajectoryAgent(model), cfg, ground_truth=gt, audit_every=4)
    res = evaluate(
        safe, world_cfg, ev, desc=f"with the module ({name})", workers=profile.ablation_workers
    )
    guarded[name], stats[name] = (res, safe), safe.stats.to_dict()
    print(f"with the module ({name}): {res.summary()}")

label = ablation.BY_KEY[key].label
table = results_table(
    [(label, without)] + [(f"{label} + safety module ({n})", guarded[n][0]) for n, _ in variants]
)
print(table + profile.caveat)
print("| module | interventions | other mode / fallback | false alarms | perception only |")
print("|---|---:|---:|---:|---:|")
for name, _ in variants:
    s = stats[name]
    print(
        f"| {name} | {s['intervention_pct']:.1f}% of {s['decisions']:,} decisions | "
        f"{s['sources'].get('other mode', 0):,} / {s['sources'].get('fallback', 0):,} | "
        f"{s['false_alarm_pct']:.1f}% | {s['perception_only_pct']:.1f}% |"
    )
verdicts = {name: compare_rates(guarded[name][0], without)["verdict"] for name, _ in variants}
for name, v in verdicts.items():
    print(f"with the module ({name}) vs without: {v}")

# %% [markdown]
# ## 3. Interventions, frame by frame
#
# What the network proposed (one colour per mode, its weight in the caption), why the module
# rejected the heaviest mode, and what was driven instead (green). Views re-rendered from the
# decision's pose with the wide camera; one column per module.

# %%
view = Camera(CameraConfig.human())
MODE_RGB = ((40, 110, 230), (240, 140, 30))
DRIVEN_RGB = (40, 200, 60)
examples = {name: guarded[name][1].examples()[:3] for name, _ in variants}
n_rows = max(len(v) for v in examples.values())
if n_rows:
    fig = Figure(figsize=(13, 3.3 * n_rows + 0.6), layout="constrained")
    axes = np.array(fig.subplots(n_rows, len(variants), squeeze=False))
    for col, (name, _) in enumerate(variants):
        for row in range(n_rows):
            ax = axes[row, col]
            ax.set_axis_off()
            if row >= len(examples[name]):
                continue
            ex = examples[name][row]
            img = view.render(ex["track"], ex["cars"], tuple(ex["pose"]), ex["s"])
            for k in np.argsort(ex["weights"]):
                draw_trajectory(img, ex["modes"][k], view, MODE_RGB[k % 2])
            draw_trajectory(img, ex["chosen"], view, DRIVEN_RGB)
            ax.imshow(img)
            weights = ", ".join(
                f"{('blue', 'orange')[k % 2]} {w:.2f}" for k, w in enumerate(ex["weights"])
            )
            caption = f"{name}: {ex['reason']}. Mode weights: {weights}; driven: {ex['source']}."
            ax.set_title(textwrap.fill(caption, 80), fontsize=8, loc="left")
    fig.legend(
        handles=[Line2D([], [], color=np.array(c) / 255, marker="o", label=t)
                 for c, t in ((MODE_RGB[0], "mode 1"), (MODE_RGB[1], "mode 2"),
                              (DRIVEN_RGB, "what was driven"))],
        loc="outside lower center", ncols=3, fontsize=9,
    )  # fmt: skip
    grid_png = save_figure(fig, artifacts.artifact_path("figures", "11_interventions.png"))
    print(f"saved {grid_png}")
else:
    grid_png = None
    print("no intervention was recorded")

# %% [markdown]
# ## 4. What the module buys, and what it needs
#
# Read the two tables together. The ground-truth row is what the rule can do when it knows where
# the parked cars are; the perceived row is what it does with the network's own affordances.
# Chapter 08 found that head no better than always answering the training mean: section 1
# measured what that does to the check (the expert's own safe trajectories rejected), and the
# closed loop shows the consequence. A safety module is only as good as the perception under it,
# and a learned perception has to be measured before it is trusted with a veto.

# %%
lines = [
    f"expert trajectories accepted: {accept['true']:.1f} % (true affordances), "
    f"{accept['predicted']:.1f} % (predicted)",
    f"without: {result_dict(without)['collisions_per_100mi']:.1f} per 100 mi at "
    f"{result_dict(without)['mean_speed_mph']:.1f} mph",
]
for name, _ in variants:
    r = guarded[name][0]
    lines.append(
        f"with ({name}): {r.collisions_per_100mi:.1f} per 100 mi at {r.mean_speed_mph:.1f} mph, "
        f"interventions {stats[name]['intervention_pct']:.1f} %, "
        f"false alarms {stats[name]['false_alarm_pct']:.1f} %; {verdicts[name]}"
    )
print("\n".join(lines))

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "11_safety_module",
    {
        "profile": profile.name,
        "headline": {
            "without collisions/100mi": result_dict(without)["collisions_per_100mi"],
            **{
                f"with ({n}) collisions/100mi": guarded[n][0].collisions_per_100mi
                for n, _ in variants
            },
        },
        "driver": key,
        "settings": repr(cfg),
        "expert_accepted_pct": accept,
        "results": {
            "without": {**result_dict(without), "events": None},
            **{n: guarded[n][0].to_dict(with_events=False) for n, _ in variants},
        },
        "module": stats,
        "verdicts": verdicts,
        "table_md": table,
        "lines": lines,
        "figures": [str(grid_png.relative_to(artifacts.outputs_dir()))] if grid_png else [],
    },
)

# %% [markdown]
# ## Summary
#
# * A trajectory can be checked before it is driven: a few lines of geometry (where the body
#   goes, which lanes it enters, whether it can still stop) decide.
# * The check is only as good as what it is fed: with the world's true gaps it is the upper
#   bound; with the network's predicted affordances it inherits their errors.
# * Caution has a price, measured here in interventions, false alarms and miles per hour.
#
# ## Exercises
#
# 1. Set `SafetyConfig(brake_mps2=8.0)` (the car's hardest braking) and `reaction_s=0.0`: how do
#    interventions, false alarms and speed move? Which setting would you defend, and why?
# 2. Feed the module the true gaps but the predicted offset and heading (or the reverse): which
#    affordance does the perceived check suffer from most?
# 3. Replace the fallback by "the heaviest mode, braking": when is it better than keep-lane?
# 4. Check the L2 driver of chapter 06 (`ground_truth=True`; it has a single mode): does it gain
#    more or less than the GMM from the module?
