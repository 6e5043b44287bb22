"""The benchmark commands run and print their figures (they assert nothing about speed)."""

from __future__ import annotations

import json

import pytest

from e2e_lite.course import bench


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--quick"],
        ["network", "--quick"],
        ["closed-loop", "--quick", "--agent", "actuators"],
        ["closed-loop", "--quick", "--agent", "gmm"],
        ["scaling", "--quick"],
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
    if argv[0] == "scaling":  # every worker count drove and collected the same as one
        same = [v for k, v in figures.items() if k.endswith(("_same_events", "_same_bytes"))]
        assert len(same) >= 3 and all(v == 1.0 for v in same)
        assert figures["eval_1w_speedup"] == pytest.approx(1.0)
    if ratio == "loop_vs_network":
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


def test_estimates_count_the_work_and_spread_driving_over_the_workers():
    """Issue 56: a long run says first how many workers and which device it will use, and how
    long it should take from the benchmarks' per-part rates."""
    from e2e_lite.config import FULL
    from e2e_lite.course.estimate import (
        RATES,
        Work,
        chapter_work,
        course_work,
        estimate_s,
        plan_text,
    )
    from e2e_lite.imitation import recipes
    from e2e_lite.record.ablation import SEED_ZERO_ONLY
    from e2e_lite.record.run import record_work

    drive = Work(collect_samples=0.0, train_samples=0.0, drive_miles=1_000.0)
    one, two = estimate_s(drive, 1), estimate_s(drive, 2)
    assert one == pytest.approx(1_000.0 / RATES["drive_mi_per_s_per_worker"])
    assert two == pytest.approx(one / (1.0 + RATES["worker_efficiency"]))
    train = Work(collect_samples=0.0, train_samples=1e6, drive_miles=0.0)
    assert estimate_s(train, 2, "cuda") < estimate_s(train, 2, "cpu") == estimate_s(train, 16)
    # the record of 10 seeds drives twice the miles of 5 and trains twice the networks
    five, ten = record_work(FULL, 5, 100.0), record_work(FULL, 10, 100.0)  # (every row per seed)
    assert ten.drive_miles == pytest.approx(2 * five.drive_miles)
    assert ten.train_samples > 1.9 * five.train_samples
    # PilotNet and L2 with seed 0 alone: 18 trainings fewer, the same miles on the record's roads
    lean = record_work(FULL, 10, 100.0, single=SEED_ZERO_ONLY)
    per_training = FULL.n_train_samples * FULL.train_epochs
    assert ten.train_samples - lean.train_samples == pytest.approx(18 * per_training)
    selecting = FULL.train_epochs * recipes.SELECT_MILES
    assert ten.drive_miles - lean.drive_miles == pytest.approx(18 * selecting)
    course = course_work(FULL)
    assert course.drive_miles > 0 and course.train_samples > 0
    # the course is the sum of its chapters; a subset's estimate counts that subset's work only
    each = chapter_work(FULL)
    assert sorted(each) == list(range(1, 13))
    assert course.collect_samples == pytest.approx(sum(w.collect_samples for w in each.values()))
    early, late = course_work(FULL, range(1, 8)), course_work(FULL, range(8, 13))
    for part in range(len(Work._fields)):
        assert early[part] + late[part] == pytest.approx(course[part])
    # chapter 12 drives DAgger's rounds and their control, 3 decisions per kept sample, and the
    # control's DART pilots: 4 seeds x 4 rounds x 8,000 x (2 x 3 + 0.25)
    assert each[12].collect_samples == pytest.approx(4 * 4 * FULL.n_train_samples // 6 * 6.25)
    assert early.collect_samples == FULL.n_train_samples + FULL.n_val_samples
    line = plan_text("the record", ten, 16, "cuda")
    assert "16 worker processes" in line and "cuda" in line and "fp32" in line and "min" in line
