"""What the DAgger lab scripts (lab/dagger_*.py) start from: the profile (``--quick``), chapter
04's training and validation data, chapter 08's affordance weight and chapter 12's seeds."""

from __future__ import annotations

import argparse

from e2e_lite.config import FULL, QUICK, Profile
from e2e_lite.learning import recipes
from e2e_lite.learning.collector import DataConfig, DrivingData, load_or_collect
from e2e_lite.simulation.world import WorldConfig


def setup(doc: str) -> tuple[Profile, WorldConfig, DrivingData, DrivingData, float, range]:
    """Parse ``--quick`` (``doc``: the script's help) and load what every DAgger arm needs:
    ``(profile, world, train, val, affordance weight, training seeds)``."""
    parser = argparse.ArgumentParser(description=doc)
    parser.add_argument("--quick", action="store_true")
    profile = QUICK if parser.parse_args().quick else FULL
    train = load_or_collect(DataConfig.for_profile(profile, "train"))
    val = load_or_collect(DataConfig.for_profile(profile, "val"))
    weight = recipes.affordance_weight(profile, train, val)
    return (
        profile,
        WorldConfig.for_profile(profile),
        train,
        val,
        weight,
        range(profile.ablation_seeds),
    )
