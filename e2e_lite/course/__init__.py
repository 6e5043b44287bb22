"""The course's own tools, above the library: running the chapters in order (:mod:`.run`,
``python -m e2e_lite.course``), a chapter run cell by cell (:mod:`.transcript`), the book of one
full run (:mod:`.book`, ``python -m e2e_lite.course.book``), how long a run should take here
(:mod:`.estimate`) and the benchmarks (:mod:`.bench`, ``python -m e2e_lite.course.bench NAME``)."""
