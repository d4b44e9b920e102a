"""Gather sampler against an independent NumPy/SciPy reference, and its exact transpose."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from conftest import look_at_camera
from jaxdistill.scene import shapes as synthetic
from jaxdistill.render import fragments as fr
from jaxdistill.render import gather_plan
from jaxdistill.render.gather_plan import build_gather_plans, build_texel_space
from jaxdistill.render.layout import TextureLayout, make_layout
from jaxdistill.render.sampler import (SplitPyramid, build_pyramid, compact, coverage, expand, push_pull, render, sample,
                                      sample_many)


def reference_sample(page, uv):
    """Bilinear, clamp-to-edge sampling of an (S, S, C) page at uv (N, 2) with v up, via SciPy."""
    size = page.shape[0]
    x = uv[:, 0] * size - 0.5
    y = (1.0 - uv[:, 1]) * size - 0.5
    return np.stack([ndimage.map_coordinates(page[..., c], [y, x], order=1, mode="nearest")
                     for c in range(page.shape[-1])], axis=-1)


def reference_pyramid(page):
    """Levels of a 2x2-mean mip pyramid down to 1x1."""
    levels = [page]
    while levels[-1].shape[0] > 1:
        p = levels[-1]
        s = p.shape[0] // 2
        levels.append(p.reshape(s, 2, s, 2, -1).mean(axis=(1, 3)))
    return levels


def reference_render(pages, layout, frag, trilinear):
    """(H, W, C) image sampled pixel by pixel from full pages, as nvdiffrast's texture would."""
    h, w = frag.shape
    channels = pages[0].shape[-1]
    out = np.zeros((h * w, channels))
    hit = frag.object_id.ravel() >= 0
    page_of = np.asarray(layout.object_page)[frag.object_id.ravel()]
    uv = frag.uv.reshape(-1, 2).astype(np.float64)
    grad = frag.uv_grad.reshape(-1, 2, 2).astype(np.float64)
    for p in range(layout.num_pages):
        sel = hit & (page_of == p)
        if not sel.any():
            continue
        if not trilinear:
            out[sel] = reference_sample(pages[p], uv[sel])
            continue
        pyramid = reference_pyramid(pages[p].astype(np.float64))
        size = pages[p].shape[0]
        a = (grad[sel, 0] ** 2).sum(-1) * size ** 2
        b = (grad[sel, 1] ** 2).sum(-1) * size ** 2
        with np.errstate(divide="ignore"):
            lam = np.clip(0.5 * np.log2(np.maximum(a, b)), 0, len(pyramid) - 1)
        lo = np.floor(lam).astype(int)
        frac = lam - lo
        vals = np.zeros((sel.sum(), channels))
        for i, (level, f) in enumerate(zip(lo, frac)):
            s0 = reference_sample(pyramid[level], uv[sel][i:i + 1])[0]
            s1 = reference_sample(pyramid[min(level + 1, len(pyramid) - 1)], uv[sel][i:i + 1])[0]
            vals[i] = (1 - f) * s0 + f * s1
        out[sel] = vals
    return out.reshape(h, w, channels)


def scene_views(width=40, height=30):
    mesh = synthetic.box_room((4.0, 2.5, 3.0), subdivisions=2, furniture=True)
    cams = [look_at_camera((1.0, 1.4, 0.7), (3.5, 0.4, 2.6), width, height, fx=22.0),
            look_at_camera((3.2, 1.0, 2.5), (0.5, 0.9, 0.4), width, height, fx=30.0, cx=18.0, cy=16.5),
            look_at_camera((2.0, 2.2, 1.5), (2.1, 0.0, 1.4), width, height, fx=15.0, up=(0, 0, 1))]
    return mesh, fr.compute_fragments(mesh, cams, cache_dir=False, progress=False)


@pytest.fixture(scope="module")
def room():
    return scene_views()


@pytest.mark.parametrize("sampler,tile_size", [("bilinear", 1), ("bilinear", 16), ("trilinear", 1), ("trilinear", 4),
                                               ("trilinear", 16)])
def test_render_matches_reference_from_full_pages(room, sampler, tile_size):
    mesh, frags = room
    trilinear = sampler == "trilinear"
    layout = TextureLayout(page_sizes=tuple(16 if i % 3 else 32 for i in range(len(mesh.object_names))),
                           object_page=tuple(range(len(mesh.object_names))), mipmaps=trilinear,
                           tile_size=tile_size)
    space = build_texel_space(frags, layout, sampler)
    plan = build_gather_plans(frags, space, sampler)
    rng = np.random.default_rng(0)
    pages = [rng.uniform(-1, 1, (s, s, 3)).astype(np.float32) for s in layout.page_sizes]
    images = np.asarray(jax.jit(render)(jnp.asarray(compact(pages, space)), plan))
    for v, frag in enumerate(frags):
        np.testing.assert_allclose(images[v], reference_render(pages, layout, frag, trilinear), atol=2e-5)
    # Untouched texels must not matter: scramble every texel that is not a parameter.
    scrambled = [np.where(m[..., None], p, 99.0) for p, m in zip(pages, coverage(space))]
    for v, frag in enumerate(frags[:1]):
        np.testing.assert_allclose(images[v], reference_render(scrambled, layout, frag, trilinear), atol=2e-5)
    if trilinear:  # distant and grazing pixels must read mip levels, also above one tile
        reads = np.asarray(plan.index)[np.asarray(plan.weight) > 0]
        assert reads.max() >= space.pyramid_size - len(space.children[-1]) and len(space.children) >= 1
        assert (reads >= space.num_texels).mean() > 0.1


def test_plane_at_grazing_angle_trilinear():
    mesh = synthetic.plane(20.0, 4)
    camera = look_at_camera((0.0, 0.15, 9.5), (0.0, 0.0, -10.0), width=48, height=32, fx=40.0)
    frags = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
    layout = TextureLayout(page_sizes=(64,), object_page=(0,), mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    page = np.random.default_rng(1).uniform(0, 1, (64, 64, 1)).astype(np.float32)
    image = np.asarray(render(jnp.asarray(compact([page], space)), plan))[0]
    np.testing.assert_allclose(image, reference_render([page], layout, frags[0], True), atol=2e-5)
    weights = np.asarray(plan.weight[0])
    np.testing.assert_allclose(weights.sum(-1)[frags[0].hit.ravel()], 1.0, atol=1e-5)
    assert np.isfinite(image).all() and frags[0].hit.mean() > 0.3


def trilinear_case(room, channels: int, seed: int):
    """The room's trilinear space and plan (8x8 tiles), the plan with float64 weights, and random
    float64 texels and image cotangents (call inside `jax.enable_x64`)."""
    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 16, frags, mipmaps=True, tile_size=8)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    rng = np.random.default_rng(seed)
    x = jnp.asarray(rng.normal(size=(space.num_texels, channels)))
    y = jnp.asarray(rng.normal(size=(len(frags), plan.height, plan.width, channels)))
    return space, plan, plan.replace(weight=plan.weight.astype(jnp.float64)), x, y, rng


def test_gradient_is_exact_transpose(room):
    with jax.enable_x64(True):
        space, plan, plan64, x, y, rng = trilinear_case(room, 2, 2)
        out, transpose = jax.vjp(lambda t: render(t, plan64), x)
        (xt,) = transpose(y)
        lhs, rhs = float(jnp.vdot(out, y)), float(jnp.vdot(x, xt))
        assert abs(lhs - rhs) <= 1e-10 * max(1.0, abs(lhs))
        assert space.tile == 8 and len(space.children) >= 1
        # Finite differences on a few texels (render is linear, so they are exact up to rounding).
        loss = lambda t: jnp.sum(render(t, plan64) * y)
        grad = jax.grad(loss)(x)
        for i in rng.choice(space.num_texels, 8, replace=False):
            e = jnp.zeros_like(x).at[i, 0].set(1e-3)
            fd = (loss(x + e) - loss(x - e)) / 2e-3
            np.testing.assert_allclose(float(grad[i, 0]), float(fd), rtol=1e-7, atol=1e-9)


def test_split_pyramid_samples_and_transposes_as_the_concatenated_one(room):
    """`build_pyramid(split=True)` holds the same entries as the concatenated pyramid, in two
    arrays: sampling reads each tap from its part (renders equal, float64), and the gradient
    w.r.t. the texels, through either form, is the same (the exact transpose of the same gather)."""
    with jax.enable_x64(True):
        space, plan, plan64, x, y, _ = trilinear_case(room, 3, 5)
        whole = build_pyramid(x, plan.chain)
        split = build_pyramid(x, plan.chain, split=True)
        assert isinstance(split, SplitPyramid) and split.texels is x
        np.testing.assert_array_equal(np.concatenate([split.texels, split.coarse]), whole)
        index = np.asarray(plan.index)[np.asarray(plan.weight) > 0]
        assert (index < space.num_texels).any() and (index >= space.num_texels).any()    # both parts are read
        np.testing.assert_allclose(sample(split, plan64), sample(whole, plan64), rtol=1e-12, atol=1e-12)
        grads = [jax.grad(lambda t, s=s: jnp.sum(sample(build_pyramid(t, plan.chain, split=s), plan64) * y))(x)
                 for s in (False, True)]
        np.testing.assert_allclose(grads[1], grads[0], rtol=1e-12, atol=1e-12)
    single = build_pyramid(x[:, :1].astype(jnp.float32), gather_plan.MipChain(tile=1, in_tile_levels=1, children=()),
                           split=True)
    assert not isinstance(single, SplitPyramid)       # nothing above the texels: the texels themselves


def test_sample_many_reads_several_plans_as_sample_reads_each(room):
    """One gather of two plans' taps (a step's renders and its photos: other views, another pixel
    count) gives each plan's image as `sample` does, from either pyramid form
    (float64), and its transpose is the sum of the two plans' transposes; its jaxpr gathers from
    the texels once where `sample` per plan gathers twice."""
    with jax.enable_x64(True):
        space, plan, plan64, x, y, _ = trilinear_case(room, 3, 6)
        half = plan.height // 2                    # the top half of views 2 and 0: another pixel count
        pixels = half * plan.width
        other = plan64.replace(index=plan64.index[np.array([2, 0]), :pixels],
                               weight=plan64.weight[np.array([2, 0]), :pixels],
                               hit=plan64.hit[np.array([2, 0]), :pixels], height=half)
        z = jnp.asarray(np.random.default_rng(7).normal(size=(2, half, plan.width, 3)))
        for split in (False, True):
            pyramid = build_pyramid(x, plan.chain, split=split)
            both = sample_many(pyramid, [plan64, other])
            np.testing.assert_allclose(both[0], sample(pyramid, plan64), rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(both[1], sample(pyramid, other), rtol=1e-12, atol=1e-12)
            joint = jax.grad(lambda t, s=split: sum(jnp.sum(i * c) for i, c in zip(
                sample_many(build_pyramid(t, plan.chain, split=s), [plan64, other]), (y, z))))(x)
            apart = jax.grad(lambda t, s=split: jnp.sum(sample(build_pyramid(t, plan.chain, split=s), plan64) * y)
                             + jnp.sum(sample(build_pyramid(t, plan.chain, split=s), other) * z))(x)
            np.testing.assert_allclose(joint, apart, rtol=1e-11, atol=1e-11)
        (one,) = sample_many(build_pyramid(x, plan.chain), [plan64])
        np.testing.assert_array_equal(one, sample(build_pyramid(x, plan.chain), plan64))

    def gathers_from_texels(fn):
        jaxpr = jax.make_jaxpr(fn)(x.astype(jnp.float32))
        return sum(e.primitive.name == "gather" and e.invars[0].aval.shape == x.shape for e in jaxpr.eqns)

    pair = [plan, plan.select(np.array([2, 0]))]
    assert gathers_from_texels(lambda t: sample_many(build_pyramid(t, plan.chain, split=True), pair)) == 1

    def primitives(jaxpr):                 # every primitive of a jaxpr and the jaxprs inside it
        for e in jaxpr.eqns:
            yield e.primitive.name
            for sub in jax.core.jaxprs_in_params(e.params):
                yield from primitives(sub)

    # the pixels split, not sliced: the gradient concatenates the plans' cotangents, with no pixels-sized pads
    grad = jax.make_jaxpr(jax.grad(lambda t: sum(jnp.sum(i) for i in sample_many(
        build_pyramid(t, plan.chain, split=True), pair))))(x.astype(jnp.float32))
    assert "pad" not in set(primitives(grad.jaxpr))
    assert gathers_from_texels(lambda t: [sample(build_pyramid(t, plan.chain, split=True), p) for p in pair]) == 2
    with pytest.raises(ValueError, match="taps"):
        sample_many(build_pyramid(x, plan.chain), [plan, plan.replace(index=plan.index[..., :4],
                                                                       weight=plan.weight[..., :4])])


def test_split_pyramid_keeps_one_texel_array_less_in_a_gradient():
    """What the split form is for: the gradient of a loss on sampled taps, compiled by XLA, holds
    about one array of the texels' size less in temporaries than through the concatenated pyramid
    (no copy of the texels into it; the cotangent's level 0 is the gradient). XLA's own buffer
    assignment (`memory_analysis`), 1M texels of 11 channels, 16x16 tiles."""
    n, channels = 4096 * 256, 11
    chain = gather_plan.MipChain(tile=16, in_tile_levels=5, children=())
    texels = jnp.zeros((n, channels), jnp.float32)
    size = build_pyramid(texels, chain).shape[0]
    rng = np.random.default_rng(0)
    plan = gather_plan.GatherPlan(index=jnp.asarray(rng.integers(0, size, (2, 20000, 8)), jnp.int32),
                                  weight=jnp.full((2, 20000, 8), 0.125, jnp.float32), hit=jnp.ones((2, 20000), bool),
                                  height=100, width=200, chain=chain)

    def temporaries(split):
        loss = lambda t: jnp.sum(sample(build_pyramid(t, chain, split=split), plan) ** 2)
        compiled = jax.jit(jax.grad(loss)).lower(texels).compile()
        return compiled.memory_analysis().temp_size_in_bytes / texels.nbytes

    whole, split = temporaries(False), temporaries(True)
    assert whole - split > 0.8, (whole, split)


def test_every_tile_is_read_by_some_view(room):
    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    ones = jnp.ones((len(frags), plan.height, plan.width, 1))
    _, transpose = jax.vjp(lambda t: render(t, plan), jnp.zeros((space.num_texels, 1)))
    (reach,) = transpose(ones)
    per_tile = np.asarray(reach).reshape(space.num_tiles, -1).max(axis=1)
    assert per_tile.min() > 0, "a tile that no view reads was allocated"
    assert space.num_texels < layout.full_size()


def test_batched_render_equals_per_view(room):
    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 16, frags)
    space = build_texel_space(frags, layout, "bilinear")
    plan = build_gather_plans(frags, space, "bilinear")
    texels = jnp.asarray(np.random.default_rng(3).normal(size=(space.num_texels, 3)), jnp.float32)
    batch = render(texels, plan)
    for v in range(len(frags)):
        np.testing.assert_array_equal(np.asarray(render(texels, plan.select(v))), np.asarray(batch[v]))
    two = render(texels, plan.select(jnp.array([2, 0])))
    np.testing.assert_array_equal(np.asarray(two[0]), np.asarray(batch[2]))


def test_compact_expand_round_trip_and_dilation(room):
    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 32, frags)
    space = build_texel_space(frags, layout, "bilinear")
    texels = np.random.default_rng(4).uniform(-1, 1, (space.num_texels, 3)).astype(np.float32)
    pages = expand(texels, space, fill=(-1.0, 0.0, 1.0), dilation=0)
    np.testing.assert_array_equal(compact(pages, space), texels)
    masks = coverage(space)
    for page, mask in zip(pages, masks):
        assert np.all(page[~mask] == [-1.0, 0.0, 1.0])
    dilated = expand(texels, space, fill=0.0, dilation=2)
    np.testing.assert_array_equal(compact(dilated, space), texels)
    for page, mask in zip(dilated, masks):
        if mask.all() or not mask.any():
            continue
        ring = ndimage.binary_dilation(mask, structure=np.ones((3, 3))) & ~mask
        r, c = np.argwhere(ring)[0]
        nb = mask[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2]
        vals = page[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2][nb]
        np.testing.assert_allclose(page[r, c], vals.mean(axis=0), rtol=1e-5)
        far = ~ndimage.binary_dilation(mask, structure=np.ones((3, 3)), iterations=2)
        assert np.all(page[far] == 0.0)


def test_auto_texture_size_follows_closest_view():
    # A plane facing the camera at distance d: one pixel spans d / fx world units, i.e.
    # d / (fx * size) in UV, so about fx * size / d texels resolve it.
    mesh = synthetic.plane(2.0, 1)
    for distance, fx, expected in ((2.0, 200.0, 256), (1.0, 200.0, 512), (1.0, 2000.0, 1024)):
        camera = look_at_camera((0.0, distance, 0.0), (0.0, 0.0, 0.0), 64, 64, fx=fx, up=(0, 0, -1))
        frags = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
        layout = make_layout(1, "pages", "auto", frags, max_size=1024)
        assert layout.page_sizes == (expected,), (distance, fx, layout.page_sizes)


def ramp(size):
    """(S, S, 2) page of a linear ramp in row and column (analytic values at texel centres)."""
    r, c = np.mgrid[0:size, 0:size].astype(np.float64)
    return np.stack([0.3 + 0.01 * c - 0.005 * r, 0.1 + 0.002 * r], -1).astype(np.float32)


def test_push_pull_fills_a_hole_in_a_ramp_with_the_ramp_and_keeps_observed_texels():
    page = ramp(64)
    weight = np.ones((64, 64), np.float32)
    weight[20:40, 10:35] = 0.0
    weight[50:53, 50:60] = 0.0
    holed = np.where(weight[..., None] > 0, page, 0.5)            # what the unobserved texels held
    filled = push_pull(holed, weight)
    np.testing.assert_array_equal(filled[weight == 1], page[weight == 1])       # observed: unchanged
    span = float(page.max() - page.min())
    assert np.abs(filled - page)[weight == 0].max() <= 0.01 * span                 # the ramp, within 1 %
    grey = np.abs(holed - page)[weight == 0].max()
    assert grey > 20 * np.abs(filled - page)[weight == 0].max()    # far from the flat fill it replaces


def reference_push_pull(page, weight, smoothing):
    """push_pull's docstring written out in float64 NumPy, the plain way (padded copies)."""
    def mean4(x):
        p = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
        return 0.25 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])

    def upsample(x):          # bilinear x2, texel centres aligned: taps 3/4 and 1/4, edges clamped
        p = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
        out = np.zeros((2 * x.shape[0], 2 * x.shape[1], x.shape[2]))
        for i in range(out.shape[0]):
            for j in range(out.shape[1]):
                r, c = i // 2 + 1, j // 2 + 1
                rn, cn = r + (1 if i % 2 else -1), c + (1 if j % 2 else -1)
                out[i, j] = (0.75 * (0.75 * p[r, c] + 0.25 * p[r, cn]) + 0.25 * (0.75 * p[rn, c] + 0.25 * p[rn, cn]))
        return out

    page, weight = np.asarray(page, np.float64), np.asarray(weight, np.float64)
    levels = [(np.where(weight[..., None] > 0, page, 0.0), weight)]
    while levels[-1][0].shape[0] > 1 and levels[-1][0].shape[0] % 2 == 0:
        x, w = levels[-1]
        s = x.shape[0] // 2
        total = w.reshape(s, 2, s, 2).sum(axis=(1, 3))
        mean = (x * w[..., None]).reshape(s, 2, s, 2, -1).sum(axis=(1, 3)) / np.maximum(total, 1e-30)[..., None]
        levels.append((np.where(total[..., None] > 0, mean, 0.0), np.minimum(total, 1.0)))
    x, w = levels[-1]
    filled = np.where(w[..., None] > 0, x, np.sum(x * w[..., None], axis=(0, 1)) / w.sum())
    for level, (x, w) in reversed(list(enumerate(levels[:-1]))):
        w3 = w[..., None]
        filled = w3 * x + (1 - w3) * upsample(filled)
        for _ in range(smoothing * 2 ** min(level, 3) if (w < 1).any() else 0):
            filled = w3 * x + (1 - w3) * mean4(filled)
    return filled


@pytest.mark.parametrize("size", [1, 2, 12, 32])
def test_push_pull_is_its_formula_in_float64(size):
    """The float32, in-place push_pull against its docstring in float64 (12: a coarsest level of
    3x3 texels, not one; 1 and 2: the smallest pages), with soft and hard weights."""
    rng = np.random.default_rng(size)
    page = rng.random((size, size, 3)).astype(np.float32)
    weight = np.where(rng.random((size, size)) < 0.4, 0.0, rng.random((size, size))).astype(np.float32)
    weight.flat[0] = 1.0
    np.testing.assert_allclose(push_pull(page, weight, smoothing=4), reference_push_pull(page, weight, 4),
                               rtol=1e-5, atol=1e-6)


def test_push_pull_weights_blend_and_extremes():
    rng = np.random.default_rng(0)
    const = np.full((16, 16, 3), [0.2, 0.4, 0.6], np.float32)
    weight = (rng.random((16, 16)) > 0.7).astype(np.float32)
    noisy = np.where(weight[..., None] > 0, const, rng.random((16, 16, 3)).astype(np.float32))
    np.testing.assert_allclose(push_pull(noisy, weight), const, rtol=1e-6)      # a constant fills with itself
    half = np.where(weight > 0, 1.0, 0.5).astype(np.float32)       # half trusted: kept more than untrusted ones
    kept, filled = (np.abs(push_pull(noisy, w) - noisy)[weight == 0].mean() for w in (half, weight))
    assert 0 < kept < 0.75 * filled
    np.testing.assert_array_equal(push_pull(noisy, np.zeros((16, 16))), noisy)  # nothing observed: as it was
    np.testing.assert_array_equal(push_pull(noisy, np.ones((16, 16))), noisy)
    assert push_pull(noisy[..., 0], weight).shape == (16, 16)


# ----------------------------------------------------------------------------- sparse tile lookup


@pytest.mark.parametrize("held", ["dense", "sparse"])
def test_tile_grid_reads_like_its_dense_table(held, monkeypatch):
    """`TileGrid` indexed with integer arrays of any shape gives what the dense int32 table gives
    (-1 off the entries), whichever way it is held; a cell outside the grid is an IndexError."""
    monkeypatch.setattr(gather_plan, "holds_dense", lambda cells, entries: held == "dense")
    rng = np.random.default_rng(3)
    shape = (50, 70)
    cells = rng.choice(shape[0] * shape[1], 300, replace=False)
    rows, cols, ids = cells // shape[1], cells % shape[1], rng.permutation(300) + 7
    table = np.full(shape, -1, np.int32)
    table[rows, cols] = ids
    grid = gather_plan.TileGrid.from_entries(shape, rows, cols, ids)
    assert grid.sparse == (held == "sparse")
    np.testing.assert_array_equal(grid.dense(), table)
    qr, qc = rng.integers(0, shape[0], (4, 9)), rng.integers(0, shape[1], (4, 9))
    qr[0, :5], qc[0, :5] = rows[:5], cols[:5]                  # some hits for certain
    np.testing.assert_array_equal(grid[qr, qc], table[qr, qc])
    assert grid[qr, qc].dtype == np.int32
    np.testing.assert_array_equal(grid[qr[0], 3], table[qr[0], 3])          # broadcast, as NumPy does
    empty = gather_plan.TileGrid.from_entries(shape, [], [], [])
    assert (empty[qr, qc] == -1).all() and (empty.dense() == -1).all()
    for r, c in ((shape[0], 0), (0, shape[1]), (-1, 0)):          # no wrap-around either way it is held
        with pytest.raises(IndexError):
            grid[np.array([r]), np.array([c])]


@pytest.mark.parametrize("sampler,tile_size", [("bilinear", 1), ("trilinear", 1), ("trilinear", 4)])
def test_plans_are_the_same_with_sparse_tile_grids(room, sampler, tile_size, monkeypatch):
    """Every tile and coarse-level grid held sparse gives the same texel space (tiles and mip
    children) and plans as dense tables (the reference test above runs with the default, dense at
    these sizes)."""
    mesh, frags = room
    layout = TextureLayout(page_sizes=tuple(16 if i % 3 else 32 for i in range(len(mesh.object_names))),
                           object_page=tuple(range(len(mesh.object_names))), mipmaps=sampler == "trilinear",
                           tile_size=tile_size)
    dense_space = build_texel_space(frags, layout, sampler)
    monkeypatch.setattr(gather_plan, "holds_dense", lambda cells, entries: False)
    sparse_space = build_texel_space(frags, layout, sampler)
    assert all(g.sparse for g in sparse_space.tile_map) and all(g.sparse for m in sparse_space.coarse_maps for g in m)
    for name in ("tile_page", "tile_row", "tile_col"):
        np.testing.assert_array_equal(getattr(sparse_space, name), getattr(dense_space, name))
    for a, b in zip(sparse_space.children, dense_space.children):
        np.testing.assert_array_equal(a, b)
    a, b = build_gather_plans(frags, sparse_space, sampler), build_gather_plans(frags, dense_space, sampler)
    np.testing.assert_array_equal(np.asarray(a.index), np.asarray(b.index))


def test_4096_pages_of_single_texel_tiles_keep_bookkeeping_of_the_tiles_read(room):
    """Bilinear, 1 x 1 tiles, 4096² pages: a dense id table would be 64 MB a page; the grids hold
    12 bytes per tile read (sorted int64 keys and int32 ids) and still index every tap."""
    mesh, frags = room
    pages = len(mesh.object_names)
    layout = TextureLayout(page_sizes=(4096,) * pages, object_page=tuple(range(pages)), mipmaps=False, tile_size=1)
    space = build_texel_space(frags, layout, "bilinear")
    assert all(g.sparse for g in space.tile_map)
    assert sum(g.nbytes for g in space.tile_map) == 12 * space.num_tiles < 1e-3 * pages * 4096 ** 2 * 4
    plan = build_gather_plans(frags, space, "bilinear")
    reads = np.asarray(plan.index)[np.asarray(plan.weight) > 0]
    assert reads.min() >= 0 and reads.max() < space.num_texels
    assert np.unique(reads).size == space.num_texels            # every tile is read, none is missing


@pytest.mark.parametrize("sampler,tile_size", [("bilinear", 1), ("trilinear", 4)])
def test_texel_space_and_plans_built_in_threads_equal_one_thread(room, sampler, tile_size, monkeypatch):
    """The views' taps are worked out two at a time (`threads.ordered_map`), merged in view order:
    the same tiles, mip children, coarse grids and plans as in one thread."""
    import functools

    from jaxdistill import threads

    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=sampler == "trilinear",
                         tile_size=tile_size)
    built = {}
    for workers in (2, 1):
        monkeypatch.setattr(gather_plan, "ordered_map", functools.partial(threads.ordered_map, workers=workers))
        space = build_texel_space(frags, layout, sampler)
        built[workers] = space, build_gather_plans(frags, space, sampler)
    (two, plan_two), (one, plan_one) = built[2], built[1]
    for name in ("tile_page", "tile_row", "tile_col"):
        np.testing.assert_array_equal(getattr(two, name), getattr(one, name))
    for a, b in zip(two.children, one.children):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(two.coarse_maps, one.coarse_maps):
        assert len(a) == len(b) and all(np.array_equal(x.dense(), y.dense()) for x, y in zip(a, b))
    for name in ("index", "weight", "hit"):
        np.testing.assert_array_equal(np.asarray(getattr(plan_two, name)), np.asarray(getattr(plan_one, name)))
    assert np.asarray(plan_one.weight).any()


def test_views_needs_taken_together_give_the_texel_space_of_all_views(room):
    """`texel_needs` of disjoint sets of views, OR-ed, give `build_texel_space` of every view (what
    a process of a multi-process run takes from the primary); one view's alone give fewer tiles."""
    from jaxdistill.render.gather_plan import space_from_needs, texel_needs

    mesh, frags = room
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True, tile_size=4)
    whole = build_texel_space(frags, layout, "trilinear")
    first, rest = texel_needs(frags[:1], layout, "trilinear"), texel_needs(frags[1:], layout, "trilinear")
    union = [[a | b for a, b in zip(pa, pb)] for pa, pb in zip(first, rest)]
    joined = space_from_needs(union, layout)
    for name in ("tile_page", "tile_row", "tile_col"):
        np.testing.assert_array_equal(getattr(joined, name), getattr(whole, name))
    assert len(joined.children) == len(whole.children) > 0
    for a, b in zip(joined.children, whole.children):
        np.testing.assert_array_equal(a, b)
    assert space_from_needs(first, layout).num_tiles < whole.num_tiles
