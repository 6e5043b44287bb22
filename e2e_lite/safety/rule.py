"""The safety module (chapter 11): check a proposed trajectory before the tracker follows it.

Seed 000's architecture (its Fig. 1) validates the network's trajectory with a safety module and
leaves it unbuilt. A trajectory, unlike a steering angle, says where the car means to be, so it
can be checked against what the car knows about the road ahead. The rule here is in the spirit of
responsibility-sensitive safety (RSS), for a road of parked cars:

Inputs (what the driver perceives): the 5 proposed points ``(x_i, y_i)`` in the car frame at
``t_i = 0.3 i`` s, the car's speed ``v``, the road's curvature ``kappa`` here (from the map, as
the cruise control knows it), and the 9 affordances (``e2e_lite.imitation.collector.AFFORDANCE_NAMES``): the
heading to the road ``h``, the offset from the lane centre, the distances to the markings and the
road edges, and the free gap ahead of the front bumper in the ego, left and right lanes (capped at
60 m: "nothing seen"). The network's own affordance head provides them; the *ground-truth variant*
feeds the world's true values into the same rule, an upper bound on what better perception buys.

1. Where the body goes. In the lane frame the rear axle moves sideways by
   ``Delta_i = y_i + h x_i - kappa x_i^2 / 2`` (the road bends by ``kappa x^2 / 2``); the body
   spans ``Delta_i +- w / 2`` (``w`` the car's width). Between points the path is interpolated.
2. Lateral: the body must stay on the road:
   ``Delta_i + w / 2 <= left_edge`` and ``-Delta_i + w / 2 <= right_edge``.
3. Lanes entered: the body occupies a lane (ego, left or right) when it is more than
   ``lane_overlap_m`` across the lane's marking. The lane's perceived gap ``g`` places a parked
   car ``g`` metres ahead of the front bumper.
4. Longitudinal, in every lane the body occupies: (a) along the 1.5 s the body never reaches the
   parked car (the front stays ``margin_m`` short of it while the body is in that lane), and
   (b) if the horizon ends in that lane (the car's centre line inside it), the car can still
   stop before the parked car: ``g - x_5 >= v_5 rho + v_5^2 / (2 beta) + margin`` (reaction time ``rho``,
   braking ``beta``; ``v_5`` the speed at the last point). A gap at the cap counts as free.

On a failed check the module falls back, in this order: the network's other GMM modes (heaviest
first) if one passes; otherwise a braking trajectory (:func:`brake_to_lane`, braking at ``beta``
to a lane centre): the first that passes the check among the current lane's and its neighbours',
nearest first to where the network's heaviest mode was going (a car half-way through a lane
change brakes on into the lane it is entering, not back towards the car it is leaving);
otherwise :func:`keep_lane_brake`, back to the centre of the current lane (the last resort,
unchecked). With ``SafetyConfig(fallback="path")`` a mode rejected for a parked car is instead
braked along its own path (:func:`brake_along`), which needs no perceived lane geometry. A car
the module falls back for may be braked harder than the rule plans with
(``SafetyConfig.emergency_brake_mps2``, applied by the driver).

The "nothing seen" thresholds of a perceived module are calibrated on training frames
(:func:`calibrate_gap_free`).

The driver that applies the rule to a trajectory network is :class:`~e2e_lite.safety.agent.SafeAgent`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..config import check_range
from ..learning.labels import (
    AFFORDANCE_INDEX,
    GAP_CAP_M,
    GAP_NAMES,
    N_POINTS,
    PATH_SUBSTEPS,
    POINT_DT_S,
    along_path,
    interpolated_path,
)

_A = AFFORDANCE_INDEX


#: What the module may fall back to (:attr:`SafetyConfig.fallback`).
FALLBACKS = ("lanes", "path", "keep-lane")
#: The version of what the module computes: part of every stored guarded evaluation's key
#: (:func:`e2e_lite.record.stored.fingerprint`). Bump it when a change to the rule, its fallback or
#: the driver's reports changes what a stored result would hold.
RESULTS_VERSION = 3  # 3: a collision's cause splits the network's (a hand-back, or silent)


@dataclass(frozen=True)
class SafetyConfig:
    """Settings of the check (twelve, each the rule's or its fallback's).

    Attributes:
        reaction_s: reaction time rho before braking [s] (one policy period and a margin).
        brake_mps2: braking beta assumed for stopping, and used by the fallback's path [m/s^2]
            (the tracker's braking limit).
        margin_m: distance always kept to a parked car [m].
        lane_overlap_m: how far across a marking the body must be to occupy that lane [m].
        edge_margin_m: how far past the road's edge line the body may go (onto the shoulder; the
            guard rail is further out) [m].
        car_width_m, car_length_m: the ego's body [m].
        parked_length_m: a parked car's length [m].
        gap_free_m: a perceived gap at least this long means nothing was seen in the ego lane
            [m]. Right for the true affordances (exactly the 60 m cap when the lane is free); a
            learned head answers near the cap with noise, so the perceived module calibrates it
            on training frames (:func:`calibrate_gap_free`).
        gap_free_side_m: the same threshold for the left and right lanes' gaps [m]; ``None``:
            ``gap_free_m``. A head may see the neighbouring lanes less sharply than its own.
        fallback: what the module drives when no mode passes (see :func:`choose`), one of
            :data:`FALLBACKS`. ``"lanes"``: braking to a lane centre, the current lane's or a
            neighbour's, the first that passes (with the true affordances the keep-lane brake
            alone pulled cars half-way through a lane change back in front of the car they were
            passing). ``"path"``: when a parked car is the reason, braking along the network's
            own path (its lane and its path need no perceived lane geometry, which the lane
            fallback is made of; road-edge rejections keep the lane fallback). ``"keep-lane"``:
            the keep-lane brake alone.
        emergency_brake_mps2: the fallback's deceleration [m/s^2]: a car the module falls back
            for is braked at this, the tracker's steering kept (the car's own limit still clips
            it). ``None``: the tracker's braking, at most ``brake_mps2``. The check still plans
            with ``brake_mps2``, so a stronger emergency brake is headroom the rule does not count
            on (chapter 11: the course's car brakes at 8 where the tracker stops at 6).
    """

    reaction_s: float = 0.2
    brake_mps2: float = 6.0
    margin_m: float = 2.0
    lane_overlap_m: float = 0.3
    edge_margin_m: float = 0.3
    car_width_m: float = 1.8
    car_length_m: float = 4.5
    parked_length_m: float = 4.5
    gap_free_m: float = GAP_CAP_M - 0.5
    gap_free_side_m: float | None = None
    fallback: str = "lanes"
    emergency_brake_mps2: float | None = None

    def __post_init__(self) -> None:
        o = "SafetyConfig"
        check_range(o, "reaction_s", self.reaction_s, 0.0, 5.0)
        check_range(o, "brake_mps2", self.brake_mps2, 0.0, 15.0, lo_open=True)
        check_range(o, "margin_m", self.margin_m, 0.0, 50.0)
        check_range(o, "lane_overlap_m", self.lane_overlap_m, 0.0, 2.0)
        check_range(o, "edge_margin_m", self.edge_margin_m, -2.0, 2.0)
        check_range(o, "car_width_m", self.car_width_m, 0.5, 4.0)
        check_range(o, "car_length_m", self.car_length_m, 1.0, 20.0)
        check_range(o, "parked_length_m", self.parked_length_m, 1.0, 20.0)
        if self.fallback not in FALLBACKS:
            raise ValueError(
                f"{o}.fallback={self.fallback!r} is invalid: must be one of {FALLBACKS}"
            )
        for name in ("gap_free_m", "gap_free_side_m"):
            if getattr(self, name) is not None:
                check_range(o, name, getattr(self, name), 1.0, 1000.0)
        if self.emergency_brake_mps2 is not None:
            check_range(
                o, "emergency_brake_mps2", self.emergency_brake_mps2, 0.0, 15.0, lo_open=True
            )

    def free_from_m(self, lane: str) -> float:
        """The perceived gap from which ``lane`` (``"ego"``, ``"left"``, ``"right"``) is free [m]."""
        side = self.gap_free_side_m
        return self.gap_free_m if lane == "ego" or side is None else side

    def stopping_m(self, speed_mps: float) -> float:
        """RSS's safe distance to a standing obstacle: ``v rho + v^2 / (2 beta) + margin`` [m]."""
        v = max(0.0, speed_mps)
        return v * self.reaction_s + v * v / (2.0 * self.brake_mps2) + self.margin_m


@dataclass(frozen=True)
class Verdict:
    """The check's answer: ``ok``, and when not, why (readable) and where (lane, point)."""

    ok: bool
    reason: str = ""
    lane: str = ""
    kind: str = ""  # "road edge", "collision course" or "cannot stop"
    t_s: float = float("inf")  # when the violation begins [s] (the horizon's end for "cannot stop")


def check(
    points: np.ndarray,
    aff: np.ndarray,
    speed_mps: float,
    curvature: float,
    cfg: SafetyConfig | None = None,
) -> Verdict:
    """Is following ``points`` safe, by the rule of the module docstring?

    Args:
        points: ``(5, 2)`` proposed rear-axle positions, car frame [m], 0.3 s apart.
        aff: the 9 affordances, in :data:`~e2e_lite.imitation.collector.AFFORDANCE_NAMES` order (perceived or
            true).
        speed_mps: the car's speed now [m/s].
        curvature: the road's curvature here [1/m] (left positive).
        cfg: the settings.
    """
    cfg = cfg or SafetyConfig()
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape != (N_POINTS, 2) or not np.all(np.isfinite(pts)):
        return Verdict(False, "the proposal is not 5 finite points", kind="invalid", t_s=0.0)
    a = np.asarray(aff, dtype=np.float64)
    x, y, _ = interpolated_path(pts)
    delta = y + a[_A["heading_rad"]] * x - curvature * x * x / 2.0
    half = cfg.car_width_m / 2.0
    off_road = _off_road(delta, half, a, cfg)
    if off_road is not None:
        return off_road
    # 3. which lanes the body occupies, relative to the ego lane's centre
    width = max(2.0, a[_A["left_marking_m"]] + a[_A["right_marking_m"]])
    lateral = a[_A["center_offset_m"]] + delta
    v_end = float(np.hypot(*(pts[-1] - pts[-2]))) / POINT_DT_S
    for lane, offset, gap_name in (
        ("ego", 0.0, "gap_ego_m"),
        ("left", width, "gap_left_m"),
        ("right", -width, "gap_right_m"),
    ):
        inside = np.minimum(lateral + half, offset + width / 2)
        inside -= np.maximum(lateral - half, offset - width / 2)
        occupied = inside > (cfg.lane_overlap_m if lane != "ego" else 0.0)
        gap = float(a[_A[gap_name]])
        if not occupied.any() or gap >= cfg.free_from_m(lane):
            continue
        ends_here = abs(lateral[-1] - offset) <= width / 2
        conflict = _parked_car_conflict(x, occupied, ends_here, gap, lane, v_end, cfg)
        if conflict is not None:
            return conflict
    return Verdict(True)


def _off_road(delta: np.ndarray, half: float, a: np.ndarray, cfg: SafetyConfig) -> Verdict | None:
    """Step 2: the body, ``half`` its width either side of the path's offsets ``delta`` [m], past
    a road edge plus its margin (None: it stays on the road)."""
    left = delta + half - (a[_A["left_edge_m"]] + cfg.edge_margin_m)
    right = -delta + half - (a[_A["right_edge_m"]] + cfg.edge_margin_m)
    for side, excess in (("left", left), ("right", right)):
        if excess.max() > 0.0:
            t_s = int(np.argmax(excess > 0.0)) * POINT_DT_S / PATH_SUBSTEPS
            why = f"leaves the road on the {side} ({excess.max():.2f} m past the edge, {t_s:.1f} s ahead)"
            return Verdict(False, why, side, "road edge", t_s)
    return None


def _parked_car_conflict(
    x: np.ndarray,
    occupied: np.ndarray,
    ends_here: bool,
    gap: float,
    lane: str,
    v_end: float,
    cfg: SafetyConfig,
) -> Verdict | None:
    """Steps 4a and 4b for the parked car ``gap`` metres ahead in ``lane``, which the body
    occupies where ``occupied`` along the path's progress ``x`` [m]: does the front bumper reach
    it while the body is in its lane, or does the path end in that lane (``ends_here``) where the
    car cannot stop in time at ``v_end`` [m/s]? None: neither."""
    front = x  # progress of the front bumper [m] (the rear axle's, the body is rigid)
    rear = x - cfg.car_length_m
    hit = occupied & (front > gap - cfg.margin_m) & (rear < gap + cfg.parked_length_m)
    if hit.any():
        t_s = int(np.argmax(hit)) * POINT_DT_S / PATH_SUBSTEPS
        why = f"runs into the car {gap:.0f} m ahead in the {lane} lane ({t_s:.1f} s ahead)"
        return Verdict(False, why, lane, "collision course", t_s)
    if ends_here and front[-1] < gap:
        need, left_m = cfg.stopping_m(v_end), gap - front[-1]
        if left_m < need:
            why = (
                f"cannot stop for the car {gap:.0f} m ahead in the {lane} lane: {left_m:.0f} m"
                f" left after 1.5 s at {v_end:.1f} m/s, {need:.0f} m needed"
            )
            return Verdict(False, why, lane, "cannot stop", N_POINTS * POINT_DT_S)
    return None


def lane_width(aff: np.ndarray) -> float:
    """The ego lane's width from its two marking distances [m] (at least 2 m)."""
    return max(2.0, float(aff[_A["left_marking_m"]] + aff[_A["right_marking_m"]]))


def end_lateral(points: np.ndarray, aff: np.ndarray, curvature: float) -> float:
    """Where a trajectory ends across the road: its last point's offset from the ego lane's
    centre, in the lane frame [m] (left positive; one lane width = the next lane's centre)."""
    x, y = (float(v) for v in np.asarray(points, dtype=np.float64)[-1])
    a = np.asarray(aff, dtype=np.float64)
    return float(a[_A["center_offset_m"]] + y + a[_A["heading_rad"]] * x - curvature * x * x / 2)


def braking_progress(speed_mps: float, brake_mps2: float) -> np.ndarray:
    """How far a car at ``speed_mps`` [m/s] braking at ``brake_mps2`` [m/s^2] to a stop has gone
    at each of the 5 points' times: ``(5,)`` [m], never decreasing, constant once stopped."""
    v = max(0.0, float(speed_mps))
    t = np.minimum(POINT_DT_S * np.arange(1, N_POINTS + 1), v / brake_mps2)
    return v * t - 0.5 * brake_mps2 * t**2


def keep_lane_brake(
    aff: np.ndarray, speed_mps: float, curvature: float, cfg: SafetyConfig | None = None
) -> np.ndarray:
    """The last-resort trajectory: back to the current lane's centre (smoothly, over the 1.5 s),
    braking at ``cfg.brake_mps2`` from ``speed_mps`` to a stop. ``(5, 2)`` car-frame points [m];
    progress never decreases and the speed never increases."""
    return brake_to_lane(aff, speed_mps, curvature, 0, cfg)


def brake_to_lane(
    aff: np.ndarray,
    speed_mps: float,
    curvature: float,
    lanes: int,
    cfg: SafetyConfig | None = None,
) -> np.ndarray:
    """Braking at ``cfg.brake_mps2`` from ``speed_mps`` to a stop while moving (smoothly, over
    the 1.5 s) to the centre of the lane ``lanes`` to the left of the current one (0: the current
    lane, -1: the one to its right). ``(5, 2)`` car-frame points [m]; progress never decreases
    and the speed never increases."""
    cfg = cfg or SafetyConfig()
    a = np.asarray(aff, dtype=np.float64)
    x = braking_progress(speed_mps, cfg.brake_mps2)
    t = POINT_DT_S * np.arange(1, N_POINTS + 1)
    u = t / t[-1]
    blend = u**3 * (10.0 - 15.0 * u + 6.0 * u**2)  # quintic: no lateral jerk at the ends
    offset = float(np.clip(a[_A["center_offset_m"]], -5.0, 5.0))
    delta = (lanes * lane_width(a) - offset) * blend
    heading = float(np.clip(a[_A["heading_rad"]], -1.0, 1.0))
    y = delta - heading * x + curvature * x * x / 2.0
    return np.stack([x, y], axis=1)


def brake_along(
    points: np.ndarray, speed_mps: float, cfg: SafetyConfig | None = None
) -> np.ndarray:
    """``points`` ``(5, 2)`` [m] driven along their own path braking at ``cfg.brake_mps2`` from
    ``speed_mps`` to a stop, never past its end (an emergency stop keeping the planned path)."""
    cfg = cfg or SafetyConfig()
    return along_path(points, lambda along: braking_progress(speed_mps, cfg.brake_mps2))


@dataclass
class Choice:
    """What the module did for one car at one decision."""

    points: np.ndarray
    source: str  # "network" (the followed mode), "other mode" or "fallback"
    verdicts: list[Verdict]  # one per mode checked, heaviest first


def choose(
    modes: np.ndarray,
    weights: np.ndarray,
    aff: np.ndarray,
    speed_mps: float,
    curvature: float,
    cfg: SafetyConfig | None = None,
) -> Choice:
    """The fallback order: the heaviest mode if it passes, else the next heaviest that passes,
    else, with ``cfg.fallback == "path"`` and the heaviest rejected for a parked car, the modes'
    paths braking (:func:`brake_along`; the first that passes, else the heaviest's), else (with
    ``"lanes"`` or ``"path"``) the first braking trajectory that passes among
    :func:`brake_to_lane` to the current lane and its two neighbours, ordered by how near each
    lane's centre is to where the heaviest mode ends (:func:`end_lateral`; on a tie the current
    lane), else :func:`keep_lane_brake`, unchecked (the last resort: nothing stops sooner).

    Args:
        modes: ``(K, 5, 2)`` proposals (K = 1 for a single trajectory) [m].
        weights: ``(K,)`` their weights.
        aff, speed_mps, curvature, cfg: as :func:`check` (every candidate is checked with them).

    Returns:
        The :class:`Choice`; its ``verdicts`` hold one per mode checked (heaviest first), then,
        when a lane's brake passed, one per braking trajectory checked up to it.
    """
    cfg = cfg or SafetyConfig()
    modes = np.asarray(modes, dtype=np.float64)
    order = np.argsort(-np.asarray(weights, dtype=np.float64), kind="stable")
    verdicts = []
    for rank, k in enumerate(order.tolist()):
        verdict = check(modes[k], aff, speed_mps, curvature, cfg)
        verdicts.append(verdict)
        if verdict.ok:
            return Choice(modes[k], "network" if rank == 0 else "other mode", verdicts)
    if cfg.fallback == "path" and verdicts[0].kind in ("collision course", "cannot stop"):
        heaviest = brake_along(modes[order[0]], speed_mps, cfg)
        for k in order.tolist():
            brake = heaviest if k == order[0] else brake_along(modes[k], speed_mps, cfg)
            verdict = check(brake, aff, speed_mps, curvature, cfg)
            verdicts.append(verdict)
            if verdict.ok:
                return Choice(brake, "fallback", verdicts)
        return Choice(heaviest, "fallback", verdicts[: len(order)])
    if cfg.fallback in ("lanes", "path"):
        heading_to = end_lateral(modes[order[0]], aff, curvature) / lane_width(aff)
        for lanes in sorted((0, 1, -1), key=lambda n: (abs(heading_to - n), abs(n))):
            brake = brake_to_lane(aff, speed_mps, curvature, lanes, cfg)
            verdict = check(brake, aff, speed_mps, curvature, cfg)
            verdicts.append(verdict)
            if verdict.ok:
                return Choice(brake, "fallback", verdicts)
        verdicts = verdicts[: len(order)]  # none passed: the last resort, as without them
    return Choice(keep_lane_brake(aff, speed_mps, curvature, cfg), "fallback", verdicts)


#: The share of training frames with nothing within the cap on which a calibrated
#: ``gap_free_m`` may still see a car (:func:`calibrate_gap_free`).
GHOST_SHARE = 0.01
_GAPS = [_A[n] for n in GAP_NAMES]


def calibrate_gap_free(
    cfg: SafetyConfig, predicted: np.ndarray, true: np.ndarray, ghost_share: float = GHOST_SHARE
) -> SafetyConfig:
    """``cfg`` with the "nothing seen" thresholds set for a perception whose gaps are noisy at
    the cap: ``gap_free_m`` for the ego lane, ``gap_free_side_m`` for the left and right lanes.

    A free lane's true gap is exactly :data:`~e2e_lite.learning.labels.GAP_CAP_M`; a learned head
    answers around it, so a threshold just under the cap sees a parked car on the free frames
    whose answer falls under it, and "cannot stop" brakes for it. Each calibrated threshold is
    the ``ghost_share`` quantile of the predicted gaps on frames whose true gap is at the cap
    (the ego lane's alone; the left and right lanes' pooled): with it, at most that share of
    those frames sees a car that is not there. The price: a car between the threshold and the
    cap counts as not seen until it comes nearer. The lanes are calibrated apart because a head
    may see its own lane more sharply than its neighbours.

    Args:
        cfg: the settings to start from; its ``gap_free_m`` bounds both thresholds.
        predicted, true: (N, 9) affordances of the same frames, predicted and true (training
            frames: the thresholds must not be chosen on the evaluation's tracks).
        ghost_share: the share of free frames allowed to see a car, in (0, 1).

    Returns:
        The settings with each threshold ``min(cfg.gap_free_m, quantile)`` (at least 1 m); a
        threshold whose lanes are never free in the frames is left as it was.
    """
    p, t = np.asarray(predicted, np.float64), np.asarray(true, np.float64)
    if p.shape != t.shape or p.ndim != 2 or p.shape[1] != len(_A):
        raise ValueError(
            f"calibrate_gap_free needs (N, {len(_A)}) predictions and truths; got {p.shape}, "
            f"{t.shape}"
        )
    if not 0.0 < ghost_share < 1.0:
        raise ValueError(f"calibrate_gap_free: ghost_share={ghost_share} must lie in (0, 1)")

    def threshold(columns: list[int], current: float | None) -> float | None:
        free = t[:, columns] >= GAP_CAP_M
        if not free.any():
            return current
        quantile = float(np.quantile(p[:, columns][free], ghost_share))
        return max(1.0, min(cfg.gap_free_m, quantile))

    ego, side = _GAPS[:1], _GAPS[1:]
    return replace(
        cfg,
        gap_free_m=threshold(ego, cfg.gap_free_m),
        gap_free_side_m=threshold(side, cfg.gap_free_side_m),
    )
