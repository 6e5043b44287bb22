"""What a full-profile course run printed, recorded from its outputs folder (``python -m
e2e_lite.record course-run OUTPUTS`` writes ``docs/results/course_run.json``, which the report
renders into ``docs/teaching.md``), with what the machine needed to run it; and what a quick one
printed (``quick-run OUTPUTS``: what a class sees live)."""

from __future__ import annotations

import json
import os
import platform
import re
from pathlib import Path
from typing import Any

import torch

from ..artifacts import code_commit
from ..course.estimate import cpu_name
from ..course.run import TIMES_FILE


def folder_bytes(path: Path) -> int:
    """The size of every file under ``path`` [bytes] (hard links counted once)."""
    seen, size = set(), 0
    for p in path.rglob("*"):
        if p.is_file() and not p.is_symlink():
            st = p.stat()
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                size += st.st_size
    return size


def peak_memory_kib(time_log: Path) -> int:
    """The largest resident set of any one process of the run [KiB], the largest of the
    ``/usr/bin/time -v`` reports in ``time_log`` (a run resumed across sittings writes one each)."""
    found = re.findall(r"Maximum resident set size \(kbytes\): (\d+)", time_log.read_text())
    if not found:
        raise ValueError(f"{time_log}: no '/usr/bin/time -v' report in it")
    return max(int(k) for k in found)


def operating_system() -> str:
    """The system the run and the tests ran on, e.g. 'Debian GNU/Linux 12 (bookworm), x86_64'."""
    try:
        name = platform.freedesktop_os_release()["PRETTY_NAME"]
    except (OSError, KeyError):
        name = f"{platform.system()} {platform.release()}"
    return f"{name}, {platform.machine()}"


def machine_needs(
    outputs: Path,
    time_log: Path | None = None,
    quick_outputs: Path | None = None,
    venv: Path | None = None,
    downloads: Path | None = None,
) -> dict[str, Any]:
    """What the run needed, each measured where its source is given: the full and the quick
    course's outputs folders, the largest process (from a ``/usr/bin/time -v`` log), the venv
    and the packages ``pip download`` fetched for it [bytes, KiB]; and the system and Python."""
    needs: dict[str, Any] = {
        "system": operating_system(),
        "python": platform.python_version(),
        "outputs_bytes": folder_bytes(outputs),
    }
    if time_log is not None:
        needs["peak_memory_kib"] = peak_memory_kib(time_log)
    if quick_outputs is not None:
        needs["quick_outputs_bytes"] = folder_bytes(quick_outputs)
    if venv is not None:
        needs["venv_bytes"] = folder_bytes(venv)
    if downloads is not None:
        needs["download_bytes"] = folder_bytes(downloads)
    return needs


def course_run_record(outputs: Path, **needs: Path | None) -> dict[str, Any]:
    """A full-profile run of the course, read from its outputs folder: each chapter's wall time
    (``course_times.json``) and the headline figures it wrote (``metrics/<chapter>.json``), with
    the machine, torch and what it needed (:func:`machine_needs`, given ``needs``' sources). A
    chapter whose metrics are another profile's is refused."""

    times = json.loads((outputs / TIMES_FILE).read_text())
    chapters = {}
    for stem, entry in sorted(times.items()):
        path = outputs / "metrics" / f"{stem}.json"
        metrics = json.loads(path.read_text()) if path.exists() else {}
        if metrics.get("profile") not in (None, "full"):
            raise ValueError(f"{path}: not a full-profile run ({metrics.get('profile')})")
        headline = {k: v for k, v in metrics.get("headline", {}).items() if v is not None}
        chapters[stem] = {
            "minutes": round(entry["seconds"] / 60.0, 1),
            "complete": entry.get("complete", False),
            "headline": headline,
        }
    found = machine_needs(outputs, **needs)
    return {
        "machine": f"{cpu_name()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "outputs_bytes": found.pop("outputs_bytes"),
        "needs": found,
        "chapters": chapters,
    }


def quick_run_record(outputs: Path, root: Path | None = None) -> dict[str, Any]:
    """A quick-profile course run, read from its outputs folder: the headline figures each
    chapter wrote (``metrics/<chapter>.json``), with the machine, torch and the commit of the
    code in ``root`` (None where it cannot be told). A chapter whose metrics are another profile's is
    refused."""
    chapters = {}
    for path in sorted((outputs / "metrics").glob("[0-9][0-9]_*.json")):
        metrics = json.loads(path.read_text())
        if metrics.get("profile") != "quick":
            raise ValueError(f"{path}: not a quick-profile run ({metrics.get('profile')})")
        chapters[path.stem] = {
            k: v for k, v in metrics.get("headline", {}).items() if v is not None
        }
    commit = code_commit(root or Path.cwd())
    return {
        "machine": f"{cpu_name()}, {os.cpu_count()} cores",
        "torch": torch.__version__,
        "commit": None if commit == "unknown" else commit,
        "chapters": chapters,
    }
