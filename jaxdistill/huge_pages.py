"""Transparent huge pages for the host's large arrays: glibc's `glibc.malloc.hugetlb=1`.

XLA's CPU runtime takes each step's temporaries (about 0.85 GB in the default run's step) and
many of the set-up's and outputs' arrays fresh from malloc, which glibc serves with `mmap` for
large blocks; the kernel then faults them in 4 KiB at a time, every step again (about 0.23 M
page faults a step in the default run). With the tunable, glibc marks its mapped blocks
`madvise(MADV_HUGEPAGE)`, so the kernel faults them in 2 MiB at a time (docs/benchmarks.md §7).

Tunables are read by the dynamic loader when a process starts, so a process cannot set them for
itself: the commands that compute (`python -m jaxdistill.main`, `.estimate`, `.precompute`, and
`jaxdistill distill|estimate|precompute`) run themselves once more with the tunable added to
`GLIBC_TUNABLES` (`os.execv`: the same process id, interpreter options and arguments), before
anything but this package's `__init__` is imported. Nothing is done, and nothing re-run, when:

- the system is not Linux with glibc 2.35 or newer (older glibc has no such tunable);
- the kernel's transparent huge pages are not in `madvise` mode (`always`: the kernel uses them
  for every large mapping already; `never`: there are none to use);
- `GLIBC_TUNABLES` names `glibc.malloc.hugetlb` already (the user's value wins);
- `JAXDISTILL_HUGE_PAGES=0`.

`status()` says which applies (`metrics.json` records it). Results do not depend on it: the
same arrays, laid out at other addresses.
"""

from __future__ import annotations

import os
import re
import sys
from typing import Callable, Mapping

TUNABLE = "glibc.malloc.hugetlb"
MIN_GLIBC = (2, 35)            # the first glibc with the tunable
OFF = "JAXDISTILL_HUGE_PAGES"   # "0": keep glibc's defaults
THP_ENABLED = "/sys/kernel/mm/transparent_hugepage/enabled"


def thp_mode(path: str = THP_ENABLED) -> str | None:
    """The kernel's transparent huge page mode (`always`, `madvise` or `never`: the bracketed word
    of `path`), or None when it cannot be read (not Linux, or a kernel without them)."""
    try:
        with open(path) as f:
            match = re.search(r"\[(\w+)\]", f.read())
    except OSError:
        return None
    return match[1] if match else None


def glibc_version() -> tuple[int, int] | None:
    """(major, minor) of the C library when it is glibc, else None."""
    try:
        match = re.fullmatch(r"glibc (\d+)\.(\d+).*", os.confstr("CS_GNU_LIBC_VERSION") or "")
    except (AttributeError, ValueError, OSError):
        return None
    return (int(match[1]), int(match[2])) if match else None


def _named(tunables: str) -> dict[str, str]:
    """{name: value} of a `GLIBC_TUNABLES` value ("a.b.c=1:d.e.f=2")."""
    return dict(item.split("=", 1) for item in tunables.split(":") if "=" in item)


def why_not(environ: Mapping[str, str], glibc: tuple[int, int] | None, mode: str | None) -> str | None:
    """Why this process does not add the tunable (None: it does, or has it already)."""
    if environ.get(OFF) == "0":
        return f"{OFF}=0"
    if glibc is None:
        return "the C library is not glibc"
    if glibc < MIN_GLIBC:
        return f"glibc {glibc[0]}.{glibc[1]} has no {TUNABLE} (2.35 and newer)"
    if mode != "madvise":
        return (f"the kernel's transparent huge pages are '{mode}'" if mode else
                "the kernel has no transparent huge pages") + " (only 'madvise' needs the tunable)"
    return None


def tunables_to_add(environ: Mapping[str, str], glibc: tuple[int, int] | None, mode: str | None) -> str | None:
    """The `GLIBC_TUNABLES` value to run again with, or None when nothing is to change (see the
    module's docstring; a value the user gave for the tunable is kept)."""
    current = environ.get("GLIBC_TUNABLES", "")
    if TUNABLE in _named(current) or why_not(environ, glibc, mode):
        return None
    return f"{current}:{TUNABLE}=1" if current else f"{TUNABLE}=1"


def status(environ: Mapping[str, str] = os.environ, glibc: tuple[int, int] | None = ...,
           mode: str | None = ...) -> str:
    """One line: whether this process's large allocations are faulted in as huge pages, and why."""
    glibc = glibc_version() if glibc is ... else glibc
    mode = thp_mode() if mode is ... else mode
    given = _named(environ.get("GLIBC_TUNABLES", "")).get(TUNABLE)
    if given is not None and given != "1":
        return f"off: GLIBC_TUNABLES has {TUNABLE}={given}"
    if mode == "always":
        return "on: the kernel's transparent huge pages are 'always'"
    reason = why_not(environ, glibc, mode)
    if reason:
        return f"off: {reason}"
    return f"on: {TUNABLE}=1 with transparent huge pages in 'madvise' mode" if given == "1" else \
        f"off: {TUNABLE} is not set (the process was not started through a command that sets it)"


def run_again_with_huge_pages(environ: Mapping[str, str] = os.environ,
                              execve: Callable[[str, list[str], dict], None] = os.execve) -> bool:
    """Runs this process's command again, with the tunable added to `environ` (never returns
    then); False when nothing is to change, or when the new process could not be started (a
    warning on stderr; this one goes on without)."""
    value = tunables_to_add(environ, glibc_version(), thp_mode())
    argv = getattr(sys, "orig_argv", None)
    if value is None or not argv or not sys.executable:
        return False
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        execve(sys.executable, [sys.executable, *argv[1:]], {**environ, "GLIBC_TUNABLES": value})
    except OSError as err:
        print(f"warning: could not run again with {TUNABLE}=1 ({err}); going on without huge pages "
              f"(set {OFF}=0 to skip this)", file=sys.stderr)
        return False
    return True
