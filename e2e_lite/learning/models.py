"""Networks: the PilotNet trunk, PilotNet itself, and the fusion network with interchangeable heads.

Every learned driver of the course sees the same 3 x 66 x 200 camera frame through the same
convolutional trunk (seed 003's PilotNet), so the ablation of chapter 10 compares heads and losses,
not backbones:

* :class:`PilotNet` (seed 003): trunk -> fully connected 100-50-10 -> outputs. Steering only in
  chapter 05 (about 250K parameters).
* :class:`FusionNet` (seed 000's architecture, scaled to a CPU): trunk -> concatenate the car's
  speed -> a *sensor-fusion* MLP -> a main head (actuators, trajectory or GMM) and, optionally, an
  affordance head on the same fused features.

Images enter as ``uint8`` (B, 3, 66, 200); a fixed, untrained layer maps them to [-1, 1] (seed 003
"hard-coded" its normalisation so it runs on the GPU with the rest). Targets are learned in
normalised units: each model carries the dataset's mean and standard deviation of its outputs (and
of the speed input) as buffers, so a checkpoint holds its own normalisation and
:meth:`DrivingModel.denormalise` returns physical units.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from typing import ClassVar

import numpy as np
import torch
from torch import nn

from ..config import apply_precision, check_range
from .heads import HEADS, Mixture

apply_precision(torch)  # fp32 on GPUs unless E2E_LITE_TF32=1 (config.precision)

TRUNK_FEATURES = 64 * 1 * 18  # seed 003's figure says 1164; the layers give 64 x 1 x 18 = 1152
N_AFFORDANCES = 9
#: what an affordance head may read (:attr:`ModelConfig.affordance_from`)
AFFORDANCE_SOURCES = ("fused", "trunk")


@dataclass(frozen=True)
class ModelConfig:
    """What network to build.

    Attributes:
        kind: ``"pilotnet"`` (seed 003: 100-50-10 head, no speed input) or ``"fusion"`` (seed 000:
            speed fused into an MLP, optional affordance head).
        head: ``"steer"`` (1 output: curvature 1/r), ``"actuators"`` (steering, acceleration),
            ``"trajectory"`` (10: five (x, y) points) or ``"gmm"`` (``gmm_modes`` x 21).
        gmm_modes: mixture components of a GMM head (the paper: 2).
        affordance: add the affordance head (fusion only).
        fusion_width: width of the fusion MLP's layers (the paper: 512; 256 fits the CPU budget).
        fusion_layers: number of fully connected layers in the fusion MLP (the paper: 3).
        dropout: dropout after each fusion layer (the paper: 0.5).
        batchnorm: batch norm in the fusion MLP's hidden layers (the paper's GMM practicality).
        affordance_from: what the affordance head reads: ``"fused"``, the fusion MLP's output (the
            paper's Fig. 1), or ``"trunk"``, the image backbone's features (chapter 08's probes:
            the trunk holds the affordances, the fusion MLP trained for the trajectory keeps only
            part of them).
        sigma_floor: a GMM head's smallest standard deviation, in normalised units (1 = one
            dataset standard deviation of that coordinate).
        sigma_floor_m: a GMM head's floor in metres instead, the same for every point and axis
            (``sigma_floor`` is then unused): :meth:`DrivingModel.sigma_floor` turns it into each
            coordinate's normalised units with the model's target scale.
    """

    kind: str = "fusion"
    head: str = "trajectory"
    gmm_modes: int = 2
    affordance: bool = False
    fusion_width: int = 256
    fusion_layers: int = 3
    dropout: float = 0.5
    batchnorm: bool = True
    affordance_from: str = "fused"
    sigma_floor: float = 0.01
    sigma_floor_m: float | None = None

    #: fields added after checkpoints existed, left out of settings keys at their default (see
    #: :func:`~e2e_lite.artifacts.settings_key`), so those checkpoints keep their keys
    KEY_DEFAULTS_OMITTED: ClassVar[tuple[str, ...]] = (
        "affordance_from",
        "sigma_floor",
        "sigma_floor_m",
    )

    def __post_init__(self) -> None:
        o = "ModelConfig"
        if self.kind not in ("pilotnet", "fusion"):
            raise ValueError(f"{o}.kind={self.kind!r} is invalid: must be 'pilotnet' or 'fusion'")
        if self.head not in HEADS:
            raise ValueError(f"{o}.head={self.head!r} is invalid: must be one of {list(HEADS)}")
        check_range(o, "gmm_modes", self.gmm_modes, 1, 16, integer=True)
        check_range(o, "fusion_width", self.fusion_width, 8, 4096, integer=True)
        check_range(o, "fusion_layers", self.fusion_layers, 1, 8, integer=True)
        check_range(o, "dropout", self.dropout, 0.0, 1.0, hi_open=True)
        check_range(o, "sigma_floor", self.sigma_floor, 0.0, 1.0, lo_open=True)
        if self.sigma_floor_m is not None:
            check_range(o, "sigma_floor_m", self.sigma_floor_m, 0.0, 10.0, lo_open=True)
        if self.affordance_from not in AFFORDANCE_SOURCES:
            raise ValueError(
                f"{o}.affordance_from={self.affordance_from!r} is invalid: must be one of "
                f"{AFFORDANCE_SOURCES}"
            )
        if self.kind == "pilotnet" and self.affordance:
            raise ValueError(f"{o}.affordance=True is invalid: only a fusion model has that head")

    @property
    def out_size(self) -> int:
        """Size of the main head's output."""
        return HEADS[self.head].out_size(self.gmm_modes)

    @property
    def target_size(self) -> int:
        """Size of the target the main head is trained on (a GMM predicts 10-d trajectories)."""
        return HEADS[self.head].target_size


class Normalise(nn.Module):
    """Fixed (untrained) input normalisation: uint8 pixels to ``x / 127.5 - 1`` in [-1, 1]."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = image.float()
        if x.data_ptr() == image.data_ptr():  # already float: never scale the caller's tensor
            x = x.clone()
        return x.div_(127.5).sub_(1.0)  # in place: the same numbers, two fewer image-sized copies


class PilotNetTrunk(nn.Module):
    """Seed 003's convolutions: 24, 36, 48 filters 5x5 stride 2, then 64, 64 filters 3x3; ReLU.

    Maps (B, 3, 66, 200) to (B, 1152) features.
    """

    def __init__(self) -> None:
        super().__init__()
        self.normalise = Normalise()
        layers: list[nn.Module] = []
        channels = [3, 24, 36, 48, 64, 64]
        kernels, strides = [5, 5, 5, 3, 3], [2, 2, 2, 1, 1]
        for c_in, c_out, k, s in zip(channels[:-1], channels[1:], kernels, strides):
            layers += [nn.Conv2d(c_in, c_out, k, s), nn.ReLU(inplace=True)]
        self.convs = nn.Sequential(*layers)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.convs(self.normalise(image)).flatten(1)


class DrivingModel(nn.Module):
    """Base of the course's networks: config, normalisation buffers, ``denormalise``.

    Buffers (saved in checkpoints, never trained): ``speed_mean``, ``speed_std`` [m/s] of the speed
    input and ``target_mean``, ``target_std`` of the main target (physical units).
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.register_buffer("speed_mean", torch.zeros(1))
        self.register_buffer("speed_std", torch.ones(1))
        self.register_buffer("target_mean", torch.zeros(cfg.target_size))
        self.register_buffer("target_std", torch.ones(cfg.target_size))
        self.register_buffer("affordance_mean", torch.zeros(N_AFFORDANCES))
        self.register_buffer("affordance_std", torch.ones(N_AFFORDANCES))

    def set_normalisation(self, stats: dict[str, np.ndarray]) -> None:
        """Copy normalisation statistics ``{"speed_mean": ..., "target_mean": ...}`` into the buffers."""
        for name, value in stats.items():
            buf = getattr(self, name)
            buf.copy_(torch.as_tensor(np.asarray(value, dtype=np.float32).reshape(buf.shape)))

    def normalisation(self) -> dict[str, np.ndarray]:
        """The normalisation buffers as numpy arrays."""
        names = (
            "speed_mean",
            "speed_std",
            "target_mean",
            "target_std",
            "affordance_mean",
            "affordance_std",
        )
        return {n: getattr(self, n).detach().cpu().numpy().copy() for n in names}

    def normalise_target(self, target: torch.Tensor) -> torch.Tensor:
        """Physical target -> normalised units."""
        return (target - self.target_mean) / self.target_std

    def denormalise(self, out: torch.Tensor) -> torch.Tensor:
        """Normalised main output (a point estimate, ``target_size`` wide) -> physical units."""
        return out * self.target_std + self.target_mean

    def sigma_floor(self) -> float | torch.Tensor:
        """A GMM head's sigma floor in normalised units: ``cfg.sigma_floor``, or
        ``cfg.sigma_floor_m`` [m] divided by each coordinate's target scale, ``(10,)``."""
        if self.cfg.sigma_floor_m is None:
            return self.cfg.sigma_floor
        return self.cfg.sigma_floor_m / self.target_std

    def mixture(self, out: torch.Tensor, sigma_fixed: bool = False) -> Mixture:
        """A GMM head's output ``(B, K x 21)`` as its :class:`~e2e_lite.learning.heads.Mixture`
        (normalised units; sigmas floored at :meth:`sigma_floor`, or all 1 when
        ``sigma_fixed``)."""
        return Mixture.from_output(out, self.cfg.gmm_modes, self.sigma_floor(), sigma_fixed)

    def config_dict(self) -> dict:
        """The model's settings as a dict (stored in checkpoints)."""
        return asdict(self.cfg)


class PilotNet(DrivingModel):
    """Seed 003's network: trunk, then fully connected 100-50-10 and the output (no speed input)."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        self.trunk = PilotNetTrunk()
        self.head = nn.Sequential(
            nn.Linear(TRUNK_FEATURES, 100),
            nn.ReLU(inplace=True),
            nn.Linear(100, 50),
            nn.ReLU(inplace=True),
            nn.Linear(50, 10),
            nn.ReLU(inplace=True),
            nn.Linear(10, cfg.out_size),
        )

    def forward(
        self, image: torch.Tensor, speed: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """``{"main": (B, out_size)}`` in normalised units; ``speed`` is ignored."""
        return {"main": self.head(self.trunk(image))}


class FusionNet(DrivingModel):
    """Trunk + speed -> fusion MLP -> main head (+ affordance head). Seed 000's Fig. 1."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        self.trunk = PilotNetTrunk()
        layers: list[nn.Module] = []
        width_in = TRUNK_FEATURES + 1
        for _ in range(cfg.fusion_layers):
            layers.append(nn.Linear(width_in, cfg.fusion_width))
            if cfg.batchnorm:
                layers.append(nn.BatchNorm1d(cfg.fusion_width))
            layers.append(nn.ReLU(inplace=True))
            if cfg.dropout > 0:
                layers.append(nn.Dropout(cfg.dropout))
            width_in = cfg.fusion_width
        self.fusion = nn.Sequential(*layers)
        self.head = HEADS[cfg.head].layer(cfg.fusion_width, cfg.gmm_modes)
        width = TRUNK_FEATURES if cfg.affordance_from == "trunk" else cfg.fusion_width
        self.affordance_head = (
            nn.Sequential(nn.Linear(width, 64), nn.ReLU(inplace=True), nn.Linear(64, N_AFFORDANCES))
            if cfg.affordance
            else None
        )

    def forward(self, image: torch.Tensor, speed: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{"main": (B, out_size)[, "affordance": (B, 9)]}`` in normalised units.

        Args:
            image: (B, 3, 66, 200) uint8 (or float in [0, 255]).
            speed: (B, 1) speed [m/s] (normalised inside with the model's statistics).
        """
        features = self.features(image, speed)
        out = {"main": self.head(features["fused"])}
        if self.affordance_head is not None:
            out["affordance"] = self.affordance_head(features[self.cfg.affordance_from])
        return out

    def features(self, image: torch.Tensor, speed: torch.Tensor) -> dict[str, torch.Tensor]:
        """The representations the heads read: ``"trunk"`` (B, 1152), the image backbone's
        features, and ``"fused"`` (B, fusion_width), the fusion MLP's output (after its last
        dropout in training mode). Arguments as in :meth:`forward`."""
        speed_n = (speed.float().reshape(-1, 1) - self.speed_mean) / self.speed_std
        trunk = self.trunk(image)
        return {"trunk": trunk, "fused": self.fusion(torch.cat([trunk, speed_n], dim=1))}


def build_model(cfg: ModelConfig) -> DrivingModel:
    """The network of ``cfg`` (weights from torch's default initialisation; seed torch first)."""
    return PilotNet(cfg) if cfg.kind == "pilotnet" else FusionNet(cfg)


def count_parameters(model: nn.Module, trainable_only: bool = True) -> int:
    """Number of (trainable) parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad or not trainable_only)


def pick_device(device: str = "auto") -> torch.device:
    """``"auto"``: CUDA when available, else CPU. Nothing in the course requires a GPU."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def prepare(model: DrivingModel, device: torch.device) -> DrivingModel:
    """Move to ``device``; on CPU use the channels-last memory format (faster convolutions here)."""
    model = model.to(device)
    if device.type == "cpu":
        model = model.to(memory_format=torch.channels_last)
    return model


def images_to_tensor(images: np.ndarray | torch.Tensor, device: torch.device) -> torch.Tensor:
    """Frames (B, H, W, 3) uint8 (numpy, as rendered) -> (B, 3, H, W) uint8 on ``device``.

    The permuted view of an HWC array already has channels-last strides; no copy on CPU."""
    t = torch.from_numpy(images) if isinstance(images, np.ndarray) else images
    if t.shape[-1] == 3:
        t = t.permute(0, 3, 1, 2)
    return t.to(device, non_blocking=True)


def weights_digest(model: torch.nn.Module) -> str:
    """A SHA-256 hex digest of a model's weights and buffers (names and bytes, in order): what
    identifies a trained network's behaviour, whatever file it came from."""
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
