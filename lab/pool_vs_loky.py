"""The course's shard pool (:mod:`e2e_lite.driving.parallel`) against loky's reusable executor,
when loky is installed (``pip install loky``), on chapter 10's drive: the first call (workers
started), a second call (workers kept), and Ctrl-C in a child driving 1,000 mi (seconds to exit,
lines on stderr, processes left behind). Its figures and the choice they led to are in
docs/benchmarks.md and the pool's module docstring. (Was ``python -m e2e_lite.course.bench pool`` until
the choice was made; a one-off experiment, so it lives in lab/.)

    python lab/pool_vs_loky.py [--quick]
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from e2e_lite.config import active_profile
from e2e_lite.driving import parallel
from e2e_lite.driving.evaluation import shard_cars
from e2e_lite.driving.metrics import M_PER_MILE
from e2e_lite.driving.rollout import EvalConfig
from e2e_lite.simulation.world import WorldConfig


def _pool_jobs(miles: float, driver: Callable) -> list[tuple]:
    """Chapter 10's drive as two shards' jobs (``driver("gmm", device)``'s network, 64 cars,
    ``miles`` in all)."""
    policy, _ = driver("gmm", torch.device("cpu"))
    world_cfg = WorldConfig.for_profile(active_profile([]))
    ev = EvalConfig(miles=miles, n_worlds=64, n_tracks=16)
    cars = shard_cars(ev.n_worlds, 2)
    return [parallel.shard_job(p, world_cfg, ev, c, False) for p, c in zip(policy.fork(2), cars)]


def _loky_shard(job: tuple, threads: int) -> object:
    """One shard in a loky worker, torch on ``threads`` threads (no progress stream: loky has
    none, so the caller hears of a shard only when it ends)."""
    torch.set_num_threads(threads)
    return parallel.run_job(job, lambda miles: None)


def _drive_with(pool: str, jobs: list[tuple]) -> list:
    """Drive ``jobs`` with the course's pool (``"ours"``) or loky's reusable executor."""
    if pool == "ours":
        return parallel.drive_in_processes(jobs, lambda miles: None)
    import loky

    executor = loky.get_reusable_executor(max_workers=len(jobs))
    threads = parallel.SHARD_TORCH_THREADS
    futures = [executor.submit(_loky_shard, job, threads) for job in jobs]
    try:
        return [f.result() for f in futures]
    except BaseException:  # Ctrl-C: its way to end the running shards (else the exit waits)
        executor.shutdown(wait=False, kill_workers=True)
        raise


def _pool_child(pool: str, driver: Callable) -> None:
    """The Ctrl-C trial's child: say "driving", then drive 1,000 mi with ``pool``."""
    jobs = _pool_jobs(1_000.0, driver)
    print("driving", flush=True)
    try:
        _drive_with(pool, jobs)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)


def _ctrl_c(pool: str, after_s: float = 3.0) -> dict[str, float]:
    """SIGINT a child that drives with ``pool``, ``after_s`` after it starts driving: seconds until
    it exits, lines it wrote to stderr, and processes of its own left running 2 s later."""
    import signal
    import subprocess
    import tempfile
    import uuid

    token = uuid.uuid4().hex
    with tempfile.TemporaryFile("w+") as err:  # (a file: workers left behind may hold a pipe)
        child = subprocess.Popen(
            [sys.executable, "-c", f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
             "from e2e_lite.course.bench import learned_driver; from pool_vs_loky import _pool_child; "
             f"_pool_child({pool!r}, learned_driver)"],
            stdout=subprocess.PIPE, stderr=err, text=True,
            env={**os.environ, "E2E_POOL_TRIAL": token},
        )  # fmt: skip
        assert child.stdout is not None
        child.stdout.readline()  # "driving"
        time.sleep(after_s)
        t0 = time.perf_counter()
        child.send_signal(signal.SIGINT)
        try:
            child.wait(timeout=60)
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
        exit_s = time.perf_counter() - t0
        child.stdout.close()
        time.sleep(2.0)
        err.seek(0)
        stderr = err.read()
    left = 0
    for environ in Path("/proc").glob("[0-9]*/environ"):
        with contextlib.suppress(OSError):
            if f"E2E_POOL_TRIAL={token}".encode() in environ.read_bytes():
                left += 1
                os.kill(int(environ.parent.name), signal.SIGKILL)
    return {"exit_s": exit_s, "stderr_lines": len(stderr.splitlines()), "left": left}


def bench_pool(quick: bool, driver: Callable) -> dict[str, float]:
    """The course's shard pool against loky's reusable executor on chapter 10's drive (64 cars,
    two processes, 20 mi a call; quick: 2): wall seconds of the first call (the workers start)
    and of a second one (kept), and Ctrl-C in a child (see :func:`_ctrl_c`). ``driver``: the
    bench's ``learned_driver``."""
    import importlib.util

    pools = ["ours"] + (["loky"] if importlib.util.find_spec("loky") else [])
    if len(pools) == 1:
        print("loky is not installed (pip install loky): the course's pool alone")
    out: dict[str, float] = {}
    for pool in pools:
        parallel.close_shard_workers()
        for call in ("first", "second"):
            jobs = _pool_jobs(2.0 if quick else 20.0, driver)
            t0 = time.perf_counter()
            shards = _drive_with(pool, jobs)
            wall = time.perf_counter() - t0
            miles = sum(float(s.car_miles_m.sum()) for s in shards) / M_PER_MILE
            out[f"{pool}_{call}_call_s"] = wall
            out[f"{pool}_{call}_sim_miles_per_wall_s"] = miles / wall
        out[f"{pool}_collisions"] = sum(len(s.events) for s in shards)
        for k, v in _ctrl_c(pool, 1.0 if quick else 3.0).items():
            out[f"{pool}_ctrl_c_{k}"] = v
    parallel.close_shard_workers()
    return out


if __name__ == "__main__":
    from e2e_lite.course.bench import learned_driver

    for key, value in bench_pool("--quick" in sys.argv, learned_driver).items():
        print(f"  {key:36s} {value:,.2f}")
