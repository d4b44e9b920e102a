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

from typing import Sequence

import numpy as np
from absl import logging

from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.gains import ALIGNED_MAPS
from jaxdistill.engine.problem import Problem
from jaxdistill.errors import InputError
from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.evaluate.scoring import Baseline, EvalContext
from jaxdistill.export.photo_light import TRACE_MIN_POINTS, traced_albedo_gain
from jaxdistill.io.images import is_linear_format, linear_to_srgb, linear_to_srgb_and_slope, srgb_to_linear
from jaxdistill.scene.maps import CHANNELS, MapChannels
from jaxdistill.scene.model import Scene

ANCHOR_GAIN_RANGE = (1.0 / 64.0, 64.0)
ESCAPED_WARNING = 0.001     # --anchor=traced warns when more of its rays leave the mesh into what no photo shows
GAIN_CHUNK = 1 << 20         # pixels a chunk of the anchor's sRGB means (`_display_mean_gain`)
ABOVE_ONE_LIMIT = 0.1       # ... and when its gain puts more than this fraction of the albedo texels above 1


def _display_mean_gain(render: np.ndarray, target_mean: float, tol: float = 1e-7) -> float:
    """g in ANCHOR_GAIN_RANGE with mean(srgb(g · render)) = target_mean, the range's end when the
    target is out of reach. The left side does not decrease with g: Newton's method on u = log g
    (about 5 sRGB encodes instead of bisection's 32), each step kept inside a bracket of the root
    and replaced by bisection where it would leave it or the slope is zero (every pixel clipped)."""
    r = np.asarray(render, np.float32)
    lo, hi = np.log(ANCHOR_GAIN_RANGE[0]), np.log(ANCHOR_GAIN_RANGE[1])

    def side(u: float) -> tuple[float, float]:
        """mean(srgb(clip(e^u r))) − target and its derivative in u, `GAIN_CHUNK` pixels at a time
        (float64 sums: the encoding's temporaries stay a chunk's, whatever the views and pixels)."""
        gain, value, slope = np.float32(np.exp(u)), 0.0, 0.0
        for first in range(0, len(r), GAIN_CHUNK):
            v, d = linear_to_srgb_and_slope(gain * r[first:first + GAIN_CHUNK])
            value, slope = value + v.sum(dtype=np.float64), slope + d.sum(dtype=np.float64)
        return value / max(len(r), 1) - target_mean, slope / max(len(r), 1)

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
        # the estimates' sRGB means summed a view at a time (float64), and the renders' covered values
        # written into one array per channel: the only per-pixel arrays held (the renders' values of one
        # map, where both maps' renders and estimates of every view were held before, each twice)
        count = sum(int(np.count_nonzero(h)) for h in hits)          # (hits: a sequence, read again below)
        channels = CHANNELS[m]
        render = np.empty((channels, count), np.float32)
        total, start = np.zeros(channels), 0
        for r, e, h in zip(renders, estimates, hits):
            h = np.asarray(h, bool)
            total += linear_to_srgb(np.asarray(e[m], np.float32)[h][:, :channels]).sum(axis=0, dtype=np.float64)
            seen = np.asarray(r[m], np.float32)[h]
            render[:, start:start + len(seen)] = seen.T
            start += len(seen)
        gain = [_display_mean_gain(render[c], float(total[c] / max(count, 1))) if render[c].max(initial=0.0) > 0
                else 1.0 for c in range(channels)]
        del render
        gains[m] = np.array(gain)
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
    """--anchor resolved. auto with the rgbx prior: `photos` when every photo is HDR (the scale
    from the photos' traced light where they show all the light that leaves the mesh, else from
    the estimates: `anchor_to_photos`), else `estimates` (SDS follows the prior's x̂0 and drifts
    from the estimates' overall scale); with the views prior `none` (a least-squares fusion of
    the targets has their scale already; docs/seams.md measures both)."""
    if config.anchor != "auto":
        return config.anchor
    if problem.rgbx_model is None:
        return "none"
    return "photos" if all(is_linear_format(v.photo) for v in problem.scene.views) else "estimates"


def anchor_to_baseline(config: DistillConfig, problem: Problem, texels: np.ndarray, ctx: EvalContext,
                       baseline: Baseline) -> tuple[np.ndarray, dict | None]:
    """With `--anchor` resolving to estimates (`anchor_mode`): the texels with albedo and irradiance
    scaled per channel so that their renders' sRGB mean over the covered pixels of all views is
    the baseline's (`align.anchor_gains`); with traced: albedo × g and irradiance ÷ g with g from
    the irradiance traced from the photos (`traced_albedo_gain`); with photos: traced where the
    trace can be trusted, else estimates; and what was done, for metrics.json. Otherwise the
    texels unchanged and None."""
    mode = anchor_mode(config, problem)
    if mode == "none":
        return texels, None
    if mode in ("traced", "photos"):
        anchored = anchor_to_photos(config, problem, texels, ctx, trusted_only=mode == "photos")
        if anchored is not None:
            return anchored
    gains = {}
    if baseline.views and any(m in ALIGNED_MAPS for m in problem.channels.maps):
        renders = _renders(problem, texels, ctx, ALIGNED_MAPS)
        gains = anchor_gains(renders, baseline.views, ctx.plan.hit_images(), problem.channels.maps)
    if not gains:
        if config.anchor == "estimates":     # asked for by name: say why nothing happened (auto: no colour map)
            logging.warning("--anchor=%s: nothing to anchor: %s has no %s for the distilled maps; the maps keep their "
                            "distilled scale", config.anchor, baseline.source, " or ".join(ALIGNED_MAPS))
        return texels, None
    logging.info("anchored to %s: per-channel gains %s", baseline.source,
                 ", ".join(f"{m} {np.round(g, 3).tolist()}" for m, g in gains.items()))
    warn_extreme(gains, baseline.folder or "the scene's targets")
    return (anchored_texels(texels, gains, problem.channels),
            {"to": baseline.source, "gains": {m: g.tolist() for m, g in gains.items()}})


def _renders(problem: Problem, texels: np.ndarray, ctx: EvalContext, maps) -> Sequence[dict]:
    """Per view, {map: render} of the run's `maps` alone (the render is per channel: the values of
    rendering every map, in less time), measured on the texels clipped to [-1, 1], as
    `anchored_texels` clips them before scaling."""
    channels = MapChannels(tuple(m for m in problem.channels.maps if m in maps))
    part = np.concatenate([texels[:, problem.channels.slice(m)] for m in channels.maps], axis=1)
    return evaluation.render_views(np.clip(part, -1.0, 1.0), ctx.plan, ctx.cameras, channels,
                                   lazy=problem.views_on_disk)


def warn_extreme(gains: dict[str, np.ndarray], source) -> None:
    """A warning naming each gain at the end of ANCHOR_GAIN_RANGE (the two scales disagree by more)."""
    low, high = ANCHOR_GAIN_RANGE
    extreme = [f"{m}[{c}] = {g:.3g}" for m, gs in gains.items() for c, g in enumerate(gs)
               if g <= low * 1.001 or g >= high * 0.999]
    if extreme:
        logging.warning("--anchor: %s reached the end of the gain range [%g, %g]: the renders and %s disagree "
                        "about that channel's scale by more than the range (run with --anchor=none to keep the "
                        "distilled scale)", ", ".join(extreme), low, high, source)


def traced_gains(gain: np.ndarray, maps) -> dict[str, np.ndarray]:
    """{albedo: g, irradiance: 1/g} (those of `maps`), g clipped to ANCHOR_GAIN_RANGE: the split
    moves, the product albedo ⊙ irradiance that the photos fixed stays."""
    g = np.clip(np.asarray(gain, np.float64), *ANCHOR_GAIN_RANGE)
    return {m: x for m, x in (("albedo", g), ("irradiance", 1.0 / g)) if m in maps}


def albedo_above_one(texels: np.ndarray, gain: np.ndarray, channels: MapChannels) -> float:
    """The fraction of texels whose albedo (file value, clipped to [0, 1]) times `gain` (3,)
    exceeds 1 in some channel: an albedo no surface has, so light the trace missed."""
    albedo = np.clip((np.asarray(texels[:, channels.slice("albedo")], np.float32) + 1.0) / 2.0, 0.0, 1.0)
    return float(np.mean(np.any(albedo * np.asarray(gain, np.float32) > 1.0, axis=1))) if len(albedo) else 0.0


def traced_light(scene: Scene, renders, hits, texels: np.ndarray, channels: MapChannels, *,
                 seed: int = 0) -> tuple[np.ndarray | None, dict]:
    """`traced_albedo_gain` of the run's renders, its record also holding `albedo_above_one` of the
    gain when there is one: everything `trace_trusted` reads."""
    gain, record = traced_albedo_gain(scene, renders, hits, seed=seed)
    if gain is not None:
        record["albedo_above_one"] = albedo_above_one(texels, gain, channels)
    return gain, record


def trace_trusted(record: dict) -> bool:
    """Whether a trace (`traced_light`'s record of a gain) can be trusted: at most ESCAPED_WARNING of
    its rays left the mesh with no radiance to take, i.e. the photos show a background (pixels
    that hit nothing, whose mean every escaping ray takes, whatever its direction) or almost no
    ray escapes (a closed room); and its gain puts at most ABOVE_ONE_LIMIT of the albedo texels
    above 1 (more means light the photos do not show: a ceiling light no view looks at). It does
    not see a directional sun (README "the overall scale")."""
    return record["escaped_unseen"] <= ESCAPED_WARNING and record["albedo_above_one"] <= ABOVE_ONE_LIMIT


def anchor_to_photos(config: DistillConfig, problem: Problem, texels: np.ndarray, ctx: EvalContext, *,
                     trusted_only: bool = False) -> tuple[np.ndarray, dict | None] | None:
    """The albedo's scale from the photos' own light (`traced_albedo_gain`): the anchored texels
    and the record. --anchor=traced: the texels unchanged and None when the trace has too few
    points (a warning), a warning when light left the mesh unseen. With `trusted_only`
    (--anchor=auto): None when the trace cannot be trusted (`trace_trusted`), for the estimates
    to anchor instead (an info line says why)."""
    if "albedo" not in problem.channels.maps:
        if not trusted_only:
            logging.warning("--anchor=traced: nothing to anchor: the run does not distil albedo")
            return texels, None
        return None
    renders = _renders(problem, texels, ctx, ("albedo",))
    gain, record = traced_light(problem.scene, renders, ctx.plan.hit_images(), texels, problem.channels,
                                seed=config.seed)
    if trusted_only and (gain is None or not trace_trusted(record)):
        logging.info("--anchor=auto: the photos' traced light is not used (%s): anchoring to the estimates",
                     "too few points with a known light" if gain is None else
                     f"{100 * record['escaped_unseen']:.2g} % of its rays left the mesh where no photo shows what "
                     f"lies beyond, {100 * record['albedo_above_one']:.2g} % of the albedo would exceed 1")
        return None
    if gain is None:
        logging.warning("--anchor=traced: too few surface points have a known light (%d counted of %d, at least %d "
                        "needed: the photos see too little of the room); the maps keep their distilled scale "
                        "(or run with --anchor=estimates)", record["counted"], record["points"], TRACE_MIN_POINTS)
        return texels, None
    if record["albedo_above_one"] > ABOVE_ONE_LIMIT:
        logging.warning("--anchor=traced: its gain puts %.2g %% of the albedo above 1: the photos do not show all of "
                        "the light (a light no view looks at?), so the albedo reads too bright; --anchor=auto uses "
                        "the estimates then", 100 * record["albedo_above_one"])
    if record["escaped_unseen"] > ESCAPED_WARNING:
        logging.warning("--anchor=traced: %.2g %% of the traced rays leave the mesh where no photo shows what lies "
                        "beyond (windows, openings): that light is missing from the trace, so the albedo reads too "
                        "bright (measured on generated rooms lit through windows: up to 2x; --anchor=auto uses the "
                        "estimates then)", 100 * record["escaped_unseen"])
    gains = traced_gains(gain, problem.channels.maps)
    logging.info("anchored to the photos' traced light: albedo gains %s", np.round(gains["albedo"], 3).tolist())
    warn_extreme(gains, "the photos' traced light")
    return (anchored_texels(texels, gains, problem.channels),
            {"to": "the irradiance traced from the photos", "gains": {m: g.tolist() for m, g in gains.items()},
             "trace": record})


def check_anchor(config: DistillConfig, scene: Scene) -> None:
    """Before compute: --anchor=traced reads the photos' radiance, which LDR photos have lost
    (sRGB-encoded and clipped, the lights above all, each view at its own auto-exposure)."""
    if config.anchor != "traced":
        return
    ldr = [v for v in scene.views if not is_linear_format(v.photo)]
    if ldr:
        raise InputError.single(str(ldr[0].photo), "photo", f"--anchor=traced needs linear HDR photos (EXR): "
                                f"{len(ldr)} of the {len(scene.views)} photos are LDR (sRGB-encoded, clipped; "
                                f"the first: view {ldr[0].name}), whose lights read too dark; run with "
                                f"--anchor=estimates or --anchor=none")
