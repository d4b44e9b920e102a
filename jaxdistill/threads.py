"""Per-view NumPy work in a few threads: `ordered_map`, a bounded, in-order `map`.

The set-up's fragments, texel space and gather plans are NumPy on one view at a time: large array
operations release the GIL, so two threads use two cores. Unlike
`ThreadPoolExecutor.map`, which submits every item at once, `ordered_map` keeps at most
`workers + ahead` items in flight: a capture's views, read from files a view at a time, are
not all brought into memory together.
"""

from __future__ import annotations

import collections
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
R = TypeVar("R")

WORKERS = min(2, os.cpu_count() or 1)        # this project's machines: 2 cores; more gains little here


def ordered_map(fn: Callable[[T], R], items: Iterable[T], *, workers: int = WORKERS, ahead: int = 1) -> Iterator[R]:
    """fn(item) for each item, in order, computed by `workers` threads with at most
    `workers + ahead` items submitted and not yet yielded (one worker: in the calling thread). An
    exception of fn is raised where its item's result is yielded; no item is submitted after it
    (those already running finish first)."""
    if workers <= 1:
        yield from map(fn, items)
        return
    pending: collections.deque = collections.deque()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) > workers + ahead - 1:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:                              # an error or an abandoned generator: start nothing more
            for future in pending:
                future.cancel()


def view_bar(items: Iterable[T], desc: str, total: int | None = None) -> Iterable[T]:
    """`items` with a progress bar and ETA of views (the set-up's passes over every view)."""
    return tqdm(items, desc=desc, total=total, unit="view", dynamic_ncols=True)
