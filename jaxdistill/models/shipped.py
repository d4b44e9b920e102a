"""The RGB<->X-family model shipped in the package: where it is and what it is.

`jaxdistill/models/rgbx_rooms/` is a diffusers folder (model_index.json, unet/, vae/,
text_encoder/, tokenizer/, scheduler/) written by `scripts/train_rgbx.py` from our own rendered
rooms (`scripts/make_rgbx_data.py`); its model card is the folder's README.md and
`jaxdistill_model.json` holds its name, version and training summary. It has RGB<->X's
architecture and interface, so it loads by the same path as the real weights
(`convert.load_rgbx`); it is a small stand-in for demos, tests and method studies, not a
general estimator for photos.
"""

from __future__ import annotations

import json
from pathlib import Path

SHIPPED_DIR = Path(__file__).resolve().parent / "rgbx_rooms"
INFO_FILE = "jaxdistill_model.json"


def shipped_folder() -> Path | None:
    """The shipped model's folder, or None when this installation lacks it (no model_index.json)."""
    return SHIPPED_DIR if (SHIPPED_DIR / "model_index.json").is_file() else None


def model_info(folder: str | Path) -> dict:
    """{"name", "version", ...} of a weights folder: the shipped model's jaxdistill_model.json,
    else {"name": <folder name>, "source": "user"} for weights a user brought (e.g. zheng95z/rgb-to-x)."""
    folder = Path(folder)
    path = folder / INFO_FILE
    if path.is_file():
        info = json.loads(path.read_text())
        return {"name": info.get("name", folder.name), "version": info.get("version"), "source": "shipped"
                if folder.resolve() == SHIPPED_DIR.resolve() else "jaxdistill-trained", "folder": str(folder)}
    return {"name": folder.name, "source": "user", "folder": str(folder)}
