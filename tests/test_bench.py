"""The benchmark commands run and print their figures (they assert nothing about speed)."""

from __future__ import annotations

import json

import pytest
import torch

from e2e_lite import bench


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--quick"],
        ["network", "--quick"],
        ["closed-loop", "--quick", "--agent", "actuators"],
        ["closed-loop", "--quick", "--agent", "gmm"],
        ["placement", "--quick"],
    ],
)
def test_benchmark_command_prints_json(argv, capsys):
    assert bench.main([*argv, "--json"]) == 0
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert figures["benchmark"] == argv[0]
    # rates (..._per_s, ..._per_wall_s) and measured times (..._ms_per_frame; "rest" and the
    # policy beyond the network are differences, which noise may take below zero)
    derived = ("rest", "beyond")
    numbers = [
        v
        for k, v in figures.items()
        if "_per_" in k
        and (k.endswith("_s") or (k.endswith("_ms_per_frame") and not any(d in k for d in derived)))
    ]
    assert numbers and all(v > 0 for v in numbers)
    # the ratios to the bare network that the README quotes (issue 19)
    ratio = {"train": "loop_vs_bare", "closed-loop": "loop_vs_network"}.get(argv[0])
    if ratio == "loop_vs_bare":
        assert figures[ratio] == pytest.approx(
            figures["loop_samples_per_s"] / figures["bare_samples_per_s"]
        )
    if argv[0] == "placement":  # the course's setting is always a row; with a GPU, three more
        rows = {k.removesuffix("_collisions") for k in figures if k.endswith("_collisions")}
        assert "cpu_2processes" in rows
        # its collisions are the evaluation's own: the same driver, roads and shards in threads
        # (processes and threads give the same events)
        from e2e_lite.config import active_profile
        from e2e_lite.driving.evaluation import evaluate
        from e2e_lite.simulation.world import WorldConfig

        policy, _ = bench.learned_driver("gmm", torch.device("cpu"))
        world, ev = WorldConfig.for_profile(active_profile([])), bench.placement_eval(quick=True)
        res = evaluate(policy, world, ev, progress=False, workers=2, parallel="threads")
        assert figures["cpu_2processes_collisions"] == res.collisions
    elif ratio == "loop_vs_network":
        assert figures[ratio] == pytest.approx(
            figures["loop_miles_per_s"] / figures["network_miles_per_s"]
        )
        # the frame's budget adds up to the loop: the network's share of it is the ratio, and
        # a free camera could only raise it
        assert figures[ratio] == pytest.approx(
            figures["budget_network_ms_per_frame"] / figures["budget_total_ms_per_frame"]
        )
        assert figures["loop_vs_network_without_render"] > figures[ratio]
        # the same miles per frame turn the network's frames into miles
        assert figures["network_miles_per_s"] == pytest.approx(
            figures["network_frames_per_s"]
            * figures["b64_2processes_sim_miles"]
            / figures["b64_2processes_frames"]
        )


def test_pool_benchmark_measures_the_course_pool(capsys, monkeypatch):
    """``bench pool`` drives both calls with the course's pool (loky only where installed) and its
    Ctrl-C trial sees the child stop within a second, one line on stderr, no process left."""
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "loky" else real(name, *a)
    )
    assert bench.main(["pool", "--quick", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert not any(k.startswith("loky") for k in figures)
    assert figures["ours_first_sim_miles_per_wall_s"] > 0
    assert figures["ours_second_sim_miles_per_wall_s"] > 0
    assert figures["ours_ctrl_c_exit_s"] < 1.5
    assert figures["ours_ctrl_c_stderr_lines"] == 1  # the child's own "interrupted"
    assert figures["ours_ctrl_c_left"] == 0
