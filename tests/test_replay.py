"""Replays: the 3D page is one self-contained file holding the animation; no server process."""

from __future__ import annotations

import base64
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import umsgpack
from PIL import Image

from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.driving import replay
from e2e_lite.driving.evaluation import close_shard_workers
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.simulation.geometry import RoadConfig
from e2e_lite.simulation.world import TrafficConfig, WorldConfig, make_world

WORLD = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(6, 6)))
EMPTY_WORLD = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(0, 0)))


def _processes() -> dict[int, str]:
    """pid -> command line of every process this machine shows (Linux), else empty."""
    out = {}
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            out[int(entry.name)] = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
    return out


def _commands(page: str) -> list[dict]:
    block = page[
        page.index("var e2eCommands = [") : page.index("];", page.index("var e2eCommands"))
    ]
    return [
        umsgpack.unpackb(base64.b64decode(b64)) for b64 in re.findall(r'"([A-Za-z0-9+/=]+)"', block)
    ]


@pytest.fixture(scope="module")
def gmm_episode():
    torch.manual_seed(0)
    model = prepare(build_model(ModelConfig(head="gmm", fusion_width=16)), torch.device("cpu"))
    agent = TrajectoryAgent(model)
    return replay.record(agent, make_world(WORLD, "val", 0), WORLD, "tiny GMM", 30.0, 1, 1.5)


def test_replay_page_is_self_contained_and_holds_the_animation(gmm_episode, tmp_path):
    close_shard_workers()  # (earlier tests' evaluations keep theirs; this test counts children)
    before = set(_processes())
    page_path = replay.export_html(gmm_episode, tmp_path / "gmm.html", "a caption")
    page = page_path.read_text()
    # the viewer is inlined whole; nothing is loaded from elsewhere
    assert replay.viewer_script() in page
    outside = page.replace(replay.viewer_script(), "")
    for needle in ("<script src", "<link", "fetch(", "http://", "https://", "import("):
        assert needle not in outside, needle
    commands = _commands(page)
    types = {c["type"] for c in commands}
    assert {"set_object", "set_animation"} <= types
    anim = next(c for c in commands if c["type"] == "set_animation")
    clips = {a["path"]: a["clip"] for a in anim["animations"]}
    ego = clips["/meshcat/ego"]["tracks"]
    assert len(ego[0]["keys"]) == len(gmm_episode.states)  # one key per decision
    # every mode's 5 points are animated, their size following the mode's weight
    k = gmm_episode.modes.shape[1]
    assert sum(p.startswith("/meshcat/plan/mode_") for p in clips) == 5 * k
    scale = next(t for t in clips["/meshcat/plan/mode_0/p0"]["tracks"] if t["name"] == ".scale")
    w = gmm_episode.weights[:, 0]
    assert np.allclose([key["value"][0] for key in scale["keys"]], 0.25 + 0.75 * w)
    assert "a caption" in page and "tiny GMM" in page
    # no meshcat server was started, and nothing new is left running
    new = {pid: cmd for pid, cmd in _processes().items() if pid not in before}
    assert not any("meshcat" in cmd for cmd in new.values()), new
    assert not any("meshcat.servers" in cmd for cmd in _processes().values())
    if os.path.exists("/proc"):
        children = [
            pid
            for pid in _processes()
            if (Path("/proc") / str(pid) / "stat").exists()
            and (Path("/proc") / str(pid) / "stat").read_text().split()[3] == str(os.getpid())
        ]
        assert children == []


def test_gif_and_index(gmm_episode, tmp_path):
    gif = replay.export_gif(gmm_episode, tmp_path / "gmm.gif", every=1)
    with Image.open(gif) as im:
        assert im.n_frames == len(gmm_episode.frames) == len(gmm_episode.states) - 1
    index = replay.write_index([("tiny <GMM>", "gmm.html", "1.5 s")], tmp_path / "index.html", "t")
    text = index.read_text()
    assert 'href="gmm.html"' in text and "tiny &lt;GMM&gt;" in text


def test_a_driver_without_proposals_replays_and_a_collision_ends_it(tmp_path):
    world = make_world(WORLD, "val", 0)
    ep = replay.record(LaneKeeper(), world, WORLD, "keeper", 30.0, 1, 60.0, frames=False)
    assert ep.modes is None and ep.frames == []
    assert ep.contact == "car" and ep.seconds < 60.0  # ignores the parked cars: runs into one
    page = replay.export_html(ep, tmp_path / "k.html").read_text()
    assert "collided with a car" in page
    with pytest.raises(ValueError, match="frames"):
        replay.export_gif(ep, tmp_path / "k.gif")


class Proposing(LaneKeeper):
    """A lane keeper that also declares two modes: straight on (weight 0.7) and a drift left."""

    def act(self, obs):
        act = super().act(obs)
        n = len(obs.s)
        ahead = np.linspace(6.0, 30.0, 5)
        straight = np.stack([ahead, np.zeros(5)], -1)
        left = np.stack([ahead, np.linspace(0.3, 3.0, 5)], -1)
        self.last = {
            "modes": np.repeat(np.stack([left, straight])[None], n, 0),
            "weights": np.repeat(np.array([[0.3, 0.7]]), n, 0),
        }
        return act


def _browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def _screenshot(browser: str, page: Path, out: Path, at_ms: int) -> np.ndarray:
    """The page as headless Chromium draws it (software WebGL) after ``at_ms`` of page time."""
    subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
         "--enable-unsafe-swiftshader", "--hide-scrollbars", "--window-size=800,600",
         f"--virtual-time-budget={at_ms}", f"--screenshot={out}", page.as_uri()],
        capture_output=True, timeout=120, check=True,
    )  # fmt: skip
    with Image.open(out) as im:
        return np.asarray(im.convert("RGB")).astype(int)


@pytest.mark.skipif(
    _browser() is None, reason="no Chromium or Chrome on this machine (.ci/run installs one)"
)
def test_the_replay_camera_shows_the_car_and_its_modes_in_a_real_browser(tmp_path):
    """The chase view: at the start and the end of the animation the red car and the heavier
    (orange) mode's spheres are drawn near the middle of the frame."""
    world = make_world(EMPTY_WORLD, "val", 0)
    ep = replay.record(Proposing(), world, EMPTY_WORLD, "proposer", 30.0, 1, 4.0, frames=False)
    assert ep.contact is None and ep.seconds >= 3.9
    page = replay.export_html(ep, tmp_path / "proposer.html", "browser test")
    for at_ms in (800, 6000):  # early in the 4 s animation, and after it ended
        rgb = _screenshot(_browser(), page, tmp_path / f"shot_{at_ms}.png", at_ms)
        h, w, _ = rgb.shape
        middle = rgb[h // 5 : 4 * h // 5, w // 5 : 4 * w // 5]  # the caption sits top left
        r, g, b = middle[..., 0], middle[..., 1], middle[..., 2]
        car = (r > 140) & (g < 90) & (b < 90)
        orange = (r > 170) & (g > 90) & (g < 175) & (b < 80)
        assert car.sum() > 200, (at_ms, car.sum())
        assert orange.sum() > 20, (at_ms, orange.sum())
        # and not elsewhere only: the car's pixels are centred horizontally
        cols = np.flatnonzero(car.any(0))
        assert abs(cols.mean() - middle.shape[1] / 2) < middle.shape[1] / 6, cols.mean()
