"""A bounded, order-keeping parallel map for per-position work on large images."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def default_workers() -> int:
    """Two threads where two cores exist (numpy, scipy.fft and OpenCV release the GIL)."""
    return min(2, os.cpu_count() or 1)


def bounded_map(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None
                ) -> Iterator[tuple[int, R]]:
    """Yield ``(index, fn(item))`` in input order (sums over them are bit-identical whatever
    the thread timing), with at most ``workers + 1`` items in flight (one worker: the calling
    thread). An exception cancels what is pending and propagates."""
    workers = default_workers() if workers is None else max(1, workers)
    if workers == 1:
        for index, item in enumerate(items):
            yield index, fn(item)
        return
    iterator = enumerate(items)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque[tuple[int, Future[R]]] = deque()
        try:
            for index, item in iterator:
                pending.append((index, pool.submit(fn, item)))
                if len(pending) > workers:
                    break
            while pending:
                index, future = pending.popleft()
                result = future.result()
                del future
                for next_index, item in iterator:   # refill one slot
                    pending.append((next_index, pool.submit(fn, item)))
                    break
                yield index, result
                del result
        finally:
            for _, future in pending:
                future.cancel()
