"""The recipe of our RGB<->X-family prior: its networks and noise schedule, and the maps it learns.

The model has RGB<->X's families and interface, only smaller: AutoencoderKL (4 blocks, factor
8), UNet2DConditionModel with 8 input channels (noisy latent || photo latent), cross-attention on
CLIP text embeddings of the five RGB<->X prompts, v-prediction on scaled-linear betas rescaled to
zero terminal SNR. The dicts are the diffusers / transformers configs the export writes; our Flax
configs are read from them (`train_prior`), so changing one here changes the shipped model.
"""

from __future__ import annotations

MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")

# diffusers / transformers configs (what export writes); our Flax configs are read from them
VAE = dict(in_channels=3, out_channels=3, block_out_channels=(16, 32, 64, 64), layers_per_block=1,
           down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
           latent_channels=4, norm_num_groups=16, sample_size=128, scaling_factor=1.0)
UNET = dict(sample_size=16, in_channels=8, out_channels=4, block_out_channels=(32, 64, 64, 64), layers_per_block=1,
            norm_num_groups=16, attention_head_dim=(2, 4, 4, 4), cross_attention_dim=64, use_linear_projection=True,
            upcast_attention=True, down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
HEAD_CHANNELS = 16          # channels per attention head in every UNet block (UNET's 2/4/4/4 heads)


def unet_config(blocks=None, layers_per_block: int | None = None) -> dict:
    """UNET, or UNET with other block widths or layers per block (v2's options; None keeps
    UNET's): new widths get heads of `HEAD_CHANNELS` channels, as UNET's have. ValueError naming
    what a width must divide."""
    blocks = tuple(UNET["block_out_channels"]) if blocks is None else tuple(int(b) for b in blocks)
    layers = UNET["layers_per_block"] if layers_per_block is None else int(layers_per_block)
    if layers < 1:
        raise ValueError(f"UNet layers per block {layers}: give 1 or more")
    heads = UNET["attention_head_dim"]
    if blocks != tuple(UNET["block_out_channels"]):
        if len(blocks) != len(UNET["block_out_channels"]) or any(
                b <= 0 or b % HEAD_CHANNELS or b % UNET["norm_num_groups"] for b in blocks):
            raise ValueError(f"UNet blocks {blocks}: give {len(UNET['block_out_channels'])} widths, each a positive "
                             f"multiple of {HEAD_CHANNELS} (the channels of one attention head) and of "
                             f"{UNET['norm_num_groups']} (GroupNorm's groups)")
        heads = tuple(b // HEAD_CHANNELS for b in blocks)
    return dict(UNET, block_out_channels=blocks, layers_per_block=layers, attention_head_dim=heads)


TEXT = dict(hidden_size=64, intermediate_size=128, num_hidden_layers=2, num_attention_heads=4,
            max_position_embeddings=77, hidden_act="gelu", layer_norm_eps=1e-5, projection_dim=64)
SCHEDULER = {"_class_name": "DDIMScheduler", "_diffusers_version": "0.20.0", "beta_end": 0.012,
             "beta_schedule": "scaled_linear", "beta_start": 0.00085, "clip_sample": False,
             "num_train_timesteps": 1000, "prediction_type": "v_prediction", "set_alpha_to_one": False,
             "skip_prk_steps": True, "steps_offset": 1, "trained_betas": None,
             "rescale_betas_zero_snr": True, "timestep_spacing": "trailing"}

