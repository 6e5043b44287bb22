"""Shared fixtures and scene builders."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

from e2e_lite.control.drivers import LaneKeeper
from e2e_lite.simulation.geometry import Track
from e2e_lite.simulation.vehicle import VehicleParams
from e2e_lite.simulation.world import ParkedCars, World

# CI and the README's test command draw the same hypothesis examples every run, so a red build
# means a change broke something; `HYPOTHESIS_PROFILE=explore pytest` searches with fresh random
# examples (how the near-integer CVaR tail bug was found) and should be run after touching maths.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("explore", max_examples=1000, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(autouse=True)
def _isolated_outputs(tmp_path, monkeypatch):
    """Every test writes artifacts to its own temporary folder, in the full profile."""
    monkeypatch.setenv("E2E_LITE_OUTPUTS", str(tmp_path / "outputs"))
    monkeypatch.delenv("E2E_LITE_QUICK", raising=False)


def straight_world(
    car_s: list[float],
    car_lane: list[int],
    length: float = 2_000.0,
    car_d: list[float] | None = None,
) -> World:
    """A straight 3-lane road along +x from the origin, with parked cars at the given places
    (centred on their lanes unless ``car_d`` gives their offsets)."""
    track = Track([0.0], [0.0], [0.0], [0.0], [length])
    lane = np.array(car_lane, dtype=int)
    d = track.lane_center(lane) if car_d is None else np.array(car_d, dtype=float)
    return World(
        track, ParkedCars.on_track(track, np.array(car_s, dtype=float), d), VehicleParams()
    )


class ForkingKeeper(LaneKeeper):
    """A lane keeper that can be split into shards (as the network agents can): it counts its
    splits over every instance (``ForkingKeeper.forks``) and keeps its own splits' sizes
    (``forked``)."""

    forks = 0

    def __init__(self) -> None:
        super().__init__()
        self.forked: list[int] = []

    def fork(self, k: int) -> list[LaneKeeper]:
        ForkingKeeper.forks += 1
        self.forked.append(k)
        return [LaneKeeper() for _ in range(k)]


@pytest.fixture
def drives(monkeypatch) -> list:
    """The drives :func:`e2e_lite.record.stored.evaluate_stored` actually drives (each call of
    ``evaluate`` appends its policy), so a test can tell a read-back result from a driven one:
    both are an ``EvalResult``."""
    import e2e_lite.record.stored

    driven: list = []
    real = e2e_lite.record.stored.evaluate

    def counted(policy, *args, **kwargs):
        driven.append(policy)
        return real(policy, *args, **kwargs)

    monkeypatch.setattr(e2e_lite.record.stored, "evaluate", counted)
    return driven
