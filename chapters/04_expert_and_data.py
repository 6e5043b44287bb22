# %% [markdown]
# # 04 · The expert and its dataset
#
# Behaviour cloning needs someone to clone. The paper built "a basic expert traversing the inner
# states of a finite state machine" with privileged access to the simulator (seed 000, 4.1.1),
# randomised its overtakes "to simulate multi-modal behaviour exhibited by real drivers", and
# found that "adding noise to the expert was found to be crucial". This chapter builds that
# expert on the LQR tracker of chapter 03 and records the dataset every learned driver trains on.
#
# **You will learn**
# 1. the expert's state machine: when it *should* overtake and when it *can*;
# 2. why its trigger distance, change duration and side are random, and what that does to the data
#    (the same scene overtaken left in one sample and right in another);
# 3. how noise injection puts recovery into the data while the labels stay clean;
# 4. what a sample holds: a 66 x 200 frame, the speed, clean actuators, a 5-point trajectory and
#    DeepDriving-style affordances;
# 5. the **ceiling** (the expert's collisions per 100 miles) and the **oracle** (the LQR tracker
#    following the expert's 5-point trajectories): what does the representation lose?
# 6. **covariate shift**: a learned driver visits states the expert never shows it, unless the
#    data is collected so that it does.
#
# Run it with `python chapters/04_expert_and_data.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(4)  # flags, profile, outputs folder: checked before any work

import dataclasses

import numpy as np
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.control.expert import Expert
from e2e_lite.control.oracle import Oracle
from e2e_lite.driving.evaluation import (
    SPEED_BINS,
    EvalConfig,
    drive,
    evaluate,
    observe,
    speed_histogram,
)
from e2e_lite.driving.figures import draw_road, save_figure
from e2e_lite.imitation.collector import (
    AFFORDANCE_NAMES,
    SLOW_MPS,
    DataConfig,
    NoiseConfig,
    describe,
    load_or_collect,
)
from e2e_lite.learning.labels import CHANGE, KEEP, STATE_NAMES
from e2e_lite.record import words
from e2e_lite.simulation.camera import Camera, CameraConfig
from e2e_lite.simulation.geometry import Track
from e2e_lite.simulation.raster import draw_trajectory, save_image, tile
from e2e_lite.simulation.scenarios import TWO_ANSWERS_CAR_S_M, two_answers_scene
from e2e_lite.simulation.world import ParkedCars, World, WorldConfig, make_world
from e2e_lite.stats.rates import compare_rates

world_cfg = WorldConfig.for_profile(profile)
human = Camera(CameraConfig.human())

# %% [markdown]
# ## 1. The state machine
#
# The expert follows three rules (the paper's): its speed never exceeds
# `min(top speed, sqrt(a_lat,max / |κ|))` over the curvature ahead (it brakes *before* a curve);
# the tracker keeps it on a lane centre or a lane-change path; and a state machine decides when it
# **should** overtake (a parked car ahead in its lane nearer than a *trigger* distance) and when
# it **can** (the target lane is free from just behind it to 40 m past the parked car).
#
# | state | does | leaves when |
# |---|---|---|
# | `keep` | follow its lane's centre | a car ahead nearer than *trigger*: `change` if a neighbour |
# | | at the speed limit | is free (a coin picks when both are), else `follow` |
# | `change` | follow a quintic path | near the new lane's centre: `keep` there |
# | `follow` | stop 15 m behind the car | a lane becomes free (slower: a shorter lane change) |
#
# It keeps whichever lane it is in (`ExpertConfig.home`; a rule that returns to a home lane adds
# a `pass` state, and the lab note "One expert for the whole course" says why this one was
# chosen). Per parked car, a generator seeded by the expert's seed, the track and the car draws
# the trigger (45-75 m: at 25 m/s a comfortable lane change needs ~60 m), the change's duration
# (2.5-3.5 s) and the side coin. The expert **reads its plan off the state** at every decision:
# the same state gets the same label whatever drove there, which chapter 12 needs of its
# labeller.

# %%
straight = Track([0.0], [0.0], [0.0], [0.0], [900.0])
scene_cars = ParkedCars.on_track(
    straight, np.array([260.0, 420.0, 560.0]), straight.lane_center(np.array([1, 2, 1]))
)
scene = World(straight, scene_cars, world_cfg.vehicle)


def expert_drive(seed: int, world: World = scene, seconds: float = 26.0):
    """The expert's rear-axle path and states on a hand-made scene, starting in the middle lane."""
    expert = Expert(seed=seed)
    states: list[int] = []
    path, contacts = drive(
        expert,
        world,
        world_cfg,
        60.0,
        0.0,
        25.0,
        seconds,
        lambda obs, act: states.append(expert.decisions[0].state),
    )
    return path, np.array(states), contacts


# %%
colours = {0: "#1f77b4", 1: "#ff7f0e", 2: "#2ca02c", 3: "#d62728"}
fig = Figure(figsize=(12, 4.6))
axes = fig.subplots(2, 1)
overtakes = {}
for ax, seed in zip(axes, (0, 3)):
    path, states, contacts = expert_drive(seed)
    assert not contacts, "the expert collided on the demonstration scene"
    draw_road(ax, straight, (40.0, 700.0), scene_cars)
    for st in np.unique(states):  # (the states this drive visits: the legend's)
        sel = states == st
        ax.scatter(
            path[:-1][sel, 0],
            path[:-1][sel, 1],
            s=4,
            color=colours[st],
            zorder=6,
            label=STATE_NAMES[st],
        )
    ax.set_aspect(6.0)
    ax.set_title(f"expert, seed {seed}")
    overtakes[seed] = path
axes[0].legend(loc="upper left", ncol=4, fontsize=8, markerscale=3)
strip_png = save_figure(fig, artifacts.artifact_path("figures", "04_overtake_strip.png"))
print(f"saved {strip_png} (lateral scale stretched 6x)")

# %% [markdown]
# ## 2. The same scene, two answers
#
# A parked car in the middle lane with both neighbours free: the coin decides. Over the seeds below
# the expert passes it on both sides, and where it starts varies with the trigger. A network that
# regresses the *mean* of these answers would aim at the parked car; chapter 07's mixture density
# head is built for exactly this.

# %%
single, _ = two_answers_scene(world_cfg)  # one parked car in the middle lane at 300 m
sides, starts = [], []
n_seeds = 16 if profile.quick else 48
for seed in range(n_seeds):
    path, states, contacts = expert_drive(seed, single, seconds=12.0)
    assert not contacts
    k = int(np.argmax(states == CHANGE))
    beside = np.argmin(np.abs(path[:, 0] - TWO_ANSWERS_CAR_S_M))  # the sample beside the car
    sides.append(int(np.sign(path[beside, 1])))
    starts.append(float(path[k, 0]))
print(f"{n_seeds} seeds: {sides.count(1)} overtakes on the left, {sides.count(-1)} on the right")
print(
    f"lane change started at x = {min(starts):.0f} to {max(starts):.0f} m "
    f"(car at {TWO_ANSWERS_CAR_S_M:.0f} m)"
)

# The same frame, eight experts: the car 44 m behind the parked car (nearer than any trigger), and
# each seed's label from this one state. The image is identical; the answers are not.
single, fleet = two_answers_scene(world_cfg, gap_m=44.0, speed_mps=25.0)
obs = observe(fleet, respawned=True)
img = human.render(single.track, single.cars, tuple(obs.state[0, :3]), obs.s[0])
label_sides = []
for seed in range(8):
    expert = Expert(seed=seed)
    expert.reset(1)
    pts = expert.trajectory_label(obs)[0]
    label_sides.append(int(np.sign(pts[-1, 1])))
    draw_trajectory(img, pts, human, colour=(255, 60, 40) if pts[-1, 1] > 0 else (40, 120, 255))
both_png = save_image(artifacts.artifact_path("figures", "04_two_answers.png"), img)
print(
    f"saved {both_png}: of 8 seeds, {label_sides.count(1)} plan left (red), {label_sides.count(-1)} right (blue)"
)

# %% [markdown]
# ## 3. The ceiling and the oracle
#
# The expert drives the test tracks (the unseen tracks every learned driver is judged on; the
# validation tracks give the validation data, on which choices are made).
# It is the ceiling: if it collided, the fix would go into the expert, not the count. The oracle
# is the LQR tracker following the expert's **5-point trajectories** (re-planned every 0.1 s),
# not its commands: if the oracle drives as well, the paper's output representation plus a
# controller loses nothing.

# %%
ev = EvalConfig(miles=profile.eval_miles, n_worlds=profile.n_worlds)
expert = Expert()
res_expert = evaluate(expert, world_cfg, ev, desc="expert")
print("expert:", res_expert.summary())
manoeuvres = {k: int(res_expert.info.get("manoeuvres", {}).get(k, 0)) for k in expert.manoeuvres}
print(f"  manoeuvres: {manoeuvres}")
oracle = Oracle()
res_oracle = evaluate(oracle, world_cfg, ev, desc="oracle")
print("oracle:", res_oracle.summary())
print("oracle vs expert:", words.rates(compare_rates(res_oracle, res_expert)))

# %% [markdown]
# ## 4. Noise and clean labels
#
# The collector drives the expert with random **bursts** added to what it executes: a steering
# offset of 0.003-0.015 rad and an acceleration offset of up to 1 m/s², lasting 0.5-1.5 s, about
# one every 8 s; a quarter of the bursts brake at 2-4 m/s² instead. The recorded states drift
# off-centre, off-heading and below cruise speed; the expert pulls back. The labels are what the
# expert would do from each recorded state:
#
# * actuators: its command **before** the burst is added;
# * trajectory: a rollout of copies of the car by the same rules for 1.5 s without noise (no physics,
#   no rendering), recorded every 0.3 s in the car frame at the sample time.
#
# ## 5. The dataset
#
# One sample per decision (10 Hz) on the training tracks, and a smaller set on the validation
# tracks (for validation losses). The paper had 500K samples; we record 48,000 (full profile),
# about 80 minutes of driving, which trains in minutes on two cores.

# %%
train = load_or_collect(DataConfig.for_profile(profile, "train"))
val = load_or_collect(DataConfig.for_profile(profile, "val"))
print("train:", describe(train))
print("val:  ", describe(val))
print(f"  trajectory mean (x, y) per point: {np.round(train.stats['trajectory_mean'], 2).tolist()}")
print(f"  trajectory std  (x, y) per point: {np.round(train.stats['trajectory_std'], 2).tolist()}")
for name, mean, std in zip(
    AFFORDANCE_NAMES, train.stats["affordances_mean"], train.stats["affordances_std"]
):
    print(f"  affordance {name:16s} mean {mean:8.3f}  std {std:7.3f}")

# %% [markdown]
# Samples with their labels, drawn on the human-sized camera view of the same pose (the network
# sees the 66 x 200 frame at the bottom right of each tile).

# %%
rng = np.random.default_rng(0)
groups = {
    "straight, keep": (np.abs(train.curvature) < 1e-4)
    & (train.expert_state == KEEP)
    & ~train.noise,
    "curve": (np.abs(train.curvature) > 2e-3) & (train.expert_state == KEEP),
    "overtake left": (train.expert_state == CHANGE) & train.overtaking & (train.change_side > 0),
    "overtake right": (train.expert_state == CHANGE) & train.overtaking & (train.change_side < 0),
    "noise burst": train.noise & (train.expert_state == KEEP),
}
dcfg = DataConfig.for_profile(profile, "train")
worlds: dict[int, World] = {}
tiles = []
for title, mask in groups.items():
    rows = np.flatnonzero(mask)
    if rows.size == 0:
        print(f"no '{title}' sample in this dataset")
        continue
    i = int(rng.choice(rows))
    t_idx = int(train.track[i])
    if t_idx not in worlds:
        worlds[t_idx] = make_world(dcfg.world, "train", t_idx)
    w = worlds[t_idx]
    x, y, h = w.track.pose(float(train.s[i]), float(train.d[i]))
    pose = (float(x), float(y), float(h) + float(train.affordances[i, 0]))
    img = human.render(w.track, w.cars, pose, float(train.s[i]))
    draw_trajectory(img, train.trajectory[i], human, label=title)
    small = train.images[i]
    img[-small.shape[0] - 4 : -4, -small.shape[1] - 4 : -4] = small
    tiles.append(img)
samples_png = save_image(artifacts.artifact_path("figures", "04_samples.png"), tile(tiles, 2))
print(f"saved {samples_png}")

# %% [markdown]
# Where the labels end after 1.5 s, across the training set: most samples go straight ahead;
# the tails left and right are the lane changes, the minority the paper cares about.

# %%
fig = Figure(figsize=(10, 3.4))
ax1, ax2 = fig.subplots(1, 2)
ax1.hist(train.trajectory[:, -1, 1], bins=80, color="C0", log=True)
ax1.set(xlabel="lateral position after 1.5 s, y5 [m]", ylabel="samples (log)", title="label tails")
gaps = train.affordances[:, AFFORDANCE_NAMES.index("gap_ego_m")]
ax2.hist(gaps, bins=60, color="C1", log=True)
ax2.set(
    xlabel="gap to the car ahead in the ego lane [m] (60 = none)", title="affordance: ego-lane gap"
)
hist_png = save_figure(fig, artifacts.artifact_path("figures", "04_label_tails.png"))

# %% [markdown]
# ## 6. The states a learned driver visits: covariate shift
#
# A cloned driver is trained on the states the *expert* visits, then judged on the states *it*
# visits. The two differ. The evaluator starts every car at 20 m/s and, after every collision,
# puts it back 15 m past the obstacle at 20 m/s (the roads' cruise speed is 25 m/s): does a
# driver that collides spend more of its time getting back to speed than the expert shows it? In
# the course's first run the training data lacked those restart states (lab note "The GMM's
# first failures were the course's"); the old way of collecting, re-run below, shows how few.
#
# The classic answer is DAgger (let the learner drive, label what it visits with the expert,
# retrain). The cheaper one used here: the collector **takes the car over** now and then (once per
# 20 s on average) and re-places it exactly as the evaluator does after a collision (one shared
# function, `evaluation.restart_state`), and some noise bursts brake. Below: the speeds of the
# dataset, of a dataset collected the old way (no take-overs, no braking bursts), and the speeds a
# driver that collides (the lane keeper of chapter 01, which ignores parked cars) and the expert
# visit in evaluation. We keep the evaluation as it is: restarting below cruise speed is what a
# car rejoining a highway does, and changing the test to suit the learner would be tuning the
# evaluation.

# %%
old_cfg = dataclasses.replace(
    DataConfig.for_profile(profile, "train"),
    restart_rate_per_s=0.0,
    noise=NoiseConfig(brake_share=0.0),
)
# as many samples as the dataset (a shorter drive would over-weight the 20 m/s starts); stored
# for chapter 07, which trains a GMM on it
old_way = load_or_collect(old_cfg, name=f"train-{old_cfg.n_samples}-old-way")
keeper_ev = dataclasses.replace(ev, miles=min(ev.miles, 20.0))
res_keeper = evaluate(LaneKeeper(), world_cfg, keeper_ev, desc="lane keeper")
coverage = {
    "dataset (take-overs + braking bursts)": speed_histogram(train.speed),
    "dataset collected the old way": speed_histogram(old_way.speed),
    "visited by the lane keeper in evaluation": np.asarray(res_keeper.speed_hist),
    "visited by the expert in evaluation": np.asarray(res_expert.speed_hist),
}
slow_shares = {name: float(h[: int(SLOW_MPS)].sum() / h.sum()) for name, h in coverage.items()}
fig = Figure(figsize=(8.5, 3.6))
ax = fig.subplots()
edges = np.arange(SPEED_BINS + 1)
for (name, h), style in zip(coverage.items(), ("-", "--", "-", ":")):
    label = f"{name} ({slow_shares[name]:.1%} below {SLOW_MPS:g} m/s)"
    ax.stairs(h / h.sum(), edges, label=label, ls=style, lw=1.8)
ax.axvline(SLOW_MPS, color="0.5", lw=0.8)
ax.set(xlim=(12, 28), yscale="log", ylim=(1e-4, 1.2), xlabel="speed [m/s] (1 m/s bins)")
ax.set(ylabel="share of samples / decisions", title="speeds in the data and in closed loop")
ax.legend(fontsize=8, loc="upper left")
coverage_png = save_figure(fig, artifacts.artifact_path("figures", "04_speed_coverage.png"))
for name, share in slow_shares.items():
    print(f"{name:42s} {share:6.1%} below {SLOW_MPS:g} m/s")
print(f"saved {coverage_png}")

# %% [markdown]
# ## Headline figures

# %%
shares = train.info["shares"]
artifacts.write_metrics(
    "04_expert_and_data",
    {
        "profile": profile.name,
        "headline": {
            "expert collisions/100mi": res_expert.collisions_per_100mi,
            "oracle collisions/100mi": res_oracle.collisions_per_100mi,
            "train samples": len(train),
        },
        "expert": res_expert.to_dict(),
        "oracle": res_oracle.to_dict(),
        "expert_manoeuvres": manoeuvres,
        "scene_sides": {"left": sides.count(1), "right": sides.count(-1)},
        "slow_shares": slow_shares,
        "train": {k: v for k, v in train.info.items() if k != "collision_events"},
        "val": {k: v for k, v in val.info.items() if k != "collision_events"},
    },
    figures=(strip_png, both_png, samples_png, hist_png, coverage_png),
)
print(
    "| driver | miles | collisions | per 100 mi [95% CI] | mph |\n|---|---:|---:|---:|---:|\n"
    + "\n".join(
        f"| {name} | {r.miles:.3g} | {r.collisions} | {r.collisions_per_100mi:.1f} "
        f"[{r.ci95_per_100mi[0]:.1f}-{r.ci95_per_100mi[1]:.1f}] | {r.mean_speed_mph:.1f} |"
        for name, r in (
            ("expert (ceiling)", res_expert),
            ("oracle (LQR on expert trajectories)", res_oracle),
        )
    )
)
back = f", return {shares['return']:.1%}" if shares["return"] else ""  # (the expert keeps its lane)
print(
    f"\ndataset: {len(train)} train / {len(val)} val samples; curves {shares['curve']:.1%}, "
    f"lane changes {shares['lane_change']:.1%} (left {shares['overtake_left']:.1%}, right "
    f"{shares['overtake_right']:.1%}{back}), "
    f"noise {shares['noise']:.1%}"
)

# %% [markdown]
# ## Summary
#
# * A privileged state machine on the LQR tracker drives the test tracks without a
#   collision: that is the ceiling every learned driver is compared with.
# * The oracle, the tracker following the expert's own 5-point trajectories, drives them too; the
#   verdict line above says whether a 5-point plan and a controller lose anything against the
#   expert, and whatever they lose, a network predicting such a plan loses too.
# * Randomised triggers, durations and sides make the data multi-modal: the same parked car is
#   passed on the left in some samples and on the right in others.
# * Noise bursts put off-centre states and recoveries into the data; the labels stay what the
#   expert would do, not what the noisy car did.
# * A driver that collides visits states the expert shows less often (covariate shift): here,
#   restarts below cruise speed (section 6's lane keeper stands in for a learned driver).
#   Take-overs that re-place the car as the evaluator does, and braking bursts, put those states
#   and the expert's way out of them into the data.
# * Curves and lane changes are minorities of the data (the shares printed above), the
#   situations the later chapters (GMM, CVaR) are about.
#
# ## Exercises
#
# 1. Set `ExpertConfig(trigger_m=(25.0, 35.0))`. Does the expert still drive without collisions?
#    What does `_change_length` do with such short triggers, and what does the expert do instead?
# 2. Make the side coin always pick the left (`coin=0.0` in `Expert.draws`). Which share in the
#    dataset statistics changes, and what would a network trained on it never learn?
# 3. Collect a dataset with `NoiseConfig(rate_per_s=0.0)`. Compare the distribution of the
#    `center_offset_m` affordance with and without noise. Which states are missing without it?
# 4. The oracle re-plans every 0.1 s. Make it re-plan every 0.3 s (hold the label for three
#    decisions). Does it still drive? What does that say about a network's inference budget?
# 5. Collect with `DataConfig(restart_rate_per_s=0.0)` and with `0.2`. How do the shares below
#    22 m/s move? Why can too many take-overs hurt (what share of the data is then the few
#    seconds after a restart)?
