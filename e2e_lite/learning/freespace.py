"""The free-space profile (chapter 11): what the front camera sees ahead, in the car's own frame.

A lane gap ("the car ahead in the left lane is 31 m away", :func:`~e2e_lite.learning.data.affordances`)
asks the camera for an inference: which lane a parked car stands in depends on the road's curve,
the car's heading and its offset, and a car 26 m ahead on a sharp curve, with the car turned by
0.07 rad, was read in another lane (chapter 11). The profile asks for what the camera sees: for
:data:`STRIP_CENTRES_M` strips of the car frame, 1 m wide, centred at ``y = -7 ... 7`` m (left
positive), the distance from the front bumper to the nearest parked car's body in that strip,
capped at :data:`PROFILE_CAP_M` ("nothing seen"). Cars wholly behind the rear bumper are left out.

* :func:`free_profile` / :func:`free_profiles`: the labels, from the world (each parked car's
  outline sampled at 48 points);
* :func:`profile_labels`: a dataset's labels, every frame's track built once;
* :class:`ProfileHead`: a small network on a driving network's frozen trunk features (the trunk
  keeps the image's 18 columns, so a strip's bearing is in them), with the thresholds from which a
  read means "nothing seen", one per strip;
* :func:`fit_profile_head`: fits it (smooth L1 on distance / cap) on all but every fifth track and
  sets each strip's threshold on the frames of the tracks it did not fit (:class:`ProfileFit`): on
  its own frames a head reads free strips closer to the cap than on new roads;
* :func:`load_or_label`, :func:`profile_head_or_load`: the same, stored.

The check that reads the profile is :func:`~e2e_lite.experiments.safety.check`'s ``profile``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from ..artifacts import artifact_path, cached, settings_key
from ..config import check_range, tqdm
from ..control.labels import GAP_CAP_M
from ..simulation.vehicle import VehicleParams
from .dataset import DrivingData, DrivingDataset
from .models import TRUNK_FEATURES, DrivingModel
from .probes import _standardiser, layer_features

if TYPE_CHECKING:  # (the labels need the simulator; the head and its fit do not)
    from ..simulation.world import World
    from .data import DataConfig

#: The strips' centres in the car frame [m] (left positive), each :data:`STRIP_HALF_M` either side.
STRIP_CENTRES_M = np.arange(-7.0, 7.5, 1.0)
STRIP_HALF_M = 0.5
N_STRIPS = len(STRIP_CENTRES_M)
#: A strip with nothing nearer reads this [m] (the lane gaps' cap).
PROFILE_CAP_M = GAP_CAP_M
#: The course's car, rear axle to front bumper [m].
FRONT_M = VehicleParams().length_m - VehicleParams().rear_overhang_m
_OUTLINE = np.linspace(0.0, 1.0, 13)[:-1]  # 12 points along each of a box's 4 edges


def _outlines(corners: np.ndarray) -> np.ndarray:
    """Points along each box's edges: ``(N, 4, 2)`` corners -> ``(N, 48, 2)`` [m]."""
    a, b = corners, np.roll(corners, -1, axis=1)
    pts = a[:, :, None, :] + (b - a)[:, :, None, :] * _OUTLINE[None, None, :, None]
    return pts.reshape(len(corners), -1, 2)


def free_profile(world: World, s: float, d: float, heading_error: float) -> np.ndarray:
    """The free-space profile of a car whose rear axle is at lane-frame ``(s, d)`` [m], turned
    ``heading_error`` [rad] from the road: ``(N_STRIPS,)`` distances [m] from the front bumper
    to the nearest parked car's body in each strip (0 when it reaches past the bumper;
    :data:`PROFILE_CAP_M` when none within it)."""
    track, cars, veh = world.track, world.cars, world.vehicle
    front_m, rear_m = veh.length_m - veh.rear_overhang_m, veh.rear_overhang_m
    out = np.full(N_STRIPS, PROFILE_CAP_M)
    near = cars.between(s - 15.0, s + PROFILE_CAP_M + 20.0)  # (a sharp curve: a margin)
    if near.stop <= near.start:
        return out
    x0, y0, road = track.pose(s, d)
    h = float(road) + heading_error
    c, sn = np.cos(h), np.sin(h)
    pts = _outlines(cars.box_corners_3d[near, :4, :2])  # (the footprints, computed once)
    dx, dy = pts[..., 0] - x0, pts[..., 1] - y0
    ahead, left = c * dx + sn * dy, -sn * dx + c * dy  # car frame, (cars, 48)
    keep = ahead.max(axis=1) > -rear_m  # not wholly behind the rear bumper
    ahead, left = ahead[keep], left[keep]
    for k, centre in enumerate(STRIP_CENTRES_M):
        inside = np.abs(left - centre) <= STRIP_HALF_M
        if inside.any():
            nearest = float(ahead[inside].min()) - front_m
            out[k] = min(PROFILE_CAP_M, max(0.0, nearest))
    return out


def in_view(
    distance_m: np.ndarray, hfov_deg: float, camera_ahead_m: float, front_m: float = FRONT_M
) -> np.ndarray:
    """Whether each strip at ``distance_m`` from the front bumper (``(..., N_STRIPS)`` [m]) lies
    in a camera's horizontal field of view ``hfov_deg`` [deg] from ``camera_ahead_m`` ahead of
    the rear axle (the strip's nearer side must be in view; ``front_m``: rear axle to front bumper
    [m]): strips to the side close to the car do not."""
    ahead = np.asarray(distance_m, dtype=float) + front_m - camera_ahead_m
    side = np.maximum(np.abs(STRIP_CENTRES_M) - STRIP_HALF_M, 0.0)
    return ahead * np.tan(np.radians(hfov_deg) / 2.0) >= side


def free_profiles(
    worlds: list[World], s: np.ndarray, d: np.ndarray, heading_error: np.ndarray
) -> np.ndarray:
    """:func:`free_profile` of B cars, ``(B, N_STRIPS)`` [m] (car i in ``worlds[i]``)."""
    rows = zip(worlds, np.asarray(s, float), np.asarray(d, float), np.asarray(heading_error, float))
    out = [free_profile(w, float(si), float(di), float(hi)) for w, si, di, hi in rows]
    return np.stack(out) if out else np.zeros((0, N_STRIPS))


def profile_labels(data: DrivingData, data_cfg: DataConfig, progress: bool = True) -> np.ndarray:
    """The free-space profile of every frame of ``data`` (recorded with ``data_cfg``, or views
    made from such frames), ``(N, N_STRIPS)`` float32 [m]: rebuilt from each frame's track,
    ``(s, d)`` and heading to the road (the first affordance)."""
    from .recovery import _world_cache  # (the simulator: only where labels are made)

    a = data.arrays
    worlds = _world_cache(data_cfg)(a["track"])  # (each track built once)
    out = np.empty((len(data), N_STRIPS), dtype=np.float32)
    bar = tqdm(range(len(data)), desc="free-space labels", unit="frame", disable=not progress)
    for i in bar:
        heading = float(a["affordances"][i, 0])
        out[i] = free_profile(worlds[i], float(a["s"][i]), float(a["d"][i]), heading)
    return out


class ProfileHead(nn.Module):
    """A driving network's frozen trunk features (B, 1152) -> the free-space profile (B, 15) [m].

    Standardises its input with the fitted frames' statistics, reads with a two-hidden-layer MLP
    (``width`` units each), scales to metres and floors at 0. ``free_m`` (a buffer, per strip) is
    where a read starts to mean "nothing seen" (set by :func:`fit_profile_head`)."""

    def __init__(self, width: int = 256) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(TRUNK_FEATURES, width),
            nn.ReLU(),
            nn.Linear(width, width),
            nn.ReLU(),
            nn.Linear(width, N_STRIPS),
        )
        self.register_buffer("x_mean", torch.zeros(TRUNK_FEATURES))
        self.register_buffer("x_std", torch.ones(TRUNK_FEATURES))
        self.register_buffer("free_m", torch.full((N_STRIPS,), PROFILE_CAP_M - 0.5))

    def forward(self, trunk: torch.Tensor) -> torch.Tensor:
        """Distances [m] from the front bumper per strip, ``(B, N_STRIPS)``."""
        x = (trunk.float() - self.x_mean) / self.x_std
        return (self.net(x) * PROFILE_CAP_M).clamp(min=0.0)


@dataclass(frozen=True)
class ProfileFit:
    """How :func:`fit_profile_head` fits and calibrates a :class:`ProfileHead`.

    Attributes:
        epochs, lr, batch_size, seed: Adam at ``lr`` with a cosine decay over ``epochs``.
        holdout_every: tracks whose index is a multiple of this are left out of the fit and set
            the thresholds.
        free_quantile: each strip's threshold is this quantile of the head's reads, on the
            held-out tracks' frames, of that strip when it is free (the share of free strips
            read as a car: the false alarms the calibration accepts).
    """

    epochs: int = 30
    lr: float = 1e-3
    batch_size: int = 256
    seed: int = 0
    holdout_every: int = 5
    free_quantile: float = 0.02

    def __post_init__(self) -> None:
        o = "ProfileFit"
        check_range(o, "epochs", self.epochs, 1, 1000, integer=True)
        check_range(o, "lr", self.lr, 0.0, 1.0, lo_open=True)
        check_range(o, "batch_size", self.batch_size, 1, 1 << 16, integer=True)
        check_range(o, "holdout_every", self.holdout_every, 2, 1000, integer=True)
        check_range(o, "free_quantile", self.free_quantile, 0.0, 0.5, lo_open=True)


def fit_profile_head(
    model: DrivingModel,
    frames: DrivingData,
    labels: np.ndarray,
    settings: ProfileFit = ProfileFit(),
    progress: bool = True,
) -> ProfileHead:
    """A :class:`ProfileHead` on ``model``'s frozen trunk, fitted to ``labels`` (``(N, 15)`` [m],
    :func:`profile_labels` of ``frames``): smooth L1 (beta 0.05) on distance / cap, on the frames
    of every track but each ``settings.holdout_every``-th; each strip's ``free_m`` is then
    ``settings.free_quantile`` of its reads on the held-out tracks' free frames (the cap when a
    strip is never free there). Seeded: the same inputs give the same head. CPU, eval mode."""
    if len(labels) != len(frames):
        raise ValueError(f"{len(labels)} label rows for {len(frames)} frames")
    x = layer_features(model, DrivingDataset(frames), "trunk")
    held = frames.arrays["track"] % settings.holdout_every == 0
    if held.all() or not held.any():
        raise ValueError(
            f"fit_profile_head: the frames' tracks must include multiples of "
            f"{settings.holdout_every} (held out) and others (fitted)"
        )
    head = ProfileHead()
    x_mean, x_std = _standardiser(x[~held])
    head.x_mean.copy_(torch.from_numpy(x_mean))
    head.x_std.copy_(torch.from_numpy(x_std))
    torch.manual_seed(settings.seed)
    head.net.apply(lambda m: m.reset_parameters() if isinstance(m, nn.Linear) else None)
    xt = torch.from_numpy(x[~held])
    yt = torch.from_numpy(np.asarray(labels, np.float32)[~held] / PROFILE_CAP_M)
    opt = torch.optim.Adam(head.net.parameters(), lr=settings.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, settings.epochs)
    gen = torch.Generator().manual_seed(settings.seed)
    head.train()
    bar = tqdm(range(settings.epochs), desc="profile head", unit="epoch", disable=not progress)
    for _ in bar:
        for rows in torch.randperm(len(xt), generator=gen).split(settings.batch_size):
            x_n = (xt[rows] - head.x_mean) / head.x_std
            loss = nn.functional.smooth_l1_loss(head.net(x_n), yt[rows], beta=0.05)
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
    head.eval()
    with torch.inference_mode():
        reads = head(torch.from_numpy(x[held])).numpy()
    free = np.asarray(labels)[held] >= PROFILE_CAP_M
    with torch.no_grad():
        for k in range(N_STRIPS):
            if free[:, k].any():
                head.free_m[k] = float(np.quantile(reads[free[:, k], k], settings.free_quantile))
            else:
                head.free_m[k] = PROFILE_CAP_M
    return head


def load_or_label(data: DrivingData, data_cfg: DataConfig, progress: bool = True) -> np.ndarray:
    """:func:`profile_labels` of ``data``, stored as ``<outputs>/data/<split>-profile-<key>.npz``
    and read back while ``data`` is the same (its key)."""
    key = settings_key("free-profile-v1", data.info["key"])
    path = artifact_path("data", f"{data_cfg.split}-profile-{key}.npz")

    def save(p: Path, labels: np.ndarray, k: str) -> None:
        with open(p, "wb") as f:
            np.savez(f, labels=labels, key=k)

    def load(p: Path) -> tuple[np.ndarray, str]:
        with np.load(p) as z:
            return z["labels"], str(z["key"])

    return cached(path, key, lambda: profile_labels(data, data_cfg, progress), save, load)


def profile_head_or_load(
    name: str,
    model: DrivingModel,
    frames: DrivingData,
    labels: np.ndarray,
    settings: ProfileFit = ProfileFit(),
    progress: bool = True,
) -> ProfileHead:
    """:func:`fit_profile_head`, stored as ``<outputs>/checkpoints/<name>_profile.pt`` and read
    back while the network's weights, the frames and ``settings`` are the same."""
    from .checkpoints import weights_digest  # (training's plots: not for a shard worker)

    key = settings_key("profile-head-v1", settings, weights_digest(model), frames.info["key"])
    path = artifact_path("checkpoints", f"{name}_profile.pt")

    def save(p: Path, head: ProfileHead, k: str) -> None:
        torch.save({"key": k, "head": head.state_dict()}, p)

    def load(p: Path) -> tuple[ProfileHead, str]:
        blob = torch.load(p, map_location="cpu", weights_only=True)
        head = ProfileHead()
        head.load_state_dict(blob["head"])
        return head.eval(), blob["key"]

    def build() -> ProfileHead:
        if progress:
            print(f"[freespace] {name}: fitting the free-space head on the frozen trunk")
        return fit_profile_head(model, frames, labels, settings, progress)

    return cached(path, key, build, save, load)
