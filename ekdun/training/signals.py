"""Hold termination signals while a run folder's files are written together.

An epoch ends with three writes (checkpoint, ``log.csv``, the learned kernel file), each
atomic. A ``SIGTERM`` between two of them (a time budget's ``timeout``, a scheduler) left the
log one epoch behind the checkpoint. :func:`deferred_termination` records a ``SIGTERM`` or
``SIGINT`` that arrives during the writes and raises it again, to the handler that was there
before, once they are done.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

HELD = (signal.SIGTERM, signal.SIGINT)


@contextmanager
def deferred_termination() -> Iterator[None]:
    """Defer ``SIGTERM``/``SIGINT`` to the end of the block (main thread only: Python runs
    signal handlers there, whichever thread the system signalled; elsewhere a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = {s: signal.signal(s, lambda signum, _frame: pending.append(signum))
                for s in HELD}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for s in dict.fromkeys(pending):
            signal.raise_signal(s)
