"""The safety module (chapter 11): check a proposed trajectory before the tracker follows it.

Seed 000's architecture (its Fig. 1) validates the network's trajectory with a safety module and
leaves it unbuilt. A trajectory, unlike a steering angle, says where the car means to be, so it
can be checked against what the car knows about the road ahead. The rule here is in the spirit of
responsibility-sensitive safety (RSS), for a road of parked cars:

Inputs (what the driver perceives): the 5 proposed points ``(x_i, y_i)`` in the car frame at
``t_i = 0.3 i`` s, the car's speed ``v``, the road's curvature ``kappa`` here (from the map, as
the cruise control knows it), and the 9 affordances (``e2e_lite.learning.data.AFFORDANCE_NAMES``): the
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
unchecked). With ``SafetyConfig.brake_along_path``, a mode rejected for a parked car is instead
braked along its own path (:func:`brake_along`): on perception, the lane fallback's path is made
of the very affordances that are wrong (chapter 11). With ``SafetyConfig.modes_only`` there is
no fallback: none of the modes passing, the heaviest is driven as proposed (a control).

Given a free-space profile (``check(..., profile=)``, chapter 11), steps 3 and 4 read the parked
cars in the car's own frame instead of the lane gaps
(:func:`~e2e_lite.experiments.freespace_rule.check_profile`); the road edges stay as in step 2.

The driver that applies the rule to a trajectory network is :class:`~e2e_lite.experiments.safe_agent.SafeAgent`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..config import check_range
from ..control.labels import (
    AFFORDANCE_INDEX,
    GAP_CAP_M,
    N_POINTS,
    PATH_SUBSTEPS,
    POINT_DT_S,
    along_path,
    interpolated_path,
)
from .freespace_rule import check_profile

_A = AFFORDANCE_INDEX


@dataclass(frozen=True)
class SafetyConfig:
    """Settings of the check.

    Attributes:
        reaction_s: reaction time rho before braking [s] (one policy period and a margin).
        brake_mps2: braking beta assumed for stopping, and used by the fallback [m/s^2] (the
            tracker's braking limit).
        margin_m: distance always kept to a parked car [m].
        lane_overlap_m: how far across a marking the body must be to occupy that lane [m].
        edge_margin_m: how far past the road's edge line the body may go (onto the shoulder; the
            guard rail is further out) [m].
        car_width_m, car_length_m: the ego's body [m].
        parked_length_m: a parked car's length [m].
        gap_free_m: a perceived gap at least this long means nothing was seen [m]. Right
            for the true affordances (exactly the 60 m cap when the lane is free); a learned head
            answers near the cap with noise, so the perceived module calibrates it on training
            frames (:func:`calibrate_gap_free`).
        gap_free_side_m: the same threshold for the left and right lanes' gaps [m]; ``None``:
            ``gap_free_m``. A head may see the neighbouring lanes less sharply than its own
            (:func:`calibrate_gap_free` sets both).
        fallback_lanes: brake into a neighbouring lane when braking in the current lane fails
            the check and braking there passes (see :func:`choose`). With the true affordances
            the keep-lane brake alone pulled cars half-way through a lane change back in front
            of the parked car they were passing (chapter 11).
        brake_along_path: when no mode passes and the heaviest was rejected for a parked car
            ("collision course" or "cannot stop"), brake along the modes' own paths
            (:func:`brake_along`, heaviest first, the first that passes, else the heaviest's)
            instead of steering to a lane centre; road-edge rejections keep the lane fallback.
            A path to a lane centre is made of the perceived heading, offset and lane width, and
            its lane is chosen by the perceived side gaps; the network's own path needs neither
            (chapter 11 measures both fallbacks on perception).
        check_fallback: check the keep-lane brake too (see :func:`choose`). Off: with the true
            affordances it traded car for rail collisions (seed 0, 40 mi: 12 car / 23 rail
            against 21 / 13 unchecked, before ``fallback_lanes``); chapter 11's exercise 5.
        gyro_heading: fuse the perceived heading with the car's yaw rate (a gyro) before the
            check (:func:`~e2e_lite.experiments.safe_agent.fuse_heading`).
        gyro_camera_weight: the camera's weight in that fusion at every speed, in (0, 1];
            ``None``: the speed-dependent weight (the camera alone at cruise speed).
        sight_speed: drive every proposal no faster than :meth:`sight_speed_mps` (:func:`cap_speed`;
            "assured clear distance ahead"): a car first seen can be stopped for (chapter 11).
        check_proposals: ``False`` drives the heaviest mode unchecked (with ``sight_speed``:
            the speed cap alone, the control that says what slowing down does by itself).
        confirm_decisions: intervene only once the heaviest mode has failed the check on this
            many consecutive decisions of a car (1: at once); before that the network drives. A
            persistence filter against a noisy head's one-off alarms, paid in reaction time.
        release_decisions: after an intervention, give the car back to the network only once its
            heaviest mode has passed the check on this many consecutive decisions (1: at the
            first pass); until then drive that passing mode's path braking (:func:`brake_along`,
            the source ``"hold"``). The opposite of ``confirm_decisions``: on perception a real
            hazard's alarm flickers (a car read at 44 m, then at 55, then at 40), and each pass
            hands the car back at cruise speed, so the brake is applied in bursts and the car
            arrives at 18-20 m/s (chapter 11). Paid in braking after false alarms.
        modes_only: the module only re-ranks the network's modes: the first that passes, else
            the heaviest, driven as proposed (no braking fallback; the source stays "network").
            The control that separates what the module's braking costs (the slow states it
            leaves the car in) from what its perception costs (chapter 11).
        emergency_brake_mps2: the fallback's deceleration [m/s^2]: a car the module falls back
            for (source ``"fallback"``) is braked at this, the tracker's steering kept (an
            emergency brake; the car's own limit still clips it). ``None``: the tracker's
            braking, at most ``brake_mps2``. The check still plans with ``brake_mps2``, so a
            stronger emergency brake is headroom the rule does not count on (chapter 11: the
            course's car brakes at 8 where the tracker stops at 6).
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
    fallback_lanes: bool = True
    check_fallback: bool = False
    gap_free_side_m: float | None = field(default=None, repr=False)  # (shown when set)
    brake_along_path: bool = field(default=False, repr=False)  # (shown when set)
    gyro_heading: bool = field(default=False, repr=False)  # (shown when set)
    gyro_camera_weight: float | None = field(default=None, repr=False)  # (shown when set)
    sight_speed: bool = field(default=False, repr=False)  # (shown when set)
    check_proposals: bool = field(default=True, repr=False)  # (shown when set)
    confirm_decisions: int = field(default=1, repr=False)  # (shown when set)
    release_decisions: int = field(default=1, repr=False)  # (shown when set)
    modes_only: bool = field(default=False, repr=False)  # (shown when set)
    emergency_brake_mps2: float | None = field(default=None, repr=False)  # (shown when set)

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
        for name in ("gap_free_m", "gap_free_side_m"):
            if getattr(self, name) is not None:
                check_range(o, name, getattr(self, name), 1.0, 1000.0)
        if self.gyro_camera_weight is not None:
            check_range(o, "gyro_camera_weight", self.gyro_camera_weight, 0.0, 1.0, lo_open=True)
        check_range(o, "confirm_decisions", self.confirm_decisions, 1, 100, integer=True)
        check_range(o, "release_decisions", self.release_decisions, 1, 100, integer=True)
        if self.emergency_brake_mps2 is not None:
            check_range(
                o, "emergency_brake_mps2", self.emergency_brake_mps2, 0.0, 15.0, lo_open=True
            )

    def __repr__(self) -> str:
        # the fields added later shown only when set (stored results are keyed by this text)
        shown = [
            f"{f.name}={getattr(self, f.name)!r}"
            for f in fields(self)
            if f.repr or getattr(self, f.name) != f.default
        ]
        return f"{type(self).__name__}({', '.join(shown)})"

    def free_from_m(self, lane: str) -> float:
        """The perceived gap from which ``lane`` (``"ego"``, ``"left"``, ``"right"``) is free [m]."""
        side = self.gap_free_side_m
        return self.gap_free_m if lane == "ego" or side is None else side

    def stopping_m(self, speed_mps: float) -> float:
        """RSS's safe distance to a standing obstacle: ``v rho + v^2 / (2 beta) + margin`` [m]."""
        v = max(0.0, speed_mps)
        return v * self.reaction_s + v * v / (2.0 * self.brake_mps2) + self.margin_m

    def sight_speed_mps(self) -> float:
        """The fastest speed that stops within sight [m/s]: :meth:`stopping_m` ``(v)`` equals the
        ego lane's threshold :meth:`free_from_m` (where a parked car is first seen)."""
        room = max(0.0, self.free_from_m("ego") - self.margin_m)
        rho, beta = self.reaction_s, self.brake_mps2
        return float(beta * (np.sqrt(rho * rho + 2.0 * room / beta) - rho))


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
    profile: tuple[np.ndarray, np.ndarray] | None = None,
) -> Verdict:
    """Is following ``points`` safe, by the rule of the module docstring?

    Args:
        points: ``(5, 2)`` proposed rear-axle positions, car frame [m], 0.3 s apart.
        aff: the 9 affordances, in :data:`~e2e_lite.learning.data.AFFORDANCE_NAMES` order (perceived or
            true).
        speed_mps: the car's speed now [m/s].
        curvature: the road's curvature here [1/m] (left positive).
        cfg: the settings.
        profile: ``(profile_m, free_m)``, a free-space profile and its thresholds (each
            ``(15,)`` [m], :mod:`e2e_lite.learning.freespace`): parked cars are then checked in the
            car's frame (:func:`~e2e_lite.experiments.freespace_rule.check_profile`) instead of
            by the lane gaps, which are ignored; the road edges as above.
    """
    cfg = cfg or SafetyConfig()
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape != (N_POINTS, 2) or not np.all(np.isfinite(pts)):
        return Verdict(False, "the proposal is not 5 finite points", kind="invalid", t_s=0.0)
    a = np.asarray(aff, dtype=np.float64)
    x, y, _ = interpolated_path(pts)
    delta = y + a[_A["heading_rad"]] * x - curvature * x * x / 2.0
    half = cfg.car_width_m / 2.0
    # 2. road edges
    left = delta + half - (a[_A["left_edge_m"]] + cfg.edge_margin_m)
    right = -delta + half - (a[_A["right_edge_m"]] + cfg.edge_margin_m)
    for side, excess in (("left", left), ("right", right)):
        if excess.max() > 0.0:
            k = int(np.argmax(excess > 0.0))
            return Verdict(
                False,
                f"leaves the road on the {side} ({excess.max():.2f} m past the edge, "
                f"{k * POINT_DT_S / PATH_SUBSTEPS:.1f} s ahead)",
                side,
                "road edge",
                k * POINT_DT_S / PATH_SUBSTEPS,
            )
    if profile is not None:  # parked cars as the camera sees them, in the car's frame
        kind, near, t_s = check_profile(pts, *profile, curvature, cfg)
        if not kind:
            return Verdict(True)
        return Verdict(False, f"{kind}: a car read {near:.0f} m ahead", "", kind, t_s)
    # 3. which lanes the body occupies, relative to the ego lane's centre
    width = max(2.0, a[_A["left_marking_m"]] + a[_A["right_marking_m"]])
    lateral = a[_A["center_offset_m"]] + delta
    lo, hi = lateral - half, lateral + half
    v_end = float(np.hypot(*(pts[-1] - pts[-2]))) / POINT_DT_S
    for lane, offset, gap_name in (
        ("ego", 0.0, "gap_ego_m"),
        ("left", width, "gap_left_m"),
        ("right", -width, "gap_right_m"),
    ):
        inside = np.minimum(hi, offset + width / 2) - np.maximum(lo, offset - width / 2)
        occupied = inside > (cfg.lane_overlap_m if lane != "ego" else 0.0)
        if not occupied.any():
            continue
        gap = float(a[_A[gap_name]])
        if gap >= cfg.free_from_m(lane):
            continue
        # 4a. the front bumper reaches the parked car while the body is in its lane
        front = x  # progress of the front bumper [m] (the rear axle's, the body is rigid)
        rear = x - cfg.car_length_m
        hit = occupied & (front > gap - cfg.margin_m) & (rear < gap + cfg.parked_length_m)
        if hit.any():
            k = int(np.argmax(hit))
            return Verdict(
                False,
                f"runs into the car {gap:.0f} m ahead in the {lane} lane "
                f"({k * POINT_DT_S / PATH_SUBSTEPS:.1f} s ahead)",
                lane,
                "collision course",
                k * POINT_DT_S / PATH_SUBSTEPS,
            )
        # 4b. ending the 1.5 s in that lane (its centre line inside it): can it stop in time?
        ends_here = abs(lateral[-1] - offset) <= width / 2
        if ends_here and front[-1] < gap:
            need = cfg.stopping_m(v_end)
            left_m = gap - front[-1]
            if left_m < need:
                return Verdict(
                    False,
                    f"cannot stop for the car {gap:.0f} m ahead in the {lane} lane: "
                    f"{left_m:.0f} m left after 1.5 s at {v_end:.1f} m/s, {need:.0f} m needed",
                    lane,
                    "cannot stop",
                    N_POINTS * POINT_DT_S,
                )
    return Verdict(True)


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
    ``speed_mps`` to a stop, never past its end (an emergency brake keeping the planned path)."""
    cfg = cfg or SafetyConfig()
    return along_path(points, lambda along: braking_progress(speed_mps, cfg.brake_mps2))


def cap_speed(points: np.ndarray, max_speed_mps: float) -> np.ndarray:
    """Trajectories ``(..., 5, 2)`` [m] driven along their own paths at no more than
    ``max_speed_mps`` [m/s] (each point moved back to ``max_speed_mps t_i`` along the path if
    further); slower proposals are unchanged."""
    limit = max(0.0, float(max_speed_mps)) * POINT_DT_S * np.arange(1, N_POINTS + 1)
    return along_path(points, lambda along: np.minimum(along, limit))


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
    profile: tuple[np.ndarray, np.ndarray] | None = None,
) -> Choice:
    """The fallback order: the heaviest mode if it passes, else the next heaviest that passes,
    else, with ``cfg.brake_along_path`` and the heaviest rejected for a parked car, the modes'
    paths braking (:func:`brake_along`; the first that passes, else the heaviest's),
    else (with ``cfg.fallback_lanes``) the first braking trajectory that passes among
    :func:`brake_to_lane` to the current lane and its two neighbours, ordered by how near each
    lane's centre is to where the heaviest mode ends (:func:`end_lateral`; on a tie the current
    lane), else :func:`keep_lane_brake`. With ``cfg.modes_only`` the order stops after the modes:
    none passing, the heaviest is driven.

    With ``cfg.check_fallback`` the braking trajectory is checked too. It is driven when it
    passes or only "cannot stop" (it already brakes as hard as the rule assumes: nothing stops
    sooner in this lane). When it would itself run into a car or off the road within the 1.5 s,
    the candidate (modes and brake) whose first violation comes **latest** is driven instead (on
    a tie the brake, which meets it slower, then the heaviest mode): braking in the lane of a car
    too close to stop for makes the contact certain, while a swerve the rule finds too tight may
    still miss it. Off by default (see :class:`SafetyConfig`).

    Args:
        modes: ``(K, 5, 2)`` proposals (K = 1 for a single trajectory) [m].
        weights: ``(K,)`` their weights.
        aff, speed_mps, curvature, cfg, profile: as :func:`check` (every candidate is checked
            with them).

    Returns:
        The :class:`Choice`; its ``verdicts`` hold one per mode checked (heaviest first), then,
        when a lane's brake passed, one per braking trajectory checked up to it, or else the
        keep-lane brake's when ``cfg.check_fallback`` checked it.
    """
    cfg = cfg or SafetyConfig()
    modes = np.asarray(modes, dtype=np.float64)
    order = np.argsort(-np.asarray(weights, dtype=np.float64), kind="stable")
    verdicts = []
    for rank, k in enumerate(order.tolist()):
        verdict = check(modes[k], aff, speed_mps, curvature, cfg, profile)
        verdicts.append(verdict)
        if verdict.ok:
            return Choice(modes[k], "network" if rank == 0 else "other mode", verdicts)
    if cfg.modes_only:  # nothing passes: the network's own choice, unbraked
        return Choice(modes[order[0]], "network", verdicts)
    if cfg.brake_along_path and verdicts[0].kind in ("collision course", "cannot stop"):
        heaviest = brake_along(modes[order[0]], speed_mps, cfg)
        for k in order.tolist():
            brake = heaviest if k == order[0] else brake_along(modes[k], speed_mps, cfg)
            verdict = check(brake, aff, speed_mps, curvature, cfg, profile)
            verdicts.append(verdict)
            if verdict.ok:
                return Choice(brake, "fallback", verdicts)
        verdicts = verdicts[: len(order)]  # none passed: the heaviest mode's path, braking
        return Choice(heaviest, "fallback", verdicts)
    if cfg.fallback_lanes:
        heading_to = end_lateral(modes[order[0]], aff, curvature) / lane_width(aff)
        for lanes in sorted((0, 1, -1), key=lambda n: (abs(heading_to - n), abs(n))):
            brake = brake_to_lane(aff, speed_mps, curvature, lanes, cfg)
            verdict = check(brake, aff, speed_mps, curvature, cfg, profile)
            verdicts.append(verdict)
            if verdict.ok:
                return Choice(brake, "fallback", verdicts)
        verdicts = verdicts[: len(order)]  # none passed: the last resort, as without them
    brake = keep_lane_brake(aff, speed_mps, curvature, cfg)
    if not cfg.check_fallback:
        return Choice(brake, "fallback", verdicts)
    brake_verdict = check(brake, aff, speed_mps, curvature, cfg, profile)
    verdicts.append(brake_verdict)
    if brake_verdict.ok or brake_verdict.kind == "cannot stop":
        return Choice(brake, "fallback", verdicts)
    latest = max(range(len(verdicts)), key=lambda j: (verdicts[j].t_s, j == len(order), -j))
    if latest == len(order):
        return Choice(brake, "fallback", verdicts)
    source = "network" if latest == 0 else "other mode"
    return Choice(modes[order[latest]], source, verdicts)
