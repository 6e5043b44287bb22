"""Drives stored and read back: a closed-loop evaluation is saved as
``evaluations/<file>-<key>.json`` under a key of everything that decides what it drives (the
driver's :func:`~e2e_lite.simulation.policy.fingerprint`, of what its ``identity()`` declares;
the world, the evaluation's settings, the precision and torch), and read back instead of driven
again while none of them changed. Chapter 10's ablation, chapter 11's guarded drives, chapter
12's iterates and the record all drive through :func:`evaluate_stored`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..artifacts import artifact_path, cached, load_json, save_json, settings_key, versioned
from ..config import precision
from ..driving.evaluation import evaluate
from ..driving.metrics import EvalResult
from ..driving.rollout import EvalConfig
from ..simulation.policy import Policy, fingerprint
from ..simulation.world import WorldConfig


def evaluate_stored(
    file: str,
    label: str,
    policy: Policy,
    world_cfg: WorldConfig,
    cfg: EvalConfig,
    *,
    reuse: bool = True,
    progress: bool = True,
    workers: int | None = None,
) -> EvalResult:
    """One driver's evaluation, stored as ``evaluations/<file>-<settings key>.json`` with what the
    policy reported (``result.info``, which must be JSON-able: :meth:`EvalResult.to_json`), and
    read back as the same :class:`EvalResult` (less its traces) instead of driven again while
    the driver (:func:`fingerprint`), world, settings and precision are the same (see
    :func:`~e2e_lite.record.ablation.evaluate_drivers`)."""
    driven = []

    def run() -> EvalResult:
        res = evaluate(policy, world_cfg, cfg, desc=label, progress=progress, workers=workers)
        if progress:
            print(f"{label}: {res.summary()}", flush=True)
        driven.append(res)
        return res

    if not reuse:
        return run()
    path, run_key = stored_at(file, policy, world_cfg, cfg)
    result = cached(path, run_key, run, _save_result, _load_result, verbose=progress)
    if progress and not driven:
        print(f"{label}: reusing {path.name} ({result.miles:.3g} mi)", flush=True)
    return result


def stored_at(
    file: str, policy: Policy, world_cfg: WorldConfig, cfg: EvalConfig, *what: Any
) -> tuple[Path, str]:
    """Where a drive of ``policy`` is stored, and its key (the driver's :func:`fingerprint`, world,
    settings, precision and ``what`` else), which is in the name: each drive's settings a file."""
    parts = (fingerprint(policy), world_cfg, cfg, precision(), torch.__version__)
    key = settings_key(versioned("evaluation"), *what, *parts)
    return artifact_path("evaluations", f"{file}-{key}.json"), key


def _save_result(path: Path, result: EvalResult, key: str) -> None:
    save_json(path, {"key": key, **result.to_json()})


def _load_result(path: Path) -> tuple[EvalResult, str]:
    stored = load_json(path)
    return EvalResult.from_json(stored), stored["key"]
