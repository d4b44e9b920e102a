"""Transparent huge pages for the host's large arrays: glibc's `glibc.malloc.hugetlb=1`.

XLA's CPU runtime takes each step's temporaries (about 0.85 GB in the default run's step) and
many of the set-up's and outputs' arrays fresh from malloc, which glibc serves with `mmap` for
large blocks; the kernel then faults them in 4 KiB at a time, every step again (about 0.23 M
page faults a step in the default run). With the tunable, glibc marks its mapped blocks
`madvise(MADV_HUGEPAGE)`, so the kernel faults them in 2 MiB at a time (docs/benchmarks.md §7).

Tunables are read by the dynamic loader when a process starts, so a process cannot set them for
itself: the commands that compute, started as commands (`python -m jaxdistill.main`, `.estimate`,
`.precompute`, `python -m jaxdistill distill|estimate|precompute`, the `jaxdistill` script, or
one of those modules' files run as a script), run themselves once more with the tunable added to
`GLIBC_TUNABLES` (`os.execve`: the same process id, interpreter options and arguments), before
anything but this package's `__init__` is imported. Nothing is done, and nothing re-run, when:

- the process was started by another program that runs the module (a notebook's `%run -m`,
  `python -m cProfile -m jaxdistill.main`, `runpy` in a script of yours, `python -c`): its
  command line is not this package's command, so it is left alone (set the tunable yourself);
- the system is not Linux with glibc 2.35 or newer (older glibc has no such tunable);
- the kernel's transparent huge pages are not in `madvise` mode (`always`: the kernel uses them
  for every large mapping already; `never`: there are none to use);
- `GLIBC_TUNABLES` names `glibc.malloc.hugetlb` already (the user's value wins);
- `JAXDISTILL_HUGE_PAGES=0`;
- the process was run again already (`RAN_AGAIN` in its environment: a loader that clears
  `GLIBC_TUNABLES`, as glibc does for setuid programs, cannot make it run itself forever).

`status()` says which applies (`metrics.json` records it). It reports glibc's malloc: an
allocator swapped in with `LD_PRELOAD` (tcmalloc, jemalloc) does not read the tunable. Results
do not depend on it: the same arrays, laid out at other addresses.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Callable, Mapping, Sequence

TUNABLE = "glibc.malloc.hugetlb"
MIN_GLIBC = (2, 35)            # the first glibc with the tunable
OFF = "JAXDISTILL_HUGE_PAGES"   # "0": keep glibc's defaults
RAN_AGAIN = "JAXDISTILL_HUGE_PAGES_RAN_AGAIN"    # set in the process run again: never a second time
THP_ENABLED = "/sys/kernel/mm/transparent_hugepage/enabled"
MODULES = ("jaxdistill", "jaxdistill.main", "jaxdistill.estimate", "jaxdistill.precompute")
_FILES = ("main.py", "estimate.py", "precompute.py", "__main__.py")
_OPTIONS_WITH_VALUE = ("--check-hash-based-pycs",)


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


def is_package_command(argv: Sequence[str]) -> bool:
    """Whether an interpreter command line (`sys.orig_argv`) runs one of this package's commands:
    `-m` one of `MODULES`, the `jaxdistill` script, or one of the modules' own files; not `-c`,
    stdin, or another program that runs the module in turn (`-m cProfile`, `-m ipykernel_launcher`).
    Short options are read as Python reads them: grouped (`-Im`), and `-c`, `-m`, `-W`, `-X` take
    the rest of their group or the next argument as their value (`-Wdefault`, `-X utf8`)."""
    args = list(argv[1:])
    i = 0
    while i < len(args):
        arg, i = args[i], i + 1
        if arg == "-":
            return False                        # the program comes from stdin
        if arg.startswith("--"):
            i += arg in _OPTIONS_WITH_VALUE     # a long option (its value is the next argument)
            continue
        if arg.startswith("-"):
            for j, letter in enumerate(arg[1:], start=1):
                if letter in "cmWX":
                    value = arg[j + 1:]
                    if not value and i < len(args):
                        value, i = args[i], i + 1
                    if letter == "c":
                        return False
                    if letter == "m":
                        return value in MODULES
                    break                       # -W or -X: its value is read
            continue
        script = Path(arg)
        return script.name == "jaxdistill" or (script.name in _FILES and script.resolve().parent ==
                                               Path(__file__).resolve().parent)
    return False


def _named(tunables: str) -> dict[str, str]:
    """{name: value} of a `GLIBC_TUNABLES` value ("a.b.c=1:d.e.f=2")."""
    return dict(item.strip().split("=", 1) for item in tunables.split(":") if "=" in item)


def _unusable(glibc: tuple[int, int] | None, mode: str | None) -> str | None:
    """Why glibc's tunable would do nothing here (None: it works)."""
    if glibc is None:
        return "the C library is not glibc"
    if glibc < MIN_GLIBC:
        return f"glibc {glibc[0]}.{glibc[1]} has no {TUNABLE} (2.35 and newer)"
    if mode != "madvise":
        return (f"the kernel's transparent huge pages are '{mode}'" if mode else
                "the kernel has no transparent huge pages") + " (only 'madvise' needs the tunable)"
    return None


def why_not(environ: Mapping[str, str], glibc: tuple[int, int] | None, mode: str | None) -> str | None:
    """Why this process would not add the tunable (None: it would, or has it already)."""
    if environ.get(OFF) == "0":
        return f"{OFF}=0"
    return _unusable(glibc, mode)


def tunables_to_add(environ: Mapping[str, str], glibc: tuple[int, int] | None, mode: str | None) -> str | None:
    """The `GLIBC_TUNABLES` value to run again with, or None when nothing is to change (see the
    module's docstring; a value the user gave for the tunable is kept)."""
    current = environ.get("GLIBC_TUNABLES", "").strip().rstrip(":")
    if environ.get(RAN_AGAIN) or TUNABLE in _named(current) or why_not(environ, glibc, mode):
        return None
    return f"{current}:{TUNABLE}=1" if current else f"{TUNABLE}=1"


def status(environ: Mapping[str, str] = os.environ, glibc: tuple[int, int] | None = ...,
           mode: str | None = ...) -> str:
    """One line, "on: ...", "off: ..." or "as given: ...": whether this process's large allocations
    are faulted in as huge pages, and why."""
    glibc = glibc_version() if glibc is ... else glibc
    mode = thp_mode() if mode is ... else mode
    given = _named(environ.get("GLIBC_TUNABLES", "")).get(TUNABLE)
    if mode == "always":                  # the kernel's own choice, whatever glibc is told
        return "on: the kernel's transparent huge pages are 'always'"
    if given == "0":
        return f"off: GLIBC_TUNABLES has {TUNABLE}=0"
    if given is not None and given != "1":             # e.g. 2: hugetlbfs pages the system set aside
        return f"as given: GLIBC_TUNABLES has {TUNABLE}={given}"
    if given == "1":
        reason = _unusable(glibc, mode)
        return f"off: {reason}" if reason else f"on: {TUNABLE}=1 with transparent huge pages in 'madvise' mode"
    reason = why_not(environ, glibc, mode)
    if reason:
        return f"off: {reason}"
    if environ.get(RAN_AGAIN):
        return f"off: run again with {TUNABLE}=1, but GLIBC_TUNABLES was cleared at start-up (a setuid or " \
               "capability-raised interpreter, or a wrapper that resets the environment)"
    return f"off: {TUNABLE} is not set (the process was not started as a jaxdistill command that sets it)"


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):
            pass


def run_again_with_huge_pages(environ: Mapping[str, str] = os.environ,
                              execve: Callable[[str, list[str], dict], None] = os.execve) -> bool:
    """Runs this process's command again, with the tunable added to `environ` (never returns
    then); False when nothing is to change, when the process is not a jaxdistill command
    (`is_package_command`), or when the new process could not be started (a warning on stderr;
    this one goes on without)."""
    value = tunables_to_add(environ, glibc_version(), thp_mode())
    argv = getattr(sys, "orig_argv", None)
    if value is None or not argv or not sys.executable or not is_package_command(argv):
        return False
    _flush()
    try:
        execve(sys.executable, [sys.executable, *argv[1:]], {**environ, "GLIBC_TUNABLES": value, RAN_AGAIN: "1"})
    except (OSError, ValueError) as err:
        print(f"warning: could not run again with {TUNABLE}=1 ({err}); going on without huge pages "
              f"(set {OFF}=0 to skip this)", file=sys.stderr)
        return False
    return True
