"""XLA flags the package sets for its CPU programs, before JAX starts its backends.

`--xla_cpu_experimental_ynn_fusion_type=` (empty: no YNNPACK library fusions). jaxlib 0.10's CPU
backend hands dots, convolutions and the element-wise and reduce operations around them to
YNNPACK fusions; for this package's networks and step XLA's own code is faster (measured side by
side, docs/benchmarks.md §1: the shipped model's UNet 1.4× and VAE decode 1.45× faster, the
default step 1.24×, the full-size step 1.19×). The flag names a CPU option only: GPU programs do
not read it.

A value the user gives in `XLA_FLAGS` for the same flag wins; `JAXDISTILL_XLA_FLAGS=0` sets none
(jaxlib's own defaults, as `scripts/bench_xla_flags.py` compares). XLA reads `XLA_FLAGS` once, when
the first backend starts: `import jaxdistill` sets it, so it applies unless JAX computed something
before the package was imported (then nothing is changed, and `apply` says so).
"""

from __future__ import annotations

import os
import sys
from typing import MutableMapping

FLAGS = ("--xla_cpu_experimental_ynn_fusion_type=",)


def with_flags(xla_flags: str, flags=FLAGS) -> str:
    """`xla_flags` (an `XLA_FLAGS` value) with each of `flags` appended unless it names that flag already."""
    given = {f.split("=", 1)[0] for f in xla_flags.split()}
    added = [f for f in flags if f.split("=", 1)[0] not in given]
    return " ".join([xla_flags.strip(), *added]).strip()


def backends_started() -> bool:
    """Whether JAX has started its backends in this process (XLA_FLAGS has then been read)."""
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge
    return bool(getattr(xla_bridge, "_backends", None))


def apply(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Sets the flags in `environ["XLA_FLAGS"]`; False when `JAXDISTILL_XLA_FLAGS=0` asks for none, or
    (with a warning) when `environ` is this process's and its backends already run."""
    if environ.get("JAXDISTILL_XLA_FLAGS") == "0":
        return False
    if environ is os.environ and backends_started():
        import warnings
        warnings.warn(f"jaxdistill was imported after JAX started its backends: XLA_FLAGS {' '.join(FLAGS)} was not "
                      "applied (import jaxdistill before computing with JAX; docs/benchmarks.md §1)", stacklevel=3)
        return False
    environ["XLA_FLAGS"] = with_flags(environ.get("XLA_FLAGS", ""))
    return True
