"""AutoencoderKL (the Stable Diffusion VAE) encoder and decoder, Flax linen, NHWC.

Images are (B, H, W, 3) in [-1, 1] (the colour space the caller chose; RGB↔X feeds linear
light); latents are (B, H/8, W/8, latent_channels), *unscaled* (multiply by
`config.scaling_factor` for the UNet). Module names mirror diffusers' (`encoder/down_blocks_0/
resnets_1/conv1`), see `convert.py`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from jaxdistill.errors import ProblemList, read_json
from jaxdistill.models import layers

_FIXED = {
    "act_fn": "silu", "use_quant_conv": True, "use_post_quant_conv": True, "mid_block_add_attention": True,
    "shift_factor": None, "latents_mean": None, "latents_std": None,
}


@dataclasses.dataclass(frozen=True)
class VAEConfig:
    """Architecture fields of a diffusers AutoencoderKL config (hashable, static)."""

    in_channels: int = 3
    out_channels: int = 3
    block_out_channels: tuple[int, ...] = (128, 256, 512, 512)
    layers_per_block: int = 2
    latent_channels: int = 4
    norm_num_groups: int = 32
    scaling_factor: float = 0.18215

    @classmethod
    def from_dict(cls, cfg: dict[str, Any], source: str = "vae/config.json") -> "VAEConfig":
        """Validated config; every unsupported field is reported at once (InputError)."""
        problems = ProblemList()
        for key, want in _FIXED.items():
            if key in cfg and cfg[key] != want:
                problems.add(source, key, f"is {cfg[key]!r}; jaxdistill implements only {want!r} "
                             "(the Stable Diffusion AutoencoderKL)")
        blocks = tuple(cfg.get("block_out_channels", (64,)))
        for key, want in (("down_block_types", "DownEncoderBlock2D"), ("up_block_types", "UpDecoderBlock2D")):
            types = cfg.get(key, [want] * len(blocks))
            if any(t != want for t in types) or len(types) != len(blocks):
                problems.add(source, key, f"must be {len(blocks)} × {want!r}, got {types}")
        groups = cfg.get("norm_num_groups", 32)
        if any(c % groups for c in blocks):
            problems.add(source, "norm_num_groups", f"{groups} must divide every block_out_channels {blocks}")
        problems.raise_if_any()
        return cls(in_channels=int(cfg.get("in_channels", 3)), out_channels=int(cfg.get("out_channels", 3)),
                   block_out_channels=blocks, layers_per_block=int(cfg.get("layers_per_block", 1)),
                   latent_channels=int(cfg.get("latent_channels", 4)), norm_num_groups=int(groups),
                   scaling_factor=float(cfg.get("scaling_factor", 0.18215)))

    @classmethod
    def from_json(cls, path: str | Path) -> "VAEConfig":
        return cls.from_dict(read_json(path, "not found"), str(path))

    @property
    def downsampling_factor(self) -> int:
        return 2 ** (len(self.block_out_channels) - 1)


class SpatialAttention(nn.Module):
    """The VAE mid-block self-attention: GroupNorm, one head over all H·W tokens, residual.

    Tokens are processed in query chunks (`layers.dot_product_attention`) so a 512² image
    (4096 latent tokens) never holds the full 4096² score matrix.
    """

    groups: int
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x):
        batch, height, width, channels = x.shape
        h = layers.GroupNorm(self.groups, 1e-6, self.dtype, name="group_norm")(x).reshape(batch, -1, channels)
        d = lambda name: layers.dense(channels, name, self.dtype, self.precision)  # noqa: E731
        q, k, v = d("to_q")(h), d("to_k")(h), d("to_v")(h)
        out = layers.dot_product_attention(q, k, v, 1, chunk_size=self.chunk_size, precision=self.precision)
        return d("to_out_0")(out).reshape(x.shape) + x


class MidBlock(nn.Module):
    """resnets_0 → attentions_0 → resnets_1 (no time embedding)."""

    channels: int
    groups: int
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x):
        resnet = lambda j: layers.ResnetBlock2D(self.channels, self.groups, 1e-6, self.dtype,  # noqa: E731
                                                self.precision, name=f"resnets_{j}")
        x = resnet(0)(x)
        x = SpatialAttention(self.groups, self.dtype, self.precision, self.chunk_size, name="attentions_0")(x)
        return resnet(1)(x)


class CoderBlock(nn.Module):
    """DownEncoderBlock2D / UpDecoderBlock2D: `num_layers` resnets, optional resampler."""

    channels: int
    num_layers: int
    groups: int
    resample: str | None  # "down", "up" or None
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        for j in range(self.num_layers):
            x = layers.ResnetBlock2D(self.channels, self.groups, 1e-6, self.dtype, self.precision,
                                     name=f"resnets_{j}")(x)
        if self.resample == "down":
            x = layers.Downsample2D(self.channels, 0, self.dtype, self.precision, name="downsamplers_0")(x)
        elif self.resample == "up":
            x = layers.Upsample2D(self.channels, self.dtype, self.precision, name="upsamplers_0")(x)
        return x


class Encoder(nn.Module):
    """Image (B, H, W, 3) → moments (B, H/f, W/f, 2·latent) before `quant_conv`."""

    config: VAEConfig
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x):
        c = self.config
        x = layers.conv(c.block_out_channels[0], 3, "conv_in", self.dtype, self.precision)(x.astype(self.dtype))
        last = len(c.block_out_channels) - 1
        for i, channels in enumerate(c.block_out_channels):
            x = CoderBlock(channels, c.layers_per_block, c.norm_num_groups, "down" if i < last else None,
                           self.dtype, self.precision, name=f"down_blocks_{i}")(x)
        x = MidBlock(c.block_out_channels[-1], c.norm_num_groups, self.dtype, self.precision, self.chunk_size,
                     name="mid_block")(x)
        x = nn.silu(layers.GroupNorm(c.norm_num_groups, 1e-6, self.dtype, name="conv_norm_out")(x))
        return layers.conv(2 * c.latent_channels, 3, "conv_out", self.dtype, self.precision)(x)


class Decoder(nn.Module):
    """Latent (B, h, w, latent) after `post_quant_conv` → image (B, h·f, w·f, 3)."""

    config: VAEConfig
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, z):
        c = self.config
        reversed_blocks = tuple(reversed(c.block_out_channels))
        x = layers.conv(reversed_blocks[0], 3, "conv_in", self.dtype, self.precision)(z.astype(self.dtype))
        x = MidBlock(reversed_blocks[0], c.norm_num_groups, self.dtype, self.precision, self.chunk_size,
                     name="mid_block")(x)
        last = len(reversed_blocks) - 1
        for i, channels in enumerate(reversed_blocks):
            x = CoderBlock(channels, c.layers_per_block + 1, c.norm_num_groups, "up" if i < last else None,
                           self.dtype, self.precision, name=f"up_blocks_{i}")(x)
        x = nn.silu(layers.GroupNorm(c.norm_num_groups, 1e-6, self.dtype, name="conv_norm_out")(x))
        return layers.conv(c.out_channels, 3, "conv_out", self.dtype, self.precision)(x)


class AutoencoderKL(nn.Module):
    """The KL autoencoder. Use `apply(params, x, method="encode")` → (mean, logvar) and
    `apply(params, z, method="decode")` → image; `__call__` runs both (for init)."""

    config: VAEConfig
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    def setup(self):
        opts = dict(dtype=self.dtype, precision=self.precision, chunk_size=self.chunk_size)
        self.encoder = Encoder(self.config, **opts)
        self.decoder = Decoder(self.config, **opts)
        width = 2 * self.config.latent_channels
        self.quant_conv = layers.conv(width, 1, None, self.dtype, self.precision)
        self.post_quant_conv = layers.conv(self.config.latent_channels, 1, None, self.dtype, self.precision)

    def encode(self, images):
        """Images (B, H, W, 3) in [-1, 1] → (mean, logvar), each (B, H/f, W/f, latent) float32;
        logvar clamped to [-30, 20] as diffusers' DiagonalGaussianDistribution."""
        moments = self.quant_conv(self.encoder(images)).astype(jnp.float32)
        mean, logvar = jnp.split(moments, 2, axis=-1)
        return mean, jnp.clip(logvar, -30.0, 20.0)

    def decode(self, latents):
        """Unscaled latents (B, h, w, latent) → images (B, h·f, w·f, 3), unclamped, float32."""
        return self.decoder(self.post_quant_conv(latents.astype(self.dtype))).astype(jnp.float32)

    def __call__(self, images):
        mean, _ = self.encode(images)
        return self.decode(mean)


def sample_latent(mean, logvar, key):
    """A draw from the diagonal Gaussian N(mean, exp(logvar)), same shape as mean."""
    return mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape, mean.dtype)
