"""The roads an evaluation drives: the blocks of test tracks (:data:`ROAD_BLOCKS`: every drive of
the course drives the open block, the numbers of record alone the sealed one), and the worlds the
cars drive them in (:class:`WorldPool`: a road and its parked cars made once per track, a pymunk
world per car). Which track each car drives next is :func:`~e2e_lite.driving.rollout.track_index`.
"""

from __future__ import annotations

from ..simulation.world import (
    SEALED_TEST_TRACKS,
    SPENT_TEST_TRACKS,
    World,
    WorldConfig,
    make_world,
)

#: Blocks of test tracks, by name: ``[first, end)`` track indices. "open" holds every road the
#: course, the lab scripts, the benchmarks and the tests drive; "record-2" is sealed: only the
#: numbers of record (:func:`e2e_lite.record.run.record_share`) drive it, after every recipe
#: choice is frozen, so no choice was ever made while looking at its roads (a test checks that
#: no other code names it, and `rollout.track_index` keeps every other drive out). "record" is
#: spent: the records of 321f6a9 and 28eba5c drove it, with a redesign between them, so no drive
#: makes its roads again (:data:`SPENT_BLOCKS`; its records stay readable).
SEALED_BLOCK = "record-2"
SPENT_BLOCKS = ("record",)
ROAD_BLOCKS = {
    "open": (0, SPENT_TEST_TRACKS.start),
    "record": (SPENT_TEST_TRACKS.start, SPENT_TEST_TRACKS.stop),
    SEALED_BLOCK: (SEALED_TEST_TRACKS.start, SEALED_TEST_TRACKS.stop),
}


class WorldPool:
    """Worlds of the evaluation split: a road and its cars are made once per track, and every car
    gets its own pymunk world of it (two cars on one track must not share an ego body). Only a
    pool of the sealed block (``block``) may make a sealed road (:func:`make_world` refuses
    every other caller)."""

    def __init__(self, world_cfg: WorldConfig, split: str, block: str = "open") -> None:
        if block in SPENT_BLOCKS:
            raise ValueError(
                f"the block {block!r} of test roads is spent (two records drove it): a record "
                f"drives {SEALED_BLOCK!r}"
            )
        self.world_cfg, self.split = world_cfg, split
        self.sealed = block == SEALED_BLOCK
        self._roads: dict[int, World] = {}
        self._worlds: dict[tuple[int, int], World] = {}

    def release(self, car: int, index: int) -> None:
        """Forget car ``car``'s world of track ``index`` (it moved on and never comes back)."""
        self._worlds.pop((car, index), None)
        if not any(k[1] == index for k in self._worlds):
            self._roads.pop(index, None)

    def get(self, car: int, index: int) -> World:
        if (car, index) not in self._worlds:
            if index not in self._roads:
                self._roads[index] = make_world(
                    self.world_cfg, self.split, index, sealed=self.sealed
                )
            road = self._roads[index]
            self._worlds[(car, index)] = (
                road
                if not any(k[1] == index for k in self._worlds)
                else World(road.track, road.cars, self.world_cfg.vehicle)
            )
        return self._worlds[(car, index)]
