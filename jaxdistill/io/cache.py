"""Where the project caches what it computes once per machine (ray casts, per-view arrays,
parameter shapes): $JAXDISTILL_CACHE, else $XDG_CACHE_HOME/jaxdistill, else ~/.cache/jaxdistill."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """$JAXDISTILL_CACHE, else $XDG_CACHE_HOME/jaxdistill, else ~/.cache/jaxdistill."""
    if "JAXDISTILL_CACHE" in os.environ:
        return Path(os.environ["JAXDISTILL_CACHE"])
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache"))
    return base / "jaxdistill"
