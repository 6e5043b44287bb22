"""The artifacts folder: keyed, atomic, self-checking files.

Everything the course writes (figures, metrics JSON, datasets, checkpoints, replays) lives under
one folder, ``outputs/`` at the repository root by default, or ``$E2E_LITE_OUTPUTS``. The quick
profile writes into its own ``quick/`` subfolder, so a smoke run never replaces the full profile's
checkpoints, datasets or metrics.

Reused artifacts are keyed by a hash of the settings that made them (:func:`settings_key`), so
changing a setting makes a new file instead of silently reusing an old one. Writes go to a
temporary file in the same folder, flushed to disk and renamed into place (:func:`atomic_write`),
so an interrupted run never leaves a half-written file that a later run trusts; a temporary left
by a killed run is removed by the next (:func:`remove_stale_temporaries`, at every chapter's
start). Every artifact that is read back (datasets, checkpoints, evaluations, metrics) is
**sealed**: a SHA-256 digest of its bytes beside it (``<name>.sha256``, :func:`seal`), checked
before it is trusted (:func:`check_seal`), so a flipped bit or a truncation is one line and a
rebuild, never a silently wrong number. :func:`cached` loads a valid artifact, or rebuilds it with
a one-line message when it is missing, corrupt, unsealed by its digest or made by other settings.

What the course guarantees after a crash (a killed process, a lost laptop battery, Ctrl-C): every
artifact is either the whole file a finished write left or absent; a digest that does not match
its file (a write cut between the two, or a disk that flipped a bit) makes the artifact rebuilt;
and the temporaries of the cut write are deleted by the next run. An artifact from before seals
existed (no ``.sha256`` beside it) is trusted as before and sealed on its first read.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import re
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from .config import QUICK_ENV, in_notebook, quick_requested

if TYPE_CHECKING:  # matplotlib is imported by whoever makes the figure
    from matplotlib.figure import Figure

OUTPUTS_ENV = "E2E_LITE_OUTPUTS"
_REPO_ROOT = Path(__file__).resolve().parents[1]

T = TypeVar("T")


def _default_root() -> Path:
    """``outputs/`` beside ``pyproject.toml`` in a source checkout, else ``./outputs``."""
    if (_REPO_ROOT / "pyproject.toml").exists():
        return _REPO_ROOT / "outputs"
    return Path.cwd() / "outputs"


def outputs_dir(quick: bool | None = None) -> Path:
    """The artifacts folder (created if missing).

    ``$E2E_LITE_OUTPUTS`` if set; else ``outputs/`` beside ``pyproject.toml`` when the package runs
    from a source checkout (so ``python chapters/01_highway.py`` from any folder writes to the same
    place); else ``./outputs``. Under the quick profile (``quick``, by default as the script's
    arguments and ``E2E_LITE_QUICK`` say), its ``quick/`` subfolder.
    """
    env = os.environ.get(OUTPUTS_ENV)
    root = Path(env) if env else _default_root()
    if quick_requested() if quick is None else quick:
        root = root / "quick"
    root.mkdir(parents=True, exist_ok=True)
    return root


@contextlib.contextmanager
def profile_outputs(quick: bool) -> Iterator[Path]:
    """Everything stored in the block goes to ``quick``'s profile's folder (:func:`outputs_dir`):
    ``E2E_LITE_QUICK`` says so for the block, and is given back after (a script started with
    ``--quick`` stays quick). A command run from Python (a test, a notebook) has another script's
    arguments, so without it a quick run would store its networks in the full profile's folder.
    Yields the folder."""
    before = os.environ.get(QUICK_ENV)
    os.environ[QUICK_ENV] = "1" if quick else "0"
    try:
        yield outputs_dir()
    finally:
        if before is None:
            os.environ.pop(QUICK_ENV, None)
        else:
            os.environ[QUICK_ENV] = before


def check_outputs_writable() -> Path:
    """The outputs folder, after checking that a file can be written there.

    Raises ``OSError`` with one line naming the folder, the reason and the setting to change.
    """
    root = Path(os.environ.get(OUTPUTS_ENV) or _default_root())
    try:
        root = outputs_dir()
        fd, tmp = tempfile.mkstemp(prefix=".write-check.", dir=root)
        os.close(fd)
        os.unlink(tmp)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise OSError(
            f"cannot write to the outputs folder {root}: {reason} "
            f"(set {OUTPUTS_ENV} to a folder you can write)"
        ) from None
    return root


def artifact_path(*parts: str) -> Path:
    """``outputs_dir() / parts...``, with the parent folder created."""
    path = outputs_dir().joinpath(*parts)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def seeded(name: str, seed: int, *, plain_zero: bool = False) -> str:
    """The stored name of training seed ``seed``'s artifact ``name``: ``<name>_seed<seed>``, or
    ``name`` itself for seed 0 with ``plain_zero`` (the chapters' own networks are seed 0)."""
    return name if plain_zero and seed == 0 else f"{name}_seed{seed}"


def added_later(**settings: tuple[Any, Any]) -> list[Any]:
    """The one rule that keeps old keys: settings a key gained after artifacts were stored under
    it, each given as ``name=(value, default)``; the values, in order, of those not at their
    default, so every key stored before a setting existed stays while it is at its default. A
    dataclass names such fields in ``KEY_DEFAULTS_OMITTED`` (:func:`key_fields` reads them by
    this rule); a driver's identity and a round's key call it directly."""
    return [value for value, default in settings.values() if value != default]


def key_fields(obj: Any, **overrides: Any) -> dict[str, Any]:
    """A dataclass's fields as its key holds them (those in ``KEY_DEFAULTS_OMITTED`` by
    :func:`added_later`'s rule), with ``overrides``: a plain dict, keyed as the dict it is."""
    return {**_plain(obj, True), **overrides}


def _plain(obj: Any, for_key: bool) -> Any:
    """``dataclasses.asdict``'s plain values, except that for a key, at every level, the fields a
    dataclass names in ``KEY_DEFAULTS_OMITTED`` are left out by :func:`added_later`'s rule."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        omitted = getattr(type(obj), "KEY_DEFAULTS_OMITTED", ()) if for_key else ()
        return {
            f.name: _plain(getattr(obj, f.name), for_key)
            for f in dataclasses.fields(obj)
            if f.name not in omitted or added_later(**{f.name: (getattr(obj, f.name), f.default)})
        }
    if isinstance(obj, (list, tuple)):
        return type(obj)(_plain(v, for_key) for v in obj)
    if isinstance(obj, dict):
        return {k: _plain(v, for_key) for k, v in obj.items()}
    return obj


def _jsonable(obj: Any, for_key: bool = False) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        # (nested dataclasses become plain dicts; fields added after artifacts were keyed keep
        # those keys at their default)
        return {"__type__": type(obj).__name__, **_jsonable(_plain(obj, for_key), for_key)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v, for_key) for k, v in obj.items()}  # keys keep their order
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v, for_key) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    return obj


def to_json(obj: Any) -> str:
    """``obj`` (dataclasses, numpy values and arrays included) as a compact JSON string."""
    return json.dumps(_jsonable(obj), allow_nan=True)


def settings_key(*settings: Any, length: int = 12) -> str:
    """A short hex hash of settings (dataclasses, dicts, numbers, strings).

    Equal settings give equal keys in every process; any changed field changes the key. A
    dataclass may name fields added after its artifacts existed in ``KEY_DEFAULTS_OMITTED``: at
    their default they are left out, so the artifacts made before keep their keys.
    """
    blob = json.dumps(_jsonable(list(settings), True), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:length]


def _process_umask() -> int:
    """The process's umask (read once, at import, when no other thread can create files)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()


def _temp_beside(path: Path, suffix: str) -> tuple[int, str]:
    """A temporary file in ``path``'s folder, with the permissions a plain ``open`` would give.

    ``mkstemp`` creates files as 0600; a renamed temporary would make every artifact private.
    """
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.fchmod(fd, 0o666 & ~_UMASK)
    return fd, tmp


#: a temporary of :func:`_temp_beside`: ``.<target's name>.<mkstemp's 8 characters><suffix>``
_TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]{8}(\.[A-Za-z0-9]+)?$")
#: a temporary whose file was last written this long before a run began is stale [s] (a live
#: write keeps its file's modification time fresh)
STALE_AFTER_S = 60.0


def remove_stale_temporaries(root: Path | str | None = None, before: float | None = None) -> int:
    """Delete the temporaries that killed writes left under ``root`` (default: the outputs
    folder): files named as :func:`atomic_write` and :func:`cached` name theirs whose last
    modification is older than ``before`` (a time, default now) less :data:`STALE_AFTER_S`.
    Returns how many were deleted; says so in one line when any were."""
    root = Path(root) if root is not None else outputs_dir()
    cutoff = (time.time() if before is None else before) - STALE_AFTER_S
    removed = 0
    for path in root.rglob(".*"):
        try:
            if path.is_file() and _TEMPORARY.match(path.name) and path.stat().st_mtime < cutoff:
                path.unlink()
                removed += 1
        except OSError:  # gone meanwhile, or not ours to delete
            continue
    if removed:
        print(f"[artifacts] removed {removed} temporary file(s) left by an interrupted run")
    return removed


def _fsync(path: Path | str) -> None:
    """Flush a written file's bytes to the disk (before it is renamed into place)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def file_digest(path: Path | str) -> str:
    """SHA-256 hex digest of a file's bytes, read in chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return digest.hexdigest()


def seal_path(path: Path | str) -> Path:
    """Where the digest of ``path`` is kept: ``<path>.sha256``."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def seal(path: Path | str) -> Path:
    """Write the SHA-256 digest of ``path``'s bytes beside it (atomically). Returns the path."""
    digest = file_digest(path)
    with atomic_write(seal_path(path), "w", sealed=False) as f:
        f.write(digest + "\n")
    return Path(path)


class CorruptArtifact(OSError):
    """A stored artifact's bytes do not match the digest sealed beside it."""


def check_seal(path: Path | str) -> str:
    """``"ok"`` when ``path``'s bytes match its sealed digest, ``"unsealed"`` when it has none
    (an artifact from before seals existed: it is sealed now, and trusted as before). Raises
    :class:`CorruptArtifact` (one line, naming the file) when they differ."""
    path = Path(path)
    try:
        stored = seal_path(path).read_text().strip()
    except FileNotFoundError:
        seal(path)
        return "unsealed"
    if stored != file_digest(path):
        raise CorruptArtifact(f"{path.name} does not match its digest (corrupt or cut short)")
    return "ok"


@contextlib.contextmanager
def atomic_write(path: Path | str, mode: str = "wb", sealed: bool = False) -> Iterator[Any]:
    """Open a temporary file beside ``path``; rename it onto ``path`` only if the block succeeds.

    Usage: ``with atomic_write(p) as f: f.write(data)``. The bytes are flushed to disk before the
    rename; on an exception the temporary file is removed and ``path`` is left as it was. With
    ``sealed``, the file's digest is written beside it (:func:`seal`) for :func:`check_seal`. The
    file gets the permissions the umask allows (0644 under the usual 022), as a plain ``open``
    would give.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _temp_beside(path, ".tmp")
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if sealed:
        seal(path)


def show_in_notebook(png: Path | str) -> None:
    """Show a saved PNG inline when running in a Jupyter kernel; do nothing elsewhere.

    Every figure writer calls it, so a chapter run as a notebook shows its figures where they are
    made, and saves them to ``outputs/figures`` either way.
    """
    if in_notebook():
        from IPython.display import Image, display  # (here: IPython is there in a notebook)

        display(Image(filename=str(png)))


def save_json(path: Path | str, obj: Any, sealed: bool = False) -> Path:
    """Write ``obj`` as indented JSON, atomically (``sealed``: its digest beside it). Returns the
    path."""
    with atomic_write(path, "w", sealed=sealed) as f:
        json.dump(_jsonable(obj), f, indent=2, allow_nan=True)
    return Path(path)


def load_json(path: Path | str) -> Any:
    """Read a JSON file."""
    with open(path) as f:
        return json.load(f)


def metrics_path(chapter: str) -> Path:
    """``<outputs>/metrics/<chapter>.json``, e.g. ``metrics_path("01_highway")``."""
    return artifact_path("metrics", f"{Path(chapter).stem}.json")


def write_metrics(
    chapter: str, metrics: dict[str, Any], figures: Sequence[Path | None] = ()
) -> Path:
    """Write a chapter's headline numbers where the course runner (and the next chapters) read
    them, with the chapter's ``figures`` (paths under the outputs folder; ``None`` skipped) as
    ``metrics["figures"]``, relative to that folder."""
    metrics = {"schema": METRICS_SCHEMA, **metrics}
    if figures:
        root = outputs_dir()
        metrics = {**metrics, "figures": [str(Path(f).relative_to(root)) for f in figures if f]}
    return save_json(metrics_path(chapter), metrics, sealed=True)


#: The versions of what each kind of stored artifact holds, part of its key: bump one when a
#: change to the code changes what such an artifact would hold, and every stored one is rebuilt
#: (``tests/test_reference.py`` refuses to record a changed behaviour under the same versions).
ARTIFACT_VERSIONS = {
    # 5: the expert reads its plan off the state at every decision (its labels are a function of
    # the state alone); 6: the course's expert carries its plan again (networks learned it
    # better), and every sample also holds the state expert's label (DAgger's relabelling); 7: a
    # return's change_side is the side it moves to again (6 recorded its overtake's); 8: one
    # expert, its plan read off the state, drives and labels (lab note "One expert for the whole
    # course"); the second label is gone
    "dataset": 8,
    # 3: the precision (fp32 / tf32) is part of the key
    "checkpoint": 3,
    # 3: the expert (and so the oracle) reads its plan off the state; 4: they carry it again;
    # 5: one expert, reading its plan off the state, with its home-lane rule
    "evaluation": 5,
    "head-refit": 1,
    # what a witnessed drive keeps (chapter 12's anatomy: ``driving.anatomy.Witness``); 2: its
    # ordinary moments counted over all cars (a short drive's cars kept none); 3: each car's at a
    # phase of its own, and no car after its share (the same moments for any number of shards);
    # 4: a mixture's mode ends and weights at each moment (the late lane change's split); 5: the
    # mode ends' 1.5 s points (read along the road) and an affordance head's gap-ahead reading;
    # 6: no ordinary moment from a collision's last seconds (they are the collision's)
    "witness": 6,
    # 2: no view of a car slower than RecoveryConfig.min_speed_mps (their labels were absurd)
    "recovery": 2,
}


def versioned(kind: str) -> str:
    """The tag a kind of artifact puts in its key, e.g. ``"dataset-v3"``."""
    return f"{kind}-v{ARTIFACT_VERSIONS[kind]}"


#: The version of what the chapters write into their metrics (``metrics["schema"]``). Bump it when
#: a chapter's metrics change what a later chapter reads: metrics of another schema are not read
#: (:func:`read_metrics` says so and names the chapter to run again).
METRICS_SCHEMA = 2


def read_metrics(chapter: str, profile: str | None = None) -> dict[str, Any] | None:
    """A chapter's metrics, or ``None`` when it has not written any, when they are unreadable or
    do not match their digest, when they were written by older code (another
    :data:`METRICS_SCHEMA`: one line names the chapter to run again), or when ``profile`` is given
    and they were written under another profile."""
    path = outputs_dir() / "metrics" / f"{Path(chapter).stem}.json"
    if not path.exists():
        return None
    try:
        check_seal(path)
        metrics = load_json(path)
    except (OSError, ValueError) as err:
        print(
            f"[artifacts] {path.name} is unreadable ({err}); run chapter {Path(chapter).stem} again"
        )
        return None
    if profile is not None and metrics.get("profile") != profile:
        return None
    if metrics.get("schema") != METRICS_SCHEMA:
        print(
            f"[artifacts] {path.name} was written by older code (schema {metrics.get('schema')}, "
            f"now {METRICS_SCHEMA}); run chapter {Path(chapter).stem} again to use its results"
        )
        return None
    return metrics


def cached(
    path: Path | str,
    key: str,
    build: Callable[[], T],
    save: Callable[[Path, T, str], None],
    load: Callable[[Path], tuple[T, str]],
    *,
    verbose: bool = True,
) -> T:
    """Load the artifact at ``path`` if it carries ``key``; otherwise build, save and return it.

    ``save(path, value, key)`` must store the key inside the file (it is called inside an atomic
    write to a temporary path), and ``load(path) -> (value, stored_key)`` must read it back.
    A file that fails to load, does not match its digest (:func:`check_seal`) or whose key
    differs is rebuilt with a one-line message; the new file is sealed.
    """
    path = Path(path)
    if path.exists():
        try:
            check_seal(path)
            value, stored = load(path)
        except CorruptArtifact as err:
            if verbose:
                print(f"[artifacts] {err}; rebuilding")
        except Exception as err:  # a corrupt artifact of any kind is rebuilt, never trusted
            if verbose:
                print(f"[artifacts] {path.name} is unreadable ({type(err).__name__}); rebuilding")
        else:
            if stored == key:
                return value
            if verbose:
                print(f"[artifacts] {path.name} was made by other settings; rebuilding")
    value = build()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = _temp_beside(path, path.suffix)
    os.close(fd)
    try:
        save(Path(tmp), value, key)
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    seal(path)
    return value


def save_figure(fig: Figure, path: Path | str, dpi: int = 110) -> Path:
    """Save ``fig`` as PNG, atomically; shown inline in a notebook. Returns the path."""
    path = Path(path)
    with atomic_write(path) as f:
        fig.savefig(f, format="png", dpi=dpi, bbox_inches="tight")
    show_in_notebook(path)
    return path


def code_commit(where: Path) -> str:
    """The short commit of the git checkout holding ``where``; a copy without git's history (a
    zip, a lent machine's copy of the tree) says it in ``$E2E_LITE_COMMIT``, else "unknown"."""
    try:
        git = ["git", "rev-parse", "--short", "HEAD"]
        return subprocess.run(
            git, capture_output=True, text=True, check=True, cwd=where
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return os.environ.get("E2E_LITE_COMMIT", "unknown")
