"""Ctrl-C stops a long evaluation at its next decision and prints one line, in threads and in
worker processes, and leaves no process behind; a worker that stops answering is stopped.

No test here asserts how many seconds something takes (machines differ by 2x and more): a stop
is bounded by what the code controls, the decisions a shard still makes after the signal, and a
timeout only guards against a hang (a drive that ignored Ctrl-C would run for many minutes)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

DRIVE = """
import signal
import sys
import time
import torch
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.imitation.agents import TrajectoryAgent
from e2e_lite.learning.models import ModelConfig, build_model, prepare
from e2e_lite.simulation.world import WorldConfig

# count the decisions made in this process (the shards of "threads"; a worker process imports
# its own, uncounted copy), and note the count when Ctrl-C arrives
decisions, at_signal = [0], [None]
act = TrajectoryAgent.act
def counted(self, obs):
    decisions[0] += 1
    return act(self, obs)
TrajectoryAgent.act = counted
def on_sigint(signum, frame):
    at_signal[0] = decisions[0]
    raise KeyboardInterrupt
signal.signal(signal.SIGINT, on_sigint)

torch.manual_seed(0)
model = prepare(build_model(ModelConfig(head="trajectory", fusion_width=16)), torch.device("cpu"))
policy = TrajectoryAgent(model.eval())
try:
    if sys.argv[2] in ("idle", "warm"):  # one short evaluation; its workers are kept, idle
        evaluate(policy, WorldConfig(), EvalConfig(miles=0.05, n_worlds=16), progress=False,
                 workers=2, parallel=sys.argv[1])
    if sys.argv[2] == "idle":
        print("driving", flush=True)
        time.sleep(600)
    if sys.argv[2] == "warm":  # the workers started: give them 3 s to answer (60 in the course)
        from e2e_lite.driving import parallel
        parallel.DEADLINE_S = 3.0
    print("driving", flush=True)
    evaluate(policy, WorldConfig(), EvalConfig(miles=1000.0, n_worlds=16), progress=False,
             workers=2, parallel=sys.argv[1])
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr, flush=True)
    print(f"after the signal {decisions[0] - at_signal[0]} of {decisions[0]}", flush=True)
    sys.exit(130)
"""


def _marked(marker: str) -> list[int]:
    """Processes whose environment carries ``marker`` (the test's child and its workers)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker.encode() in (entry / "environ").read_bytes():
                found.append(int(entry.name))
        except OSError:
            continue
    return found


def _start(parallel: str, when: str, tmp_path: Path) -> tuple[subprocess.Popen, str]:
    """The drive in a child of its own process group, marked; returns it once it drives."""
    marker = f"E2E_LITE_TEST_MARK={uuid.uuid4().hex}"
    env = {**os.environ, marker.split("=")[0]: marker.split("=")[1]}
    proc = subprocess.Popen(
        [sys.executable, "-c", DRIVE, parallel, when],
        env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,  # its own process group: Ctrl-C reaches it and its workers
    )  # fmt: skip
    assert proc.stdout.readline().strip() == "driving"
    return proc, marker


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize(
    "parallel, when",
    [("threads", "driving"), ("processes", "driving"), ("processes", "idle")],
)
def test_ctrl_c_stops_an_evaluation_at_its_next_decision_with_one_line(parallel, when, tmp_path):
    """Ctrl-C while the shards drive, or between evaluations with the workers kept idle (they
    each printed a KeyboardInterrupt traceback before). In threads, each of the two shards makes
    at most two decisions after the signal (the one under way, and one before the stop reaches
    it); in processes, the workers ignore Ctrl-C and the parent ends them: none is left, and
    the parent's evaluation of 1,000 mi ends with Ctrl-C's exit code."""
    proc, marker = _start(parallel, when, tmp_path)
    try:
        time.sleep(4.0)  # the workers started and the shards are driving
        assert proc.poll() is None, proc.stderr.read()
        if parallel == "processes":
            assert len(_marked(marker)) == 3  # the child and its two workers (kept if idle)
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
        proc.wait(timeout=60)  # a hang guard, not a measure: 1,000 mi take many minutes
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    err, out = proc.stderr.read(), proc.stdout.read()
    assert proc.returncode == 130, err
    assert err.strip() == "interrupted", err  # one line: no traceback of a worker or a thread
    after, made = map(int, re.fullmatch(r"after the signal (\d+) of (\d+)", out.strip()).groups())
    if parallel == "threads":
        assert made > 0 and after <= 2 * 2, (after, made)  # two shards, at most two each
    else:
        assert made == 0  # every decision was a worker's
    time.sleep(0.2)
    assert _marked(marker) == []  # no process left


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux's /proc")
def test_workers_whose_parent_is_killed_mid_drive_exit_quietly(tmp_path):
    """A parent killed outright (no Ctrl-C handling): its workers find the pipe closed, and end
    without a traceback (about 25 lines of chained BrokenPipeError each, before)."""
    proc, marker = _start("processes", "driving", tmp_path)
    time.sleep(4.0)
    assert len(_marked(marker)) == 3
    os.kill(proc.pid, signal.SIGKILL)  # the parent only
    proc.wait(timeout=10)
    deadline = time.perf_counter() + 10.0
    while _marked(marker) and time.perf_counter() < deadline:
        time.sleep(0.1)
    assert _marked(marker) == []  # the workers ended by themselves
    err = proc.stderr.read()  # (the workers wrote to the same stderr)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err[-3000:]


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux's /proc")
def test_a_drive_stopped_with_its_workers_and_continued_drives_on(tmp_path):
    """Ctrl-Z, then ``fg`` after longer than the workers' deadline: the whole group stood
    still, so the stop is not the workers' silence and the drive goes on (before, the parent
    woke, saw no message for longer than the deadline and killed its workers)."""
    proc, marker = _start("processes", "warm", tmp_path)  # the workers' deadline 3 s
    try:
        time.sleep(2.0)  # the shards are driving
        os.killpg(proc.pid, signal.SIGSTOP)  # as Ctrl-Z stops a terminal's foreground group
        time.sleep(5.0)  # longer than the deadline
        os.killpg(proc.pid, signal.SIGCONT)
        time.sleep(4.0)  # the deadline again, now watched: the shards are heard
        assert proc.poll() is None, proc.stderr.read()
        assert len(_marked(marker)) == 3  # the child and its two workers, none killed
        os.killpg(proc.pid, signal.SIGINT)  # then stopped as Ctrl-C stops it
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, proc.stderr.read()


def test_silence_counts_only_the_time_the_parent_watched():
    from e2e_lite.driving.parallel import LOOK_GAP_S, Silence

    silence = Silence(2, now=0.0)
    for t in range(1, 9):  # looks every 0.5 s; shard 0 heard at each
        silence.look(0.5 * t, heard=0)
    assert silence.quiet == [0.0, 4.0] and silence.overdue(3.0, done={}) == 1
    assert silence.overdue(3.0, done={1: "its result"}) is None
    silence.look(4.0 + 600.0)  # the group stopped for 10 min, then continued
    assert silence.quiet == [LOOK_GAP_S, 4.0 + LOOK_GAP_S]


STUCK = """
import time
from e2e_lite.driving import parallel
from e2e_lite.driving.evaluation import EvalConfig, evaluate
from e2e_lite.simulation.world import WorldConfig
from tests_stuck import Stuck

parallel.DEADLINE_S = 2.0
try:
    evaluate(Stuck(), WorldConfig(), EvalConfig(miles=1.0, n_worlds=16), progress=False,
             workers=2, parallel="processes")
except RuntimeError as err:
    print(str(err).splitlines()[0])
"""

STUCK_POLICY = """
import time
from e2e_lite.control.drivers import LaneKeeper

class Stuck(LaneKeeper):
    '''A lane keeper whose second shard hangs at its first decision.'''
    shard = 0
    def fork(self, k):
        out = [Stuck() for _ in range(k)]
        for j, p in enumerate(out):
            p.shard = j
        return out
    def act(self, obs):
        if self.shard == 1:
            time.sleep(3600)
        return super().act(obs)
"""


def test_a_worker_that_stops_answering_is_stopped_with_one_line(tmp_path):
    (tmp_path / "tests_stuck.py").write_text(STUCK_POLICY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    out = subprocess.run(
        [sys.executable, "-c", STUCK], env=env, cwd=tmp_path, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().startswith("evaluation shard 1 (process ")
    # the deadline stopped it (subprocess's timeout only guards against a hang)
    assert "sent nothing for 2 s: stopped" in out.stdout
