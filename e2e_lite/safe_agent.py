"""The safety module as a driver (chapter 11): :class:`SafeAgent` wraps a trajectory network,
checks each proposed trajectory with :func:`~e2e_lite.safety.check` on perceived (or true)
affordances, falls back as :func:`~e2e_lite.safety.choose` says, and counts what it did
(:class:`SafetyStats`): interventions by source and kind, and false alarms audited against a
fresh expert's trajectory from the same state.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .config import check_range
from .data import affordances
from .expert import Expert
from .policy import Actuation, Observation
from .safety import SafetyConfig, check, choose
from .world import SimConfig


@dataclass
class SafetyStats:
    """Counters of a :class:`SafeAgent` (shared by its forks, thread-safe).

    Attributes:
        decisions: car-decisions checked.
        sources: how many times each source was driven (``network``, ``other mode``,
            ``fallback``).
        kinds: why the followed mode was rejected (``road edge``, ``collision course``,
            ``cannot stop``).
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
    false_alarms: int = 0
    perception_only: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def interventions(self) -> int:
        """Decisions where the followed mode was not driven."""
        return self.decisions - self.sources["network"]

    def __getstate__(self) -> dict[str, Any]:  # the lock stays behind (a worker makes its own)
        return {k: v for k, v in self.__dict__.items() if k != "lock"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.lock = threading.Lock()

    def counts(self) -> dict[str, Any]:
        """The counters as plain data (copies; picklable, unlike the lock)."""
        return {
            "decisions": self.decisions,
            "audited": self.audited,
            "sources": Counter(self.sources),
            "kinds": Counter(self.kinds),
            "false_alarms": self.false_alarms,
            "perception_only": self.perception_only,
        }

    def add(self, counts: dict[str, Any], sign: int = 1) -> None:
        """Add (``sign=-1``: subtract) counters given as :meth:`counts`, under the lock."""
        with self.lock:
            for name in ("decisions", "audited", "false_alarms", "perception_only"):
                setattr(self, name, getattr(self, name) + sign * counts[name])
            for name in ("sources", "kinds"):
                table = getattr(self, name)
                for key, n in counts[name].items():
                    table[key] += sign * n
                setattr(self, name, +table)  # drop zero counts

    def to_dict(self) -> dict[str, Any]:
        """Counts and rates, JSON-ready (examples left out)."""
        n, k = max(1, self.decisions), max(1, self.audited)
        return {
            "decisions": self.decisions,
            "interventions": self.interventions,
            "intervention_pct": 100.0 * self.interventions / n,
            "sources": dict(self.sources),
            "kinds": dict(self.kinds),
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
        agent: a :class:`~e2e_lite.agents.TrajectoryAgent` (or any policy with its
            ``trajectories(obs)``, ``last``, ``follow(points, obs)``, ``camera`` and ``fork``).
        cfg: the check's settings.
        ground_truth: check with the world's true affordances instead of the network's
            predictions (the upper bound; needs no affordance head).
        audit: at every intervention, also ask a fresh expert and the ground-truth check whether
            it was needed (the false-alarm counts; costs time).
        audit_every: audit one intervention in this many (1: all; the rates are then
            estimated from that sample).
        keep_examples: interventions kept per shard for figures (with the camera frame).
    """

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
        model = getattr(agent, "model", None)
        if not ground_truth and model is not None and not model.cfg.affordance:
            raise ValueError(
                "the perceived check needs predicted affordances: give an agent whose model has "
                "an affordance head, or use ground_truth=True"
            )
        self.agent, self.cfg = agent, cfg or SafetyConfig()
        self.ground_truth, self.audit, self.keep_examples = ground_truth, audit, keep_examples
        self.audit_every = audit_every
        self._seen = 0  # interventions met by this shard (for audit_every)
        self.camera = agent.camera
        self.stats = SafetyStats()
        self._kept: list[dict[str, Any]] = []
        self._forks: list[SafeAgent] = []
        self._shard = 0
        self._at_reset = self.stats.counts()
        self.last: dict[str, Any] = {}

    @property
    def forks_in_processes(self) -> bool:
        """The forks may run in processes when the network agent's may: each child sends its
        counts and kept examples back (:meth:`shard_report`, :meth:`absorb_report`)."""
        return bool(getattr(self.agent, "forks_in_processes", False))

    def reset(self, n_worlds: int) -> None:
        """Reset the network agent; :attr:`stats` keep counting (forks share them)."""
        self.agent.reset(n_worlds)
        self._at_reset = self.stats.counts()

    def shard_report(self) -> dict[str, Any]:
        """What this fork counted and kept since its :meth:`reset` (sent home by an
        evaluation's shard process)."""
        delta = SafetyStats()
        delta.add(self.stats.counts())
        delta.add(self._at_reset, sign=-1)
        return {"counts": delta.counts(), "kept": self._kept}

    def absorb_report(self, report: dict[str, Any]) -> None:
        """Take in a :meth:`shard_report` of this fork's process: add its counts to the shared
        :attr:`stats`, keep its examples."""
        self.stats.add(report["counts"])
        self._kept = list(report["kept"])

    def fork(self, k: int) -> list[SafeAgent]:
        """``k`` agents for parallel shards, sharing the model and the counters."""
        out = []
        for shard, inner in enumerate(self.agent.fork(k)):
            twin = SafeAgent.__new__(SafeAgent)
            twin.__dict__.update(self.__dict__)
            twin.agent, twin._kept, twin._forks, twin._shard = inner, [], [], shard
            twin._seen = 0
            out.append(twin)
        self._forks += out
        return out

    def act(self, obs: Observation) -> Actuation:
        """Propose, check, follow."""
        proposal = self.agent.trajectories(obs)
        last = self.agent.last
        modes = last.get("modes", proposal[:, None])
        weights = last.get("weights", np.ones((len(proposal), 1)))
        truth = None
        if self.ground_truth:
            truth = affordances(obs.worlds, obs.s, obs.d, obs.heading_error)
        if not self.ground_truth and "affordances" not in last:
            raise ValueError("the agent predicted no affordances; use ground_truth=True")
        seen = truth if self.ground_truth else last["affordances"]
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
        false_alarms = perception_only = 0
        audited = []
        for i, _ in audits:
            if self.audit and self._seen % self.audit_every == 0:
                audited.append(i)
            self._seen += 1
        if audited:
            expert_pts = _expert_labels(obs, audited, getattr(self.agent, "sim", None))
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
        for i, c in audits:
            if len(self._kept) < self.keep_examples and obs.images is not None:
                self._kept.append(
                    {
                        "shard": self._shard,
                        "time_s": obs.time_s,
                        "track": obs.worlds[i].track,
                        "cars": obs.worlds[i].cars,
                        "pose": obs.state[i, :3].copy(),
                        "s": float(obs.s[i]),
                        "speed": float(obs.speed[i]),
                        "frame": obs.images[i].copy(),
                        "modes": np.asarray(modes[i]).copy(),
                        "weights": np.asarray(weights[i]).copy(),
                        "chosen": c.points.copy(),
                        "source": c.source,
                        "reason": c.verdicts[0].reason,
                    }
                )
        with self.stats.lock:
            self.stats.audited += len(audited)
            self.stats.decisions += len(proposal)
            self.stats.sources.update(sources)
            self.stats.kinds.update(kinds)
            self.stats.false_alarms += false_alarms
            self.stats.perception_only += perception_only
        self.last = {"chosen": chosen, "sources": sources}
        return self.agent.follow(chosen, obs)

    def examples(self) -> list[dict[str, Any]]:
        """The kept interventions of this agent and its forks, in shard order then time."""
        kept = [e for agent in [self, *self._forks] for e in agent._kept]
        return sorted(kept, key=lambda e: (e["shard"], e["time_s"]))


def _expert_labels(obs: Observation, idx: list[int], sim: SimConfig | None = None) -> np.ndarray:
    """What a fresh expert would drive from cars ``idx``'s states: ``(len(idx), 5, 2)`` [m]
    (``sim``: the driven agent's time steps, default :class:`~e2e_lite.world.SimConfig`)."""
    sub = Observation(
        state=obs.state[idx],
        s=obs.s[idx],
        d=obs.d[idx],
        heading_error=obs.heading_error[idx],
        curvature=obs.curvature[idx],
        lane=obs.lane[idx],
        respawned=np.ones(len(idx), dtype=bool),
        time_s=obs.time_s,
        worlds=[obs.worlds[i] for i in idx],
    )
    # the expert of the car and time steps being driven, not a default one
    expert = Expert(vehicle=obs.worlds[idx[0]].vehicle, sim=sim)
    expert.reset(len(idx))
    return expert.trajectory_label(sub)
