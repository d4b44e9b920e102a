"""`jaxdistill import` as a script: imports a dataset as a jaxdistill scene folder.

The logic lives in `jaxdistill/import_scene.py` (its docstring lists the formats and options);
this wrapper keeps `python scripts/import_scene.py --format=... --path=... --out=...` working.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxdistill.import_scene import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
