"""Benchmarks: one command for every speed figure in the README.

    python -m e2e_lite.course.bench NAME [--json] [--quick]

Readable lines by default; with ``--json`` the last line is one JSON object of the figures.
Benchmarks measure; they assert nothing (the tests do that).

Names:
    world   physics steps per second of one world with 80 parked cars, and closed-loop simulated
            miles per wall-second of the scripted drivers (B worlds in lockstep).
    camera  frames per second at 66x200 and 240x640 on busy curved scenes (10+ parked cars within
            100 m), rendered 16 at a time (as the evaluator does) and one by one.
    data    samples collected per second (noisy expert, frames, label rollouts, affordances), and
            the expert's and the oracle's closed-loop simulated miles per wall-second.
    train   training samples per second at batch 64: the bare train step (one batch in memory)
            and the real training loop, and their ratio (``loop_vs_bare``).
    network inference time per frame of the GMM fusion network by batch size, on one torch
            thread and on all of them.
    closed-loop [--agent pilotnet|actuators|gmm]   (default pilotnet)
            simulated miles per wall-second with camera + CNN in the loop, B = 64 in one shard,
            two threads and two processes, against the network alone (``loop_vs_network``), and
            where each frame's core-milliseconds go (``budget_*``).
    scaling [--agent ...]   (default gmm)
            driving with 1, 2, 4, ... and all worker processes, collecting with one and all:
            speed, speed-up, share of the ideal, and whether the results equal one worker's.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable

import numpy as np
import torch

from ..artifacts import artifact_path
from ..config import active_profile, available_cores
from ..control.drivers import LaneChanger, LaneKeeper
from ..control.expert import Expert
from ..control.oracle import Oracle
from ..driving.evaluation import FORWARD_GROUP, close_shard_workers, evaluate
from ..driving.parallel import SHARD_TORCH_THREADS
from ..driving.rollout import EvalConfig
from ..imitation import recipes
from ..imitation.agents import ActuatorAgent, NetworkAgent, SteeringAgent, TrajectoryAgent
from ..imitation.collector import DataConfig, DrivingDataset, collect, synthetic_data
from ..learning.checkpoints import load_checkpoint
from ..learning.losses import Objective
from ..learning.models import ModelConfig, build_model, images_to_tensor, pick_device, prepare
from ..learning.training import TrainConfig, fit
from ..simulation.camera import Camera, CameraConfig
from ..simulation.geometry import RoadConfig
from ..simulation.world import Fleet, TrafficConfig, WorldConfig, make_world


def _machine() -> dict[str, object]:
    return {
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
    }


def bench_world(quick: bool) -> dict[str, float]:
    """Physics steps/s with 80 parked cars; scripted closed-loop simulated miles per wall-second."""
    cfg = WorldConfig(road=RoadConfig(length_m=17_000.0), traffic=TrafficConfig(n_cars=(80, 80)))
    world = make_world(cfg, "test", 0)
    n_cars = len(world.cars)
    fleet = Fleet([world], cfg)
    fleet.place(0, 30.0, float(world.track.lane_center(0)), 25.0)
    steps = 2_000 if quick else 20_000
    # raw pymunk: set the ego's velocity and step the space
    t0 = time.perf_counter()
    for _ in range(steps):
        world.physics_step(25.0, 0.0, 0.0, cfg.sim.dt_s)
    raw = steps / (time.perf_counter() - t0)
    # the fleet's physics step: vectorised bicycle + pymunk, per car
    fleet.place(0, 30.0, float(world.track.lane_center(0)), 25.0)
    periods = steps // cfg.sim.steps_per_policy
    zero = np.zeros(1)
    t0 = time.perf_counter()
    for _ in range(periods):
        fleet.step(zero, zero)
    fleet_rate = periods * cfg.sim.steps_per_policy / (time.perf_counter() - t0)
    out = {"parked_cars": n_cars, "pymunk_steps_per_s": raw, "fleet_steps_per_s_b1": fleet_rate}
    miles = 4.0 if quick else 40.0
    prof = active_profile([])
    world_cfg = WorldConfig.for_profile(prof)
    for name, policy in (("lane_keeper", LaneKeeper()), ("lane_changer", LaneChanger())):
        res = evaluate(
            policy, world_cfg, EvalConfig(miles=miles, n_worlds=16, n_tracks=16), progress=False
        )
        out[f"{name}_sim_miles_per_wall_s"] = res.sim_miles_per_wall_s
        out[f"{name}_sim_miles"] = res.miles
    return out


def camera_scene(n_frames: int = 16) -> tuple[list, list, np.ndarray, np.ndarray]:
    """A realistic busy scene per frame: on a curve, 10+ parked cars within 100 m.

    Returns ``(tracks, cars, poses, s)`` for :meth:`~e2e_lite.simulation.camera.Camera.render_batch`.
    """
    cfg = WorldConfig(
        road=RoadConfig(length_m=3_000.0),
        traffic=TrafficConfig(n_cars=(300, 300), spacing_m=(6.0, 10.0), first_car_m=20.0),
    )
    tracks, cars, poses, s_list = [], [], [], []
    for i in range(n_frames):
        world = make_world(cfg, "test", i)
        arc = int(np.flatnonzero(world.track.k != 0)[0])
        s = float(world.track.s0[arc]) + 10.0
        tracks.append(world.track)
        cars.append(world.cars)
        poses.append(world.track.pose(s, 0.3))
        s_list.append(s)
    return tracks, cars, np.array(poses), np.array(s_list)


def bench_camera(quick: bool) -> dict[str, float]:
    """Frames per second at 66x200 and 240x640 on busy curved scenes, batched and one by one."""
    tracks, cars, poses, s = camera_scene(16)
    in_view = [c.between(si, si + 100.0) for c, si in zip(cars, s)]
    counts = [sl.stop - sl.start for sl in in_view]
    out: dict[str, float] = {
        "cars_within_100m_min": min(counts),
        "cars_within_100m_mean": float(np.mean(counts)),
    }
    reps = 10 if quick else 60
    for name, cfg in (("66x200", CameraConfig()), ("240x640", CameraConfig.human())):
        cam = Camera(cfg)
        frames = cam.render_batch(tracks, cars, poses, s)
        t0 = time.perf_counter()
        for _ in range(reps):
            cam.render_batch(tracks, cars, poses, s, out=frames)
        out[f"fps_{name}_batch16"] = reps * len(poses) / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        for _ in range(reps):
            for b in range(len(poses)):
                cam.render(tracks[b], cars[b], tuple(poses[b]), s[b], out=frames[b])
        out[f"fps_{name}_one_by_one"] = reps * len(poses) / (time.perf_counter() - t0)
    return out


def bench_data(quick: bool) -> dict[str, float]:
    """Samples collected per second (noisy expert, 66x200 frames, label rollouts, affordances);
    closed-loop simulated miles per wall-second of the expert and of the oracle (B = 16)."""
    prof = active_profile([])
    n = 800 if quick else 8_000
    cfg = DataConfig.for_profile(prof, "train", n_samples=n)
    t0 = time.perf_counter()
    collect(cfg, progress=False)
    out: dict[str, float] = {"samples": n, "samples_per_s": n / (time.perf_counter() - t0)}
    world_cfg = WorldConfig.for_profile(prof)
    ev = EvalConfig(miles=4.0 if quick else 40.0, n_worlds=16, n_tracks=16)
    for name, policy in (("expert", Expert()), ("oracle", Oracle())):
        res = evaluate(policy, world_cfg, ev, progress=False)
        out[f"{name}_sim_miles_per_wall_s"] = res.sim_miles_per_wall_s
        out[f"{name}_sim_miles"] = res.miles
    return out


def bare_train_samples_per_s(
    model: torch.nn.Module, objective: Objective, batch: dict[str, torch.Tensor], steps: int
) -> float:
    """The network's own training speed [samples/s]: forward, the objective's loss, backward and
    an Adam step, ``steps`` times on one batch already in memory (after 3 warm-up steps). What the
    training loop adds (batch assembly, shuffling, metrics, progress) is left out."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    device = next(model.parameters()).device

    def step() -> None:
        out = model(batch["image"], batch["speed"])
        loss = objective.batch_loss(out, batch, model, epoch=0)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(3):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return steps * len(batch["speed"]) / (time.perf_counter() - t0)


def bench_train(quick: bool) -> dict[str, float]:
    """Training samples per second at batch 64 for the full fusion model (trajectory head +
    affordance head) and PilotNet: the bare train step (:func:`bare_train_samples_per_s`, before
    and after the loop, averaged) and the real loop (:func:`~e2e_lite.learning.training.fit`, one epoch on
    synthetic frames, validation left out), and their ratio ``loop_vs_bare``."""
    n = 512 if quick else 6_144
    steps = 8 if quick else 48
    train, val = synthetic_data(n, 0), synthetic_data(64, 1)
    device = pick_device()
    out: dict[str, float] = {"threads": torch.get_num_threads(), "device": str(device)}
    for name, cfg in (
        ("fusion_trajectory_affordance", ModelConfig(head="trajectory", affordance=True)),
        ("pilotnet", ModelConfig(kind="pilotnet", head="steer")),
    ):
        objective = Objective("steer" if cfg.head == "steer" else "trajectory")
        batch = DrivingDataset(train).batch(np.arange(64), device=device)
        torch.manual_seed(0)
        bare = [
            bare_train_samples_per_s(prepare(build_model(cfg), device), objective, batch, steps)
        ]
        torch.manual_seed(0)
        hist = fit(
            prepare(build_model(cfg), device),
            objective,
            DrivingDataset(train),
            DrivingDataset(val),
            TrainConfig(epochs=1, batch_size=64),
            name=f"bench_{name}",
            progress=False,
        )
        torch.manual_seed(0)
        bare.append(
            bare_train_samples_per_s(prepare(build_model(cfg), device), objective, batch, steps)
        )
        out[f"{name}_bare_samples_per_s"] = float(np.mean(bare))
        out[f"{name}_loop_samples_per_s"] = hist.samples_per_s
        out[f"{name}_loop_vs_bare"] = hist.samples_per_s / float(np.mean(bare))
    # the headline figures: the course's main network (chapters 06-11 train the fusion model)
    main = "fusion_trajectory_affordance"
    out["bare_samples_per_s"] = out[f"{main}_bare_samples_per_s"]
    out["loop_samples_per_s"] = out[f"{main}_loop_samples_per_s"]
    out["loop_vs_bare"] = out[f"{main}_loop_vs_bare"]
    return out


def learned_driver(agent: str, device: torch.device) -> tuple[NetworkAgent, str]:
    """The chapter's driver ``agent`` (pilotnet, actuators or gmm) on ``device``: its checkpoint
    when it exists, else an untrained network of the same shape; and where it came from."""
    name, cfg = {
        "pilotnet": ("05_pilotnet", recipes.PILOTNET_CFG),
        "actuators": ("05_actuators", recipes.ACTUATORS_CFG),
        "gmm": ("07_gmm", recipes.gmm_config()),
    }[agent]
    path = artifact_path("checkpoints", f"{name}.pt")
    if path.exists():
        model, _ = load_checkpoint(path, cfg, device=device)
        source = f"checkpoint {path.name}"
    else:
        torch.manual_seed(0)
        model = prepare(build_model(cfg), device).eval()
        source = "untrained network (no checkpoint yet)"
    policy = {"steer": SteeringAgent, "actuators": ActuatorAgent, "gmm": TrajectoryAgent}[cfg.head](
        model
    )
    return policy, source


def bench_closed_loop(quick: bool, agent: str = "pilotnet") -> dict[str, float]:
    """Closed-loop simulated miles per wall-second with camera + CNN in the loop (the chapter's
    checkpoint when it exists, else an untrained network of the same shape), B = 64 (chapters
    10-11) in one shard, in two threads and in two worker processes (also without the workers'
    start, which an evaluation pays once)."""
    policy, source = learned_driver(agent, pick_device())
    world_cfg = WorldConfig.for_profile(active_profile([]))
    print(f"closed loop with {agent}: {source}")
    out: dict[str, float] = {}
    runs = (
        ("b64_1thread", 64, 1, "threads", 20.0),
        ("b64_2threads", 64, 2, "threads", 20.0),
        ("b64_2processes", 64, 2, "processes", 100.0),
    )
    for label, n_worlds, workers, parallel, miles in runs:
        ev = EvalConfig(miles=0.5 if quick else miles, n_worlds=n_worlds, n_tracks=16)
        res = evaluate(policy, world_cfg, ev, progress=False, workers=workers, parallel=parallel)
        out[f"{label}_sim_miles_per_wall_s"] = res.sim_miles_per_wall_s
        out[f"{label}_decisions_per_wall_s"] = (
            res.sim_time_s / world_cfg.sim.policy_period_s / res.wall_time_s
        )
        out[f"{label}_sim_miles"] = res.miles
        startup = res.timing_s.get("startup", 0.0)
        if parallel == "processes":  # the same, leaving out the workers' start (once per call)
            out[f"{label}_startup_s"] = startup
            out[f"{label}_after_startup_sim_miles_per_wall_s"] = res.miles / (
                res.wall_time_s - startup
            )
        frames = max(1.0, res.timing_s["frames"])
        out[f"{label}_frames"] = frames
        for part in ("render", "policy", "physics"):  # shard-seconds per frame, in ms
            out[f"{label}_{part}_ms_per_frame"] = 1e3 * res.timing_s[part] / frames
        loop = (res.wall_time_s - startup) * workers - sum(
            res.timing_s[p] for p in ("render", "policy", "physics")
        )
        out[f"{label}_rest_ms_per_frame"] = 1e3 * loop / frames
    # the headline: chapter 10's setting (64 cars, two worker processes, one core each), the
    # whole evaluation (workers' start included) against the network alone at the shards' batch
    # on the shards' threads, both in simulated miles per wall-second (the loop's miles per frame)
    workers = 2
    network_fps = workers * network_frames_per_s(  # (the agent's groups, one thread a shard)
        policy.model, FORWARD_GROUP, reps=40 if quick else 800, threads=SHARD_TORCH_THREADS
    )
    miles_per_frame = out["b64_2processes_sim_miles"] / out["b64_2processes_frames"]
    out["network_frames_per_s"] = network_fps
    out["network_miles_per_s"] = network_fps * miles_per_frame
    out["loop_miles_per_s"] = out["b64_2processes_sim_miles_per_wall_s"]
    out["loop_vs_network"] = out["loop_miles_per_s"] / out["network_miles_per_s"]
    out.update(frame_budget(out, workers))
    return out


def frame_budget(out: dict[str, float], workers: int) -> dict[str, float]:
    """Where the headline's frame goes, in core-milliseconds per frame [ms]: the network alone,
    what the policy spends beyond it (batching the frames, reading the modes, the tracker), the
    camera, the physics, the rest of the loop (worlds built, bookkeeping) and the workers' start
    spread over the frames; and ``loop_vs_network_without_render``, the ratio the same run would
    give with every other part as measured and the camera free (derived from these parts, not a
    run without a camera): how far making the camera faster alone could take the ratio."""
    p = "b64_2processes"
    frames = out[f"{p}_frames"]
    network = 1e3 * workers / out["network_frames_per_s"]
    startup = 1e3 * out[f"{p}_startup_s"] * workers / frames
    parts = {
        "network": network,
        "policy_beyond_network": out[f"{p}_policy_ms_per_frame"] - network,
        "render": out[f"{p}_render_ms_per_frame"],
        "physics": out[f"{p}_physics_ms_per_frame"],
        "rest": out[f"{p}_rest_ms_per_frame"],
        "startup": startup,
    }
    total = sum(parts.values())
    budget = {f"budget_{k}_ms_per_frame": v for k, v in parts.items()}
    budget["budget_total_ms_per_frame"] = total
    budget["loop_vs_network_without_render"] = network / (total - parts["render"])
    return budget


def network_frames_per_s(
    model: torch.nn.Module, batch: int, reps: int, threads: int | None = None
) -> float:
    """Frames per second of ``model``'s forward pass alone (inference mode, random 66 x 200
    frames and speeds already in memory) at ``batch`` frames per call on ``threads`` torch
    threads (None: as set), after 3 warm-up calls."""
    device = next(model.parameters()).device
    rng = np.random.default_rng(0)
    image = images_to_tensor(rng.integers(0, 256, (batch, 66, 200, 3), dtype=np.uint8), device)
    speed = torch.full((batch, 1), 20.0, device=device)
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        with torch.inference_mode():
            for _ in range(3):  # warm-up (allocations, kernel choices)
                model(image, speed)
            if device.type == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            for _ in range(reps):
                model(image, speed)
            if device.type == "cuda":
                torch.cuda.synchronize()
            return reps * batch / (time.perf_counter() - t0)
    finally:
        torch.set_num_threads(before)


def bench_network(quick: bool) -> dict[str, float]:
    """Inference cost of the fusion network with a GMM head (chapters 07-11's drivers) per frame
    [ms], by batch size, on one torch thread and on all of them (what a closed-loop shard pays)."""
    torch.manual_seed(0)
    model = prepare(build_model(ModelConfig(kind="fusion", head="gmm")), pick_device()).eval()
    out: dict[str, float] = {}
    for n_threads in sorted({1, torch.get_num_threads()}):
        for batch in (8, 16, 32, 64):
            reps = max(3, (200 if quick else 2_000) // batch)
            rate = network_frames_per_s(model, batch, reps, n_threads)
            out[f"threads{n_threads}_batch{batch}_ms_per_frame"] = 1e3 / rate
    return out


def scaling_workers(cores: int) -> list[int]:
    """1, 2, 4, ... and the core count: the worker counts the scaling benchmark measures."""
    counts = [1]
    while counts[-1] * 2 < cores:
        counts.append(counts[-1] * 2)
    return sorted({*counts, cores})


def bench_scaling(quick: bool, agent: str = "gmm") -> dict[str, float]:
    """How driving and collecting scale with worker processes here. Driving: chapter
    10's evaluation (64 cars, or FORWARD_GROUP per core if more; 20 mi, quick 1) with 1, 2, 4, ...
    and all workers: miles per wall-second with and without the workers' start, the speed-up over
    one worker, its share of the ideal (``efficiency``), and whether the events equal one
    worker's; with a GPU, the network there in this process and in every worker. Collecting
    (16,000 samples, quick 400; 16 cars, or one per core) with one process and with all: samples
    per second (the workers' start included), and whether the arrays are the same bytes."""

    cores = available_cores()
    policy, source = learned_driver(agent, torch.device("cpu"))
    print(f"scaling with {agent}: {source}; {cores} cores")
    prof = active_profile([])
    world_cfg = WorldConfig.for_profile(prof)
    ev = EvalConfig(miles=1.0 if quick else 20.0, n_worlds=max(64, FORWARD_GROUP * cores))
    out: dict[str, float] = {"cores": cores, "eval_cars": ev.n_worlds}
    first = None
    for w in scaling_workers(cores):
        close_shard_workers()  # (every row pays its workers' start)
        res = evaluate(policy, world_cfg, ev, progress=False, workers=w)
        rate = res.miles / (res.wall_time_s - res.timing_s.get("startup", 0.0))
        first = first or (res, rate)
        out[f"eval_{w}w_sim_miles_per_wall_s"] = res.sim_miles_per_wall_s
        out[f"eval_{w}w_after_startup_sim_miles_per_wall_s"] = rate
        out[f"eval_{w}w_speedup"], out[f"eval_{w}w_efficiency"] = (
            rate / first[1],
            rate / first[1] / w,
        )
        out[f"eval_{w}w_same_events"] = float(res.events == first[0].events)
    if torch.cuda.is_available():  # where the network runs with a GPU: there, in this process
        gpu, _ = learned_driver(agent, torch.device("cuda"))  # (one shard) or in every worker
        for w, how in ((1, "threads"), (cores, "processes")):
            res = evaluate(gpu, world_cfg, ev, progress=False, workers=w, parallel=how)
            out[f"eval_cuda_{w}{how}_sim_miles_per_wall_s"] = res.sim_miles_per_wall_s
    n = 400 if quick else 16_000
    cfg = DataConfig.for_profile(prof, "train", n_samples=n, n_worlds=max(16, cores))
    arrays = None
    for w in sorted({1, cores}):
        close_shard_workers()
        t0 = time.perf_counter()
        data = collect(cfg, progress=False, workers=w)
        out[f"collect_{w}w_samples_per_s"] = n / (time.perf_counter() - t0)
        arrays = arrays or data.arrays
        out[f"collect_{w}w_same_bytes"] = float(
            all(np.array_equal(arrays[k], data.arrays[k]) for k in arrays)
        )
    close_shard_workers()
    return out


BENCHMARKS: dict[str, Callable[..., dict[str, float]]] = {
    "world": bench_world,
    "camera": bench_camera,
    "data": bench_data,
    "train": bench_train,
    "closed-loop": bench_closed_loop,
    "network": bench_network,
    "scaling": bench_scaling,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    parser = argparse.ArgumentParser(
        prog="python -m e2e_lite.course.bench", description="e2e-lite benchmarks"
    )
    parser.add_argument("name", choices=sorted(BENCHMARKS))
    parser.add_argument("--json", action="store_true", help="end with one JSON line of the figures")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (a smoke run)")
    parser.add_argument(
        "--agent",
        choices=["pilotnet", "actuators", "gmm"],
        default=None,
        help="closed-loop (default pilotnet) and scaling (default gmm): which driver",
    )
    args = parser.parse_args(argv)
    if args.name in ("closed-loop", "scaling"):
        default = "pilotnet" if args.name == "closed-loop" else "gmm"
        figures = BENCHMARKS[args.name](args.quick, args.agent or default)
    else:
        figures = BENCHMARKS[args.name](args.quick)
    print(f"benchmark {args.name} ({'quick' if args.quick else 'full'}) on {_machine()}")
    for key, value in figures.items():
        print(f"  {key:36s} {value:,.2f}" if isinstance(value, float) else f"  {key:36s} {value}")
    if args.json:
        print(json.dumps({"benchmark": args.name, **_machine(), **figures}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
