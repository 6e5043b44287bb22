# %% [markdown]
# # 03 · LQR tracking
#
# The paper's networks do not steer. They predict **where the car should be** over the next
# 1.5 s, five points 0.3 s apart, and a controller makes the car go there: "We implemented the
# commonly used LQR controller to follow the trajectory" (seed 000, section 3.1). This chapter
# builds that controller. Every trajectory-predicting driver of chapters 06-11 drives through it.
#
# **You will learn**
# 1. the lateral error model of the kinematic bicycle, linearised around a path;
# 2. how `control.c2d` and `control.dlqr` turn it into a gain, and why the gain depends on speed;
# 3. how a table of gains over speeds replaces solving a Riccati equation in the loop;
# 4. how a 5-point trajectory becomes a lateral error, a heading error, a curvature and a speed;
# 5. that the tracker drives: recovery, a lane change, a curve, and a whole obstacle-free track.
#
# Run it with `python chapters/03_lqr_tracking.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(3)  # flags, profile, outputs folder: checked before any work

import math
import timeit

import control
import numpy as np
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.control.tracker import (
    LaneChangePath,
    LQRTracker,
    TrackerConfig,
    follow_trajectory,
    gain_table,
    lane_reference,
    lateral_model,
    trajectory_reference,
)
from e2e_lite.driving.evaluation import Actuation, EvalConfig, Observation, evaluate
from e2e_lite.driving.figures import save_figure
from e2e_lite.learning.labels import POINT_DT_S
from e2e_lite.simulation.geometry import Track
from e2e_lite.simulation.vehicle import VehicleParams, bicycle_step, make_state
from e2e_lite.simulation.world import SimConfig, TrafficConfig, WorldConfig

veh = VehicleParams()
SIM = SimConfig()  # physics every SIM.dt_s, a decision every SIM.steps_per_policy physics steps
cfg = TrackerConfig(period_s=SIM.policy_period_s)  # discretised at the policy period
tracker = LQRTracker(cfg, veh)
print(
    f"wheelbase {veh.wheelbase_m} m, policy period {cfg.period_s} s "
    f"({SIM.steps_per_policy} physics steps of {SIM.dt_s} s)"
)

# %% [markdown]
# ## 1. The lateral error model
#
# Let `e` be the rear axle's lateral offset from the path (left positive) and `ψ` the heading
# error (car minus path). The kinematic bicycle at speed `v` with steering `δ` turns at
# `v tan δ / L`; the path turns at `v κ`. For small errors:
#
# $$\dot e = v\,\psi, \qquad \dot\psi = \frac{v}{L}\tan\delta - v\kappa
#   \;\approx\; \frac{v}{L}\,(\delta - \delta_{ff}), \qquad \delta_{ff} = \arctan(L\kappa).$$
#
# The **feed-forward** `δ_ff` steers the path's own curve; the feedback `u = δ - δ_ff` only
# corrects errors. With `x = (e, ψ)`: `ẋ = A x + B u`, `A = [[0, v], [0, 0]]`,
# `B = [[0], [v/L]]`. The policy holds its command for 0.1 s, so we discretise with a
# zero-order hold at that period.

# %%
v = 20.0
sysd = lateral_model(v, veh.wheelbase_m, cfg.period_s)
print("A_d =\n", np.round(sysd.A, 4), "\nB_d =\n", np.round(sysd.B, 5))
# by hand: exp(A dt) = I + A dt (A^2 = 0), B_d = [v^2 dt^2 / (2L), v dt / L]
a_hand = np.array([[1.0, v * cfg.period_s], [0.0, 1.0]])
b_hand = np.array(
    [[v**2 * cfg.period_s**2 / (2 * veh.wheelbase_m)], [v * cfg.period_s / veh.wheelbase_m]]
)
assert np.allclose(sysd.A, a_hand) and np.allclose(sysd.B, b_hand)

# %% [markdown]
# ## 2. The gain
#
# LQR minimises `Σ x'Qx + u'Ru`. Bryson's rule picks the weights from acceptable sizes:
# `Q = diag(1/e_max², 1/ψ_max²)`, `R = 1/δ_max²`, with `e_max = 1 m`, `ψ_max = 0.1 rad`,
# `δ_max = 0.01 rad`. `control.dlqr` solves the discrete Riccati equation and returns the gain `K`
# of `u = -K x` and the closed-loop eigenvalues.

# %%
q = np.diag([1 / cfg.lateral_max_m**2, 1 / cfg.heading_max_rad**2])
r = np.array([[1 / cfg.steer_max_rad**2]])
k20, _, poles20 = control.dlqr(sysd.A, sysd.B, q, r)
print(f"K(20 m/s) = {np.round(k20, 4)}  (steer per metre, per radian)")
print(f"closed-loop eigenvalues {np.round(poles20, 4)}, |z| = {np.abs(poles20).round(4)}")

# %% [markdown]
# ### The Riccati recursion, by hand
#
# What `dlqr` solves. `P` is the cost-to-go matrix: from state `x`, driving optimally costs
# `x'Px`. Going back one step from the end of a long horizon,
#
# * the gain that is optimal against that cost-to-go: `K = (R + B'PB)⁻¹ B'PA`;
# * the cost-to-go one step earlier: `P ← Q + A'P(A - BK)` (this step's cost, then the rest);
#
# starting from `P = Q` (the last step costs only its state). Iterated until `P` stops changing,
# `K` is the infinite-horizon gain.

# %%
a_d, b_d = sysd.A, sysd.B
cost_to_go, previous, sweeps = q.copy(), np.zeros_like(q), 0  # P = Q
while np.max(np.abs(cost_to_go - previous)) > 1e-12 * np.max(np.abs(cost_to_go)):
    # K = (R + B'PB)^-1 B'PA
    k_hand = np.linalg.solve(r + b_d.T @ cost_to_go @ b_d, b_d.T @ cost_to_go @ a_d)
    # P <- Q + A'P(A - BK)
    previous, cost_to_go = cost_to_go, q + a_d.T @ cost_to_go @ (a_d - b_d @ k_hand)
    sweeps += 1
print(f"by hand, after {sweeps} sweeps: K = {np.round(k_hand, 4)}")
assert np.allclose(k_hand, k20, rtol=1e-6), (k_hand, k20)
print("equal to control.dlqr's gain (to 1e-6)")

# %% [markdown]
# The model depends on v, so the gain does too. One dlqr solve is fine once per speed of a grid,
# and slow for every car at every decision (both are timed below): the tracker precomputes a
# table and interpolates it.

# %%
speeds, gains, poles = gain_table(cfg, veh.wheelbase_m)
print(f"gain table: {len(speeds)} speeds from {speeds[0]} to {speeds[-1]} m/s")
for vv in (5.0, 10.0, 20.0, 30.0, 40.0):
    k = tracker.gain(np.array([vv]))[0]
    print(f"  v = {vv:4.0f} m/s: K = ({k[0]:.4f} rad/m, {k[1]:.4f} rad/rad)")
t_dlqr = min(timeit.repeat(lambda: control.dlqr(sysd.A, sysd.B, q, r), number=20, repeat=3)) / 20
t_table = min(timeit.repeat(lambda: tracker.gain(np.full(32, 23.4)), number=200, repeat=3)) / 200
print(f"one dlqr solve {t_dlqr * 1e3:.2f} ms; the table's gains for 32 cars {t_table * 1e6:.0f} us")
max_pole = float(np.abs(poles).max())
print(f"largest |eigenvalue| over the grid: {max_pole:.4f} (< 1: stable at every speed)")

fig = Figure(figsize=(10, 3.6))
ax1, ax2 = fig.subplots(1, 2)
ax1.plot(speeds, gains[:, 0], label="K_e [rad/m]")
ax1.plot(speeds, gains[:, 1] / 10, label="K_ψ / 10 [rad/rad]")
ax1.set(xlabel="speed [m/s]", title="LQR gains over speed")
ax1.legend()
theta = np.linspace(0, 2 * np.pi, 200)
ax2.plot(np.cos(theta), np.sin(theta), color="0.6", lw=0.8)
sc = ax2.scatter(
    poles.real.ravel(), poles.imag.ravel(), c=np.repeat(speeds, 2), s=8, cmap="viridis"
)
fig.colorbar(sc, ax=ax2, label="speed [m/s]")
ax2.set(xlim=(0.5, 1.05), ylim=(-0.3, 0.3), aspect="equal", xlabel="real", ylabel="imaginary")
ax2.set_title("closed-loop poles (unit circle)")
gains_png = save_figure(fig, artifacts.artifact_path("figures", "03_gains.png"))
print(f"saved {gains_png}")

# %% [markdown]
# ## 3. Recovering from an offset
#
# A car starts 1 m left of a straight line at three speeds. The error model is the same in
# *distance* at every speed (with `s = vt`, `e'' = v² δ / L` is `d²e/ds² = δ / L`), and the gain
# per metre and per radian barely changes with speed (printed above), so the tracker settles
# within about the same distance: faster in time at higher speed.


# %%
def drive_offset(speed: float, offset: float = 1.0, seconds: float = 8.0) -> np.ndarray:
    """Lateral position [m] every 0.1 s of a car starting ``offset`` m left of the line y = 0."""
    st = make_state(0.0, offset, 0.0, speed)
    ys = [offset]
    for _ in range(int(seconds / cfg.period_s)):
        steer = tracker.steer(st[:, 1], st[:, 2], np.zeros(1), st[:, 3])
        for _ in range(SIM.steps_per_policy):
            bicycle_step(st, steer, np.zeros(1), veh, SIM.dt_s)
        ys.append(float(st[0, 1]))
    return np.array(ys)


fig = Figure(figsize=(10, 3.4))
ax1, ax2 = fig.subplots(1, 2)
settle = {}
for speed in (10.0, 20.0, 30.0):
    ys = drive_offset(speed)
    t = np.arange(len(ys)) * cfg.period_s
    above = np.flatnonzero(np.abs(ys) >= 0.1)
    settle[speed] = float(t[above[-1] + 1])
    ax1.plot(t, ys, label=f"{speed:.0f} m/s")
    ax2.plot(t * speed, ys, label=f"{speed:.0f} m/s")
    print(
        f"{speed:4.0f} m/s: |e| < 0.1 m after {settle[speed]:.1f} s ({settle[speed] * speed:.0f} m); "
        f"overshoot {max(0.0, -ys.min()):.3f} m"
    )
ax1.set(xlabel="time [s]", ylabel="lateral error [m]", title="recovery from 1 m")
ax2.set(xlabel="distance [m]", title="the same, over distance")
for ax in (ax1, ax2):
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.axhline(-1.85, color="C3", lw=0.8, ls="--")
    ax.legend()
ax1.text(0.2, -1.75, "next lane's marking", color="C3", fontsize=8)
recovery_png = save_figure(fig, artifacts.artifact_path("figures", "03_recovery.png"))

# %% [markdown]
# ## 4. A lane change on a curve
#
# A lane change is a lateral path in the lane frame: `d(s) = d₀ + (d₁ - d₀) b(u)`, with the
# quintic `b(u) = 10u³ - 15u⁴ + 6u⁵` (zero slope and curvature at both ends). Following it, the
# reference lateral error is `d - d_ref(s)`, the heading error `ψ - atan d'_ref`, and the curvature
# the lane's plus `d''_ref`. Its peak lateral acceleration is `5.77 Δd v² / ℓ²`: at 25 m/s a
# 3.7 m change over 60 m needs 3.7 m/s².

# %%
curve = Track([0.0], [0.0], [0.0], [1 / 300], [700.0])
x0, y0, h0 = curve.pose(10.0, 0.0)
st = make_state(float(x0), float(y0), float(h0), 20.0)
path = LaneChangePath(s_start=80.0, length_m=70.0, d_from=0.0, d_to=3.7)
rows = []
for _ in range(150):
    s_arr, d_arr = curve.to_frenet(st[:, 0], st[:, 1])
    s_now, d_now = float(s_arr[0]), float(d_arr[0])
    he = float(st[0, 2] - curve.heading(s_now))
    e, psi, kap = path.reference(s_now, d_now, he, 1 / 300)
    steer = tracker.steer(np.array([e]), np.array([psi]), np.array([kap]), st[:, 3])
    rows.append((s_now, d_now, path.offset(s_now)[0], float(steer[0])))
    for _ in range(SIM.steps_per_policy):
        bicycle_step(st, steer, np.zeros(1), veh, SIM.dt_s)
rows = np.array(rows)
lc_err = float(np.abs(rows[:, 1] - rows[:, 2]).max())
print(f"lane change on a 300 m curve at 20 m/s: worst tracking error {lc_err:.3f} m")

fig = Figure(figsize=(10, 3.2))
ax1, ax2 = fig.subplots(1, 2)
ax1.plot(rows[:, 0], rows[:, 2], "--", label="path d_ref(s)")
ax1.plot(rows[:, 0], rows[:, 1], label="driven d(s)")
ax1.set(xlabel="s [m]", ylabel="d [m]", title="lane change on a left curve (R = 300 m)")
ax1.legend()
ax2.plot(rows[:, 0], np.degrees(rows[:, 3]))
ax2.axhline(
    math.degrees(math.atan(veh.wheelbase_m / 300)),
    color="0.5",
    ls=":",
    label="curve's feed-forward",
)
ax2.set(xlabel="s [m]", ylabel="steering [deg]", title="steering command")
ax2.legend()
lane_change_png = save_figure(fig, artifacts.artifact_path("figures", "03_lane_change.png"))

# %% [markdown]
# ## 5. Following a 5-point trajectory
#
# The networks output 5 points `(x, y)` in the car frame at `t = 0.3, 0.6, ..., 1.5 s`. The
# tracker needs `(e, ψ, κ)` and a speed. The conversion (`trajectory_reference`): put the origin
# (the car now, `t = 0`) in front of the points, fit `x(t)` and `y(t)` each with a cubic in `t` by
# least squares, and read the fit at `t = 0`:
#
# $$e = -y(0),\quad \psi = -\operatorname{atan2}(\dot y, \dot x),\quad
#   \kappa = \frac{\dot x \ddot y - \dot y \ddot x}{(\dot x^2 + \dot y^2)^{3/2}},\quad
#   v_{ref} = \sqrt{\dot x^2 + \dot y^2}.$$
#
# The six sample times are the same for every trajectory, so the fit is one fixed 4 x 6 matrix
# applied to a whole batch. Below: a left curve of radius 80 m at 15 m/s, written as five points.

# %%
radius, speed = 80.0, 15.0
t_pts = np.arange(1, 6) * POINT_DT_S
ang = speed * t_pts / radius
pts = np.stack([radius * np.sin(ang), radius * (1 - np.cos(ang))], axis=-1)
e, psi, kap, v_ref, a_ref = trajectory_reference(pts)
print(
    f"5 points on R = {radius} m at {speed} m/s -> kappa {kap:.5f} (1/R = {1 / radius:.5f}), v_ref {v_ref:.2f} m/s"
)
st = make_state(0.0, 0.0, 0.0, speed)
driven = [st[0, :2].copy()]
for _ in range(int(6.0 / cfg.period_s)):
    # a network re-predicts every 0.1 s; here it always predicts the same curve in its own frame
    steer, accel = follow_trajectory(tracker, pts[None], st[:, 3])
    for _ in range(SIM.steps_per_policy):
        bicycle_step(st, steer, accel, veh, SIM.dt_s)
    driven.append(st[0, :2].copy())
driven = np.array(driven)
radial_err = float(np.abs(np.hypot(driven[:, 0], driven[:, 1] - radius) - radius).max())
print(f"driven for 6 s: worst distance from the circle {radial_err:.3f} m")

fig = Figure(figsize=(5.5, 4.2))
ax = fig.subplots()
circ = np.linspace(0, speed * 6.0 / radius, 200)
ax.plot(
    radius * np.sin(circ), radius * (1 - np.cos(circ)), color="0.6", lw=3, label="circle R = 80 m"
)
ax.plot(driven[:, 0], driven[:, 1], label="driven")
ax.scatter(pts[:, 0], pts[:, 1], color="C3", zorder=3, label="the 5 points (first plan)")
ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal", title="following a 5-point trajectory")
ax.legend()
trajectory_png = save_figure(fig, artifacts.artifact_path("figures", "03_trajectory.png"))

# %% [markdown]
# ## 6. A whole track, closed loop
#
# A lane-centre follower built on the tracker, driven through the evaluator on test tracks
# **without parked cars**: it should never touch a rail. It records the lateral error at every
# decision.


# %%
class LaneCentreFollower:
    """Follows the centre of the lane it (re)spawned in at a constant speed, with the LQR tracker."""

    camera = None

    def __init__(self, speed_mps: float = 25.0) -> None:
        self.speed_mps = speed_mps
        self.errors: list[np.ndarray] = []

    def reset(self, n_worlds: int) -> None:
        self.lane = np.zeros(n_worlds, dtype=np.int64)

    def act(self, obs: Observation) -> Actuation:
        self.lane = np.where(obs.respawned, obs.lane, self.lane)
        track = obs.worlds[0].track
        e, psi, kap = lane_reference(
            obs.d, obs.heading_error, obs.curvature, track.lane_center(self.lane)
        )
        self.errors.append(e)
        return Actuation(
            tracker.steer(e, psi, kap, obs.speed), tracker.accel(obs.speed, self.speed_mps)
        )


empty_roads = WorldConfig.for_profile(profile)
empty_roads = WorldConfig(road=empty_roads.road, traffic=TrafficConfig(n_cars=(0, 0)))
miles = 5.0 if profile.quick else 50.0
follower = LaneCentreFollower()
res = evaluate(
    follower,
    empty_roads,
    EvalConfig(miles=miles, n_worlds=profile.n_worlds),
    desc="LQR lane centre",
)
errs = np.concatenate(follower.errors)
rms_cm = float(np.sqrt(np.mean(errs**2)) * 100)
max_cm = float(np.abs(errs).max() * 100)
print(res.summary())
print(f"lateral error: RMS {rms_cm:.1f} cm, max {max_cm:.1f} cm over {len(errs):,} decisions")

# %% [markdown]
# ## Headline figures

# %%
artifacts.write_metrics(
    "03_lqr_tracking",
    {
        "profile": profile.name,
        "headline": {
            "collisions/100mi (no parked cars)": res.collisions_per_100mi,
            "lateral RMS [cm]": rms_cm,
        },
        "gains": {"speeds_mps": speeds.tolist(), "K": gains.tolist(), "max_abs_pole": max_pole},
        "settle_s_from_1m": settle,
        "lane_change_max_error_m": lc_err,
        "trajectory_max_radial_error_m": radial_err,
        "lane_centre": {
            **res.to_dict(with_events=False),
            "lateral_rms_cm": rms_cm,
            "lateral_max_cm": max_cm,
        },
    },
    figures=(gains_png, recovery_png, lane_change_png, trajectory_png),
)
print(
    "| driver | miles | collisions | lateral RMS | mph |\n|---|---:|---:|---:|---:|\n"
    f"| LQR lane centre (no parked cars) | {res.miles:.3g} | {res.collisions} | {rms_cm:.1f} cm | "
    f"{res.mean_speed_mph:.1f} |"
)

# %% [markdown]
# ## Summary
#
# * Around a path the kinematic bicycle is a double integrator in the lateral error; curvature is
#   handled by feed-forward `atan(Lκ)`, so LQR only corrects errors.
# * `control.c2d` + `control.dlqr` give a gain per speed (`dlqr` iterates the Riccati recursion
#   `K = (R + B'PB)⁻¹B'PA`, `P ← Q + A'P(A - BK)` to its fixed point; section 2 does it by hand);
#   a precomputed table interpolated at run time costs a small part of one `dlqr` solve (both
#   timed in section 2).
# * The same tracker follows lane centres, lane-change paths and the networks' 5-point
#   trajectories (a fixed least-squares cubic turns points into error, heading, curvature, speed).
# * On obstacle-free test tracks it drives without touching a rail; what remains is to say
#   *where* to drive: the expert (chapter 04), then the networks.
#
# ## Exercises
#
# 1. Double `steer_max_rad` in `TrackerConfig` (a cheaper control effort). How do the settling
#    distance and the overshoot of section 3 change? Where do the poles move?
# 2. Remove the feed-forward (`atan(Lκ)`) from `LQRTracker.steer`. What steady error does the
#    tracker keep on the 300 m curve, and why can't the two-state LQR remove it?
# 3. The conversion reads the fit at `t = 0`. Try `preview_s = 0.2` in `follow_trajectory` on the
#    curve of section 5. What changes, and when would a preview help a network's noisy output?
# 4. Fit a quadratic instead of a cubic (edit `_fit_matrix`'s degree). Which of the tests in
#    `tests/test_tracker.py` still pass?
