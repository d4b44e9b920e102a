"""`threads.ordered_map`: results in order, a bounded number of items in flight, errors raised."""

from __future__ import annotations

import threading
import time

import pytest

from jaxdistill.threads import ordered_map


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_results_come_in_the_items_order(workers):
    def slow_square(x):                     # later items finish first
        time.sleep(0.002 * (5 - x % 5))
        return x * x
    assert list(ordered_map(slow_square, range(23), workers=workers)) == [x * x for x in range(23)]


def test_at_most_workers_plus_ahead_items_are_taken_before_one_is_yielded():
    taken, lock = [], threading.Lock()

    def items():
        for i in range(20):
            with lock:
                taken.append(i)
            yield i

    out = ordered_map(lambda x: x, items(), workers=2, ahead=1)
    seen = []
    for value in out:
        seen.append((value, len(taken)))
    assert [v for v, _ in seen] == list(range(20))
    assert all(n - v <= 3 for v, n in seen), seen          # item v yielded with at most v + 3 taken


def test_an_error_is_raised_at_its_item_and_no_item_is_submitted_after_it():
    started = []

    def fail_at_3(x):
        started.append(x)
        if x == 3:
            raise ValueError("item 3")
        return x

    got = []
    with pytest.raises(ValueError, match="item 3"):
        for value in ordered_map(fail_at_3, range(100), workers=2, ahead=1):
            got.append(value)
    assert got == [0, 1, 2] and max(started) <= 5              # 3 + workers + ahead - 1 at most
