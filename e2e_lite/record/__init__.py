"""The numbers of record: every paper row, L2, DAgger's rows and the controls, each learned row
trained with several seeds, every seed driving its miles on the sealed block of test roads
(:mod:`e2e_lite.driving.roads`), which nothing else drives (a quick smoke run drives open roads).

The record is a **pool of shares**, one command per job (``python -m e2e_lite.record --help``):

* ``run --seeds A-B`` trains and drives every row for training seeds ``A .. B``
  (:func:`~e2e_lite.record.run.record_share`) and writes one share file with what a pool checks
  (the recipes' commit, a key of the settings, the profile, the machine, each seed's roads and a
  digest of its content); ``run --seeds N`` runs seeds ``0 .. N-1`` on one machine and pools them;
* ``pool SHARE...`` merges shares (:func:`~e2e_lite.record.pool.pool`, which refuses a share that
  does not belong, naming its file) into ``docs/results/table1.json`` and renders it;
* ``plan`` prints the seeds and miles that reach the record's power, and what each costs;
* ``course-run OUTPUTS`` records what a full-profile course run printed
  (``docs/results/course_run.json``, rendered into ``docs/teaching.md``), ``quick-run OUTPUTS``
  what a quick one printed (``docs/results/quick_run.json``: what a class sees live).

:mod:`.rows` types the data, :mod:`.stats` holds the tests declared before a record runs,
:mod:`.pool` pools, :mod:`.run` runs. :mod:`e2e_lite.record.report` renders, and does nothing else.
"""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: the committed record of record, and what a full-profile course run printed
RECORD = ROOT / "docs" / "results" / "table1.json"
COURSE_RUN = ROOT / "docs" / "results" / "course_run.json"
#: what a quick-profile course run printed (what a class sees live)
QUICK_RUN = ROOT / "docs" / "results" / "quick_run.json"
