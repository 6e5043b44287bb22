"""The record's data, typed: what a share of the record holds (:class:`Share`: per row, each
training seed's drive of the sealed block) and what the pooled record holds (:class:`Record`:
per row, each seed's collisions and miles), each seed's drive one :class:`SeedRun`. Every class reads
its JSON (``from_json``) and writes it back unchanged (``to_json``: the same keys in the same
order), so the committed files load and re-render byte for byte.

The sums a reader of a row needs live here once: its miles, its collisions, its pooled rate, and
whether it drove slow beside the expert (:data:`SLOW_SHARE`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar

from ..driving.metrics import EvalResult
from ..stats.rates import poisson_ci

#: a row slower than this share of the expert's speed is marked, and its verdicts name its speed
SLOW_SHARE = 0.9


def slow(mph: float, expert_mph: float | None) -> float | None:
    """``mph`` when it is more than ``1 - SLOW_SHARE`` slower than the expert's, else None."""
    return mph if expert_mph and mph < SLOW_SHARE * expert_mph else None


class _Json:
    """JSON in and out for the record's dataclasses: ``to_json`` writes every field in field
    order, leaving out the :attr:`OPTIONAL` ones that are None; ``from_json`` reads the fields
    back, building the :attr:`NESTED` ones (a list of items, or one object) as their class."""

    #: fields left out of the JSON when None
    OPTIONAL: ClassVar[tuple[str, ...]] = ()
    #: fields held as another of these classes (a JSON list: a tuple of them)
    NESTED: ClassVar[dict[str, type[_Json]]] = {}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Any:
        typed = {}
        for name, kind in cls.NESTED.items():
            if name in d:
                value = d[name]
                is_list = isinstance(value, list)
                typed[name] = (
                    tuple(map(kind.from_json, value)) if is_list else kind.from_json(value)
                )
        return cls(**{**d, **typed})

    def to_json(self) -> dict[str, Any]:
        out = {}
        for f in fields(self):  # type: ignore[arg-type]
            value = getattr(self, f.name)
            if value is None and f.name in self.OPTIONAL:
                continue
            if isinstance(value, tuple) and f.name in self.NESTED:
                value = [v.to_json() for v in value]
            elif isinstance(value, _Json):
                value = value.to_json()
            out[f.name] = value
        return out


@dataclass(frozen=True)
class SeedRun(_Json):
    """One training seed's drive of one row: in a share, from which track of the block it drove
    (``first_track``) and its car and rail collisions; in the pooled record, on which machine
    (``machine``). A field that a file does not hold is None and left out of its JSON.

    Attributes:
        seed: the training seed (0 for a row driven by one network or none).
        first_track: the first track of its run of the block (a share's).
        collisions: car and rail collisions.
        car, rail: collisions into parked cars and into the rails (a share's).
        miles: miles driven [mi].
        mph: mean speed [mph] (None: not recorded).
        stalls: re-placements after standing still (None: not recorded).
        machine: index into :attr:`Record.machines` (None: a row without training seeds).
        interventions: the autonomy metric's interventions, collisions and off-centre episodes
            (:attr:`~e2e_lite.driving.metrics.EvalResult.off_centre`; None: not recorded, as in
            shares before 2026-11-29).
    """

    seed: int
    collisions: int
    miles: float
    first_track: int | None = None
    car: int | None = None
    rail: int | None = None
    mph: float | None = None
    stalls: int | None = None
    machine: int | None = None
    interventions: int | None = None

    OPTIONAL: ClassVar[tuple[str, ...]] = (
        "first_track",
        "car",
        "rail",
        "mph",
        "stalls",
        "machine",
        "interventions",
    )
    #: the order a share's JSON holds them in (the pooled record's: the fields' order)
    SHARE_ORDER: ClassVar[tuple[str, ...]] = tuple(
        "seed first_track collisions car rail miles mph stalls interventions".split()
    )

    @classmethod
    def of(cls, result: EvalResult, seed: int, first_track: int) -> SeedRun:
        """One seed's drive of one row in a share, from its evaluation's result."""
        return cls(
            seed=seed,
            first_track=first_track,
            collisions=result.collisions,
            car=result.car_collisions,
            rail=result.rail_collisions,
            miles=round(result.miles, 3),
            mph=round(result.mean_speed_mph, 2),
            stalls=result.stalls,
            interventions=result.interventions,
        )

    @property
    def off_centre(self) -> int | None:
        """Off-centre episodes: the interventions that were neither collisions nor stalls (None:
        not recorded)."""
        if self.interventions is None:
            return None
        return self.interventions - self.collisions - (self.stalls or 0)

    def to_json(self) -> dict[str, Any]:
        out = super().to_json()
        if self.first_track is None:
            return out
        return {k: out[k] for k in self.SHARE_ORDER if k in out}


@dataclass(frozen=True)
class Row(_Json):
    """One driver of the record: its seeds' runs and their sums.

    Attributes:
        key, label: the driver's key (:data:`~e2e_lite.record.ablation.BY_KEY`) and its table name.
        paper_per_100mi: the paper's Table 1 figure, if it has one [collisions / 100 mi].
        seeds: each training seed's run.
        car, rail: collisions into parked cars and into the rails, over every seed.
        mph: mean speed over every seed's miles [mph].
        stalls: re-placements over every seed (None: not recorded).
        commit: the recipes' commit that trained and drove it (None: not recorded).
        control: whether the row is a control (a method's twin without it).
    """

    key: str
    label: str
    paper_per_100mi: float | None
    seeds: tuple[SeedRun, ...]
    car: int
    rail: int
    mph: float
    stalls: int | None
    commit: str | None = None
    control: bool | None = None

    OPTIONAL: ClassVar[tuple[str, ...]] = ("commit", "control")
    NESTED: ClassVar[dict[str, type[_Json]]] = {"seeds": SeedRun}

    @property
    def interventions(self) -> int | None:
        """The autonomy metric's interventions over every seed, collisions and off-centre
        episodes (None: not recorded for every seed)."""
        kept = [s.interventions for s in self.seeds]
        return None if None in kept else sum(kept)

    @property
    def off_centre(self) -> int | None:
        """Off-centre episodes over every seed: the interventions that were neither collisions
        nor stalls (the count :attr:`~e2e_lite.driving.metrics.EvalResult.off_centre` takes of
        one drive; None: not recorded for every seed)."""
        kept = [s.off_centre for s in self.seeds]
        return None if None in kept else sum(kept)

    @property
    def miles(self) -> float:
        """Miles driven over every seed [mi]."""
        return sum(s.miles for s in self.seeds)

    @property
    def collisions(self) -> int:
        """Collisions over every seed (car and rail)."""
        return self.car + self.rail

    def pooled(self) -> tuple[float, float, float]:
        """The pooled rate per 100 miles and its exact 95 % Poisson interval (secondary: it
        treats the seeds' miles as one draw)."""
        k = sum(s.collisions for s in self.seeds)
        lo, hi = poisson_ci(k, self.miles / 100.0)
        return 100.0 * k / self.miles, lo, hi

    def minutes_between(self) -> float | None:
        """The mean driving time between two collisions [min] (None without a collision)."""
        return 60.0 * self.miles / self.mph / self.collisions if self.collisions else None

    def slow_beside(self, expert_mph: float | None) -> bool:
        """Whether the row drove more than ``1 - SLOW_SHARE`` slower than the expert."""
        return slow(self.mph, expert_mph) is not None


@dataclass(frozen=True)
class Block(_Json):
    """The block of test roads a record drove (:data:`~e2e_lite.driving.roads.ROAD_BLOCKS`):
    its name, its range of tracks, and in a pooled record the commit of the recipes frozen before
    it was driven and whether it is sealed (the quick profile's smoke run drives the open one)."""

    name: str
    range: list[int]
    recipes_commit: str | None = None
    sealed: bool | None = None

    OPTIONAL: ClassVar[tuple[str, ...]] = ("recipes_commit", "sealed")


@dataclass(frozen=True)
class Family(_Json):
    """The families of tests a record declared: each family's question, each test's family, the
    adjustment within a family, when they were declared (before the record ran, or not) and why
    the tests are grouped so (a record that declared no reason: None)."""

    families: dict[str, str]
    tests: dict[str, str]
    adjustment: str
    declared: str
    reason: str | None = None

    OPTIONAL: ClassVar[tuple[str, ...]] = ("reason",)


@dataclass(frozen=True)
class ShareRef(_Json):
    """A share a record was pooled from: its file, its seeds and its digest."""

    file: str
    seeds: list[int]
    digest: str


@dataclass(frozen=True, kw_only=True)
class Record(_Json):
    """A record of Table 1: its rows, where and how they were driven, the families of tests it
    declared, and the shares it was pooled from (see :mod:`e2e_lite.record`). Its fields are in
    the order its JSON holds them."""

    title: str
    status: str
    machine: str
    machines: list[str] | None = None
    torch: str
    precision: str | None = None
    roads: str | None = None
    block: Block | None = None
    commits: dict[str, str] | None = None
    miles_note: str
    single_seed_rows: list[str] | None = None
    family: Family | None = None
    shares: tuple[ShareRef, ...] | None = None
    paper_mph: float
    rows: tuple[Row, ...]
    notes: list[str] | None = None
    torch_threads: int | None = None

    OPTIONAL: ClassVar[tuple[str, ...]] = tuple(
        "machines precision roads block commits single_seed_rows family shares notes"
        " torch_threads".split()
    )
    NESTED: ClassVar[dict[str, type[_Json]]] = {
        "rows": Row,
        "block": Block,
        "family": Family,
        "shares": ShareRef,
    }

    def row(self, key: str) -> Row | None:
        """The row of driver ``key`` (None when the record has none)."""
        return next((r for r in self.rows if r.key == key), None)

    @property
    def expert_mph(self) -> float | None:
        """The expert's speed, beside which a row is slow (None without an expert row)."""
        expert = self.row("expert")
        return expert.mph if expert else None


#: what a share file says it is
SHARE_FORMAT = "e2e-lite record share"


@dataclass(frozen=True)
class ShareRow(_Json):
    """One driver in a share: each of the share's seeds' drives."""

    key: str
    label: str
    paper_per_100mi: float | None
    control: bool
    runs: tuple[SeedRun, ...]

    NESTED: ClassVar[dict[str, type[_Json]]] = {"runs": SeedRun}


@dataclass(frozen=True)
class Share(_Json):
    """One share of the record (:func:`~e2e_lite.record.run.record_share`): every row for some
    training seeds, with what a pool checks before it takes it (:func:`~e2e_lite.record.pool.pool`):
    the profile, the miles per seed, the recipes' commit, a key of the settings, the data, the
    precision, torch, the machine, the block, the single-seed rows, the families of tests, and a
    digest of all of it (:meth:`content_digest`; empty until :meth:`sealed`)."""

    format: str
    profile: str
    seeds: list[int]
    miles_per_seed: float
    recipes_commit: str
    settings_key: str
    data: dict[str, str]
    precision: str
    torch: str
    machine: str
    block: Block
    single_seed_rows: list[str]
    family: Family
    rows: tuple[ShareRow, ...]
    digest: str = ""

    NESTED: ClassVar[dict[str, type[_Json]]] = {"block": Block, "family": Family, "rows": ShareRow}

    def content_digest(self) -> str:
        """A SHA-256 digest of the share's content (everything but the digest itself)."""
        body = {k: v for k, v in self.to_json().items() if k != "digest"}
        return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()

    def sealed(self) -> Share:
        """The share with its digest written."""
        return dataclasses.replace(self, digest=self.content_digest())


def check_rows(record: Record, name: str) -> Record:
    """``record`` if each row has seeds with miles and its seeds add up to its car and rail
    collisions; else a ``ValueError`` naming ``name`` and the row."""
    for row in record.rows:
        if not row.seeds or any(s.miles <= 0 or s.collisions < 0 for s in row.seeds):
            raise ValueError(f"{name}: row {row.key!r} needs seeds with miles > 0")
        if sum(s.collisions for s in row.seeds) != row.collisions:
            raise ValueError(f"{name}: row {row.key!r}: seeds do not add up to car + rail")
    return record


def load_record(path: Path) -> Record:
    """The record in ``path``, checked (:func:`check_rows`)."""
    return check_rows(Record.from_json(json.loads(path.read_text())), path.name)


def dump(obj: Record | Share) -> str:
    """The JSON text a record or a share is written as (as the committed files are)."""
    return json.dumps(obj.to_json(), indent=1)
