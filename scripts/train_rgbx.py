"""Trains our small RGB<->X-family prior on `make_rgbx_data.py` shards and exports it.

    python scripts/train_rgbx.py --data=data/rgbx/train --work=data/rgbx_model            # all stages
    python scripts/train_rgbx.py --data=... --work=... --stage=unet --unet_steps=8000     # one stage

The model has RGB<->X's families and interface, only smaller (`jaxdistill/models/training/
recipe.py`); the stages (vae, latents, unet, export) are `jaxdistill/models/training/
train_prior.py`'s, whose docstring describes them, and this wrapper keeps the command working.
Every stage is deterministic from `--seed`, shows a progress bar with ETA, saves orbax
checkpoints in `--work` every `--ckpt_every` steps and on SIGINT/SIGTERM, and resumes from the
newest one when run again (a finished stage is skipped). The export needs the test extras
(torch 2.13.0 CPU, diffusers, transformers).
"""

from __future__ import annotations

import sys

from jaxdistill.models.training.train_prior import main

if __name__ == "__main__":
    sys.exit(main())
