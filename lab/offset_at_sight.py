"""Do chapter 04's data hold approaches begun off the lane's centre as often as the networks
drive into them? (issue 88, item 3)

``lab/own_states.py`` found the start networks' late lane changes mostly in approaches first
seen with the car 0.2 m or more off its lane's centre. This counts, in chapter 04's training
and validation data, the frames at a first sight's distance (a parked car 75-80 m ahead of the
front bumper in the car's lane, the true gap from the frame's world) by the car's offset from
its lane's centre, beside the networks' own first sights (``docs/results/lab/own_states.json``
and ``own_states_fresh.json``, every approach). A measurement, not a choice.

    python lab/offset_at_sight.py [--quick]

Writes docs/results/lab/offset_at_sight.json (full profile).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from e2e_lite import artifacts
from e2e_lite.config import FULL, QUICK, Profile
from e2e_lite.imitation.collector import DataConfig, load_or_collect
from e2e_lite.learning.labels import AFFORDANCE_INDEX
from e2e_lite.simulation.world import World, WorldConfig, make_world

SIGHT_M = (75.0, 80.0)  # a first sight's gap, as lab/own_states.py's approaches [m]
OFFSET_BINS_M = (0.0, 0.2, 0.5, 2.0)  # as lab/own_states.py's [m]
LAB = Path(__file__).resolve().parents[1] / "docs/results/lab"


def at_sight(split: str, profile: Profile, world_cfg: WorldConfig) -> list[int]:
    """Frames of ``split``'s data at a first sight's gap, per bin of the offset."""
    data = load_or_collect(DataConfig.for_profile(profile, split))
    a, front = data.arrays, world_cfg.vehicle.rear_to_front_m
    offset = np.abs(a["affordances"][:, AFFORDANCE_INDEX["center_offset_m"]])
    worlds: dict[int, World] = {}
    gap = np.full(len(data), np.inf)
    for i in range(len(data)):
        k = int(a["track"][i])
        if k not in worlds:
            worlds[k] = make_world(world_cfg, split, k)
        gap[i] = worlds[k].gap_ahead(float(a["s"][i]) + front, int(a["lane"][i]), SIGHT_M[1])
    seen = offset[(gap >= SIGHT_M[0]) & (gap < SIGHT_M[1])]
    return np.histogram(np.minimum(seen, OFFSET_BINS_M[-1] - 1e-9), OFFSET_BINS_M)[0].tolist()


def driven(name: str) -> list[int] | None:
    """The networks' first sights per bin of the offset, from ``lab/own_states.py``'s JSON."""
    path = LAB / name
    if not path.exists():
        return None
    seeds = json.loads(path.read_text())["seeds"].values()
    bins = [s["every_approach"]["by_first_offset"] for s in seeds]
    return [sum(b[i]["approaches"] for b in bins) for i in range(len(OFFSET_BINS_M) - 1)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    profile = QUICK if ap.parse_args().quick else FULL
    world_cfg = WorldConfig.for_profile(profile)
    out: dict = {"offset_bins_m": OFFSET_BINS_M, "sight_m": SIGHT_M, "frames": {}}
    for split in ("train", "val"):
        out["frames"][split] = at_sight(split, profile, world_cfg)
    for name in ("own_states.json", "own_states_fresh.json"):
        out["frames"][f"driven ({name})"] = driven(name)
    for name, counts in out["frames"].items():
        if counts:
            n = sum(counts)
            shares = ", ".join(
                f"{lo:g}-{hi:g} m {100 * c / max(n, 1):.0f} %"
                for (lo, hi), c in zip(itertools.pairwise(OFFSET_BINS_M), counts)
            )
            what = "approaches" if name.startswith("driven") else "frames"
            print(f"{name}: {n} {what} at a first sight's gap; {shares}")
    out["commit"] = artifacts.code_commit(Path(__file__).parent)
    if not profile.quick:
        (LAB / "offset_at_sight.json").write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {LAB / 'offset_at_sight.json'}")


if __name__ == "__main__":
    main()
