"""RGB→X prediction: guided x̂0 for score distillation, and full DDIM sampling of one map.

Colour spaces: photos enter in sRGB [0, 1] and are linearised with x**2.2 (as the authors'
demo); the VAE sees [-1, 1]. Latents are NHWC and *scaled* by `scaling_factor` (0.18215) as
the UNet sees them. RGB↔X predicts v (v-prediction).

Multi-modal classifier-free guidance (thesis eq. 4.2), with w_t the text and w_i the image
weight:  v = v_uncond + w_t (v_full − v_image) + w_i (v_image − v_uncond)
           = w_t · v_full + (w_i − w_t) · v_image + (1 − w_i) · v_uncond
where full = prompt + photo latent, image = empty prompt + photo latent, uncond = empty
prompt + zero latent. Only branches with a non-zero coefficient are evaluated, batched in one
UNet call: the thesis's w_t = w_i = 1 costs one UNet pass, not three.
"""

from __future__ import annotations

import dataclasses
import functools
import zlib
from typing import Any, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.errors import InputError
from jaxdistill.models import scheduler as sched
from jaxdistill.models.convert import LoadedRgbx
from jaxdistill.models.tokenizer import MAP_PROMPTS, ClipTokenizer, load_tokenizer
from jaxdistill.models.unet import UNet2DCondition

# the authors' demo samples with these scheduler settings (docs/design.md §5)
DEMO_SCHEDULER_OVERRIDES = {"rescale_betas_zero_snr": True, "timestep_spacing": "trailing"}
PHOTO_GAMMA = 2.2
GAMMA_MAPS = ("albedo", "irradiance")   # the demo writes these with x**(1/2.2)
GREY_MAPS = ("roughness", "metallic")   # RGB↔X writes these as grey images: channel 0 holds the value


@dataclasses.dataclass(frozen=True)
class Guidance:
    """Guidance weights of eq. 4.2 (static Python floats: they select branches at trace time)."""

    text: float = 1.0
    image: float = 1.0

    def branch_weights(self) -> dict[str, float]:
        """Coefficient of each branch's prediction; branches with 0 are never evaluated."""
        return {"full": float(self.text), "image": float(self.image - self.text), "uncond": float(1.0 - self.image)}


class TextEmbedding(NamedTuple):
    """CLIP last hidden states (1, 77, D) float32 of the map prompt and of the empty prompt (the
    prompt may hold one per sample, (B, 77, D): `estimate_batch` of several maps)."""

    prompt: jax.Array
    empty: jax.Array


def guided_prediction(unet: UNet2DCondition, unet_params, noisy_latent, t, image_latent,
                      text_emb: TextEmbedding, guidance: Guidance):
    """Guided UNet output (v for RGB↔X), (B, h, w, 4) float32.

    noisy_latent (B, h, w, 4) and image_latent (B, h, w, 4) are scaled latents; t is a scalar
    or (B,) timestep; text_emb holds (1 or B, 77, D) embeddings.
    """
    batch = noisy_latent.shape[0]
    context_of = {"full": text_emb.prompt, "image": text_emb.empty, "uncond": text_emb.empty}
    active = [(name, w) for name, w in guidance.branch_weights().items() if w != 0.0]
    if not active:
        raise ValueError(f"{guidance}: every branch weight is zero")
    latents, contexts, images = [], [], []
    for name, _ in active:
        latents.append(noisy_latent)
        images.append(jnp.zeros_like(image_latent) if name == "uncond" else image_latent)
        contexts.append(jnp.broadcast_to(context_of[name], (batch,) + context_of[name].shape[1:]))
    sample = jnp.concatenate([jnp.concatenate(latents), jnp.concatenate(images)], axis=-1)
    t_all = jnp.tile(jnp.broadcast_to(jnp.asarray(t, jnp.float32).reshape(-1), (batch,)), len(active))
    out = unet.apply(unet_params, sample, t_all, jnp.concatenate(contexts))
    outs = jnp.split(out, len(active)) if len(active) > 1 else [out]
    guided = outs[0] * active[0][1]
    for (_, w), o in zip(active[1:], outs[1:]):
        guided = guided + w * o
    return guided


def predict_x0(unet: UNet2DCondition, config: sched.SchedulerConfig, unet_params, noisy_latent, t,
               image_latent, text_emb: TextEmbedding, guidance: Guidance):
    """x̂0 (B, h, w, 4), scaled latent space, from the guided prediction at x_t = noisy_latent.

    Pure; `unet`, `config` and `guidance` are static: bind them with functools.partial to get
    predict_x0(params, noisy_latent, t, image_latent, text_emb). t: scalar or (B,) int."""
    prediction = guided_prediction(unet, unet_params, noisy_latent, t, image_latent, text_emb, guidance)
    alpha_bar = sched.alphas_cumprod(config)[jnp.asarray(t, jnp.int32)]
    return sched.x0_from_prediction(prediction, noisy_latent, alpha_bar, config.prediction_type)


def photo_to_model_space(photo_srgb) -> jax.Array:
    """sRGB photo (..., H, W, 3) in [0, 1] → linear (x**2.2) → [-1, 1], as the demo feeds it."""
    lin = jnp.clip(jnp.asarray(photo_srgb, jnp.float32), 0.0, 1.0) ** PHOTO_GAMMA
    return 2.0 * lin - 1.0


def model_space_to_map(image, map_name: str, gamma: bool = True) -> jax.Array:
    """Decoded image (..., H, W, 3) in [-1, 1] → map in [0, 1]: grey maps take channel 0;
    albedo and irradiance get x**(1/2.2) when `gamma` (the demo's display encoding)."""
    x = jnp.clip((image + 1.0) / 2.0, 0.0, 1.0)
    if map_name in GREY_MAPS:
        x = jnp.repeat(x[..., :1], 3, axis=-1)
    if gamma and map_name in GAMMA_MAPS:
        x = x ** (1.0 / PHOTO_GAMMA)
    return x


@dataclasses.dataclass
class RgbxPrior:
    """A loaded RGB↔X model with its tokenizer, scheduler and the five prompt embeddings."""

    loaded: LoadedRgbx
    tokenizer: ClipTokenizer
    scheduler: sched.SchedulerConfig
    text: dict[str, TextEmbedding]       # per map name, computed once

    @property
    def networks(self):
        return self.loaded.networks

    @property
    def params(self):
        return self.loaded.params

    @property
    def scaling_factor(self) -> float:
        return self.loaded.networks.vae.config.scaling_factor


def text_embeddings(loaded: LoadedRgbx, tokenizer: ClipTokenizer, prompts: dict[str, str]) -> dict[str, TextEmbedding]:
    """CLIP last hidden states of each prompt and of the empty prompt (one encoder pass)."""
    names = list(prompts)
    ids = tokenizer.encode([prompts[n] for n in names] + [""])
    hidden = encode_text(loaded.networks.text_encoder, loaded.params["text_encoder"], jnp.asarray(ids))
    empty = hidden[-1:]
    return {n: TextEmbedding(hidden[i:i + 1], empty) for i, n in enumerate(names)}


def load_prior(loaded: LoadedRgbx, scheduler_overrides: dict | None = None) -> RgbxPrior:
    """Tokenizer, scheduler (the demo's settings unless overridden) and prompt embeddings."""
    tokenizer = load_tokenizer(loaded.folder / "tokenizer")
    overrides = dict(DEMO_SCHEDULER_OVERRIDES, **(scheduler_overrides or {}))
    config = sched.read_scheduler_config(loaded.folder / "scheduler", **overrides)
    return RgbxPrior(loaded, tokenizer, config, text_embeddings(loaded, tokenizer, MAP_PROMPTS))


@functools.partial(jax.jit, static_argnames=("networks", "config", "num_steps", "guidance"))
def _sample(networks, config, num_steps, guidance, params, image_latent, text_emb, x_T):
    def model_fn(sample, t):
        return guided_prediction(networks.unet, params["unet"], sample, t, image_latent, text_emb, guidance)

    return sched.ddim_sample(model_fn, x_T, config, num_steps)


@functools.partial(jax.jit, static_argnames=("text_encoder",))
def encode_text(text_encoder, params, ids):
    """CLIP last hidden states (B, 77, D) of token ids (B, 77), one jitted program."""
    return text_encoder.apply(params, ids)


@functools.partial(jax.jit, static_argnames=("vae",))
def encode_images(vae, vae_params, images):
    """Images (B, H, W, 3) in [-1, 1] → scaled latents (B, H/8, W/8, 4): VAE mode × scaling_factor."""
    mean, _ = vae.apply(vae_params, images, method="encode")
    return mean * vae.config.scaling_factor


@functools.partial(jax.jit, static_argnames=("vae",))
def decode_latents(vae, vae_params, latents):
    """Scaled latents (B, h, w, 4) → images (B, 8h, 8w, 3) in [-1, 1] (clamped)."""
    image = vae.apply(vae_params, latents / vae.config.scaling_factor, method="decode")
    return jnp.clip(image, -1.0, 1.0)


def encode_photo(prior: RgbxPrior, photo_srgb, name: str = "photo") -> jax.Array:
    """Photo (H, W, 3) sRGB [0, 1], sides multiples of 8 (checked) → scaled image latent
    (1, H/8, W/8, 4), the thesis's c_v."""
    photo = check_photo(photo_srgb, prior.networks.vae.config.downsampling_factor, name)
    return encode_images(prior.networks.vae, prior.params["vae"], photo_to_model_space(photo)[None])


def check_photo(photo, factor: int, name: str = "photo") -> np.ndarray:
    """The photo as float32 (H, W, 3), after checking shape, range and divisibility by `factor`."""
    photo = np.asarray(photo, np.float32)
    if photo.ndim != 3 or photo.shape[-1] != 3:
        raise InputError.single(name, "shape", f"must be (H, W, 3), got {photo.shape}")
    h, w = photo.shape[:2]
    if h % factor or w % factor:
        raise InputError.single(name, "shape", f"{w}×{h} pixels: width and height must be multiples of {factor} "
                                "(the VAE's downsampling); crop or resize the photo")
    if not np.isfinite(photo).all():
        raise InputError.single(name, "values", "contains NaN or Inf")
    return photo


def estimate(prior: RgbxPrior, photo_srgb, map_name: str, key: jax.Array, num_steps: int = 50,
             guidance: Guidance = Guidance(), gamma: bool = True) -> np.ndarray:
    """RGB→X estimate of one map for one photo: (H, W, 3) float32 in [0, 1].

    Full DDIM sampling (default 50 steps, the demo's scheduler: zero-terminal-SNR, trailing)
    from noise drawn with `key`. Albedo/irradiance come back display-encoded (x**(1/2.2)) when
    `gamma`, roughness/metallic as grey, normals as (n+1)/2 in camera space.
    """
    return estimate_from_latent(prior, encode_photo(prior, photo_srgb), map_name, key, num_steps, guidance, gamma)


def estimate_from_latent(prior: RgbxPrior, image_latent, map_name: str, key: jax.Array, num_steps: int = 50,
                         guidance: Guidance = Guidance(), gamma: bool = True) -> np.ndarray:
    """`estimate` for a photo already encoded by `encode_photo` (encode once, estimate every map)."""
    if map_name not in MAP_PROMPTS:
        raise InputError.single("estimate", "map_name", f"{map_name!r}; choose one of {sorted(MAP_PROMPTS)}")
    x_T = jax.random.normal(key, image_latent.shape, jnp.float32)  # DDIM's init_noise_sigma is 1
    return estimate_batch(prior, image_latent, map_name, x_T, num_steps, guidance, gamma)[0]


def view_map_key(key: jax.Array, view_name: str, map_name: str) -> jax.Array:
    """The noise key of one view's estimate of one map: `key` folded with the view name's CRC-32
    and the map's index, so every view and map has its own noise whatever is estimated with it."""
    return jax.random.fold_in(jax.random.fold_in(key, zlib.crc32(view_name.encode())), list(MAP_PROMPTS).index(map_name))


def compile_estimate_batch(prior: RgbxPrior, map_names: Sequence[str], latent_shape: tuple[int, ...],
                           num_steps: int = 50, guidance: Guidance = Guidance()) -> None:
    """Compiles the two programs `estimate_batch` runs for a batch of one map name per sample and
    (B, h, w, 4) latents, lowered with arguments of the kinds it passes (NumPy latents, JAX noise
    and prompts), so that its calls find them in JAX's cache instead of compiling."""
    text = TextEmbedding(jnp.concatenate([prior.text[n].prompt for n in map_names]), prior.text[map_names[0]].empty)
    _sample.lower(prior.networks, prior.scheduler, num_steps, guidance, prior.params,
                  np.zeros(latent_shape, np.float32), text, jnp.zeros(latent_shape, jnp.float32)).compile()
    decode_latents.lower(prior.networks.vae, prior.params["vae"], jnp.zeros(latent_shape, jnp.float32)).compile()


def estimate_batch(prior: RgbxPrior, image_latents, map_name: str | Sequence[str], x_T, num_steps: int = 50,
                   guidance: Guidance = Guidance(), gamma: bool = True) -> np.ndarray:
    """`estimate_from_latent` for a batch: image latents and initial noise x_T (B, h, w, 4) →
    (B, H, W, 3) float32 maps (one DDIM sampling of the whole batch). `map_name` is one map for
    the whole batch or one per sample: a batch may mix maps, each sample with its own prompt (a
    sequence gives the UNet (B, 77, D) prompts whatever it holds, so every batch of one size runs
    one compiled program)."""
    names = [map_name] * len(x_T) if isinstance(map_name, str) else list(map_name)
    if not names or len(names) != len(x_T):
        raise ValueError(f"{len(names)} map names for a batch of {len(x_T)}")
    for name in names:
        if name not in MAP_PROMPTS:
            raise InputError.single("estimate", "map_name", f"{name!r}; choose one of {sorted(MAP_PROMPTS)}")
    if isinstance(map_name, str):
        text = prior.text[map_name]
    else:
        text = TextEmbedding(jnp.concatenate([prior.text[n].prompt for n in names]), prior.text[names[0]].empty)
    latent = _sample(prior.networks, prior.scheduler, num_steps, guidance, prior.params, image_latents,
                     text, jnp.asarray(x_T, jnp.float32))
    image = decode_latents(prior.networks.vae, prior.params["vae"], latent)
    if isinstance(map_name, str):                     # one map: converted where it was decoded
        return np.asarray(model_space_to_map(image, map_name, gamma), np.float32)
    out = np.empty(image.shape[:-1] + (3,), np.float32)
    # each map's samples converted as that map: the conversion runs on the whole batch (one shape, so
    # its eager operations are compiled once per map and batch size) and keeps that map's rows
    for name in dict.fromkeys(names):
        rows = np.array([i for i, n in enumerate(names) if n == name])
        out[rows] = np.asarray(model_space_to_map(image, name, gamma))[rows]
    return out
