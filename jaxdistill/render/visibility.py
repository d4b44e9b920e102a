"""Visibility (thesis §4.3.1): per-texel view counts V and per-pixel loss weights W.

V(p) counts the views whose gather plan reads texel p with a non-zero weight (directly or
through a coarser mip level), i.e. where the transpose of `render` is positive. Per pixel,
V is sampled through the view's own plan and turned into W = clip(1 / (2 clip(V, 1, 6)), 0.1, 10);
missed pixels get W = 0.

Coverage: the fraction of each view's pixels whose ray hits the mesh, computed right after the
ray cast. Views under MIN_HIT_FRACTION are named in a warning; a scene no view sees stops with
an InputError (a camera convention or units mix-up), before anything is jitted.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera
from jaxdistill.errors import InputError
from jaxdistill.render.gather_plan import GatherPlan, TexelSpace
from jaxdistill.render.sampler import expand, render
from jaxdistill.scene.model import Mesh
from jaxdistill.threads import view_bar

log = logging.getLogger(__name__)

MIN_HIT_FRACTION = 0.01   # views whose rays hit the mesh less often than this are named in a warning
COVERAGE_WIDTH = 128      # cast_hit_fractions: rays across per view (a grid of cell centres)
WORST_VIEWS = 3           # views named in the coverage summary


def visibility_weights(counts):
    """W = clip(1 / (2 clip(V, 1, 6)), 0.1, 10) for view counts V (any shape, float32)."""
    counts = jnp.asarray(counts, jnp.float32)
    return jnp.clip(1.0 / (2.0 * jnp.clip(counts, 1.0, 6.0)), 0.1, 10.0)


def view_counts(plan: GatherPlan, num_texels: int) -> np.ndarray:
    """(N,) int32: number of views whose plan touches each compact texel."""
    counts = np.zeros(num_texels, np.int32)
    for v in view_bar(range(plan.num_views), "view counts"):
        counts += np.asarray(_evidence(plan.select(v), num_texels=num_texels) > 0)
    return counts


def _transposed(plan: GatherPlan, plane: jnp.ndarray, num_texels: int) -> jnp.ndarray:
    """(N,) float32: the transpose of the single-view `plan`'s render applied to one (H, W) image
    plane: per texel, the gather-weighted sum of the plane's values at the pixels that read it."""
    _, transpose = jax.vjp(lambda t: render(t, plan), jnp.zeros((num_texels, 1), jnp.float32))
    (grad,) = transpose(plane.reshape(plan.height, plan.width, 1).astype(jnp.float32))
    return grad[:, 0]


@functools.partial(jax.jit, static_argnames=("num_texels",))
def _evidence(plan: GatherPlan, *, num_texels: int) -> jnp.ndarray:
    """(N,) float32: the transpose of the single-view `plan` applied to its hit mask (its read weight)."""
    return _transposed(plan, plan.hit, num_texels)


def texel_evidence(plan: GatherPlan, num_texels: int) -> np.ndarray:
    """(N,) float32: per compact texel, the summed weight with which all views' pixels read it
    (the transpose of `render` applied to every view's hit mask). A texel that one pixel reads
    alone at level 0 gets 1; a read through mip level l spreads over 4^l texels, 4^-l each, so
    texels seen only at grazing angles or through coarse levels get little evidence."""
    total = np.zeros(num_texels, np.float64)
    for v in view_bar(range(plan.num_views), "texel evidence"):
        total += np.asarray(_evidence(plan.select(v), num_texels=num_texels), np.float64)
    return total.astype(np.float32)


def texel_view_statistics(plan: GatherPlan, images: Iterable[np.ndarray], num_texels: int
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the views say about each texel: (count (N,) int32 of views that read it, mean (N, C)
    float32 and variance (N, C) float64 (float32 sums of squares over the counts) of their values
    across those views; 0 where none reads it).
    A view's value at a texel is the gather-weighted mean of the pixels of its image (H, W, C)
    that read the texel (through the transpose of `render`), so every view counts once.
    `images` (one per view of `plan`, in order) may be a generator: one view's image is in memory
    at a time. The statistics are kept on the device as Welford's running mean and sum of squared
    deviations (float32, stable where the views agree closely), updated a view at a time on the
    texels that view reads only (`_read_texels`: a few to a fifth of a room's texels per view;
    `_accumulate`, a chunk of them per call), so the update's cost goes with what a view sees; the
    transposes it starts from (the read weight, `_evidence`, and one per channel, `_channel_sum`)
    are still dense over the texels. A NaN or infinite value on a missed pixel is not read. The
    work arrays are (C, N), so a caller with many channels asks per map and holds a few at once
    (or several maps in one pass, `texel_view_statistics_of`)."""
    return texel_view_statistics_of(plan, ((image,) for image in images), num_texels)[0]


def texel_view_statistics_of(plan: GatherPlan, images: Iterable[Sequence[np.ndarray]], num_texels: int
                             ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`texel_view_statistics` of several quantities in one pass over the views: `images` gives per
    view a tuple of images (H, W, C_k), one per quantity (e.g. per map; the same quantities for
    every view). A list of (count, mean, variance), one per quantity, each as
    `texel_view_statistics` gives it for that quantity's images alone; the count, which depends on
    the plan alone, is one array shared by all. What depends on the view's plan alone (its read
    weight, `_evidence`, and the texels it reads, `_read_texels`) is computed once per view for all
    the quantities, once instead of K times for K of them; the work arrays are then all K quantities'
    at once (about `EVIDENCE_BYTES_PER_TEXEL` + `EVIDENCE_BYTES_PER_CHANNEL` * sum C_k bytes a texel). The
    count is shared: a caller must not write into it."""
    state = None
    for v, group in enumerate(images):
        group = tuple(jnp.asarray(image, jnp.float32) for image in group)
        if state is None:
            state = (jnp.zeros(num_texels, jnp.int32),
                     tuple(jnp.zeros((image.shape[-1], num_texels), jnp.float32) for image in group),
                     tuple(jnp.zeros((image.shape[-1], num_texels), jnp.float32) for image in group))
        one = jax.device_put(plan.select(v))              # once for the view's several calls
        weight = _evidence(one, num_texels=num_texels)     # the view's read weight w per texel
        read = _read_texels(np.asarray(weight), num_texels)
        sums = tuple(tuple(_channel_sum(one, image[..., c], num_texels=num_texels) for c in range(image.shape[-1]))
                     for image in group)
        for start in range(0, len(read), READ_CHUNK):      # one compiled update for every view
            state = _accumulate(state, weight, sums, read[start:start + READ_CHUNK])
        state = jax.block_until_ready(state)              # one view's inputs in memory at a time
    if state is None:
        raise ValueError("texel_view_statistics: no images")
    count = np.array(jax.device_get(state[0]))
    means, squares = list(state[1]), list(state[2])
    del state, sums, weight, read, group, one
    out = []
    for k in range(len(means)):         # a quantity at a time, its device arrays let go as it is handed back
        mean, square = (np.ascontiguousarray(np.asarray(jax.device_get(a)).T) for a in (means[k], squares[k]))
        means[k] = squares[k] = None
        # rounding can leave -ulp where views agree
        variance = np.maximum(square, 0.0) / np.maximum(count, 1)[:, None]
        del square
        out.append((count, mean, variance))
    return out


READ_CHUNK = 1 << 18     # texels per `_accumulate` call: one compiled shape, whatever a view reads
# about what `texel_view_statistics_of` holds, in bytes a texel a channel: while it runs, the running mean and
# sum of squares and the view's channel sum (float32 each: 12); while it hands them back, the mean (float32)
# and variance (float64) handed back (12) beside the running arrays not handed back yet (8 each). And a
# texel whatever the channels: the count, the view's read weight and the ids of the texels it reads
# (int32, up to one a texel)
EVIDENCE_BYTES_PER_CHANNEL = 20
EVIDENCE_BYTES_PER_TEXEL = 12


def _read_texels(weight: np.ndarray, num_texels: int) -> np.ndarray:
    """int32 ids of the texels with w > 0, padded with `num_texels` (out of range: reads give 0,
    writes are dropped) to a multiple of READ_CHUNK."""
    read = np.flatnonzero(weight > 0).astype(np.int32)
    return np.pad(read, (0, -len(read) % READ_CHUNK), constant_values=num_texels)


@functools.partial(jax.jit, static_argnames=("num_texels",))
def _channel_sum(plan: GatherPlan, plane: jnp.ndarray, *, num_texels: int) -> jnp.ndarray:
    """(N,) float32: the transpose of the single-view `plan`'s render applied to one channel (H, W)
    of an image on the plan's hit pixels: per texel the gather-weighted sum s. One channel per
    compiled call: on the CPU that is several times faster per channel than an (N, C) transpose,
    and than C of them in one program."""
    hit = plan.hit.reshape(plan.height, plan.width)
    return _transposed(plan, jnp.where(hit, plane, 0.0), num_texels)


@functools.partial(jax.jit, donate_argnums=(0,))
def _accumulate(state, weight: jnp.ndarray, sums: tuple, read: jnp.ndarray):
    """One view's update of (count (N,), means, sums of squared deviations: one (C_k, N) each per
    quantity) at the texels `read` (a chunk of `_read_texels`), from the view's read weight w (N,)
    (`_evidence`) and its weighted sums s, per quantity C_k arrays (N,) (`_channel_sum`): the view's
    value s / w joins the texels with w > 0. The texels outside `read` are left as they are, as a
    dense update would."""
    count, means, squares = state
    at = lambda a: a.at[..., read].get(mode="fill", fill_value=0)
    w = at(weight)
    seen = w > 0
    n = at(count) + seen
    new_means, new_squares = [], []
    for mean, square, quantity in zip(means, squares, sums):
        value = jnp.stack([at(s) for s in quantity]) / jnp.where(seen, w, 1.0)
        old = at(mean)
        delta = value - old
        new = old + jnp.where(seen, delta / jnp.maximum(n, 1), 0.0)
        squared = at(square) + jnp.where(seen, delta * (value - new), 0.0)
        new_means.append(mean.at[:, read].set(new, mode="drop"))
        new_squares.append(square.at[:, read].set(squared, mode="drop"))
    return count.at[read].set(n, mode="drop"), tuple(new_means), tuple(new_squares)


def pixel_weights(plan: GatherPlan, counts: np.ndarray, out=None) -> np.ndarray:
    """(V, H, W) float32 loss weights per view and pixel (0 on missed pixels), a view at a time,
    into `out` when given (anything that takes `out[v] = image`, e.g. a file's rows)."""
    counts = jnp.asarray(counts, jnp.float32)[:, None]
    out = np.empty((plan.num_views, plan.height, plan.width), np.float32) if out is None else out
    for v in view_bar(range(plan.num_views), "pixel weights"):
        one = plan if plan.index.ndim == 2 else plan.select(v)    # (a single view's plan has no view axis)
        out[v] = np.asarray(_pixel_weights(one, counts))
    return out


@jax.jit
def _pixel_weights(plan: GatherPlan, counts: jnp.ndarray) -> jnp.ndarray:
    sampled = render(counts, plan)[..., 0]
    hit = plan.hit.reshape(sampled.shape)
    return jnp.where(hit, visibility_weights(sampled), 0.0)


def write_visibility_pages(counts: np.ndarray, space: TexelSpace, folder, object_names=None) -> list[Path]:
    """Writes V per page as `visibility_<page>.exr` (raw counts) and `.png` (counts / max, grey)."""
    folder = Path(folder)
    pages = expand(counts.astype(np.float32)[:, None], space, 0.0, dilation=0)
    peak = max(1.0, float(counts.max(initial=0)))
    written = []
    for page, image in enumerate(pages):
        name = object_names[page] if object_names and space.layout.num_pages == len(object_names) else f"page{page:03d}"
        stem = folder / f"visibility_{page:03d}_{name}"
        imageio.write_image(stem.with_suffix(".exr"), image)
        imageio.write_image(stem.with_suffix(".png"), image / peak, encode_srgb=False)
        written += [stem.with_suffix(".exr"), stem.with_suffix(".png")]
    return written


# ----------------------------------------------------------------------------- coverage


def hit_fractions(fragments: Sequence) -> np.ndarray:
    """(V,) float64: per view, the fraction of its pixels whose ray hits the mesh."""
    return np.array([float(np.mean(f.hit)) if f.hit.size else 0.0 for f in fragments], np.float64)


def cast_hit_fractions(mesh: Mesh, cameras: Sequence[Camera], *, max_width: int = COVERAGE_WIDTH) -> np.ndarray:
    """(V,) float64 hit fractions from a cheap cast: per camera a grid of at most `max_width`
    cell centres across (same aspect; every pixel when the photo is narrower). Needs no UVs."""
    from jaxdistill.render.fragments import RayCaster

    caster = RayCaster(mesh)
    out = np.zeros(len(cameras), np.float64)
    for i, cam in enumerate(cameras):
        gw = max(1, min(cam.width, int(max_width)))
        gh = max(1, min(cam.height, int(round(cam.height * gw / cam.width))))
        xs = (np.arange(gw) + 0.5) * (cam.width / gw)
        ys = (np.arange(gh) + 0.5) * (cam.height / gh)
        px, py = np.meshgrid(xs, ys)
        triangle, _, _ = caster.intersect(*cam.pixel_rays(np.stack([px.ravel(), py.ravel()], axis=1)))
        out[i] = float(np.mean(triangle >= 0))
    return out


def coverage_summary(names: Sequence[str], fractions: np.ndarray) -> str:
    """One line: min / median / max of the views' hit fractions and the views that see least."""
    f = np.asarray(fractions, np.float64)
    if not len(f):
        return "pixels that hit the mesh: no views"
    order = np.argsort(f, kind="stable")[:WORST_VIEWS]
    worst = ", ".join(f"{names[i]} {100 * f[i]:.1f} %" for i in order)
    return (f"pixels that hit the mesh per view ({len(f)} views): min {100 * f.min():.1f} %, median "
            f"{100 * np.median(f):.1f} %, max {100 * f.max():.1f} %; fewest: {worst}")


SCENE_CONVENTION = ("check the camera convention (OpenCV camera-to-world c2w: x right, y down, z forward; not "
                    "world-to-camera, not OpenGL) and units (cameras and mesh in the same world and units)")


def check_coverage(names: Sequence[str], fractions: np.ndarray, cameras: Sequence[Camera], mesh: Mesh,
                   scene_file: str, *, min_fraction: float = MIN_HIT_FRACTION,
                   what_to_check: str = SCENE_CONVENTION) -> list[str]:
    """Logs the coverage summary and a warning naming the views under `min_fraction`; returns
    their names. InputError (naming `scene_file`, ending with `what_to_check`) when no ray of any
    view hits the mesh: then no texel is observed and there is nothing to distil."""
    f = np.asarray(fractions, np.float64)
    log.info("%s", coverage_summary(names, f))
    if len(f) and not f.max() > 0:
        raise InputError.single(scene_file, "views", f"no view sees the mesh (every ray of the {len(f)} views misses "
                                f"it, so no texel is observed); {_placement(cameras, mesh)}; {what_to_check}")
    low = np.nonzero(f < min_fraction)[0]
    blind = [names[i] for i in low]
    if blind:
        shown = ", ".join(f"{names[i]} {100 * f[i]:.1f} %" for i in low[:10])
        more = f" and {len(blind) - 10} more" if len(blind) > 10 else ""
        log.warning("%d of %d views see (almost) nothing, under %.0f %% of their pixels hit the mesh: %s%s; check "
                    "their c2w / K (camera convention, units) or drop them", len(blind), len(f), 100 * min_fraction,
                    shown, more)
    return blind


def _placement(cameras: Sequence[Camera], mesh: Mesh) -> str:
    """Where the cameras are relative to the mesh's bounding box (a units mix-up shows here)."""
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    centres = np.array([c.c2w[:3, 3] for c in cameras])
    inside = int(np.all((centres >= lo) & (centres <= hi), axis=1).sum())
    fmt = lambda v: "(" + ", ".join(f"{x:.4g}" for x in v) + ")"  # noqa: E731
    return (f"{inside} of {len(cameras)} camera centres lie inside the mesh's bounding box {fmt(lo)}..{fmt(hi)}; "
            f"camera centres span {fmt(centres.min(axis=0))}..{fmt(centres.max(axis=0))}")
