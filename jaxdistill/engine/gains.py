"""Photometric alignment across views: a per-view, per-channel gain on the colour maps' targets.

Single-image intrinsic estimators have an arbitrary per-image scale (and colour cast), so views
disagree about albedo and irradiance by a factor; every place where the set of views that sees a
texel changes then becomes a visible edge. With `--align=gain` the step learns, jointly with the
texels, one log-gain a_vc per view v and colour channel c of albedo and irradiance, and compares
each render with its view's target scaled in linear light:

    target_aligned = g_vc · (x + 1) − 1,    g_vc = exp(a_vc − mean_v a_vc)

(model space x = 2·linear − 1). Subtracting the mean over views anchors the overall scale: the
geometric mean of every channel's gains is exactly 1, so the textures keep the scale of the
targets (the estimates, or the prior's x̂0) on average and only the views' disagreement is
removed. A ridge term λ · W̄_v · Σ_c (a_vc − mean)², W̄_v the view's summed pixel weight (so λ is
per pixel and independent of the render size), keeps gains of views with little evidence near 1.
Normals, roughness and metallic are not scaled (unit vectors; values in [0, 1] with no
per-image scale ambiguity of the same kind).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxdistill.scene.maps import MapChannels

ALIGNED_MAPS = ("albedo", "irradiance")


def aligned_maps(channels: MapChannels) -> tuple[str, ...]:
    """The requested maps that get a per-view gain, in the texel order."""
    return tuple(m for m in channels.maps if m in ALIGNED_MAPS)


def num_gains(channels: MapChannels) -> int:
    """Gains per view: the channels of the aligned maps."""
    return sum(channels.slice(m).stop - channels.slice(m).start for m in aligned_maps(channels))


def initial_log_gains(num_views: int, channels: MapChannels) -> np.ndarray:
    """(V, G) float32 zeros: every gain starts at 1."""
    return np.zeros((num_views, num_gains(channels)), np.float32)


def centred(log_gains):
    """log-gains minus their mean over views (per channel): the gains' geometric mean is 1."""
    return log_gains - jnp.mean(log_gains, axis=0, keepdims=True)


def apply_gains(targets: dict, log_gains, view_ids, channels: MapChannels) -> dict:
    """Targets with each view's gains applied in linear light to the aligned maps.

    targets: {map: (B, H, W, C_map)} model-space images; log_gains (V, G) (not yet centred);
    view_ids (B,) int32 the views of the batch."""
    a = centred(log_gains)[view_ids]                                    # (B, G)
    out, start = dict(targets), 0
    for m in aligned_maps(channels):
        c = targets[m].shape[-1]
        gain = jnp.exp(a[:, start:start + c])[:, None, None, :]
        out[m] = gain * (targets[m] + 1.0) - 1.0
        start += c
    return out


def ridge(log_gains, view_ids, pixel_weight, strength: float):
    """λ · (1/B) Σ_b W̄_b Σ_c a_bc², a the centred log-gains of the batch's views and W̄_b the
    view's summed pixel weight (the loss's own per-view scale)."""
    a = centred(log_gains)[view_ids]
    per_view = jnp.sum(pixel_weight, axis=(1, 2))
    return strength * jnp.sum(per_view * jnp.sum(jnp.square(a), axis=-1)) / pixel_weight.shape[0]
