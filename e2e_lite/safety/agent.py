"""The safety module as a driver (chapter 11): :class:`SafeAgent` wraps a trajectory network,
checks each proposed trajectory with :func:`~e2e_lite.safety.rule.check` on perceived (or true)
affordances, falls back as :func:`~e2e_lite.safety.rule.choose` says, and reports what it did with
each decision (``Actuation.info``, added up by the evaluator into ``result.info``; read it with
:meth:`SafetyStats.from_info`): interventions by source and kind, who drove the last decision
before each collision, false alarms audited against a fresh expert's trajectory from the same
state, and a few examples (JSON-able: the track's id, the pose, the modes and what was driven;
rebuild the view with :func:`~e2e_lite.simulation.world.make_world`).
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..config import check_range
from ..control.affordances import affordances
from ..control.expert import expert_labels
from ..control.rules import ExpertConfig, SpeedLimits
from ..simulation.policy import Actuation, Observation, fingerprint
from ..simulation.world import SimConfig
from .rule import RESULTS_VERSION, SafetyConfig, check, choose

#: a collision within this long after the module last intervened for the car, with the network
#: driving, counts as after a hand-back [s]
HANDBACK_S = 2.0
#: the causes of a collision (:attr:`SafetyStats.at_impact`): the module's own manoeuvre (its
#: other mode or its fallback drove the last decision), the network within ``HANDBACK_S`` of an
#: intervention (the module handed the car back, often slowed), or the network with the module
#: silent (a miss: it saw nothing wrong, or saw it too late)
IMPACT_CAUSES = ("fallback", "other mode", "network after a hand-back", "network, module silent")


def impact_cause(source: str, decisions_since: float, period_s: float | None = None) -> str:
    """The cause of a collision (one of :data:`IMPACT_CAUSES`): ``source`` drove the car's last
    decision, ``decisions_since`` decisions after the module last intervened for it (``inf``:
    never, since the car's start); ``period_s``, the policy's period [s] (the simulator's
    default)."""
    if source != "network":
        return source
    period = SimConfig().policy_period_s if period_s is None else period_s
    handed_back = decisions_since * period <= HANDBACK_S + 1e-9
    return IMPACT_CAUSES[2] if handed_back else IMPACT_CAUSES[3]


#: the counters a :class:`SafeAgent` reports with each decision (``Actuation.info``)
COUNTS = ("decisions", "audited", "false_alarms", "perception_only")
TABLES = ("sources", "kinds", "at_impact")


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
        at_impact: every collision by its cause (:data:`IMPACT_CAUSES`): who drove the car's
            last decision before it, and for the network whether the module had intervened for
            that car within :data:`HANDBACK_S` (it handed the car back) or not (it was silent).
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
            "audited": self.audited,
            "false_alarms": self.false_alarms,
            "false_alarm_pct": 100.0 * self.false_alarms / k,
            "perception_only": self.perception_only,
            "perception_only_pct": 100.0 * self.perception_only / k,
        }


class SafeAgent:
    """A trajectory agent behind the safety module: the network proposes, the module checks
    (:func:`choose`), the tracker follows what was chosen; a car the module falls back for is
    braked at ``cfg.emergency_brake_mps2`` when that is set.

    Args:
        agent: a :class:`~e2e_lite.imitation.agents.TrajectoryAgent` (or any policy with its
            ``trajectories(obs)``, ``last``, ``follow(points, obs)``, ``camera`` and ``fork``).
        cfg: the check's settings.
        ground_truth: check with the world's true affordances instead of the network's
            predictions (the upper bound; needs no affordance head).
        audit: at every intervention, also ask a fresh expert and the ground-truth check whether
            it was needed (the false-alarm counts; costs time).
        audit_every: audit one intervention in this many (1: all; the rates are then
            estimated from that sample).
        keep_examples: interventions kept per shard for figures (JSON-able, see above).
    """

    #: in every stored guarded evaluation's key (:func:`e2e_lite.record.stored.fingerprint`)
    RESULTS_VERSION = RESULTS_VERSION

    def __init__(
        self,
        agent: Any,
        cfg: SafetyConfig | None = None,
        ground_truth: bool = False,
        audit: bool = True,
        audit_every: int = 1,
        keep_examples: int = 6,
    ) -> None:
        check_range("SafeAgent", "audit_every", audit_every, 1, integer=True)
        check_range("SafeAgent", "keep_examples", keep_examples, 0, integer=True)
        if cfg is not None and not isinstance(cfg, SafetyConfig):
            raise TypeError(f"SafeAgent: cfg must be a SafetyConfig, not {type(cfg).__name__}")
        model = getattr(agent, "model", None)
        if not ground_truth and model is not None and not model.cfg.affordance:
            raise ValueError(
                "SafeAgent: the perceived check needs predicted affordances: give an agent whose "
                "model has an affordance head, or use ground_truth=True"
            )
        self.agent, self.cfg = agent, cfg or SafetyConfig()
        self.ground_truth, self.audit, self.keep_examples = ground_truth, audit, keep_examples
        self.audit_every = audit_every
        self._seen = 0  # interventions met by this copy (for audit_every)
        self._kept = 0  # examples reported since the last reset
        self._driven: list[str] = []  # each car's last source
        self._since = np.zeros(0)  # each car's decisions since the module last intervened
        self._limits = SpeedLimits(ExpertConfig())  # the audits' speed limits, once per track
        self.camera = agent.camera
        self.last: dict[str, Any] = {}

    def identity(self) -> list[Any]:
        """What decides its behaviour and what it reports
        (:func:`~e2e_lite.simulation.policy.fingerprint`): its settings, its network's identity,
        what it perceives with, its audits and examples, and the version of what it reports."""
        audits = [self.audit, self.audit_every, self.keep_examples]
        inner = [fingerprint(self.agent), self.ground_truth]
        return [repr(self.cfg), *inner, *audits, ("results version", self.RESULTS_VERSION)]

    def reset(self, n_worlds: int) -> None:
        """Reset the network agent, the count of reported examples and the audits' limits."""
        self.agent.reset(n_worlds)
        self._kept = 0
        self._driven = [""] * n_worlds
        self._since = np.full(n_worlds, np.inf)
        self._limits = SpeedLimits(ExpertConfig())  # (one evaluation's tracks)

    def fork(self, k: int) -> list[SafeAgent]:
        """``k`` agents for parallel shards, sharing the model."""
        out = []
        for inner in self.agent.fork(k):
            twin = type(self).__new__(type(self))
            twin.__dict__.update(self.__dict__)
            twin.agent, twin._seen, twin._kept, twin.last = inner, 0, 0, {}
            twin._driven, twin._since = [], np.zeros(0)
            twin._limits = SpeedLimits(ExpertConfig())
            out.append(twin)
        return out

    def act(self, obs: Observation) -> Actuation:
        """Propose, check, follow."""
        at_impact = Counter()
        if obs.collided is not None and self._driven:
            at_impact.update(
                impact_cause(self._driven[i], self._since[i])
                for i in np.flatnonzero(obs.collided).tolist()
            )
        if len(self._since) != len(obs.s):
            self._since = np.full(len(obs.s), np.inf)
        self._since[np.asarray(obs.respawned, dtype=bool)] = np.inf  # a new start: no history
        proposal = self.agent.trajectories(obs)
        last = self.agent.last
        modes = last.get("modes", proposal[:, None])
        weights = last.get("weights", np.ones((len(proposal), 1)))
        if self.ground_truth:
            seen = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        elif "affordances" in last:
            seen = last["affordances"]
        else:
            raise ValueError("SafeAgent: the agent predicted no affordances; use ground_truth=True")
        chosen = np.empty_like(proposal)
        sources, kinds, audits = [], [], []
        for i in range(len(proposal)):
            c = choose(
                modes[i], weights[i], seen[i], float(obs.speed[i]), obs.curvature[i], self.cfg
            )
            chosen[i] = c.points
            sources.append(c.source)
            if c.source != "network":
                kinds.append(c.verdicts[0].kind)
                audits.append((i, c))
        audited, false_alarms, perception_only = self._audit([i for i, _ in audits], obs, proposal)
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
            "audited": audited,
            "false_alarms": false_alarms,
            "perception_only": perception_only,
            "sources": Counter(sources),
            "kinds": Counter(kinds),
            "at_impact": at_impact,
            "examples": examples,
        }
        self.last = {"chosen": chosen, "sources": sources, "seen": seen}
        self._driven = sources
        self._since += 1.0
        self._since[np.array(sources) != "network"] = 0.0
        out = self.agent.follow(chosen, obs)
        if self.cfg.emergency_brake_mps2 is not None:  # the fallback brakes at it
            accel = np.array(out.accel_mps2, dtype=np.float64)
            accel[np.array(sources) == "fallback"] = -self.cfg.emergency_brake_mps2
            out = dataclasses.replace(out, accel_mps2=accel)
        return dataclasses.replace(out, info=info)

    def _audit(
        self, intervened: list[int], obs: Observation, proposal: np.ndarray
    ) -> tuple[int, int, int]:
        """Audit one in ``audit_every`` of this decision's interventions (cars ``intervened``).
        Returns ``(audited, false alarms, perception only)``: how many were audited, how many a
        fresh expert from the same state would not have needed (its trajectory within 1 m
        sideways and 5 m along of the proposal at 1.5 s), and how many the rule on the world's
        true affordances would have let pass (perception alone caused them)."""
        audited = []
        for i in intervened:
            if self.audit and self._seen % self.audit_every == 0:
                audited.append(i)
            self._seen += 1
        if not audited:
            return 0, 0, 0
        expert_pts = expert_labels(obs, audited, getattr(self.agent, "sim", None), self._limits)
        false_alarms = 0
        for j, i in enumerate(audited):
            dx, dy = np.abs(expert_pts[j, -1] - proposal[i, -1])
            false_alarms += int(dy <= 1.0 and dx <= 5.0)
        if self.ground_truth:  # (the ground-truth check already saw the truth)
            return len(audited), false_alarms, 0
        worlds = [obs.worlds[i] for i in audited]
        true_aff = affordances(worlds, obs.s[audited], obs.d[audited], obs.heading_error[audited])
        perception_only = sum(
            int(check(proposal[i], true_aff[j], float(obs.speed[i]), obs.curvature[i], self.cfg).ok)
            for j, i in enumerate(audited)
        )
        return len(audited), false_alarms, perception_only
