"""Lane frame: analytic geometry of straights and arcs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from e2e_lite.simulation.geometry import RoadConfig, Track, generate_track


@pytest.fixture(scope="module")
def track() -> Track:
    return generate_track(RoadConfig(length_m=6_000.0), "train", 3)


def test_track_has_straights_and_arcs_of_both_sides(track):
    assert np.any(track.k == 0) and np.any(track.k != 0)
    assert track.length == pytest.approx(6_000.0)
    assert 0.05 < track.curve_share() < 0.5  # curves are the minority


@pytest.mark.parametrize("kind", ["straight", "arc"])
def test_round_trip_world_frenet_world(track, kind):
    rng = np.random.default_rng(0)
    segs = np.flatnonzero(track.k == 0) if kind == "straight" else np.flatnonzero(track.k != 0)
    j = rng.choice(segs, 500)
    s = track.s0[j] + rng.uniform(0, 1, 500) * track.seg_len[j]
    d = rng.uniform(-track.rail_d, track.rail_d, 500)
    xy = track.position(s, d)
    s2, d2 = track.to_frenet(xy[:, 0], xy[:, 1])
    assert np.max(np.abs(s2 - s)) < 1e-6
    assert np.max(np.abs(d2 - d)) < 1e-6
    back = track.position(s2, d2)
    assert np.max(np.abs(back - xy)) < 1e-6


def test_scalar_hint_lookup_matches_vectorised(track):
    s = np.linspace(0, track.length - 1, 300)
    xy = track.position(s, 1.3)
    hint = 0
    for si, (x, y) in zip(s, xy):
        s2, d2, hint = track.to_frenet_hint(float(x), float(y), hint)
        assert s2 == pytest.approx(si, abs=1e-6) and d2 == pytest.approx(1.3, abs=1e-6)


def test_heading_continuous_across_joins(track):
    eps = 1e-6
    for s in track.s0[1:]:
        assert track.heading(s - eps) == pytest.approx(track.heading(s + eps), abs=1e-5)
        p_before, p_after = track.position(s - eps), track.position(s + eps)
        assert np.hypot(*(p_after - p_before)) == pytest.approx(2 * eps, abs=1e-7)


def test_arc_curvature_is_inverse_radius():
    radius = 250.0
    # a hand-made track: a straight then a left arc; the arc starts where the straight ends
    t = Track([0.0, 100.0], [0.0, 0.0], [0.0, 0.0], [0.0, 1 / radius], [100.0, 300.0])
    assert float(t.curvature(250.0)) == pytest.approx(1 / radius)
    # points on the arc are radius from its centre (100, 250)
    xy = t.position(np.linspace(100, 400, 50))
    assert np.allclose(np.hypot(xy[:, 0] - 100, xy[:, 1] - radius), radius)
    # the heading turns by length / radius
    assert float(t.heading(400.0)) == pytest.approx(300 / radius)
    # numerical curvature of the centre line = 1/R: heading change over arc length
    s = np.array([200.0, 200.1])
    assert np.diff(t.heading(s))[0] / 0.1 == pytest.approx(1 / radius)


def test_lanes():
    t = generate_track(RoadConfig(n_lanes=3, lane_width_m=3.7), "val", 0)
    assert np.allclose(t.lane_center(np.arange(3)), [-3.7, 0.0, 3.7])
    assert t.lane_index(-3.0) == 0 and t.lane_index(0.4) == 1 and t.lane_index(5.0) == 2
    assert t.lane_index(-20.0) == 0  # clipped to the road
    assert t.half_width == pytest.approx(5.55)
    t4 = generate_track(RoadConfig(n_lanes=4), "val", 0)
    assert np.allclose(t4.lane_center(np.arange(4)), [-5.55, -1.85, 1.85, 5.55])
    # the settings know the same centres before a track is made
    assert np.allclose(RoadConfig(n_lanes=4).lane_centers(), [-5.55, -1.85, 1.85, 5.55])


def test_generator_is_seeded_and_splits_differ():
    cfg = RoadConfig(length_m=3_000.0)
    a, b = generate_track(cfg, "val", 1), generate_track(cfg, "val", 1)
    assert np.array_equal(a.k, b.k) and np.array_equal(a.seg_len, b.seg_len)
    c = generate_track(cfg, "train", 1)
    d = generate_track(cfg, "val", 2)
    assert not np.array_equal(a.seg_len, c.seg_len)
    assert not np.array_equal(a.seg_len, d.seg_len)


def test_heading_stays_bounded():
    cfg = RoadConfig(length_m=20_000.0, max_heading_deg=45.0, arc_deg=(20.0, 45.0))
    t = generate_track(cfg, "train", 0)
    h = t.heading(np.linspace(0, t.length, 2000))
    assert np.max(np.abs(h)) <= math.radians(45.0) + 1e-9


def test_polyline_is_exact_on_straights_and_close_on_arcs(track):
    pts = track.polyline(track.rail_d, max_sag_m=0.02)
    _s, d = track.to_frenet(pts[:, 0], pts[:, 1])
    assert np.allclose(d, track.rail_d, atol=1e-6)
    mid = 0.5 * (pts[1:] + pts[:-1])
    _, d_mid = track.to_frenet(mid[:, 0], mid[:, 1])
    assert np.max(np.abs(d_mid - track.rail_d)) <= 0.0201


def test_positions_on_many_tracks_matches_each_track():
    from e2e_lite.simulation.geometry import positions_on

    tracks = [generate_track(RoadConfig(length_m=4_000.0), "val", i) for i in range(4)]
    rng = np.random.default_rng(1)
    # rows 0-1 inside one segment (the fast path); rows 2-3 spanning joins (the general path)
    s = np.stack(
        [
            np.linspace(10, 90, 50),
            np.linspace(5, 40, 50),
            np.linspace(0, 3_900, 50),
            np.linspace(250, 400, 50),
        ]
    )
    d = rng.uniform(-8, 8, 50)
    got = positions_on(tracks, s, d)
    for b, t in enumerate(tracks):
        assert np.allclose(got[b], t.position(s[b], d), atol=1e-9)
        assert np.allclose(t.position(s[b, :20], d[:20]), t.position(s[b], d)[:20], atol=1e-9)
