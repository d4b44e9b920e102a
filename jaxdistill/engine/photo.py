"""The re-rendering term: each photo rendered back from the texels and compared with the photo.

On a diffuse surface the exposed linear photo is albedo x irradiance (irradiance = E/pi, the
map's own units), so the photo fixes the product of the two maps pixel by pixel at the photos'
resolution, finer than the prior's renders, while the prior (SDS on both maps) decides the split
between them. Per view b and pixel p of the photo-sized gather plan (`--photo_size`):

    d = a ⊙ E,  a = (x_albedo + 1) / 2,  E = (x_irradiance + 1) / 2   (file space, linear light)
    r = log(photo + eps) − log(s·d + eps)   (--photo_space=log; linear: photo − s·d)
    L_photo = (1/B) Σ_b (H·W / (Hp·Wp)) Σ_p W_bp (1 − m_bp) Σ_c ρ(r_bpc)

with W the visibility weights and masks the SDS term uses (at the photo size), times the photo's
valid pixels (clipped LDR pixels dropped), m the metallic map (held fixed here: a metal's
colour comes from reflections, not from albedo x irradiance, so metal pixels drop out instead of
pulling metallic towards 0), ρ the Charbonnier penalty sqrt(r² + δ²) − δ (robust to the
highlights and the path-tracing noise no diffuse product explains) or the square, and s the
photo's scale against the maps: the least-squares value given the current maps (held fixed,
closed form) over the batch, per view (a camera's auto-exposure), per view and colour channel
(auto-exposure and auto white balance: s is then an RGB gain), or 1. `resolve_scale` turns
"auto" into "view_rgb" for scenes with LDR photos (phones and consumer cameras set exposure and
white balance per shot) and "batch" for HDR photos (one known exposure). A free scale leaves the
maps' overall brightness to the prior, as RGB<->X's irradiance has no absolute unit. The factor
H·W / (Hp·Wp) gives one photo the pixel budget of one map of the prior's renders, so
--photo_weight=1 weighs the photo like one distilled map.

`--irradiance_smoothness` adds λ_s Σ W ρ(Δ log E) over neighbouring covered pixels of the same
render: the classic prior that shading varies slowly where albedo changes (Retinex), pushing
texture detail into albedo. `--albedo_smoothness` adds λ_a Σ W g ρ(Δ log a) with g the photo's
`chroma_guide` (colour Retinex: a brightness step at constant chromaticity is light, a shadow
or sun-patch edge, so it is pushed out of the albedo into the irradiance; a colour change is not
penalised), which also averages the photos' noise out of uniformly coloured albedo.

`--photo_noise_ref=σ0` weighs each view's term (its pixel weights, so its smoothness pairs too)
by min(1, (σ0/σ_v)²), σ_v the photo's own noise in log units (`log_noise`): inverse-variance
weighting of the log residual above σ0, nothing below it. A path-traced photo with few samples
(or a dark, high-ISO shot) then cannot pull its noise into the albedo through the term, while
clean photos are used as before.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

PHOTO_EPS = 0.01            # log(x + eps): relative errors above eps, absolute below (dark noise)
CHARBONNIER_DELTA = 0.05    # ρ is quadratic below this residual, linear above
PHOTO_SPACES = ("log", "linear")
PHOTO_LOSSES = ("charbonnier", "l2")
PHOTO_SCALES = ("auto", "batch", "view", "view_rgb", "none")


def penalty(r, loss: str):
    """ρ(r) elementwise: Charbonnier sqrt(r² + δ²) − δ, or r²."""
    if loss == "l2":
        return jnp.square(r)
    return jnp.sqrt(jnp.square(r) + CHARBONNIER_DELTA ** 2) - CHARBONNIER_DELTA


def diffuse_photo(images: dict) -> jax.Array:
    """(B, H, W, 3) the diffuse image albedo ⊙ irradiance in linear file units, from model-space
    renders {map: (B, H, W, C)} (values below 0 count as 0)."""
    albedo = jnp.maximum(0.5 * (images["albedo"] + 1.0), 0.0)
    irradiance = jnp.maximum(0.5 * (images["irradiance"] + 1.0), 0.0)
    return albedo * irradiance


def pixel_weights(images: dict, weights) -> jax.Array:
    """(B, H, W) the photo term's pixel weights: W times 1 − metallic (held fixed) when metallic
    is distilled."""
    if "metallic" not in images:
        return weights
    metal = jnp.clip(0.5 * (jax.lax.stop_gradient(images["metallic"][..., 0]) + 1.0), 0.0, 1.0)
    return weights * (1.0 - metal)


SCALE_ITERATIONS = 4        # fixed-point steps of the log-space scale (each shrinks its error by Σ w·eps/(s·d + eps) / Σ w)


def resolve_scale(mode: str, ldr: bool) -> str:
    """The photo scale a run uses: `mode`, or for "auto" "view_rgb" when the photos are LDR
    (per-shot exposure and white balance) and "batch" when they are HDR."""
    if mode != "auto":
        return mode
    return "view_rgb" if ldr else "batch"


def log_scale(photo, rendered, weights, mode: str, space: str) -> jax.Array:
    """(B, 1, 1, 1) log s, the photo's scale against the rendered image (held fixed): the weighted
    least-squares value over the batch ("batch") or per view ("view"), or 0 ("none"); (B, 1, 1, 3)
    per view and channel ("view_rgb"). In log space
    it solves Σ w (log(photo + eps) − log(s·d + eps)) = 0 by fixed-point steps from the ratio of
    the means; in linear space s = Σ w·photo·d / Σ w·d²."""
    if mode == "none":
        return jnp.zeros((photo.shape[0], 1, 1, 1), jnp.float32)
    if mode not in ("batch", "view", "view_rgb"):
        raise ValueError(f"photo scale {mode!r} is not resolved: one of batch, view, view_rgb, none")
    axes = {"batch": (0, 1, 2, 3), "view": (1, 2, 3), "view_rgb": (1, 2)}[mode]
    w = jnp.broadcast_to(weights[..., None], photo.shape)
    if space == "log":
        total = jnp.maximum(jnp.sum(w, axis=axes, keepdims=True), 1e-12)
        target = jnp.log(photo + PHOTO_EPS)
        value = jnp.sum(w * (target - jnp.log(rendered + PHOTO_EPS)), axis=axes, keepdims=True) / total
        for _ in range(SCALE_ITERATIONS):
            value = value + jnp.sum(w * (target - jnp.log(jnp.exp(value) * rendered + PHOTO_EPS)), axis=axes,
                                    keepdims=True) / total
    else:
        num = jnp.sum(w * photo * rendered, axis=axes, keepdims=True)
        den = jnp.sum(w * rendered * rendered, axis=axes, keepdims=True)
        value = jnp.log(jnp.maximum(num, 1e-12) / jnp.maximum(den, 1e-12))
    value = jnp.broadcast_to(value, (photo.shape[0], 1, 1, value.shape[-1]))
    return jax.lax.stop_gradient(value)


def residual(photo, rendered, log_s, space: str) -> jax.Array:
    """(B, H, W, 3) photo − its rendering s·d, in log or linear space (`log_s` the photo's scale)."""
    if space == "log":
        return jnp.log(photo + PHOTO_EPS) - jnp.log(jnp.exp(log_s) * rendered + PHOTO_EPS)
    return photo - jnp.exp(log_s) * rendered


def pair_penalty(log_x, weights, hit, loss: str, guide=None) -> jax.Array:
    """(B,) Σ over horizontally and vertically neighbouring covered pixels of the mean of their
    weights (times guide[..., 0] for the pair (x, x+1), guide[..., 1] for (y, y+1), when given)
    times ρ(Δ log_x), summed over channels."""
    total = 0.0
    for axis in (1, 2):
        n = log_x.shape[axis]
        first = [slice(None)] * 4
        second = [slice(None)] * 4
        first[axis], second[axis] = slice(0, n - 1), slice(1, n)
        diff = log_x[tuple(second)] - log_x[tuple(first)]
        pair = (hit[tuple(second[:3])] & hit[tuple(first[:3])]).astype(jnp.float32)
        w = 0.5 * (weights[tuple(second[:3])] + weights[tuple(first[:3])]) * pair
        if guide is not None:
            w = w * guide[tuple(first[:3])][..., 2 - axis]     # axis 2 (x) → channel 0, axis 1 (y) → 1
        total = total + jnp.sum(w * jnp.sum(penalty(diff, loss), axis=-1), axis=(1, 2))
    return total


def log_map(image) -> jax.Array:
    """log(x + eps) of a model-space render of a linear map (values below 0 count as 0)."""
    return jnp.log(jnp.maximum(0.5 * (image + 1.0), 0.0) + PHOTO_EPS)


def smoothness(irradiance, weights, hit, loss: str) -> jax.Array:
    """(B,) `pair_penalty` of log-irradiance (`irradiance` model space)."""
    return pair_penalty(log_map(irradiance), weights, hit, loss)


CHROMA_SIGMA = 0.02     # chromaticity step (r, g, b)/(r + g + b) at which a pair's albedo weight falls to e^-1/2
CHROMA_FLOOR = 1e-4     # added to r + g + b, times the photo's mean: keeps black pixels' chromaticity finite


NOISE_MIN_PAIRS = 64    # fewer usable neighbour pairs than this: the noise is not estimated (σ = 0, weight 1)


def log_noise(photo: np.ndarray, usable: np.ndarray | None = None) -> float:
    """σ, the per-pixel noise of a linear photo (H, W, 3) in the term's log units: the median
    absolute difference of log(mean over channels + PHOTO_EPS) between horizontally and vertically
    neighbouring usable pixels, times 1.4826 / √2 (a Gaussian's σ from the MAD of the difference of
    two independent samples). Edges and texture touch few pairs, so the median reads the noise
    (Donoho's robust noise estimate, on neighbour differences); 0 with fewer than
    NOISE_MIN_PAIRS pairs."""
    grey = np.log(np.maximum(np.asarray(photo, np.float64), 0.0).mean(axis=-1) + PHOTO_EPS)
    u = np.ones(grey.shape, bool) if usable is None else np.asarray(usable) > 0.5
    diffs = np.concatenate([(grey[:, 1:] - grey[:, :-1])[u[:, 1:] & u[:, :-1]],
                            (grey[1:] - grey[:-1])[u[1:] & u[:-1]]])
    if diffs.size < NOISE_MIN_PAIRS:
        return 0.0
    return float(1.4826 * np.median(np.abs(diffs)) / np.sqrt(2.0))


def noise_weight(sigma: float, ref: float) -> float:
    """min(1, (ref / sigma)²): the view's weight in the term for a photo of noise σ (`log_noise`);
    1 when ref is 0 (off) or σ is 0 (not estimated)."""
    if ref <= 0 or sigma <= 0:
        return 1.0
    return float(min(1.0, (ref / sigma) ** 2))


def chroma_guide(photo: np.ndarray, usable: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 2) float32 weights of the albedo smoothness for the pairs (x, x+1) and (y, y+1) of a
    linear photo (H, W, 3): exp(−|Δc|² / (2 σ²)) with c the chromaticity of the photo box-filtered
    over 3 × 3 (path-tracing and sensor noise), σ = CHROMA_SIGMA. Light changes brightness, not
    chromaticity (white light), so a step in brightness at constant chromaticity — a shadow or sun
    patch edge — is smoothed out of the albedo (colour Retinex), while a change of colour stays.
    The last column / row (no pair) and pairs touching an unusable pixel are 0."""
    p = np.maximum(np.asarray(photo, np.float64), 0.0)
    padded = np.pad(p, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = p.shape[:2]
    box = sum(padded[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0
    total = np.sum(box, axis=-1, keepdims=True) + CHROMA_FLOOR * max(float(np.mean(p)) * 3.0, 1e-12)
    c = box / total
    out = np.zeros((h, w, 2), np.float64)
    out[:, :-1, 0] = np.exp(-np.sum(np.square(c[:, 1:] - c[:, :-1]), axis=-1) / (2 * CHROMA_SIGMA ** 2))
    out[:-1, :, 1] = np.exp(-np.sum(np.square(c[1:] - c[:-1]), axis=-1) / (2 * CHROMA_SIGMA ** 2))
    if usable is not None:
        u = np.asarray(usable, bool)
        out[:, :-1, 0] *= u[:, 1:] & u[:, :-1]
        out[:-1, :, 1] *= u[1:] & u[:-1]
    return out.astype(np.float32)


def photo_loss(images: dict, photo, weights, hit, *, loss: str, space: str, scale: str, pixel_ratio: float,
               smooth: float = 0.0, albedo_smooth: float = 0.0, guide=None) -> tuple[jax.Array, dict]:
    """(L_photo (+ the smoothness terms), metrics) for renders {map: (B, Hp, Wp, C)} of a batch,
    photos (B, Hp, Wp, 3) linear and exposed, weights (B, Hp, Wp) (visibility x masks x valid),
    hit (B, Hp, Wp) bool; `pixel_ratio` = H·W / (Hp·Wp) (the module docstring); `guide`
    (B, Hp, Wp, 2) the photos' `chroma_guide` when albedo_smooth > 0."""
    rendered = diffuse_photo(images)
    w = pixel_weights(images, weights)
    log_s = log_scale(photo, rendered, w, scale, space)
    r = residual(photo, rendered, log_s, space)
    per_view = jnp.sum(w * jnp.sum(penalty(r, loss), axis=-1), axis=(1, 2))
    batch = photo.shape[0]
    total = pixel_ratio * jnp.sum(per_view) / batch
    metrics = {"loss_photo": total, "photo_log_scale": jnp.mean(log_s)}
    if smooth > 0:
        term = smooth * pixel_ratio * jnp.sum(smoothness(images["irradiance"], weights, hit, loss)) / batch
        metrics["loss_smooth"] = term
        total = total + term
    if albedo_smooth > 0:
        term = albedo_smooth * pixel_ratio * jnp.sum(
            pair_penalty(log_map(images["albedo"]), weights, hit, loss, guide)) / batch
        metrics["loss_albedo_smooth"] = term
        total = total + term
    return total, metrics

