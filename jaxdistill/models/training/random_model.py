"""Random-weight RGB↔X folders in the real diffusers format (nothing downloaded).

`write_tiny_rgbx(folder)` creates UNet2DConditionModel / AutoencoderKL / CLIPTextModel with
diffusers and transformers (PyTorch CPU, seeded), `save_pretrained`s them as safetensors in
the zheng95z/rgb-to-x layout, with the tiny CLIP vocabulary (`vocabulary.py`) and RGB↔X's
scheduler config. The structure is the real one (4 UNet blocks, 3 with cross-attention, linear
projection, upcast attention, per-block head counts, in_channels 8; 23→2 text layers); only
widths shrink, or with the `RGBX_*` sizes nothing does (`scripts/make_random_rgbx.py --size=full`).
Used by the parity tests, `scripts/check_parity.py` and the benchmarks; needs the test extras
(torch, diffusers, transformers). `nchw` / `nhwc` move images between the two layouts.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxdistill.models.convert import MODEL_INDEX
from jaxdistill.models.training.vocabulary import write_tiny_clip_tokenizer

# The real RGB↔X sizes (docs/design.md §5), for scripts that time real-size networks.
RGBX_UNET = dict(
    sample_size=96, in_channels=8, out_channels=4, block_out_channels=(320, 640, 1280, 1280), layers_per_block=2,
    norm_num_groups=32, attention_head_dim=(5, 10, 20, 20), cross_attention_dim=1024, use_linear_projection=True,
    upcast_attention=True, down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
    up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3,
)
RGBX_VAE = dict(
    in_channels=3, out_channels=3, block_out_channels=(128, 256, 512, 512), layers_per_block=2,
    down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
    latent_channels=4, norm_num_groups=32, sample_size=768, scaling_factor=0.18215,
)
RGBX_TEXT = dict(
    hidden_size=1024, intermediate_size=4096, num_hidden_layers=23, num_attention_heads=16,
    max_position_embeddings=77, hidden_act="gelu", layer_norm_eps=1e-5, projection_dim=512, vocab_size=49408,
)
# The tiny sizes: the real structure (block types, layers per block, projections, upcast), small widths.
TINY_UNET = dict(RGBX_UNET, sample_size=16, block_out_channels=(32, 32, 64, 64), norm_num_groups=8,
                 attention_head_dim=(2, 2, 4, 4), cross_attention_dim=32)
TINY_VAE = dict(RGBX_VAE, block_out_channels=(16, 32, 32, 32), norm_num_groups=8, sample_size=64)
TINY_TEXT = dict(RGBX_TEXT, hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4,
                 projection_dim=32)
del TINY_TEXT["vocab_size"]   # set from the tiny vocabulary
RGBX_SCHEDULER = {
    "_class_name": "DDIMScheduler", "_diffusers_version": "0.20.0", "beta_end": 0.012,
    "beta_schedule": "scaled_linear", "beta_start": 0.00085, "clip_sample": False,
    "num_train_timesteps": 1000, "prediction_type": "v_prediction", "set_alpha_to_one": False,
    "skip_prk_steps": True, "steps_offset": 1, "trained_betas": None,
}


def _randomise(module, seed: int) -> None:
    """Every parameter random (norm scales and biases too), so no mapping error can hide."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if name.endswith("weight") and p.ndim == 1:  # norm scales around 1
                p.copy_(1.0 + 0.2 * torch.randn(p.shape, generator=gen))
            else:
                scale = 1.0 / max(1, p[0].numel()) ** 0.5 if p.ndim > 1 else 0.1
                p.copy_(scale * torch.randn(p.shape, generator=gen))


def build_tiny_models(seed: int = 0, unet=None, vae=None, text=None, bos: int = 2, eos: int = 2):
    """(unet, vae, text_encoder) PyTorch modules in eval mode, every parameter random."""
    import torch
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)
    u = UNet2DConditionModel(**(unet or TINY_UNET)).eval()
    v = AutoencoderKL(**(vae or TINY_VAE)).eval()
    cfg = dict(text or TINY_TEXT)
    cfg.setdefault("vocab_size", 600)
    t = CLIPTextModel(CLIPTextConfig(**cfg, bos_token_id=bos, eos_token_id=eos, pad_token_id=eos)).eval()
    for i, m in enumerate((u, v, t)):
        _randomise(m, seed + 101 * (i + 1))
    return u, v, t


def write_tiny_rgbx(folder: str | Path, seed: int = 0, pad_token: str = "!", unet=None, vae=None,
                    text=None) -> Path:
    """Write the tiny random RGB↔X folder (or other sizes: diffusers/transformers config dicts
    for `unet`, `vae`, `text`); returns its path. The tokenizer is always the tiny one."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_tiny_clip_tokenizer(folder / "tokenizer", pad_token=pad_token)
    vocab_size = len(json.loads((folder / "tokenizer" / "vocab.json").read_text()))
    text = dict(text or TINY_TEXT)
    text["vocab_size"] = max(text.get("vocab_size", 0), vocab_size)
    u, v, t = build_tiny_models(seed, unet=unet, vae=vae, text=text)
    u.save_pretrained(folder / "unet", safe_serialization=True)
    v.save_pretrained(folder / "vae", safe_serialization=True)
    t.save_pretrained(folder / "text_encoder", safe_serialization=True)
    (folder / "scheduler").mkdir(exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(RGBX_SCHEDULER, indent=2))
    (folder / "model_index.json").write_text(json.dumps(MODEL_INDEX, indent=2))
    return folder


def nchw(x) -> np.ndarray:
    """(B, H, W, C) -> (B, C, H, W), contiguous (JAX's image layout to PyTorch's)."""
    return np.ascontiguousarray(np.asarray(x).transpose(0, 3, 1, 2))


def nhwc(x) -> np.ndarray:
    """(B, C, H, W) -> (B, H, W, C), contiguous (PyTorch's image layout to JAX's)."""
    return np.ascontiguousarray(np.asarray(x).transpose(0, 2, 3, 1))
