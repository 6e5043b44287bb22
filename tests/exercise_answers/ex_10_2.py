"""The reference answer of exercise 10.2 (the suite checks that it passes and the stub
does not; keep it from students)."""


def record_size() -> tuple[int, float]:
    """(seeds per row, miles per seed [mi])."""
    return 80, 300.0
