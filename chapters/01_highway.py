# %% [markdown]
# # 01 · The highway
#
# The paper (Glassner et al., 2019) judged every driver the same way: let it drive, closed loop,
# on tracks it never saw, and count **collisions per 100 miles**. Before any learning, this
# chapter builds the world that count is taken in, and shows that the count depends as much on
# what a driver sees and does as on the road.
#
# **You will learn**
# 1. how a procedural highway is made of straights and arcs, and named by a lane frame `(s, d)`;
# 2. how a kinematic bicycle moves, and why it is simulated as a pymunk kinematic body;
# 3. how collisions are counted exactly once, and what happens after one;
# 4. how the closed-loop evaluator turns a drive into collisions per 100 miles with an honest
#    confidence interval.
#
# Run it with `python chapters/01_highway.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(1)  # flags, profile, outputs folder: checked before any work

import math

import numpy as np

import e2e_lite
from e2e_lite import artifacts
from e2e_lite.control.drivers import LaneChanger, LaneKeeper
from e2e_lite.driving.evaluation import EvalConfig, evaluate, miles_text
from e2e_lite.driving.figures import highway_figure, save_figure
from e2e_lite.simulation.geometry import generate_track
from e2e_lite.simulation.world import WorldConfig, make_world
from e2e_lite.stats.rates import poisson_ci

world_cfg = WorldConfig.for_profile(profile)
print(
    f"e2e-lite {e2e_lite.__version__}, {profile.name} profile: tracks of "
    f"{profile.track_length_m / 1000:.0f} km, {miles_text(profile.eval_miles)} per driver"
)

# %% [markdown]
# ## 1. A road is a chain of straights and arcs
#
# A highway is mostly straight. Our generator opens with a straight (where cars start) and then
# alternates straights of 300-1200 m with arcs of radius 200-900 m turning 10-50°, left or right
# at random, keeping the heading within ±60° of the start so a track never turns back on itself.
# Curves are the minority of the distance, rare events of one kind (chapter 09's table of the
# worst samples says which situations a learned driver finds hardest).
#
# Every point is named by its **lane frame** coordinates: arc length `s` along the road's centre
# line and signed offset `d` to the left. On an arc of curvature `k` starting at `p0` with heading
# `h0`, the centre line is
#
# $$h(u) = h_0 + k u, \qquad p(u) = p_0 + \Big(\tfrac{\sin h - \sin h_0}{k},\; \tfrac{\cos h_0 - \cos h}{k}\Big)$$
#
# and the point at offset `d` lies `d` along the left normal `(-sin h, cos h)`. Going back, from a
# world point to `(s, d)`, is one `atan2` per arc: no search over thousands of samples.

# %%
track = generate_track(world_cfg.road, "test", 0)
print(
    f"track {track.track_id}: {track.length:.0f} m in {len(track.k)} segments, "
    f"{track.curve_share():.0%} of it on arcs, {track.n_lanes} lanes of {track.lane_width} m"
)

# A teaching version of the inverse for one arc, checked against the library.
arc = int(np.flatnonzero(track.k != 0)[0])
s_true, d_true = track.s0[arc] + 0.4 * track.seg_len[arc], 2.5
x, y = track.position(s_true, d_true)
k, h0 = track.k[arc], track.h0[arc]
cx, cy = track.x0[arc] - math.sin(h0) / k, track.y0[arc] + math.cos(h0) / k  # arc centre
h = math.atan2(y - cy, x - cx) + math.copysign(math.pi / 2, k)  # heading at the foot point
s_hand = track.s0[arc] + ((h - h0 + math.pi) % (2 * math.pi) - math.pi) / k
d_hand = 1 / k - math.copysign(1, k) * math.hypot(x - cx, y - cy)
s_lib, d_lib = track.to_frenet(x, y)
print(
    f"by hand: s={s_hand:.6f} d={d_hand:.6f};  library: s={float(s_lib):.6f} d={float(d_lib):.6f}"
)
assert abs(s_hand - s_lib) < 1e-6 and abs(d_hand - d_lib) < 1e-6

# %% [markdown]
# ## 2. Parked cars and guard rails
#
# As in the paper, 20 to 80 parked cars stand on each track, 50 to 200 m apart, each in a random
# lane; since consecutive cars are at least 50 m apart, a place never has every lane blocked.
# Guard rails run along both road edges a shoulder further out, so leaving the road is a
# collision too. In pymunk the rails are static segments and the cars static boxes. The ego car
# is a **kinematic** body: the bicycle model says where it goes, and pymunk only tells us when it
# touches something (a callback registered with `Space.on_collision`).

# %%
world = make_world(world_cfg, "test", 0)  # the first road the evaluator drives
print(
    f"{len(world.cars)} parked cars, {len(world.space.shapes)} pymunk shapes "
    f"(rail segments + cars + ego)"
)
gaps = np.diff(world.cars.s)
print(
    f"gaps between cars: {gaps.min():.0f}-{gaps.max():.0f} m; lanes used: "
    f"{np.bincount(world.cars.lane, minlength=track.n_lanes).tolist()}"
)

# %% [markdown]
# ## 3. The car: a kinematic bicycle
#
# The state is rear-axle position, heading `h`, speed `v` and road-wheel angle `δ`:
#
# $$\dot x = v\cos h,\quad \dot y = v \sin h,\quad \dot h = \frac{v \tan\delta}{L}.$$
#
# Each physics step (50 Hz, as the paper's simulator) moves the car along the chord of the arc
# it drives, which is exact at constant steering: a fixed `δ` traces a circle of radius
# `L / tan δ`. Let us check that on the library's model.

# %%
from e2e_lite.simulation.vehicle import VehicleParams, bicycle_step, make_state

car = VehicleParams()
state = make_state(0.0, 0.0, 0.0, speed=15.0, steer=0.1)
radius = car.wheelbase_m / math.tan(0.1)
points = []
for _ in range(400):  # 8 s, more than one lap
    bicycle_step(state, np.array([0.1]), np.array([0.0]), car, 0.02)
    points.append(state[0, :2].copy())
r_measured = np.hypot(np.array(points)[:, 0], np.array(points)[:, 1] - radius)
print(f"L/tan(δ) = {radius:.4f} m; driven radius {r_measured.min():.4f}-{r_measured.max():.4f} m")

# %% [markdown]
# ## 4. Two scripted drivers
#
# Both steer with the same proportional law on the lane frame (speed-scheduled gains plus a
# curvature feed-forward; `e2e_lite/control/drivers.py`) and cruise at 25 m/s (56 mph).
#
# * the **lane keeper** follows the centre of its lane and sees nothing else;
# * the **lane changer** also asks the world (a pymunk range query) for the gap to the next parked
#   car in its lane, and moves to a free neighbouring lane when that gap falls under 70 m.
#
# The evaluator drives each on the same unseen test tracks, B cars at once, until the
# budget of miles is spent. After a collision the car is put back 15 m past the obstacle on the
# nearest free lane centre, aligned with the road, and driving goes on.

# %%
eval_cfg = EvalConfig(miles=profile.eval_miles, n_worlds=profile.n_worlds)
results = {}
for name, driver in (("lane keeper", LaneKeeper()), ("lane changer", LaneChanger())):
    results[name] = evaluate(driver, world_cfg, eval_cfg, desc=name, record_traces=True)
    print(f"{name:13s} {results[name].summary()}")

# %% [markdown]
# ## 5. Where they went
#
# The top map is the whole test track (colour = curvature, red dots = parked cars). Below,
# a zoomed stretch: the lane keeper's path ends in collisions (yellow crosses) while the lane
# changer weaves around the same cars.

# %%
key = "-".join(map(str, track.track_id))
s_from = float(world.cars.s[0]) - 80.0
s_range = (s_from, s_from + 320.0)
paths = []
for (name, res), color in zip(results.items(), ("tab:blue", "tab:orange")):
    xy = np.array(res.traces.get(key, [[np.nan, np.nan]]))
    s_path, _ = track.to_frenet(xy[:, 0], xy[:, 1])
    paths.append((name, xy[(s_path >= s_range[0]) & (s_path <= s_range[1])], color))
crashes = [
    (e["x_m"], e["y_m"])
    for e in results["lane keeper"].events
    if tuple(e["track"]) == track.track_id and s_range[0] <= e["s_m"] <= s_range[1]
]
fig = highway_figure(track, world.cars, s_range, paths=paths, crashes=crashes)
png = save_figure(fig, artifacts.artifact_path("figures", "01_highway.png"))
print(f"figure: {png}")

# %% [markdown]
# ## 6. How sure is a count?
#
# Collisions are rare, random events: a count `k` over `m` miles is a Poisson sample. The exact
# (Garwood) 95 % interval of the rate uses the chi-square quantiles
# `[χ²(0.025; 2k) / 2, χ²(0.975; 2k + 2) / 2] / m`. Even **zero collisions in 100 miles** leaves
# an interval reaching a few collisions per 100 miles (the cell below prints it): this is why
# the ablation (chapter 10) drives hundreds of miles per row, over several training seeds.

# %%
for k_col, m in ((0, 100.0), (0, 500.0), (1, 100.0), (10, 100.0)):
    lo, hi = poisson_ci(k_col, m / 100.0)
    print(f"{k_col:3d} collisions in {m:5.0f} mi -> 95% CI {lo:5.2f}-{hi:5.2f} per 100 mi")

# %% [markdown]
# ## Headline figure

# %%
headline = {f"{name} collisions/100mi": res.collisions_per_100mi for name, res in results.items()}
headline.update({f"{name} mph": res.mean_speed_mph for name, res in results.items()})
artifacts.write_metrics(
    "01_highway",
    {
        "profile": profile.name,
        "headline": headline,
        "drivers": {name: res.to_dict(with_events=False) for name, res in results.items()},
    },
    figures=(png,),
)
print("| driver | miles | collisions | per 100 mi [95% CI] | mph | autonomy |")
print("|---|---:|---:|---|---:|---:|")
for name, res in results.items():
    lo, hi = res.ci95_per_100mi
    print(
        f"| {name} | {res.miles:.1f} | {res.collisions} | {res.collisions_per_100mi:.1f} "
        f"[{lo:.1f}-{hi:.1f}] | {res.mean_speed_mph:.1f} | {res.autonomy_pct:.1f}% |"
    )

# %% [markdown]
# ## Summary
#
# * A track is a chain of straights and arcs; the lane frame `(s, d)` is the one reference every
#   later layer (camera, tracker, expert, affordance labels) asks.
# * The car is a kinematic bicycle integrated exactly per step; pymunk is the referee that reports
#   contacts, each collision counted once (`tests/test_world.py`), followed by a documented
#   re-spawn.
# * The same road gives wildly different counts to drivers that see different things: the lane
#   keeper drives into the parked cars in its lane, the lane changer, with a 70 m look-ahead,
#   few or none.
#   A collision rate is a property of driver *and* world, and it comes with an interval.
# * Nothing moves in this world but the driven car: a car that drives beside its lane, or
#   straddles two, costs no collision here, where on a road with traffic it would. So the
#   course counts each driver's off-centre episodes beside its collisions (chapter 05's
#   autonomy; Table 1's last column).
#
# ## Exercises
#
# 1. Lower the lane changer's `trigger_m` until it starts to collide. What look-ahead does a lane
#    change at 25 m/s need with this steering law? (Hint: time the lateral move.)
# 2. Raise the lane keeper's natural frequency `wn_radps` to 3 rad/s. What happens on the arcs,
#    and why does the 10 Hz policy rate matter?
# 3. Make a track with `RoadConfig(radius_m=(60, 100))`. Which driver hits the rails, and why does
#    the curvature feed-forward alone not save it?
# 4. How many miles without a collision would you need to claim a rate below one per 100 miles
#    with 95 % confidence?
