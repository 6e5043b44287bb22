"""Replays: the 3D page is one self-contained file holding the animation; no server process."""

from __future__ import annotations

import base64
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import umsgpack
from PIL import Image

from e2e_lite import replay
from e2e_lite.agents import TrajectoryAgent
from e2e_lite.drivers import LaneKeeper
from e2e_lite.geometry import RoadConfig
from e2e_lite.models import ModelConfig, build_model, prepare
from e2e_lite.world import TrafficConfig, WorldConfig, make_world

WORLD = WorldConfig(road=RoadConfig(length_m=1_000.0), traffic=TrafficConfig(n_cars=(6, 6)))


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
