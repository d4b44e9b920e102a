"""CLIP text transformer (transformers' CLIPTextModel), Flax linen: token ids → last hidden state.

Token ids (B, L) int → (B, L, hidden) float32 after the final LayerNorm, causal self-attention,
no padding mask (as Stable Diffusion pipelines call it). Module names mirror transformers'
(`encoder/layers_3/self_attn/q_proj`); checkpoint keys may carry a `text_model.` prefix.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax.numpy as jnp
from flax import linen as nn

from jaxdistill.errors import ProblemList, read_json
from jaxdistill.models import layers

ACTIVATIONS = {
    "gelu": lambda x: nn.gelu(x, approximate=False),
    "quick_gelu": lambda x: x * nn.sigmoid(1.702 * x),
    "gelu_new": lambda x: nn.gelu(x, approximate=True),
    "gelu_pytorch_tanh": lambda x: nn.gelu(x, approximate=True),
}


@dataclasses.dataclass(frozen=True)
class CLIPTextConfig:
    """Architecture fields of a transformers CLIPTextConfig (hashable, static)."""

    vocab_size: int = 49408
    hidden_size: int = 1024
    intermediate_size: int = 4096
    num_hidden_layers: int = 23
    num_attention_heads: int = 16
    max_position_embeddings: int = 77
    hidden_act: str = "gelu"
    layer_norm_eps: float = 1e-5

    @classmethod
    def from_dict(cls, cfg: dict[str, Any], source: str = "text_encoder/config.json") -> "CLIPTextConfig":
        """Validated config (InputError naming each bad field)."""
        cfg = dict(cfg.get("text_config", cfg))
        problems = ProblemList()
        act = cfg.get("hidden_act", "quick_gelu")
        if act not in ACTIVATIONS:
            problems.add(source, "hidden_act", f"{act!r} is not supported; supported: {sorted(ACTIVATIONS)}")
        hidden, heads = int(cfg.get("hidden_size", 512)), int(cfg.get("num_attention_heads", 8))
        if hidden % heads:
            problems.add(source, "num_attention_heads", f"{heads} heads do not divide hidden_size {hidden}")
        archs = cfg.get("architectures") or ["CLIPTextModel"]
        if not any(a in ("CLIPTextModel", "CLIPTextModelWithProjection", "CLIPModel") for a in archs):
            problems.add(source, "architectures", f"{archs}: not a CLIP text model")
        problems.raise_if_any()
        return cls(vocab_size=int(cfg.get("vocab_size", 49408)), hidden_size=hidden,
                   intermediate_size=int(cfg.get("intermediate_size", 2048)),
                   num_hidden_layers=int(cfg.get("num_hidden_layers", 12)), num_attention_heads=heads,
                   max_position_embeddings=int(cfg.get("max_position_embeddings", 77)), hidden_act=act,
                   layer_norm_eps=float(cfg.get("layer_norm_eps", 1e-5)))

    @classmethod
    def from_json(cls, path: str | Path) -> "CLIPTextConfig":
        return cls.from_dict(read_json(path, "not found"), str(path))


class SelfAttention(nn.Module):
    """q/k/v/out projections with biases, causal multi-head attention."""

    num_heads: int
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        channels, length = x.shape[-1], x.shape[1]
        d = lambda name: layers.dense(channels, name, self.dtype, self.precision)  # noqa: E731
        causal = jnp.tril(jnp.ones((length, length), bool))
        out = layers.dot_product_attention(d("q_proj")(x), d("k_proj")(x), d("v_proj")(x), self.num_heads,
                                           mask=causal, precision=self.precision)
        return d("out_proj")(out)


class EncoderLayer(nn.Module):
    """Pre-LayerNorm transformer layer: x + attn(ln1(x)); x + mlp(ln2(x))."""

    config: CLIPTextConfig
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        c = self.config
        x = x + SelfAttention(c.num_attention_heads, self.dtype, self.precision, name="self_attn")(
            layers.LayerNorm(c.layer_norm_eps, self.dtype, name="layer_norm1")(x))
        h = layers.LayerNorm(c.layer_norm_eps, self.dtype, name="layer_norm2")(x)
        h = _MLP(c.intermediate_size, c.hidden_act, self.dtype, self.precision, name="mlp")(h)
        return x + h


class _MLP(nn.Module):
    intermediate: int
    act: str
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        h = layers.dense(self.intermediate, "fc1", self.dtype, self.precision)(x)
        return layers.dense(x.shape[-1], "fc2", self.dtype, self.precision)(ACTIVATIONS[self.act](h))


class _Embeddings(nn.Module):
    config: CLIPTextConfig

    @nn.compact
    def __call__(self, ids):
        c = self.config
        tokens = layers.Embed(c.vocab_size, c.hidden_size, name="token_embedding")(ids)
        positions = layers.Embed(c.max_position_embeddings, c.hidden_size, name="position_embedding")(
            jnp.arange(ids.shape[1]))
        return tokens + positions[None]


class _Encoder(nn.Module):
    config: CLIPTextConfig
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, x):
        for i in range(self.config.num_hidden_layers):
            x = EncoderLayer(self.config, self.dtype, self.precision, name=f"layers_{i}")(x)
        return x


class CLIPTextTransformer(nn.Module):
    """Token ids (B, L ≤ max_position_embeddings) → last hidden state (B, L, hidden) float32."""

    config: CLIPTextConfig
    dtype: Any = jnp.float32
    precision: str = "default"

    @nn.compact
    def __call__(self, ids):
        c = self.config
        x = _Embeddings(c, name="embeddings")(ids).astype(self.dtype)
        x = _Encoder(c, self.dtype, self.precision, name="encoder")(x)
        return layers.LayerNorm(c.layer_norm_eps, self.dtype, name="final_layer_norm")(x).astype(jnp.float32)
