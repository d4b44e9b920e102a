"""Training data for our RGB<->X-family prior: procedural rooms path traced with exact intrinsics.

    python scripts/make_rgbx_data.py --out=data/rgbx/train --rooms=400            # resumable
    python scripts/make_rgbx_data.py --out=data/rgbx/heldout --split=heldout --rooms=8

Each room (`jaxdistill/models/training/procedural_rooms.py`) becomes one shard
`room_<seed>.npz` of its views: photo, albedo, normal, roughness, metallic, irradiance and a
valid mask, all uint8 (`jaxdistill/models/training/room_render.py` says how each is made,
`shards.py` the file format). Shards are written atomically; a rerun skips rooms already
written, so a killed run resumes. Training rooms use seeds 0, 1, ...; held-out rooms seeds
1_000_000 + i; the embedded bedroom is a different generator and never appears. Uses Mitsuba's
`llvm_ad_rgb` variant when LLVM 19 is installed (`apt-get install libllvm19`), else `scalar_rgb`
(slower, same images up to noise).
"""

from __future__ import annotations

import sys

from jaxdistill.models.training.room_render import main

if __name__ == "__main__":
    sys.exit(main())
