"""Closed-loop evaluation: drive any policy on unseen tracks and count collisions per 100 miles.

:func:`evaluate` is the composition of four layers, each a module of its own:

* :mod:`e2e_lite.simulation.policy`: what a driver sees and answers (:class:`Observation`,
  :class:`Actuation`, :class:`Policy`);
* :mod:`e2e_lite.driving.rollout`: the lockstep loop over B cars in B worlds, where cars (re)start, which
  roads each car drives (:class:`EvalConfig`, :func:`drive_shard`);
* :mod:`e2e_lite.driving.parallel`: shards of the cars in threads or kept worker processes;
* :mod:`e2e_lite.driving.metrics`: what was measured (:class:`EvalResult`: collisions per 100 miles with
  exact Poisson intervals, time to collision, autonomy, stalls) and how to compare and pool it.

Their public names are re-exported here, so a chapter imports the evaluation from one module.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ..config import check_range, tqdm
from ..simulation.policy import Actuation, Observation, Policy, observe  # noqa: F401 (re-exported)
from ..simulation.world import WorldConfig
from .metrics import (  # noqa: F401 (re-exported: the chapters read the evaluation's names here)
    COLLISION_KINDS,
    M_PER_MILE,
    MPS_TO_MPH,
    SPEED_BINS,
    EvalResult,
    collision_kinds,
    compare_rates,
    compare_seeds,
    merge_shards,
    miles_text,
    poisson_ci,
    pool_results,
    result_dict,
    result_events,
    result_info,
    results_table,
    seed_rates,
    speed_histogram,
)
from .parallel import (  # noqa: F401 (close_shard_workers re-exported, as above)
    close_shard_workers,
    drive_in_processes,
    drive_in_threads,
    pinned_threads,
    processes_ok,
    shard_threads,
    shard_worker,
)
from .rollout import (  # noqa: F401 (re-exported, as above)
    EvalConfig,
    check_policy_rate,
    disjoint_runs,
    drive,
    drive_shard,
    restart_state,
    roll_out,
    start_state,
    track_index,
)


def evaluate(
    policy: Policy,
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    *,
    progress: bool = True,
    desc: str = "closed loop",
    record_traces: bool = False,
    stop_when: Callable[[], bool] | None = None,
    workers: int | None = None,
    parallel: str = "auto",
) -> EvalResult:
    """Drive ``policy`` closed-loop until ``cfg.miles`` are driven; return the metrics.

    Car ``i`` drives tracks ``f + i, f + i + B, ...`` (:func:`track_index`) until it has driven
    ``miles / B``. With
    ``workers > 1`` the cars are split into that many shards, each driven with its own copy of
    the policy: a policy that can be split has a ``fork(k)`` method returning ``k`` independent
    copies. The shards run in worker processes (interpreters of their own, ``python -m
    e2e_lite.driving.shard_worker``, the job pickled to them; started once and kept for the next
    evaluations, see :func:`close_shard_workers`) unless the policy's class cannot be unpickled
    there (:func:`processes_ok`); then in threads (the network's forward
    pass releases the GIL, so one shard renders and steps physics while the other runs
    convolutions, but their Python still takes turns). What a policy reports with its actuations
    (``Actuation.info``) is added up over the decisions and shards into ``result.info``. Either way the torch threads
    are shared out (one core per shard on two cores) and the results are the same. Each shard
    draws its cars' start lanes from its own generator (shard 0's is the one a single thread
    uses), so ``workers`` is part of the settings: compare drivers evaluated with the same value
    (chapter 10 uses 2 for every driver).

    Args:
        policy: the driver (see :class:`Policy`).
        world_cfg: roads, traffic, car and time steps.
        cfg: the evaluation settings.
        progress: show a progress bar of miles driven.
        desc: the progress bar's label.
        record_traces: keep every car's rear-axle path per track (for top-down figures), in
            ``result.traces["<split>-<track>"] = [[x, y], ...]``.
        stop_when: called after every decision; the drive ends early when it returns True (the
            data collector stops at a sample count this way). The metrics cover what was driven.
        workers: shards of cars (threads or processes, see ``parallel``), default 1; a policy
            without ``fork``, or a call with ``stop_when``, always runs in one. The network then sees batches of
            ``B / workers`` frames on ``1 / workers`` of the cores.
        parallel: how shards run: ``"auto"`` (processes where possible, see above),
            ``"threads"`` or ``"processes"`` (the policy must pickle; its forks' state stays in
            the workers: report what the caller needs through ``Actuation.info``).
    """
    t_wall = time.perf_counter()
    n = cfg.n_worlds
    check_policy_rate(policy, world_cfg)
    workers = 1 if workers is None else workers
    check_range("evaluate", "workers", workers, 1, integer=True)
    if parallel not in ("auto", "threads", "processes"):
        raise ValueError(f"parallel must be 'auto', 'threads' or 'processes', not {parallel!r}")
    if stop_when is not None or not hasattr(policy, "fork"):
        workers = 1
    workers = min(workers, n)
    bar = tqdm(
        total=round(cfg.miles, 2),
        desc=desc,
        unit="mi",
        disable=not progress,
        leave=False,
        mininterval=0.5,
        bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} mi [{elapsed}<{remaining}]",
    )
    lock = threading.Lock()

    def advance(miles: float) -> None:
        with lock:  # (the shards' rounded sums may overshoot the total by a hair)
            bar.update(max(0.0, min(miles, bar.total - bar.n)))

    cars = np.array_split(np.arange(n), workers)
    if workers == 1:
        with pinned_threads(1):  # (as in the shards: parallel.EVAL_TORCH_THREADS)
            shards = [
                drive_shard(policy, world_cfg, cfg, cars[0], 0, advance, record_traces, stop_when)
            ]
    else:
        policies = policy.fork(workers)  # type: ignore[attr-defined]
        jobs = [
            (p, world_cfg, cfg, c, k, record_traces) for k, (p, c) in enumerate(zip(policies, cars))
        ]
        if parallel == "auto":
            parallel = "processes" if processes_ok(policy) else "threads"
        if parallel == "processes":
            shards = drive_in_processes(jobs, advance)
        else:
            shards = drive_in_threads(jobs, advance)
    bar.close()
    return merge_shards(shards, cfg.intervention_cost_s, time.perf_counter() - t_wall)
