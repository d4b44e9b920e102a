"""Exports the trained prior as a diffusers folder and checks that our loader reads it back.

`export` writes model_index.json, unet/, vae/, text_encoder/, tokenizer/ and scheduler/ with
diffusers' and transformers' own `save_pretrained` from our Flax weights (`torch_state` inverts
`jaxdistill.models.convert`'s naming and layout rules), so diffusers, transformers and
`convert.load_rgbx` all read the same networks; `check_export` reads the folder back with our
loader and requires exactly the trained weights (rounded to the export dtype). Needs the test
extras (torch 2.13.0 CPU, diffusers, transformers).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import numpy as np

from jaxdistill.models.tokenizer import load_tokenizer
from jaxdistill.models.training import recipe


def torch_state(flax_params: dict, torch_shapes: dict[str, tuple]) -> dict:
    """The PyTorch state dict (name -> float32 array) of our Flax params, by the inverse of
    `convert.convert_state_dict`'s rules: conv kernel HWIO -> OIHW, linear kernel transposed,
    scale/embedding -> weight. Keys come from the PyTorch model itself."""
    from flax import traverse_util

    from jaxdistill.models.convert import _IGNORED_KEYS, _normalise_key, flax_path

    flat = traverse_util.flatten_dict(flax_params)
    out = {}
    for key, shape in torch_shapes.items():
        norm = _normalise_key(key)
        if norm in _IGNORED_KEYS:
            continue
        path = flax_path(norm)
        module, leaf = path[:-1], path[-1]
        if leaf == "weight":
            leaf = next(n for n in ("kernel", "scale", "embedding") if module + (n,) in flat)
        array = np.asarray(flat[module + (leaf,)], np.float32)
        if leaf == "kernel":
            array = array.transpose(3, 2, 0, 1) if array.ndim == 4 else array.T
        assert tuple(array.shape) == tuple(shape), (key, array.shape, shape)
        out[key] = np.ascontiguousarray(array)
    return out


def export(folder: Path, tokenizer_dir: Path, unet_params, vae_params, text_params, *, scaling: float,
           unet: dict = recipe.UNET, vae: dict = recipe.VAE, text: dict = recipe.TEXT, dtype: str = "float32") -> None:
    """Writes the diffusers folder with diffusers/transformers' own save_pretrained (configs are
    the diffusers/transformers dicts; `scaling` becomes the VAE's scaling_factor); weights
    stored as `dtype` (float16 halves the folder; loaders compute in float32 either way)."""
    import torch
    from diffusers import AutoencoderKL as TorchVAE
    from diffusers import UNet2DConditionModel
    from transformers import CLIPTextConfig as TorchTextConfig
    from transformers import CLIPTextModel

    from jaxdistill.models.convert import _IGNORED_KEYS, MODEL_INDEX, _normalise_key

    folder.mkdir(parents=True, exist_ok=True)
    tok = load_tokenizer(tokenizer_dir)
    text_config = TorchTextConfig(**text, vocab_size=len(tok.backend.get_vocab()), bos_token_id=tok.bos_id,
                                  eos_token_id=tok.eos_id, pad_token_id=tok.pad_id)
    for name, model, params in (("unet", UNet2DConditionModel(**unet), unet_params),
                                ("vae", TorchVAE(**dict(vae, scaling_factor=scaling)), vae_params),
                                ("text_encoder", CLIPTextModel(text_config), text_params)):
        shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
        state = {k: torch.tensor(v) for k, v in torch_state(params["params"], shapes).items()}
        missing, unexpected = model.load_state_dict(state, strict=False)
        missing = [k for k in missing if _normalise_key(k) not in _IGNORED_KEYS]
        if missing or unexpected:
            raise RuntimeError(f"{name}: missing {missing[:5]}, unexpected {unexpected[:5]}")
        model = model.eval().to(getattr(torch, dtype))
        model.save_pretrained(folder / name, safe_serialization=True)
    shutil.copytree(tokenizer_dir, folder / "tokenizer", dirs_exist_ok=True)
    (folder / "scheduler").mkdir(exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(recipe.SCHEDULER, indent=2))
    (folder / "model_index.json").write_text(json.dumps(MODEL_INDEX, indent=2))


def check_export(folder: Path, unet_params, vae_params, text_params, dtype: str = "float32") -> None:
    """Our loader reads the exported folder back to exactly the trained parameters (rounded to
    the export dtype)."""
    from jaxdistill.models.convert import load_rgbx

    loaded = load_rgbx(folder)
    for part, params in (("unet", unet_params), ("vae", vae_params), ("text_encoder", text_params)):
        a, b = jax.tree.leaves(loaded.params[part]), jax.tree.leaves(params)
        assert len(a) == len(b) and all(np.array_equal(np.asarray(x), np.asarray(y).astype(dtype).astype(np.float32))
                                        for x, y in zip(a, b)), part
