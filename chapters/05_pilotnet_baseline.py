# %% [markdown]
# # 05 · The PilotNet baselines
#
# Before the paper's ideas, its baseline: learn the **actuators** straight from the camera. Two
# published systems do that, and the GM paper's Table 1 calls them "Baseline E2E":
#
# * **PilotNet** (seed 003, NVIDIA 2016): one front image in, the steering out (as an inverse
#   turning radius), trained with extra *recovery* views from shifted and rotated cameras;
# * **modified PilotNet** (seed 002, Arain): image and speed in, steering **and** acceleration out,
#   no controller. The GM paper's own baseline predicted all actuators too and collided 183.3
#   times per 100 miles.
#
# This chapter builds the learning stack every later chapter reuses (models, one training loop,
# checkpoints that refuse the wrong normalisation, agents that drive B worlds at once) and judges
# both baselines in closed loop on the unseen test tracks.
#
# **You will learn**
# 1. PilotNet's layers, and the fixed normalisation layer;
# 2. why seed 003 needed recovery views, and how our renderer makes them exactly;
# 3. what a held-out loss says, and what it does not say about driving;
# 4. how often each baseline collides, and how long it drives before it does.
#
# Run it with `python chapters/05_pilotnet_baseline.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(5)  # flags, profile, outputs folder: checked before any work

import numpy as np
import torch

from e2e_lite import artifacts
from e2e_lite.driving.evaluation import EvalConfig, evaluate, results_table
from e2e_lite.imitation import recipes
from e2e_lite.imitation.agents import ActuatorAgent, SteeringAgent
from e2e_lite.imitation.collector import DataConfig, DrivingDataset, concat, load_or_collect
from e2e_lite.imitation.recovery import RecoveryConfig, load_or_make_recovery
from e2e_lite.learning.losses import Objective
from e2e_lite.learning.models import build_model, count_parameters, pick_device, prepare
from e2e_lite.learning.training import TrainConfig, epoch_batches, evaluate_loss, fit, model_stats
from e2e_lite.record import words
from e2e_lite.simulation.camera import Camera, CameraConfig
from e2e_lite.simulation.raster import save_image, tile
from e2e_lite.simulation.world import WorldConfig, make_world
from e2e_lite.stats.rates import compare_rates

world_cfg = WorldConfig.for_profile(profile)
device = pick_device()
print(f"training on {device}")

# %% [markdown]
# ## 1. PilotNet
#
# A fixed normalisation layer (pixels to [-1, 1]; not trained), five convolutions (24, 36, 48
# filters 5x5 with stride 2, then 64, 64 filters 3x3), and fully connected layers of 100, 50 and
# 10 units. Seed 003's figure counts 1164 features after the convolutions; at 66 x 200 the layers
# give 64 x 1 x 18 = 1152. The modified PilotNet of this course shares the convolutions and adds
# the speed through a fusion MLP (the GM paper's architecture, chapter 06 explains it), so every
# baseline and every later driver sees the image through the same trunk.

# %%
pilot_cfg, actuator_cfg = recipes.PILOTNET_CFG, recipes.ACTUATORS_CFG
print(build_model(pilot_cfg))
n_pilot = count_parameters(build_model(pilot_cfg))
n_act = count_parameters(build_model(actuator_cfg))
print(f"PilotNet (steering): {n_pilot:,} parameters;  image + speed -> actuators: {n_act:,}")

# %% [markdown]
# ## 2. Data and recovery views
#
# The expert's dataset of chapter 04 (reused when it exists). Seed 003 found that a network
# trained only on a good driver's frames never sees what to do when it drifts: its own errors
# take it to states the data does not hold. Its answer was extra views from cameras shifted and
# rotated, labelled with the steering that brings the car back within 2 s. We render those views
# exactly: the same road and cars, the car moved 0.3-1.2 m sideways and turned up to 3.4°, for
# half of the samples. The label is the expert's steering plus the LQR tracker's correction
# towards the expert's own trajectory from the moved pose (chapter 03 prints how far it takes to
# settle a 1 m error). Our expert data already holds noise and its recoveries (chapter 04), so
# the question here is whether the views add anything on top.

# %%
train_cfg_data = DataConfig.for_profile(profile, "train")
train = load_or_collect(train_cfg_data)
val = load_or_collect(DataConfig.for_profile(profile, "val"))
views = load_or_make_recovery(train, train_cfg_data, RecoveryConfig())
with_views = concat(train, views)
print(f"train {len(train)} samples, recovery views {len(views)}, validation {len(val)}")

human = Camera(CameraConfig.human())
net_cam = Camera(CameraConfig())
tiles = []
src = views.info["source_rows"]
for k in np.linspace(0, len(views) - 1, 3).round().astype(int):
    i = int(src[k])
    pair = []
    for data, row in ((train, i), (views, k)):
        img = np.repeat(np.repeat(data.images[row], 3, axis=0), 3, axis=1)  # 198 x 600, as seen
        steer_deg = np.degrees(data.actuators[row, 0])
        import cv2  # local: only this figure writes text

        cv2.putText(
            img,
            f"d={data.d[row]:+.2f} m  steer {steer_deg:+.2f} deg",
            (8, 22),
            0,
            0.6,
            (255, 255, 0),
            2,
        )
        pair.append(img)
    tiles += pair
views_png = save_image(artifacts.artifact_path("figures", "05_recovery_views.png"), tile(tiles, 2))
print(
    f"saved {views_png}: left the recorded frame, right its recovery view (network resolution, 3x)"
)

# %% [markdown]
# ## 3. Training
#
# ### One training step, written out
#
# Every network of the course learns with the same six lines. For a batch of frames and labels:
#
# 1. forget the previous step's gradients (`zero_grad`);
# 2. forward: the network's outputs for the batch;
# 3. the loss: one number, the batch's mean error in normalised units;
# 4. backward: the gradient of that number with respect to every weight;
# 5. clip: when the gradient's norm is above `c`, scale it down to `c` (one bad batch cannot
#    throw the weights far);
# 6. step: Adam moves every weight against its gradient, scaled by running estimates of the
#    gradient's mean and spread.
#
# We write them once here and check them against the library's loop (`e2e_lite.learning.training.fit`):
# the same start, the same batches, the same weights at the end. The library adds only
# bookkeeping around them: the validation losses, the kept epoch, the progress bar, the curve.

# %%
steer_loss = Objective("steer")
check_cfg = TrainConfig(epochs=1, batch_size=32, grad_clip=1.0, device="cpu")
few = DrivingDataset(train, np.arange(min(len(train), 3 * check_cfg.batch_size)))
few_val = DrivingDataset(val, np.arange(min(len(val), check_cfg.batch_size)))


def fresh_pilotnet() -> torch.nn.Module:
    """PilotNet with torch's seeded initial weights and the training set's normalisation."""
    torch.manual_seed(check_cfg.seed)
    net = build_model(pilot_cfg)
    net.set_normalisation(model_stats(pilot_cfg, train, steer_loss))
    return prepare(net, torch.device("cpu"))


by_library = fresh_pilotnet()
fit(by_library, steer_loss, few, few_val, check_cfg, name="05_step_check", progress=False)

by_hand = fresh_pilotnet()
adam = torch.optim.Adam(by_hand.parameters(), lr=check_cfg.lr)
by_hand.train()  # dropout on, batch norm learning its statistics
for rows in epoch_batches(len(few), check_cfg.batch_size, check_cfg.seed, epoch=0):
    batch = few.batch(few.indices[rows])
    adam.zero_grad(set_to_none=True)  # 1. forget the last step's gradients
    out = by_hand(batch["image"], batch["speed"])  # 2. forward
    loss = steer_loss.batch_loss(out, batch, by_hand)  # 3. the batch's mean loss
    loss.backward()  # 4. d loss / d weights
    torch.nn.utils.clip_grad_norm_(by_hand.parameters(), check_cfg.grad_clip)  # 5. clip
    adam.step()  # 6. Adam's update
gap = max(
    float((a - b).detach().abs().max())
    for a, b in zip(by_hand.parameters(), by_library.parameters())
)
steps = len(few) // check_cfg.batch_size
between = "between the written-out loop and the library's"
print(f"{len(few)} samples, {steps} steps: the largest weight difference {between} is {gap:.1e}")
assert gap < 1e-6, gap

# %% [markdown]
# ### The course's trainings
#
# One loop for every chapter (`e2e_lite.learning.training.fit`): Adam at 1e-3 without weight decay (the
# paper), batches of 64, per-epoch metrics JSON and a training curve in
# `outputs/figures/train_<name>.png`. Of several epochs, the one kept is the one that collides
# least when it drives 20 mi on validation roads (held-out errors did not predict the driving:
# lab note "The GMM's worst seeds of record, epoch by epoch"; with one epoch, as in the quick profile, there is nothing
# to choose). A checkpoint carries the model's settings,
# its normalisation statistics and the dataset's key; running the chapter again reuses it. The
# settings of each trained driver live in `e2e_lite/imitation/recipes.py`, so chapter 10 retrains or reuses
# exactly these models.

# %%
pilot, steer_obj, h_pilot = recipes.pilotnet(profile, train, val)
pilot_aug, _, h_pilot_aug = recipes.pilotnet(profile, with_views, val, name="05_pilotnet_views")
actuator, act_obj, h_act = recipes.actuators(profile, train, val)
for name, h in (("PilotNet", h_pilot), ("PilotNet + views", h_pilot_aug), ("actuators", h_act)):
    print(
        f"{name}: kept epoch {h.best_epoch + 1}/{len(h.epochs)}, {h.samples_per_s:,.0f} samples/s"
    )

# %% [markdown]
# ## 4. Held-out losses (seed 002's Table 4)
#
# Loss and mean absolute error per output on the validation samples (tracks never trained on).
# Each model's loss is in its own normalised units (the curvature statistics of the training set
# with views differ from those without), so compare models by the errors in degrees and m/s².

# %%
val_ds = DrivingDataset(val)
held_out = {}
for name, model, obj in (
    ("PilotNet", pilot, steer_obj),
    ("PilotNet + views", pilot_aug, steer_obj),
    ("actuators", actuator, act_obj),
):
    losses, metrics = evaluate_loss(model, obj, val_ds)
    held_out[name] = {
        "loss": float(losses.mean()),
        **{k: float(v.mean()) for k, v in metrics.items()},
    }
print(
    "| model | val loss (normalised MSE) | steer MAE [deg] | accel MAE [m/s2] |\n|---|---:|---:|---:|"
)
for name, row in held_out.items():
    accel = f"{row['accel MAE [m/s2]']:.3f}" if "accel MAE [m/s2]" in row else "-"
    print(f"| {name} | {row['loss']:.4f} | {row['steer MAE [deg]']:.3f} | {accel} |")

# %% [markdown]
# ## 5. Closed loop
#
# The evaluator renders each car's 66 x 200 frame every 0.1 s and asks the agent for a batch of
# commands. PilotNet steers and a cruise control holds the road's speed limit (the expert's
# curve-speed profile: it knows the curves ahead, not the parked cars). The actuator baseline
# does both itself. Same tracks, same seeds for every driver.

# %%
ev = EvalConfig(miles=profile.eval_miles, n_worlds=profile.n_worlds)
results = {}
for name, agent in (
    ("PilotNet (steering)", SteeringAgent(pilot)),
    ("PilotNet + recovery views", SteeringAgent(pilot_aug)),
    ("image + speed -> actuators", ActuatorAgent(actuator)),
):
    results[name] = evaluate(agent, world_cfg, ev, desc=name)
    print(f"{name}: {results[name].summary()}")

table = results_table(list(results.items()))
print(table + profile.caveat)
print(
    "paper (TORCS): Baseline E2E 183.3 per 100 mi; seed 002 (CARLA): time to collision 10.2 s vs 1.1 s"
)

# Is the difference between the two PilotNets more than chance? The exact test of two rates
# (`compare_rates`: given the total, how the collisions split by miles; overlapping intervals
# are no test).
plain, aug = results["PilotNet (steering)"], results["PilotNet + recovery views"]
verdict = "recovery views vs without: " + words.rates(compare_rates(aug, plain))
print(verdict)

# %% [markdown]
# ## 6. What the network saw
#
# The frame at the pose of a few collisions (network resolution, 3x), with the obstacle's kind.

# %%
tiles = []
worlds = {}
for name, r in results.items():
    for event in r.events[:2]:
        key = tuple(event["track"])
        if key not in worlds:
            worlds[key] = make_world(world_cfg, key[0], key[1])
        w = worlds[key]
        pose = (event["x_m"], event["y_m"], event["heading_rad"])
        img = net_cam.render(w.track, w.cars, pose, event["s_m"])
        img = np.repeat(np.repeat(img, 3, axis=0), 3, axis=1)
        cv2.putText(img, f"{name[:26]}: {event['kind']}", (8, 22), 0, 0.55, (255, 255, 0), 2)
        tiles.append(img)
if tiles:
    crashes_png = save_image(
        artifacts.artifact_path("figures", "05_collisions.png"), tile(tiles, 2)
    )
    print(f"saved {crashes_png}")
else:
    crashes_png = None
    print("no collisions to show")

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "05_pilotnet_baseline",
    {
        "profile": profile.name,
        "headline": {
            f"{name} collisions/100mi": r.collisions_per_100mi for name, r in results.items()
        },
        "results": {name: r.to_dict() for name, r in results.items()},
        "held_out": held_out,
        "training": {
            name: {
                "best_epoch": h.best_epoch,
                "epochs": len(h.epochs),
                "samples_per_s": h.samples_per_s,
            }
            for name, h in (
                ("pilotnet", h_pilot),
                ("pilotnet_views", h_pilot_aug),
                ("actuators", h_act),
            )
        },
        "parameters": {"pilotnet": n_pilot, "actuators": n_act},
        "table_md": table,
        "recovery_views_verdict": verdict,
    },
    figures=(views_png, crashes_png),
)

# %% [markdown]
# ## Summary
#
# * Learning is six lines per batch (section 3: zero the gradients, forward, loss, backward,
#   clip, step); the library's loop runs exactly those, with bookkeeping around them.
# * PilotNet and the all-actuators network learn the expert's commands to a small held-out error,
#   and still collide in closed loop: a low loss on recorded frames does not say what happens once
#   the network drives (that its own errors then choose the next frames, ones the data never
#   showed, is the hypothesis chapter 12 measures). The table above is the course's baseline.
# * The recovery views are cheap here (the renderer makes them exactly); compare the two PilotNet
#   rows to see whether they help on top of the expert's own noise recoveries.
# * The all-actuators network must also learn *when to brake and accelerate* from one frame and
#   the speed; PilotNet leaves that to a cruise control that knows the road.
# * A collision is a parked car (an overtake gone wrong or missed) or a guard rail (the car left
#   its road: chapter 10 counts each kind per driver). The next chapters change the output (a
#   trajectory), the loss (a mixture), the features (affordances) and the emphasis (CVaR).
#
# ## Exercises
#
# 1. Train PilotNet with `RecoveryConfig(fraction=1.0, shift_m=(0.5, 2.0))`. Does the held-out
#    loss go up or down? And the collisions? Explain the difference.
# 2. Replace the cruise control of `SteeringAgent` by a constant 25 m/s. Which collisions appear?
# 3. Seed 002 predicted throttle and brake instead of acceleration. Use
#    `e2e_lite.imitation.collector.throttle_brake` to make those targets and train a 3-output head. What changes?
# 4. Look at `outputs/figures/train_05_actuators.png`. Is the kept epoch the last? What would more
#    epochs buy, and what would they cost on this CPU?
