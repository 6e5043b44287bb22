"""``python -m e2e_lite.exercises check NN.k``: :func:`e2e_lite.exercises.checks.main`."""

import sys

from .checks import main

sys.exit(main())
