"""How our RGB<->X-family prior (jaxdistill/models/rgbx_rooms) is made, and the synthetic scenes
beside it. The scripts under scripts/ are thin command lines over these modules:

- `procedural_rooms`: one seed, one room (layout, furniture, parametric materials, lights);
  `room_geometry` and `textures` are its building blocks, shared with the embedded bedroom.
- `room_render`: a room path traced with exact intrinsics into a training shard
  (`scripts/make_rgbx_data.py`); `shards`: splits, seeds and the shard files.
- `recipe`, `stages`, `train_prior`, `export_model`: the networks, the resumable stage runner,
  the VAE / latents / UNet training and the diffusers export (`scripts/train_rgbx.py`);
  `vocabulary`: the tokenizer the prior trains with and ships.
- `heldout`: ground truth, trivial baseline and estimates in file space, for scoring the prior.
- `standins`, `scene_files`: stand-in per-view estimates and the files of a synthetic scene
  folder (`scripts/make_bedroom.py`, `scripts/make_room_scene.py`).
- `random_model`: random-weight RGB<->X folders at tiny or real size (parity checks, timings).

Layering: these modules use the scene, render, datasets and models stages, nothing above.
"""
