"""The safety module as a driver (chapter 11): :class:`SafeAgent` wraps a trajectory network,
checks each proposed trajectory with :func:`~e2e_lite.experiments.safety.check` on perceived (or true)
affordances, falls back as :func:`~e2e_lite.experiments.safety.choose` says, and reports what it did with
each decision (``Actuation.info``, added up by the evaluator into ``result.info``; read it with
:meth:`SafetyStats.from_info`): interventions by source and kind, false alarms audited against a
fresh expert's trajectory from the same state, and a few examples (JSON-able: the
track's id, the pose, the modes and what was driven; rebuild the view with
:func:`~e2e_lite.simulation.world.make_world`).
"""

from __future__ import annotations

import dataclasses
from collections import Counter, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..config import check_range
from ..control.expert import ExpertConfig, SpeedLimits, fresh_labels
from ..control.labels import AFFORDANCE_INDEX, AFFORDANCE_NAMES
from ..learning.data import affordances
from ..learning.freespace import N_STRIPS, PROFILE_CAP_M, free_profiles
from ..simulation.geometry import wrap_angle
from ..simulation.policy import Actuation, Observation
from ..simulation.vehicle import H
from .safety import Choice, SafetyConfig, Verdict, brake_along, cap_speed, check, choose
from .traces import decision_record

#: where :class:`SafeAgent` reads parked cars from (``None``: the lane gaps)
PROFILES = (None, "perceived", "true")
#: the counters a :class:`SafeAgent` reports with each decision (``Actuation.info``)
COUNTS = ("decisions", "audited", "false_alarms", "perception_only")
TABLES = ("sources", "kinds", "at_impact", "before_impact")
#: the decisions before a collision in which :class:`SafeAgent` counts its interventions (3 s)
BEFORE_IMPACT = 30
#: the speed from which the fused heading is the camera's alone [m/s] (the roads' cruise speed)
GYRO_FULL_SPEED_MPS = 25.0
#: the camera's least weight in the fused heading (at standstill)
GYRO_MIN_CAMERA_WEIGHT = 0.1
_HEADING = AFFORDANCE_INDEX["heading_rad"]


def fuse_heading(
    previous: np.ndarray,
    camera: np.ndarray,
    yaw_change: np.ndarray,
    speed_mps: np.ndarray,
    curvature: np.ndarray,
    dt_s: float,
    camera_weight: float | None = None,
) -> np.ndarray:
    r"""One step of a complementary filter on the heading to the lane [rad], per car.

    The camera's heading is sharp at cruise speed and poor when the car is slow or turned (the
    views it learned from are the expert's); the car's own yaw rate (a gyro) is exact over a few
    decisions. Predict with the gyro, correct with the camera, trusting it more the faster:

        h_t = (1 - g) (h_{t-1} + dpsi - kappa v dt) + g h_camera,
        g = clip((v / GYRO_FULL_SPEED_MPS)^2, GYRO_MIN_CAMERA_WEIGHT, 1)

    Args:
        previous: the fused heading at the last decision [rad], ``(B,)``.
        camera: the perceived heading now [rad], ``(B,)``.
        yaw_change: the car's yaw change since the last decision [rad], ``(B,)`` (wrapped).
        speed_mps: speeds [m/s], ``(B,)``.
        curvature: the road's curvature [1/m], ``(B,)`` (kappa v dt: how far the road turned
            under the car).
        dt_s: time since the last decision [s].
        camera_weight: ``g`` at every speed instead (in (0, 1]); ``None``: the formula above.

    Returns:
        The fused heading [rad], ``(B,)``.
    """
    v = np.maximum(np.asarray(speed_mps, dtype=float), 0.0)
    g = np.clip((v / GYRO_FULL_SPEED_MPS) ** 2, GYRO_MIN_CAMERA_WEIGHT, 1.0)
    if camera_weight is not None:
        g = np.full_like(v, camera_weight)
    predicted = previous + yaw_change - curvature * v * dt_s
    return (1.0 - g) * predicted + g * camera


@dataclass
class SafetyStats:
    """What a :class:`SafeAgent` did over one or more evaluations: made from their results'
    ``info`` (:meth:`from_info`), pooled with :meth:`add`.

    Attributes:
        decisions: car-decisions checked.
        sources: how many times each source was driven (``network``, ``other mode``,
            ``fallback``).
        kinds: why the followed mode was rejected (``road edge``, ``collision course``,
            ``cannot stop``).
        at_impact: for every collision, who drove the car's last decision before it
            (``network``, ``other mode``, ``fallback``): the module's own fallback, or the
            network it let through.
        before_impact: for every collision, how many of the car's last :data:`BEFORE_IMPACT`
            decisions (3 s at 10 Hz) the module overrode, keyed by that number (as text): a
            collision after a run of interventions is the module's doing even when the network
            drove the very last decision.
        audited: interventions audited (all, or one in ``audit_every``).
        false_alarms: audited interventions where a fresh expert, from the same state, would have driven
            what the network proposed (its trajectory within 1 m sideways and 5 m along at 1.5 s).
        perception_only: audited interventions where the same rule with the world's true affordances
            accepts the proposal (the perceived affordances caused the rejection).
    """

    decisions: int = 0
    audited: int = 0
    sources: Counter = field(default_factory=Counter)
    kinds: Counter = field(default_factory=Counter)
    at_impact: Counter = field(default_factory=Counter)
    before_impact: Counter = field(default_factory=Counter)
    false_alarms: int = 0
    perception_only: int = 0

    @classmethod
    def from_info(cls, info: dict[str, Any]) -> SafetyStats:
        """The counts in an evaluation's ``result.info`` (zero where the module never ran)."""
        stats = cls()
        stats.add(info)
        return stats

    @property
    def interventions(self) -> int:
        """Decisions where the followed mode was not driven."""
        return self.decisions - self.sources["network"]

    def add(self, counts: dict[str, Any]) -> None:
        """Add the counters in a result's ``info`` (other names ignored)."""
        for name in COUNTS:
            setattr(self, name, getattr(self, name) + int(counts.get(name, 0)))
        for name in TABLES:
            getattr(self, name).update(counts.get(name, {}))

    def to_dict(self) -> dict[str, Any]:
        """Counts and rates, JSON-ready."""
        n, k = max(1, self.decisions), max(1, self.audited)
        return {
            "decisions": self.decisions,
            "interventions": self.interventions,
            "intervention_pct": 100.0 * self.interventions / n,
            "sources": dict(self.sources),
            "kinds": dict(self.kinds),
            "at_impact": dict(self.at_impact),
            "before_impact": dict(self.before_impact),
            "audited": self.audited,
            "false_alarms": self.false_alarms,
            "false_alarm_pct": 100.0 * self.false_alarms / k,
            "perception_only": self.perception_only,
            "perception_only_pct": 100.0 * self.perception_only / k,
        }


class SafeAgent:
    """A trajectory agent behind the safety module: the network proposes, the module checks
    (:func:`choose`), the tracker follows what was chosen.

    Args:
        agent: a :class:`~e2e_lite.learning.agents.TrajectoryAgent` (or any policy with its
            ``trajectories(obs)``, ``last``, ``follow(points, obs)``, ``camera`` and ``fork``).
        cfg: the check's settings.
        ground_truth: check with the world's true affordances instead of the network's
            predictions (the upper bound; needs no affordance head).
        audit: at every intervention, also ask a fresh expert and the ground-truth check (the
            lane rule on the true affordances, also with a ``profile``) whether it was needed
            (the false-alarm counts; costs time).
        audit_every: audit one intervention in this many (1: all; the rates are then
            estimated from that sample).
        keep_examples: interventions kept per shard for figures (JSON-able, see above).
        true_affordances: names (of :data:`~e2e_lite.control.labels.AFFORDANCE_NAMES`) whose
            true values replace the network's in the perceived check, the others staying
            predicted: which affordances' errors matter (chapter 11's targeted runs).
        seer: a second network agent (a :class:`~e2e_lite.learning.agents.TrajectoryAgent`
            whose model has an affordance head) whose affordances the perceived check reads
            instead of the driver's own head: a separate perception network for the module,
            seeing the same frame (``None``: the driver's head). Its trajectories are ignored.
        vote: with a ``seer``, intervene only when the driver's own head also rejects the
            heaviest mode, checked with these settings (its own calibrated thresholds; a
            two-out-of-two vote: two networks whose errors differ seldom raise the same false
            alarm, and the price is the alarms only one of them raises). The check and the
            fallback read the seer's affordances, the vote the driver's (with the seer's
            heading when ``cfg.gyro_heading`` fuses it). ``None``: no vote.
        trace_before_impact: keep each car's last this many decisions and report them with
            every collision (``info["traces"]``, one :func:`decision_record` list per collision,
            oldest first; 0: none). Each record holds what the module perceived and the truth,
            and the check's verdict on the heaviest mode with both: when the rule with the true
            affordances first objected, and what the perceived module did from then on. Costs
            the true affordances and a second check per car per decision.
        profile: check parked cars by the free-space profile in the car's frame
            (:mod:`e2e_lite.experiments.freespace_rule`) instead of the lane gaps: ``"perceived"``
            reads the driver's (a :class:`~e2e_lite.learning.agents.TrajectoryAgent` with a
            ``profile_head``), ``"true"`` computes it from the world (the profile's upper bound;
            free from 59.5 m); ``None``: the lane gaps.
    """

    def __init__(
        self,
        agent: Any,
        cfg: SafetyConfig | None = None,
        ground_truth: bool = False,
        audit: bool = True,
        audit_every: int = 1,
        keep_examples: int = 6,
        true_affordances: Sequence[str] = (),
        seer: Any = None,
        vote: SafetyConfig | None = None,
        trace_before_impact: int = 0,
        profile: str | None = None,
    ) -> None:
        if profile not in PROFILES:
            raise ValueError(
                f"SafeAgent: profile={profile!r} is invalid: must be one of {PROFILES}"
            )
        if profile == "perceived" and getattr(agent, "profile_head", None) is None:
            raise ValueError("SafeAgent: profile='perceived' needs an agent with a profile_head")
        self.profile = profile
        check_range("SafeAgent", "audit_every", audit_every, 1, integer=True)
        check_range("SafeAgent", "trace_before_impact", trace_before_impact, 0, 1000, integer=True)
        unknown = sorted(set(true_affordances) - set(AFFORDANCE_NAMES))
        if unknown:
            raise ValueError(
                f"SafeAgent: true_affordances {unknown} are not affordances; they are "
                f"{', '.join(AFFORDANCE_NAMES)}"
            )
        self.true_affordances = tuple(n for n in AFFORDANCE_NAMES if n in set(true_affordances))
        self._true_columns = [AFFORDANCE_INDEX[n] for n in self.true_affordances]
        model = getattr(seer if seer is not None else agent, "model", None)
        if not ground_truth and model is not None and not model.cfg.affordance:
            raise ValueError(
                "the perceived check needs predicted affordances: give an agent (or a seer) "
                "whose model has an affordance head, or use ground_truth=True"
            )
        if seer is not None and seer.camera != agent.camera:
            raise ValueError(
                f"SafeAgent: the seer's camera {seer.camera} is not the driver's {agent.camera}: "
                "both networks read the same frame"
            )
        if vote is not None and (seer is None or ground_truth):
            raise ValueError("SafeAgent: vote needs a seer (and a perceived check)")
        self.agent, self.seer, self.cfg = agent, seer, cfg or SafetyConfig()
        self.vote = vote
        self.ground_truth, self.audit, self.keep_examples = ground_truth, audit, keep_examples
        self.audit_every = audit_every
        self.trace_before_impact = trace_before_impact
        self._traces: list[deque] = []  # each car's last decisions (tracing)
        self._seen = 0  # interventions met by this copy (for audit_every)
        self._kept = 0  # examples reported since the last reset
        self._driven: list[str] = []  # each car's last source
        self._overrode = np.zeros((0, BEFORE_IMPACT), dtype=bool)  # each car's recent decisions
        self._alarms = np.zeros(0, dtype=np.int64)  # each car's consecutive failed checks
        self._passes = np.zeros(0, dtype=np.int64)  # each car's consecutive passes (holding)
        self._gyro: tuple[float, np.ndarray, np.ndarray] | None = None  # time, yaw, fused heading
        self.camera = agent.camera
        self.last: dict[str, Any] = {}

    def reset(self, n_worlds: int) -> None:
        """Reset the network agent and the count of reported examples."""
        self.agent.reset(n_worlds)
        self._kept = 0
        self._driven = [""] * n_worlds
        self._overrode = np.zeros((n_worlds, BEFORE_IMPACT), dtype=bool)
        self._alarms = np.zeros(n_worlds, dtype=np.int64)
        self._passes = np.full(n_worlds, self.cfg.release_decisions, dtype=np.int64)
        self._traces = [deque(maxlen=self.trace_before_impact) for _ in range(n_worlds)]
        self._gyro = None
        self._limits = SpeedLimits(ExpertConfig())  # the audits' speed limits, once per track

    def fork(self, k: int) -> list[SafeAgent]:
        """``k`` agents for parallel shards, sharing the model."""
        out = []
        seers = [None] * k if self.seer is None else self.seer.fork(k)
        for inner, seer in zip(self.agent.fork(k), seers):
            twin = type(self).__new__(type(self))
            twin.__dict__.update(self.__dict__)
            twin.agent, twin.seer, twin._seen, twin._kept, twin.last = inner, seer, 0, 0, {}
            twin._driven = []
            twin._overrode = np.zeros((0, BEFORE_IMPACT), dtype=bool)
            twin._alarms = np.zeros(0, dtype=np.int64)
            twin._passes = np.zeros(0, dtype=np.int64)
            twin._traces = []
            twin._gyro = None
            twin._limits = SpeedLimits(ExpertConfig())
            out.append(twin)
        return out

    def act(self, obs: Observation) -> Actuation:
        """Propose, check, follow."""
        at_impact = Counter()
        before_impact = Counter()
        if obs.collided is not None and self._driven:
            hit = np.flatnonzero(obs.collided).tolist()
            at_impact.update(self._driven[i] for i in hit)
            before_impact.update(str(int(self._overrode[i].sum())) for i in hit)
            self._overrode[hit] = False  # the car starts afresh
        tracing = self.trace_before_impact > 0 and len(self._traces) == len(obs.speed)
        fresh = _flags(obs.respawned, len(obs.speed))  # re-placed cars: a new episode
        traces = []  # the decisions before each collision this decision reports
        if tracing:
            for i in np.flatnonzero(_flags(obs.collided, len(obs.speed))).tolist():
                traces.append(list(self._traces[i]))
            for i in np.flatnonzero(fresh).tolist():
                self._traces[i].clear()
        proposal = self.agent.trajectories(obs)
        last = self.agent.last
        modes = last.get("modes", proposal[:, None])
        weights = last.get("weights", np.ones((len(proposal), 1)))
        if self.cfg.sight_speed:  # what the module checks and audits is the capped proposal
            cap = self.cfg.sight_speed_mps()
            modes, proposal = cap_speed(modes, cap), cap_speed(proposal, cap)
        truth = None
        if self.ground_truth or self.true_affordances or tracing:
            truth = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        own = last.get("affordances")  # the driver's head (the vote's second opinion)
        if self.seer is not None and not self.ground_truth:
            self.seer.trajectories(obs)  # the perception network, on the same frames
            last = {**last, "affordances": self.seer.last["affordances"]}
        if not self.ground_truth and "affordances" not in last:
            raise ValueError("the agent predicted no affordances; use ground_truth=True")
        seen = truth if self.ground_truth else last["affordances"]
        if not self.ground_truth and (self.true_affordances or self.cfg.gyro_heading):
            seen = seen.copy()  # (the agent's own predictions stay as they were)
            if self.true_affordances:
                seen[:, self._true_columns] = truth[:, self._true_columns]
            if self.cfg.gyro_heading:
                seen[:, _HEADING] = self._fused_heading(obs, seen[:, _HEADING])
        if self.vote is not None:
            if own is None:
                raise ValueError("SafeAgent: vote needs the driver's own affordance head")
            own = own.copy()
            if self.true_affordances:
                own[:, self._true_columns] = truth[:, self._true_columns]
            if self.cfg.gyro_heading:
                own[:, _HEADING] = seen[:, _HEADING]
        if self.profile == "true":
            cap = np.full(N_STRIPS, PROFILE_CAP_M - 0.5)
            reads = free_profiles(obs.worlds, obs.s, obs.d, obs.heading_error)
        elif self.profile == "perceived":
            cap, reads = self.agent.last["profile_free_m"], self.agent.last["profile"]
        chosen = np.empty_like(proposal)
        sources, kinds, audits, perceived = [], [], [], []
        # a persistence filter (confirm_decisions > 1); a re-placed car starts at 0
        counting = self.cfg.confirm_decisions > 1 and len(self._alarms) == len(proposal)
        # a hold after each intervention (release_decisions > 1); a re-placed car starts free
        release = self.cfg.release_decisions
        holding = release > 1 and len(self._passes) == len(proposal)

        def heaviest(i: int) -> Choice:
            """Car i's heaviest mode, driven unchecked."""
            return Choice(modes[i][int(np.argmax(weights[i]))], "network", [])

        for i in range(len(proposal)):
            if self.cfg.check_proposals:
                profile = None if self.profile is None else (reads[i], cap)
                speed = float(obs.speed[i])
                c = choose(
                    modes[i], weights[i], seen[i], speed, obs.curvature[i], self.cfg, profile
                )
            else:  # the control: the heaviest mode (capped with sight_speed), unchecked
                c = heaviest(i)
            if tracing:  # the check's verdict on the heaviest mode (None: not checked)
                perceived.append(c.verdicts[0] if c.verdicts else None)
            if self.vote is not None and c.source != "network":  # the driver's head must agree
                top = heaviest(i)
                if check(top.points, own[i], float(obs.speed[i]), obs.curvature[i], self.vote).ok:
                    c = top
            if counting:
                before = 0 if fresh[i] else self._alarms[i]
                self._alarms[i] = 0 if c.source == "network" else before + 1
                if 0 < self._alarms[i] < self.cfg.confirm_decisions:
                    c = heaviest(i)
            if holding:
                passes = release if fresh[i] else self._passes[i]
                self._passes[i] = min(release, passes + 1) if c.source == "network" else 0
                if c.source == "network" and self._passes[i] < release:  # held: it brakes
                    c = Choice(
                        brake_along(c.points, float(obs.speed[i]), self.cfg),
                        "hold",
                        [Verdict(True, "held after an alarm", kind="hold")],
                    )
            chosen[i] = c.points
            sources.append(c.source)
            if c.source != "network":
                kinds.append(c.verdicts[0].kind)
                audits.append((i, c))
        false_alarms = perception_only = 0
        audited = []
        for i, _ in audits:
            if self.audit and self._seen % self.audit_every == 0:
                audited.append(i)
            self._seen += 1
        if audited:
            expert_pts = fresh_labels(obs, audited, getattr(self.agent, "sim", None), self._limits)
            for j, i in enumerate(audited):
                dx, dy = np.abs(expert_pts[j, -1] - proposal[i, -1])
                false_alarms += int(dy <= 1.0 and dx <= 5.0)
            if not self.ground_truth:  # (the ground-truth check already saw the truth)
                true_aff = affordances(
                    [obs.worlds[i] for i in audited],
                    obs.s[audited],
                    obs.d[audited],
                    obs.heading_error[audited],
                )
                for j, i in enumerate(audited):
                    gt = check(
                        proposal[i], true_aff[j], float(obs.speed[i]), obs.curvature[i], self.cfg
                    )
                    perception_only += int(gt.ok)
        examples = []  # JSON-able: stored with the evaluation (rebuild the world from track_id)
        for i, c in audits[: max(0, self.keep_examples - self._kept)]:
            examples.append(
                {
                    "time_s": float(obs.time_s),
                    "track_id": list(obs.worlds[i].track.track_id),
                    "pose": obs.state[i, :3].tolist(),
                    "s": float(obs.s[i]),
                    "speed": float(obs.speed[i]),
                    "modes": np.asarray(modes[i]).tolist(),
                    "weights": np.asarray(weights[i]).tolist(),
                    "chosen": c.points.tolist(),
                    "source": c.source,
                    "reason": c.verdicts[0].reason,
                }
            )
        self._kept += len(examples)
        info = {
            "decisions": len(proposal),
            "audited": len(audited),
            "false_alarms": false_alarms,
            "perception_only": perception_only,
            "sources": Counter(sources),
            "kinds": Counter(kinds),
            "at_impact": at_impact,
            "before_impact": before_impact,
            "examples": examples,
        }
        if tracing:
            for i in range(len(proposal)):
                self._traces[i].append(
                    decision_record(
                        obs, i, heaviest(i).points, seen[i], perceived[i], truth[i], chosen[i],
                        sources[i], self.cfg,
                    )
                )  # fmt: skip
            info["traces"] = traces
        self.last = {"chosen": chosen, "sources": sources, "seen": seen}
        self._driven = sources
        if len(self._overrode) == len(sources):
            self._overrode = np.roll(self._overrode, -1, axis=1)
            self._overrode[:, -1] = [src != "network" for src in sources]
        out = self.agent.follow(chosen, obs)
        if self.cfg.emergency_brake_mps2 is not None:  # the fallback brakes at it
            accel = np.array(out.accel_mps2, dtype=np.float64)
            accel[np.array(sources) == "fallback"] = -self.cfg.emergency_brake_mps2
            out = dataclasses.replace(out, accel_mps2=accel)
        return dataclasses.replace(out, info=info)

    def _fused_heading(self, obs: Observation, camera: np.ndarray) -> np.ndarray:
        """The perceived heading fused with each car's yaw change since the last decision
        (:func:`fuse_heading`); a car just (re)placed starts from the camera's [rad]."""
        yaw = obs.state[:, H].copy()
        fused = camera.copy()  # (camera is a column of the agent's array)
        if self._gyro is not None and len(self._gyro[1]) == len(yaw):
            t, last_yaw, last = self._gyro
            turned = wrap_angle(yaw - last_yaw)
            dt_s, weight = obs.time_s - t, self.cfg.gyro_camera_weight
            step = fuse_heading(last, camera, turned, obs.speed, obs.curvature, dt_s, weight)
            fused = np.where(obs.respawned, camera, step)
        self._gyro = (obs.time_s, yaw, fused)
        return fused


def _flags(values: np.ndarray | None, n: int) -> np.ndarray:
    """``values`` as ``(n,)`` booleans (``None``: all False)."""
    return np.broadcast_to(np.asarray(False if values is None else values, dtype=bool), n)
