"""Building blocks shared by the UNet, the VAE and the text encoder (Flax linen, NHWC).

Module and parameter names mirror the PyTorch (diffusers) modules with the list
index folded into the name (`resnets.0` → `resnets_0`), so `convert.py` maps
checkpoint keys to leaves by rule. Parameters are float32; activations run in
`dtype` (float32 or bfloat16). Normalisation statistics, attention scores and
softmax always run in float32.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import errors as flax_errors
from flax.core import meta as flax_meta
from flax import linen as nn

Dtype = Any

# Attention over more than this many query×key score entries (per batch element and
# head) is computed in query chunks, so the VAE's mid-block attention at 512² (4096
# tokens) or 1024² (16384 tokens) never holds the full score matrix at once.
DEFAULT_ATTENTION_CHUNK = 1024
FUSED_CUDNN = 0          # chunk size that means: one fused cuDNN attention call (GPU, bf16/fp16)


def fused_head_fits(head_dim: int) -> bool:
    """Whether cuDNN's fused attention takes heads of `head_dim` channels (a multiple of 8, at most 128)."""
    return head_dim % 8 == 0 and 0 < head_dim <= 128


def precision_of(name: str) -> jax.lax.Precision | None:
    """`"default"` → None (the backend's choice, TF32 on recent GPUs), `"highest"` → full fp32."""
    if name == "default":
        return None
    if name == "highest":
        return jax.lax.Precision.HIGHEST
    raise ValueError(f"precision must be 'default' or 'highest', got {name!r}")


def _standardise(x, axes, epsilon):
    """(x − mean) / sqrt(var + ε) over `axes`, with the two-pass variance (as PyTorch)."""
    mean = x.mean(axis=axes, keepdims=True)
    var = jnp.square(x - mean).mean(axis=axes, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + epsilon)


def group_norm(x, scale, bias, num_groups: int, epsilon: float):
    """GroupNorm of x (B, ..., C) over its spatial axes and each group of C / num_groups channels,
    then `scale` and `bias` per channel; float32, the two-pass variance (as PyTorch).

    The statistics are summed per channel over the spatial axes first (a reduction along rows of
    x's own layout), then over each group's channels (a (B, C) array): grouping the channels of a
    (B, H, W, C) array first, as (B, H, W, G, C / G), makes XLA's CPU backend reduce over a minor
    axis of 2–8 elements: 1.4–3.1× slower at the VAE's 32–256 channels with jaxlib 0.10's own flags,
    about the same with the package's (docs/benchmarks.md §1). The normalisation is one multiply-add per
    element with a per-channel factor.
    """
    x = x.astype(jnp.float32)
    channels = x.shape[-1]
    if channels % num_groups:
        raise ValueError(f"GroupNorm of {channels} channels in {num_groups} groups: the groups must divide the channels")
    per_group = channels // num_groups
    if per_group == 1:                        # a group is a channel: nothing to gather
        return _standardise(x, tuple(range(1, x.ndim - 1)), epsilon) * scale + bias
    spatial = tuple(range(1, x.ndim - 1))
    count = math.prod(x.shape[1:-1]) * per_group
    as_channels = (x.shape[0],) + (1,) * len(spatial) + (channels,)

    def group_mean(channel_sums):             # (B, C) → each channel's group mean, (B, 1.., C)
        means = channel_sums.reshape(-1, num_groups, per_group).sum(axis=-1) / count
        return jnp.repeat(means, per_group, axis=-1).reshape(as_channels)

    centred = x - group_mean(x.sum(axis=spatial))
    factor = scale * jax.lax.rsqrt(group_mean(jnp.square(centred).sum(axis=spatial)) + epsilon)
    return centred * factor + bias


class ParamsByShape:
    """Mixin for a Flax module whose stored parameters are read by name and checked by shape.

    `nn.Module.param` checks a parameter that exists by tracing its initialiser with `jax.eval_shape`
    each time an apply is traced: milliseconds a parameter, which is most of the time it takes to
    trace a network of hundreds of them (the UNet's step, the sampler). Here a stored parameter's
    shape (an array's; not checked leaf by leaf for a pytree-valued parameter, which these layers
    do not have) is compared with the shape asked for (the first of `init_args`, the initialiser's
    argument after the key, as in every Flax initialiser) instead. Everything else (`init`, a
    missing parameter, arguments that are not a shape) goes through `nn.Module.param` itself: the
    same values and errors.
    """

    def param(self, name, init_fn, *init_args, unbox=True, **init_kwargs):
        if not (init_args and isinstance(init_args[0], (tuple, list)) and self.has_variable("params", name)):
            return super().param(name, init_fn, *init_args, unbox=unbox, **init_kwargs)
        value = self.variable("params", name, unbox=unbox).value
        found, asked = tuple(jnp.shape(flax_meta.unbox(value))), tuple(init_args[0])
        if found != asked:
            raise flax_errors.ScopeParamShapeError(name, self.scope.path_text, found, asked)
        return value


class Dense(ParamsByShape, nn.Dense):
    """`nn.Dense` with its parameters read by shape (`ParamsByShape`)."""


class Conv(ParamsByShape, nn.Conv):
    """`nn.Conv` with its parameters read by shape (`ParamsByShape`)."""


class Embed(ParamsByShape, nn.Embed):
    """`nn.Embed` with its parameters read by shape (`ParamsByShape`)."""


class GroupNorm(ParamsByShape, nn.Module):
    """GroupNorm over the channel axis (last), statistics in float32 (two-pass variance)."""

    num_groups: int
    epsilon: float
    dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x):
        channels = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (channels,), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros, (channels,), jnp.float32)
        return group_norm(x, scale, bias, self.num_groups, self.epsilon).astype(self.dtype)


class LayerNorm(ParamsByShape, nn.Module):
    """LayerNorm over the last axis, statistics in float32."""

    epsilon: float = 1e-5
    dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(self, x):
        features = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (features,), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros, (features,), jnp.float32)
        return (_standardise(x.astype(jnp.float32), (-1,), self.epsilon) * scale + bias).astype(self.dtype)


def dense(features: int, name: str | None, dtype: Dtype, precision: str, use_bias: bool = True) -> Dense:
    """A linear layer with float32 parameters computing in `dtype`."""
    return Dense(features, use_bias=use_bias, dtype=dtype, param_dtype=jnp.float32,
                 precision=precision_of(precision), name=name)


def conv(features: int, kernel: int, name: str | None, dtype: Dtype, precision: str, stride: int = 1,
         padding: Any = "SAME_TORCH") -> nn.Module:
    """A 2-D convolution, PyTorch padding `kernel // 2` unless `padding` is given; 3×3 with stride 1
    and that padding is `Conv3x3`."""
    if kernel == 3 and stride == 1 and padding == "SAME_TORCH":
        return Conv3x3(features, dtype, precision, name=name)
    if padding == "SAME_TORCH":
        padding = ((kernel // 2, kernel // 2),) * 2
    return Conv(features, (kernel, kernel), strides=(stride, stride), padding=padding, dtype=dtype,
                param_dtype=jnp.float32, precision=precision_of(precision), name=name)


# Winograd's F(2×2, 3×3) (Lavin & Gray 2016, "Fast Algorithms for Convolutional Neural Networks"):
# input tile transform Bᵀ, kernel transform G, output transform Aᵀ
_WINOGRAD_BT = np.array([[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]], np.float32)
_WINOGRAD_G = np.array([[1, 0, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0, 0, 1]], np.float32)
_WINOGRAD_AT = np.array([[1, 1, 1, 0], [0, 1, -1, -1]], np.float32)
WINOGRAD_MIN_CHANNELS = 256        # on XLA's CPU backend, below these it was slower (docs/benchmarks.md §1)
WINOGRAD_MIN_PIXELS = 3072


def _combine(matrix, terms):
    """Σ_j matrix[i, j] · terms[j] for each row i, skipping zero coefficients (elementwise, fused by XLA)."""
    return [sum(c * t for c, t in zip(row, terms) if c != 0) for row in matrix.tolist()]


def winograd_3x3(padded, taps, precision: str = "default"):
    """The 'VALID' 3×3 convolution of an NHWC image padded by one (output sides even) with HWIO
    `taps`, by Winograd's F(2×2, 3×3): each 2×2 output tile from its 4×4 input tile, with 16
    products of (tiles × Cin) by (Cin × Cout) where the direct convolution has 36. Equal up to
    rounding (relative 2e-6 at 512 channels). The transforms and products run in float32 whatever
    the image's dtype (in bfloat16 the output transform's cancellations cost 2.5× the error of the
    direct convolution); the result is cast back."""
    dtype = padded.dtype
    padded = padded.astype(jnp.float32)           # the transforms add and cancel: float32 even for bfloat16
    batch, height, width = padded.shape[0], padded.shape[1] - 2, padded.shape[2] - 2
    tiles = [[padded[:, u:u + height:2, v:v + width:2] for v in range(4)] for u in range(4)]
    rows = _combine(_WINOGRAD_BT, [jnp.stack(row) for row in tiles])           # Bᵀ d, each (4 v, B, h, w, C)
    inputs = jnp.stack([t for r in rows for t in _combine(_WINOGRAD_BT, list(r))])   # Bᵀ d B: (16, B, h, w, C)
    kernel = jnp.einsum("ai,ijco,bj->abco", _WINOGRAD_G, taps.astype(jnp.float32), _WINOGRAD_G,
                        precision=jax.lax.Precision.HIGHEST).reshape(16, *taps.shape[2:])
    products = jnp.einsum("pbhwc,pco->pbhwo", inputs, kernel, precision=precision_of(precision))
    products = products.reshape(4, 4, *products.shape[1:])
    half = _combine(_WINOGRAD_AT, list(products))                                  # Aᵀ M, each (4, B, h, w, O)
    out = jnp.stack([jnp.stack(_combine(_WINOGRAD_AT, list(h)), axis=3) for h in half], axis=2)
    return out.reshape(batch, height, width, taps.shape[-1]).astype(dtype)         # (B, h, 2, w, 2, O) interleaved


def convolve_valid(image, taps, precision: str = "default"):
    """The 'VALID' convolution of an NHWC `image` with HWIO `taps` (stride 1), in their dtype.

    On a GPU (or any backend but the CPU) it is `lax.conv_general_dilated`, as `nn.Conv`, whose
    libraries choose their own algorithm. On XLA's CPU backend, by the shapes (each choice was
    measured faster there, docs/benchmarks.md §1):
    - fewer output pixels in the batch than output channels (the UNet's 3×4 to 12×16 latents at
      640–1280 channels): a matrix product of the image's patches (at most the kernel's size) with
      the kernel reshaped to (kh·kw·Cin, Cout): 1.1–2.1× faster with jaxlib 0.10's own flags, about
      the same as XLA's convolution with the package's (0.95–1.10);
    - 3×3 taps, at least `WINOGRAD_MIN_CHANNELS` in and out and `WINOGRAD_MIN_PIXELS` output
      pixels, even sides (the full-size VAE's 256–512-channel resolutions): `winograd_3x3`,
      1.3–1.4× faster with the package's XLA flags (`jaxdistill/xla_flags.py`; at 64 channels it
      was faster only with jaxlib's YNNPACK fusions on, and slower with 32 channels or 768 pixels);
    - otherwise the XLA convolution.
    """
    rows, cols = taps.shape[:2]
    height, width = image.shape[1] - rows + 1, image.shape[2] - cols + 1
    pixels = image.shape[0] * height * width
    prec = precision_of(precision)

    def direct(image, taps):
        return jax.lax.conv_general_dilated(image, taps, (1, 1), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                            precision=prec)

    def on_cpu(image, taps):
        if pixels < taps.shape[-1]:
            patches = jnp.concatenate([image[:, i:i + height, j:j + width] for i in range(rows) for j in range(cols)],
                                      axis=-1)
            return jnp.einsum("bhwk,ko->bhwo", patches, taps.reshape(-1, taps.shape[-1]), precision=prec)
        if ((rows, cols) == (3, 3) and min(taps.shape[2:]) >= WINOGRAD_MIN_CHANNELS and pixels >= WINOGRAD_MIN_PIXELS
                and height % 2 == 0 and width % 2 == 0):
            return winograd_3x3(image, taps, precision)
        return direct(image, taps)

    return jax.lax.platform_dependent(image, taps, cpu=on_cpu, default=direct)


def pad_one(image):
    """An NHWC image with one zero row and column on each side."""
    return jnp.pad(image, ((0, 0), (1, 1), (1, 1), (0, 0)))


def _conv3x3_params(module: nn.Module, in_channels: int):
    """(kernel (3, 3, Cin, features), bias): `nn.Conv`'s parameters, names and initialisers."""
    kernel = module.param("kernel", nn.linear.default_kernel_init, (3, 3, in_channels, module.features), jnp.float32)
    return kernel, module.param("bias", nn.initializers.zeros, (module.features,), jnp.float32)


class Conv3x3(ParamsByShape, nn.Module):
    """A 3×3 convolution, stride 1, padding 1, with `nn.Conv`'s parameters (`kernel` (3, 3, Cin,
    Cout), `bias`) and initialiser; computed by `convolve_valid` on the padded image."""

    features: int
    dtype: Dtype = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        kernel, bias = _conv3x3_params(self, x.shape[-1])
        padded = pad_one(x.astype(self.dtype))
        return convolve_valid(padded, kernel.astype(self.dtype), self.precision) + bias.astype(self.dtype)


def _scores_softmax_values(q, k, v, scale, precision, mask=None):
    """softmax(q·kᵀ·scale)·v for q (B, Nq, H, D), k/v (B, Nk, H, D); scores in float32;
    `mask` (Nq, Nk) True = attend."""
    prec = precision_of(precision)
    scores = jnp.einsum("bqhd,bkhd->bhqk", q.astype(jnp.float32), k.astype(jnp.float32),
                        precision=prec) * scale
    if mask is not None:
        scores = jnp.where(mask[None, None], scores, jnp.finfo(jnp.float32).min)
    weights = jax.nn.softmax(scores, axis=-1).astype(v.dtype)
    return jnp.einsum("bhqk,bkhd->bqhd", weights, v, precision=prec)


def dot_product_attention(q, k, v, num_heads: int, mask=None, chunk_size: int = DEFAULT_ATTENTION_CHUNK,
                          precision: str = "default"):
    """Multi-head attention of q (B, Nq, C) over k, v (B, Nk, C) → (B, Nq, C).

    `mask` (Nq, Nk) bool, True = attend (used for CLIP's causal mask, never chunked).
    Without a mask, when Nq·Nk exceeds `chunk_size`², queries are processed in chunks of
    `chunk_size` with `lax.map`, so peak memory is chunk_size·Nk scores per head.
    `chunk_size=FUSED_CUDNN` (0) hands the whole attention to cuDNN's fused (flash) kernel through
    `jax.nn.dot_product_attention(implementation="cudnn")`: NVIDIA GPUs only, float16/bfloat16
    activations, head size a multiple of 8 up to 128, no mask; anything else is refused here.
    """
    batch, num_q, channels = q.shape
    head_dim = channels // num_heads
    scale = 1.0 / math.sqrt(head_dim)
    q = q.reshape(batch, num_q, num_heads, head_dim)
    k = k.reshape(batch, k.shape[1], num_heads, head_dim)
    v = v.reshape(batch, v.shape[1], num_heads, head_dim)
    if chunk_size == FUSED_CUDNN:
        if mask is not None or q.dtype not in (jnp.float16, jnp.bfloat16) or not fused_head_fits(head_dim):
            raise ValueError(f"cuDNN's fused attention needs float16/bfloat16 activations, a head size that is a "
                             f"multiple of 8 up to 128 and no mask; got {q.dtype}, head size {head_dim}, "
                             f"mask {mask is not None}: use a positive chunk size")
        return jax.nn.dot_product_attention(q, k, v, scale=scale, implementation="cudnn").reshape(
            batch, num_q, channels)
    if mask is not None:
        out = _scores_softmax_values(q, k, v, scale, precision, mask)
    elif num_q * k.shape[1] <= chunk_size * chunk_size or num_q <= chunk_size:
        out = _scores_softmax_values(q, k, v, scale, precision)
    else:
        num_chunks = -(-num_q // chunk_size)
        padded = jnp.pad(q, ((0, 0), (0, num_chunks * chunk_size - num_q), (0, 0), (0, 0)))
        chunks = padded.reshape(batch, num_chunks, chunk_size, num_heads, head_dim).swapaxes(0, 1)
        out = jax.lax.map(lambda qc: _scores_softmax_values(qc, k, v, scale, precision), chunks)
        out = out.swapaxes(0, 1).reshape(batch, num_chunks * chunk_size, num_heads, head_dim)[:, :num_q]
    return out.reshape(batch, num_q, channels)


class Attention(nn.Module):
    """diffusers `Attention`: to_q/to_k/to_v projections, attention, to_out.0 (B, N, C) → (B, N, C)."""

    num_heads: int
    qkv_bias: bool = False
    dtype: Dtype = jnp.float32
    precision: str = "default"
    chunk_size: int = DEFAULT_ATTENTION_CHUNK

    @nn.compact
    def __call__(self, x, context=None):
        channels = x.shape[-1]
        context = x if context is None else context
        q = dense(channels, "to_q", self.dtype, self.precision, self.qkv_bias)(x)
        k = dense(channels, "to_k", self.dtype, self.precision, self.qkv_bias)(context)
        v = dense(channels, "to_v", self.dtype, self.precision, self.qkv_bias)(context)
        out = dot_product_attention(q, k, v, self.num_heads, chunk_size=self.chunk_size,
                                    precision=self.precision)
        return dense(channels, "to_out_0", self.dtype, self.precision)(out)


class ResnetBlock2D(nn.Module):
    """diffusers `ResnetBlock2D` (scale-shift 'default', SiLU, output scale 1), NHWC.

    x (B, H, W, Cin), optional temb (B, T) → (B, H, W, out_channels).
    """

    out_channels: int
    groups: int
    epsilon: float
    dtype: Dtype = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x, temb=None):
        h = nn.silu(GroupNorm(self.groups, self.epsilon, self.dtype, name="norm1")(x))
        h = conv(self.out_channels, 3, "conv1", self.dtype, self.precision)(h)
        if temb is not None:
            t = dense(self.out_channels, "time_emb_proj", self.dtype, self.precision)(nn.silu(temb))
            h = h + t[:, None, None, :]
        h = nn.silu(GroupNorm(self.groups, self.epsilon, self.dtype, name="norm2")(h))
        h = conv(self.out_channels, 3, "conv2", self.dtype, self.precision)(h)
        if x.shape[-1] != self.out_channels:
            x = conv(self.out_channels, 1, "conv_shortcut", self.dtype, self.precision)(x)
        return x + h


class Downsample2D(nn.Module):
    """Stride-2 3×3 convolution; `padding` 1 (UNet) or 0 with PyTorch's (0, 1) pad (VAE)."""

    channels: int
    padding: int = 1
    dtype: Dtype = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        if self.padding == 0:
            pad = ((0, 1), (0, 1))
        else:
            pad = ((self.padding, self.padding),) * 2
        return conv(self.channels, 3, "conv", self.dtype, self.precision, stride=2, padding=pad)(x)


def nearest_resize(x, size: tuple[int, int]):
    """PyTorch `interpolate(mode='nearest')` of x (B, H, W, C) to `size`: source index floor(i·H/h)."""
    height, width = x.shape[1:3]
    rows = (jnp.arange(size[0]) * height) // size[0]
    cols = (jnp.arange(size[1]) * width) // size[1]
    return x[:, rows][:, :, cols]


def _phase_taps(kernel, axis: int):
    """A 3-tap kernel along `axis` applied to a nearest ×2 upsampling, as two 2-tap kernels on the
    input: the even outputs read input rows (i − 1, i) with taps (k0, k1 + k2), the odd ones rows
    (i, i + 1) with taps (k0 + k1, k2)."""
    k0, k1, k2 = (jax.lax.index_in_dim(kernel, j, axis) for j in range(3))
    return jnp.concatenate([k0, k1 + k2], axis), jnp.concatenate([k0 + k1, k2], axis)


class UpsampleConv(ParamsByShape, nn.Module):
    """Nearest upsampling, then a 3×3 convolution with padding 1 (`kernel` (3, 3, Cin, Cout) and
    `bias`, as `nn.Conv`'s, whose initialiser it uses).

    At ×2 the convolution is computed on the input itself: each of the four output phases (row
    and column parity) is a 2×2 convolution of the input padded by one, with taps summed from the
    3×3 kernel (`_phase_taps`). Same result up to the rounding of the summed taps; 16 multiplies
    per output where the upsampled image needs 36. To another size (`size`, the UNet's odd latent
    sides), the image is resized first (`nearest_resize`) and convolved as it is.
    """

    features: int
    dtype: Dtype = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x, size: tuple[int, int] | None = None):
        kernel, bias = _conv3x3_params(self, x.shape[-1])
        x = x.astype(self.dtype)
        height, width = x.shape[1:3]
        convolve = lambda image, taps: convolve_valid(image, taps.astype(self.dtype), self.precision)  # noqa: E731
        if size is not None and tuple(size) != (2 * height, 2 * width):
            out = convolve(pad_one(nearest_resize(x, size)), kernel)
        else:
            padded = pad_one(x)
            rows = []
            for a, by_rows in enumerate(_phase_taps(kernel, 0)):
                cols = [convolve(padded[:, a:a + height + 1, b:b + width + 1], taps)
                        for b, taps in enumerate(_phase_taps(by_rows, 1))]
                rows.append(jnp.stack(cols, axis=3))                  # (B, H, W, 2 column phases, C)
            out = jnp.stack(rows, axis=2).reshape(x.shape[0], 2 * height, 2 * width, self.features)
        return out + bias.astype(self.dtype)


class Upsample2D(nn.Module):
    """Nearest upsampling (×2, or to `size` when given) followed by a 3×3 convolution (`UpsampleConv`)."""

    channels: int
    dtype: Dtype = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x, size: tuple[int, int] | None = None):
        return UpsampleConv(self.channels, self.dtype, self.precision, name="conv")(x, size)
