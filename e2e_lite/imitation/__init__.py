"""Imitation in the loop: what drives the simulator so that a network can learn and be chosen.
The noisy expert's data collected by driving (:mod:`.collector`, its noise :mod:`.noise`), the
recorded frames seen from shifted cars (:mod:`.recovery`), a network turned into a driver
(:mod:`.agents`), an epoch kept by driving (:mod:`.selection`), the course's trained drivers
(:mod:`.recipes`) and DAgger (:mod:`.dagger`). What learns, without a simulator, is
:mod:`e2e_lite.learning`."""
