"""bounded_map: input order, bounded in-flight work, errors propagate."""

import threading
import time

import pytest

from psfkit.numerics.parallel import bounded_map


def test_results_come_in_input_order_even_when_later_items_finish_first():
    delays = [0.05, 0.0, 0.03, 0.0, 0.01]

    def work(i: int) -> int:
        time.sleep(delays[i])
        return 10 * i

    assert list(bounded_map(work, range(5), workers=2)) == [(i, 10 * i) for i in range(5)]


def test_at_most_workers_plus_one_items_in_flight():
    started, lock, peak = [], threading.Lock(), [0]

    def items():
        for i in range(12):
            with lock:
                started.append(i)
            yield i

    consumed = 0
    for _index, _ in bounded_map(lambda i: time.sleep(0.005) or i, items(), workers=2):
        consumed += 1
        with lock:
            peak[0] = max(peak[0], len(started) - consumed)
    assert consumed == 12 and peak[0] <= 3


def test_an_exception_propagates():
    def work(i: int) -> int:
        if i == 3:
            raise RuntimeError("boom")
        return i

    with pytest.raises(RuntimeError, match="boom"):
        list(bounded_map(work, range(8), workers=2))
