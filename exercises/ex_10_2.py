"""Exercise 10.2: the seeds per row and the miles per seed that would find a true 1.5x step (not
2x) at the + affordance row's rate nine times in ten, with seeds that spread as the record's do
(``e2e_lite.stats.power.power``; the record's rate and dispersion: ``record.stats.record_power``).

Check: ``python -m e2e_lite.exercises check 10.2``
"""


def record_size() -> tuple[int, float]:
    """(seeds per row, miles per seed [mi])."""
    raise NotImplementedError("your answer")
