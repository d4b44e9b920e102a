"""The anchor: the distilled colour maps' overall scale set to the per-view estimates' (`--anchor`).

Score distillation follows the prior's mode-seeking x̂0, not the estimates' average, and its
albedo drifts in overall brightness (staircase2: renders at 0.83× the model's own estimates in
linear light). `--anchor=estimates` measures, after the loop, one gain g_c per channel of each
aligned map such that the renders' mean over every view's covered pixels, sRGB-encoded (where
albedo is compared, `metrics.evaluate_view`, and where both colour maps are shown), equals the
estimates' (irradiance is scored scale-invariantly, so for it only the files change):

    mean_hit srgb(clip(g_c · render_c, 0, 1)) = mean_hit srgb(estimate_c)

(solved by Newton's method in log g_c inside a bisection bracket: the left side increases with
g_c), and scales the texels by it in linear light. Every texel keeps its place relative to the
others: the structure SDS found is untouched.
A mean in sRGB is less dominated by the brightest pixels than a linear one (on the held-out
rooms a linear mean lowered albedo PSNR by up to 0.5 dB, the sRGB mean changed it by −0.17 to
+0.19 dB; docs/seams.md). The per-view `gain` alignment (`engine.gains`) removes the views' disagreement
around a scale; this sets the scale itself.
"""

from __future__ import annotations

import numpy as np
from absl import logging

from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.gains import ALIGNED_MAPS
from jaxdistill.engine.problem import Problem
from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.evaluate.scoring import Baseline, EvalContext
from jaxdistill.io.images import linear_to_srgb, linear_to_srgb_and_slope, srgb_to_linear
from jaxdistill.scene.maps import MapChannels

ANCHOR_GAIN_RANGE = (1.0 / 64.0, 64.0)


def _display_mean_gain(render: np.ndarray, target_mean: float, tol: float = 1e-7) -> float:
    """g in ANCHOR_GAIN_RANGE with mean(srgb(g · render)) = target_mean, the range's end when the
    target is out of reach. The left side does not decrease with g: Newton's method on u = log g
    (about 5 sRGB encodes instead of bisection's 32), each step kept inside a bracket of the root
    and replaced by bisection where it would leave it or the slope is zero (every pixel clipped)."""
    r = np.asarray(render, np.float32)
    lo, hi = np.log(ANCHOR_GAIN_RANGE[0]), np.log(ANCHOR_GAIN_RANGE[1])

    def side(u: float) -> tuple[float, float]:
        """mean(srgb(clip(e^u r))) − target and its derivative in u."""
        value, slope = linear_to_srgb_and_slope(np.float32(np.exp(u)) * r)
        return value.mean(dtype=np.float64) - target_mean, slope.mean(dtype=np.float64)

    start = float(srgb_to_linear(np.float32(np.clip(target_mean, 0.0, 1.0)))) / max(float(r.mean()), 1e-12)     # as if linear
    u = float(np.clip(np.log(max(start, 1e-12)), lo, hi))
    for _ in range(64):
        f, slope = side(u)
        if f == 0:
            break
        if f < 0:
            lo = u
        else:
            hi = u
        step = -f / slope if slope > 0 else None
        nxt = u + step if step is not None and lo < u + step < hi else 0.5 * (lo + hi)
        converged = abs(nxt - u) < tol or hi - lo < tol
        u = nxt
        if converged:
            break
    return float(np.exp(u))


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


def anchor_mode(config: DistillConfig, problem: Problem) -> str:
    """--anchor resolved: auto is `estimates` with the rgbx prior (SDS follows the prior's x̂0 and
    drifts from the estimates' overall scale) and `none` with the views prior (a least-squares
    fusion of the targets has their scale already; docs/seams.md measures both)."""
    if config.anchor != "auto":
        return config.anchor
    return "estimates" if problem.rgbx_model is not None else "none"


def anchor_to_baseline(config: DistillConfig, problem: Problem, texels: np.ndarray, ctx: EvalContext,
                       baseline: Baseline) -> tuple[np.ndarray, dict | None]:
    """With `--anchor` resolving to estimates (`anchor_mode`): the texels with albedo and irradiance
    scaled per channel so that their renders' sRGB mean over the covered pixels of all views is
    the baseline's (`align.anchor_gains`), and what was done, for metrics.json; otherwise the
    texels unchanged and None."""
    if anchor_mode(config, problem) == "none":
        return texels, None
    gains = {}
    if baseline.views:
        # measured on the texels clipped to [-1, 1], as `anchored_texels` clips them before scaling
        renders = evaluation.render_views(np.clip(texels, -1.0, 1.0), ctx.plan, ctx.cameras, problem.channels,
                                          lazy=problem.views_on_disk)
        hits = np.asarray(ctx.plan.hit).reshape(-1, ctx.plan.height, ctx.plan.width)
        gains = anchor_gains(renders, baseline.views, list(hits), problem.channels.maps)
    if not gains:
        if config.anchor == "estimates":     # asked for by name: say why nothing happened (auto: no colour map)
            logging.warning("--anchor=%s: nothing to anchor: %s has no %s for the distilled maps; the maps keep their "
                            "distilled scale", config.anchor, baseline.source, " or ".join(ALIGNED_MAPS))
        return texels, None
    logging.info("anchored to %s: per-channel gains %s", baseline.source,
                 ", ".join(f"{m} {np.round(g, 3).tolist()}" for m, g in gains.items()))
    low, high = ANCHOR_GAIN_RANGE
    extreme = [f"{m}[{c}] = {g:.3g}" for m, gs in gains.items() for c, g in enumerate(gs)
               if g <= low * 1.001 or g >= high * 0.999]
    if extreme:
        logging.warning("--anchor: %s reached the end of the gain range [%g, %g]: the renders and the per-view "
                        "estimates disagree about that channel's scale by more than the range (check the "
                        "estimates in %s, or run with --anchor=none)", ", ".join(extreme), low, high,
                        baseline.folder or "the scene's targets")
    return (anchored_texels(texels, gains, problem.channels),
            {"to": baseline.source, "gains": {m: g.tolist() for m, g in gains.items()}})
