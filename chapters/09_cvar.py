# %% [markdown]
# # 09 · Training on the worst cases (CVaR)
#
# An average loss is dominated by the easy frames: most of a highway is a straight lane with
# nothing ahead. The frames that decide collisions (a parked car close ahead, an overtake on a
# curve) are few, and a model can be very good on average while bad exactly there. The paper's
# answer (seed 000, section 3.4, "focusing on rare events") borrows a tool from finance.
#
# A bank does not ask "what do I lose on an average day?" but "how bad are my worst days?". The
# **value at risk** `VaR_α` is the α-quantile of the loss (at α = 0.9, the loss exceeded on 10 %
# of days); the **conditional value at risk** is the mean loss on those days:
#
# $$\mathrm{CVaR}_\alpha(L) = \mathbb{E}\,[\,L \mid L \ge \nu_\alpha\,], \qquad
#   \nu_\alpha = \text{the } \alpha\text{-quantile of } L .$$
#
# Trained on, it means: in every batch, back-propagate only through the samples whose loss is
# above the batch's α-quantile (the paper's eq. 3). `α = 0` is the ordinary mean. The paper
# fine-tuned its GMM + affordance model for **one epoch with CVaR-90** and reports 0.83 -> 0
# collisions per 100 miles. The batch must grow with α: at α = 0.9 a batch of 64 leaves 6.4
# samples in the tail, so the fine-tune uses batches of 256.
#
# Run it with `python chapters/09_cvar.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(9)  # flags, profile, outputs folder: checked before any work


import numpy as np
import torch
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.driving.evaluation import EvalConfig, miles_text, results_table
from e2e_lite.driving.figures import collision_chart, save_figure
from e2e_lite.imitation import recipes
from e2e_lite.imitation.collector import (
    AFFORDANCE_NAMES,
    GAP_CAP_M,
    DataConfig,
    DrivingDataset,
    load_or_collect,
    situation_shares,
)
from e2e_lite.learning.cvar import cvar, cvar_curve, cvar_loss, cvar_ru
from e2e_lite.learning.training import evaluate_loss
from e2e_lite.record import ablation, words
from e2e_lite.simulation.raster import save_image
from e2e_lite.simulation.world import WorldConfig
from e2e_lite.stats.rates import compare_rates
from e2e_lite.stats.seeds import compare_seeds

world_cfg = WorldConfig.for_profile(profile)

# %% [markdown]
# ## 1. CVaR by hand
#
# Sort the losses, keep the worst `(1 - α) n`, average them. When `(1 - α) n` is not a whole
# number (a small batch) or several losses tie at the quantile, the boundary sample counts with a
# fractional weight; that keeps `CVaR_0` = mean, CVaR non-decreasing in α, and tends to the
# maximum as α -> 1.


# %%
def cvar_by_hand(losses: np.ndarray, alpha: float) -> float:
    """Mean of the worst (1 - alpha) share, the boundary sample weighted by the fraction left."""
    worst_first = np.sort(losses)[::-1]
    k = (1 - alpha) * len(losses)
    whole = int(np.floor(k + 1e-9))
    total = worst_first[:whole].sum() + (k - whole) * (
        worst_first[whole] if whole < len(losses) else 0
    )
    return float(total / k)


x = np.random.default_rng(0).exponential(size=37)
for alpha in (0.0, 0.5, 0.9, 0.99):
    print(f"alpha {alpha:.2f}: by hand {cvar_by_hand(x, alpha):.6f}, library {cvar(x, alpha):.6f}")
    assert abs(cvar_by_hand(x, alpha) - cvar(x, alpha)) < 1e-9
# the training loss: gradients reach the tail only
t = torch.tensor(x, requires_grad=True)
cvar_loss(t, 0.9, min_tail=1).backward()
grad = t.grad.numpy()
g = np.sort(grad[grad > 0])[::-1] * (1 - 0.9) * 37  # each tail sample's weight (1: a whole one)
print(f"CVaR-90 of 37 losses: {len(g)} get a gradient, weights {np.round(g, 2).tolist()}")

# %% [markdown]
# Rockafellar and Uryasev wrote the same number without a sort, as a minimum over a threshold
# `ν`:
#
# $$\mathrm{CVaR}_\alpha(L) = \min_\nu \; \nu + \frac{\mathbb{E}\,[(L - \nu)_+]}{1 - \alpha},$$
#
# attained at the α-quantile. With `ν` a parameter learned across batches, a sample gets a
# gradient whenever its loss is above `ν`, not only when it is in its own batch's tail
# (`e2e_lite.learning.cvar.cvar_ru`; exercise 6 below). Check it on the same 37 losses:

# %%
grid = torch.linspace(float(x.min()), float(x.max()), 2001, dtype=torch.float64)
ru = torch.stack([cvar_ru(torch.tensor(x), nu, 0.9) for nu in grid])
print(
    f"min over nu of the RU form: {float(ru.min()):.6f} at nu = {float(grid[ru.argmin()]):.3f}; "
    f"sorted-tail CVaR-90: {cvar(x, 0.9):.6f}; the 90 % quantile (boundary sample): "
    f"{np.sort(x)[::-1][int((1 - 0.9) * len(x))]:.3f}"
)

# %% [markdown]
# ## 2. The starting point and its tail
#
# The chapter-08 model (GMM + affordance; trained here if missing, with the `w` its grid chose).
# For every validation sample the loss the fine-tunes train, then `CVaR_α` of those losses for α
# from 0 to 99 % (the paper's Fig. 5). That loss is the trajectory NLL with **every sigma held at
# 1**, plus `w` x the affordance error. With unit sigmas a mode's NLL is half its squared error
# (in target units) plus a constant, so a sample's loss says how far its best modes are from the
# expert's trajectory. Section 6 explains what could go wrong if the fine-tune trained the learned
# sigmas instead, as the paper's NLL does (exercise 2 drives it).

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
m08 = artifacts.read_metrics("08_affordance", profile.name)
if m08 is not None:
    w = float(m08["chosen_weight"])
    print(f"affordance weight from chapter 08: w = {w:g}")
else:
    w, why = recipes.choose_affordance_weight(recipes.affordance_grid(profile, train, val))
    print(f"chapter 08 has not run: grid search here, chosen {why}")
base, _, _ = recipes.gmm_affordance(profile, train, val, w)
# the fine-tunes' own per-sample loss (their single epoch is epoch 0: sigma held at 1)
tuned_objective, _ = recipes.finetune_settings(profile, w, reduction="mean")
base_losses, _ = evaluate_loss(base, tuned_objective, DrivingDataset(val), epoch=0)
alphas, base_curve = cvar_curve(base_losses)
print(
    f"chapter-08 model, held-out loss: mean {base_curve[0]:.3f}, CVaR-90 {base_curve[90]:.3f}, "
    f"CVaR-99 {base_curve[99]:.3f}"
)

# %% [markdown]
# ## 3. What the tail is made of (the paper's Fig. 4)
#
# Replay the fine-tune's batching on training samples with the chapter-08 model: in each random
# batch of 256, which samples are above the batch's 90 % quantile? Those are the samples the
# fine-tune's first steps train on. Compare their situations with random samples.
#
# *What* is ranked is a choice. The paper ranks by the loss trained on; with sigma held at 1 that
# is the modes' squared error, softly minimised over the modes and weighted by their mixing
# weights (plus the affordance term). The alternative (`CVaRObjective(rank_by="followed_error")`)
# ranks by the error of the one trajectory the car would follow. The table shows both tails.

# %%
rng = np.random.default_rng(9)
batch = recipes.CVAR_BATCH
probe_rows = rng.permutation(len(train))[: min(len(train), batch * (8 if profile.quick else 24))]
probe_losses, probe_metrics = evaluate_loss(
    base, tuned_objective, DrivingDataset(train, probe_rows), epoch=0
)


def batch_tails(score: np.ndarray) -> np.ndarray:
    """Which probe samples are above their batch's 90 % quantile of ``score``."""
    tail = np.zeros(len(score), bool)
    for start in range(0, len(score) - batch + 1, batch):
        chunk = slice(start, start + batch)
        tail[chunk] = score[chunk] >= np.quantile(score[chunk], recipes.CVAR_ALPHA)
    return tail


# %%
in_tail = batch_tails(probe_losses)
in_error_tail = batch_tails(probe_metrics["ADE [m]"])
tail_rows, error_rows, random_rows = probe_rows[in_tail], probe_rows[in_error_tail], probe_rows
gap_ego = train.affordances[:, AFFORDANCE_NAMES.index("gap_ego_m")]
shares = {
    name: {
        **situation_shares(train.arrays, rows),
        "car_within_60m": float(np.mean(gap_ego[rows] < GAP_CAP_M)),
    }
    for name, rows in (("tail", tail_rows), ("error_tail", error_rows), ("random", random_rows))
}
shares_tail, shares_all = shares["tail"], shares["random"]
print(f"{len(tail_rows)} tail samples out of {len(probe_rows)}:")
print(f"  {'situation':28s} {'by loss':>8s} {'by error':>9s} {'random':>7s}")
for key in shares_all:
    tail, error_tail, anywhere = (shares[k][key] for k in ("tail", "error_tail", "random"))
    if tail == error_tail == anywhere == 0:  # (returns and passing: the expert does neither)
        continue
    print(f"  {key:28s} {tail:8.1%} {error_tail:9.1%} {anywhere:7.1%}")
both_tails = float(np.mean(in_error_tail[in_tail]))
ade = probe_metrics["ADE [m]"]
shared = f"the loss's tail and the followed error's tail share {both_tails:.0%} of their samples"
in_tails = f"in the loss's tail {ade[in_tail].mean():.2f} m, in the error's"
print(
    f"{shared}; followed ADE {in_tails} {ade[in_error_tail].mean():.2f} m, overall {ade.mean():.2f} m"
)
pick_tail = tail_rows[np.argsort(probe_losses[in_tail])[::-1][:8]]
pick_random = rng.choice(random_rows, size=min(8, len(random_rows)), replace=False)
grid_img = np.concatenate(
    [
        np.concatenate([train.images[i] for i in pick_tail], axis=1),
        np.full((6, 200 * len(pick_tail), 3), 255, np.uint8),
        np.concatenate([train.images[i] for i in pick_random], axis=1),
    ],
    axis=0,
)
grid_png = save_image(artifacts.artifact_path("figures", "09_tail_vs_random.png"), grid_img)
print(f"saved {grid_png} (top row: the 8 worst samples; bottom row: 8 random ones)")

# %% [markdown]
# ## 4. One epoch of CVaR-90
#
# From the chapter-08 weights, one epoch over the training set, batches of 256, each batch
# reduced by `cvar_loss` at α = 0.9 (so each step learns from its 25-26 worst samples). Every
# sigma is held at 1 (`recipes.CVAR_SIGMA`; section 6 says why). The fine-tune **continues the
# chapter-08 training's Adam state** (its moment
# estimates, `train_or_load(..., carry_optimizer=True)`) at a tenth of its learning rate: a fresh
# Adam's bias-corrected first step is the learning rate times the gradient's *sign*, for every
# weight whatever its gradient's size: a restart, not a fine-tune.
#
# Any fine-tune changes a model, so CVaR is judged against a **control**: the identical
# fine-tune (parent, epoch, batches, rate, optimiser state) reducing each batch by its mean
# (`recipes.finetune_settings` builds both; they differ in the reduction only).

# %%
model, objective, hist = recipes.gmm_affordance_cvar(profile, train, val, w)
control, control_objective, _ = recipes.gmm_affordance_cvar(
    profile, train, val, w, reduction="mean"
)
cvar_losses, cvar_metrics = evaluate_loss(model, objective, DrivingDataset(val), epoch=0)
control_losses, _ = evaluate_loss(control, control_objective, DrivingDataset(val), epoch=0)
_, tuned_curve = cvar_curve(cvar_losses)
_, control_curve = cvar_curve(control_losses)


def change(before: float, after: float) -> str:
    """``before -> after`` with the direction and the relative change spelled out."""
    word = "lower" if after < before else "higher" if after > before else "equal"
    return f"{before:.3f} -> {after:.3f} ({word}, {100 * (after - before) / abs(before):+.2f} %)"


for label, curve in (("CVaR-90", tuned_curve), ("control (mean)", control_curve)):
    print(f"held-out loss before -> after the {label} fine-tune:")
    for name, k in (("mean", 0), ("CVaR-90", 90), ("CVaR-99", 99)):
        print(f"  {name}: {change(base_curve[k], curve[k])}")
# %%
fig = Figure(figsize=(8, 4.5))
ax = fig.subplots()
ax.plot(100 * alphas, base_curve, label="chapter 08 (mean loss)", color="tab:blue")
ax.plot(100 * alphas, control_curve, label="+ 1 epoch, mean (control)", color="tab:gray", ls="--")
ax.plot(100 * alphas, tuned_curve, label="+ 1 epoch CVaR-90", color="tab:red")
ax.set_xlabel("alpha [%]")
ax.set_ylabel("CVaR_alpha of the held-out loss (sigma at 1)")
ax.set_title("the paper's Fig. 5 on held-out frames: base, control and CVaR")
ax.legend()
curve_png = save_figure(fig, artifacts.artifact_path("figures", "09_cvar_curve.png"))
lower, under = tuned_curve < base_curve, tuned_curve < control_curve


def spans(percent: np.ndarray) -> str:
    """Whole percentages as runs: [0, 1, 2, 7] -> "0-2, 7"."""
    runs, start = [], None
    for k, p in enumerate(percent):
        start = p if start is None else start
        if k + 1 == len(percent) or percent[k + 1] != p + 1:
            runs.append(f"{start}" if start == p else f"{start}-{p}")
            start = None
    return ", ".join(runs) or "none"


pct = np.round(100 * alphas).astype(int)
print(
    f"the fine-tune's CVaR is lower than the base's at {int(lower.sum())} of {len(alphas)} alphas "
    f"(alpha [%]: {spans(pct[lower])}) and not lower at alpha [%]: {spans(pct[~lower])}; "
    f"saved {curve_png}"
)
print(f"it is lower than its control's at {int(under.sum())}: alpha [%] {spans(pct[under])}")

# %% [markdown]
# ## 5. Closed loop: base, control and CVaR, over the training seeds
#
# The three drivers (the chapter-08 model, its control fine-tune, its CVaR fine-tune), each
# trained with chapter 10's seeds, on chapter 10's roads and miles: each seed drives its share of
# the miles on roads of its own, and the counts are pooled. Chapter 10 reuses these evaluations.

# %%
keys = ("gmm_affordance", "gmm_affordance_control", "gmm_affordance_cvar")
names = {
    "gmm_affordance": "base",
    "gmm_affordance_control": "control",
    "gmm_affordance_cvar": "cvar",
}
seeded = ablation.build_seeded_drivers(profile, keys, train=train, val=val)
ev = EvalConfig(miles=profile.ablation_miles, n_worlds=profile.ablation_worlds)
closed = ablation.evaluate_drivers(seeded, world_cfg, ev)
rows = [(ablation.BY_KEY[k].label, closed[k]) for k in keys]
table = results_table(
    rows, extra=[("per seed, per 100 mi", [ablation.per_seed(closed[k]) for k in keys])]
)
print(table + profile.caveat)
pairs = {  # (the fine-tune, what it is judged against)
    "cvar_vs_control": ("gmm_affordance_cvar", "gmm_affordance_control"),
    "cvar_vs_base": ("gmm_affordance_cvar", "gmm_affordance"),
    "control_vs_base": ("gmm_affordance_control", "gmm_affordance"),
}
# the verdict: seed by seed (the training seed is the unit); the pooled Poisson test, secondary
verdicts = {w: compare_seeds(closed[a], closed[b]) for w, (a, b) in pairs.items()}
pooled = {w: words.rates(compare_rates(closed[a], closed[b])) for w, (a, b) in pairs.items()}
for what, test in verdicts.items():
    print(f"{what.replace('_', ' ')}: {words.seeds(test)}; pooled: {pooled[what]}")

# %% [markdown]
# A rate per mile says nothing about how the miles were driven. Section 3 measured which
# situations the tail holds; where it holds lane changes and frames with a parked car close ahead,
# where the expert brakes or swerves, a network fine-tuned on them may learn to hold back. Does
# it? Read the speed and the
# **stalls** (a car stopped for too long is restarted by the evaluator, an
# intervention that is not a collision) beside each rate, seed by seed, and compare each
# fine-tune with its control before crediting the tail: whatever the control also gains is the
# extra epoch at a tenth of the rate, not CVaR.

# %%
for k in keys:
    r = closed[k]
    per_seed_mph = " / ".join(f"{s.mean_speed_mph:.1f}" for s in r.seeds or [r])
    per_seed_stalls = " / ".join(str(s.stalls) for s in r.seeds or [r])
    print(
        f"{names[k]:8s} {r.collisions_per_100mi:6.1f} per 100 mi ({r.car_collisions} car / "
        f"{r.rail_collisions} rail), {r.mean_speed_mph:.1f} mph (seeds {per_seed_mph}), "
        f"stalls {r.stalls} (seeds {per_seed_stalls}), autonomy {r.autonomy_pct:.1f} %"
    )

# %% [markdown]
# ## 6. Why the fine-tunes hold sigma at 1
#
# With the sigmas open (the paper's NLL), a sample's loss is large when its error is large
# *relative to its sigma*, and the cheapest way to lower the loss of the worst samples is to
# widen their sigmas. That also weakens the pull on the means (each mean is pulled with weight
# 1 / sigma², chapter 07). The course's base network never trained its sigmas (chapter 07 holds
# them at 1), so an open fine-tune would also spend its one epoch moving them away from an
# untrained layer. Either way the sigmas, not the reduction, could decide which fine-tune drives
# better; held at 1, as the base trained, the two differ in the reduction alone. Exercise 2 drives
# both with the sigmas open (lab note "CVaR with the sigmas held at 1").

# %%
res = closed["gmm_affordance_cvar"]
chart_png = save_figure(
    collision_chart(
        rows,
        title=f"{miles_text(round(res.miles, 1))} each, {profile.ablation_seeds} training seeds",
    ),
    artifacts.artifact_path("figures", "09_collisions.png"),
)

# %% [markdown]
# ## Headline figures

# %%
control_res = closed["gmm_affordance_control"]
headline = {
    "GMM + affordance + CVaR collisions/100mi": res.collisions_per_100mi,
    "control (mean fine-tune) collisions/100mi": control_res.collisions_per_100mi,
    "base collisions/100mi": closed["gmm_affordance"].collisions_per_100mi,
    "CVaR mph": res.mean_speed_mph,
    "control mph": control_res.mean_speed_mph,
    "CVaR stalls": res.stalls,
    "val CVaR-90 before": float(base_curve[90]),
    "val CVaR-90 after": float(tuned_curve[90]),
    "val CVaR-90 after the control": float(control_curve[90]),
}
print("\n".join(f"{name:45s} {value:10.3f}" for name, value in headline.items()))

# %%
artifacts.write_metrics(
    "09_cvar",
    {
        "profile": profile.name,
        "headline": headline,
        "affordance_weight": w,
        "curves": {
            "alpha": alphas.tolist(),
            "before": base_curve.tolist(),
            "after": tuned_curve.tolist(),
            "control": control_curve.tolist(),
        },
        "tail_shares": {
            **shares,
            "tail_samples": len(tail_rows),
            "probe_samples": len(probe_rows),
            "loss_tail_in_error_tail": both_tails,
            "rank_by": recipes.CVAR_RANK_BY,
        },
        "held_out": {k: float(v.mean()) for k, v in cvar_metrics.items()},
        "fine_tune": {
            "lr": recipes.CVAR_LR,
            "batch": recipes.CVAR_BATCH,
            "alpha": recipes.CVAR_ALPHA,
            "optimizer": "carried from the base training",
            "sigma": recipes.CVAR_SIGMA,
        },
        **{names[k]: closed[k].to_dict(with_events=False) for k in keys},
        "tests": {
            k: {**vars(v), "verdict": words.seeds(v), "pooled": pooled[k]}
            for k, v in verdicts.items()
        },
        "table_md": table,
    },
    figures=(grid_png, curve_png, chart_png),
)

# %% [markdown]
# ## Summary
#
# * `CVaR_α` is the mean of the worst `1 - α` of the losses; as a training loss it sends gradients
#   only to the samples above the batch's quantile, so the batch must hold enough of them.
# * The tail is not a random sample: section 3 shows which situations it over-represents, and
#   how many samples ranking by the loss and by the followed trajectory's error share.
# * A fine-tune continues its base's optimiser, and it is judged against its control: the same
#   fine-tune with the mean. Only the difference between the two is CVaR's.
# * One epoch of CVaR-90 moves the per-percentile curve: section 4 prints at which alphas it lies
#   below the base's and its control's, and the closed-loop verdicts (over the training seeds)
#   say whether that reaches the road.
# * A rate per mile is read with the speed and the stalls: a driver fine-tuned on a tail rich in
#   lane changes and close cars could buy fewer collisions per mile by driving slower or stalling
#   (section 5 prints both per seed).
# * With a GMM, the fine-tune's sigmas are a second change beside the reduction: held at 1, the
#   fine-tunes differ in the reduction alone.
#
# ## Exercises
#
# 1. Fine-tune with α = 0.5 and α = 0.99 (mind the batch size). Which part of the curve moves?
# 2. Rank the tail by the followed trajectory's error (`CVaRObjective(..., rank_by=
#    "followed_error")`, or `recipes.CVAR_RANK_BY`). Does section 3's table change the way you
#    expected, and does the closed loop follow?
#    Then fine-tune both with the sigmas open (`recipes.gmm_affordance_cvar(..., sigma="open")`,
#    the drivers `gmm_affordance_cvar_open` and `gmm_affordance_control_open` of
#    `ablation.DIAGNOSTICS`), seed by seed: does the sign of CVaR against its control change
#    when the sigmas may move?
# 3. Two epochs of CVaR-90: where does the mean loss go next? Does the closed-loop rate follow the
#    CVaR-90 or the mean?
# 4. Does CVaR cost the easy cases anything, and where? On straight validation frames where the
#    expert keeps its lane, compare the followed trajectory's lateral error at 1.5 s of base,
#    control and CVaR. Then measure section 3's tail with the validation loss.
# 5. Fine-tune with a fresh Adam instead (`carry_optimizer=False` in `recipes.gmm_affordance_cvar`'s
#    `train_or_load` call). How far do the weights move in the first ten steps, against the
#    carried optimiser?
# 6. A learned threshold: write a fine-tune whose batch loss is `cvar_ru(losses, nu, 0.9)` with
#    `nu` a parameter in the optimiser (start it at the base's 90 % quantile of the training
#    loss). Does `nu` settle? Do more samples get a gradient per step than with `cvar_loss`, and
#    does the closed loop differ from section 5's CVaR row?
