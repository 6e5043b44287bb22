"""Exercises that check themselves: a stub a student fills in ``exercises/``, and one command that
says whether the answer holds, or what is off and a hint (``python -m e2e_lite.exercises
check 03.2``; ``list`` names them). Each check computes what it expects from the library, never
from a typed number: the course's code is the answer key.

The exercises checked here are the core ones whose answer is determinate; the kit
(``docs/teaching.md``) says which core exercises stay prose, and why.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..control.drivers import LaneChanger
from ..control.tracker import LQRTracker, TrackerConfig, lateral_model
from ..learning.heads import Mixture
from ..record.report import load
from ..record.stats import POWER_ROW, record_dispersion, record_power
from ..simulation.camera import Camera, CameraConfig
from ..simulation.policy import observe
from ..simulation.scenarios import TWO_ANSWERS_CAR_S_M, two_answers_scene
from ..simulation.vehicle import VehicleParams
from ..simulation.world import TrafficConfig, WorldConfig
from ..stats.power import power
from ..stats.rates import poisson_ci

#: where the stubs are: ``exercises/`` beside the chapters
STUBS = Path(__file__).resolve().parents[2] / "exercises"


@dataclass(frozen=True)
class Exercise:
    """One exercise that checks itself.

    Attributes:
        number: ``"NN.k"``, chapter and exercise as the chapter numbers them.
        stub: the stub's file name in :data:`STUBS`.
        function: the function the student fills in.
        check: the student's answer -> ``""`` when it holds, else what is off and a hint.
        takes_function: the answer is the function itself (the check calls it), not its value.
    """

    number: str
    stub: str
    function: str
    check: Callable[[Any], str]
    takes_function: bool = False


def _relative(answer: float, expected: float, tolerance: float, what: str, hint: str) -> str:
    """ "" when ``answer`` is within ``tolerance`` (a share) of ``expected``, else the message."""
    answer = float(answer)
    if math.isfinite(answer) and abs(answer - expected) <= tolerance * abs(expected):
        return ""
    return f"{what}: {answer:.4g}, expected about {expected:.4g} (within {tolerance:.0%}). {hint}"


def _passes(trigger_m: float) -> bool:
    """Whether the lane changer, at 25 m/s behind chapter 04's parked car, passes it when it
    changes lanes at a gap of ``trigger_m`` [m]."""
    world_cfg = WorldConfig()
    _, fleet = two_answers_scene(world_cfg, gap_m=150.0, speed_mps=25.0)
    driver = LaneChanger(trigger_m=trigger_m)
    driver.reset(1)
    for k in range(round(20.0 / world_cfg.sim.policy_period_s)):
        act = driver.act(observe(fleet, respawned=k == 0))
        if fleet.step(act.steer_rad, act.accel_mps2)[0]:
            return False
        if fleet.lane_frame()[0][0] > TWO_ANSWERS_CAR_S_M + 10.0:
            return True
    return False


def _lookahead(answer: float) -> str:
    """01.1: the smallest trigger at which the lane changer still passes a parked car at 25 m/s
    (found by halving the range between one that collides and one that passes)."""
    lo, hi = 1.0, 120.0
    while hi - lo > 0.25:
        mid = (lo + hi) / 2.0
        lo, hi = (lo, mid) if _passes(mid) else (mid, hi)
    hint = (
        "Hint: the lateral error follows e'' + 2 zeta wn e' + wn^2 e = 0 from a lane's step; the "
        "car is clear once it moved the two cars' half widths (0.9 + 0.9 m); times 25 m/s."
    )
    return _relative(answer, hi, 0.2, "look-ahead [m]", hint)


def _miles_without_collision(answer: float) -> str:
    """01.4: the miles with no collision whose exact 95 % interval lies below 1 per 100 mi."""
    # upper bound of the exact interval with 0 collisions: -ln(0.025) / (miles / 100) per 100 mi
    expected = 100.0 * poisson_ci(0, 1.0)[1]
    if abs(float(answer) - 300.0) < 5.0:
        return (
            "300 mi is the 'rule of three', a one-sided 95 % bound; the course's interval is the "
            "exact two-sided one (stats.rates.poisson_ci): its upper end at 0 collisions is "
            "-ln(0.025) / exposure"
        )
    hint = "Hint: solve poisson_ci(0, miles / 100)[1] = 1 for miles."
    return _relative(answer, expected, 0.01, "miles", hint)


def _car_width_px(answer: float) -> str:
    """02.1: how many pixels a parked car 60 m ahead covers across a 90° camera's 200 px."""
    fx = Camera(CameraConfig(hfov_deg=90.0)).fx  # (W / 2) / tan(hfov / 2) [px]
    expected = fx * TrafficConfig().car_width_m / 60.0
    hint = "Hint: a width w at distance z covers f w / z pixels, f = (W / 2) / tan(hfov / 2)."
    return _relative(answer, expected, 0.05, "width [px]", hint)


def _pole_radius(answer: float) -> str:
    """03.1: the closed-loop poles' modulus at 20 m/s with ``steer_max_rad`` doubled."""
    import control  # (here: python-control loads matplotlib's parts; only this check needs it)

    cfg = TrackerConfig(steer_max_rad=2 * TrackerConfig().steer_max_rad)
    sysd = lateral_model(20.0, VehicleParams().wheelbase_m, cfg.period_s)
    q = np.diag([1.0 / cfg.lateral_max_m**2, 1.0 / cfg.heading_max_rad**2])
    _, _, poles = control.dlqr(sysd.A, sysd.B, q, np.array([[1.0 / cfg.steer_max_rad**2]]))
    hint = (
        "Hint: design the gain as chapter 03 does (lateral_model, control.dlqr) with the doubled "
        "steer_max_rad, and take |eig(A - B K)|; smaller is faster (nearer the origin)."
    )
    return _relative(answer, float(np.abs(poles).max()), 0.01, "pole modulus", hint)


def _steady_error(answer: float) -> str:
    """03.2: the lateral error the tracker keeps on the 300 m curve at 20 m/s without its
    feed-forward."""
    # at steady state psi = 0, so the feedback must give the feed-forward's angle: k_e e = atan(L k)
    k_e = LQRTracker().gain(20.0)[0]
    expected = math.atan(VehicleParams().wheelbase_m / 300.0) / k_e
    hint = (
        "Hint: at steady state the heading error is 0, so the feedback's k_e * e alone must give "
        "the steering the curve needs, atan(L / R); read k_e from LQRTracker().gain(20.0)."
    )
    return _relative(abs(float(answer)), expected, 0.1, "steady lateral error [m]", hint)


def _mixture_mean(answer: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> str:
    """07.3: the mixture's mean, each mode weighted by its mixing weight."""
    rng = np.random.default_rng(7)
    logits, modes = rng.normal(size=(4, 3)), rng.normal(size=(4, 3, 10))
    weights = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    t = torch.as_tensor
    expected = Mixture(t(logits), t(modes), t(np.zeros_like(modes))).followed("mean").numpy()
    got = np.asarray(answer(weights, modes), dtype=float)
    if got.shape != expected.shape:
        return f"shape {got.shape}, expected {expected.shape}: one mean per sample, (B, D)."
    if not np.allclose(got, expected, atol=1e-9):
        return (
            "not the weighted mean of the modes. Hint: sum over k of weights[:, k] * modes[:, k]."
        )
    # a car with two equally likely answers, 2.7 m left and right: the mean heads straight on
    two = np.array([[[0.0, 2.7], [0.0, -2.7]]]).reshape(1, 2, 2)
    mean = np.asarray(answer(np.array([[0.5, 0.5]]), two), dtype=float)
    return "" if np.allclose(mean, 0.0) else "two equal modes left and right should average to 0."


def _record_size(answer: tuple[int, float]) -> str:
    """10.2: seeds per row and miles per seed that find a true 1.5x step at the + affordance
    row's rate nine times in ten, under the record's seed spread."""
    seeds, miles = int(answer[0]), float(answer[1])
    if not 2 <= seeds <= 80 or not 1.0 <= miles <= 2000.0:
        return f"{seeds} seeds x {miles:g} mi: give 2-80 seeds and 1-2,000 mi per seed."
    record = load()
    rate = record_power(record).rate_per_100mi
    k = record_dispersion(record, near=POWER_ROW).k
    found = power(seeds, miles, rate, step=1.5, n_sim=250, dispersion=k).power
    if found >= 0.87:  # (0.9 less the simulation's own spread at 250 records)
        return ""
    return (
        f"{seeds} seeds x {miles:g} mi find a 1.5x step in {found:.0%} of records, not 90 %. "
        "Hint: the seeds' spread (dispersion) caps what more miles per seed can buy: add seeds."
    )


EXERCISES = {
    e.number: e
    for e in (
        Exercise("01.1", "ex_01_1.py", "lookahead_m", _lookahead),
        Exercise("01.4", "ex_01_4.py", "miles", _miles_without_collision),
        Exercise("02.1", "ex_02_1.py", "car_width_px", _car_width_px),
        Exercise("03.1", "ex_03_1.py", "pole_radius", _pole_radius),
        Exercise("03.2", "ex_03_2.py", "steady_error_m", _steady_error),
        Exercise("07.3", "ex_07_3.py", "mixture_mean", _mixture_mean, takes_function=True),
        Exercise("10.2", "ex_10_2.py", "record_size", _record_size),
    )
}


def check(number: str, stubs: Path = STUBS) -> tuple[bool, str]:
    """Check exercise ``number`` in the folder ``stubs``: ``(holds, the line to print)``."""
    if number not in EXERCISES:
        raise ValueError(f"no exercise {number!r} checks itself: {', '.join(EXERCISES)}")
    ex = EXERCISES[number]
    path = stubs / ex.stub
    spec = importlib.util.spec_from_file_location(f"exercise_{ex.stub[:-3]}", path)
    if spec is None or not path.exists():
        return False, f"{number}: no stub at {path}"
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    fn = getattr(module, ex.function)
    try:
        answer = fn if ex.takes_function else fn()
        said = ex.check(answer)
    except NotImplementedError:
        return False, f"{number}: not answered yet: fill in {ex.function} in {path}"
    return (not said), f"{number}: " + ("pass" if not said else said)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m e2e_lite.exercises", description=__doc__)
    sub = parser.add_subparsers(dest="what", required=True)
    sub.add_parser("list", help="the exercises that check themselves")
    one = sub.add_parser("check", help="check one exercise, or all")
    one.add_argument("number", nargs="?", help="NN.k (all when left out)")
    one.add_argument("--stubs", type=Path, default=STUBS, help="the folder of the stubs")
    args = parser.parse_args(argv)
    if args.what == "list":
        for e in EXERCISES.values():
            print(f"{e.number}  exercises/{e.stub}: {e.function}")
        return 0
    numbers = [args.number] if args.number else list(EXERCISES)
    try:
        results = [check(n, args.stubs) for n in numbers]
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for _, line in results:
        print(line)
    return 0 if all(ok for ok, _ in results) else 1
