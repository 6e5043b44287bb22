"""Closed-loop driving and what it measures: the lockstep rollout of B cars, its shards in
threads or worker processes, collisions per 100 miles with their intervals (the tests that
compare them: :mod:`e2e_lite.stats`), and
:func:`~e2e_lite.driving.evaluation.evaluate`, which composes them. Knows nothing of learning:
the data collector drives the expert through it."""
