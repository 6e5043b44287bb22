"""The safety module of the paper's Fig. 1, which the paper left unbuilt (chapter 11): the rule
that checks a proposed trajectory against the perceived affordances, its fallback and its
calibrated thresholds (:mod:`~e2e_lite.safety.rule`), and the driver that puts a trajectory
network behind it (:mod:`~e2e_lite.safety.agent`)."""
