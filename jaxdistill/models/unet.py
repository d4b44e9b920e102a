"""UNet2DCondition of the Stable Diffusion 2.x family (RGB↔X's denoiser), Flax linen, NHWC.

Configured from a diffusers `unet/config.json` (`UNetConfig.from_json`); fields outside the
SD-2.1 family are refused with an error naming the field. Module names mirror diffusers'
(`down_blocks_0/attentions_1/transformer_blocks_0/attn2/to_q`), see `convert.py`.

Note on names: diffusers' `attention_head_dim` of SD 2.x is, in fact, the number of heads
per block (320 channels / 5 heads = 64 per head); we follow diffusers exactly.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import jax.numpy as jnp
from flax import linen as nn

from jaxdistill.errors import ProblemList, read_json
from jaxdistill.models import layers

DOWN_BLOCKS = ("CrossAttnDownBlock2D", "DownBlock2D")
UP_BLOCKS = ("CrossAttnUpBlock2D", "UpBlock2D")

# config fields whose value must be exactly this for the SD-2.x family we implement
_FIXED = {
    "act_fn": "silu", "center_input_sample": False, "time_embedding_type": "positional",
    "mid_block_type": "UNetMidBlock2DCrossAttn", "only_cross_attention": False,
    "dual_cross_attention": False, "class_embed_type": None, "addition_embed_type": None,
    "num_class_embeds": None, "encoder_hid_dim": None, "encoder_hid_dim_type": None,
    "time_cond_proj_dim": None, "resnet_time_scale_shift": "default", "resnet_skip_time_act": False,
    "resnet_out_scale_factor": 1.0, "mid_block_scale_factor": 1, "downsample_padding": 1,
    "conv_in_kernel": 3, "conv_out_kernel": 3, "attention_type": "default",
    "time_embedding_dim": None, "time_embedding_act_fn": None, "timestep_post_act": None,
    "class_embeddings_concat": False, "mid_block_only_cross_attention": None,
    "cross_attention_norm": None, "reverse_transformer_layers_per_block": None,
    "projection_class_embeddings_input_dim": None, "addition_time_embed_dim": None,
}


def _per_block(value, num_blocks: int) -> tuple:
    return tuple(value) if isinstance(value, (list, tuple)) else (value,) * num_blocks


@dataclasses.dataclass(frozen=True)
class UNetConfig:
    """The architecture fields of a diffusers UNet2DConditionModel config (hashable, static)."""

    in_channels: int = 8
    out_channels: int = 4
    block_out_channels: tuple[int, ...] = (320, 640, 1280, 1280)
    down_block_types: tuple[str, ...] = ("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",)
    up_block_types: tuple[str, ...] = ("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3
    layers_per_block: tuple[int, ...] = (2, 2, 2, 2)
    num_heads: tuple[int, ...] = (5, 10, 20, 20)
    transformer_layers_per_block: tuple[int, ...] = (1, 1, 1, 1)
    cross_attention_dim: int = 1024
    norm_num_groups: int = 32
    norm_eps: float = 1e-5
    use_linear_projection: bool = True
    upcast_attention: bool = True
    flip_sin_to_cos: bool = True
    freq_shift: float = 0.0

    @classmethod
    def from_dict(cls, cfg: dict[str, Any], source: str = "unet/config.json") -> "UNetConfig":
        """Validated config; every unsupported field is reported at once (InputError)."""
        problems = ProblemList()
        for key, want in _FIXED.items():
            if key in cfg and cfg[key] != want:
                problems.add(source, key, f"is {cfg[key]!r}; jaxdistill implements only {want!r} "
                             "(the Stable Diffusion 2.x UNet that RGB↔X uses)")
        blocks = tuple(cfg.get("block_out_channels", cls.block_out_channels))
        n = len(blocks)
        down = tuple(cfg.get("down_block_types", cls.down_block_types))
        up = tuple(cfg.get("up_block_types", cls.up_block_types))
        for key, types, allowed in (("down_block_types", down, DOWN_BLOCKS), ("up_block_types", up, UP_BLOCKS)):
            bad = [t for t in types if t not in allowed]
            if bad:
                problems.add(source, key, f"unsupported block types {bad}; supported: {list(allowed)}")
            if len(types) != n:
                problems.add(source, key, f"has {len(types)} entries but block_out_channels has {n}")
        heads = cfg.get("num_attention_heads") or cfg.get("attention_head_dim", 8)
        heads = _per_block(heads, n)
        cross = cfg.get("cross_attention_dim", cls.cross_attention_dim)
        if isinstance(cross, (list, tuple)):
            problems.add(source, "cross_attention_dim", "per-block cross-attention dims are not supported")
        groups = cfg.get("norm_num_groups", cls.norm_num_groups)
        if groups is None or any(c % groups for c in blocks):
            problems.add(source, "norm_num_groups", f"{groups} must divide every block_out_channels {blocks}")
        for i, (c, h) in enumerate(zip(blocks, heads)):
            if h is None or c % h:
                problems.add(source, f"attention_head_dim[{i}]", f"{h} heads do not divide {c} channels")
        problems.raise_if_any()
        return cls(
            in_channels=int(cfg.get("in_channels", 4)), out_channels=int(cfg.get("out_channels", 4)),
            block_out_channels=blocks, down_block_types=down, up_block_types=up,
            layers_per_block=_per_block(cfg.get("layers_per_block", 2), n), num_heads=heads,
            transformer_layers_per_block=_per_block(cfg.get("transformer_layers_per_block", 1), n),
            cross_attention_dim=int(cross), norm_num_groups=int(groups),
            norm_eps=float(cfg.get("norm_eps", 1e-5)),
            use_linear_projection=bool(cfg.get("use_linear_projection", False)),
            upcast_attention=bool(cfg.get("upcast_attention", False)),
            flip_sin_to_cos=bool(cfg.get("flip_sin_to_cos", True)), freq_shift=float(cfg.get("freq_shift", 0)),
        )

    @classmethod
    def from_json(cls, path: str | Path) -> "UNetConfig":
        return cls.from_dict(read_json(path, "not found"), str(path))


def timestep_embedding(t, dim: int, flip_sin_to_cos: bool, freq_shift: float, max_period: float = 10000.0):
    """Sinusoidal embedding of timesteps t (B,) → (B, dim) float32, as diffusers' `Timesteps`."""
    half = dim // 2
    freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / (half - freq_shift))
    args = jnp.asarray(t, jnp.float32)[:, None] * freqs[None, :]
    sin, cos = jnp.sin(args), jnp.cos(args)
    emb = jnp.concatenate([cos, sin] if flip_sin_to_cos else [sin, cos], axis=-1)
    if dim % 2:
        emb = jnp.pad(emb, ((0, 0), (0, 1)))
    return emb


class FeedForward(nn.Module):
    """GEGLU feed-forward: net.0.proj (C → 2·4C), value·gelu(gate), net.2 (4C → C)."""

    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        channels = x.shape[-1]
        h = GEGLU(4 * channels, self.dtype, self.precision, name="net_0")(x)
        return layers.dense(channels, "net_2", self.dtype, self.precision)(h)


class GEGLU(nn.Module):
    """proj (C → 2·inner), split into value and gate, value · gelu(gate) (exact erf GELU)."""

    inner: int
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        h = layers.dense(2 * self.inner, "proj", self.dtype, self.precision)(x)
        value, gate = jnp.split(h, 2, axis=-1)
        return value * nn.gelu(gate, approximate=False)


class BasicTransformerBlock(nn.Module):
    """Self-attention, cross-attention on the text context, GEGLU MLP; pre-LayerNorm, residual."""

    num_heads: int
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x, context):
        attn = dict(num_heads=self.num_heads, dtype=self.dtype, precision=self.precision,
                    chunk_size=self.chunk_size)
        x = x + layers.Attention(**attn, name="attn1")(layers.LayerNorm(1e-5, self.dtype, name="norm1")(x))
        x = x + layers.Attention(**attn, name="attn2")(layers.LayerNorm(1e-5, self.dtype, name="norm2")(x),
                                                      context)
        return x + FeedForward(self.dtype, self.precision, name="ff")(
            layers.LayerNorm(1e-5, self.dtype, name="norm3")(x))


class Transformer2D(nn.Module):
    """diffusers `Transformer2DModel` (continuous input): GroupNorm, proj_in, blocks, proj_out, residual."""

    num_heads: int
    num_layers: int
    groups: int
    linear_projection: bool
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x, context):
        batch, height, width, channels = x.shape
        h = layers.GroupNorm(self.groups, 1e-6, self.dtype, name="norm")(x)
        if self.linear_projection:
            h = layers.dense(channels, "proj_in", self.dtype, self.precision)(h.reshape(batch, -1, channels))
        else:
            h = layers.conv(channels, 1, "proj_in", self.dtype, self.precision)(h).reshape(batch, -1, channels)
        for i in range(self.num_layers):
            h = BasicTransformerBlock(self.num_heads, self.dtype, self.precision, self.chunk_size,
                                      name=f"transformer_blocks_{i}")(h, context)
        if self.linear_projection:
            h = layers.dense(channels, "proj_out", self.dtype, self.precision)(h).reshape(x.shape)
        else:
            h = layers.conv(channels, 1, "proj_out", self.dtype, self.precision)(h.reshape(x.shape))
        return h + x


class TimestepEmbedding(nn.Module):
    """linear_1 → SiLU → linear_2 on the sinusoidal embedding."""

    features: int
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, emb):
        h = nn.silu(layers.dense(self.features, "linear_1", self.dtype, self.precision)(emb.astype(self.dtype)))
        return layers.dense(self.features, "linear_2", self.dtype, self.precision)(h)


class UNetBlock(nn.Module):
    """One down, mid or up block of the UNet: `resnets_j` (each followed by `attentions_j` when the
    block has cross-attention), then an optional `downsamplers_0` / `upsamplers_0`.

    Down and up blocks return the hidden states after every layer (the skip connections);
    up blocks consume them (`skips`, last first). Mid blocks are resnet, attention, resnet.
    """

    config: UNetConfig
    kind: str            # "down", "mid" or "up"
    block: int           # index into block_out_channels
    num_layers: int
    cross_attention: bool
    resample: bool
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x, temb, context, skips=None, upsample_size=None):
        c = self.config
        channels = c.block_out_channels[self.block]
        resnet = lambda j: layers.ResnetBlock2D(channels, c.norm_num_groups, c.norm_eps, self.dtype,  # noqa: E731
                                                self.precision, name=f"resnets_{j}")
        attention = lambda j: Transformer2D(  # noqa: E731
            c.num_heads[self.block], c.transformer_layers_per_block[self.block], c.norm_num_groups,
            c.use_linear_projection, self.dtype, self.precision, self.chunk_size, name=f"attentions_{j}")
        if self.kind == "mid":
            x = resnet(0)(x, temb)
            x = attention(0)(x, context)
            return resnet(1)(x, temb)
        outputs = []
        skips = list(skips) if skips is not None else None
        for j in range(self.num_layers):
            if self.kind == "up":
                x = jnp.concatenate([x, skips.pop()], axis=-1)
            x = resnet(j)(x, temb)
            if self.cross_attention:
                x = attention(j)(x, context)
            outputs.append(x)
        if self.kind == "down":
            if self.resample:
                x = layers.Downsample2D(channels, 1, self.dtype, self.precision, name="downsamplers_0")(x)
                outputs.append(x)
            return x, outputs
        if self.resample:
            x = layers.Upsample2D(channels, self.dtype, self.precision, name="upsamplers_0")(x, upsample_size)
        return x


class UNet2DCondition(nn.Module):
    """ε/v-prediction UNet: (sample (B, h, w, in_channels), t (B,) or scalar, context (B, L, D))
    → (B, h, w, out_channels) float32. Any h, w: upsampling follows the skip connections' sizes."""

    config: UNetConfig
    dtype: Any = jnp.float32
    precision: str = "default"
    chunk_size: int = layers.DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, sample, t, context):
        c = self.config
        opts = dict(dtype=self.dtype, precision=self.precision, chunk_size=self.chunk_size)
        batch = sample.shape[0]
        t = jnp.broadcast_to(jnp.asarray(t, jnp.float32).reshape(-1), (batch,))
        temb = timestep_embedding(t, c.block_out_channels[0], c.flip_sin_to_cos, c.freq_shift)
        temb = TimestepEmbedding(4 * c.block_out_channels[0], self.dtype, self.precision,
                                 name="time_embedding")(temb)
        context = context.astype(self.dtype)
        x = layers.conv(c.block_out_channels[0], 3, "conv_in", self.dtype, self.precision)(sample.astype(self.dtype))
        skips = [x]
        num_blocks = len(c.block_out_channels)
        for i, kind in enumerate(c.down_block_types):
            x, outputs = UNetBlock(c, "down", i, c.layers_per_block[i], kind == "CrossAttnDownBlock2D",
                                   i < num_blocks - 1, **opts, name=f"down_blocks_{i}")(x, temb, context)
            skips.extend(outputs)
        x = UNetBlock(c, "mid", num_blocks - 1, 1, True, False, **opts, name="mid_block")(x, temb, context)
        for i, kind in enumerate(c.up_block_types):
            block = num_blocks - 1 - i
            layers_here = c.layers_per_block[block] + 1
            block_skips, skips = skips[-layers_here:], skips[:-layers_here]
            size = skips[-1].shape[1:3] if i < num_blocks - 1 else None
            x = UNetBlock(c, "up", block, layers_here, kind == "CrossAttnUpBlock2D", i < num_blocks - 1,
                          **opts, name=f"up_blocks_{i}")(x, temb, context, block_skips, size)
        x = nn.silu(layers.GroupNorm(c.norm_num_groups, c.norm_eps, self.dtype, name="conv_norm_out")(x))
        x = layers.conv(c.out_channels, 3, "conv_out", self.dtype, self.precision)(x)
        return x.astype(jnp.float32)
