"""Hold termination signals while a run folder's files are written together, so that a
``SIGTERM`` between the epoch's atomic writes cannot leave them out of step.
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
