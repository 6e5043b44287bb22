# %% [markdown]
# # 08 · Perception as an auxiliary task (affordances)
#
# The paper's auxiliary loss (seed 000, section 3.5): besides the trajectory, ask the network to say
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
# features instead (`recipes.AFFORDANCE_FROM`): probes on the frozen features of both placements
# read the gap ahead better from the trunk (lab note "Where the affordance head reads"; exercise
# 6).
#
# Run it with `python chapters/08_affordance.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(8)  # flags, profile, outputs folder: checked before any work

import numpy as np
import torch
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.driving.evaluation import EvalConfig, EvalResult, evaluate, miles_text, results_table
from e2e_lite.driving.figures import collision_chart, save_figure
from e2e_lite.imitation import recipes
from e2e_lite.imitation.agents import Recorder, TrajectoryAgent
from e2e_lite.imitation.collector import (
    AFFORDANCE_NAMES,
    GAP_CAP_M,
    DataConfig,
    DrivingDataset,
    affordances,
    load_or_collect,
)
from e2e_lite.learning.heldout import affordance_errors, goal_ratios
from e2e_lite.learning.labels import AFFORDANCE_INDEX, CHANGE
from e2e_lite.learning.training import evaluate_loss
from e2e_lite.record import words
from e2e_lite.simulation.world import WorldConfig
from e2e_lite.stats.rates import compare_rates

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
# set for a short schedule (every sigma held at 1, as in chapter 07); the score is the
# trajectory NLL alone on the validation samples. `w = 0` is the chapter-07 model with an unused
# head: the reference. If it wins, this short grid shows no help to the trajectory, and the head
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
# Same schedule as chapter 07 (every sigma held at 1), so the two recipes differ only by the
# auxiliary head and its loss; each network keeps its own epoch by its drive.

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
# ### The loss, line by line
#
# The library's `WithAffordance` adds the head's error to the mixture's NLL, sample by sample;
# here is the same sum on a validation batch, written out and checked against it.

# %%
val_set = DrivingDataset(val)
batch = val_set.batch(val_set.indices[:64])
with torch.inference_mode():
    out = model(batch["image"], batch["speed"])
    nll = objective.base.per_sample(out, batch, model)  # L_GMM, (B,)
    a_norm = (batch["affordances"] - model.affordance_mean) / model.affordance_std  # (B, 9)
    aux = ((out["affordance"] - a_norm) ** 2).mean(dim=1)  # (1/9) sum_j (a_hat_j - a_j)^2
    total = nll + objective.weight * aux  # L = L_GMM + w * aux
    assert torch.allclose(total, objective.per_sample(out, batch, model))
print(f"w = {objective.weight:g}: mean NLL {nll.mean():.3f} + w x mean auxiliary {aux.mean():.3f}")

# %% [markdown]
# ### The head, trained to the end on the kept trunk
#
# The network is kept by its drive on validation roads (ties: the decisive ADE), not for its
# head. So the head alone is trained on, on the frozen trunk it reads, with the same loss
# (`recipes.perceiving`): the network drives exactly as the kept one, and everything below that
# reads its affordances (and chapter 11) reads this head, the joint head's errors beside it.

# %%
perceiver = recipes.perceiving(model, train, "08_gmm_affordance")

# %% [markdown]
# ## 4. What the network sees: predicted against true affordances
#
# On the validation frames, coloured by situation (a parked car within 60 m in the own lane, a
# lane change, a curve, the rest). Points on the diagonal are right; the gaps saturate at 60 m
# (no car in range), which shows as a column at the right edge. The floor to beat is the mean
# predictor (always answering the training set's mean); a head is worth reading, for the course,
# when its error on the gap ahead, the lane-centre offset and the heading is at most half the
# mean predictor's (`heldout.goal_ratios`).

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
# %%
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
    met = "met" if ratio <= 0.5 else "not met"
    joint = f"the joint head of the kept epoch {goals_joint[what]:.2f}"
    print(f"{what}: {ratio:.2f} of the mean predictor's ({met}: the goal is at most half); {joint}")
better = sum(goals[w] < goals_joint[w] for w in goals)
print(
    f"the refit head (the one read from here on) beats the joint head on {better} of {len(goals)}"
)
print(f"saved {scatter_png}")

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
# Same test tracks and seeds as chapters 05-07; the speed comes from the trajectory, as in
# chapter 07.

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
        rows_table.append((label, EvalResult.from_dict(m["result"])))
rows_table.append((f"GMM + affordance (w = {w_best:g}) + LQR", res))
table = results_table(rows_table)
print(table + profile.caveat)
gmm_row = dict(rows_table).get("trajectory GMM + LQR")
verdict = (
    "GMM + affordance vs GMM: " + words.rates(compare_rates(res, gmm_row))
    if gmm_row is not None
    else "run chapter 07 first to compare with the GMM alone"
)
print(verdict)
chart = collision_chart(
    rows_table,
    title=f"{miles_text(round(res.miles, 1))} each, same test tracks and seeds",
)
chart_png = save_figure(chart, artifacts.artifact_path("figures", "08_collisions.png"))

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
        "kept_epoch": hist.best_epoch,
        "affordances_learned": learned,
        "drive_gap_mae_m": drive_mae,
        "verdict_vs_gmm": verdict,
        "table_md": table,
    },
    figures=(scatter_png, drive_png, chart_png),
)

# %% [markdown]
# ## Summary
#
# * An affordance head adds 9 dense labels per frame; the total loss is the GMM NLL plus `w`
#   times their normalised squared error, with `w` chosen on held-out trajectory NLL (when
#   w = 0 wins, on the head's held-out error instead: section 2).
# * The predicted affordances make the network's perception readable: the scatter and the drive
#   show what it sees of the lane and the car ahead, and where it is wrong. Judge them against
#   the floor printed beside them (always answering the mean): a head can train without learning.
# * A network kept for how it drives carries the head of that epoch; training the head alone on
#   the kept trunk afterwards (`recipes.perceiving`) moves no weight that drives. Whether it beats
#   the joint head is printed in section 4 (lab note "The affordance head refit on the kept
#   trunk": once it did, once not; when it does not, which head to read is *open*).
# * Whether the auxiliary task lowers collisions here is the verdict line above, on the same roads
#   as chapter 07 (the paper reports its step from 12.7 to 0.83 per 100 miles). It compares two
#   *training runs*, one per setting. **The test of the loss is the w = 0 control** (the same
#   network and head, the loss weight 0), seed by seed: the record's verdict table prints it
#   (`docs/results.md`, for its recipes), and until + affordance beats w = 0 there, a step from the
#   GMM is not shown to be the loss's (exercise 4; chapter 10's exercise 7 drives it with your
#   seeds).
#
# ## Exercises
#
# 1. Train with `w = 30` (`recipes.gmm_affordance(profile, train, val, 30.0,
#    name="08_gmm_affordance_w30")`), refit its head and drive it. Is its error at most half the
#    mean predictor's on the gap, the offset and the heading (section 4's bar), and what does
#    the driving pay (lab note "A heavier affordance weight")?
# 2. Drop the three gap affordances (train on the six lane geometry ones only). Which part of the
#    closed-loop result moves?
# 3. Use the predicted gap ahead as a brake: if it is below 20 m, set the followed trajectory's
#    speed to zero. This is the seed of chapter 11's safety module.
# 4. Train the same network with `w = 0` (head present, unused) and, separately, chapter 07's GMM
#    with `TrainConfig.seed=1`. How far apart are two training runs of one recipe in closed loop?
#    Compare with the difference you would attribute to the affordance loss.
# 5. The lane-centre offset jumps by a lane width when the car crosses a marking. Split the
#    offset's squared error into lane changes and lane keeping, and read it wrapped to a lane
#    width: how much of the head's error is the label's ambiguity?
# 6. Probe where the affordances are: `probes.probe_affordances(net, train_set, val_set, layer)`
#    on the trunk and on the fused features, for this network and for one trained with
#    `affordance_from="fused"` (the paper's placement). Which layer holds the affordances, and
#    does the head get them out?
