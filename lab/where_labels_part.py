"""Where do the two experts' labels part, and where do DAgger's rounds drive? Chapter 12 prints
the share of chapter 04's states whose two labels (the course's expert's, which carries its plan,
and the state expert's, which relabels them for DAgger) end more than 1 m apart at 1.5 s; this
script says which states those are, drives each labeller (the tracker following it at every
decision) to count its off-centre episodes, and reads where the kept samples of chapter 12's
rounds lie across the road. Descriptive: no test, nothing chosen, nothing trained.

    E2E_LITE_OUTPUTS=<a full-profile course run's outputs> python lab/where_labels_part.py

Reads chapter 04's training data and chapter 12's stored rounds (only the fields it needs),
drives validation roads (chapter 12's section 2's), and writes
docs/results/lab/where_labels_part.json (lab note "The two experts part over the home lane").
A label's end across the road is its 1.5 s point turned into the lane frame with the road's
curvature at the sample taken as constant over the 1.5 s (checked: the JSON's "geometry_check";
within about 30 m of where a straight meets an arc it can be off by up to about 2 m). "Along the
road": the car's heading within 0.01 rad of the road's at that instant (the turning point of an
abandoned change passes through it too).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from e2e_lite.artifacts import artifact_path
from e2e_lite.config import FULL, QUICK, Profile
from e2e_lite.control.expert import Expert
from e2e_lite.control.oracle import Oracle
from e2e_lite.control.state_expert import StateExpert
from e2e_lite.driving.evaluation import evaluate
from e2e_lite.imitation import dagger
from e2e_lite.imitation.collector import DataConfig, dataset_path
from e2e_lite.learning.dataset import road_lateral
from e2e_lite.learning.labels import AFFORDANCE_INDEX, CHANGE, KEEP, STATE_NAMES
from e2e_lite.simulation.world import WorldConfig

OUT = Path(__file__).resolve().parents[1] / "docs" / "results" / "lab" / "where_labels_part.json"
FIELDS = (
    "trajectory",
    "state_trajectory",
    "affordances",
    "curvature",
    "d",
    "lane",
    "expert_state",
    "overtaking",
)
OFF_M = 1.0  # a label or a car more than this from every lane centre is off-centre [m]


def fields(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a stored dataset this script reads (not its images)."""
    if not path.exists():
        raise SystemExit(f"{path} is missing: run chapter 12 in this profile first (--seeds N?)")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in FIELDS}


def label_end(z: dict[str, np.ndarray], field: str) -> np.ndarray:
    """Where the 1.5 s point of each label of ``field`` lies across the road: the car's ``d``
    plus the point's offset from its lane-keeping path (:func:`~e2e_lite.learning.dataset.
    road_lateral`, the road's curvature at the sample taken as constant over the 1.5 s) [m]."""
    psi = z["affordances"][:, AFFORDANCE_INDEX["heading_rad"]]
    return z["d"] + road_lateral(z[field], psi, z["curvature"])


def from_centre(d: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Distance from the nearest lane centre [m] of lateral offsets ``d`` [m]."""
    return np.min(np.abs(d[:, None] - centres[None]), axis=1)


def heads_for_middle(z: dict[str, np.ndarray], field: str, middle_m: float) -> np.ndarray:
    """Whether each label of ``field`` ends nearer the middle lane's centre (at ``middle_m`` [m])
    than the car is, by more than 0.3 m."""
    return np.abs(label_end(z, field) - middle_m) < np.abs(z["d"] - middle_m) - 0.3


def where_apart(z: dict[str, np.ndarray], centres: np.ndarray, middle: int) -> dict[str, Any]:
    """Which of chapter 04's states carry labels more than 1 m apart (chapter 12's measure), and
    where each expert's label ends there (shares 0-1)."""
    apart = np.linalg.norm(z["trajectory"][:, -1] - z["state_trajectory"][:, -1], axis=-1) > 1.0
    off = {f: from_centre(label_end(z, f), centres) > OFF_M for f in FIELDS[:2]}
    keep = z["expert_state"] == KEEP
    side_keep = keep & (z["lane"] != middle)
    toward_middle = heads_for_middle(z, "state_trajectory", centres[middle])
    centred = keep & (np.abs(z["affordances"][:, AFFORDANCE_INDEX["center_offset_m"]]) < 0.25)
    own_end = from_centre(label_end(z, "trajectory"), centres)
    curved = centred & (np.abs(z["curvature"]) > 1.0 / 500.0)
    by_lane = {}
    for lane in range(len(centres)):
        rows = keep & (z["lane"] == lane)
        by_lane[f"lane {lane}"] = {
            "share_of_states": float(rows.mean()),
            "expert's label ends off-centre": float(off["trajectory"][rows].mean()),
            "state expert's label ends off-centre": float(off["state_trajectory"][rows].mean()),
        }
    return {
        "geometry_check": {
            "expert's keep states within 0.25 m of a centre: its label's end from a centre, "
            "median and 90th percentile [m]": np.percentile(own_end[centred], [50, 90]).tolist(),
            "the same on curves of radius under 500 m": (
                np.percentile(own_end[curved], [50, 90]).tolist() if curved.any() else None
            ),
            "share of those states on such curves": float(curved[centred].mean()),
        },
        "share_apart": float(apart.mean()),
        "of those, the expert keeping in a side lane": float(side_keep[apart].mean()),
        "there, the state expert's label heads for the middle lane": float(
            toward_middle[apart & side_keep].mean()
        ),
        "the expert keeping, by lane (0: rightmost), labels ending off-centre": by_lane,
    }


def rounds(profile: Profile, arm: str, seeds: int, centres: np.ndarray) -> list[dict[str, Any]]:
    """Per round, over the seeds: where the round's kept samples lie across the road, and at
    those off-centre and heading along the road (within 0.01 rad), what the labeller was doing
    and where its label heads (shares 0-1)."""
    cfg = dagger.DaggerConfig.for_profile(profile)
    out = []
    for r in range(cfg.rounds):
        parts = []
        for k in range(seeds):
            spec = dagger.RoundSpec(profile, cfg, k, r, arm)
            parts.append(fields(artifact_path("data", spec.samples_name)))
        z = {f: np.concatenate([p[f] for p in parts]) for f in FIELDS}
        off = from_centre(z["d"], centres) > OFF_M
        level = np.abs(z["affordances"][:, AFFORDANCE_INDEX["heading_rad"]]) < 0.01
        lingering = off & level
        middle = len(centres) // 2
        inward = heads_for_middle(z, "trajectory", centres[middle])
        nearest = np.argmin(np.abs(z["d"][:, None] - centres[None]), axis=1)
        states = np.bincount(z["expert_state"][off], minlength=len(STATE_NAMES))
        returns = (z["expert_state"] == CHANGE) & ~z["overtaking"]
        along = {}
        for where, rows in (("side", nearest != middle), ("middle", nearest == middle)):
            at = lingering & rows
            along[f"nearest a {where} lane's centre"] = {
                "share of the round": float(at.mean()),
                "the label heads for the middle": float(inward[at].mean()) if at.any() else None,
                "the labeller returns (a change, not an overtake)": (
                    float(returns[at].mean()) if at.any() else None
                ),
            }
        out.append(
            {
                "samples": len(z["d"]),
                "by lane (0: rightmost)": [
                    float(np.mean(np.abs(z["d"] - c) <= np.diff(centres).mean() / 2))
                    for c in centres
                ],
                "off-centre": float(off.mean()),
                "off-centre and along the road, all": float(lingering.mean()),
                "off-centre: the labeller's state": dict(
                    zip(STATE_NAMES, (states / max(1, off.sum())).tolist())
                ),
                "off-centre and along the road": along,
            }
        )
    return out


def drives(profile: Profile, miles: float) -> dict[str, dict[str, float]]:
    """Each labeller followed by the tracker on chapter 12's section 2 roads: collisions and
    off-centre episodes (counts), miles [mi]."""
    world = WorldConfig.for_profile(profile)
    check = dagger.val_roads(miles, 32)
    out = {}
    for name, labeller in (("expert", Expert), ("state expert", StateExpert)):
        res = evaluate(Oracle(labeller(sim=world.sim)), world, check, desc=name, workers=1)
        out[f"the oracle on the {name}'s labels"] = res.brief()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=4, help="chapter 12's training seeds 0 .. N-1")
    ap.add_argument("--miles", type=float, default=20.0, help="each labeller's drive [mi]")
    ap.add_argument("--quick", action="store_true", help="the quick profile (tests the script)")
    args = ap.parse_args()
    profile = QUICK if args.quick else FULL
    road = WorldConfig.for_profile(profile).road
    centres = road.lane_centers()
    train = fields(dataset_path(DataConfig.for_profile(profile, "train")))
    result = {
        "profile": profile.name,
        "chapter_04_states": where_apart(train, centres, (road.n_lanes - 1) // 2),
        "rounds": {a: rounds(profile, a, args.seeds, centres) for a in ("dagger", "control")},
        "labellers_driven": drives(profile, args.miles),
    }
    print(json.dumps(result, indent=1))
    if not args.quick:
        OUT.write_text(json.dumps(result, indent=1) + "\n")
        print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
