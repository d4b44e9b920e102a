"""The main job's malloc settings: freed memory kept in the process, not faulted in again each step.

XLA's CPU runtime allocates a step's buffers (texel-sized arrays of 100-200 MB and the networks'
activations) with malloc from its worker threads and frees them when the step ends. glibc gives
each such thread its own arena, whose large blocks are fresh `mmap`s, returned to the system on
free: every step the kernel maps and zeroes the same memory again, page by page. On the default
bedroom run that was 0.23 M page faults and about 0.5 s of system time a step, a quarter of the
step's CPU time (`scripts/bench_malloc.py`, docs/benchmarks.md §7).

`keep_freed_memory` asks glibc (`mallopt`) for one arena, blocks up to 1 GiB from the heap rather
than from `mmap`, and the heap's free top kept up to 2 GiB: a step's buffers are then reused.
The price is memory the process keeps after a peak (measured: +0.3-0.5 GB of peak RSS on the
bedroom run). The main job calls it first thing (before XLA starts its threads), unless
`JAXDISTILL_MALLOC=system` is set. Elsewhere than glibc it does nothing and says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

from absl import logging

M_TRIM_THRESHOLD = -1          # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8
SETTINGS = ((M_ARENA_MAX, 1), (M_MMAP_THRESHOLD, 1 << 30), (M_TRIM_THRESHOLD, (1 << 31) - 1))   # C ints
ENV = "JAXDISTILL_MALLOC"        # "system": leave malloc as it is


def keep_freed_memory(environ=os.environ) -> bool:
    """Applies `SETTINGS` with glibc's mallopt; True when all were accepted. False (with a log line)
    when `JAXDISTILL_MALLOC=system`, or the C library is not glibc or refuses one."""
    if environ.get(ENV, "").strip().lower() == "system":
        logging.info("%s=system: malloc left as it is", ENV)
        return False
    libc = _glibc()
    if libc is None:
        logging.info("malloc left as it is: the C library is not glibc (no mallopt)")
        return False
    refused = [name for (name, value) in SETTINGS if libc.mallopt(ctypes.c_int(name), ctypes.c_int(value)) != 1]
    if refused:
        logging.warning("glibc refused mallopt parameter(s) %s: freed memory may be faulted in again each step",
                        refused)
        return False
    return True


def _glibc():
    """The process's C library when it is glibc (it has `gnu_get_libc_version` and `mallopt`), else None."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    if not (hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")):
        return None
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    libc.mallopt.restype = ctypes.c_int
    return libc
