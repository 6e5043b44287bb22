"""``python -m e2e_lite.course``: the chapters in order (:func:`e2e_lite.course.run.main`)."""

import sys

from .run import main

sys.exit(main())
