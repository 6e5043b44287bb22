# %% [markdown]
# # 07 · A mixture of trajectories (GMM)
#
# Chapter 06 ended with L2 regression aiming between two right answers. The paper's fix
# (seed 000, section 3.3) is a **mixture density network**: the head predicts K trajectories
# (modes), a spread for each, and how likely each is. For a sample `x` with expert trajectory `y`
# (10 normalised numbers), the loss is the negative log-likelihood of `y` under the mixture:
#
# $$\mathcal{L}(x, y) = -\log \sum_{k=1}^{K} \pi_k(x)\; \mathcal{N}\!\big(y \mid \mu_k(x),
#   \operatorname{diag}\sigma_k^2(x)\big), \qquad \pi = \operatorname{softmax}(\text{logits}).$$
#
# Computed stably: `log_softmax` for the weights, `log σ` parameterised (σ = floor + exp(raw), the
# floor 0.01 standard deviations keeps 1/σ finite), and a log-sum-exp over the modes. The
# constant `D/2 log 2π` is kept. At inference the paper follows the mean of the most likely mode.
#
# The paper's practicalities, each a switch here: batch norm in the hidden layers (`ModelConfig`),
# normalised targets (chapter 06), gradient clipping (`TrainConfig.grad_clip`), and **sigma frozen
# for the first epochs** (the paper: 5), then opened (`GMMObjective.sigma_warmup_epochs`).
#
# Run it with `python chapters/07_gmm.py` (add `--quick` for a run of seconds).

# %%
import math

import numpy as np
import torch

from e2e_lite import artifacts
from e2e_lite.agents import TrajectoryAgent
from e2e_lite.camera import Camera, CameraConfig, draw_trajectory, save_image
from e2e_lite.config import active_profile
from e2e_lite.data import DataConfig, DrivingDataset, load_or_collect
from e2e_lite.evaluation import EvalConfig, evaluate, observe
from e2e_lite.geometry import Track
from e2e_lite.losses import GMMObjective, Objective, gmm_nll
from e2e_lite.models import ModelConfig
from e2e_lite.tracker import trajectory_reference
from e2e_lite.training import TrainConfig, evaluate_loss, train_or_load
from e2e_lite.world import Fleet, ParkedCars, World, WorldConfig, make_world

profile = active_profile()
world_cfg = WorldConfig.for_profile(profile)
human = Camera(CameraConfig.human())
net_cam = Camera(CameraConfig())
print(f"{profile.name} profile")

# %% [markdown]
# ## 1. The loss, by hand
#
# A teaching version for one sample, straight from the equation (products of 1-D densities, then
# a weighted sum), checked against the library's stable version.


# %%
def nll_by_hand(y: np.ndarray, logits: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> float:
    """-log sum_k pi_k prod_d N(y_d | mu_kd, sigma_kd) for one sample (K modes, D dims)."""
    pi = np.exp(logits - logits.max())
    pi /= pi.sum()
    density = 0.0
    for k in range(len(pi)):
        gauss = np.exp(-0.5 * ((y - mu[k]) / sigma[k]) ** 2) / (np.sqrt(2 * math.pi) * sigma[k])
        density += pi[k] * np.prod(gauss)
    return -math.log(density)


rng = np.random.default_rng(0)
for k in (1, 2, 3):
    y, mu = rng.normal(size=10), rng.normal(size=(k, 10))
    sigma, logits = rng.uniform(0.5, 2.0, (k, 10)), rng.normal(size=k)
    lib = float(
        gmm_nll(
            torch.tensor(y)[None],
            torch.tensor(logits)[None],
            torch.tensor(mu)[None],
            torch.tensor(np.log(sigma))[None],
        )[0]
    )
    hand = nll_by_hand(y, logits, mu, sigma)
    print(f"K={k}: by hand {hand:.6f}, library {lib:.6f}")
    assert abs(hand - lib) < 1e-9
# The by-hand version underflows where the library does not: a target 40 sigmas from every mean
far = np.full(10, 40.0)
zeros_k, zeros_kd = (
    torch.zeros(1, 2, dtype=torch.float64),
    torch.zeros(1, 2, 10, dtype=torch.float64),
)
far_nll = float(gmm_nll(torch.tensor(far)[None], zeros_k, zeros_kd, zeros_kd)[0])
print(f"far target: library NLL {far_nll:.1f}")
try:
    print(
        f"far target: by hand {nll_by_hand(far, np.zeros(2), np.zeros((2, 10)), np.ones((2, 10)))}"
    )
except ValueError as err:  # log(0)
    print(f"far target: by hand fails ({err}): the density underflowed to 0")

# %% [markdown]
# ## 2. Training with the sigma warm-up
#
# While sigma is frozen (held at 1, its layer not trained) the loss is a weighted mixture of
# squared errors: the modes learn *where* before they learn *how sure*. With 3 epochs in the full
# profile we freeze the first (the paper froze 5 of many more).

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
warmup = max(1, profile.train_epochs // 3) if profile.train_epochs > 1 else 0
objective = GMMObjective(n_modes=2, sigma_warmup_epochs=warmup)
cfg = ModelConfig(kind="fusion", head="gmm", gmm_modes=2)
tcfg = TrainConfig(epochs=profile.train_epochs, batch_size=64, max_val_samples=4000, grad_clip=10.0)
model, hist = train_or_load("07_gmm", cfg, tcfg, objective, train, val)
objective.start_epoch(10**6)  # evaluate with sigma open
for rec in hist.epochs:
    print(f"epoch {rec['epoch'] + 1}: val NLL {rec['val_loss']:.3f}, frozen {rec['frozen'] or '-'}")
val_losses, val_metrics = evaluate_loss(model, objective, DrivingDataset(val))
held = {k: float(v.mean()) for k, v in val_metrics.items()}
print(
    f"held out: NLL {val_losses.mean():.3f}; " + ", ".join(f"{k} {v:.3f}" for k, v in held.items())
)
print("training curve: outputs/figures/train_07_gmm.png (the shaded epoch had sigma frozen)")

# %% [markdown]
# ## 3. One mode or two (the paper's Fig. 3)
#
# Left: a straight road with nothing ahead; both modes should agree (or one should carry all the
# weight). Right: the frame of chapter 06's failure, a parked car 44 m ahead in the middle lane;
# two plausible answers, left and right, with their weights.

# %%
agent = TrajectoryAgent(model, sigma_floor=objective.sigma_floor)
dcfg = DataConfig.for_profile(profile, "val")


def draw_modes(img: np.ndarray, last: dict, b: int = 0) -> np.ndarray:
    colours = [(255, 60, 40), (40, 120, 255), (250, 200, 0), (200, 0, 200)]
    for k in range(last["modes"].shape[1]):
        draw_trajectory(
            img,
            last["modes"][b, k],
            human,
            colour=colours[k % 4],
            label=f"{last['weights'][b, k]:.2f}",
        )
    return img


# unimodal: a straight validation sample in lane keeping, no car within 60 m
straight_rows = np.flatnonzero(
    (np.abs(val.curvature) < 1e-4) & (val.expert_state == 0) & (val.affordances[:, 6] >= 59.9)
)
i = int(straight_rows[len(straight_rows) // 2]) if straight_rows.size else 0
w_val = make_world(dcfg.world, dcfg.split, int(val.track[i]))
x, y, h = w_val.track.pose(float(val.s[i]), float(val.d[i]))
pose = (float(x), float(y), float(h) + float(val.affordances[i, 0]))
fleet = Fleet([w_val], world_cfg)
fleet.place(0, float(val.s[i]), float(val.d[i]), float(val.speed[i]))
fleet.state[0, 2] = pose[2]
obs = observe(fleet, True, images=val.images[i][None])
agent.trajectories(obs)
uni = {k: v.copy() for k, v in agent.last.items()}
left_img = draw_modes(human.render(w_val.track, w_val.cars, pose), uni)
draw_trajectory(left_img, val.trajectory[i], human, colour=(40, 200, 40), label="expert")

# bimodal: chapter 06's scene
straight = Track([0.0], [0.0], [0.0], [0.0], [900.0])
scene = World(
    straight, ParkedCars.on_track(straight, np.array([300.0]), np.array([0.0])), world_cfg.vehicle
)
fleet = Fleet([scene], world_cfg)
fleet.place(0, 300.0 - 2.25 - 3.6 - 44.0, 0.0, 25.0)
obs = observe(
    fleet, True, images=net_cam.render(straight, scene.cars, tuple(fleet.state[0, :3]))[None]
)
agent.trajectories(obs)
bi = {k: v.copy() for k, v in agent.last.items()}
right_img = draw_modes(human.render(straight, scene.cars, tuple(fleet.state[0, :3])), bi)
fig3_png = save_image(
    artifacts.artifact_path("figures", "07_gmm_modes.png"),
    np.concatenate([left_img, right_img], axis=1),
)
gap_uni = float(np.abs(uni["modes"][0, 0, -1] - uni["modes"][0, 1, -1]).max())
print(
    f"straight road: weights {np.round(uni['weights'][0], 2).tolist()}, modes {gap_uni:.2f} m apart at 1.5 s"
)
print(
    f"parked car ahead: weights {np.round(bi['weights'][0], 2).tolist()}, mode end points y5 "
    f"{np.round(bi['modes'][0, :, -1, 1], 2).tolist()} m"
)
print(f"saved {fig3_png}")

# %% [markdown]
# ## 4. Chapter 06's failure, revisited
#
# Over the validation samples where the expert starts an overtake from the middle lane: does the
# followed mode point to the side the expert took? (For L2 see chapter 06's numbers.)

# %%
starts = np.flatnonzero(
    (val.expert_state == 1) & val.overtaking & (val.lane == 1) & (np.abs(val.d) < 0.5)
)
side_ok = None
if starts.size:
    batch = DrivingDataset(val).batch(starts)
    with torch.inference_mode():
        weights, means, _ = objective.modes(model(batch["image"], batch["speed"]), model)
    modes = model.denormalise(means).reshape(len(starts), -1, 5, 2).numpy()
    top = weights.argmax(dim=-1).numpy()
    followed_y5 = modes[np.arange(len(starts)), top, -1, 1]
    expert_y5 = val.trajectory[starts, -1, 1]
    side_ok = float(np.mean(np.sign(followed_y5) == np.sign(expert_y5)))
    print(
        f"{starts.size} overtake starts in the middle lane: the followed mode takes the expert's side in {side_ok:.0%}"
    )
    l2 = artifacts.read_metrics("06_trajectory_regression")
    if l2 is not None and l2.get("profile") == profile.name:
        print(f"chapter 06 (L2): {l2['averaging']['validation_starts']}")

# %% [markdown]
# ## 5. Closed loop

# %%
ev = EvalConfig(miles=profile.eval_miles, n_worlds=profile.n_worlds, n_tracks=profile.n_val_tracks)
res = evaluate(agent, world_cfg, ev, desc="trajectory GMM")
print(res.summary())
rows_md = [
    "| driver | per 100 mi [95% CI] | mph | time to collision | autonomy |",
    "|---|---|---:|---:|---:|",
]
earlier = []
for chapter, key in (("05_pilotnet_baseline", "results"), ("06_trajectory_regression", "result")):
    m = artifacts.read_metrics(chapter)
    if m is None or m.get("profile") != profile.name:
        continue
    entries = m[key].items() if key == "results" else [("trajectory L2 + LQR", m[key])]
    for name, r in entries:
        earlier.append((name, r))
for name, r in [*earlier, ("trajectory GMM + LQR", res.to_dict())]:
    lo, hi = r["ci95_per_100mi"]
    ttc = "-" if r["time_to_collision_s"] is None else f"{r['time_to_collision_s']:.1f} s"
    rows_md.append(
        f"| {name} | {r['collisions_per_100mi']:.1f} [{lo:.1f}-{hi:.1f}] | "
        f"{r['mean_speed_mph']:.1f} | {ttc} | {r['autonomy_pct']:.1f}% |"
    )
table = "\n".join(rows_md)
print(table)
l2 = dict(earlier).get("trajectory L2 + LQR")
if l2 is not None:
    lo2, hi2 = l2["ci95_per_100mi"]
    overlap = res.ci95_per_100mi[0] <= hi2 and lo2 <= res.ci95_per_100mi[1]
    better = res.collisions_per_100mi < l2["collisions_per_100mi"]
    verdict = (
        f"GMM {res.collisions_per_100mi:.1f} vs L2 {l2['collisions_per_100mi']:.1f} per 100 mi: "
        + (
            "intervals overlap, no measurable difference at this mileage"
            if overlap
            else ("GMM better beyond chance" if better else "GMM worse beyond chance")
        )
    )
else:
    verdict = "run chapter 06 first to compare with L2"
print(verdict)

# %% [markdown]
# ## 6. Looking for why: what the followed trajectories ask of the tracker
#
# Held-out errors say the GMM's most likely mode is about as accurate as L2 on recorded frames.
# Closed loop is different: the network sees the states its own driving creates. Drive both
# agents on the same tracks and record, every decision, the car's speed and what the tracker reads
# from the followed trajectory (`trajectory_reference`): the reference speed `v_ref` and the
# reference acceleration `a_ref`. The tracker commands `a_ref + 1 s⁻¹ (v_ref - v)`.


# %%
class Recorder:
    """Wraps a trajectory agent; keeps (speed, v_ref, a_ref) of every car at every decision."""

    def __init__(self, agent: TrajectoryAgent) -> None:
        self.agent, self.camera, self.rows = agent, agent.camera, []

    def reset(self, n: int) -> None:
        self.agent.reset(n)

    def act(self, obs):
        act = self.agent.act(obs)
        _, _, _, v_ref, a_ref = trajectory_reference(self.agent.last["points"])
        self.rows.append(np.stack([obs.speed, v_ref, a_ref], axis=1))
        return act


l2_model, _ = train_or_load(
    "06_trajectory_l2",
    ModelConfig(kind="fusion", head="trajectory"),
    TrainConfig(epochs=profile.train_epochs, batch_size=64, max_val_samples=4000),
    Objective("trajectory"),
    train,
    val,
)
diag_miles = 2.0 if profile.quick else 10.0
diagnosis = {}
for name, m in (("L2", l2_model), ("GMM", model)):
    rec = Recorder(TrajectoryAgent(m, sigma_floor=objective.sigma_floor))
    r = evaluate(
        rec,
        world_cfg,
        EvalConfig(miles=diag_miles, n_worlds=profile.n_worlds, n_tracks=profile.n_val_tracks),
        desc=f"diagnose {name}",
    )
    log = np.concatenate(rec.rows)
    crash_speeds = [e["speed_mps"] for e in r.events]
    diagnosis[name] = {
        "speed_mps": float(log[:, 0].mean()),
        "v_ref_minus_speed_mps": float((log[:, 1] - log[:, 0]).mean()),
        "a_ref_mps2": float(log[:, 2].mean()),
        "collision_speed_mps": float(np.mean(crash_speeds)) if crash_speeds else None,
        "collisions_per_100mi": r.collisions_per_100mi,
    }
    d = diagnosis[name]
    print(
        f"{name}: speed {d['speed_mps']:.2f} m/s, v_ref - v {d['v_ref_minus_speed_mps']:+.2f} m/s, "
        f"a_ref {d['a_ref_mps2']:+.2f} m/s2, {r.collisions} collisions in {r.miles:.0f} mi"
    )
slow_share = float(np.mean(train.speed < 22.0))
print(
    f"expert data: mean speed {train.speed.mean():.2f} m/s; samples below 22 m/s {slow_share:.1%}"
)

# %% [markdown]
# If the GMM's `v_ref - v` and `a_ref` have opposite signs, the tracker's speed loop settles where
# they cancel, below the expert's cruise speed: a speed the data rarely shows on straights, where
# the network's lateral predictions are less reliable. That is a lead, not yet a proof: the
# exercises below test it.

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "07_gmm",
    {
        "profile": profile.name,
        "headline": {
            "trajectory GMM collisions/100mi": res.collisions_per_100mi,
            "val ADE [m]": held["ADE [m]"],
        },
        "result": res.to_dict(),
        "held_out": {"nll": float(val_losses.mean()), **held},
        "training": {
            "best_epoch": hist.best_epoch,
            "epochs": len(hist.epochs),
            "sigma_warmup_epochs": warmup,
        },
        "fig3": {
            "straight_weights": uni["weights"][0].tolist(),
            "straight_mode_gap_m": gap_uni,
            "bimodal_weights": bi["weights"][0].tolist(),
            "bimodal_y5_m": bi["modes"][0, :, -1, 1].tolist(),
        },
        "overtake_side_agreement": side_ok,
        "verdict_vs_l2": verdict,
        "closed_loop_diagnosis": {**diagnosis, "train_share_below_22mps": slow_share},
        "table_md": table,
        "figures": [str(fig3_png.relative_to(artifacts.outputs_dir()))],
    },
)

# %% [markdown]
# ## Summary
#
# * A mixture head predicts several trajectories and their probabilities; its NLL is computed with
#   log-softmax, a floored log-sigma and a log-sum-exp, and agrees with the textbook formula where
#   that does not underflow.
# * Holding sigma for the first epoch lets the means settle before the spreads move.
# * Where the expert's behaviour splits (overtake left or right), the modes split too, and the
#   followed mode takes one side instead of the average.
# * Whether that lowers collisions here is measured above against L2 on the same tracks and seeds;
#   the verdict line says whether the difference is beyond chance. If it is not, look at where the
#   collisions happen (`result["events"]` in the metrics): a mixture fixes *averaging*, not errors
#   that both L2 and the GMM make.
#
# ## Exercises
#
# 1. Train with `sigma_warmup_epochs=0`. Does the validation NLL of the first epoch differ? Do the
#    modes still separate on the overtake frame?
# 2. Use K = 3 modes. What does the third mode learn on the overtake frame, and on a curve?
# 3. Follow the *weighted mean* of the modes instead of the most likely mode. Which failure of
#    chapter 06 comes back?
# 4. Section 6's lead: follow the GMM's mode with `a_ref` set to zero (edit a copy of
#    `follow_trajectory`). Does the car keep 25 m/s, and do the collisions fall towards L2's?
# 5. Lower `sigma_floor` to 1e-4 and train. Watch the training loss: what does an over-confident
#    mode do to the NLL of a sample it gets wrong?
