"""The numbers of record and their render: Table 1 in the README and docs/results.md come from
docs/results/ by one command, and the paper's steps are judged on the training seeds."""

from __future__ import annotations

import dataclasses
import json
import re
from types import SimpleNamespace

import pytest

from e2e_lite.record import kit, report, words
from e2e_lite.record.rows import Record, Row, SeedRun
from e2e_lite.record.stats import OFF_CENTRE_READING, STEPS, off_centre_steps, record_power, steps
from e2e_lite.stats.seeds import spread

ROOT = report.ROOT


def row(key: str, counts: list[int], miles: float = 100.0, mph: float = 55.0) -> Row:
    """A hand-made row: one entry per training seed, all collisions into parked cars."""
    seeds = tuple(SeedRun(k, c, miles) for k, c in enumerate(counts))
    return Row(key, key, None, seeds, car=sum(counts), rail=0, mph=mph, stalls=0)


def with_rows(record: Record, *rows: Row) -> Record:
    """``record`` with ``rows`` in place of its own."""
    return dataclasses.replace(record, rows=tuple(rows))


def by_step(record: Record) -> dict:
    return {s.step: s for s in steps(record)}


#: the first sealed record's seeds (5f7918c, 10 x 100 mi): a spread of about 0.32 across its
#: rows, on which the power and plan tests below are calibrated (the committed record may grow)
SPREAD = {
    "actuators": [68, 50, 128, 55, 69, 84, 89, 66, 68, 57],
    "gmm": [11, 9, 8, 11, 6, 3, 2, 16, 4, 4],
    "gmm_affordance": [1, 0, 2, 6, 6, 1, 4, 10, 4, 2],
    "gmm_affordance_cvar": [1, 0, 1, 0, 2, 2, 0, 8, 3, 2],
    "gmm_affordance_w0": [2, 17, 2, 6, 4, 1, 5, 25, 3, 4],
    "gmm_affordance_control": [0, 0, 3, 1, 4, 0, 3, 6, 1, 1],
}


def spread_record() -> Record:
    """The committed record with :data:`SPREAD`'s rows in place of its own."""
    return with_rows(report.load(), *(row(key, counts) for key, counts in SPREAD.items()))


def test_the_readme_and_results_page_are_the_render_of_the_committed_record() -> None:
    assert report.main(["--check"]) == 0, "run python -m e2e_lite.record.report"
    readme = (ROOT / "README.md").read_text()
    assert report.table1(report.load()) in readme
    assert report.chapters_table() in readme


def test_the_readme_is_a_front_door_with_one_table_1() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    assert readme.count("## Table 1") == 1 and readme.count(report.BEGIN) == 1
    # one table of steps, one Table 1
    assert readme.count("| step, or method against control |") == 1
    for page in ("results.md", "lab-notes.md", "benchmarks.md"):
        assert (ROOT / "docs" / page).exists() and f"docs/{page}" in readme


def test_every_lab_note_names_the_commit_of_its_code() -> None:
    notes = (ROOT / "docs" / "lab-notes.md").read_text()
    headings = re.findall(r"^## (.*)$", notes, flags=re.M)
    assert len(headings) >= 10
    assert all(re.search(r"\b[0-9a-f]{7}\b", h) for h in headings), headings


def test_each_step_gives_its_p_ratio_interval_and_paired_test_and_the_record_its_power() -> None:
    """Per step, the primary p-value (paired where a fine-tune shares its parent), the rate ratio
    with its bootstrap interval, the unpaired and paired p-values; and the record's power at its
    own + affordance rate, stated under the table."""
    record = with_rows(
        report.load(),
        row("expert", [0]),
        row("gmm", [6, 10, 5, 3, 11]),
        row("gmm_affordance", [6, 5, 3, 2, 3]),
        row("gmm_affordance_cvar", [5, 4, 4, 3, 6]),
    )
    tested = by_step(record)
    aff = tested["GMM -> + affordance"]
    assert abs(aff.p_fewer - 0.087) < 0.005 and aff.test == "rank"
    assert words.verdict(aff) == "not shown at the seed level"
    assert aff.ratio == pytest.approx(19 / 35) and aff.ratio_ci[0] < aff.ratio
    cvar = tested["+ affordance -> + CVaR"]
    assert cvar.test == "paired sign-flip" and cvar.p_paired == cvar.p_fewer
    table = report.table1(record)
    assert "0.54 [" in table and "Power: 5 seeds x 100 mi" in table
    found = record_power(record)
    assert found.rate_per_100mi == 3.0 and 0.5 < found.power < 0.7
    # three seeds against three: the verdict says it cannot decide
    few = with_rows(record, row("gmm", [20, 21, 22]), row("gmm_affordance", [1, 2, 3]))
    assert words.verdict(steps(few)[0]) == "cannot be decided with these seeds"


def test_a_row_with_one_catastrophic_seed_is_not_called_reproduced() -> None:
    expert, gmm = row("expert", [0]), row("gmm", [20, 21, 22, 19, 23])
    # four seeds far better than the GMM, one catastrophic: the pooled rate is worse
    bad = row("gmm_affordance", [1, 2, 1, 2, 200])
    step = by_step(with_rows(report.load(), expert, gmm, bad))["GMM -> + affordance"]
    assert step.p_fewer > 0.05 and not words.verdict(step).startswith("reproduces")
    # five clean seeds below the GMM's five are
    good = row("gmm_affordance", [1, 2, 1, 2, 3])
    step = by_step(with_rows(report.load(), expert, gmm, good))["GMM -> + affordance"]
    assert words.verdict(step) == "reproduces" and step.p_fewer == pytest.approx(1 / 252)


def test_a_slow_row_is_marked_and_its_verdict_names_its_speed() -> None:
    record = with_rows(
        report.load(),
        row("expert", [0], mph=55.0),
        row("gmm", [20, 21, 22, 19, 23]),
        row("gmm_affordance", [1, 2, 1, 2, 3], mph=40.0),
    )
    assert words.verdict(by_step(record)["GMM -> + affordance"]) == "reproduces, at 40.0 mph"
    assert "40.0 (slow)" in report.table1(record)


def test_a_record_whose_seeds_do_not_add_up_is_refused(tmp_path) -> None:
    record = json.loads(report.RECORD.read_text())
    record["rows"][2]["car"] += 1
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(record))
    with pytest.raises(ValueError, match="do not add up"):
        report.load(path)


def test_the_committed_record_and_shares_load_and_write_back_byte_for_byte() -> None:
    """The typed record reads the committed JSON and writes it back unchanged (the same keys in
    the same order), and the committed shares too, each with its digest; pooled again, the
    shares give the committed record, and its render is the committed README and results page."""
    from e2e_lite.record.pool import pool
    from e2e_lite.record.rows import Share, dump

    text = report.RECORD.read_text()
    record = report.load()
    assert dump(record) == text
    shares = []
    for ref in record.shares:
        path = report.RECORD.parent / "shares" / ref.file
        share = Share.from_json(json.loads(path.read_text()))
        assert dump(share) == path.read_text() and share.content_digest() == ref.digest
        shares.append((ref.file, share))
    assert dump(pool(shares)) == text
    assert report.render(record, check=True) == []


def test_the_spread_is_the_worst_seed_over_the_median_and_a_paper_row_over_the_goal_is_marked():
    def row(counts):
        return SimpleNamespace(seeds=[SimpleNamespace(collisions=c, miles=100.0) for c in counts])

    assert spread(row((10, 12, 60))) == pytest.approx(5.0)
    assert spread(row((3,))) is None
    assert spread(row((0, 0, 2))) == float("inf")
    record = report.load()
    paper = next(r for r in record.rows if r.paper_per_100mi is not None)
    seeds = tuple(SeedRun(k, c, 100.0, mph=50.0, stalls=0) for k, c in enumerate((10, 12, 60)))
    changed = dataclasses.replace(paper, seeds=seeds, car=82, rail=0)
    assert spread(changed) == pytest.approx(5.0)
    rows = tuple(changed if r is paper else r for r in record.rows)
    md = report.results_md(dataclasses.replace(record, rows=rows))
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| {paper.label} | 82"))
    assert line.endswith("| 5.0 (over the goal) |")


def test_a_course_run_is_recorded_from_its_outputs_and_rendered_for_teachers(tmp_path) -> None:
    """docs/teaching.md's per-chapter block is rendered from what a full-profile run wrote (its
    chapter times and headline figures), never typed; a cut run says so."""
    from e2e_lite.record.course_run import course_run_record

    (tmp_path / "metrics").mkdir()
    times = {
        "01_highway": {"seconds": 6.0, "complete": True},
        "02_camera": {"seconds": 90.0, "complete": False},
    }
    (tmp_path / "course_times.json").write_text(json.dumps(times))
    metrics = {"profile": "full", "headline": {"lane keeper collisions/100mi": 0.0}}
    (tmp_path / "metrics" / "01_highway.json").write_text(json.dumps(metrics))
    run = course_run_record(tmp_path)
    assert run["chapters"]["01_highway"]["headline"] == {"lane keeper collisions/100mi": 0.0}
    table = kit.course_run_table(run)
    assert "| 01_highway | 0.1 | lane keeper collisions/100mi: 0 |" in table
    assert "| 02_camera | 1.5 (cut) | - |" in table and "cut after chapter 01" in table
    assert "No full-profile run" in kit.course_run_table(None)
    (tmp_path / "metrics" / "02_camera.json").write_text(json.dumps({"profile": "quick"}))
    with pytest.raises(ValueError, match="not a full-profile run"):
        course_run_record(tmp_path)


def test_what_a_class_sees_live_is_rendered_from_a_recorded_quick_run(tmp_path) -> None:
    """Issue 89: the kit lists each chapter's quick-profile headline figures from a recorded
    quick run (never typed), naming its commit and machine; a full-profile chapter is refused,
    and without a recorded run the kit says how to make one."""
    from e2e_lite.record.course_run import quick_run_record

    (tmp_path / "metrics").mkdir()
    metrics = {"profile": "quick", "headline": {"expert collisions/100mi": 0.0, "x": None}}
    (tmp_path / "metrics" / "04_expert_and_data.json").write_text(json.dumps(metrics))
    run = quick_run_record(tmp_path, ROOT)
    assert run["chapters"] == {"04_expert_and_data": {"expert collisions/100mi": 0.0}}
    lines = kit.quick_run_lines(run)
    assert "- **04_expert_and_data**: expert collisions/100mi 0" in lines
    assert run["machine"] in lines and "No quick run" in kit.quick_run_lines(None)
    (tmp_path / "metrics" / "05_pilotnet_baseline.json").write_text(json.dumps({"profile": "full"}))
    with pytest.raises(ValueError, match="not a quick-profile run"):
        quick_run_record(tmp_path, ROOT)
    teaching = (ROOT / "docs" / "teaching.md").read_text()
    assert kit.LIVE_BEGIN in teaching and "### What a class sees live" in teaching


def test_what_a_machine_needs_is_measured_and_only_what_was_measured_is_said(tmp_path) -> None:
    """The kit's machine needs come from measurements: folder sizes (a hard link counted once),
    the peak memory a '/usr/bin/time -v' log reports, and the system the run was on."""
    from e2e_lite.record.course_run import course_run_record, peak_memory_kib

    full, quick = tmp_path / "full", tmp_path / "quick"
    for d in (full, quick):
        (d / "data").mkdir(parents=True)
    (full / "course_times.json").write_text(json.dumps({"01_highway": {"seconds": 60.0}}))
    (full / "data" / "a.npz").write_bytes(b"x" * 1000)
    (quick / "data" / "a.npz").write_bytes(b"x" * 300)
    (quick / "data" / "b.npz").hardlink_to(quick / "data" / "a.npz")
    log = tmp_path / "time.log"
    log.write_text("chapter output\n\tMaximum resident set size (kbytes): 3145728\n")
    assert peak_memory_kib(log) == 3145728
    run = course_run_record(full, time_log=log, quick_outputs=quick)
    assert run["outputs_bytes"] > 1000 and run["needs"]["quick_outputs_bytes"] == 300
    text = kit.machine_needs_list(run)
    assert "3.0 GiB resident" in text and "after the quick one" in text
    assert "Download" not in text and "venv" not in text  # not measured: not said
    assert run["needs"]["system"] in text and run["needs"]["python"] in text
    (tmp_path / "empty.log").write_text("no report here")
    with pytest.raises(ValueError, match="time -v"):
        peak_memory_kib(tmp_path / "empty.log")


def test_the_committed_record_drives_a_sealed_block_and_states_its_power() -> None:
    """The record of record names its block of test roads (not the open one), the block's range
    and the commit of its frozen recipes, and docs/results.md states its power at its own +
    affordance rate."""
    from e2e_lite.driving.roads import ROAD_BLOCKS

    record = report.load()
    block = record.block
    assert block.name != "open" and block.range == list(ROAD_BLOCKS[block.name])
    assert re.fullmatch(r"[0-9a-f]{7,40}", block.recipes_commit) and block.sealed
    found = record_power(record)
    assert found is not None and found.seeds >= 10
    results = (ROOT / "docs" / "results.md").read_text()
    assert f"Power: {found.seeds} seeds x {found.miles_per_seed:.0f} mi" in results


def test_a_family_of_tests_is_read_at_holm_adjusted_p_with_controls_and_the_papers_ratio() -> None:
    """The record names its families of tests; each step's p is Holm-adjusted within its family
    and the verdict word reads the adjusted p; the table shows raw and adjusted p, the paper's
    ratio beside ours, and a line on what each control found."""
    committed = report.load()
    assert set(committed.family.tests.values()) <= set(committed.family.families)
    rows = [
        dataclasses.replace(row("actuators", [60, 70, 80, 65, 75]), paper_per_100mi=183.3),
        dataclasses.replace(row("gmm", [6, 10, 5, 9, 11]), paper_per_100mi=12.7),
        row("gmm_affordance", [5, 4, 6, 3, 5]),
        row("gmm_affordance_w0", [6, 4, 5, 3, 4]),
    ]
    record = with_rows(committed, *rows)
    tested = by_step(record)
    aff = tested["GMM -> + affordance"]
    # raw p = 7/252 (0.028); in the paper's family of two (beside the Baseline step's 1/252)
    # Holm leaves it at max(2/252, 7/252): still "reproduces"
    assert aff.p_fewer == pytest.approx(7 / 252) and aff.p_holm_fewer == pytest.approx(7 / 252)
    assert words.verdict(aff) == "reproduces"
    assert tested["Baseline E2E -> trajectory GMM"].paper_ratio == pytest.approx(12.7 / 183.3)
    assert aff.paper_ratio is None  # the hand-made row has no paper figure
    # a method that beats its control says so in its family's words, and is credited
    beaten = with_rows(committed, *rows[:3], row("gmm_affordance_w0", [30, 35, 28, 40, 33]))
    control = by_step(beaten)["affordance loss against its control (w = 0)"]
    assert words.verdict(control) == "beats its control"
    assert "so 'GMM -> + affordance' is credited to its method" in words.controls(steps(beaten))
    # a control that collides less reads "the opposite", and the table, the controls line and
    # the teacher's line show the p for more collisions that verdict reads, not the p = 1 for fewer
    worse = with_rows(committed, *rows[:3], row("gmm_affordance_w0", [0, 1, 0, 1, 0]))
    opposite = next(s for s in steps(worse) if s.step.startswith("affordance loss"))
    assert words.verdict(opposite) == "the opposite" and opposite.p_fewer == pytest.approx(1.0)
    assert opposite.verdict_p == opposite.p_holm_more < 0.05
    assert words.cell(opposite) == "the opposite: more collisions"
    cells = f"{opposite.p_more:.2g}: more (rank) | {opposite.p_holm_more:.2g} |"
    assert cells in report.table1(worse)  # the p the verdict reads, not the p = 1 for fewer
    assert f"the control collides less (Holm p = {opposite.p_holm_more:.2g}" in (
        words.controls(steps(worse))
    )
    # a family that holds every test in one: Holm over three (the control's p is about 0.5)
    # takes it to 2 x 7/252 = 0.056, and the same seeds no longer read "reproduces"
    tests = dict.fromkeys(committed.family.tests, "paper")
    one_family = dataclasses.replace(record.family, tests=tests)
    one = by_step(dataclasses.replace(record, family=one_family))["GMM -> + affordance"]
    assert one.p_holm_fewer == pytest.approx(14 / 252) and one.p_fewer == aff.p_fewer
    assert words.verdict(one) == "not shown at the seed level"
    table = report.table1(committed)
    assert "| Holm p |" in table and "the paper's ratio" in table
    assert "**What the controls found.**" in table and "not credited to its method" in table
    assert "The families of tests, declared " in table


def test_the_committed_record_states_its_power_under_its_seeds_spread() -> None:
    """Power is simulated under the dispersion fitted to the record's own rows (about 0.3 across
    the first record's), with the Poisson figure beside as an upper bound."""
    found = record_power(spread_record())
    k = found.dispersion
    assert 0.15 < k.k < 0.6 and k.low < k.k < k.high
    assert found.power < found.power_poisson and found.power_paired < found.power_poisson
    found = record_power(report.load())  # the committed record's, as rendered
    k = found.dispersion
    assert 0.0 <= k.low <= k.k <= k.high
    results = (ROOT / "docs" / "results.md").read_text()
    assert f"in {100 * found.power:.0f} % of records under the seeds' spread" in results
    assert f"{100 * found.power_poisson:.0f} % if seeds did not differ" in results


def test_the_record_plan_reaches_its_power_at_the_least_time_and_the_class_can_run_it() -> None:
    """The plan, per budget of miles per seed, the fewest seeds (at most 30) that find a 2x step
    with the target power under the record's fitted spread, the cheapest chosen; the teacher's
    kit says how a class runs and pools shares, and a job-array script runs them."""
    from e2e_lite.record.run import plan

    # (the fixture's spread, Cox-Reid adjusted: about 0.59; plain maximum likelihood found less)
    found = plan(spread_record(), target=0.6, most=20, miles_options=(100.0, 200.0), n_sim=200)
    assert 0.15 < found["dispersion"] < 0.7 and len(found["options"]) == 2
    for option in found["options"]:
        assert (
            10 <= option["seeds"] <= 20 and option["hours_2_cores"] > option["hours_16_cores_gpu"]
        )
    assert found["chosen"]["power"] >= 0.6 and found["row"] == "gmm_affordance"
    # the low-rate rows' own plan: their median rate, their own spread (issue 88, item 5)
    from e2e_lite.record.run import low_rate_row

    low = low_rate_row(spread_record())
    assert low == "gmm_affordance_control"  # (median 1 per 100 mi: the lowest of SPREAD's)
    own = plan(spread_record(), target=0.6, most=20, miles_options=(100.0,), n_sim=200, row=low)
    assert own["row"] == low and own["rate_per_100mi"] == 1.0
    assert own["options"][0]["seeds"] >= found["options"][0]["seeds"]  # a rarer step: more seeds
    teaching = (ROOT / "docs" / "teaching.md").read_text()
    assert "## A class's Table 1" in teaching
    assert "e2e_lite.record pool" in teaching and "e2e_lite.record plan" in teaching
    script = (ROOT / "docs" / "record-array.sh").read_text()
    assert "e2e_lite.record run --seeds" in script and "SLURM_ARRAY_TASK_ID" in script
    assert "e2e_lite.record pool" in script


def test_the_record_command_runs_pools_and_plans_and_the_report_only_renders(capsys) -> None:
    """One command per job: ``python -m e2e_lite.record`` names its jobs, ``report`` has no flag
    but ``--check``."""
    from e2e_lite.record.__main__ import main

    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert all(job in text for job in ("run", "pool", "plan", "course-run"))
    with pytest.raises(SystemExit):
        report.main(["--help"])
    text = capsys.readouterr().out
    assert "--check" in text and "--record" not in text and "--pool" not in text


def test_a_copy_without_git_names_its_recipes_commit_from_the_environment(monkeypatch) -> None:
    """A lent machine's copy of the tree has no git history: its shares say the commit they ran
    through $E2E_LITE_COMMIT, so a pool can check them against shares made in a clone."""
    import subprocess

    from e2e_lite.record import run as record

    assert re.fullmatch(r"[0-9a-f]{7,40}", record._commit())  # this checkout: git answers

    def no_git(*args, **kwargs):
        raise subprocess.CalledProcessError(128, "git")

    monkeypatch.setattr(subprocess, "run", no_git)  # (the one git call: artifacts.code_commit)
    monkeypatch.delenv("E2E_LITE_COMMIT", raising=False)
    assert record._commit() == "unknown"
    monkeypatch.setenv("E2E_LITE_COMMIT", "6e94ed0")
    assert record._commit() == "6e94ed0"


def test_a_verdict_says_whether_the_papers_size_lies_in_its_interval() -> None:
    """A step in the paper's direction reproduces its size only when the paper's ratio lies in
    the step's interval; a step not shown whose interval excludes the paper's ratio excludes a
    step of the paper's size."""
    committed = report.load()
    big = dataclasses.replace(row("actuators", [60, 70, 80, 65, 75]), paper_per_100mi=100.0)
    gmm = dataclasses.replace(row("gmm", [6, 7, 8, 6, 7]), paper_per_100mi=10.0)
    same = dataclasses.replace(row("gmm_affordance", [6, 7, 8, 6, 7]), paper_per_100mi=0.5)
    tested = by_step(with_rows(committed, big, gmm, same))
    assert (
        words.cell(tested["Baseline E2E -> trajectory GMM"]) == "reproduces: the paper's size too"
    )
    assert words.cell(tested["GMM -> + affordance"]).endswith(
        "a step of the paper's size is excluded"
    )
    small = dataclasses.replace(gmm, paper_per_100mi=0.5)  # the paper's ratio 0.005
    tested = by_step(with_rows(committed, big, small))
    assert words.cell(tested["Baseline E2E -> trajectory GMM"]) == (
        "reproduces: the direction only, not the paper's size"
    )


def test_a_record_that_kept_interventions_renders_off_centre_episodes_beside_each_row() -> None:
    record = spread_record()
    assert "off-centre" not in report.table1(record)  # the records before 2026-11-29 kept none
    kept = row("gmm", [2, 0, 1])
    seeds = tuple(dataclasses.replace(s, interventions=s.collisions + 5) for s in kept.seeds)
    kept = dataclasses.replace(kept, seeds=seeds)  # 15 off-centre episodes in 300 mi
    assert kept.off_centre == 15 and row("gmm", [2, 0, 1]).off_centre is None
    table = report.table1(with_rows(record, row("actuators", [9, 8, 7]), kept))
    header, _, unkept, gmm = table.splitlines()[:4]
    assert header.endswith("| off-centre per 100 mi |")
    assert unkept.endswith("| - |") and gmm.endswith("| 5.0 |")
    assert "for more than 3 s" in table


def test_every_step_of_the_record_is_taught_in_one_session() -> None:
    """The kit's sessions name the record's steps by their names: a renamed or a new step must
    not drop out of the kit unnoticed."""
    taught = [name for _, names in kit.SESSIONS.values() for name in names]
    assert sorted(taught) == sorted(st.what for st in STEPS)


def test_the_kit_names_the_recipes_its_record_drove() -> None:
    """A course run's chapters may be newer than the record's recipes (chapter 12 was rewritten
    after the record of 321f6a9): the kit's record sentences name the recipes' commit."""
    record = report.load()
    commit = record.block.recipes_commit
    findings = kit.session_findings(None, record)
    assert findings.count(f"The record (recipes {commit}): ") == sum(
        1 for _, steps_taught in kit.SESSIONS.values() if steps_taught
    )
    unnamed = dataclasses.replace(
        record, block=dataclasses.replace(record.block, recipes_commit=None)
    )
    assert "The record: " in kit.session_findings(None, unnamed)


def test_the_status_says_seed_zero_rows_were_trained_on_each_machine_when_there_are_several():
    """A share trains its own seed 0 for the single-seed rows: pooled from two machines, those
    rows hold two networks, and the record's first sentence says so (one machine: it does not)."""
    from types import SimpleNamespace

    from e2e_lite.record.pool import status

    def share(seeds: list[int]) -> SimpleNamespace:
        return SimpleNamespace(seeds=seeds, miles_per_seed=200.0, single_seed_rows=["pilotnet"])

    shares = [("a", share([24, 25])), ("b", share([26]))]
    one = status(shares, ["AMD EPYC, 2 cores, 2 workers, cpu"])
    two = status(
        shares, ["AMD EPYC, 2 cores, 2 workers, cpu", "Intel Xeon, 2 cores, 2 workers, cpu"]
    )
    assert "seed 0 alone, 600 mi" in one and "2 shares on 1 machine of 1 kind" in one
    assert "seed 0 alone, trained on each machine, 600 mi" in two
    assert "on 2 machines of 2 kinds" in two


def test_every_step_reads_both_outcomes_and_a_better_driver_needs_both() -> None:
    """Issue 88: each step is tested on its off-centre episodes too (interventions that were
    neither collisions nor stalls), seed by seed; a step with fewer collisions and more off-centre
    episodes is said to be that, and not a better driver; a reading after the record ran can
    refute a better driver but not make one."""

    def kept(key: str, collisions: list[int], off: list[int], stalls: int = 1) -> Row:
        base = row(key, collisions)
        seeds = tuple(
            dataclasses.replace(s, interventions=c + o + stalls, stalls=stalls)
            for s, c, o in zip(base.seeds, collisions, off)
        )
        return dataclasses.replace(base, seeds=seeds, stalls=stalls * len(seeds))

    start = kept("gmm_affordance_cvar", [4, 5, 6, 5, 4, 6], [1, 0, 1, 2, 1, 0])
    drifted = kept("dagger", [1, 2, 1, 2, 1, 2], [30, 40, 35, 50, 45, 38])
    record = with_rows(report.load(), row("expert", [0]), start, drifted)
    (off,) = off_centre_steps(record)
    assert off.step == "+ CVaR -> + DAgger" and off.family == OFF_CENTRE_READING
    assert words.off_centre(off) == "more off-centre episodes"  # every seed, paired: p 1/64
    assert start.seeds[0].off_centre == 1  # (its stall is no off-centre episode)
    (collisions,) = steps(record)
    said = words.better_driver(collisions, off)
    assert said == "fewer collisions, more off-centre episodes: not a better driver"
    table = report.table1(record)
    assert "| a better driver? |" in table and said in table
    assert "were not declared" in table
    # both outcomes better: a reading cannot make it a better driver, a declared test can
    kept_lane = kept("dagger", [1, 2, 1, 2, 1, 2], [0, 0, 0, 0, 0, 0])
    (off,) = off_centre_steps(with_rows(record, start, kept_lane))
    assert words.better_driver(collisions, off).startswith("not shown")
    declared = dataclasses.replace(off, family="beyond")
    assert words.better_driver(collisions, declared) == "a better driver"


def test_a_record_that_declares_both_outcomes_tests_each_in_its_family_and_over_all() -> None:
    """Issue 88, item 5: the next record declares every step on both outcomes before it runs,
    DAgger against no new data among them; each test is Holm-adjusted in its family and over
    every test of the record (never below the family's), the table shows both, and a declared
    off-centre test can make a better driver. The committed record, declared before, is read as
    it declared (its steps and its off-centre reading unchanged)."""
    from e2e_lite.record.stats import declares_off_centre, family

    def kept(key: str, collisions: list[int], off: list[int]) -> Row:
        base = row(key, collisions)
        seeds = tuple(
            dataclasses.replace(s, interventions=c + o, stalls=0)
            for s, c, o in zip(base.seeds, collisions, off)
        )
        return dataclasses.replace(base, seeds=seeds)

    rows = (
        row("expert", [0]),
        kept("gmm_affordance_cvar", [4, 5, 6, 5, 4, 6, 5, 6], [1, 0, 1, 2, 1, 0, 1, 1]),
        kept("dagger", [1, 2, 1, 2, 1, 2, 1, 1], [1, 0, 0, 1, 1, 0, 1, 0]),
        kept("dagger_no_new_data", [4, 4, 5, 6, 4, 5, 6, 5], [0, 1, 1, 1, 0, 1, 1, 1]),
        kept("dagger_control", [3, 4, 5, 5, 4, 4, 5, 5], [1, 1, 0, 1, 1, 1, 0, 1]),
    )
    old = report.load()
    assert not declares_off_centre(old)
    assert "DAgger against its fine-tunes on no new data" not in {s.step for s in steps(old)}
    new = dataclasses.replace(with_rows(old, *rows), family=family("before it ran"))
    assert declares_off_centre(new) and new.family.reason
    tested, off = steps(new), off_centre_steps(new)
    assert {s.step for s in tested} == {s.step for s in off}
    assert "DAgger against its fine-tunes on no new data" in {s.step for s in tested}
    for st in (*tested, *off):
        assert st.family != OFF_CENTRE_READING
        assert st.p_holm_all_fewer >= st.p_holm_fewer - 1e-12
    dagger = {s.step: s for s in tested}["+ CVaR -> + DAgger"]
    dagger_off = {s.step: s for s in off}["+ CVaR -> + DAgger"]
    assert dagger.measure == "collisions" and dagger_off.measure == "off_centre"
    assert words.better_driver(dagger, dagger_off) in (
        "a better driver",
        "not shown to be a better driver",
    )
    table = report.table1(new)
    assert "(all: " in table and "Why: a family is one question" in table
    assert "were not declared" not in table


def test_a_new_record_takes_fresh_seeds() -> None:
    """Issue 88: seeds that trained the course's networks or an earlier record are refused for a
    record of the fresh block, before any work starts (the quick smoke run takes any)."""
    from e2e_lite.config import FULL
    from e2e_lite.record.run import FRESH_SEEDS_FROM, record_share

    with pytest.raises(ValueError, match=f"fresh block takes seeds {FRESH_SEEDS_FROM} and up"):
        record_share(FULL, [FRESH_SEEDS_FROM - 1, FRESH_SEEDS_FROM])
    assert FRESH_SEEDS_FROM >= 58  # (38-57: the record of 7a36b30, one expert)


def test_a_step_that_holm_keeps_above_the_cut_whatever_the_seeds_is_undecidable() -> None:
    """A review's finding: 4 seeds against 4 reach a rank p of 1/70 at best; in a family of six
    (three steps on both outcomes) Holm takes even that to 6/70 > 0.05, so no data could decide
    the step: "undecidable", not "not shown" (which says the seeds could have shown it). In a
    family of two the same seeds still decide (2/70 < 0.05)."""
    from e2e_lite.record.stats import FEWER, UNDECIDABLE, StepResult, _read_at_holm

    best = StepResult(
        "a step",
        "f",
        None,
        1 / 70,
        1.0,
        1 / 70,
        "rank",
        1 / 70,
        None,
        0.1,
        (0.0, 0.5),
        None,
        (4, 4),
    )
    six = _read_at_holm([dataclasses.replace(best, step=f"step {k}") for k in range(6)])
    assert {r.outcome for r in six} == {UNDECIDABLE}
    assert six[0].p_holm_fewer == pytest.approx(6 / 70)
    two = _read_at_holm([best, dataclasses.replace(best, step="another")])
    assert {r.outcome for r in two} == {FEWER}
