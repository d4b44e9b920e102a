"""XLA flags the package sets for its CPU programs, before JAX starts its backends.

`--xla_cpu_experimental_ynn_fusion_type=` (empty: no YNNPACK library fusions). jaxlib 0.10's CPU
backend hands dots, convolutions and the element-wise and reduce operations around them to
YNNPACK fusions; for this package's networks and step XLA's own code is faster (measured side by
side on jaxlib 0.10.2, `scripts/bench_xla_flags.py`, docs/benchmarks.md §1: the shipped model's
UNet 1.22× faster at batch 16 and 1.65× at 40, its VAE decode 1.63×, the default run's step with
the prior's pass 1.35×). The flag names a CPU option only: GPU programs do not read it.

Only jaxlib from `MIN_JAXLIB` on gets it: XLA aborts on a flag its build does not know, and the
flag is newer than the oldest jaxlib the package accepts. A value the user gives in `XLA_FLAGS`
for the same flag wins; `JAXDISTILL_XLA_FLAGS=0` sets none (jaxlib's own defaults, as
`scripts/bench_xla_flags.py` compares). XLA reads `XLA_FLAGS` once, when the first backend
starts: `import jaxdistill` sets it, so it applies unless JAX computed something before the
package was imported (then nothing is changed, and `apply` warns).
"""

from __future__ import annotations

import os
import re
import sys
from typing import MutableMapping

FLAGS = ("--xla_cpu_experimental_ynn_fusion_type=",)
MIN_JAXLIB = (0, 10)          # the first jaxlib measured with it (0.10.2); older ones are left as they are


def with_flags(xla_flags: str, flags=FLAGS) -> str:
    """`xla_flags` (an `XLA_FLAGS` value) with each of `flags` appended unless it names that flag already."""
    given = {f.split("=", 1)[0] for f in xla_flags.split()}
    added = [f for f in flags if f.split("=", 1)[0] not in given]
    return " ".join([xla_flags.strip(), *added]).strip()


def jaxlib_version() -> tuple[int, int] | None:
    """The installed jaxlib's (major, minor) from its metadata, or None when it cannot be read."""
    from importlib import metadata
    try:
        match = re.match(r"(\d+)\.(\d+)", metadata.version("jaxlib"))
    except metadata.PackageNotFoundError:
        return None
    return (int(match[1]), int(match[2])) if match else None


def backends_started() -> bool:
    """Whether JAX has started its backends in this process (XLA_FLAGS has then been read)."""
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(started()) if started is not None else bool(getattr(xla_bridge, "_backends", None))


def apply(environ: MutableMapping[str, str] = os.environ, version: tuple[int, ...] | None = ...) -> bool:
    """Sets the flags in `environ["XLA_FLAGS"]`; True when they are there afterwards. False when
    `JAXDISTILL_XLA_FLAGS=0` asks for none, when jaxlib is older than `MIN_JAXLIB` (or unknown),
    or (with a warning) when `environ` is this process's and its backends already run."""
    if environ.get("JAXDISTILL_XLA_FLAGS") == "0":
        return False
    version = jaxlib_version() if version is ... else version
    if version is None or version < MIN_JAXLIB:
        return False
    current = environ.get("XLA_FLAGS", "")
    wanted = with_flags(current)
    if wanted == current:                 # given already (by the user, or inherited from a parent process)
        return True
    if environ is os.environ and backends_started():
        import warnings
        warnings.warn(f"jaxdistill was imported after JAX started its backends: XLA_FLAGS {' '.join(FLAGS)} was not "
                      "applied (import jaxdistill before computing with JAX; docs/benchmarks.md §1)", stacklevel=3)
        return False
    environ["XLA_FLAGS"] = wanted
    return True
