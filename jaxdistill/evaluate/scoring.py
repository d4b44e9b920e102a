"""Scoring a run: the views at the photos' native size, their ground truth and masks (built
once), the per-view estimates a run is compared with, and the scores of a set of renders."""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import jax
import numpy as np

from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.problem import Problem
from jaxdistill.evaluate import ground_truth as evaluation, metrics
from jaxdistill.io.view_rows import MapRows
from jaxdistill.models import estimates as model_estimates
from jaxdistill.render.fragments import FragmentRows
from jaxdistill.render.gather_plan import GatherPlan, build_gather_plans
from jaxdistill.scene.gt_file import ground_truth_maps
from jaxdistill.scene.maps import MapChannels
from jaxdistill.threads import view_bar


@dataclasses.dataclass(frozen=True)
class EvalContext:
    """The views' native (height, width), cameras, GT maps and masks, plans and seams, built once
    from the native-resolution fragments (which it does not keep: `Problem.without_fragments`)."""

    gt: object
    shapes: list
    cameras: list
    gt_maps: Sequence | None    # per view {map: GT}: a list, or a `MapRows` of files with --view_data on disk
    masks: Sequence          # per view (H, W) bool: a list, or a `ViewRows` file with --view_data on disk
    plan: GatherPlan
    seams: Sequence          # per view, its (a, b) seam pairs (`SeamPairs`: two bits a pixel in memory or a file)


class SeamPairs(Sequence):
    """Per view, its (a, b) seam pairs (`metrics.seam_pairs`), made when asked for from the view's
    packed seam edges (`packed[v]`: a list or a `ViewRows` file of `metrics.pack_seam_edges`) and
    its (H, W) in `shapes`: 2 bits a pixel held, where the pairs take up to 16 bytes a pixel."""

    def __init__(self, packed: Sequence, shapes: Sequence[tuple[int, int]]):
        if len(packed) != len(shapes):
            raise ValueError(f"{len(packed)} views' seam edges for {len(shapes)} views' shapes")
        self.packed, self.shapes = packed, list(shapes)

    def __len__(self) -> int:
        return len(self.shapes)

    def __getitem__(self, v):
        if isinstance(v, slice):
            return [self[i] for i in range(*v.indices(len(self)))]
        v = range(len(self))[v]                       # a negative index counts from the end; IndexError past it
        return metrics.seam_edge_pairs(metrics.unpack_seam_edges(self.packed[v], *self.shapes[v]))


def training_plan(problem: Problem) -> GatherPlan:
    """The gather plans of all views at the render size the run trains at."""
    return GatherPlan(index=problem.plan_index, weight=problem.plan_weight, hit=problem.plan_hit,
                      chain=problem.frozen["chain"], height=problem.height, width=problem.width)


def evaluation_context(config: DistillConfig, problem: Problem) -> EvalContext:
    """What evaluating at the photos' native size needs, built once: plans at native size (the
    training plans when the run renders at native size, the re-rendering term's when it renders
    the photos there), GT maps and masks (None without GT)."""
    scene = problem.scene
    cameras = [v.camera for v in scene.views]
    native = all((c.height, c.width) == (problem.height, problem.width) for c in cameras)
    frags = problem.native_fragments
    if frags is None:
        raise ValueError("evaluation_context needs the problem's fragments: build it before Problem.without_fragments")
    photos = problem.photos            # the re-rendering term's plans, when they are at the photos' own size
    if native:
        plan = training_plan(problem)
    elif photos is not None and all((c.height, c.width) == (photos.height, photos.width) for c in cameras):
        plan = GatherPlan(index=photos.index, weight=photos.weight, hit=photos.hit, chain=problem.frozen["chain"],
                          height=photos.height, width=photos.width)
    else:
        plan = build_gather_plans(frags, problem.space, config.sampler, empty=problem.empty_views)
    # with --view_data on disk (the fragments in files, one size) the GT maps go in files too, a view at a time
    on_disk = isinstance(frags, FragmentRows)
    gt, gt_maps = evaluation.view_ground_truth(scene, frags, out=MapRows(
        problem.view_folder, "gt", len(frags), frags.shape, ground_truth_maps(scene)) if on_disk else None)
    # with --view_data on disk (the fragments in files, one size) the masks go in a file too: 1 byte a pixel
    masks = evaluation.evaluation_masks(gt, scene, frags, out=problem.empty_views(
        "eval_masks", (len(frags), *frags.shape), bool) if on_disk else None)
    owner = evaluation.dominant_views(problem.plan_index, problem.plan_weight, problem.space.pyramid_size)
    # every view's seam pairs, kept for the scores as two bits a pixel (`metrics.pack_seam_edges`): with
    # --view_data on disk in a file, whose size the set-up's disk check counts (`problem.view_data_bytes`)
    shapes = [frags.shape] * len(frags) if isinstance(frags, FragmentRows) else [f.shape for f in frags]  # (no read)
    packed = (problem.empty_views("seams", (len(frags), metrics.seam_edge_bytes(*frags.shape)), np.uint8)
              if on_disk else [None] * len(frags))
    regions = view_bar(zip(evaluation.seam_regions(plan, frags, owner), frags, masks), "seams", len(frags))
    for v, (region, f, m) in enumerate(regions):
        packed[v] = metrics.pack_seam_edges(metrics.seam_edges(region, f.object_id, m))
    seams = SeamPairs(packed, shapes)
    return EvalContext(gt, shapes, cameras, gt_maps, masks, plan, seams)


def quick_psnr(state, problem: Problem, ctx: EvalContext) -> float:
    """Albedo PSNR (dB, sRGB, masked) of the state's renders against GT at native size; NaN
    when albedo is not distilled. Only the albedo's channels are rendered (the render is per
    channel, so the same values as rendering all maps, at about 0.4 of the time: 0.9 s against
    2.2 s on the bedroom's 48 views of 320x240, run every --eval_every steps)."""
    if "albedo" not in problem.channels.maps:
        return math.nan
    texels = np.asarray(jax.device_get(state.texels[:, problem.channels.slice("albedo")]))
    pred = evaluation.render_views(texels, ctx.plan, ctx.cameras, MapChannels(("albedo",)),
                                   lazy=problem.views_on_disk)
    return evaluation.albedo_psnr(pred, ctx.gt_maps, ctx.masks)


@dataclasses.dataclass(frozen=True)
class Baseline:
    """The per-view estimates a run is scored against (and anchored to): per view {map: (H, W, C)
    file-space image} at the evaluation size, where they come from, and the cache folder of the
    model's estimates (None for the views prior's targets)."""

    views: Sequence[dict] | None      # a list, or `LazyViews` with --view_data on disk
    source: str
    folder: Path | None = None
    steps: int | None = None          # the model's DDIM steps (--estimate_steps resolved), None for targets


def per_view_baseline(config: DistillConfig, problem: Problem, shapes: list[tuple[int, int]]) -> Baseline:
    """The rgbx prior's baseline is the model's own per-view estimates (computed once, cached);
    the views prior's is the scene's per-view targets (None when the scene has none)."""
    scene, channels = problem.scene, problem.channels
    lazy = problem.views_on_disk                    # --view_data on disk: a view's images read when asked for
    if problem.rgbx_model is None:
        return Baseline(evaluation.read_baseline(scene, channels.maps, shapes, lazy),
                        "the scene's per-view target images")
    steps, photos = _estimate_steps(config, problem), _photos(problem)
    folder = model_estimates.cached_estimates(problem.rgbx_model, photos, channels.maps, problem.height,
                                              problem.width, dtype=config.prior_dtype, steps=steps, seed=config.seed)
    views = model_estimates.read_estimates(folder, [v.name for v in scene.views], channels.maps, shapes, lazy)
    return Baseline(views, f"the model's own per-view estimates ({steps} DDIM steps, "
                    f"{folder})", folder, steps)


def compile_baseline_ahead(config: DistillConfig, problem: Problem) -> float | None:
    """Compiles the programs of the model's per-view estimates that `per_view_baseline` will
    compute (`model_estimates.compile_ahead`), for a thread beside the set-up and the loop: their
    seconds, or None when nothing will be computed (the views prior, or the estimates cached)."""
    if problem.rgbx_model is None:
        return None
    steps, photos, maps = _estimate_steps(config, problem), _photos(problem), problem.channels.maps
    if model_estimates.is_cached(problem.rgbx_model, photos, maps, problem.height, problem.width,
                                 dtype=config.prior_dtype, steps=steps, seed=config.seed):
        return None
    return model_estimates.compile_ahead(problem.rgbx_model, maps, len(photos), problem.height, problem.width,
                                         steps=steps)


def _estimate_steps(config: DistillConfig, problem: Problem) -> int:
    return config.estimate_steps or model_estimates.default_steps(problem.choice.folder)


def _photos(problem: Problem) -> list[tuple[str, Path, float]]:
    return [(v.name, v.photo, v.exposure) for v in problem.scene.views]


def improvement(ours: dict, baseline: dict) -> dict:
    """ours - baseline for every metric both have (positive is better for PSNR/SSIM, worse for errors)."""
    return {k: ours[k] - baseline[k] for k in ours if k in baseline and k != "num_views" and not k.endswith("_gt")}


def score(pred: list[dict], problem: Problem, ctx: EvalContext, baseline: Baseline) -> dict:
    """metrics.json's scores: `ours` (and the baseline's, and their difference) against the scene's
    ground truth, with a note where there is nothing to score."""
    channels = problem.channels
    if ctx.gt_maps is None:
        return {"ours": None, "note": ("the scene has no ground truth (neither gt.json in jaxdistill-gt format nor "
                                       "views' ground_truth images): no metrics against GT")}
    result = {}
    covered = sorted({m for per_view in ctx.gt_maps for m in per_view} & set(channels.maps))
    if not covered:
        result["note"] = (f"the scene's ground truth covers none of the distilled maps ({', '.join(channels.maps)})"
                          ": no metrics against GT")
    with ThreadPoolExecutor(2) as pool:          # the metrics are NumPy: two threads, two cores
        ours = pool.submit(evaluation.evaluate, pred, ctx.gt_maps, ctx.masks, ctx.seams)
        base = (pool.submit(evaluation.evaluate, baseline.views, ctx.gt_maps, ctx.masks, ctx.seams)
                if baseline.views else None)
        result["ours"] = ours.result()
        if base is not None:
            result["baseline_per_view_estimates"] = base.result()
            result["baseline_source"] = baseline.source
            if baseline.steps is not None:
                result["baseline_estimate_steps"] = baseline.steps
            result["improvement"] = improvement(result["ours"], result["baseline_per_view_estimates"])
            same = ([] if problem.rgbx_model is not None
                    else evaluation.targets_are_ground_truth(problem.scene, channels.maps))
            if same:
                result["baseline_note"] = (f"the per-view targets of {', '.join(same)} are the ground truth "
                                           "files: their baseline is GT scored against itself")
    return result
