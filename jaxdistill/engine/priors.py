"""Priors: what each view's render of each map should look like, behind one interface.

A prior has three parts used by the distillation step (`distill.make_step`):
- `frozen`: a device pytree of constants (network weights, prompt embeddings), replicated;
- `view_data(view_ids)`: host arrays for a batch of views (photo latents, or target images);
- `features(frozen, images, key)` (differentiated): the quantity the loss compares —
  the renders themselves (image-space loss) or their VAE latents (latent-space loss);
- `targets(frozen, features, data, t, key)` (forward only, under stop_gradient): x_pred.

`images` are per-map dicts of (B, H, W, C_map) model-space renders (normals in camera space).
Two priors:
- `ViewsPrior`: the scene's per-view target images (offline RGB->X estimates, stand-ins, or GT
  for ablations). No networks; t is unused.
- `RgbxPrior`: thesis §4.2: VAE encode (mode or sample) x scaling_factor → noise at t → one
  guided UNet pass with the view's photo latent and the map's prompt → x̂0 → VAE decode →
  clamp to [-1, 1]. All maps of all views in the batch go through the networks in one call.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.scene.maps import GREY_MAPS, MapChannels
from jaxdistill.models import scheduler as sched
from jaxdistill.models.prior import Guidance, RgbxPrior as LoadedPrior, TextEmbedding, encode_photo, predict_x0


class Prior(Protocol):
    """What the step needs of a prior (`ViewsPrior`, `RgbxPrior`); see the module docstring."""

    name: str
    latent_space: bool

    @property
    def num_train_timesteps(self) -> int:
        """T: timesteps are drawn from [0, T - 1] (the diffusion schedule's length)."""

    def view_data(self, view_ids) -> dict[str, np.ndarray]:
        """Host arrays for a batch of views (the step's batch["prior"])."""

    def features(self, frozen, images: dict, key) -> dict:
        """The differentiated quantity the loss compares: the renders, or their latents."""

    def targets(self, frozen, features: dict, data: dict, t, key) -> dict:
        """x_pred per map (forward only, under stop_gradient)."""

    def target_struct(self, features: dict) -> dict:
        """Shapes and dtypes of `targets` for `features` (shapes or arrays), without running or
        tracing the prior: what a step keeps between prior passes (--reuse_steps) is shaped by it."""


@dataclasses.dataclass(frozen=True)
class ViewsPrior:
    """Per-view targets: (V, H, W, C) float32 model-space images, channels as `channels`, in
    memory or in a file read a batch at a time (`io/view_rows.py`, --view_data)."""

    channels: MapChannels
    target_images: np.ndarray = dataclasses.field(hash=False, compare=False)
    name: str = "views"
    latent_space: bool = False

    @property
    def num_train_timesteps(self) -> int:
        return 1000           # t is drawn (and reported as t_mean) but unused by the targets

    def view_data(self, view_ids) -> dict[str, np.ndarray]:
        return {"target": self.target_images[np.asarray(view_ids)]}

    def features(self, frozen, images: dict, key) -> dict:
        del frozen, key
        return images

    def targets(self, frozen, features: dict, data: dict, t, key) -> dict:
        del frozen, features, t, key
        return self.channels.split(data["target"])

    def target_struct(self, features: dict) -> dict:
        return _float32_like(features)


@dataclasses.dataclass(frozen=True)
class RgbxPrior:
    """The RGB<->X model as an SDS prior (static parts only: networks, scheduler, settings).

    photo_latents: (V, H/8, W/8, 4) float32 scaled photo latents c_v, computed once per view.
    """

    channels: MapChannels
    networks: Any
    scheduler: sched.SchedulerConfig
    guidance: Guidance
    scaling_factor: float
    photo_latents: np.ndarray = dataclasses.field(hash=False, compare=False)
    sample_latent: bool = False
    latent_space: bool = False
    name: str = "rgbx"

    @property
    def num_train_timesteps(self) -> int:
        return self.scheduler.num_train_timesteps

    def view_data(self, view_ids) -> dict[str, np.ndarray]:
        return {"photo_latent": self.photo_latents[np.asarray(view_ids)]}

    def encode(self, frozen, images: dict, key):
        """Scaled latents (B, M, h, w, 4) of all maps' renders, view-major (sharding-friendly)."""
        stacked = jnp.stack([_three_channels(images[m]) for m in self.channels.maps], axis=1)   # (B, M, H, W, 3)
        b, m = stacked.shape[:2]
        mean, logvar = self.networks.vae.apply(frozen["vae"], stacked.reshape(b * m, *stacked.shape[2:]),
                                               method="encode")
        z = mean
        if self.sample_latent:
            z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape, mean.dtype)
        return (z * self.scaling_factor).reshape(b, m, *z.shape[1:])

    def features(self, frozen, images: dict, key) -> dict:
        if not self.latent_space:
            return images
        z = self.encode(frozen, images, key)
        return {name: z[:, i] for i, name in enumerate(self.channels.maps)}

    def targets(self, frozen, features: dict, data: dict, t, key) -> dict:
        """x_pred per map: (B, H, W, C_map) images, or (B, h, w, 4) x̂0 latents in latent space.

        t: (B, M) int32 timesteps per view and map."""
        k_enc, k_noise = jax.random.split(key)
        maps = self.channels.maps
        if self.latent_space:
            z0 = jnp.stack([features[m] for m in maps], axis=1)
        else:
            z0 = self.encode(frozen, features, k_enc)
        x0 = self.denoise(frozen, z0, data, t, k_noise)
        if self.latent_space:
            return {name: x0[:, i] for i, name in enumerate(maps)}
        return self.decode(frozen, x0)

    def target_struct(self, features: dict) -> dict:
        """float32 arrays shaped like `features` (the loss compares them element by element): the
        decoded maps are cast to float32, and x̂0 is computed in float32 from the UNet's float32
        output whatever the activations' dtype."""
        return _float32_like(features)

    def denoise(self, frozen, z0, data: dict, t, key):
        """x̂0 (B, M, h, w, 4) from scaled latents z0 (B, M, h, w, 4): noise at t (B, M), then
        one guided UNet pass with each view's photo latent and each map's prompt."""
        b, m = z0.shape[:2]
        z0 = z0.reshape(b * m, *z0.shape[2:])
        t = t.reshape(b * m)
        noise = jax.random.normal(key, z0.shape, jnp.float32)
        alpha_bar = sched.alphas_cumprod(self.scheduler)[t]
        z_t = sched.add_noise(z0, noise, alpha_bar)
        photo = jnp.repeat(data["photo_latent"], m, axis=0)                  # view-major, like z0
        text = batch_text_embedding(frozen, b)
        x0 = predict_x0(self.networks.unet, self.scheduler, frozen["unet"], z_t, t, photo, text, self.guidance)
        return x0.reshape(b, m, *x0.shape[1:])

    def decode(self, frozen, x0) -> dict:
        """Per map, (B, H, W, C_map) float32 images in [-1, 1] decoded from x̂0 (B, M, h, w, 4)."""
        b, m = x0.shape[:2]
        decoded = self.networks.vae.apply(frozen["vae"], x0.reshape(b * m, *x0.shape[2:]) / self.scaling_factor,
                                          method="decode")
        decoded = jnp.clip(decoded.astype(jnp.float32), -1.0, 1.0).reshape(b, m, *decoded.shape[1:])
        return {name: decoded[:, i, ..., :1] if name in GREY_MAPS else decoded[:, i]
                for i, name in enumerate(self.channels.maps)}


def _float32_like(features: dict) -> dict:
    return {name: jax.ShapeDtypeStruct(tuple(x.shape), jnp.float32) for name, x in features.items()}


def batch_text_embedding(frozen, batch: int) -> TextEmbedding:
    """Prompt embeddings for a view-major (B * M) batch: prompt (B * M, 77, D), empty (1, 77, D)."""
    prompts = frozen["prompts"]                                          # (M, 77, D)
    return TextEmbedding(jnp.tile(prompts, (batch, 1, 1)), frozen["empty"])


def _three_channels(x):
    """Grey (…, 1) images repeated to RGB for the VAE; RGB unchanged."""
    return jnp.repeat(x, 3, axis=-1) if x.shape[-1] == 1 else x


def rgbx_frozen(loaded: LoadedPrior, channels: MapChannels) -> dict:
    """Device constants of the rgbx prior: UNet and VAE weights, prompt embeddings (M, 77, D)."""
    return {"unet": loaded.params["unet"], "vae": loaded.params["vae"],
            "prompts": jnp.concatenate([loaded.text[m].prompt for m in channels.maps]),
            "empty": loaded.text[channels.maps[0]].empty}


def make_rgbx_prior(loaded: LoadedPrior, channels: MapChannels, photos_srgb, *, guidance: Guidance,
                    sample_latent: bool, latent_space: bool, progress=None) -> tuple[RgbxPrior, dict]:
    """(prior, frozen): photo latents c_v encoded once per view (VAE mode × scaling_factor).

    photos_srgb: sequence of (H, W, 3) sRGB [0, 1] photos, sides multiples of 8."""
    photos = list(photos_srgb)
    iterator = progress(photos) if progress else photos
    latents = np.concatenate([np.asarray(encode_photo(loaded, p, f"photo {i}")) for i, p in enumerate(iterator)])
    prior = RgbxPrior(channels=channels, networks=loaded.networks, scheduler=loaded.scheduler, guidance=guidance,
                      scaling_factor=float(loaded.scaling_factor), photo_latents=latents.astype(np.float32),
                      sample_latent=sample_latent, latent_space=latent_space)
    return prior, rgbx_frozen(loaded, channels)
