"""Per-view evaluation of distilled texels: renders in file space, ground truth, and metrics.

Ground truth per view and map (`view_ground_truth`) comes from two sources:
- the scene's `gt.json` (format "jaxdistill-gt", as the embedded bedroom ships): per-object GT
  texture pages sampled through the scene's UVs with our bilinear gather, normals from the
  geometry (face normals as the mesh orients them, in RGB<->X camera space), and emitter
  objects excluded;
- the views' `ground_truth` images (image space, as `scripts/prepare_scene.py` and datasets
  such as FIPT's write them), for every map gt.json does not provide (all of them without one).
Views' masks drop pixels in both cases. Scenes with neither are evaluated against nothing
(metrics say so). A gt.json in our format that provides no map is refused, naming the file.
All per-view maps here are in file space (see maps.py), at the photos' native resolution.
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator, Sequence

import jax.numpy as jnp
import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.evaluate import metrics
from jaxdistill.errors import InputError
from jaxdistill.scene.cameras import camera_normals, rgbx_camera_rotation
from jaxdistill.scene.maps import CHANNELS, MapChannels, model_to_file, png_pixels
from jaxdistill.render.gather_plan import GatherPlan
from jaxdistill.io.view_rows import LazyViews
from jaxdistill.render.sampler import iter_sample_pages, render_compiled
from jaxdistill.scene.mesh import face_normals
from jaxdistill.scene.gt_file import GT_FORMAT, read_gt_document  # noqa: F401  (moved there; callers read them here)
from jaxdistill.scene.model import Scene


@dataclasses.dataclass(frozen=True, eq=False)
class GroundTruth:
    """Per-object GT texture pages per map (file space), whether normals come from geometry,
    and the objects whose pixels are excluded from metrics."""

    pages: dict            # map -> list of (S, S, C) float32, one per object
    geometry_normals: bool
    exclude_objects: tuple[str, ...]


def read_ground_truth(scene: Scene) -> GroundTruth | None:
    """The scene's gt.json ground truth, or None when the scene has none in our format."""
    doc = read_gt_document(scene.root)
    if doc is None:
        return None
    path = scene.root / "gt.json"
    names = scene.mesh.object_names
    if scene.texture_layout != "pages":
        raise InputError.single(path, "textures", "per-object GT textures need a scene with texture_layout 'pages'")
    pages = {}
    for name, per_object in doc.get("textures", {}).items():
        missing = [o for o in names if o not in per_object]
        if missing:
            raise InputError.single(path, f"textures.{name}", f"no texture for objects {missing}")
        encoding = doc.get("texture_encoding", {}).get(name, "linear")
        pages[name] = [_channels(imageio.read_image(scene.root / per_object[o], linear=encoding == "srgb"), name)
                       for o in names]
    unknown = [o for o in doc.get("exclude_objects", []) if o not in names]
    if unknown:
        raise InputError.single(path, "exclude_objects", f"{unknown} are not objects of the scene")
    return GroundTruth(pages=pages, geometry_normals=doc.get("normal") == "geometry",
                       exclude_objects=tuple(doc.get("exclude_objects", [])))


def _channels(image: np.ndarray, name: str) -> np.ndarray:
    """A GT texture with its map's channels (`maps.CHANNELS`): a grey one as R = G = B for the RGB
    maps, as targets are read (`check_gt_textures` has refused the counts a map cannot use)."""
    if image.shape[-1] == 1 and CHANNELS[name] == 3:
        return np.repeat(image, 3, axis=-1)
    return image[..., :CHANNELS[name]]


def gt_view_maps(gt: GroundTruth, scene: Scene, fragments: Sequence) -> list[dict[str, np.ndarray]]:
    """Per view, {map: (H, W, C) file-space GT} for the maps the GT provides."""
    return list(iter_gt_view_maps(gt, scene, fragments))


def iter_gt_view_maps(gt: GroundTruth, scene: Scene, fragments: Sequence) -> Iterator[dict[str, np.ndarray]]:
    """`gt_view_maps`' per-view maps a view at a time."""
    names = list(gt.pages)
    sampled = iter([None] * len(fragments))
    if names:
        stacked = [np.concatenate([gt.pages[m][o] for m in names], -1) for o in range(scene.num_objects)]
        sampled = iter_sample_pages(stacked, fragments, range(scene.num_objects))
    normals = face_normals(scene.mesh) if gt.geometry_normals else None
    for view, frag, image in zip(scene.views, fragments, sampled):
        maps, start = {}, 0
        for m in names:
            c = gt.pages[m][0].shape[-1]
            maps[m] = image[..., start:start + c]
            start += c
        if gt.geometry_normals:
            maps["normal"] = camera_normals(normals, frag.triangle, view.camera)
        yield maps


def evaluation_masks(gt: GroundTruth | None, scene: Scene, fragments: Sequence, out=None) -> Sequence[np.ndarray]:
    """Per view (H, W) bool: hit pixels not on excluded (emitter) objects nor masked by the view's
    mask. A list, or written a view at a time into `out` (V, H, W) (such as a `ViewRows` file) and
    that returned."""
    from jaxdistill.io.view_images import read_mask

    excluded = [scene.mesh.object_names.index(o) for o in (gt.exclude_objects if gt else ())]
    masks = [None] * len(fragments) if out is None else out
    for v, (view, f) in enumerate(zip(scene.views, fragments)):
        drop = np.isin(f.object_id, excluded)
        if view.mask is not None:
            drop |= ~read_mask(view.mask, *f.shape)
        masks[v] = metrics.evaluation_mask(f.hit, drop)
    return masks


def image_ground_truth(scene: Scene, fragments: Sequence) -> list[dict[str, np.ndarray]] | None:
    """Per view, {map: (H, W, C) file-space GT} from the views' `ground_truth` images (at the
    fragments' size), or None when no view has any. Views without one get {} (no metric)."""
    if not any(v.ground_truth for v in scene.views):
        return None
    return list(iter_image_ground_truth(scene, fragments))


def iter_image_ground_truth(scene: Scene, fragments: Sequence) -> Iterator[dict[str, np.ndarray]]:
    """`image_ground_truth`'s per-view maps a view at a time (for a scene whose views have some)."""
    from jaxdistill.io.view_images import read_target, resize

    for view, f in zip(scene.views, fragments):
        maps = {}
        for m, path in view.ground_truth.items():
            image = resize(read_target(m, path), *f.shape)
            maps[m] = image[..., :CHANNELS[m]]
        yield maps


def view_ground_truth(scene: Scene, fragments: Sequence, out=None) -> tuple[GroundTruth | None, Sequence | None]:
    """(gt.json ground truth or None, per view {map: (H, W, C) file-space GT} or None when the
    scene has no ground truth at all): gt.json's maps, and the views' `ground_truth` images for
    the maps gt.json does not provide. Made a view at a time: a list, or with `out` (a
    `view_rows.MapRows`, files of --view_data on disk) written into it view by view and that
    returned, so memory holds one view's maps, not every view's."""
    gt = read_ground_truth(scene)
    textured = iter_gt_view_maps(gt, scene, fragments) if gt else None
    images = iter_image_ground_truth(scene, fragments) if any(v.ground_truth for v in scene.views) else None
    if textured is None and images is None:
        return gt, None
    if textured is None or images is None:
        per_view = textured if textured is not None else images
    else:
        per_view = ({**i, **t} for t, i in zip(textured, images))
    if out is None:
        return gt, list(per_view)
    for v, maps in enumerate(per_view):
        out[v] = maps
    return gt, out


def render_views(texels, plan: GatherPlan, cameras: Sequence, channels: MapChannels,
                 chunk: int = 8, lazy: bool = False) -> Sequence[dict[str, np.ndarray]]:
    """Per view, {map: (H, W, C) file-space render} of model-space texels through the batched
    `plan` (V views), `chunk` views at a time; normals in RGB<->X camera space, 0 on misses. A
    list, or with `lazy` a `LazyViews` that renders a view's chunk when asked for (the same
    batches, so the same values, one chunk in memory: for captures whose renders would not fit)."""
    texels = jnp.asarray(texels)

    def load(start: int) -> list[dict[str, np.ndarray]]:
        ids = np.arange(start, min(start + chunk, plan.num_views))
        padded = np.pad(ids, (0, chunk - len(ids)), mode="edge")          # one shape: one compilation
        images = np.asarray(render_compiled(texels, plan.select(padded)))
        out = []
        for j, v in enumerate(ids):
            maps = channels.split(images[j])
            if "normal" in maps:
                maps["normal"] = maps["normal"] @ rgbx_camera_rotation(cameras[v].c2w).astype(np.float32)
            hit = np.asarray(plan.hit[v]).reshape(plan.height, plan.width)
            out.append({m: np.where(hit[..., None], model_to_file(m, x), 0.0) for m, x in maps.items()})
        return out

    if lazy:
        return LazyViews(plan.num_views, load, chunk)
    return [view for start in range(0, plan.num_views, chunk) for view in load(start)]


def evaluate(pred: Sequence[dict], gt: Sequence[dict], masks: Sequence[np.ndarray],
             seams: Sequence[tuple] | None = None) -> dict[str, float]:
    """Mean metrics over views (metrics.evaluate_view per view, then metrics.aggregate); with
    `seams` (per view `metrics.seam_pairs`) also the seam metrics and their ratios to GT's."""
    per_view = []
    for v, (p, g, m) in enumerate(zip(pred, gt, masks)):
        shared = {k: g[k] for k in p if k in g}
        values = metrics.evaluate_view(p, shared, m)
        if seams is not None:
            values.update(metrics.seam_metrics(p, shared, seams[v], m))
        per_view.append(values)
    out = metrics.aggregate(per_view)
    out.update(metrics.seam_ratios(out))
    return out


def dominant_views(index: np.ndarray, weight: np.ndarray, size: int) -> np.ndarray:
    """(size,) int32: per compact pyramid entry, the view whose taps read it with the largest
    summed weight (the view that supplies most of its evidence), -1 where no view reads it.
    index, weight: (V, P, T) gather plans of all views (ties go to the lower view)."""
    best = np.zeros(size, np.float64)
    owner = np.full(size, -1, np.int32)
    for v in range(index.shape[0]):
        w = np.bincount(np.asarray(index[v]).ravel(), weights=np.asarray(weight[v], np.float64).ravel(), minlength=size)
        better = w > best
        best[better], owner[better] = w[better], v
    return owner


def seam_regions(plan: GatherPlan, fragments: Sequence, owner: np.ndarray) -> Iterator[np.ndarray]:
    """Per view, (H, W) int64 region labels whose changes are seams: the triangle a pixel sees
    (triangle and chart boundaries) and the footprint it reads, i.e. the view that supplies
    most of the evidence (`dominant_views`) of the pyramid entry its heaviest tap reads. -1 on
    misses. A generator: one view's labels at a time."""
    views = int(owner.max(initial=-1)) + 2
    for v, frag in enumerate(fragments):
        one = plan if plan.index.ndim == 2 else plan.select(v)      # a view at a time (plans may be files)
        index, weight = np.asarray(one.index), np.asarray(one.weight)
        heaviest = index[np.arange(index.shape[0]), np.argmax(weight, axis=1)]
        footprint = owner[heaviest].reshape(frag.shape).astype(np.int64) + 1
        yield np.where(frag.hit, frag.triangle.astype(np.int64) * views + footprint, -1)


def albedo_psnr(pred: Sequence[dict], gt: Sequence[dict], masks: Sequence[np.ndarray]) -> float:
    """Mean albedo PSNR (sRGB-encoded, as `metrics.evaluate_view`) over views: the quick progress figure."""
    values = []
    for p, g, m in zip(pred, gt, masks):
        if "albedo" not in g:                       # a view without albedo ground truth
            continue
        a, b = (imageio.linear_to_srgb(np.clip(x["albedo"], 0.0, 1.0)) for x in (p, g))
        values.append(min(metrics.psnr(a, b, m), metrics.PSNR_CAP_DB))
    return float(np.nanmean(values)) if values else math.nan


def read_baseline(scene: Scene, maps: Sequence[str], shapes: Sequence[tuple[int, int]],
                  lazy: bool = False) -> Sequence[dict] | None:
    """Per view, the scene's target images in file space (the per-view estimates), or None if any
    is missing; a list, or with `lazy` a `LazyViews` reading a view's files when asked for."""
    from jaxdistill.io.view_images import read_target, resize

    if not all(m in view.targets for view in scene.views for m in maps):
        return None

    def load(v: int) -> list[dict]:
        (h, w), view = shapes[v], scene.views[v]
        return [{m: resize(read_target(m, view.targets[m]), h, w)[..., :3 if m not in ("roughness", "metallic")
                                                                  else 1] for m in maps}]

    views = LazyViews(len(scene.views), load)
    return views if lazy else list(views)


def targets_are_ground_truth(scene: Scene, maps: Sequence[str]) -> list[str]:
    """The maps whose per-view targets are every view's ground-truth file itself (as
    scripts/prepare_scene.py writes them): their baseline scores are GT against GT."""
    return [m for m in maps if all(m in v.targets and v.ground_truth.get(m) is not None
                                   and Path(v.targets[m]).resolve() == Path(v.ground_truth[m]).resolve()
                                   for v in scene.views)]


def write_renders(folder: Path, names: Sequence[str], views: Sequence[dict], threads: int = 2) -> None:
    """renders/<map>/<view>.png in the maps' PNG encoding (`maps.png_pixels`), a view at a time
    (`views` may be lazy: one view's images in memory)."""
    def write(job):
        path, name, image = job
        pixels, encode = png_pixels(name, image)
        imageio.write_image(path, pixels, encode_srgb=encode)

    with ThreadPoolExecutor(threads) as pool:       # encoding and NumPy release the GIL
        for name, maps in zip(names, views):
            list(pool.map(write, [(folder / m / f"{name}.png", m, image) for m, image in maps.items()]))


def display_image(name: str, image: np.ndarray) -> np.ndarray:
    """(H, W, 3) display values in [0, 1] of a file-space map: its PNG encoding, grey as RGB."""
    pixels, encode = png_pixels(name, image)
    pixels = imageio.linear_to_srgb(pixels) if encode else pixels
    return np.repeat(pixels, 3, axis=-1) if pixels.shape[-1] == 1 else pixels
