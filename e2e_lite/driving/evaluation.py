"""Closed-loop evaluation: drive any policy on unseen tracks and count collisions per 100 miles.

:func:`evaluate` is the composition of four layers, each a module of its own:

* :mod:`e2e_lite.simulation.policy`: what a driver sees and answers (:class:`Observation`,
  :class:`Actuation`, :class:`Policy`);
* :mod:`e2e_lite.driving.rollout`: the lockstep loop over B cars in B worlds, where cars (re)start, which
  roads each car drives (:class:`EvalConfig`, :func:`drive_shard`);
* :mod:`e2e_lite.driving.parallel`: shards of the cars in threads or kept worker processes;
* :mod:`e2e_lite.driving.metrics`: what was measured (:class:`EvalResult`: collisions per 100 miles with
  exact Poisson intervals, time to collision, autonomy, stalls) and how to pool it.

Their public names are re-exported here, so a chapter imports the evaluation from one module; the
tests that compare results are :mod:`e2e_lite.stats`'.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ..config import check_range, default_workers, tqdm
from ..simulation.policy import FORWARD_GROUP, Actuation, Observation, Policy, observe  # noqa: F401 (re-exported)
from ..simulation.world import WorldConfig
from .metrics import (  # noqa: F401 (re-exported: the chapters read the evaluation's names here)
    COLLISION_KINDS,
    M_PER_MILE,
    MPS_TO_MPH,
    SPEED_BINS,
    EvalResult,
    collision_kinds,
    merge_shards,
    miles_text,
    pool_results,
    results_table,
    speed_histogram,
)
from .parallel import (  # noqa: F401 (close_shard_workers re-exported, as above)
    close_shard_workers,
    drive_in_processes,
    drive_in_threads,
    pinned_threads,
    processes_ok,
    shard_job,
    shard_worker,
)
from .rollout import (  # noqa: F401 (re-exported, as above)
    EvalConfig,
    check_policy_rate,
    disjoint_runs,
    drive,
    drive_shard,
    restart_state,
    start_lane,
    start_state,
    track_index,
)

#: the least road that ``parallel="auto"`` starts worker processes for [mi]: the workers' start
#: (an interpreter and torch each, in parallel) costs about as much as driving 3-5 mi on one core,
#: and they are kept for the next evaluations; shorter drives run their shards in threads
MIN_MILES_PER_WORKER = 5.0


def shard_cars(n_cars: int, workers: int) -> list[np.ndarray]:
    r"""The cars ``0 .. n_cars - 1`` cut into at most ``workers`` shards of whole
    :data:`~e2e_lite.simulation.policy.FORWARD_GROUP`\ s, in order (so a network sees every frame
    in the same group of frames whatever the count: the events do not depend on it)."""
    n_groups = -(-n_cars // FORWARD_GROUP)  # the last group may be short
    split = np.array_split(np.arange(n_groups), min(workers, n_groups))
    return [
        np.arange(part[0] * FORWARD_GROUP, min(n_cars, (part[-1] + 1) * FORWARD_GROUP))
        for part in split
    ]


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
    ``miles / B``. The cars are cut into shards (:func:`shard_cars`), each driven with its own
    copy of the policy (a policy that can be split has a ``fork(k)`` method returning ``k``
    independent copies) in a worker process (an interpreter of its own, ``python -m
    e2e_lite.driving.shard_worker``, the job pickled to it; started once and kept for the next
    evaluations, see :func:`close_shard_workers`), or in threads where the policy's class cannot
    be unpickled there (:func:`processes_ok`). What a policy reports with its actuations
    (``Actuation.info``) is added up over the decisions and shards into ``result.info``.

    The result does not depend on ``workers``: each car draws its own start lanes, a network sees
    its frames in the same groups, and every shard's torch runs on one thread (see
    :mod:`e2e_lite.driving.parallel`). So the default is every core.

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
        workers: shards (threads or processes, see ``parallel``); default
            :func:`~e2e_lite.config.default_workers` (every core, or ``E2E_LITE_WORKERS``),
            capped by the groups of cars. A policy without ``fork``, or a call with
            ``stop_when``, runs in one.
        parallel: how shards run: ``"auto"`` (processes where possible, see above, for a drive
            of at least :data:`MIN_MILES_PER_WORKER`; else threads),
            ``"threads"`` or ``"processes"`` (the policy must pickle; its forks' state stays in
            the workers: report what the caller needs through ``Actuation.info``; a policy
            with ``threads_only`` set is refused).
    """
    t_wall = time.perf_counter()
    n = cfg.n_worlds
    check_policy_rate(policy, world_cfg)
    workers = default_workers() if workers is None else workers
    check_range("evaluate", "workers", workers, 1, integer=True)
    if parallel not in ("auto", "threads", "processes"):
        raise ValueError(f"parallel must be 'auto', 'threads' or 'processes', not {parallel!r}")
    if parallel == "processes" and getattr(policy, "threads_only", False):
        raise ValueError(
            f"{type(policy).__name__} keeps its states in this process: not 'processes'"
        )
    if stop_when is not None or not hasattr(policy, "fork"):
        workers = 1
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

    cars = shard_cars(n, workers)
    try:
        if len(cars) == 1:
            with pinned_threads():  # (as in the shards: parallel.SHARD_TORCH_THREADS)
                shards = [
                    drive_shard(policy, world_cfg, cfg, cars[0], advance, record_traces, stop_when)
                ]
        else:
            policies = policy.fork(len(cars))  # type: ignore[attr-defined]
            jobs = [shard_job(p, world_cfg, cfg, c, record_traces) for p, c in zip(policies, cars)]
            if parallel == "auto":  # (a drive too short to pay its workers' start: threads)
                short = cfg.miles < MIN_MILES_PER_WORKER
                parallel = "processes" if processes_ok(policy) and not short else "threads"
            run = drive_in_processes if parallel == "processes" else drive_in_threads
            shards = run(jobs, advance)
    finally:
        bar.close()
    return merge_shards(shards, cfg.intervention_cost_s, time.perf_counter() - t_wall)
