"""Everything the distillation needs that is computed once, outside jit (NumPy and I/O).

`build_problem(config)` reads the scene, resamples views to the render size, ray casts
fragments (cached), lays out the compact texel space, builds every view's gather plan,
visibility counts and pixel weights, and sets up the prior (`choose_prior` says which and why).
In a process of a multi-process run other than process 0 "every view" is the views of its
share (`distributed.held_views`), and the layout, texel space and counts are process 0's.
`Problem.batch(view_ids)` then assembles one step's host arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import time
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np
from absl import logging

from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera
from jaxdistill.engine import distributed, photo as photo_lib
from jaxdistill.engine.config import RGBX_DIR_ENV, DistillConfig, import_options, rgbx_dir
from jaxdistill.errors import InputError, ProblemList
from jaxdistill.scene.cameras import rgbx_camera_rotation
from jaxdistill.scene.maps import INITIAL_VALUE, MapChannels, file_to_model
from jaxdistill.render import fragments as fr
from jaxdistill.render.gather_plan import TAPS, TexelSpace, build_gather_plans, space_from_needs, texel_needs
from jaxdistill.render.layout import make_layout, object_pages, page_footprints, sized_layout
from jaxdistill.render.visibility import (check_coverage, coverage_summary, hit_fractions, pixel_weights,
                                         texel_evidence, view_counts)
from jaxdistill.scene.gt_file import check_gt_textures, ground_truth_maps
from jaxdistill.scene.model import Scene
from jaxdistill.threads import view_bar
from jaxdistill.scene.paths import resolve_scene_path  # noqa: F401  (--scene as a path; scripts use it from here)
from jaxdistill.io.view_images import read_mask, read_photo_linear, read_target, resize
from jaxdistill.io.view_rows import (DISK_HEADROOM, SourceRows, ViewFolder, ViewRows, free_bytes, placement,
                                     view_array)

def rgbx_hint() -> str:
    """How to obtain the RGB<->X weights, and their licence."""
    return ("download them with `huggingface-cli download zheng95z/rgb-to-x --local-dir DIR` (needs internet; "
            "Adobe Research License: non-commercial research use only, never redistribute them), then pass "
            f"--rgbx_dir=DIR or set ${RGBX_DIR_ENV}=DIR")


@dataclasses.dataclass(frozen=True)
class PriorChoice:
    """Which prior runs, why (for the log and metrics.json), and the weights folder if rgbx."""

    kind: str
    reason: str
    folder: str | None = None


def choose_prior(config: DistillConfig) -> PriorChoice:
    """rgbx or views, from --prior, --rgbx_dir and $JAXDISTILL_RGBX_DIR. The rgbx prior's weights:
    the user's (--rgbx_dir, else the variable), else the model shipped in the package
    (`models/shipped.py`). Never a silent fallback: a folder that was named but does not exist
    is an error, not a reason to use another model."""
    from jaxdistill.models.shipped import model_info, shipped_folder

    folder = rgbx_dir(config)
    source = "--rgbx_dir" if config.rgbx_dir else f"${RGBX_DIR_ENV}"
    if config.prior == "views":
        return PriorChoice("views", "--prior=views: the scene's per-view target images")
    if folder and not Path(folder).expanduser().is_dir():
        raise InputError.single("flags", source, f"{folder} does not exist; {rgbx_hint()}")
    if folder:
        return PriorChoice("rgbx", f"--prior={config.prior} with weights from {source}={folder}", folder)
    shipped = shipped_folder()
    if shipped is not None:
        info = model_info(shipped)
        return PriorChoice("rgbx", f"--prior={config.prior}: no weights given (--rgbx_dir, ${RGBX_DIR_ENV} unset), "
                           f"so the model shipped in the package, {info['name']} v{info.get('version')}: a small "
                           f"RGB<->X-family stand-in trained on synthetic rooms ({shipped / 'README.md'}); for the "
                           f"real RGB<->X, {rgbx_hint()}", str(shipped))
    if config.prior == "rgbx":
        raise InputError.single("flags", "--prior=rgbx", "needs weights and this installation has no shipped model "
                                f"(jaxdistill/models/rgbx_rooms); {rgbx_hint()}")
    return PriorChoice("views", f"--prior=auto found no RGB<->X weights (--rgbx_dir unset, ${RGBX_DIR_ENV} unset, "
                                "no shipped model): distilling the scene's per-view target images instead")


# ----------------------------------------------------------------------------- view resampling

def render_shape(scene: Scene, render_size: int, multiple: int = 1, flag: str = "--render_size") -> tuple[int, int]:
    """(height, width) every view is rendered at: the photos' size, or longer side = render_size
    (the shorter side rounded to `multiple`). All views must agree. `flag` names the setting."""
    sizes = {(v.camera.height, v.camera.width) for v in scene.views}
    if render_size == 0:
        if len(sizes) > 1:
            raise InputError.single("flags", flag, f"the views have different sizes {sorted(sizes)}; "
                                    f"set {flag} to render them all at one size")
        h, w = sizes.pop()
        if h % multiple or w % multiple:
            raise InputError.single("flags", flag, f"the photos are {w}x{h}, not multiples of {multiple} "
                                    f"(the rgbx prior's VAE needs that); set {flag}")
        return h, w
    if render_size % multiple:
        raise InputError.single("flags", flag, f"{render_size} is not a multiple of {multiple} "
                                "(the rgbx prior's VAE needs that)")
    h, w = max(sizes, key=lambda s: s[0] * s[1])
    scale = render_size / max(h, w)
    short = max(multiple, int(round(min(h, w) * scale / multiple)) * multiple)
    return (render_size, short) if h >= w else (short, render_size)


def scaled_camera(camera: Camera, height: int, width: int) -> Camera:
    """The camera re-sampled to width x height pixels (same field of view; pixel centres at +0.5)."""
    if (camera.height, camera.width) == (height, width):
        return camera
    scale = np.diag([width / camera.width, height / camera.height, 1.0])
    return Camera(scale @ camera.K, camera.c2w, width, height)


# ----------------------------------------------------------------------------- the problem

@dataclasses.dataclass(frozen=True, eq=False)
class PhotoData:
    """What the re-rendering term needs (`photo.py`), per view at (height, width): gather plans
    index (V, P, T) int32, weight (V, P, T) float32, hit (V, P) bool; photos (V, H, W, 3) float32
    linear and exposed, in memory or a `ViewRows` file (--view_data); pixel_weight (V, H, W)
    float32: the visibility weights times the view's mask times the photo's usable pixels; guide
    (V, H, W, 2) float32 the photos' `chroma_guide` (--albedo_smoothness > 0; held as the photos
    are) or None; scale the photo scale --photo_scale resolved to (`photo.resolve_scale`: "auto"
    by whether the photos are LDR); noise (V,) each photo's `photo.log_noise` and noise_weight
    (V,) the weight --photo_noise_ref gives its view (already in pixel_weight)."""

    height: int
    width: int
    index: np.ndarray
    weight: np.ndarray
    hit: np.ndarray
    photos: np.ndarray
    pixel_weight: np.ndarray
    guide: np.ndarray | None = None
    scale: str = "batch"
    noise: np.ndarray | None = None
    noise_weight: np.ndarray | None = None

    def batch(self, ids: np.ndarray) -> dict:
        out = {"photo_index": self.index[ids], "photo_tap_weight": self.weight[ids], "photo_hit": self.hit[ids],
               "photo": self.photos[ids], "photo_pixel_weight": self.pixel_weight[ids]}
        if self.guide is not None:
            out["photo_guide"] = self.guide[ids]
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """The precomputed, fixed part of a run (host NumPy arrays unless noted).

    plan_index (V, P, T) int32 / plan_weight (V, P, T) float32 / plan_hit (V, P) bool: gather
    plans of the views held (`held`) at (height, width); pixel_weight (V, H, W) float32 loss weights. Per-view
    arrays (these, the photos, the views prior's targets; fragments as `FragmentRows`) are NumPy
    or, with --view_data on disk, `ViewRows` files: read them by views (`a[ids]`), as `batch` does;
    counts (N,) int32 view counts per texel; evidence (N,) float32 summed tap weights per texel
    (`visibility.texel_evidence`); normal_rotation (V, 3, 3) float32. `held`: the views those
    per-view arrays hold, one row each in this order (a process's share of a multi-process run,
    `distributed.held_views`), or None for every view; `batch` takes views by id either way.
    counts are of every view; evidence too, in the process that holds every view (None elsewhere:
    only the outputs read it).
    """

    scene: Scene
    channels: MapChannels
    choice: PriorChoice
    prior: Any
    frozen: dict                      # device constants: {"chain", "prior", "alphas_cumprod"}
    space: TexelSpace
    fragments: list | None            # ray hits at render / native size: only the evaluation context
    native_fragments: list | None     # needs them, then `without_fragments` lets them go
    height: int
    width: int
    plan_index: np.ndarray
    plan_weight: np.ndarray
    plan_hit: np.ndarray
    pixel_weight: np.ndarray
    counts: np.ndarray
    evidence: np.ndarray | None
    normal_rotation: np.ndarray
    timings: dict
    rgbx_model: Any = None            # the loaded RgbxPrior (rgbx prior only): per-view estimates use it
    photos: PhotoData | None = None   # --photo_weight > 0: the re-rendering term's plans and photos
    view_folder: ViewFolder | None = None   # --view_data: where per-view arrays live on disk (None: memory)
    held: np.ndarray | None = None          # the views of the per-view arrays' rows (None: every view, in order)

    @property
    def num_views(self) -> int:
        return len(self.scene.views)

    @property
    def views_on_disk(self) -> bool:
        """--view_data put the per-view arrays in files: what is made per view afterwards (renders,
        estimates read back) is made a view or a chunk at a time too (`LazyViews`)."""
        return self.view_folder is not None

    def empty_views(self, name: str, shape: tuple[int, ...], dtype):
        """A new (V, ...) per-view array where this problem keeps its own (`view_rows.view_array`)."""
        return view_array(name, shape, dtype, self.view_folder)

    def without_fragments(self) -> "Problem":
        """This problem without its fragments (and native fragments): nothing after the evaluation
        context (`scoring.evaluation_context`) reads them, and they grow with views x pixels
        (44 bytes a pixel in memory, 12 or 28 in files: 1.05 GiB at 50 views of 876x584 in memory). Their
        files (--view_data on disk) are closed here, which frees their disk space now; this problem's
        fragments cannot be read after."""
        for frags in (self.fragments, self.native_fragments):
            for array in getattr(frags, "arrays", {}).values():
                if isinstance(array, ViewRows):
                    array.close()
        return dataclasses.replace(self, fragments=None, native_fragments=None)

    def initial_texels(self) -> np.ndarray:
        return self.channels.initial_texels(self.space.num_texels)

    def rows(self, view_ids) -> np.ndarray:
        """The rows of the per-view arrays that hold `view_ids`; ValueError for a view not held."""
        ids = np.asarray(view_ids)
        if self.held is None:
            return ids
        rows = np.minimum(np.searchsorted(self.held, ids), len(self.held) - 1)
        if not np.array_equal(self.held[rows], ids):
            missing = sorted(set(ids.tolist()) - set(self.held.tolist()))
            raise ValueError(f"views {missing} are not among the {len(self.held)} this process holds")
        return rows

    def batch(self, view_ids) -> dict:
        """Host arrays of one step for `view_ids` (B,)."""
        ids = np.asarray(view_ids)
        rows = self.rows(ids)
        batch = {"index": self.plan_index[rows], "weight": self.plan_weight[rows], "hit": self.plan_hit[rows],
                 "pixel_weight": self.pixel_weight[rows], "normal_rotation": self.normal_rotation[rows],
                 "view": ids.astype(np.int32), "prior": self.prior.view_data(rows)}
        if self.photos is not None:
            batch.update(self.photos.batch(rows))
        return batch

    @property
    def photo_shape(self) -> tuple[int, int]:
        """(height, width) of the re-rendered photos; (0, 0) without the re-rendering term."""
        return (self.photos.height, self.photos.width) if self.photos is not None else (0, 0)

    def view_ids(self, step: int, batch_size: int, seed: int, shares: int = 1) -> np.ndarray:
        """The views of `step`: a function of (seed, step, shares) only, so a resumed run samples the
        same. batch_size / shares views from each share (`distributed.view_share`), share q's
        in rows q * batch_size / shares onwards: with one share per process, the rows each process
        places are views it holds. One share draws from every view, as runs did before shares."""
        rng = np.random.default_rng([seed, step])
        if batch_size % shares:
            raise ValueError(f"{batch_size} views a step do not split over {shares} view shares")
        per = batch_size // shares
        parts = [distributed.view_share(self.num_views, q, shares) for q in range(shares)]
        return np.concatenate([rng.choice(part, per, replace=per > len(part)) for part in parts])


def read_view_targets(scene: Scene, maps: Sequence[str], height: int, width: int, folder: ViewFolder | None = None,
                      views: Sequence | None = None, sources: bool = False):
    """(V, H, W, C) float32 model-space targets of every view (or of `views`, some of the scene's),
    in memory, or in a `ViewRows` file of `folder` when one is given, or with `sources` (and a
    folder) read again from their files when those are at this size (`SourceRows`); InputError
    listing missing ones (of every view of the scene)."""
    problems = ProblemList()
    for i, view in enumerate(scene.views):
        for m in maps:
            if m not in view.targets:
                problems.add(scene.root / "scene.json" if scene.root else "scene", f"views[{i}].targets.{m}",
                             f"view {view.name} has no {m} target: the views prior needs one per view and map "
                             "(drop the map with --maps, or use --prior=rgbx)")
    problems.raise_if_any()
    channels = MapChannels(tuple(maps))
    views = scene.views if views is None else views
    shape = (len(views), height, width, channels.num_channels)

    def row(view) -> np.ndarray:
        return np.concatenate([file_to_model(m, resize(read_target(m, view.targets[m]), height, width))
                               for m in maps], axis=-1)

    paths = [[view.targets[m] for m in maps] for view in views]
    from_files = sources and folder is not None and files_at_size(itertools.chain(*paths), height, width)
    out = None if from_files else view_array("targets", shape, np.float32, folder)
    for i, view in enumerate(view_bar(views, "targets")):
        image = row(view)                  # read once here either way: a damaged file stops the set-up
        if out is not None:
            out[i] = image
    if from_files:
        return SourceRows(shape, np.float32, lambda v: row(views[v]), paths, name="targets")
    return out


def files_at_size(paths, height: int, width: int) -> bool:
    """Whether every image file of `paths` is `width` x `height` (headers only): then its rows are
    its pixels without resampling, and a `SourceRows` array reads them again from the file instead
    of holding a float32 copy (--view_data on disk, where the copies would not fit)."""
    return all(imageio.image_size(p)[:2] == (width, height) for p in paths)


def _views_prior(scene, views, channels, height, width, folder: ViewFolder | None, sources: bool):
    from jaxdistill.engine.priors import ViewsPrior

    return ViewsPrior(channels=channels, target_images=read_view_targets(scene, channels.maps, height, width,
                                                                         folder, views, sources)), {}


def _network_options(config: DistillConfig) -> dict:
    """How the prior's networks are built (`convert.build_networks`' dtype and attention chunk)."""
    import jax.numpy as jnp

    from jaxdistill.models import layers

    # cudnn: checked in loop.check_before_compute (dtype, prior, device, the UNet's head sizes)
    return {"dtype": {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[config.prior_dtype],
            "chunk_size": layers.FUSED_CUDNN if config.prior_attention == "cudnn" else None}


def _rgbx_prior(config: DistillConfig, choice: PriorChoice, views, channels, height, width):
    from jaxdistill.models import convert
    from jaxdistill.models import prior as rgbx
    from jaxdistill.engine.priors import make_rgbx_prior

    loaded = convert.load_rgbx(choice.folder, cache_dir=config.convert_cache, **_network_options(config))
    model = rgbx.load_prior(loaded)
    logging.info("RGB<->X loaded from %s in %.1f s", choice.folder, sum(loaded.seconds.values()))
    photos = (resize(imageio.read_photo_srgb(v.photo, v.exposure), height, width) for v in views)
    guidance = rgbx.Guidance(text=config.w_t, image=config.w_i)
    prior, frozen = make_rgbx_prior(model, channels, photos, guidance=guidance, sample_latent=config.latent == "sample",
                                    latent_space=config.loss_space == "latent",
                                    progress=lambda it: view_bar(it, "photo latents", len(views)))
    frozen["alphas_cumprod"] = np.asarray(rgbx.sched.alphas_cumprod(model.scheduler))
    return prior, frozen, model


STATE_COPIES = 3        # texels and AdamW's two moments, float32


def memory_budget() -> tuple[int, str]:
    """(bytes, what): the accelerator's memory limit when the default device reports one, else
    the host's physical memory."""
    stats = jax.devices()[0].memory_stats() if jax.default_backend() != "cpu" else None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{jax.devices()[0].device_kind} memory"
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "host RAM"


def check_state_fits(num_texels: int, channels: int, config: DistillConfig, full_texels: int,
                     budget: tuple[int, str] | None = None) -> None:
    """InputError before any allocation when the optimiser state alone (texels + AdamW moments,
    float32) cannot fit in memory, naming the flags that size it. The step needs more than the
    state (gathered taps, their cotangents): this only catches runs that cannot possibly fit."""
    need = num_texels * channels * 4 * STATE_COPIES
    limit, what = budget or memory_budget()
    if need <= limit:
        return
    hint = ("--texture_size=auto sizes pages by what the closest view resolves"
            if config.texture_size != "auto" else "lower --max_texture_size")
    if config.sampler == "trilinear":
        hint += ("; with --sampler=trilinear every texel under a coarse mip entry a view reads is a parameter, "
                 "so pages finer than the views resolve cost nearly full pages (--sampler=bilinear keeps only "
                 "the texels the views' taps read)")
    raise InputError.single("flags", "--texture_size/--max_texture_size",
                            f"{num_texels:,} texels x {channels} channels (of {full_texels:,} in full pages) need "
                            f"{need / 2**30:.1f} GiB for texels and AdamW state alone, more than the "
                            f"{limit / 2**30:.1f} GiB of {what}: {hint}")


def build_problem(config: DistillConfig, *, cache_dir=None, check_scene=None) -> Problem:
    """Reads and precomputes everything for `config`; InputError before any compute if input is bad.
    `check_scene(scene)`, if given, runs as soon as the scene is read, before any ray casting.
    Images are decoded once: validation's reads are reused by the pipeline (`imageio.cached_reads`).
    With the rgbx prior its networks' parameter shapes are traced in a thread from the start
    (`convert.trace_ahead`), beside reading the scene and casting rays; a set-up that stops early
    waits for that trace, so no thread is left running into the process's exit or the next call."""
    tracing = None
    choice = choose_prior(config)
    if choice.kind == "rgbx":
        from jaxdistill.models import convert
        tracing = convert.trace_ahead(choice.folder, **_network_options(config))
    try:
        with imageio.cached_reads():
            return _build_problem(config, choice, cache_dir=cache_dir, check_scene=check_scene)
    finally:
        if tracing is not None:
            tracing.join()            # done already when the weights were loaded (they wait for it)


def _build_problem(config: DistillConfig, choice: PriorChoice, *, cache_dir=None, check_scene=None) -> Problem:
    timings = {}
    t0 = time.perf_counter()
    from jaxdistill.datasets import open_scene

    scene = open_scene(config.scene, import_options(config.as_dict()))
    check_gt_textures(scene)                       # gt.json's textures: before any ray is cast
    if check_scene is not None:
        check_scene(scene)
    channels = MapChannels(tuple(config.maps))
    height, width = render_shape(scene, config.render_size, 8 if choice.kind == "rgbx" else 1)
    timings["read_scene_s"] = time.perf_counter() - t0
    logging.info("scene %s: %d faces, %d objects, %d views rendered at %dx%d", scene.name, scene.mesh.num_faces,
                 scene.num_objects, len(scene.views), width, height)

    # a process of a multi-process run other than the primary builds its share of the views alone
    held = distributed.held_views(len(scene.views))
    views = list(scene.views) if held is None else [scene.views[v] for v in held]
    if held is not None:
        logging.info("process %d holds %d of the %d views (share %d of %d: %s)", jax.process_index(), len(views),
                     len(scene.views), jax.process_index(), jax.process_count(),
                     ", ".join(v.name for v in views[:8]) + (", ..." if len(views) > 8 else ""))
    view_folder, sources, cache_dir = _view_data_folder(config, scene, choice, channels, (height, width), cache_dir,
                                                        views=views, evaluation=held is None)

    t0 = time.perf_counter()
    cameras = [scaled_camera(v.camera, height, width) for v in views]
    # on disk, the fragments' files keep uv_grad only for the trilinear sampler's levels; the page sizes'
    # footprints are taken per view as the fragments are made (texture_size=auto reads nothing else of them)
    object_page = object_pages(scene.num_objects, scene.texture_layout)
    fragments = functools.partial(_fragments, scene.mesh, cache_dir=cache_dir, folder=view_folder,
                                  uv_grad=config.sampler == "trilinear",
                                  footprints=functools.partial(page_footprints, object_page=object_page,
                                                               num_pages=max(object_page) + 1))
    frags = fragments(cameras)
    native = all((v.camera.height, v.camera.width) == (height, width) for v in views)
    # the evaluation's fragments, at the photos' own size: the primary's (it evaluates and writes the outputs)
    native_frags = frags if native else fragments([v.camera for v in views]) if held is None else None
    photo_frags = _photo_fragments(config, scene, views, (height, width), frags, native_frags, fragments)
    timings["fragments_s"] = time.perf_counter() - t0
    scene_file = os.fspath(scene.root / "scene.json") if scene.root and (scene.root / "scene.json").is_file() \
        else config.scene

    t0 = time.perf_counter()
    trilinear = config.sampler == "trilinear"
    empty = functools.partial(view_array, folder=view_folder)
    # What depends on every view comes from the primary, which holds them all: the layout and the texel
    # space, then the view counts (evidence: only its outputs read it). Its refusals reach every process.
    built = {}

    def layout_and_space() -> dict:
        check_coverage([v.name for v in views], hit_fractions(frags), cameras, scene.mesh, scene_file)
        size = config.texture_size if config.texture_size == "auto" else int(config.texture_size)
        # pages resolve what the finest fragments the loss sees resolve: the photos' with the re-rendering term
        sized_by = photo_frags or frags
        layout = make_layout(scene.num_objects, scene.texture_layout, size, sized_by,
                             max_size=config.max_texture_size, mipmaps=trilinear,
                             footprints=getattr(sized_by, "footprints", None))
        # evaluation renders at the photos' size: its texels must exist too (they get no gradient)
        seen = [frags] + ([] if native else [native_frags])
        if photo_frags is not None and photo_frags is not frags and photo_frags is not native_frags:
            seen.append(photo_frags)
        needs = texel_needs(itertools.chain(*seen), layout, config.sampler,      # a view at a time
                            count=sum(len(f) for f in seen))
        shared = _needs_arrays(needs) if jax.process_count() > 1 else {}
        built["space"] = space_from_needs(needs, layout)
        check_state_fits(built["space"].num_texels, channels.num_channels, config, layout.full_size())
        return {"page_sizes": np.asarray(layout.page_sizes, np.int32), **shared}

    shared = distributed.from_primary(layout_and_space)
    if held is None:
        space = built["space"]
    else:
        logging.info("%s", coverage_summary([v.name for v in views], hit_fractions(frags)))
        layout = sized_layout(scene.num_objects, scene.texture_layout, shared["page_sizes"], mipmaps=trilinear)
        space = space_from_needs(_needs_of(shared, layout), layout)
    plan = build_gather_plans(frags, space, config.sampler, empty=empty)
    if held is None:
        counts = view_counts(plan, space.num_texels)
        evidence = texel_evidence(plan, space.num_texels)
    counts = distributed.from_primary(lambda: {"counts": counts})["counts"]
    evidence = evidence if held is None else None
    layout = space.layout
    weights = _loss_weights(config, views, plan, counts, empty)
    photos = None
    if photo_frags is not None:
        photos = _photo_data(config, scene, views, photo_frags, space, counts, empty,
                             plan=plan if photo_frags is frags else None, sources=sources)
    timings["plans_s"] = time.perf_counter() - t0
    logging.info("texels: %d parameters x %d channels (%s pages, %.1fx fewer than full pages), %d observed",
                 space.num_texels, channels.num_channels, list(layout.page_sizes),
                 layout.full_size() / max(space.num_texels, 1), int((counts > 0).sum()))

    t0 = time.perf_counter()
    if choice.kind == "views":
        prior, prior_frozen = _views_prior(scene, views, channels, height, width, view_folder, sources)
        alphas, model = None, None
    else:
        prior, prior_frozen, model = _rgbx_prior(config, choice, views, channels, height, width)
        alphas = prior_frozen.pop("alphas_cumprod")
    timings["prior_setup_s"] = time.perf_counter() - t0
    frozen = {"chain": plan.chain, "prior": prior_frozen, "alphas_cumprod": alphas}
    rotations = np.stack([rgbx_camera_rotation(c.c2w) for c in cameras]).astype(np.float32)     # held views'
    return Problem(scene=scene, channels=channels, choice=choice, prior=prior, frozen=frozen, space=space,
                   fragments=frags, native_fragments=native_frags, height=height, width=width,
                   plan_index=plan.index, plan_weight=plan.weight, plan_hit=plan.hit, pixel_weight=weights,
                   counts=counts, evidence=evidence, normal_rotation=rotations, timings=timings,
                   rgbx_model=model, photos=photos, view_folder=view_folder, held=held)


def _needs_arrays(needs) -> dict[str, np.ndarray]:
    """`texel_needs`' grids as named arrays of packed bits for `distributed.from_primary`."""
    return {f"need_{p}_{j}": np.packbits(grid) for p, grids in enumerate(needs) for j, grid in enumerate(grids)}


def _needs_of(arrays: dict, layout) -> list[list[np.ndarray]]:
    """`_needs_arrays`' grids back as `texel_needs` gives them for `layout`."""
    k = int(np.log2(layout.tile))
    out = []
    for p, side in enumerate(layout.page_sizes):
        levels = layout.num_levels(p) - k if layout.mipmaps else 1
        shapes = [(side >> (k + j),) * 2 for j in range(levels)]
        out.append([np.unpackbits(arrays[f"need_{p}_{j}"], count=h * w).astype(bool).reshape(h, w)
                    for j, (h, w) in enumerate(shapes)])
    return out


def view_data_bytes(config: DistillConfig, scene: Scene, choice: PriorChoice, channels: MapChannels,
                    render: tuple[int, int], *, views: Sequence | None = None, evaluation: bool = True,
                    form: str = "copies") -> int:
    """Bytes of the per-view arrays the set-up and the evaluation context make for `views` (the
    views this process holds, default all) when they are files (--view_data on disk): the fragments
    (12 bytes a pixel, 28 with the trilinear sampler's uv_grad: `fragments.row_bytes_per_pixel`) and gather plans (T taps of an int32 index and a
    float32 weight, a float32 pixel weight and a 1-byte hit mask) at the render size, the views
    prior's targets (C float32 channels) there, and with the re-rendering term fragments, plans,
    photos (3 float32) and chroma guides (2, --albedo_smoothness) at the photo size; the
    evaluation's (`evaluation`: the primary's) 1-byte masks at the photos' own size, with fragments
    and plans (no pixel weight) there when neither size is theirs, its seam pairs, two bits a pixel
    there (`metrics.seam_edge_bytes`, a view's bits in whole bytes), and its ground-truth maps,
    float32 channels there (`gt_file.ground_truth_maps`: a file per map a view has, all views'
    rows). `form`: "copies", the bytes in files with every image copied into them; "sources", where
    targets and photos whose files are at their size take none (`SourceRows`: read again from the
    scene's files); "memory", what the same arrays take in memory (--view_data=memory), which
    --view_data=auto weighs."""
    if form not in ("copies", "sources", "memory"):
        raise ValueError(f"form must be copies, sources or memory, got {form!r}")
    sources = form == "sources"
    held = scene.views if views is None else views
    taps = TAPS[config.sampler]
    # fragments: in memory all their fields (a list of `Fragments`), in files what `FragmentRows` keeps
    frag = fr.BYTES_PER_PIXEL if form == "memory" else fr.row_bytes_per_pixel(uv_grad=config.sampler == "trilinear")
    plan = 8 * taps + 4 + 1
    targets = choice.kind == "views" and not (sources and files_at_size(
        (v.targets[m] for v in held for m in channels.maps if m in v.targets), *render))
    per_pixel = {render: frag + plan + (4 * channels.num_channels if targets else 0)}
    if config.photo_weight > 0:
        photo = render_shape(scene, config.photo_size, flag="--photo_size")
        photos = not (sources and files_at_size((v.photo for v in held), *photo))
        images = 4 * ((3 if photos else 0) + (2 if config.albedo_smoothness > 0 else 0))
        # the photos' own pixel weights even where they share the render size's fragments and plans
        per_pixel[photo] = per_pixel.get(photo, 0) + images + (4 if photo in per_pixel else frag + plan)
    sizes = {(v.camera.height, v.camera.width) for v in scene.views}
    native = next(iter(sizes)) if len(sizes) == 1 else None
    if evaluation and native is not None:
        # the masks; the fragments and plans too (the hit mask, no pixel weight) when no other size is theirs
        per_pixel[native] = per_pixel.get(native, frag + plan - 4) + 1 + 4 * sum(ground_truth_maps(scene).values())
    seams = len(held) * ((2 * native[0] * native[1] + 7) // 8) if evaluation and native is not None else 0
    return seams + sum(len(held) * h * w * nbytes for (h, w), nbytes in per_pixel.items())


def _view_data_folder(config: DistillConfig, scene: Scene, choice: PriorChoice, channels: MapChannels,
                      render: tuple[int, int], cache_dir, *, views: Sequence | None = None,
                      evaluation: bool = True) -> tuple[ViewFolder | None, bool, Any]:
    """(folder, sources, casts' cache), decided before any compute from the disk's free space.

    folder: where the per-view arrays are held (--view_data: None for memory, else the cache's
    `ViewFolder`); sources: whether targets and photos at their files' size are read again from
    those files (`SourceRows`) instead of copied into float32 files, which is done only where the
    copies would not fit (reading them back costs each batch its decoding: 1.04 s against 0.23 s
    for 8 views of 876x584 of the capture room, 2.53 s a step against 2.14; the same values bit for bit);
    per-view files that would not fit either way are refused, naming the folder. The casts' cache:
    `cache_dir`, or False (cast, not kept) where the ray casts not cached yet would not fit beside
    the per-view files (a warning says so; a cache changes no result, and casting is the cheap part
    of the fragments). `views`: the views this process holds (default all)."""
    held = scene.views if views is None else views
    folder, sources, nbytes = None, False, 0
    kwargs = dict(views=held, evaluation=evaluation)
    where = Path(cache_dir) if cache_dir else fr.default_cache_dir()
    if placement(config.view_data, view_data_bytes(config, scene, choice, channels, render, form="memory", **kwargs)):
        folder = ViewFolder(where)
        what = f"the per-view arrays of {len(held)} views (--view_data={config.view_data})"
        nbytes = view_data_bytes(config, scene, choice, channels, render, form="copies", **kwargs)
        free = free_bytes(folder.root)
        if free is not None and nbytes + DISK_HEADROOM > free:
            sourced = view_data_bytes(config, scene, choice, channels, render, form="sources", **kwargs)
            if sourced < nbytes:
                logging.warning("%s: %.2f GB of files would not fit in %s (%.2f GB free); targets and photos are read "
                                "again from the scene's files for each batch instead of copied (%.2f GB of files; "
                                "slower batches, the same values)", what, nbytes / 2 ** 30, folder.root,
                                free / 2 ** 30, sourced / 2 ** 30)
                sources, nbytes = True, sourced
        folder.check_space(nbytes, what)
        logging.info("%s: %.2f GB on disk in %s, read a batch at a time", what, nbytes / 2 ** 30, folder.root)
    missing = fr.uncached_cameras(scene.mesh, _cameras_cast(config, scene, render, held, evaluation), cache_dir)
    casts = fr.cast_bytes(missing)
    if not casts:
        return folder, sources, cache_dir
    free = free_bytes(where)
    if free is not None and nbytes + casts + DISK_HEADROOM > free:
        gb = 2 ** 30
        logging.warning("the ray casts are not cached: those of %d views not cached yet (%.2f GB) would not fit in "
                        "%s beside %.2f GB of per-view files (%.2f GB free, %.2f GB kept free); the set-up casts them "
                        "without keeping them, and a later run casts them again (point $JAXDISTILL_CACHE at a larger "
                        "disk to keep them)", len(missing), casts / gb,
                        where / "fragments", nbytes / gb, free / gb, DISK_HEADROOM / gb)
        return folder, sources, False
    return folder, sources, cache_dir


def _cameras_cast(config: DistillConfig, scene: Scene, render: tuple[int, int], views: Sequence,
                  evaluation: bool = True) -> list[Camera]:
    """Every camera the set-up casts rays for, of `views` (the views this process holds): at the
    render size, the photos' own (`evaluation`: the primary's), and the photo size."""
    cameras = [scaled_camera(v.camera, *render) for v in views] + ([v.camera for v in views] if evaluation else [])
    if config.photo_weight > 0:
        photo = render_shape(scene, config.photo_size, flag="--photo_size")
        cameras += [scaled_camera(v.camera, *photo) for v in views]
    return cameras


def _loss_weights(config: DistillConfig, views: Sequence, plan, counts: np.ndarray, empty):
    """(V, H, W) float32 pixel weights of `plan`'s views (`views`, in order: visibility weights, or
    the hit mask with --visibility_weighting=false) times each view's mask (emitters, anonymised
    faces, unfilled pixels), in an array from `empty`, a view at a time."""
    height, width = plan.height, plan.width
    weights = empty("pixel_weight", (plan.num_views, height, width), np.float32)
    if config.visibility_weighting:
        pixel_weights(plan, counts, out=weights)
    else:
        for v in range(plan.num_views):
            weights[v] = plan.hit[v].reshape(height, width).astype(np.float32)
    for v, view in enumerate(views):
        if view.mask is not None:
            weights[v] = weights[v] * read_mask(view.mask, height, width)
    return weights


def _fragments(mesh, cameras: Sequence[Camera], *, cache_dir, folder: ViewFolder | None, uv_grad: bool,
               footprints):
    """The cameras' fragments: a list, or with --view_data on disk (`folder`) and one resolution,
    `FragmentRows` in files of `folder` (a view at a time in memory; 12 bytes a pixel on disk, 28
    with `uv_grad`), with each view's `footprints(fragments)` (`layout.page_footprints`)."""
    one_size = len({(c.height, c.width) for c in cameras}) == 1
    empty = functools.partial(view_array, folder=folder) if folder is not None and one_size else None
    return fr.compute_fragments(mesh, cameras, cache_dir=cache_dir, empty=empty, uv_grad=uv_grad,
                                footprints=footprints if empty is not None else None)


def _photo_fragments(config: DistillConfig, scene: Scene, views: Sequence, render: tuple[int, int], frags,
                     native_frags, fragments) -> Sequence | None:
    """The fragments of `views` (the views this process holds) that the re-rendering term renders
    the photos at (--photo_size, of the whole scene), or None when --photo_weight is 0. Reuses the
    render-size or native fragments (when computed) where the size is theirs; `fragments(cameras)`
    computes others."""
    if config.photo_weight <= 0:
        return None
    shape = render_shape(scene, config.photo_size, flag="--photo_size")
    if shape == render:
        return frags
    if native_frags is not None and all((v.camera.height, v.camera.width) == shape for v in views):
        return native_frags
    return fragments([scaled_camera(v.camera, *shape) for v in views])


def _photo_data(config: DistillConfig, scene: Scene, views: Sequence, photo_frags, space: TexelSpace, counts,
                empty=None, *, plan=None, sources: bool = False) -> PhotoData:
    """The re-rendering term's plans, photos and pixel weights (`PhotoData`) of `views` (the views
    this process holds, of `scene`), at the photo fragments' size, in arrays from
    `empty(name, shape, dtype)` (`view_rows.view_array`: memory or files); `plan`: the photo
    fragments' plan when the caller has it already (the render size's). `sources` (--view_data on
    disk, where copies would not fit): photo files of that size are read again from them
    (`SourceRows`), not copied."""
    empty = empty or functools.partial(view_array, folder=None)
    plan = plan if plan is not None else build_gather_plans(photo_frags, space, config.sampler, empty=empty)
    height, width = plan.height, plan.width
    weights = _loss_weights(config, views, plan, counts, empty)
    count = len(views)
    # on disk, photos at the photo size are read again from their files a batch at a time (`SourceRows`)
    from_files = sources and files_at_size((view.photo for view in views), height, width)
    photos = None if from_files else empty("photos", (count, height, width, 3), np.float32)
    guide = empty("guides", (count, height, width, 2), np.float32) if config.albedo_smoothness > 0 else None
    noise = np.zeros(count, np.float64)
    noise_weight = np.ones(count, np.float64)
    for v, view in enumerate(view_bar(views, "photos")):
        photo, usable = read_photo_linear(view.photo, view.exposure, height, width)
        if photos is not None:
            photos[v] = photo
        if guide is not None:
            guide[v] = photo_lib.chroma_guide(photo, usable)
        noise[v] = photo_lib.log_noise(photo, usable)
        noise_weight[v] = photo_lib.noise_weight(noise[v], config.photo_noise_ref)
        weight = weights[v]
        weight *= usable
        weight *= np.float32(noise_weight[v])              # × 1 is exact: a weight-1 view is unchanged
        weights[v] = weight
    if config.photo_noise_ref > 0:
        logging.info("--photo_noise_ref=%g: the photos' noise %.3f (median, %.3f-%.3f) in log units; %d of %d views "
                     "weigh less in the term (weights %.2f-%.2f)", config.photo_noise_ref, float(np.median(noise)),
                     float(noise.min()), float(noise.max()), int(np.sum(noise_weight < 1)), len(noise),
                     float(noise_weight.min()), float(noise_weight.max()))
    if from_files:
        photos = SourceRows((count, height, width, 3), np.float32,
                            lambda v: read_photo_linear(views[v].photo, views[v].exposure, height, width)[0],
                            [[view.photo] for view in views], name="photos")
    ldr = any(not imageio.is_linear_format(view.photo) for view in scene.views)     # every process's answer
    scale = photo_lib.resolve_scale(config.photo_scale, ldr)
    if scale != config.photo_scale:
        logging.info("--photo_scale=auto: %s (%s)", scale, "LDR photos: a gain per view and colour channel, their "
                     "exposure and white balance" if ldr else "HDR photos: one scale per batch, their exposure known")
    return PhotoData(height=height, width=width, index=plan.index, weight=plan.weight, hit=plan.hit, photos=photos,
                     pixel_weight=weights, guide=guide, scale=scale,
                     noise=noise, noise_weight=noise_weight)


def initial_file_values(maps: Sequence[str]) -> dict[str, float]:
    """Per map, the file-space value of the initial texels (the fill of never-observed texels)."""
    return {m: 0.5 * (INITIAL_VALUE[m] + 1.0) if m != "normal" else 0.0 for m in maps}

