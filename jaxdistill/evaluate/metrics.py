"""Evaluation of reconstructed per-view maps against ground truth (NumPy, float64, outside jit).

Conventions:
- Images are (H, W) or (H, W, C) arrays; pred and gt must have the same shape. Everything is
  computed in float64.
- `mask` is an (H, W) bool array of the pixels that count (None: all pixels), usually
  `evaluation_mask(fragments.hit, exclude)`. Values outside the mask never reach a metric,
  not even through the SSIM windows, and may be anything (NaN included).
- An empty mask gives NaN, never an error. Mismatched shapes raise ValueError.
- `psnr` is 10 log10(data_range^2 / mse) and is +inf for identical images; `aggregate` caps
  PSNR values at `PSNR_CAP_DB` before averaging.
- `ssim` is Wang et al. (2004): 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, weighted
  (population) moments, computed per channel and restricted to the mask by normalisation.
- Scale-invariant metrics (`si_psnr`, `si_ssim`) first fit one least-squares scale per
  channel, as the intrinsic-image literature does: albedo and lighting are only known up to
  a scale.
- `evaluate_view` takes the maps as the program holds them (albedo linear RGB, normals unit
  vectors in [-1, 1], irradiance linear HDR) and applies the per-map conventions itself.
"""

from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage

from jaxdistill import MAP_NAMES

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
PSNR_CAP_DB = 100.0
ZERO_NORMAL_LENGTH = 1e-12
"""Normals at most this long count as zero vectors (angular error 90 degrees)."""


# ----------------------------------------------------------------------------- checks

def _image(x, name: str) -> np.ndarray:
    x = np.asarray(x, np.float64)
    if x.ndim not in (2, 3):
        raise ValueError(f"{name} must be (H, W) or (H, W, C), got shape {x.shape}")
    return x


def _pair(pred, gt) -> tuple[np.ndarray, np.ndarray]:
    """pred and gt as float64 (H, W, C) arrays of the same shape."""
    pred, gt = _image(pred, "pred"), _image(gt, "gt")
    if pred.shape != gt.shape:
        raise ValueError(f"pred shape {pred.shape} does not match gt shape {gt.shape}")
    if pred.ndim == 2:
        pred, gt = pred[:, :, None], gt[:, :, None]
    return pred, gt


def _mask(mask, hw: tuple[int, ...]) -> np.ndarray:
    """(H, W) bool mask; None means all pixels."""
    if mask is None:
        return np.ones(hw, bool)
    mask = np.asarray(mask)
    if mask.dtype != bool:
        raise ValueError(f"mask must be a bool array, got dtype {mask.dtype}")
    if mask.shape != tuple(hw):
        raise ValueError(f"mask shape {mask.shape} does not match image shape (H, W) = {tuple(hw)}")
    return mask


def evaluation_mask(hit, exclude=None) -> np.ndarray:
    """(H, W) bool pixels that count: `hit & ~exclude`.

    hit: (H, W) bool, the pixel's ray hit the mesh (`Fragments.hit`). exclude: (H, W) bool or
    None, pixels whose ground truth is not meaningful (emitters, glass, mirrors).
    """
    hit = np.asarray(hit)
    if hit.ndim != 2 or hit.dtype != bool:
        raise ValueError(f"hit must be an (H, W) bool array, got shape {hit.shape}, dtype {hit.dtype}")
    if exclude is None:
        return hit.copy()
    exclude = np.asarray(exclude)
    if exclude.shape != hit.shape or exclude.dtype != bool:
        raise ValueError(f"exclude must be a bool array of shape {hit.shape}, "
                         f"got shape {exclude.shape}, dtype {exclude.dtype}")
    return hit & ~exclude


# ----------------------------------------------------------------------------- pixel errors

def mse(pred, gt, mask=None) -> float:
    """Mean squared error over the masked pixels and all channels; NaN for an empty mask."""
    pred, gt = _pair(pred, gt)
    mask = _mask(mask, pred.shape[:2])
    if not mask.any():
        return math.nan
    return float(np.mean((pred[mask] - gt[mask]) ** 2))


def psnr(pred, gt, mask=None, data_range: float = 1.0) -> float:
    """10 log10(data_range^2 / mse) in dB; +inf when mse is 0, NaN for an empty mask."""
    error = mse(pred, gt, mask)
    if math.isnan(error):
        return math.nan
    if error == 0.0:
        return math.inf
    return float(10.0 * np.log10(data_range ** 2 / error))


def grey_mse(pred, gt, mask=None) -> float:
    """MSE of grey maps (roughness, metallic): (H, W) or (H, W, C) inputs, only channel 0 used.

    Grey maps are often stored as RGB or RGBA with equal channels; other channels are ignored.
    """
    pred, gt = _image(pred, "pred"), _image(gt, "gt")
    pred = pred if pred.ndim == 2 else pred[:, :, 0]
    gt = gt if gt.ndim == 2 else gt[:, :, 0]
    return mse(pred, gt, mask)


# ----------------------------------------------------------------------------- SSIM

def _gaussian_kernel() -> np.ndarray:
    """(SSIM_WINDOW,) 1-D Gaussian taps, sigma SSIM_SIGMA, summing to 1."""
    r = SSIM_WINDOW // 2
    t = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-t ** 2 / (2.0 * SSIM_SIGMA ** 2))
    return k / k.sum()


def _gaussian_filter(x: np.ndarray) -> np.ndarray:
    """Separable Gaussian filter over axes 0 and 1 of (H, W, ...), zeros outside the image, same
    shape (SciPy's one-pass correlation per axis; float64 in, float64 out)."""
    k = _gaussian_kernel()
    y = ndimage.correlate1d(np.asarray(x, np.float64), k, axis=0, mode="constant", cval=0.0)
    return ndimage.correlate1d(y, k, axis=1, mode="constant", cval=0.0)


def ssim_map(pred, gt, mask=None, data_range: float = 1.0) -> np.ndarray:
    """(H, W, C) per-pixel, per-channel SSIM; NaN outside the mask.

    With G the Gaussian filter (zero outside the image) and m the mask, every local statistic
    is a mask-weighted Gaussian average  E[f] = G(m f) / G(m),  so pixels outside the mask
    (and outside the image) get zero weight. mu_x = E[x], sigma_x^2 = E[x^2] - mu_x^2,
    sigma_xy = E[xy] - mu_x mu_y (weighted population moments, no N/(N-1) correction), and
        SSIM = (2 mu_x mu_y + C1)(2 sigma_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2))
    with C1 = (K1 data_range)^2, C2 = (K2 data_range)^2. Without a mask this is Wang et al.'s
    Gaussian SSIM with border windows renormalised instead of zero-padded or cropped.
    """
    pred, gt = _pair(pred, gt)
    mask = _mask(mask, pred.shape[:2])
    return _ssim_of_moments(_ssim_moments(pred, gt, mask), 1.0, mask, data_range)


def _ssim_moments(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(5, H, W, C) `ssim_map`'s local moments E[x], E[y], E[x^2], E[y^2], E[xy] (float64)."""
    m = mask[:, :, None]
    x, y = np.where(m, pred, 0.0), np.where(m, gt, 0.0)
    weight = _gaussian_filter(mask.astype(np.float64))[:, :, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        stats = _gaussian_filter(np.stack([x, y, x * x, y * y, x * y], axis=-1)) / weight[..., None]
    return np.moveaxis(stats, -1, 0)


def _ssim_of_moments(moments: np.ndarray, scale, mask: np.ndarray, data_range: float) -> np.ndarray:
    """`ssim_map` of (scale * pred, gt) from pred's and gt's `_ssim_moments`: scaling pred scales
    E[x] and E[xy] by s and E[x^2] by s^2 (scale: a number or one per channel)."""
    mu_x, mu_y, xx, yy, xy = moments
    mu_x, xx, xy = mu_x * scale, xx * np.square(scale), xy * scale
    var_x, var_y, cov = xx - mu_x ** 2, yy - mu_y ** 2, xy - mu_x * mu_y
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return np.where(mask[:, :, None], s, np.nan)


def ssim(pred, gt, mask=None, data_range: float = 1.0) -> float:
    """Mean of `ssim_map` over the masked pixels and all channels; 1 for identical images,
    NaN for an empty mask."""
    return ssim_and_si_ssim(pred, gt, mask, data_range, scale_invariant_too=False)[0]


def ssim_and_si_ssim(pred, gt, mask=None, data_range: float = 1.0, *,
                     scale_invariant_too: bool = True) -> tuple[float, float]:
    """(`ssim`, `si_ssim`) of one pair from one Gaussian filtering: the scale-invariant one is SSIM
    of (s pred, gt), whose moments are pred's scaled (`_ssim_of_moments`); NaN for an empty mask
    (and si_ssim NaN unless `scale_invariant_too`)."""
    pred, gt = _pair(pred, gt)
    mask = _mask(mask, pred.shape[:2])
    if not mask.any():
        return math.nan, math.nan
    moments = _ssim_moments(pred, gt, mask)
    plain = float(np.mean(_ssim_of_moments(moments, 1.0, mask, data_range)[mask]))
    if not scale_invariant_too:
        return plain, math.nan
    scales = scale_invariant(pred, gt, mask)[1]
    return plain, float(np.mean(_ssim_of_moments(moments, scales, mask, data_range)[mask]))


# ----------------------------------------------------------------------------- scale-invariant

def scale_invariant(pred, gt, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """(s * pred, s): pred times its per-channel least-squares scale onto gt.

    s_c = sum_mask(pred_c gt_c) / sum_mask(pred_c^2), or 0 when sum_mask(pred_c^2) is 0 (an
    all-zero channel, or an empty mask). Returns the scaled pred, float64, same shape as pred,
    not clipped, and s with shape (C,) ((1,) for (H, W) input). This is the intrinsic-image
    literature's convention: albedo and lighting are only determined up to a scale each.
    """
    pred2, gt2 = _pair(pred, gt)
    mask = _mask(mask, pred2.shape[:2])
    p, g = pred2[mask], gt2[mask]                                   # (N, C)
    num, den = np.sum(p * g, axis=0), np.sum(p * p, axis=0)
    scales = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    scaled = pred2 * scales
    return scaled.reshape(np.shape(pred)), scales


def si_psnr(pred, gt, mask=None, data_range: float = 1.0) -> float:
    """`psnr` of `scale_invariant(pred, gt, mask)` against gt."""
    return psnr(scale_invariant(pred, gt, mask)[0], gt, mask, data_range)


def si_ssim(pred, gt, mask=None, data_range: float = 1.0) -> float:
    """`ssim` of `scale_invariant(pred, gt, mask)` against gt (`ssim_and_si_ssim`)."""
    return ssim_and_si_ssim(pred, gt, mask, data_range)[1]


# ----------------------------------------------------------------------------- normals

def angular_error_deg(pred, gt, mask=None) -> float:
    """Mean angle in degrees between (H, W, 3) normal vectors over the masked pixels.

    Inputs are vectors (components in [-1, 1]), not the (n + 1) / 2 image encoding; any length
    is accepted, each vector is normalised. The angle is degrees(arccos(clip(dot, -1, 1))) of the
    normalised vectors, computed as atan2(|a x b|, a . b), which is the same angle but exact near
    0 and 180 degrees. A vector of length <= ZERO_NORMAL_LENGTH in pred or gt counts as 90 degrees
    (no information: as wrong as a random guess on average). NaN for an empty mask.
    """
    pred, gt = _pair(pred, gt)
    if pred.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got shape {pred.shape}")
    mask = _mask(mask, pred.shape[:2])
    if not mask.any():
        return math.nan
    a, b = pred[mask], gt[mask]                                     # (N, 3)
    zero = (np.linalg.norm(a, axis=1) <= ZERO_NORMAL_LENGTH) | (np.linalg.norm(b, axis=1) <= ZERO_NORMAL_LENGTH)
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))
    return float(np.mean(np.where(zero, 90.0, angle)))


# ----------------------------------------------------------------------------- per view, aggregate

def _srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encode of linear values in [0, 1], float64 (as imageio.linear_to_srgb)."""
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def evaluate_view(pred: Mapping[str, np.ndarray], gt: Mapping[str, np.ndarray], mask=None) -> dict[str, float]:
    """Metrics of one view for every map present in both `pred` and `gt` (maps in only one are skipped).

    - albedo (H, W, 3) linear RGB: clipped to [0, 1] and sRGB-encoded (how albedo images are
      compared in the literature), then albedo_psnr, albedo_ssim, albedo_si_psnr, albedo_si_ssim
      with data_range 1 (the scale is fitted on the encoded values).
    - roughness, metallic (H, W) or (H, W, C), channel 0: roughness_mse, metallic_mse.
    - normal (H, W, 3) unit vectors (world or camera space, both maps the same): normal_angular_deg.
    - irradiance (H, W, C) linear HDR: irradiance_si_psnr, data_range = max of gt over the mask
      (1 when that is not positive), so it depends on neither map's exposure.
    - albedo_shading_leak (`shading_leak`) when pred has albedo and gt has albedo and irradiance:
      how much of the light the albedo carries (0 none, 1 all of it, as the photo).
    Map names outside `MAP_NAMES` raise ValueError.
    """
    for name in list(pred) + list(gt):
        if name not in MAP_NAMES:
            raise ValueError(f"unknown map {name!r}: expected one of {', '.join(MAP_NAMES)}")
    out: dict[str, float] = {}
    for name in MAP_NAMES:
        if name not in pred or name not in gt:
            continue
        try:
            out.update(_map_metrics(name, pred[name], gt[name], mask))
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None
    if "albedo" in pred and "albedo" in gt and "irradiance" in gt:
        out["albedo_shading_leak"] = shading_leak(pred["albedo"], gt["albedo"], gt["irradiance"], mask)
    return out


LEAK_FLOOR = 1e-3      # albedo luminance and irradiance below this (relative to the view's mean) are left out


def shading_leak(pred_albedo, gt_albedo, gt_irradiance, mask=None) -> float:
    """How much of the lighting an albedo map carries: the least-squares slope β of
    log(pred / gt) on log(irradiance GT), luminances (channel means, linear), over the masked
    pixels where all three are above LEAK_FLOOR times their mean (both sides centred, so an
    overall scale does not count). β = 0: the albedo's error is unrelated to the light; β = 1:
    the albedo is the photo (albedo × irradiance), all shading baked in; β < 0: it divides out
    more light than there is. NaN with fewer than two usable pixels or a uniform irradiance.
    """
    a, g = _pair(pred_albedo, gt_albedo)
    e = _image(gt_irradiance, "irradiance")
    e = e[..., None] if e.ndim == 2 else e
    if e.shape[:2] != g.shape[:2]:
        raise ValueError(f"irradiance GT {e.shape[:2]} and albedo GT {g.shape[:2]} differ in size")
    m = _mask(mask, g.shape[:2])
    la, lg, le = (np.mean(x, axis=2)[m] for x in (a, g, e))
    if la.size < 2:
        return math.nan
    usable = ((la > LEAK_FLOOR * max(np.mean(la), 1e-12)) & (lg > LEAK_FLOOR * max(np.mean(lg), 1e-12))
              & (le > LEAK_FLOOR * max(np.mean(le), 1e-12)))
    if np.count_nonzero(usable) < 2:
        return math.nan
    x = np.log(le[usable])
    y = np.log(la[usable]) - np.log(lg[usable])
    x, y = x - np.mean(x), y - np.mean(y)
    den = float(np.sum(x * x))
    return float(np.sum(x * y) / den) if den > 1e-12 else math.nan


def _map_metrics(name: str, pred, gt, mask) -> dict[str, float]:
    """`evaluate_view`'s metrics of one map."""
    p, g = _image(pred, "pred"), _image(gt, "gt")
    out: dict[str, float] = {}
    if name == "albedo":
        p, g = _srgb_encode(np.clip(p, 0.0, 1.0)), _srgb_encode(np.clip(g, 0.0, 1.0))
        out["albedo_psnr"] = psnr(p, g, mask)
        out["albedo_si_psnr"] = si_psnr(p, g, mask)
        out["albedo_ssim"], out["albedo_si_ssim"] = ssim_and_si_ssim(p, g, mask)      # one filtering
    elif name in ("roughness", "metallic"):
        out[f"{name}_mse"] = grey_mse(p, g, mask)
    elif name == "normal":
        out["normal_angular_deg"] = angular_error_deg(p, g, mask)
    elif name == "irradiance":
        m = _mask(mask, g.shape[:2])
        peak = float(np.max(g[m])) if m.any() else 1.0
        out["irradiance_si_psnr"] = si_psnr(p, g, mask, peak if peak > 0 else 1.0)
    return out


def aggregate(per_view: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Mean of each metric over the views that have it, plus `num_views` (all views given).

    NaN values (empty masks) are skipped; a metric that is NaN in every view stays NaN.
    Metrics whose name ends in "psnr" are capped at PSNR_CAP_DB before averaging, so one
    perfect view (+inf dB) counts as 100 dB instead of making the mean infinite.
    """
    values: dict[str, list[float]] = {}
    for view in per_view:
        for key, value in view.items():
            values.setdefault(key, []).append(float(value))
    out: dict[str, float] = {}
    for key, vals in values.items():
        v = np.array(vals, np.float64)
        if key.endswith("psnr"):
            v = np.minimum(v, PSNR_CAP_DB)
        v = v[~np.isnan(v)]
        out[key] = float(np.mean(v)) if v.size else math.nan
    out["num_views"] = len(per_view)
    return out


# ----------------------------------------------------------------------------- seams

def seam_edges(region, object_id, mask=None) -> np.ndarray:
    """(2, H, W) bool: [0, y, x] where pixel (y, x) and its right neighbour straddle a seam, [1, y, x]
    where it and its lower neighbour do (the last column of [0] and last row of [1] are False).

    region: (H, W) int labels whose changes are seams (a triangle, a chart, the view that
    supplies a texel's evidence: see `evaluation.seam_regions`); object_id: (H, W) int, the
    object a pixel sees. A pair straddles a seam when both pixels are in `mask`, on the same
    object (object outlines are edges in any map, not seams), with different regions. Two bits a
    pixel, a size known before the regions are (`pack_seam_edges`), where the pairs' flat indices
    take up to 16 bytes a pixel.
    """
    region, object_id = np.asarray(region), np.asarray(object_id)
    if region.ndim != 2 or object_id.shape != region.shape:
        raise ValueError(f"region and object_id must be (H, W) arrays of one shape, got {region.shape} and "
                         f"{object_id.shape}")
    mask = _mask(mask, region.shape)
    edges = np.zeros((2,) + region.shape, bool)
    for k, (a, b) in enumerate(((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:-1, :], np.s_[1:, :]))):
        edges[k][a] = mask[a] & mask[b] & (object_id[a] == object_id[b]) & (region[a] != region[b])
    return edges


def seam_edge_pairs(edges) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) flat pixel indices of `seam_edges`' pairs: the right-neighbour pairs, then the
    lower-neighbour ones, each in row-major order of a. Row-major flat indices into H * W, int32
    below 2**31 pixels (half of int64's memory)."""
    edges = np.asarray(edges, bool)
    if edges.ndim != 3 or edges.shape[0] != 2:
        raise ValueError(f"seam edges are a (2, H, W) bool array, got shape {edges.shape}")
    width = edges.shape[2]
    dtype = np.int32 if edges[0].size < 2 ** 31 else np.int64
    right, down = np.flatnonzero(edges[0]).astype(dtype), np.flatnonzero(edges[1]).astype(dtype)
    return np.concatenate([right, down]), np.concatenate([right + 1, down + width])


def seam_pairs(region, object_id, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """(a, b) flat pixel indices of the 4-neighbour pairs that straddle a seam: a pixel and its
    right or lower neighbour (`seam_edges` says which pairs, `seam_edge_pairs` in what order)."""
    return seam_edge_pairs(seam_edges(region, object_id, mask))


def seam_edge_bytes(height: int, width: int) -> int:
    """Bytes of a view's `pack_seam_edges`: two bits a pixel."""
    return (2 * height * width + 7) // 8


def pack_seam_edges(edges) -> np.ndarray:
    """`seam_edges` as (seam_edge_bytes(H, W),) uint8 bits (numpy's packbits, big-endian)."""
    return np.packbits(np.asarray(edges, bool).ravel())


def unpack_seam_edges(packed, height: int, width: int) -> np.ndarray:
    """`pack_seam_edges`' bits back as the (2, H, W) bool edges."""
    packed = np.asarray(packed, np.uint8)
    if packed.shape != (seam_edge_bytes(height, width),):
        raise ValueError(f"the seam edges of a {height}x{width} view are {seam_edge_bytes(height, width)} bytes, "
                         f"got an array of shape {packed.shape}")
    return np.unpackbits(packed, count=2 * height * width).astype(bool).reshape(2, height, width)


def seam_energy(image, pairs: tuple[np.ndarray, np.ndarray]) -> float:
    """Mean over the seam `pairs` of the squared difference across them, summed over channels
    (the image's gradient energy on seams); NaN when there is no pair."""
    image = _image(image, "image")
    flat = image.reshape(image.shape[0] * image.shape[1], -1)
    a, b = pairs
    if len(a) == 0:
        return math.nan
    return float(np.mean(np.sum((flat[a] - flat[b]) ** 2, axis=1)))


def _seam_values(name: str, pred: np.ndarray, gt: np.ndarray, mask) -> tuple[np.ndarray, np.ndarray]:
    """(pred, gt) of one map as the seam metric compares them: albedo clipped and sRGB-encoded,
    roughness/metallic channel 0, normals as vectors, irradiance scale-fitted onto gt (per
    channel) and both divided by gt's peak (exposure-free, as `irradiance_si_psnr`)."""
    p, g = _image(pred, "pred"), _image(gt, "gt")
    if name == "albedo":
        return _srgb_encode(np.clip(p, 0.0, 1.0)), _srgb_encode(np.clip(g, 0.0, 1.0))
    if name in ("roughness", "metallic"):
        return (p if p.ndim == 2 else p[:, :, 0]), (g if g.ndim == 2 else g[:, :, 0])
    if name == "irradiance":
        m = _mask(mask, g.shape[:2])
        peak = float(np.max(g[m])) if m.any() else 1.0
        peak = peak if peak > 0 else 1.0
        return scale_invariant(p, g, mask)[0] / peak, g / peak
    return p, g


def seam_metrics(pred: Mapping[str, np.ndarray], gt: Mapping[str, np.ndarray], pairs, mask=None) -> dict[str, float]:
    """Per map in both: `<map>_seam_energy` (`seam_energy` of pred on the seam `pairs`) and
    `<map>_seam_energy_gt` (the same of gt, which has no seams of ours: what pred should have)."""
    out: dict[str, float] = {}
    for name in MAP_NAMES:
        if name in pred and name in gt:
            p, g = _seam_values(name, pred[name], gt[name], mask)
            out[f"{name}_seam_energy"] = seam_energy(p, pairs)
            out[f"{name}_seam_energy_gt"] = seam_energy(g, pairs)
    return out


SEAM_GT_FLOOR = 1e-6
"""GT seam energies below this (a 0.1 % step, squared) count as none: no ratio is formed."""


def seam_ratios(aggregated: Mapping[str, float]) -> dict[str, float]:
    """For every map of an `aggregate` of `seam_metrics`: `<map>_seam_excess` = mean seam energy
    - mean GT seam energy (0 is the ground truth's) and `<map>_seam_ratio` = their quotient (1 is
    the ground truth's, above 1 seams show), NaN when GT's is below SEAM_GT_FLOOR (a map that is
    flat across the seams, where only the excess means something)."""
    out = {}
    for key, value in aggregated.items():
        if key.endswith("_seam_energy") and f"{key}_gt" in aggregated:
            gt = aggregated[f"{key}_gt"]
            out[key.replace("_seam_energy", "_seam_excess")] = value - gt
            out[key.replace("_seam_energy", "_seam_ratio")] = value / gt if gt >= SEAM_GT_FLOOR else math.nan
    return out
