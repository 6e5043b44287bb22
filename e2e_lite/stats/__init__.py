"""The course's statistics: counts of collisions and their miles in, frozen results out, and no
sentence (the words a verdict prints are :mod:`e2e_lite.record.words`'). Below every layer that
drives: it imports nothing of the simulator, the drivers or the record.

:mod:`.rates` (a Poisson rate's interval, two pooled rates compared), :mod:`.seeds` (the
seed-level rank and sign-flip tests, the rate ratio and its interval, the worst seed's spread),
:mod:`.power` (power under the seeds' spread, the negative binomial's dispersion, Holm).
"""
