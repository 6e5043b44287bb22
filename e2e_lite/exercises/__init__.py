"""Exercises that check themselves (:mod:`.checks`; ``python -m e2e_lite.exercises``): the top
floor, since a check may read the record (:mod:`e2e_lite.record`) and anything below it."""
