# %% [markdown]
# # 02 · The camera
#
# The learned drivers of chapters 05-11 never see the world state: they see a **front camera**,
# as the paper's agents saw TORCS. This chapter builds that camera: a pinhole model, rasterised
# with OpenCV polygon fills, fast enough to render a frame for every car at every decision.
#
# **You will learn**
# 1. the pinhole model: intrinsics from the field of view, extrinsics from the car's pose;
# 2. why the sky is cropped and how the pitch puts the horizon at the top of the image;
# 3. how a rasteriser draws far to near, and why polygons must be clipped at a near plane;
# 4. how to draw a trajectory (the paper's output) on a camera frame;
# 5. what the network will see: a 66 x 200 image (PilotNet's size).
#
# Run it with `python chapters/02_camera.py` (add `--quick` for a run of seconds).

# %%
from e2e_lite.course.run import start_chapter

profile = start_chapter(2)  # flags, profile, outputs folder: checked before any work

import math
import time

import numpy as np
from matplotlib.figure import Figure

from e2e_lite import artifacts
from e2e_lite.driving.figures import save_figure
from e2e_lite.simulation.camera import Camera, CameraConfig
from e2e_lite.simulation.geometry import generate_track
from e2e_lite.simulation.raster import clip_near, draw_trajectory, save_image
from e2e_lite.simulation.topdown import render_topdown
from e2e_lite.simulation.world import ParkedCars, WorldConfig, make_world

world_cfg = WorldConfig.for_profile(profile)
cam = Camera()  # the network's camera: 66 x 200
human = Camera(CameraConfig.human())  # the same optics at 240 x 640, for people
print(f"network camera {cam.shape}, human camera {human.shape}")

# %% [markdown]
# ## 1. The pinhole model
#
# A camera maps a point in front of it to the pixel where the ray through the lens meets the
# image plane. In the camera frame (x right, y down, z along the optical axis):
#
# $$\text{col} = c_x + f_x \frac{x}{z}, \qquad \text{row} = c_y + f_y \frac{y}{z}, \qquad
#   f_x = f_y = \frac{W/2}{\tan(\text{hfov}/2)}.$$
#
# The camera sits 1.5 m ahead of the rear axle, 1.4 m above the road, pitched down by θ. A point
# `(f, l, u)` ahead, left and up of the lens has camera coordinates
# `z = f cos θ - u sin θ`, `y = -(f sin θ + u cos θ)`, `x = -l`.
#
# **The field of view is a design choice with consequences.** At 90° a 1.8 m wide car 60 m ahead
# (about where chapter 04's expert starts to overtake, its trigger drawn per manoeuvre) is a few
# pixels wide at 200 px (the cell below prints how many): barely there. We use 50°.

# %%
for hfov in (90.0, 50.0):
    f_px = (200 / 2) / math.tan(math.radians(hfov) / 2)
    print(
        f"hfov {hfov:4.0f} deg: f = {f_px:5.1f} px; a 1.8 m car at 60 m is {f_px * 1.8 / 60:.1f} px wide"
    )

# A ground point 20 m ahead and 1.85 m left of the rear axle, by hand:
fwd, left = 20.0, 1.85
f = fwd - cam.cfg.forward_offset_m
u = -cam.cfg.mount_height_m  # the road is below the lens
th = cam.pitch
z = f * math.cos(th) - u * math.sin(th)
y = -(f * math.sin(th) + u * math.cos(th))
col_hand, row_hand = cam.cx + cam.fx * (-left) / z, cam.cy + cam.fy * y / z
(col_lib, row_lib), _ = cam.project_car(np.array([fwd, left, 0.0]))
print(
    f"by hand: col {col_hand:.3f}, row {row_hand:.3f};  library: col {col_lib:.3f}, row {row_lib:.3f}"
)
assert abs(col_hand - col_lib) < 1e-9 and abs(row_hand - row_lib) < 1e-9

# %% [markdown]
# ## 2. Cropping the sky
#
# PilotNet fed its network only the part of the image below the horizon: the sky carries no
# information about where to drive. We get the same crop for free by pitching the camera down
# until the horizon (a point infinitely far ahead at lens height) sits near the top row:
# `row_h = c_y - f_y tan θ`, so `θ = atan((c_y - row_h) / f_y)`.

# %%
print(
    f"pitch {math.degrees(cam.pitch):.2f} deg down; horizon at row {cam.horizon_row():.2f} "
    f"of {cam.shape[0]}"
)
bottom_row_angle = cam.pitch + math.atan((cam.shape[0] - 1 - cam.cy) / cam.fy)
print(
    f"the bottom row sees the road {cam.cfg.mount_height_m / math.tan(bottom_row_angle):.1f} m "
    f"ahead of the lens"
)

# %% [markdown]
# ## 3. Drawing far to near, and the near plane
#
# The rasteriser is a painter: it copies a prebuilt background (sky and grass), then fills
# polygons from the ground up and from far to near: the shoulder, the road surface (a polygon
# between samples of the road's edges, so curves stay curved), the lane markings, the guard
# rails, and every car as a box whose visible faces are shaded differently, farthest car first.
#
# A polygon that reaches behind the camera cannot simply be projected: a vertex with `z <= 0`
# lands on the wrong side of the image, through infinity. Every polygon is first **clipped** at
# a near plane `z >= near` (Sutherland-Hodgman: walk the edges, keep the vertices in front, add
# the crossing point of each edge that crosses). Here is a road quad that starts behind the lens:

# %%
quad = np.array([[-2.0, 1.4, -3.0], [2.0, 1.4, -3.0], [2.0, 1.4, 10.0], [-2.0, 1.4, 10.0]])
print("clipped at z >= 0.3:\n", clip_near(quad, 0.3).round(3))

# %% [markdown]
# ## 4. A gallery of scenes
#
# Six situations a driver must read, each seen by the human-size camera and from above:
# a straight, a left and a right curve, a parked car ahead in the ego lane, cars in both
# neighbouring lanes, and the ego off-centre and rotated (what noise injection produces in
# chapter 04).


# %%
def first_arc(sign: float) -> tuple:
    """The first validation track with an arc turning to ``sign``, and that arc's index."""
    for index in range(50):
        track = generate_track(world_cfg.road, "val", index)
        arcs = np.flatnonzero(np.sign(track.k) == sign)
        if arcs.size:
            return track, int(arcs[0])
    raise RuntimeError("no such arc in the first 50 validation tracks")


straight = generate_track(world_cfg.road, "val", 0)
left_track, left_arc = first_arc(+1.0)
right_track, right_arc = first_arc(-1.0)
lane_w = straight.lane_width
s0 = 120.0  # on the opening straight
scenes = {
    "straight": (straight, None, s0, 0.0, 0.0),
    "left curve": (left_track, None, float(left_track.s0[left_arc]) + 15.0, 0.0, 0.0),
    "right curve": (right_track, None, float(right_track.s0[right_arc]) + 15.0, 0.0, 0.0),
    "car ahead in my lane": (
        straight,
        ParkedCars.on_track(straight, [s0 + 30.0], [0.0]),
        s0,
        0.0,
        0.0,
    ),
    "cars in both neighbours": (
        straight,
        ParkedCars.on_track(straight, [s0 + 18.0, s0 + 35.0], [lane_w, -lane_w]),
        s0,
        0.0,
        0.0,
    ),
    "off-centre and rotated": (
        straight,
        ParkedCars.on_track(straight, [s0 + 40.0], [lane_w]),
        s0,
        1.2,
        math.radians(-6.0),
    ),
}
# %%
fig = Figure(figsize=(12, 13))
axes = fig.subplots(len(scenes), 2, gridspec_kw={"width_ratios": [3.2, 1]})
for (name, (track, cars, s, d, yaw)), (ax_cam, ax_top) in zip(scenes.items(), axes):
    x, y, h = track.pose(s, d)
    pose = (float(x), float(y), float(h) + yaw)
    ax_cam.imshow(human.render(track, cars, pose, s))
    ax_top.imshow(render_topdown(track, cars, pose))
    ax_cam.set_title(name, loc="left")
    for ax in (ax_cam, ax_top):
        ax.set_xticks([])
        ax.set_yticks([])
fig.tight_layout()
gallery = save_figure(fig, artifacts.artifact_path("figures", "02_camera_gallery.png"), dpi=80)
print(f"gallery: {gallery}")

# %% [markdown]
# ## 5. What the network sees, and a trajectory drawn on it
#
# The same scene at the network's 66 x 200 and at 240 x 640. The paper's networks output a
# trajectory: 5 points (x forward, y left) in the car frame, 0.3 s apart. `draw_trajectory`
# projects such points onto the road in the image (paper Fig. 2); the top-down view shows the
# same points from above. Here a made-up lane change at 25 m/s, to the free neighbouring lane.

# %%
world = make_world(world_cfg, "val", 0)
lane = int(world.cars.lane[0])
s_view = float(world.cars.s[0]) - 45.0
pose = tuple(float(v) for v in world.track.pose(s_view, world.track.lane_center(lane)))
t_pts = 0.3 * np.arange(1, 6)
side = 1.0 if lane < world.track.n_lanes - 1 else -1.0  # +1: to the left
lateral = side * lane_w * (1 - np.cos(np.pi * t_pts / 1.5)) / 2
plan = np.stack([25.0 * t_pts, lateral], axis=1)  # (5, 2) [m]
small = cam.render(world.track, world.cars, pose, s_view)
big = draw_trajectory(
    human.render(world.track, world.cars, pose, s_view), plan, human, label="plan"
)
top = render_topdown(world.track, world.cars, pose, trajectory=plan)
fig = Figure(figsize=(12, 3.2))
ax_small, ax_big, ax_top = fig.subplots(1, 3, gridspec_kw={"width_ratios": [2.2, 2.2, 0.8]})
for ax, img, title in (
    (ax_small, small, "network: 66 x 200"),
    (ax_big, big, "human: 240 x 640"),
    (ax_top, top, "top-down"),
):
    ax.imshow(img)
    ax.set_title(title)
    ax.set_xticks([])
    ax.set_yticks([])
fig.tight_layout()
sizes_png = save_figure(fig, artifacts.artifact_path("figures", "02_camera_sizes.png"), dpi=90)
save_image(artifacts.artifact_path("figures", "02_network_frame.png"), small)
print(f"figure: {sizes_png}")

# %% [markdown]
# ## 6. How fast?
#
# The evaluator asks for a frame for each of its B cars at every decision, so the camera renders
# a whole batch at once: the geometry of all frames is a handful of array operations and only
# the polygon fills run per frame. `python -m e2e_lite.course.bench camera` measures busy curved scenes;
# here a shorter measurement on the gallery's scenes.

# %%
frames = list(scenes.values())
tracks = [sc[0] for sc in frames] * 3
cars = [sc[1] for sc in frames] * 3
poses = np.array([sc[0].pose(sc[2], sc[3]) + np.array([0.0, 0.0, sc[4]]) for sc in frames] * 3)
s_arr = np.array([sc[2] for sc in frames] * 3)
out = cam.render_batch(tracks, cars, poses, s_arr)
reps = 5 if profile.quick else 50
t0 = time.perf_counter()
for _ in range(reps):
    cam.render_batch(tracks, cars, poses, s_arr, out=out)
fps = reps * len(poses) / (time.perf_counter() - t0)
print(f"66 x 200: {fps:,.0f} frames per second (batches of {len(poses)})")

# %% [markdown]
# ## Headline figure

# %%
artifacts.write_metrics(
    "02_camera",
    {
        "profile": profile.name,
        "headline": {"fps 66x200 (batched)": fps},
        "camera": {
            "hfov_deg": cam.cfg.hfov_deg,
            "pitch_deg": math.degrees(cam.pitch),
            "horizon_row": cam.horizon_row(),
            "shape": list(cam.shape),
        },
    },
    figures=(gallery, sizes_png),
)
print(f"| camera | frames/s |\n|---|---:|\n| 66 x 200, batches of {len(poses)} | {fps:,.0f} |")

# %% [markdown]
# ## Summary
#
# * A pinhole camera is two matrices: intrinsics from the field of view and image size, and
#   extrinsics from the car's pose, the mount height and the pitch. Pitching down crops the sky.
# * The rasteriser fills polygons far to near; anything reaching behind the lens is clipped at a
#   near plane first, so nothing is projected through infinity.
# * At 50° a parked car 60 m ahead is about twice as wide in the image as at 90° (section 1
#   prints both): the driver can see what it must avoid. A trajectory in the car frame projects
#   onto the same image.
# * Images are RGB uint8 everywhere; convert to BGR only when OpenCV writes a file.
#
# ## Exercises
#
# 1. Set `hfov_deg=90` and look at the "car ahead" scene at 66 x 200. How many pixels does the car
#    cover at 60 m? What would that do to a network that must decide when to overtake?
# 2. Turn on `CameraConfig(augment=True)` and render the gallery with a seeded generator. Which
#    of the jitters would you expect to help a network generalise to unseen tracks?
# 3. Comment out the near-plane clipping in `Camera._car_faces` and render the "off-centre and
#    rotated" scene with a car beside the ego. What goes wrong, and why?
# 4. Rails are drawn before all cars. Construct a curve where this is visibly wrong, and propose
#    a drawing order that fixes it at little cost.
