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

from jaxdistill.imageio import linear_to_srgb
from jaxdistill.maps import MapChannels

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


# -- the global anchor: the distilled maps' overall scale set to the per-view estimates' -----------
#
# Score distillation follows the prior's mode-seeking x̂0, not the estimates' average, and its
# albedo drifts in overall brightness (staircase2: renders at 0.83× the model's own estimates in
# linear light). `--anchor=estimates` measures, after the loop, one gain g_c per channel of each
# aligned map such that the renders' mean over every view's covered pixels, sRGB-encoded (where
# albedo is compared, `metrics.evaluate_view`, and where both colour maps are shown), equals the
# estimates' (irradiance is scored scale-invariantly, so for it only the files change):
#
#     mean_hit srgb(clip(g_c · render_c, 0, 1)) = mean_hit srgb(estimate_c)
#
# (solved by bisection: the left side increases with g_c), and scales the texels by it in linear
# light. Every texel keeps its place relative to the others: the structure SDS found is untouched.
# A mean in sRGB is less dominated by the brightest pixels than a linear one (on the held-out
# rooms a linear mean lowered albedo PSNR by up to 0.5 dB, the sRGB mean changed it by −0.17 to
# +0.19 dB; docs/seams.md). The per-view `gain` alignment above removes the views' disagreement
# around a scale; this sets the scale itself.

ANCHOR_GAIN_RANGE = (1.0 / 64.0, 64.0)


def _display_mean_gain(render: np.ndarray, target_mean: float, iterations: int = 32) -> float:
    """g in ANCHOR_GAIN_RANGE with mean(srgb(g · render)) = target_mean (bisection on log g, to
    2e-9 relative; the range's end when the target is out of reach)."""
    lo, hi = np.log(ANCHOR_GAIN_RANGE[0]), np.log(ANCHOR_GAIN_RANGE[1])
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if linear_to_srgb(np.float32(np.exp(mid)) * render).mean(dtype=np.float64) < target_mean:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def anchor_gains(renders, estimates, hits, maps) -> dict[str, np.ndarray]:
    """{map: (C,) float64 g_c} for the aligned maps among `maps` that the estimates have.

    renders, estimates: per view {map: (H, W, C) file-space image} of the same size; hits: per
    view (H, W) bool, the pixels the mesh covers. A channel that renders black on every covered
    pixel gets gain 1 (nothing to scale)."""
    gains = {}
    for m in maps:
        if m not in ALIGNED_MAPS or not all(m in e for e in estimates):
            continue
        render = np.concatenate([np.asarray(r[m], np.float32)[h] for r, h in zip(renders, hits)])
        target = np.concatenate([np.asarray(e[m], np.float32)[h] for e, h in zip(estimates, hits)])
        gains[m] = np.array([_display_mean_gain(np.ascontiguousarray(render[:, c]),
                                                float(linear_to_srgb(target[:, c]).mean(dtype=np.float64)))
                             if render[:, c].max(initial=0.0) > 0 else 1.0 for c in range(render.shape[1])])
    return gains


def anchored_texels(texels: np.ndarray, gains: dict[str, np.ndarray], channels: MapChannels) -> np.ndarray:
    """Model-space texels with each map in `gains` scaled by its per-channel gain in linear light
    (x' = clip(g · clip(x + 1, 0, 2), 0, 2) − 1: the file value v in [0, 1] becomes g · v clipped
    to [0, 1]); other maps unchanged."""
    out = np.array(texels, np.float32, copy=True)
    for m, g in gains.items():
        part = channels.slice(m)
        out[:, part] = np.clip(np.asarray(g, np.float32) * np.clip(out[:, part] + 1.0, 0.0, 2.0), 0.0, 2.0) - 1.0
    return out
