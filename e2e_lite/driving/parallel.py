"""Shards of one evaluation (or of one data collection), driven side by side: in threads, or in
worker processes (``python -m e2e_lite.driving.shard_worker``) that are started once and kept for
the next jobs of the same interpreter (:func:`close_shard_workers` ends them; also done at exit). A
job ``(function, args, kwargs)`` is pickled to its worker, which calls ``function(*args,
advance=..., **kwargs)`` (for an evaluation, :func:`~e2e_lite.driving.rollout.drive_shard`) and
sends back its progress and its result.

Why a small pool of our own rather than the field's (joblib's loky, ``concurrent.futures``):
the workers must be fresh interpreters (a fork of a process whose torch threads ran can deadlock,
and one that started CUDA must not fork), must be kept between the evaluations of a chapter (an
interpreter and torch's import cost about 1 s each time), must stream progress while a shard
drives, and must leave their thread count to the evaluator (the results depend on it). loky's
reusable executor brings the first two. ``python -m e2e_lite.course.bench pool`` drives chapter 10's
64 cars in two processes with both (docs/benchmarks.md has the figures): the same events, the
same speed within the runs' noise, first call and kept workers alike. What decides it: loky
streams no progress (a shard is heard of when it ends, so the bar would jump), and on Ctrl-C
its executor waits at exit for the running shards, and leaves its workers and its resource
tracker driving, unless the caller shuts it down with ``kill_workers=True``; with that, both
stop in about 0.6 s. Equal speed and stopping, for a dependency (loky and cloudpickle) and no
progress bar: the pool stays ours.

Stopping: Ctrl-C (or any exception) in the parent stops every shard at its next decision (a stop
flag that the threads' shard loops check, the worker processes killed), and idle workers exit
quietly on Ctrl-C and when their parent's pipe closes. A worker that sends nothing for
:data:`DEADLINE_S` while it owes a result is killed, with one line naming it; the time a drive
stood stopped with its workers (Ctrl-Z, then ``fg``) is not counted as their silence.

Results do not depend on the number of shards: every random choice is a car's own
(:func:`~e2e_lite.simulation.policy.car_rng`), a network sees its frames in the same groups
(:data:`~e2e_lite.simulation.policy.FORWARD_GROUP`) in every shard, and each shard's torch runs on
:data:`SHARD_TORCH_THREADS` thread (torch's kernels round differently with other thread counts,
and a closed loop amplifies the difference). So an evaluation uses every core
(:func:`~e2e_lite.config.default_workers`) and still gives the same events on any machine.
"""

from __future__ import annotations

import atexit
import contextlib
import pickle
import queue
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from ..simulation.policy import Policy
from .metrics import ShardResult
from .rollout import drive_shard

#: torch threads of every shard of an evaluation, in a worker or in this process. One: a shard per
#: core, and the same rounding in every shard (see the module docstring).
SHARD_TORCH_THREADS = 1
#: a worker that owes a result and sends nothing for this long is killed [s] (a shard sends
#: progress at least every 0.25 s while it drives)
DEADLINE_S = 60.0
#: the longest gap between two looks at the workers that counts as watching them [s]: a longer
#: one is the parent stopped with its workers (Ctrl-Z, then ``fg``), not a worker's silence
LOOK_GAP_S = 1.0


@contextlib.contextmanager
def pinned_threads() -> Iterator[None]:
    """Torch (when loaded: the policy is a network) on :data:`SHARD_TORCH_THREADS` threads for the
    shards driven in this process, the caller's count given back after."""
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(SHARD_TORCH_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class _Stopped(Exception):
    """Raised inside a shard's loop when its evaluation was stopped."""


def processes_ok(policy: Policy) -> bool:
    """Shards may run in worker processes when a fresh interpreter can unpickle the policy: its
    class is not defined in a script run as ``__main__``. A network on a GPU goes too: each
    worker is a fresh interpreter (never a fork of one that started CUDA) and loads the network
    onto the device itself, which drove faster than threads sharing it in this process on a lent
    H200 (docs/benchmarks.md; ``python -m e2e_lite.course.bench scaling`` measures both on a
    GPU). What a policy's shards count comes home in their results (``Actuation.info``), so a
    policy never needs to know where it runs. A policy whose forks keep their states in this
    process says so (``threads_only``, e.g. the anatomy's witness) and is driven in threads."""
    return type(policy).__module__ != "__main__" and not getattr(policy, "threads_only", False)


def drive_in_threads(jobs: list[tuple], advance: Callable[[float], None]) -> list[Any]:
    """Run each job in its own thread (torch on :data:`SHARD_TORCH_THREADS` thread). An
    exception in the caller's thread (Ctrl-C) stops every shard at its next decision."""
    interval = sys.getswitchinterval()
    stop = threading.Event()

    def guarded(miles: float) -> None:
        if stop.is_set():
            raise _Stopped
        advance(miles)

    try:
        sys.setswitchinterval(5e-4)  # hand the GIL over soon after a forward pass ends
        with pinned_threads(), ThreadPoolExecutor(len(jobs)) as pool:
            futures = [pool.submit(run_job, job, guarded) for job in jobs]
            try:
                return [f.result() for f in futures]
            except BaseException:
                stop.set()  # the other shards stop at their next decision
                raise
    finally:
        sys.setswitchinterval(interval)


def run_job(job: tuple, advance: Callable[[float], None]) -> Any:
    """Run one job ``(function, args, kwargs)``: ``function(*args, advance=advance, **kwargs)``."""
    function, args, kwargs = job
    return function(*args, advance=advance, **kwargs)


def shard_job(policy: Policy, world_cfg: Any, cfg: Any, cars: Any, record_traces: bool) -> tuple:
    """The job that drives one shard of an evaluation (:func:`drive_shard` on ``cars``)."""
    return (drive_shard, (policy, world_cfg, cfg, cars), {"record_traces": record_traces})


def _send(stream: Any, message: Any) -> None:
    """One length-prefixed pickle on a binary stream (the shard workers' protocol)."""
    blob = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(len(blob).to_bytes(8, "little") + blob)
    stream.flush()


def _receive(stream: Any) -> Any:
    """The next message of :func:`_send` (EOFError when the writer is gone)."""
    head = stream.read(8)
    size = int.from_bytes(head, "little") if len(head) == 8 else -1
    blob = stream.read(size) if size >= 0 else b""
    if size < 0 or len(blob) < size:
        raise EOFError
    return pickle.loads(blob)


def shard_worker(inbox: Any, outbox: Any) -> None:
    """Body of a shard process (``python -m e2e_lite.driving.shard_worker``): for each job until its
    input ends, read ``(sys.path, torch threads, job)``, drive the shard, send ``("ready", None)``,
    progress ``("miles", m)`` now and then and finally ``("ok", shard)`` or ``("error",
    traceback)``. A worker serves its parent's evaluations until :func:`close_shard_workers`; it
    returns quietly when its parent is gone (its input ends, or its output pipe breaks)."""
    try:
        _serve(inbox, outbox)
    except (BrokenPipeError, ConnectionError):  # the parent is gone: nobody to tell
        return


def _serve(inbox: Any, outbox: Any) -> None:
    while True:
        try:
            sys.path[:] = _receive(inbox)  # where the parent found the policy's classes
        except (EOFError, OSError):  # the parent closed the pool, or is gone
            return
        try:
            torch_threads, job = _receive(inbox)
            if torch_threads > 0:  # the parent ran torch (0: it had not imported it)
                import torch  # (here: a worker loads torch only when its parent ran it)

                torch.set_num_threads(torch_threads)
            _send(outbox, ("ready", None))
            last = [time.perf_counter(), 0.0]

            def advance(m: float, last: list[float] = last) -> None:
                last[1] += m
                if time.perf_counter() - last[0] > 0.25:
                    _send(outbox, ("miles", last[1]))
                    last[:] = [time.perf_counter(), 0.0]

            result = run_job(job, advance)
            _send(outbox, ("miles", last[1]))
            _send(outbox, ("ok", result))
            del job, result  # the next job's policy replaces this one's
        except (BrokenPipeError, ConnectionError):
            raise  # the parent is gone (handled by shard_worker)
        except BaseException:  # everything goes back to the parent, which then ends the pool
            _send(outbox, ("error", traceback.format_exc()))
            return


class _Workers:
    """Shard processes kept alive between evaluations: an interpreter and the imports (about 1 s
    on a 2-core machine, most of it torch) are paid once per process instead of once per
    evaluation. Messages of every worker go to one queue as ``(k, message)``; an evaluation that
    fails or is interrupted ends them all (the next one starts fresh), so no message of an old
    job can reach a new one."""

    def __init__(self, n: int) -> None:
        self.messages: queue.Queue = queue.Queue()
        self.procs = []
        for k in range(n):
            proc = subprocess.Popen(
                [sys.executable, "-m", "e2e_lite.driving.shard_worker"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
            )
            self.procs.append(proc)
            threading.Thread(target=self._listen, args=(k, proc.stdout), daemon=True).start()

    def _listen(self, k: int, stream: Any) -> None:
        try:
            while True:
                self.messages.put((k, _receive(stream)))
        except (EOFError, OSError, ValueError):
            self.messages.put((k, ("gone", None)))

    def alive(self) -> bool:
        return all(proc.poll() is None for proc in self.procs)

    def close(self) -> None:
        """End every worker and wait. Workers are only closed idle (between evaluations) or
        after a failed one, so none holds anything worth a graceful exit: they are killed, which
        takes milliseconds where an interpreter's shutdown with torch takes most of a second."""
        for proc in self.procs:
            with contextlib.suppress(OSError, ValueError):
                proc.stdin.close()
            if proc.poll() is None:
                proc.kill()
        for proc in self.procs:
            proc.wait()
            proc.stdout.close()


_WORKERS: dict[int, _Workers] = {}


_WORKERS_LOCK = threading.Lock()


def close_shard_workers() -> None:
    """End the shard processes kept for later evaluations (also done when Python exits)."""
    with _WORKERS_LOCK:
        while _WORKERS:
            _WORKERS.popitem()[1].close()


atexit.register(close_shard_workers)


class Silence:
    """How long each of ``n`` shards has sent nothing while the parent watched [s]. A gap
    between two looks counts as at most :data:`LOOK_GAP_S`: a process group stopped and
    continued (Ctrl-Z, then ``fg``) stood still as a whole, so its workers were not silent."""

    def __init__(self, n: int, now: float) -> None:
        self.quiet = [0.0] * n
        self.last = now

    def look(self, now: float, heard: int | None = None) -> None:
        """A look at ``now`` [s, ``time.perf_counter``]; ``heard``: the shard a message came
        from."""
        watched = min(max(now - self.last, 0.0), LOOK_GAP_S)
        self.last = now
        self.quiet = [q + watched for q in self.quiet]
        if heard is not None:
            self.quiet[heard] = 0.0

    def overdue(self, deadline_s: float, done: Any) -> int | None:
        """The first shard not in ``done`` silent for longer than ``deadline_s`` [s], if any."""
        late = (k for k, q in enumerate(self.quiet) if k not in done and q > deadline_s)
        return next(late, None)


def drive_in_processes(jobs: list[tuple], advance: Callable[[float], None]) -> list[Any]:
    """Drive each job's shard in a worker process: no shared GIL, so one shard's rendering and
    physics never wait on the other's Python, and no ``fork`` of a process whose torch threads are
    running (that can deadlock the child). The workers are fresh interpreters (``python -m
    e2e_lite.driving.shard_worker``), started at the first evaluation that needs that many and kept for
    the next ones (:func:`close_shard_workers` ends them). Each gets its job pickled (policy,
    model included) and sends its :class:`ShardResult` back, with what the policy reported
    (``info``)."""
    torch = sys.modules.get("torch")
    per_shard = 0 if torch is None else SHARD_TORCH_THREADS
    started, ready, startup_s = time.perf_counter(), 0, 0.0
    with _WORKERS_LOCK:  # one evaluation at a time uses a pool
        workers = _WORKERS.pop(len(jobs), None)
    if workers is None or not workers.alive():
        if workers is not None:
            workers.close()
        workers = _Workers(len(jobs))
    results: dict[int, Any] = {}
    try:
        for k, job in enumerate(jobs):
            _send(workers.procs[k].stdin, list(sys.path))
            _send(workers.procs[k].stdin, (per_shard, job))
        silence = Silence(len(jobs), time.perf_counter())
        while len(results) < len(jobs):
            try:
                k, (status, payload) = workers.messages.get(timeout=0.5)
            except queue.Empty:
                k = None
            silence.look(time.perf_counter(), heard=k)
            late = silence.overdue(DEADLINE_S, results)
            if late is not None:
                raise RuntimeError(
                    f"evaluation shard {late} (process {workers.procs[late].pid}) sent nothing "
                    f"for {DEADLINE_S:.0f} s: stopped"
                )
            if k is None:
                continue
            if status == "miles":
                advance(payload)
            elif status == "ready":
                ready += 1
                if ready == len(jobs):
                    startup_s = time.perf_counter() - started
            elif status == "ok":
                results[k] = payload
            elif status == "error":
                raise RuntimeError(f"evaluation shard {k} failed:\n{payload}")
            elif k not in results:  # the worker's output ended before its result
                raise RuntimeError(
                    f"evaluation shard {k} died (exit code {workers.procs[k].wait()})"
                )
    except BaseException:
        for proc in workers.procs:  # a failed or interrupted evaluation ends its workers
            if proc.poll() is None:
                proc.kill()
        workers.close()
        raise
    with _WORKERS_LOCK:
        spare = _WORKERS.setdefault(len(jobs), workers)
    if spare is not workers:  # another thread kept a pool of this size meanwhile
        workers.close()
    for result in results.values():  # the workers' start, counted once in the merged timing
        if isinstance(result, ShardResult):
            result.timing["startup"] = startup_s / len(jobs)
    return [results[k] for k in range(len(jobs))]
