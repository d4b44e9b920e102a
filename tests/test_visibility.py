"""Visibility counts and weights against a brute-force NumPy count."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill.io import images as imageio
from jaxdistill.render.gather_plan import build_gather_plans, build_texel_space, view_taps
from jaxdistill.render.layout import make_layout
from jaxdistill.render.sampler import render
from jaxdistill.render.visibility import (pixel_weights, texel_evidence, texel_view_statistics, view_counts,
                                          visibility_weights, write_visibility_pages)
from test_sampler import scene_views


def test_weight_formula_and_extremes():
    counts = np.array([0, 1, 2, 3, 6, 7, 10_000], np.float32)
    expected = np.clip(1.0 / (2.0 * np.clip(counts, 1, 6)), 0.1, 10)
    np.testing.assert_allclose(np.asarray(visibility_weights(counts)), expected, rtol=1e-6)
    assert np.isfinite(np.asarray(visibility_weights(jnp.array([0.0, 1e30])))).all()


def level0_taps(frags, layout, space):
    """(texel index, weight) of every level-0 bilinear tap with positive weight, per view."""
    out = []
    for frag in frags:
        page, _, row, col, weight = view_taps(frag, layout, "bilinear")
        used = weight > 0
        out.append((space.texel_index(page[used], row[used], col[used]), weight[used]))
    return out


def test_counts_match_brute_force_bilinear(tmp_path):
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags)
    space = build_texel_space(frags, layout, "bilinear")
    plan = build_gather_plans(frags, space, "bilinear")
    counts = view_counts(plan, space.num_texels)
    brute = np.zeros(space.num_texels, np.int32)
    for index, _ in level0_taps(frags, layout, space):  # one vote per view
        seen = np.unique(index)
        assert seen.min() >= 0
        brute[seen] += 1
    np.testing.assert_array_equal(counts, brute)
    assert counts.min() >= 1 and counts.max() <= len(frags)  # tile 1: texel-exact, every parameter is read

    weights = np.asarray(pixel_weights(plan, counts))
    hit = np.stack([f.hit for f in frags])
    assert np.all(weights[~hit] == 0) and np.all((weights[hit] >= 0.1 - 1e-6) & (weights[hit] <= 0.5 + 1e-6))

    files = write_visibility_pages(counts, space, tmp_path, mesh.object_names)
    exr = [f for f in files if f.suffix == ".exr"]
    assert len(exr) == layout.num_pages
    page0 = imageio.read_image(exr[0])
    assert page0.shape == (32, 32, 1) and page0.max() <= len(frags)


def test_trilinear_counts_cover_coarse_taps():
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 64, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    counts = view_counts(plan, space.num_texels)
    assert counts.max() <= len(frags) and (counts > 0).mean() > 0.5


def test_evidence_is_the_summed_level0_tap_weight_and_spreads_coarse_reads():
    """Bilinear: a texel's evidence is the sum of its taps' weights over all pixels and views
    (brute force), so the total is the number of hit pixels. Trilinear: the total is still the
    hit pixel count (a mip mean passes a read's weight on, 1/4 to each child), and evidence > 0
    exactly where the view counts are."""
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags)
    space = build_texel_space(frags, layout, "bilinear")
    evidence = texel_evidence(build_gather_plans(frags, space, "bilinear"), space.num_texels)
    brute = np.zeros(space.num_texels, np.float64)
    for index, weight in level0_taps(frags, layout, space):
        np.add.at(brute, index, weight)
    np.testing.assert_allclose(evidence, brute, rtol=1e-5, atol=1e-6 * brute.max())
    hits = sum(int(f.hit.sum()) for f in frags)
    assert evidence.sum() == np.float32(evidence.sum()) and abs(evidence.sum() - hits) <= 1e-4 * hits

    layout = make_layout(len(mesh.object_names), "pages", 64, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    evidence = texel_evidence(plan, space.num_texels)
    assert abs(float(evidence.astype(np.float64).sum()) - hits) <= 1e-4 * hits
    np.testing.assert_array_equal(evidence > 0, view_counts(plan, space.num_texels) > 0)


def test_texel_view_statistics_match_brute_force_per_view_values():
    """Each view paints its pixels one constant (2 channels): at a texel, the views that read it
    (brute force from the taps) give mean and population variance of their constants."""
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags)
    space = build_texel_space(frags, layout, "bilinear")
    plan = build_gather_plans(frags, space, "bilinear")
    values = np.array([[0.2, 3.0], [0.5, -1.0], [0.9, 2.0]], np.float32)
    images = [np.broadcast_to(values[v], (*frags[v].shape, 2)) for v in range(len(frags))]
    count, mean, variance = texel_view_statistics(plan, images, space.num_texels)
    readers = [[] for _ in range(space.num_texels)]
    for v, frag in enumerate(frags):
        page, _, row, col, weight = view_taps(frag, layout, "bilinear")
        used = weight > 0
        for texel in np.unique(space.texel_index(page[used], row[used], col[used])):
            readers[texel].append(v)
    np.testing.assert_array_equal(count, [len(r) for r in readers])
    assert (count >= 2).sum() > 100 and (count == 1).sum() > 100          # both cases really occur
    for texel in range(space.num_texels):
        if readers[texel]:
            np.testing.assert_allclose(mean[texel], values[readers[texel]].mean(axis=0), atol=1e-5)
            np.testing.assert_allclose(variance[texel], values[readers[texel]].var(axis=0), atol=1e-5)
        else:
            assert not mean[texel].any() and not variance[texel].any()
    # per channel from a generator (as the evidence export asks, map by map): the same figures
    for c in range(2):
        part = texel_view_statistics(plan, (image[..., c:c + 1] for image in images), space.num_texels)
        np.testing.assert_array_equal(part[0], count)
        np.testing.assert_allclose(part[1][:, 0], mean[:, c], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(part[2][:, 0], variance[:, c], rtol=1e-6, atol=1e-7)


def test_texel_view_statistics_of_varying_images_match_a_float64_reference():
    """Random images per view (values near 10 with spreads of 1e-3, where a float32 sum of
    squares would cancel): every texel's count, mean and variance against float64 NumPy from the
    per-view values, each view's value the gather-weighted mean of its pixels that read the texel
    (taps expanded to level-0 texels through the mip chain by the plan's own transpose, in float64)."""
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    rng = np.random.default_rng(5)
    images = [(10.0 + 1e-3 * rng.standard_normal((*f.shape, 3))).astype(np.float32) for f in frags]
    count, mean, variance = texel_view_statistics(plan, iter(images), space.num_texels)
    with jax.enable_x64(True):
        per_view = []
        for v, image in enumerate(images):
            one = plan.select(v)
            zeros = jnp.zeros((space.num_texels, 1), jnp.float64)
            _, pull = jax.vjp(lambda t: render(t, one), zeros)
            hit = np.asarray(one.hit, np.float64).reshape(*image.shape[:2], 1)
            weight = np.asarray(pull(jnp.asarray(hit))[0])[:, 0]
            sums = np.stack([np.asarray(pull(jnp.asarray(image[..., c:c + 1] * hit, jnp.float64))[0])[:, 0]
                             for c in range(3)], axis=1)
            per_view.append((weight > 0, sums / np.where(weight > 0, weight, 1.0)[:, None]))
    seen = np.stack([s for s, _ in per_view])                          # (V, N)
    values = np.stack([x for _, x in per_view])                        # (V, N, 3)
    np.testing.assert_array_equal(count, seen.sum(axis=0))
    many = count >= 2
    assert many.sum() > 100
    ref_mean = np.where(seen[..., None], values, 0.0).sum(axis=0) / np.maximum(count, 1)[:, None]
    ref_var = np.where(seen[..., None], (values - ref_mean) ** 2, 0.0).sum(axis=0) / np.maximum(count, 1)[:, None]
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-6)
    np.testing.assert_allclose(variance[many], ref_var[many], rtol=0.02, atol=1e-9)
    assert np.median(ref_var[many]) > 1e-8                              # the spreads are really there


def test_texel_view_statistics_ignore_what_missed_pixels_hold():
    """A missed pixel reads no texel: NaN and infinities there leave the statistics as zeros there
    would, bit for bit."""
    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    rng = np.random.default_rng(11)
    hit = np.asarray(plan.hit) & (rng.uniform(size=plan.hit.shape) > 0.1)   # a tenth of the pixels missed
    plan = plan.replace(hit=jnp.asarray(hit), weight=jnp.where(jnp.asarray(hit)[..., None], plan.weight, 0.0))
    clean, dirty = [], []
    for v, f in enumerate(frags):
        image = rng.uniform(-1, 1, (*f.shape, 2)).astype(np.float32)
        missed = ~np.asarray(plan.hit[v]).reshape(f.shape)
        clean.append(np.where(missed[..., None], 0.0, image).astype(np.float32))
        dirty.append(np.where(missed[..., None], np.float32(np.nan), image).astype(np.float32))
        dirty[-1][missed.nonzero()[0][:1], missed.nonzero()[1][:1]] = np.inf
    assert sum(np.isnan(d).any() for d in dirty) >= 1                 # missed pixels really occur
    for a, b in zip(texel_view_statistics(plan, clean, space.num_texels),
                    texel_view_statistics(plan, dirty, space.num_texels)):
        np.testing.assert_array_equal(a, b)


def test_texel_view_statistics_do_not_depend_on_how_the_read_texels_are_chunked(monkeypatch):
    """Each view updates only the texels it reads, a chunk of them per call (`READ_CHUNK`, the ids
    padded with an out-of-range id): chunks of 37 texels (many per view, the last one padded)
    give the same statistics, bit for bit, as one chunk."""
    from jaxdistill.render import visibility

    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    rng = np.random.default_rng(7)
    images = [rng.uniform(-1, 1, (*f.shape, 3)).astype(np.float32) for f in frags]
    whole = texel_view_statistics(plan, images, space.num_texels)
    read = [int((visibility._evidence(plan.select(v), num_texels=space.num_texels) > 0).sum())
            for v in range(plan.num_views)]
    assert max(read) <= visibility.READ_CHUNK                              # one chunk each by default
    monkeypatch.setattr(visibility, "READ_CHUNK", 37)
    assert min(read) > 3 * 37 and any(n % 37 for n in read)               # many chunks, a padded last one
    chunked = texel_view_statistics(plan, images, space.num_texels)
    for a, b in zip(whole, chunked):
        np.testing.assert_array_equal(a, b)
    assert (whole[0] >= 2).sum() > 100 and (whole[0] == 0).sum() < len(whole[0])


def test_texel_trust_expands_to_the_page_trust_of_the_expanded_evidence():
    """What texel_space.npz stores per texel (charts.texel_trust) gives, expanded to pages, the
    very trust pages the export weights its push-pull fill with (charts.page_trust)."""
    from jaxdistill.render import charts
    from jaxdistill.render.sampler import expand

    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags)
    space = build_texel_space(frags, layout, "bilinear")
    evidence = texel_evidence(build_gather_plans(frags, space, "bilinear"), space.num_texels)
    rng = np.random.default_rng(0)
    coverage = [rng.uniform(size=(s, s)) < 0.7 for s in layout.page_sizes]
    expected = charts.page_trust(expand(evidence[:, None], space, 0.0, dilation=0), coverage)
    got = expand(charts.texel_trust(evidence, coverage, space)[:, None], space, 0.0, dilation=0)
    assert any((e > 0).any() and (e < 1).any() for e in expected)                 # partial trust really occurs
    for e, g in zip(expected, got):
        np.testing.assert_array_equal(g[..., 0], e)


def test_several_quantities_in_one_pass_give_each_ones_statistics_alone(monkeypatch):
    """`texel_view_statistics_of` with three quantities a view (3, 1 and 2 channels, as albedo,
    roughness and a 2-channel map): each quantity's count, mean and variance equal, bit for bit, what
    `texel_view_statistics` gives for its images alone (chunks of 37 read texels, so several
    `_accumulate` calls a view); the count, from the plan alone, is one array for all."""
    from jaxdistill.render import visibility

    mesh, frags = scene_views()
    layout = make_layout(len(mesh.object_names), "pages", 32, frags, mipmaps=True)
    space = build_texel_space(frags, layout, "trilinear")
    plan = build_gather_plans(frags, space, "trilinear")
    rng = np.random.default_rng(13)
    widths = (3, 1, 2)
    images = [[rng.uniform(-1, 1, (*f.shape, c)).astype(np.float32) for c in widths] for f in frags]
    for chunk in (visibility.READ_CHUNK, 37):
        monkeypatch.setattr(visibility, "READ_CHUNK", chunk)
        together = visibility.texel_view_statistics_of(plan, (tuple(i) for i in images), space.num_texels)
        alone = [texel_view_statistics(plan, (i[k] for i in images), space.num_texels) for k in range(len(widths))]
        assert len(together) == len(widths)
        for k, (a, b) in enumerate(zip(together, alone)):
            assert a[1].shape == (space.num_texels, widths[k])
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
        assert all(t[0] is together[0][0] for t in together)
        assert (together[0][0] >= 2).sum() > 100 and np.abs(together[0][2]).max() > 0.01     # spreads really there
    with pytest.raises(ValueError, match="no images"):
        visibility.texel_view_statistics_of(plan, iter(()), space.num_texels)
