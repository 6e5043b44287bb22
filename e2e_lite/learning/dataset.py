"""The dataset: its schema, its container, its situations and its ``torch`` view.

No simulator here: the training side (models, losses, training) imports this module, not the
collector (:mod:`e2e_lite.imitation.collector`, chapter 04), so it loads without pymunk, OpenCV or
python-control. One sample per policy step (10 Hz); the schema (:data:`SCHEMA`) is the one
place that says what a sample holds, and the table below, the field list (:data:`FIELDS`), the
collector's arrays (:func:`allocate`) and :func:`synthetic_data` are all made from it.

Labels are clean: the actuator label is the expert's command from the recorded state *before*
the noise is added, and the trajectory is what the expert would drive from that state without
noise (:meth:`~e2e_lite.control.expert.Expert.trajectory_label`), not the noisy future. Throttle
and brake (seed 002's outputs) are recoverable from the acceleration label
(:func:`~e2e_lite.learning.labels.throttle_brake`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..artifacts import settings_key, to_json
from .labels import AFFORDANCE_NAMES, CHANGE, FOLLOW, N_POINTS, PASS, POINT_DIMS

#: The camera frame's size (height, width) [px] (:class:`~e2e_lite.simulation.camera.CameraConfig`'s default).
IMAGE_HW = (66, 200)

#: Every field of a sample: name -> (shape after the sample axis, dtype, meaning). ``"hw"`` in a
#: shape stands for the camera frame's height and width.
SCHEMA: dict[str, tuple[tuple, type, str]] = {
    "images": (("hw", 3), np.uint8, "the front camera frame, RGB"),
    "speed": ((), np.float32, "the car's speed [m/s]"),
    "actuators": (
        (2,),
        np.float32,
        "the expert's **clean** command: steering [rad], accel [m/s^2]",
    ),
    "trajectory": (
        (N_POINTS, POINT_DIMS),
        np.float32,
        "the expert's noise-free rollout, rear axle in the car frame at 0.3 ... 1.5 s [m] "
        "(x forward, y left)",
    ),
    "affordances": ((len(AFFORDANCE_NAMES),), np.float32, "see labels.AFFORDANCE_NAMES"),
    "track": ((), np.int32, "the track index within the split"),
    "s": ((), np.float32, "lane-frame arc length of the rear axle [m]"),
    "d": ((), np.float32, "lane-frame lateral position of the rear axle [m], left positive"),
    "lane": ((), np.int8, "nearest lane (0 = rightmost)"),
    "curvature": ((), np.float32, "the road's curvature at s [1/m]"),
    "expert_state": ((), np.int8, "KEEP 0, CHANGE 1, PASS 2, FOLLOW 3 (labels.KEEP ...)"),
    "change_side": ((), np.int8, "during a change: +1 to the left, -1 to the right; else 0"),
    "overtaking": ((), np.bool_, "during a change: True for an overtake, False for a return"),
    "noise": ((), np.bool_, "a noise burst was active (the executed command differed)"),
}
#: The fields besides the images, in the schema's order.
FIELDS = tuple(name for name in SCHEMA if name != "images")


def allocate(
    n: int, image_hw: tuple[int, int] = IMAGE_HW, fill: float | None = None
) -> dict[str, np.ndarray]:
    """Arrays for ``n`` samples of every field in :data:`SCHEMA` (uninitialised, or ``fill``).

    Args:
        n: samples.
        image_hw: the camera frame's (height, width) [px].
        fill: a value for every element; ``None`` leaves them uninitialised (``np.empty``).
    """
    out = {}
    for name, (shape, dtype, _) in SCHEMA.items():
        dims = tuple(d for s in shape for d in (image_hw if s == "hw" else (s,)))
        out[name] = (
            np.empty((n, *dims), dtype) if fill is None else np.full((n, *dims), fill, dtype)
        )
    return out


def schema_table() -> str:
    """The schema as a reStructuredText table (field, shape and dtype, meaning)."""
    short = {np.uint8: "u8", np.float32: "f32", np.int32: "i32", np.int8: "i8", np.bool_: "bool"}
    header = ("field", "shape, dtype", "meaning")
    rows = []
    for name, (shape, dtype, meaning) in SCHEMA.items():
        dims = ",".join(str(d) for s in shape for d in (IMAGE_HW if s == "hw" else (s,)))
        rows.append((f"``{name}``", f"(N,{dims}) {short[dtype]}", meaning))
    widths = [max(len(r[k]) for r in (header, *rows)) for k in range(3)]
    rule = "  ".join("=" * w for w in widths)

    def line(cells: tuple[str, str, str]) -> str:
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()

    return "\n".join([rule, line(header), rule, *map(line, rows), rule])


__doc__ = (__doc__ or "") + "\nThe schema:\n\n" + schema_table() + "\n"


@dataclass
class DrivingData:
    """A collected dataset: the arrays of the module table, their statistics and how it was made.

    Attributes:
        arrays: field name -> array (``images`` and every name in :data:`FIELDS`).
        stats: normalisation statistics, ``{"<field>_mean": ..., "<field>_std": ...}`` for speed,
            actuators, trajectory (per coordinate, (5, 2)) and affordances (per affordance).
        info: shares of situations, the collection's closed-loop metrics, the settings key.
    """

    arrays: dict[str, np.ndarray]
    stats: dict[str, np.ndarray]
    info: dict[str, Any]

    def __len__(self) -> int:
        return len(self.arrays["speed"])

    def __getattr__(self, name: str) -> np.ndarray:
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(name)


def dataset_stats(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-column mean and standard deviation (floored at 1e-6) of speed, actuators, trajectory
    and affordances: ``{"<field>_mean": ..., "<field>_std": ...}``, float32."""
    out = {}
    for name in ("speed", "actuators", "trajectory", "affordances"):
        x = arrays[name].astype(np.float64)
        out[f"{name}_mean"] = x.mean(axis=0).astype(np.float32)
        out[f"{name}_std"] = np.maximum(x.std(axis=0), 1e-6).astype(np.float32)
    return out


def situation_shares(
    arrays: dict[str, np.ndarray], rows: np.ndarray | None = None
) -> dict[str, float]:
    """Shares of samples (0..1): on curves (|kappa| > 1e-4 1/m), in a lane change, overtaking to
    the left / right, returning, following (blocked), with a noise burst active. ``rows``: only
    these samples (default all)."""
    if rows is not None:
        keys = ("expert_state", "change_side", "overtaking", "curvature", "noise")
        arrays = {k: arrays[k][rows] for k in keys}
    state, side, over = arrays["expert_state"], arrays["change_side"], arrays["overtaking"]
    change = state == CHANGE
    return {
        "curve": float(np.mean(np.abs(arrays["curvature"]) > 1e-4)),
        "lane_change": float(np.mean(change)),
        "overtake_left": float(np.mean(change & over & (side > 0))),
        "overtake_right": float(np.mean(change & over & (side < 0))),
        "return": float(np.mean(change & ~over)),
        "pass": float(np.mean(state == PASS)),
        "follow": float(np.mean(state == FOLLOW)),
        "noise": float(np.mean(arrays["noise"])),
    }


#: Below this speed a sample is "slow" [m/s]: the evaluator restarts cars at 20 m/s and the roads'
#: cruise speed is 25 m/s.
SLOW_MPS = 22.0
#: An overtake whose rear axle has moved less than this from its lane centre towards its side has
#: just started [m].
CHANGE_START_M = 0.5


def situations(
    arrays: dict[str, np.ndarray], rows: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Masks of the situations that decide collisions, each (N,) bool (``rows``: only these):

    * ``"overtake_start"``: the expert has just started an overtake (in a lane change that is an
      overtake, the rear axle has moved less than :data:`CHANGE_START_M` from its lane centre
      towards the change's side: the change's end, near the target lane's centre, is left out);
    * ``"slow"``: speed below :data:`SLOW_MPS` (the states a learned driver restarts in);
    * ``"curve"``: on an arc (|curvature| > 1e-4 1/m).
    """
    take = (lambda x: x) if rows is None else (lambda x: x[rows])
    state, over = take(arrays["expert_state"]), take(arrays["overtaking"]).astype(bool)
    offset = take(arrays["affordances"])[:, AFFORDANCE_NAMES.index("center_offset_m")]
    moved = offset * take(arrays["change_side"])  # towards the change's side [m]
    return {
        "overtake_start": (state == CHANGE) & over & (moved >= 0.0) & (moved < CHANGE_START_M),
        "slow": take(arrays["speed"]) < SLOW_MPS,
        "curve": np.abs(take(arrays["curvature"])) > 1e-4,
    }


def oversampled(
    arrays: dict[str, np.ndarray], situation: str = "overtake_start", times: int = 4
) -> np.ndarray:
    """Training rows that draw one of :func:`situations`' situations ``times`` as often as the
    rest: every row once, then that situation's rows ``times - 1`` more times (a recipe's
    ``train_rows``; an epoch grows by as many rows)."""
    if times < 1:
        raise ValueError(f"oversampled: times={times} must be at least 1")
    n = len(arrays["speed"])
    chosen = np.flatnonzero(situations(arrays)[situation])
    return np.concatenate([np.arange(n), np.tile(chosen, times - 1)])


def road_lateral(
    points_m: np.ndarray, heading_rad: np.ndarray, curvature: np.ndarray
) -> np.ndarray:
    """The lateral offset [m] of the last of each trajectory's points from where the car would be
    keeping its lane, in the road's frame (left positive), ``(B,)``: the car-frame ``y`` plus what
    the car's heading error turns away (``psi x``) minus the road's own bend (``kappa x^2 / 2``).
    So "which side" does not depend on the car's heading or on the curve (small-angle forms).

    Args:
        points_m: (B, 5, 2) car-frame trajectories [m].
        heading_rad: (B,) heading minus the road's [rad] (the ``heading_rad`` affordance).
        curvature: (B,) the road's curvature [1/m].
    """
    x, y = np.asarray(points_m)[:, -1, 0], np.asarray(points_m)[:, -1, 1]
    return y + np.asarray(heading_rad) * x - np.asarray(curvature) * x * x / 2.0


def save_dataset(path: Path, data: DrivingData, key: str) -> None:
    """Write ``data`` (arrays, statistics, info with ``key``) to the ``.npz`` file ``path``,
    compressed: the camera's flat colours deflate about 12x (a chapter-12 round of 8,000 samples:
    318 MB as raw arrays, 28 MB compressed), for about 0.5 ms per sample to write and 0.2 ms to
    read on 2 cores. Files written raw by earlier versions load as before."""
    np.savez_compressed(
        path,
        **data.arrays,
        **{f"stat_{k}": v for k, v in data.stats.items()},
        info=np.array(to_json({**data.info, "key": key})),
    )


def load_dataset(path: Path) -> tuple[DrivingData, str]:
    """Read a dataset written by :func:`save_dataset`: ``(data, its settings key)``."""
    with np.load(path, allow_pickle=False) as z:
        info = json.loads(str(z["info"]))
        arrays = {k: z[k] for k in ("images", *FIELDS)}
        stats = {k[5:]: z[k] for k in z.files if k.startswith("stat_")}
    return DrivingData(arrays, stats, info), info["key"]


def concat(first: DrivingData, second: DrivingData) -> DrivingData:
    """Rows of ``first`` then ``second``; statistics (normalisation) of ``first``."""
    arrays = {k: np.concatenate([first.arrays[k], second.arrays[k]]) for k in first.arrays}
    info = {
        **first.info,
        "key": settings_key(first.info["key"], second.info["key"]),
        "parts": [first.info["key"], second.info["key"]],
    }
    return DrivingData(arrays, dict(first.stats), info)


def synthetic_data(n: int = 64, seed: int = 0) -> DrivingData:
    """Random frames and plausible random labels with every field of a real dataset: for tests and
    speed benchmarks that must not depend on a collected dataset (nothing to learn in it)."""
    rng = np.random.default_rng([seed, 97])
    arrays = allocate(n, fill=0)
    arrays["images"][:] = rng.integers(0, 256, arrays["images"].shape, dtype=np.uint8)
    arrays["speed"][:] = rng.uniform(15.0, 25.0, n)
    arrays["actuators"][:] = np.stack([rng.normal(0, 0.02, n), rng.normal(0, 1, n)], 1)
    ahead = np.array([7.5, 0.0]) * np.arange(1, N_POINTS + 1)[:, None]  # 7.5 m per point
    arrays["trajectory"][:] = rng.normal(0, 1, (n, N_POINTS, POINT_DIMS)) + ahead
    arrays["affordances"][:] = rng.normal(0, 1, (n, len(AFFORDANCE_NAMES)))
    return DrivingData(
        arrays, dataset_stats(arrays), {"key": f"synthetic-{seed}-{n}", "split": "train"}
    )


class DrivingDataset(torch.utils.data.Dataset):
    """A ``torch`` view of :class:`DrivingData` (or a subset of its rows).

    Each item is a dict of tensors: ``image`` (3, H, W) uint8 (CHW; the models normalise),
    ``speed`` (1,) [m/s], ``actuators`` (2,) [rad, m/s^2], ``trajectory`` (10,) [m] (the 5 points
    flattened as x1, y1, ..., x5, y5), ``affordances`` (9,) (units in :data:`AFFORDANCE_NAMES`).
    Targets are in physical units; normalise them with ``data.stats``.

    Args:
        data: the dataset.
        indices: rows to expose (default: all).
    """

    def __init__(self, data: DrivingData, indices: np.ndarray | None = None) -> None:
        self.data = data
        self.indices = np.arange(len(data)) if indices is None else np.asarray(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.batch(np.array([self.indices[i]]), squeeze=True)

    def batch(
        self, rows: np.ndarray, squeeze: bool = False, device: torch.device | str | None = None
    ) -> dict[str, torch.Tensor]:
        """Items of dataset rows ``rows`` stacked along a first axis (one copy, no Python loop),
        on ``device`` when given (a model's, e.g. ``next(model.parameters()).device``)."""
        a = self.data.arrays
        out = {
            # NHWC rows permuted to NCHW: a channels-last view, no second copy
            "image": torch.from_numpy(a["images"][rows]).permute(0, 3, 1, 2),
            "speed": torch.from_numpy(a["speed"][rows, None].astype(np.float32)),
            "actuators": torch.from_numpy(a["actuators"][rows]),
            "trajectory": torch.from_numpy(a["trajectory"][rows].reshape(len(rows), -1)),
            "affordances": torch.from_numpy(a["affordances"][rows]),
        }
        if device is not None:
            out = {k: v.to(device) for k, v in out.items()}
        return {k: v[0] for k, v in out.items()} if squeeze else out
