"""What a full-profile course run printed, recorded from its outputs folder (``python -m
e2e_lite.record course-run OUTPUTS`` writes ``docs/results/course_run.json``, which the report
renders into ``docs/teaching.md``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any


def course_run_record(outputs: Path) -> dict[str, Any]:
    """A full-profile run of the course, read from its outputs folder: each chapter's wall time
    (``course_times.json``) and the headline figures it wrote (``metrics/<chapter>.json``), with
    the machine, torch and the outputs folder's size on disk [bytes]. A chapter whose metrics
    are another profile's is refused."""
    import torch

    from ..course import TIMES_FILE
    from ..estimate import cpu_name

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
    machine = f"{cpu_name()}, {os.cpu_count()} cores"
    size = sum(p.stat().st_size for p in outputs.rglob("*") if p.is_file())
    return {
        "machine": machine,
        "torch": torch.__version__,
        "outputs_bytes": size,
        "chapters": chapters,
    }
