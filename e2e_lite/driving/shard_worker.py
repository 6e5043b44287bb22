"""A shard process of :func:`~e2e_lite.driving.evaluation.evaluate` (see
:mod:`e2e_lite.driving.parallel`; started by it, not for people).

Reads its job from standard input and writes its messages to standard output as length-prefixed
pickles; anything the driven code prints goes to standard error instead.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys


def main() -> None:
    """Keep the binary standard output for messages, send stray prints to standard error, run.

    Ctrl-C is the parent's to handle: a worker ignores it (the parent kills the workers of an
    interrupted evaluation, and an idle worker ends when the parent's pipe closes), so a Ctrl-C
    prints no traceback per worker."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    outbox = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # C-level and Python prints of the driven code now go to stderr
    sys.stdout = sys.stderr
    from .parallel import shard_worker  # (here: what its import prints goes to stderr)

    shard_worker(sys.stdin.buffer, outbox)
    with contextlib.suppress(OSError):  # (the parent may be gone)
        outbox.close()


if __name__ == "__main__":
    main()
