"""What :class:`~e2e_lite.experiments.safe_agent.SafeAgent` records of each decision when it traces
the decisions before each collision (``trace_before_impact``; chapter 11)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..simulation.policy import Observation
from .safety import SafetyConfig, Verdict, check

#: The records' format (in a traced evaluation's stored key, so a stored trace has every key
#: :func:`decision_record` writes). 2: the car's pose, ``s`` and track, to re-render the frame.
RECORD_VERSION = 2


def decision_record(
    obs: Observation,
    i: int,
    heaviest: np.ndarray,
    seen: np.ndarray,
    seen_verdict: Verdict | None,
    truth: np.ndarray,
    chosen: np.ndarray,
    source: str,
    cfg: SafetyConfig,
) -> dict[str, Any]:
    """One decision of car ``i``, JSON-able (:class:`SafeAgent`'s ``trace_before_impact``).

    Keys: ``time_s`` [s], ``speed_mps`` [m/s], ``lane``; ``seen`` and ``true``, the 9 affordances
    (:data:`~e2e_lite.control.labels.AFFORDANCE_NAMES` order; perceived after any gyro fusion);
    ``perceived`` and ``rule_on_truth``: the check's verdict on the heaviest mode with each
    (``seen_verdict``, the one the module already made, or checked here when ``None``; ``"ok"``
    or the kind: ``"cannot stop"``, ``"collision course"``, ``"road edge"``), and
    ``truth_lane``, the lane the rule on the truth objected about (``"ego"``, ``"left"``,
    ``"right"``; for a road edge its side; ``""`` when it did not);
    ``source``: what was driven; ``heaviest_end`` and ``chosen_end``: the 1.5 s points [m];
    ``track_id``, ``pose`` (rear axle ``x, y, heading`` [m, m, rad]) and ``s`` [m]: where the car
    was, to re-render what its camera saw (``make_world(world_cfg, *track_id)``).
    """
    speed, kappa = float(obs.speed[i]), float(obs.curvature[i])

    def verdict(aff: np.ndarray, v: Verdict | None = None) -> tuple[str, str]:
        v = v or check(heaviest, aff, speed, kappa, cfg)
        return ("ok", "") if v.ok else (v.kind, v.lane)

    (perceived, _), (on_truth, truth_lane) = verdict(seen, seen_verdict), verdict(truth)

    return {
        "time_s": round(float(obs.time_s), 2),
        "speed_mps": round(speed, 2),
        "lane": int(obs.lane[i]),
        "seen": [round(float(a), 3) for a in seen],
        "true": [round(float(a), 3) for a in truth],
        "perceived": perceived,
        "rule_on_truth": on_truth,
        "truth_lane": truth_lane,
        "source": source,
        "heaviest_end": [round(float(a), 2) for a in heaviest[-1]],
        "chosen_end": [round(float(a), 2) for a in chosen[-1]],
        "track_id": list(obs.worlds[i].track.track_id),
        "pose": [float(a) for a in obs.state[i, :3]],
        "s": float(obs.s[i]),
    }
