"""The rasterised front camera: pinhole geometry, visibility, near-plane clipping, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import straight_world

from e2e_lite.simulation.camera import Camera, CameraConfig
from e2e_lite.simulation.geometry import RoadConfig, generate_track
from e2e_lite.simulation.raster import MARKING, ROAD, SHOULDER, SKY, clip_near, draw_trajectory
from e2e_lite.simulation.topdown import TopDownConfig, render_topdown
from e2e_lite.simulation.world import WorldConfig, make_world

CAM = Camera()
CENTRE_POSE = (100.0, 0.0, 0.0)  # rear axle at s = 100 m, middle lane, aligned


def view(world, pose=CENTRE_POSE, cam=CAM, **kw):
    return cam.render(world.track, world.cars, pose, **kw)


def changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(row, col) of pixels that differ."""
    return np.argwhere(np.any(a != b, axis=-1))


def test_pinhole_formula_by_hand():
    cfg = CAM.cfg
    h, th = cfg.mount_height_m, CAM.pitch
    for fwd, left in [(10.0, 0.0), (25.0, 3.7), (7.0, -2.0), (80.0, 5.0)]:
        f = fwd - cfg.forward_offset_m  # ahead of the lens
        z = f * math.cos(th) + h * math.sin(th)
        col = CAM.cx + CAM.fx * (-left) / z
        row = CAM.cy + CAM.fy * (h * math.cos(th) - f * math.sin(th)) / z
        px, front = CAM.project_car(np.array([fwd, left, 0.0]))
        assert (
            front
            and px[0] == pytest.approx(col, abs=1e-9)
            and px[1] == pytest.approx(row, abs=1e-9)
        )
    # the horizon: a point at infinity straight ahead, at the configured row
    assert CAM.horizon_row() == pytest.approx(cfg.horizon_frac * (cfg.height_px - 1))
    far, _ = CAM.project_car(np.array([1e7, 0.0, cfg.mount_height_m]))
    assert far[1] == pytest.approx(CAM.horizon_row(), abs=1e-3)


def test_output_is_rgb_uint8_of_the_documented_shape():
    img = view(straight_world([], []))
    assert img.dtype == np.uint8 and img.shape == (66, 200, 3)
    assert tuple(img[0, 100]) == SKY  # the sky band above the horizon, in RGB order
    human = Camera(CameraConfig.human())
    assert view(straight_world([], []), cam=human).shape == (240, 640, 3)


def test_a_ground_marking_lands_where_the_formula_says():
    """Row by row, the rasterised left edge line is centred (coverage-weighted, to half a pixel)
    on the column where the pinhole formula puts its centre line (d = half_width - 7.5 cm)."""
    world = straight_world([], [])
    img = view(world).mean(axis=-1)
    d_line = world.track.half_width - 0.075
    for row in (12, 18, 26):
        lo, hi = 2.0, 500.0  # find the forward distance whose ground point lands on this row
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            (_, r), _ = CAM.project_car(np.array([mid, d_line, 0.0]))
            lo, hi = (mid, hi) if r > row else (lo, mid)
        (col, _), _ = CAM.project_car(np.array([lo, d_line, 0.0]))
        cols = np.arange(int(col) - 4, int(col) + 6)
        vals = img[row, cols]
        # coverage of each pixel by the white line: against the shoulder on its left, the road right
        base = np.where(cols < col, np.mean(SHOULDER), np.mean(ROAD))
        cover = np.clip((vals - base) / (np.mean(MARKING) - base), 0.0, 1.0)
        assert cover.sum() > 0.5, f"no marking near column {col:.1f} on row {row}"
        centroid = float((cols * cover).sum() / cover.sum())
        assert centroid == pytest.approx(col, abs=0.5), (row, col, centroid)


def test_centred_on_a_straight_the_view_is_mirror_symmetric():
    """The lane centre straight ahead is the image's centre column: left and right mirror."""
    img = view(straight_world([], [])).astype(int)
    mirror = img[:, ::-1]
    assert np.mean(np.abs(img - mirror)) < 1.0
    assert np.percentile(np.abs(img - mirror), 99) < 40


def test_car_ahead_in_ego_lane_is_seen_centred_and_a_left_lane_car_is_not():
    empty = view(straight_world([], []))
    ahead = view(straight_world([100.0 + 20.0], [1]))
    px = changed(empty, ahead)
    assert len(px) > 50
    assert px[:, 1].min() < CAM.cx < px[:, 1].max()  # spans the centre column
    left = view(straight_world([100.0 + 20.0], [2]))
    px_left = changed(empty, left)
    assert len(px_left) > 20 and px_left[:, 1].max() < CAM.cx  # wholly left of centre


def test_a_car_60_m_ahead_is_visible_at_network_size():
    empty = view(straight_world([], []))
    far = view(straight_world([100.0 + 60.0], [1]))
    assert len(changed(empty, far)) >= 8


def test_nothing_behind_the_camera_is_drawn():
    empty = view(straight_world([], []))
    behind = view(straight_world([100.0 - 15.0], [1]))
    assert np.array_equal(empty, behind)


def test_a_car_beside_and_partly_behind_the_camera_is_clipped_not_wrapped():
    """A car in the left lane straddling the lens plane: drawn without error, only on the left.

    (A 50 degree camera cannot see a 4.5 m car beside it at all, so this uses a 120 degree one.)
    """
    wide = Camera(CameraConfig(hfov_deg=120.0))
    empty = view(straight_world([], []), cam=wide)
    lens_s = 100.0 + CAM.cfg.forward_offset_m
    img = view(straight_world([lens_s + 0.5], [2]), cam=wide)  # rear 1.75 m behind the lens
    px = changed(empty, img)
    assert len(px) > 0
    assert px[:, 1].max() < wide.cx  # nothing projected through infinity onto the right
    # rotated ego: the near plane cuts the road strips; the frame still draws and stays sane
    rot = view(straight_world([110.0], [2]), pose=(100.0, 0.0, math.radians(40)))
    assert rot.shape == (66, 200, 3)


def test_clip_near_keeps_the_part_in_front():
    square = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]])
    out = clip_near(square, 0.5)
    assert out is not None and np.all(out[:, 2] >= 0.5 - 1e-12)
    assert sorted(map(tuple, out.round(9))) == sorted(
        [(1.0, 0.0, 0.5), (1.0, 0.0, 1.0), (-1.0, 0.0, 1.0), (-1.0, 0.0, 0.5)]
    )
    assert clip_near(square - np.array([0.0, 0.0, 5.0]), 0.5) is None
    ahead = square + np.array([0.0, 0.0, 5.0])
    assert clip_near(ahead, 0.5) is ahead  # untouched when wholly in front
    # a triangle with one vertex in front becomes a triangle
    tri = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, -2.0], [-1.0, 0.0, -2.0]])
    assert len(clip_near(tri, 0.0)) == 3


def test_same_state_same_image_and_curves_are_drawn():
    track = generate_track(RoadConfig(length_m=3_000.0), "val", 0)
    arc = int(np.flatnonzero(track.k != 0)[0])
    s = float(track.s0[arc]) - 20.0
    pose = tuple(track.pose(s, 0.0))
    a = CAM.render(track, None, pose, s)
    b = CAM.render(track, None, pose)  # the arc length looked up instead of given
    assert np.array_equal(a, b)
    straight = CAM.render(track, None, tuple(track.pose(50.0, 0.0)), 50.0)
    assert not np.array_equal(a, straight)


def test_augmentation_is_seeded_and_off_by_default():
    world = straight_world([120.0], [1])
    cam = Camera(CameraConfig(augment=True))
    with pytest.raises(ValueError, match="rng"):
        view(world, cam=cam)
    a = view(world, cam=cam, rng=np.random.default_rng(3))
    b = view(world, cam=cam, rng=np.random.default_rng(3))
    c = view(world, cam=cam, rng=np.random.default_rng(4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert not np.array_equal(a, view(world))


def test_trajectory_overlay_lands_on_the_projection():
    img = np.zeros((66, 200, 3), np.uint8)
    point = np.array([[20.0, 1.5]])
    draw_trajectory(img, point, CAM, colour=(255, 0, 0), radius_px=2)
    (col, row), _ = CAM.project_car(np.array([20.0, 1.5, 0.0]))
    red = np.argwhere(img[..., 0] > 128)
    # the dot is centred on the projection (the line from the near road point ends there too)
    near_dot = red[np.hypot(red[:, 0] - row, red[:, 1] - col) <= 3]
    assert len(near_dot) >= 9
    assert near_dot[:, 0].mean() == pytest.approx(row, abs=0.75)
    assert near_dot[:, 1].mean() == pytest.approx(col, abs=0.75)


def test_topdown_puts_the_ego_at_its_place_and_cars_ahead_above_it():
    world = straight_world([120.0], [1])
    cfg = TopDownConfig()
    img = render_topdown(world.track, world.cars, CENTRE_POSE, cfg)
    row0, col0 = cfg.ego_row_frac * (cfg.size_px[0] - 1), (cfg.size_px[1] - 1) / 2
    assert tuple(img[round(row0 - 4), round(col0)]) == (30, 110, 255)  # the ego (blue), 1 m ahead
    car_row = round(row0 - 20.0 / cfg.m_per_px)  # 20 m ahead
    assert tuple(img[car_row, round(col0)]) != tuple(img[car_row, 5])  # a car, not road or grass


def test_a_batch_renders_exactly_what_single_frames_do():
    world = make_world(WorldConfig(road=RoadConfig(length_m=3_000.0)), "val", 2)
    s = np.array([40.0, 180.0, 800.0, 1_500.0])
    poses = np.array([world.track.pose(si, di) for si, di in zip(s, (0.0, 3.7, -2.0, 1.0))])
    poses[1, 2] += 0.2  # one car turned off the road direction
    batch = CAM.render_batch([world.track] * 4, [world.cars] * 4, poses, s)
    for b in range(4):
        assert np.array_equal(batch[b], CAM.render(world.track, world.cars, tuple(poses[b]), s[b]))


@pytest.mark.parametrize("heading_deg", [100.0, 180.0, -135.0])
def test_a_car_turned_across_or_against_the_road_renders_sanely(heading_deg):
    """Road lines that never come in front of the lens take the polygon-by-polygon clipping path:
    the frame renders, the sky stays sky, and ground is only drawn below the horizon."""
    world = straight_world([130.0], [1], length=400.0)
    img = view(world, pose=(200.0, 0.0, math.radians(heading_deg)))
    assert img.shape == (66, 200, 3) and img.dtype == np.uint8
    horizon = int(CAM.horizon_row())
    assert np.all(img[:horizon] == SKY)
    if heading_deg != -135.0:  # looking back to the right, the sampled road is out of view
        assert np.any(img != view(straight_world([], [], length=400.0), pose=(0.0, 500.0, 0.0)))


def test_tile_lays_images_out_in_rows_and_fills_the_last_with_black():
    from e2e_lite.simulation.raster import tile

    imgs = [np.full((2, 3, 3), v, np.uint8) for v in (10, 20, 30)]
    out = tile(imgs, 2)
    assert out.shape == (4, 6, 3)
    assert out[0, 0, 0] == 10 and out[0, 3, 0] == 20 and out[2, 0, 0] == 30 and out[2, 3, 0] == 0
    assert tile(imgs, 3).shape == (2, 9, 3)
    with pytest.raises(ValueError, match="at least one"):
        tile([], 2)
