# %% [markdown]
# # 08 · Perception as an auxiliary task (affordances)
#
# The paper's third idea (seed 000, section 3.4): besides the trajectory, ask the network to say
# what it sees, a handful of **affordances** (after DeepDriving): the heading relative to the
# road, the offset from the lane centre, the distances to the lane markings and road edges, and
# the gaps to the nearest car ahead in the ego, left and right lanes. They are not used to drive;
# they shape the shared features. Two arguments:
#
# * **sample efficiency**: every frame now carries 9 more labels, dense and cheap to get in a
#   simulator; features that must predict "a car 35 m ahead in my lane" are the features an
#   overtake needs;
# * **interpretability**: when the car does something odd, the predicted affordances say whether
#   it mis-saw (a gap of 60 m where there are 20) or mis-decided.
#
# A small head predicts the 9 affordances, normalised per affordance with the training set's
# statistics, and the loss becomes
#
# $$\mathcal{L} = \mathcal{L}_{\text{GMM}}(x, y) + w\,\frac{1}{9}\sum_{j=1}^{9}
#   \big(\hat a_j(x) - a_j\big)^2 \quad\text{(normalised } a_j\text{)}.$$
#
# The paper chose `w` by grid search; so do we, on held-out *trajectory* NLL (the combined loss
# is not comparable across `w`).
#
# *Where* the head reads is a choice too. The paper's Fig. 1 puts it on the fusion network's
# output, beside the trajectory head. The course's head reads the image backbone's (trunk's)
# features instead: section 4 shows the measurement behind that choice, the paper's placement
# beside ours (`recipes.AFFORDANCE_FROM`).
#
# Run it with `python chapters/08_affordance.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course import start_chapter

profile = start_chapter(8)  # flags, profile, outputs folder: checked before any work

import numpy as np
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.control.labels import AFFORDANCE_INDEX, CHANGE
from e2e_lite.driving.evaluation import (
    EvalConfig,
    compare_rates,
    evaluate,
    miles_text,
    results_table,
)
from e2e_lite.learning import recipes
from e2e_lite.learning.agents import Recorder, TrajectoryAgent
from e2e_lite.learning.data import (
    AFFORDANCE_NAMES,
    GAP_CAP_M,
    DataConfig,
    DrivingDataset,
    affordances,
    load_or_collect,
)
from e2e_lite.learning.heldout import affordance_errors, goal_ratios
from e2e_lite.learning.probes import PROBE_LAYERS, probe_affordances
from e2e_lite.learning.training import evaluate_loss
from e2e_lite.simulation.world import WorldConfig
from e2e_lite.viz import collision_chart, save_figure

world_cfg = WorldConfig.for_profile(profile)
GAP, OFFSET = AFFORDANCE_INDEX["gap_ego_m"], AFFORDANCE_INDEX["center_offset_m"]

# %% [markdown]
# ## 1. The affordance labels
#
# Recorded with every sample by chapter 04's collector (pymunk segment queries in the ego's lane
# and its neighbours). A gap with no car within 60 m reads 60 m; a lane that does not exist reads
# 0 m (nothing to drive into).

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
a_mean, a_std = train.stats["affordances_mean"], train.stats["affordances_std"]
for name, m, s in zip(AFFORDANCE_NAMES, a_mean, a_std):
    print(f"  {name:16s} mean {m:8.3f}   std {s:7.3f}")
print(
    f"samples with a car within 60 m in the ego lane: {np.mean(train.affordances[:, GAP] < GAP_CAP_M):.1%}"
)

# %% [markdown]
# ## 2. Choosing w
#
# Each candidate trains the same GMM + affordance model on the same fixed subset of the training
# set for a short schedule (sigma frozen in the first epoch when there are two); the score is the
# trajectory NLL alone on the validation samples. `w = 0` is the chapter-07 model with an unused
# head: the reference. If it wins, the auxiliary loss does not help the trajectory, and the head
# is kept for what it perceives (chapter 11's safety module reads it): the `w > 0` whose head has
# the lowest held-out affordance error is trained (each affordance's MAE over its spread,
# averaged).

# %%
scores = recipes.affordance_grid(profile, train, val, progress=False)
for w, sc in scores.items():
    print(
        f"w = {w:<4g}: held-out trajectory NLL {sc['trajectory_nll']:7.3f}, "
        f"ADE {sc['ADE_m']:.3f} m, affordance error {sc['affordance_rel_mae']:.3f} of the "
        f"spread, gap-ahead error {sc['gap_ego_mae_m']:.2f} m"
    )
w_best, why = recipes.choose_affordance_weight(scores)
first = next(iter(scores.values()))
print(f"chosen {why} ({first['train_samples']} samples, {first['epochs']} epoch(s) each)")

# %% [markdown]
# ## 3. Training with the chosen w
#
# Same schedule as chapter 07 (sigma frozen in the first epoch, then opened), so the two models
# differ only by the auxiliary head and its loss.

# %%
model, objective, hist = recipes.gmm_affordance(profile, train, val, w_best)
val_losses, val_metrics = evaluate_loss(model, objective, DrivingDataset(val))
held = {k: float(v.mean()) for k, v in val_metrics.items()}
print(
    f"held out: trajectory NLL {held['main loss']:.3f}, ADE {held['ADE [m]']:.3f} m, "
    f"FDE {held['FDE [m]']:.3f} m"
)
gmm07 = artifacts.read_metrics("07_gmm", profile.name)
if gmm07 is not None:
    print(
        f"chapter 07 (no affordance head): NLL {gmm07['held_out']['nll']:.3f}, "
        f"ADE {gmm07['held_out']['ADE [m]']:.3f} m"
    )

# %% [markdown]
# ### The head over the epochs, and the epoch that was kept
#
# The checkpoint is the epoch with the lowest *decisive ADE* (chapter 07: the trajectory on the
# frames that decide a drive), because the network is kept for how it drives. The head has no
# say in that choice. Its validation error after each epoch (all frames, MAE, from the training
# history) against the mean predictor's shows what the choice costs the perception: when the
# first epoch (sigma frozen) drives best, the head that is kept has trained for one epoch.

# %%
head_names = ("center_offset_m", "gap_ego_m", "heading_rad")
mean_mae_all = {  # the mean predictor on every validation frame, as the history's errors are
    n: float(np.mean(np.abs(a_mean[AFFORDANCE_INDEX[n]] - val.affordances[:, AFFORDANCE_INDEX[n]])))
    for n in head_names
}
head_by_epoch = [
    {
        "epoch": e["epoch"],
        "decisive_ade_m": e.get("decisive ADE [m]"),
        **{n: e[f"|err| {n}"] / mean_mae_all[n] for n in head_names},
    }
    for e in hist.epochs
    if all(f"|err| {n}" in e for n in head_names)
]
print("epoch  decisive ADE [m]  head MAE / mean predictor's MAE: " + ", ".join(head_names))
for row in head_by_epoch:
    kept = "  <- kept" if row["epoch"] == hist.best_epoch else ""
    ratios = "  ".join(f"{row[n]:5.2f}" for n in head_names)
    print(f"{row['epoch'] + 1:5d}  {row['decisive_ade_m'] or float('nan'):16.3f}  {ratios}{kept}")

# %% [markdown]
# ### The head, trained to the end on the kept trunk
#
# The kept network is kept for how it drives; the head it carries need not stay as young as
# that epoch. So the course trains the head **alone** on, on the frozen features it reads (the
# kept trunk), with the loss it trained with, for the probes' schedule (section 4: 30 passes of
# Adam at 1e-3 over every training frame, inputs standardised while it trains and folded back
# into its first layer after). No other weight moves, so the network drives exactly as the kept
# one (`recipes.perceiving`; tested to the bit). Everything below that reads the network's
# affordances (the scatter, the drive, chapter 11's safety module) reads this head; the joint
# head's errors are printed beside it.

# %%
perceiver = recipes.perceiving(model, train, "08_gmm_affordance")

# %% [markdown]
# ## 4. What the network sees: predicted against true affordances
#
# On the validation frames, coloured by situation (a parked car within 60 m in the own lane, a
# lane change, a curve, the rest). Points on the diagonal are right; the gaps saturate at 60 m
# (no car in range), which shows as a column at the right edge.

# %%
rows = np.arange(0, len(val), max(1, len(val) // 3000))


def head_affordances(net) -> np.ndarray:
    """A network's own affordance predictions on the scatter's frames (``rows``)."""
    seer = TrajectoryAgent(net)
    out = []
    for c in np.array_split(rows, max(1, len(rows) // 256)):
        seer.trajectories_from(val.images[c], val.speed[c])
        out.append(seer.last["affordances"])
    return np.concatenate(out)


pred = head_affordances(perceiver)  # the refit head: what the course reads
pred_joint = head_affordances(model)  # the head as the kept epoch left it
true = val.affordances[rows].astype(np.float64)
mae = {n: float(np.mean(np.abs(pred[:, j] - true[:, j]))) for j, n in enumerate(AFFORDANCE_NAMES)}
gap_ahead = true[:, AFFORDANCE_NAMES.index("gap_ego_m")] < GAP_CAP_M
changing = val.expert_state[rows] == CHANGE
curved = np.abs(val.curvature[rows]) > 1e-4
situation = {  # each frame in the first that applies
    "parked car ahead": gap_ahead,
    "lane change": changing & ~gap_ahead,
    "curve": curved & ~changing & ~gap_ahead,
    "other": ~(curved | changing | gap_ahead),
}
fig = Figure(figsize=(12, 10.5), layout="constrained")
axes = fig.subplots(3, 3).ravel()
for j, (ax, name) in enumerate(zip(axes, AFFORDANCE_NAMES)):
    lo, hi = np.percentile(true[:, j], [0.5, 99.5])
    for (what, mask), colour in zip(situation.items(), ("C3", "C1", "C2", "0.6")):
        ax.scatter(true[mask, j], pred[mask, j], s=3, alpha=0.35, color=colour, label=what)
    ax.plot([lo, hi], [lo, hi], color="black", lw=1)
    ax.set_title(f"{name}: MAE {mae[name]:.3g}", fontsize=10)
    unit = "rad" if name.endswith("_rad") else "m"  # the names carry their units
    ax.set_xlabel(f"true [{unit}]")
    ax.set_ylabel(f"predicted [{unit}]")
fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=4, markerscale=4)
scatter_png = save_figure(fig, artifacts.artifact_path("figures", "08_affordance_scatter.png"))
# the floor to beat: always answering the training set's mean
errors = affordance_errors(pred, true, a_mean)
mae_const = {n: errors[n]["mean_predictor"]["mae"] for n in AFFORDANCE_NAMES}
print(f"  {'affordance':22s} {'MAE':>8s} {'mean pred.':>10s} {'RMSE':>8s} {'mean pred.':>10s}")
for name, e in errors.items():
    m, c = e["model"], e["mean_predictor"]
    print(f"  {name:22s} {m['mae']:8.3f} {c['mae']:10.3f} {m['rmse']:8.3f} {c['rmse']:10.3f}")
learned = [n for n in AFFORDANCE_NAMES if mae[n] < 0.8 * mae_const[n]]
print(f"clearly better than the mean (MAE < 80 % of it): {', '.join(learned) or 'none'}")
goals = goal_ratios(errors)
errors_joint = affordance_errors(pred_joint, true, a_mean)
goals_joint = goal_ratios(errors_joint)
for what, ratio in goals.items():
    print(f"{what}: {ratio:.2f} of the mean predictor's ({'met' if ratio <= 0.5 else 'not met'}: "
          f"the goal is at most half); the joint head of the kept epoch {goals_joint[what]:.2f}")  # fmt: skip
print(f"saved {scatter_png}")

# %% [markdown]
# ### Where the offset's error sits
#
# The lane-centre offset is measured from the *nearest* lane's centre, so it jumps by a lane
# width when the rear axle crosses a marking: at the crossing, +1.85 m and -1.85 m are the same
# place (the scatter's two off-diagonal clouds). Near the jump the least-squares answer is the
# middle, 0, and every lane change passes through it. We split the squared error by situation
# and also read it *wrapped* to a lane width (an error of 3.5 m counts as 0.2 m), which forgives
# exactly that ambiguity and nothing else.

# %%
j_off = OFFSET
lane_w = world_cfg.road.lane_width_m


def wrapped(err: np.ndarray) -> np.ndarray:
    """An offset error [m] read modulo one lane width, into [-w/2, w/2)."""
    return (err + lane_w / 2) % lane_w - lane_w / 2


off_err = pred[:, j_off] - true[:, j_off]
off_mean_err = a_mean[j_off] - true[:, j_off]
near_marking = np.abs(true[:, j_off]) >= lane_w / 3
offset_split = {}
for what, mask in (
    ("all frames", np.ones(len(true), bool)),
    ("lane change", changing),
    ("keeping the lane", ~changing),
    ("within a third of a lane width of a marking", near_marking),
):
    if not mask.any():  # the quick profile's few frames may hold no lane change
        continue
    offset_split[what] = {
        "frames": int(mask.sum()),
        "share_of_squared_error": float(np.sum(off_err[mask] ** 2) / np.sum(off_err**2)),
        "rmse_ratio": float(
            np.sqrt(np.mean(off_err[mask] ** 2) / np.mean(off_mean_err[mask] ** 2))
        ),
    }
offset_split["wrapped to a lane width"] = {
    "frames": len(true),
    "rmse_ratio": float(
        np.sqrt(np.mean(wrapped(off_err) ** 2) / np.mean(wrapped(off_mean_err) ** 2))
    ),
}
print("lane-centre offset, RMSE as a share of the mean predictor's (the goal: at most 0.5):")
for what, e in offset_split.items():
    share = e.get("share_of_squared_error")
    share_txt = f", {share:.0%} of the squared error" if share is not None else ""
    print(f"  {what:46s} {e['rmse_ratio']:.2f}  ({e['frames']} frames{share_txt})")

# %% [markdown]
# ### Where is the information? Probes, and where the head should read
#
# A head no better than the mean can mean two things: the network's features do not hold the
# affordance, or they hold it and the head does not get it out. A **probe** separates the two: a
# small network (one hidden layer) trained on the *frozen* features of a trained model, asked on
# the same held-out frames. We probe two layers: the trunk's 1,152 image features and the fusion
# MLP's 256 outputs. And we do it for two networks trained alike except for where their head
# reads: on the fused features (the paper's Fig. 1; chapter 10's control `gmm_affordance_fused`)
# and on the trunk (the course). A probe that beats its network's head says the information is
# there and the head does not get it out; the layer where a probe does best says where to read.

# %%
paper_model, paper_objective, _ = recipes.gmm_affordance(
    profile, train, val, w_best, name="08_gmm_affordance_fused", affordance_from="fused"
)


def head_goals(predicted: np.ndarray) -> dict[str, float]:
    """Each goal affordance's error on the validation frames as a share of the mean predictor's."""
    return goal_ratios(affordance_errors(predicted, true, a_mean))


probe_train = DrivingDataset(train, np.arange(0, len(train), 2))  # half the training frames
probe_val = DrivingDataset(val, rows)  # the scatter's frames
probe_goals = {}
for placement, net in (("fused (paper)", paper_model), ("trunk (course)", model)):
    probe_goals[f"head on {placement}: the head"] = head_goals(head_affordances(net))
    if net is model:
        probe_goals[f"head on {placement}: the head, refit"] = goals
    for layer in PROBE_LAYERS:
        predicted_by_probe = probe_affordances(net, probe_train, probe_val, layer)
        probe_goals[f"head on {placement}: probe on {layer}"] = head_goals(predicted_by_probe)
print("error as a share of the mean predictor's (the goal: at most 0.5):")
print(f"  {'':44s}" + "".join(f"{what:>26s}" for what in goals))
for who, ratios in probe_goals.items():
    print(f"  {who:44s}" + "".join(f"{ratios.get(what, np.nan):26.2f}" for what in goals))

# %% [markdown]
# ## 5. Along a drive
#
# The same model driving closed loop; at every decision we record, for the first car, what it
# predicted and what was true (the world computes the true affordances from the car's pose). A
# car ahead shows as the gap falling from 60 m, then the lane change, then the gap jumping back.


# %%
def car0_affordances(obs, agent):
    """(time, predicted, true affordances) of the first car."""
    truth = affordances(obs.worlds[:1], obs.s[:1], obs.d[:1], obs.heading_error[:1])[0]
    return obs.time_s, agent.last["affordances"][0], truth


recorder = Recorder(TrajectoryAgent(perceiver), car0_affordances)  # drives as `model` does
evaluate(
    recorder,
    world_cfg,
    EvalConfig(miles=0.2 if profile.quick else 3.0, n_worlds=2),
    desc="recording a drive",
)
t = np.array([r[0] for r in recorder.rows])
p_aff = np.array([r[1] for r in recorder.rows])
t_aff = np.array([r[2] for r in recorder.rows])
# show the 60 s window with the most happening ahead (smallest mean true gap)
win = int(60.0 / 0.1)
if len(t) > win:
    gaps = np.convolve(t_aff[:, GAP], np.ones(win) / win, mode="valid")
    start = int(np.argmin(gaps))
else:
    start = 0
sl = slice(start, start + win)
fig = Figure(figsize=(11, 6))
ax1, ax2 = fig.subplots(2, 1, sharex=True)
ax1.plot(t[sl], t_aff[sl, GAP], color="black", label="true gap ahead (ego lane)")
ax1.plot(t[sl], p_aff[sl, GAP], color="tab:red", label="predicted")
ax1.set_ylabel("gap [m]")
ax1.legend(loc="lower left", fontsize=8)
ax2.plot(t[sl], t_aff[sl, OFFSET], color="black", label="true offset from lane centre")
ax2.plot(t[sl], p_aff[sl, OFFSET], color="tab:red", label="predicted")
ax2.set_ylabel("[m]")
ax2.set_xlabel("simulated time [s]")
ax2.legend(loc="lower left", fontsize=8)
fig.tight_layout()
drive_png = save_figure(fig, artifacts.artifact_path("figures", "08_affordance_drive.png"))
drive_mae = float(np.mean(np.abs(p_aff[:, GAP] - t_aff[:, GAP])))
print(
    f"closed loop, car 0: gap-ahead MAE {drive_mae:.2f} m over {len(t)} decisions; saved {drive_png}"
)

# %% [markdown]
# ## 6. Closed loop
#
# Same validation tracks and seeds as chapters 05-07; the speed comes from the trajectory, as in
# chapter 07's headline.

# %%
ev = EvalConfig(miles=profile.eval_miles, n_worlds=profile.n_worlds)
res = evaluate(TrajectoryAgent(model), world_cfg, ev, desc="GMM + affordance")
print(res.summary())
rows_table = []
for chapter, label in (
    ("06_trajectory_regression", "trajectory L2 + LQR"),
    ("07_gmm", "trajectory GMM + LQR"),
):
    m = artifacts.read_metrics(chapter, profile.name)
    if m is not None:
        rows_table.append((label, m["result"]))
rows_table.append((f"GMM + affordance (w = {w_best:g}) + LQR", res))
table = results_table(rows_table)
print(table + profile.caveat)
gmm_row = dict(rows_table).get("trajectory GMM + LQR")
verdict = (
    "GMM + affordance vs GMM: " + compare_rates(res, gmm_row)["verdict"]
    if gmm_row is not None
    else "run chapter 07 first to compare with the GMM alone"
)
print(verdict)
chart = collision_chart(
    rows_table,
    title=f"{miles_text(round(res.miles, 1))} each, same validation tracks and seeds",
)
chart_png = save_figure(chart, artifacts.artifact_path("figures", "08_collisions.png"))

# %% [markdown]
# ## 7. A heavier w: what the head gains, what the driving pays
#
# The head refit on the kept trunk beats the mean predictor, but a goal of half the mean
# predictor's error on the lane-centre offset asks more of it (the goals line of section 4), and
# a probe on the same trunk does no better (section 4's table): the trunk does not hold the
# offset more sharply. A trunk trained with more weight on the affordances might. The same
# recipe again with `w = 30` (the trajectory loss still there, the affordances ten times the
# grid's largest weight), the head refit as above, driven on the same tracks: does the head reach
# the goals, and what does the driving pay for it?

# %%
HEAVY_W = 30.0
heavy_name = f"08_gmm_affordance_w{HEAVY_W:g}"
heavy, _, heavy_hist = recipes.gmm_affordance(profile, train, val, HEAVY_W, name=heavy_name)
heavy_goals = head_goals(head_affordances(recipes.perceiving(heavy, train, heavy_name)))
heavy_res = evaluate(TrajectoryAgent(heavy), world_cfg, ev, desc=f"w = {HEAVY_W:g}")
print("| w | kept epoch | " + " | ".join(heavy_goals) + " | collisions per 100 mi | mph |")
print("|---:|---:|" + "---:|" * (len(heavy_goals) + 2))
for w, kept, g, r in ((w_best, hist.best_epoch, goals, res),
                      (HEAVY_W, heavy_hist.best_epoch, heavy_goals, heavy_res)):  # fmt: skip
    print(f"| {w:g} | {kept + 1} | " + " | ".join(f"{g[k]:.2f}" for k in heavy_goals)
          + f" | {r.collisions_per_100mi:.1f} | {r.mean_speed_mph:.1f} |")  # fmt: skip
print("(each goal: the refit head's error over the mean predictor's; at most 0.5 is the goal)")
heavy_verdict = f"w = {HEAVY_W:g} vs w = {w_best:g}: " + compare_rates(heavy_res, res)["verdict"]
print(heavy_verdict)

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "08_affordance",
    {
        "profile": profile.name,
        "headline": {
            "GMM + affordance collisions/100mi": res.collisions_per_100mi,
            "chosen w": w_best,
            "val gap-ahead MAE [m]": mae["gap_ego_m"],
        },
        "grid": {f"{w:g}": v for w, v in scores.items()},
        "chosen_weight": w_best,
        "chosen_because": why,
        "result": res.to_dict(),
        "held_out": held,
        "affordance_mae": mae,
        "affordance_mae_constant": mae_const,
        "affordance_error": errors,
        "affordance_goals": goals,
        "affordance_error_joint_head": errors_joint,
        "affordance_goals_joint_head": goals_joint,
        "head_refit": recipes.HEAD_REFIT,
        "offset_error_split": offset_split,
        "affordance_probes": probe_goals,
        "head_by_epoch": head_by_epoch,
        "kept_epoch": hist.best_epoch,
        "affordances_learned": learned,
        "drive_gap_mae_m": drive_mae,
        "verdict_vs_gmm": verdict,
        "heavy_w": {
            "w": HEAVY_W,
            "kept_epoch": heavy_hist.best_epoch,
            "affordance_goals": heavy_goals,
            "result": heavy_res.to_dict(),
            "verdict": heavy_verdict,
        },
        "table_md": table,
    },
    figures=(scatter_png, drive_png, chart_png),
)

# %% [markdown]
# ## Summary
#
# * An affordance head adds 9 dense labels per frame; the total loss is the GMM NLL plus `w`
#   times their normalised squared error, with `w` chosen on held-out trajectory NLL.
# * Where the head reads matters, and a probe on frozen features measures it: the table of
#   section 4 compares the paper's placement (the fused features) with the course's (the trunk).
# * The predicted affordances make the network's perception readable: the scatter and the drive
#   show what it sees of the lane and the car ahead, and where it is wrong. Judge them against
#   the floor printed beside them (always answering the mean): a head can train without learning.
# * A network kept for how it drives carries the head of that epoch. When an early epoch drives
#   best, the head has barely trained (the per-epoch table); training the head alone on the kept
#   trunk afterwards (`recipes.perceiving`) finishes it without moving a weight that drives.
# * An error can also sit in the label: the lane-centre offset jumps by a lane width at every
#   marking the car crosses, so a lane change's frames weigh in its RMSE far beyond their number
#   (the split after the scatter).
# * A head perceives only what its trunk encodes. Weighting the affordances heavily (section 7)
#   trains a trunk that encodes them better, and that trunk is trained less for the trajectory:
#   the auxiliary loss is a trade, read both sides of it (the goals and the collisions).
# * Whether the auxiliary task lowers collisions here is the verdict line above, measured on the
#   same tracks and seeds as chapter 07; the paper reports 12.7 -> 0.83 per 100 miles. The verdict
#   compares two *training runs*, one per setting: it is only evidence for the auxiliary loss if
#   two runs of the same setting agree far better than that (exercise 4 measures it).
#
# ## Exercises
#
# 1. Train with `w = 10` (between the grid and section 7's 30). What happens to the trajectory
#    NLL, to the affordance errors, and to the collisions?
# 2. Drop the three gap affordances (train on the six lane geometry ones only). Which part of the
#    closed-loop result moves?
# 3. Use the predicted gap ahead as a brake: if it is below 20 m, set the followed trajectory's
#    speed to zero. This is the seed of chapter 11's safety module.
# 4. Train the same network with `w = 0` (head present, unused) and, separately, chapter 07's GMM
#    with `TrainConfig.seed=1`. How far apart are two training runs of one recipe in closed loop?
#    Compare with the difference you would attribute to the affordance loss.
# 5. The grid search trains on a quarter of the data for two epochs. Is its winner the winner at
#    full length? Train two values of `w` at full length and compare.
# 6. Probe the trunk of chapter 07's GMM (no affordance head, no auxiliary loss):
#    `probe_affordances(gmm07, probe_train, probe_val, "trunk")`. How much of the affordances does
#    a trajectory network learn to see without being asked?
