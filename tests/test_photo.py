"""The re-rendering term (engine/photo.py): its value against a NumPy formula, where its gradient
goes, that --photo_weight=0 is today's step exactly, LDR photos, and photos refused before compute."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill import pipeline
from jaxdistill.engine import config as config_lib, loop, photo
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.problem import build_problem
from jaxdistill.engine.step import StepSettings, _photo_fn, init_state, make_optimizer, make_step
from jaxdistill.errors import InputError
from jaxdistill.io import images as imageio
from jaxdistill.io.view_images import read_photo_linear
from jaxdistill.scene.maps import MapChannels
from tiny_scene import write_tiny_scene
from tolerance import assert_close


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_photo"))


@pytest.fixture(autouse=True)
def fragment_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "fragment_cache"))


def tiny_config(scene, out, **kw) -> DistillConfig:
    base = dict(scene=str(scene), out_dir=str(out), steps=4, views_per_step=2, prior="views", log_every=2,
                renders=False, contact_views=0, lr=0.05)
    base.update(kw)
    return config_lib.validate(DistillConfig(**base))


# ----------------------------------------------------------------------------- the formula


def numpy_photo_loss(images, photo, weights, *, loss, space, scale, ratio):
    """The module docstring's L_photo, written out in float64 NumPy."""
    a = np.maximum(0.5 * (np.asarray(images["albedo"], np.float64) + 1), 0)
    e = np.maximum(0.5 * (np.asarray(images["irradiance"], np.float64) + 1), 0)
    d = a * e
    w = np.asarray(weights, np.float64)
    if "metallic" in images:
        w = w * (1 - np.clip(0.5 * (np.asarray(images["metallic"][..., 0], np.float64) + 1), 0, 1))
    p = np.asarray(photo, np.float64)
    eps = 0.01
    total = 0.0
    if scale == "view":
        groups = [(slice(i, i + 1),) for i in range(p.shape[0])]
    elif scale == "view_rgb":      # one gain per view and colour channel
        groups = [(slice(i, i + 1), Ellipsis, slice(c, c + 1)) for i in range(p.shape[0]) for c in range(3)]
    else:
        groups = [(slice(None),)]
    for g in groups:
        ww = np.broadcast_to(w[..., None], p.shape)[g]
        if scale == "none":
            log_s = 0.0
        elif space == "log":       # the root of Σ w (log(p + eps) − log(s d + eps)) = 0, by bisection
            lo, hi = -20.0, 20.0
            for _ in range(80):
                mid = 0.5 * (lo + hi)
                f = np.sum(ww * (np.log(p[g] + eps) - np.log(np.exp(mid) * d[g] + eps)))
                lo, hi = (mid, hi) if f > 0 else (lo, mid)
            log_s = 0.5 * (lo + hi)
        else:
            log_s = np.log(np.sum(ww * p[g] * d[g]) / np.sum(ww * d[g] ** 2))
        if space == "log":
            r = np.log(p[g] + eps) - np.log(np.exp(log_s) * d[g] + eps)
        else:
            r = p[g] - np.exp(log_s) * d[g]
        rho = r ** 2 if loss == "l2" else np.sqrt(r ** 2 + 0.05 ** 2) - 0.05
        total += np.sum(ww * rho)
    return ratio * total / p.shape[0]


@pytest.mark.parametrize("space,loss,scale", [("log", "charbonnier", "batch"), ("linear", "l2", "view"),
                                              ("log", "l2", "none"), ("linear", "charbonnier", "batch"),
                                              ("log", "charbonnier", "view_rgb"), ("linear", "l2", "view_rgb")])
def test_the_photo_loss_is_the_documented_formula(space, loss, scale):
    rng = np.random.default_rng(3)
    b, h, w = 3, 5, 7
    images = {"albedo": rng.uniform(-1, 1, (b, h, w, 3)), "irradiance": rng.uniform(-1, 1, (b, h, w, 3)),
              "metallic": rng.uniform(-1, 1, (b, h, w, 1)), "normal": rng.normal(size=(b, h, w, 3))}
    photo_img = rng.uniform(0, 1.5, (b, h, w, 3))
    weights = rng.uniform(0, 1, (b, h, w))
    hit = np.ones((b, h, w), bool)
    got, metrics = photo.photo_loss({k: jnp.asarray(v, jnp.float32) for k, v in images.items()},
                                    jnp.asarray(photo_img, jnp.float32), jnp.asarray(weights, jnp.float32),
                                    jnp.asarray(hit), loss=loss, space=space, scale=scale, pixel_ratio=0.25)
    want = numpy_photo_loss(images, photo_img, weights, loss=loss, space=space, scale=scale, ratio=0.25)
    assert_close(float(got), want, rtol=2e-5)
    assert_close(float(metrics["loss_photo"]), want, rtol=2e-5)


def test_a_photo_that_is_the_product_scaled_costs_nothing_with_a_fitted_scale():
    """photo = 3 x albedo x irradiance exactly: the fitted scale is log 3 and the loss 0."""
    rng = np.random.default_rng(0)
    images = {"albedo": jnp.asarray(rng.uniform(-0.8, 0.8, (2, 4, 4, 3)), jnp.float32),
              "irradiance": jnp.asarray(rng.uniform(-0.8, 0.8, (2, 4, 4, 3)), jnp.float32)}
    product = photo.diffuse_photo(images)
    for space in photo.PHOTO_SPACES:
        value, metrics = photo.photo_loss(images, 3.0 * product, jnp.ones((2, 4, 4)), jnp.ones((2, 4, 4), bool),
                                          loss="l2", space=space, scale="batch", pixel_ratio=1.0)
        assert float(value) < 1e-8
        assert_close(float(metrics["photo_log_scale"]), np.log(3.0), rtol=1e-4)


def test_a_per_view_white_balance_and_exposure_cost_nothing_with_view_rgb_alone():
    """Each view's photo is the product times its own RGB gain (auto-exposure and white balance):
    view_rgb recovers every gain and the loss is 0; one scale per view or batch cannot."""
    rng = np.random.default_rng(1)
    images = {"albedo": jnp.asarray(rng.uniform(-0.8, 0.8, (3, 6, 5, 3)), jnp.float32),
              "irradiance": jnp.asarray(rng.uniform(-0.8, 0.8, (3, 6, 5, 3)), jnp.float32)}
    gains = np.exp(rng.normal(0.0, 0.4, (3, 1, 1, 3)))
    photo_img = gains * np.asarray(photo.diffuse_photo(images))
    ones, hit = jnp.ones((3, 6, 5)), jnp.ones((3, 6, 5), bool)
    for space in photo.PHOTO_SPACES:
        losses = {}
        for scale in ("view_rgb", "view", "batch"):
            losses[scale], metrics = photo.photo_loss(images, jnp.asarray(photo_img, jnp.float32), ones, hit,
                                                      loss="l2", space=space, scale=scale, pixel_ratio=1.0)
        assert float(losses["view_rgb"]) < 1e-8
        assert float(losses["view"]) > 1e3 * max(float(losses["view_rgb"]), 1e-10)
        assert float(losses["batch"]) >= float(losses["view"])
        log_s = photo.log_scale(jnp.asarray(photo_img, jnp.float32), photo.diffuse_photo(images), ones,
                                "view_rgb", space)
        assert log_s.shape == (3, 1, 1, 3)
        assert_close(np.asarray(log_s), np.log(gains), rtol=1e-3)


def test_photo_scale_auto_is_per_view_and_channel_for_ldr_photos_and_per_batch_for_hdr():
    assert photo.resolve_scale("auto", ldr=True) == "view_rgb"
    assert photo.resolve_scale("auto", ldr=False) == "batch"
    for mode in ("batch", "view", "view_rgb", "none"):
        assert photo.resolve_scale(mode, ldr=True) == photo.resolve_scale(mode, ldr=False) == mode
    with pytest.raises(ValueError, match="not resolved"):
        photo.log_scale(jnp.ones((1, 2, 2, 3)), jnp.ones((1, 2, 2, 3)), jnp.ones((1, 2, 2)), "auto", "log")


def test_the_smoothness_term_counts_only_pairs_of_covered_pixels():
    """Δ log E over horizontal and vertical neighbours, weighted by the pair's mean weight, only
    where both pixels are covered (NumPy reference)."""
    rng = np.random.default_rng(1)
    irr = rng.uniform(-1, 1, (2, 4, 5, 3))
    weights = rng.uniform(0, 1, (2, 4, 5))
    hit = rng.uniform(size=(2, 4, 5)) > 0.3
    got = photo.smoothness(jnp.asarray(irr, jnp.float32), jnp.asarray(weights, jnp.float32), jnp.asarray(hit), "l2")
    log_e = np.log(np.maximum(0.5 * (irr + 1), 0) + 0.01)
    want = np.zeros(2)
    for b in range(2):
        for y in range(4):
            for x in range(5):
                for dy, dx in ((0, 1), (1, 0)):
                    yy, xx = y + dy, x + dx
                    if yy < 4 and xx < 5 and hit[b, y, x] and hit[b, yy, xx]:
                        wpair = 0.5 * (weights[b, y, x] + weights[b, yy, xx])
                        want[b] += wpair * np.sum((log_e[b, yy, xx] - log_e[b, y, x]) ** 2)
    assert_close(np.asarray(got), want, rtol=2e-5)
    # a guide multiplies each pair's weight: channel 0 the (x, x+1) pairs, channel 1 the (y, y+1) pairs
    guide = rng.uniform(0, 1, (2, 4, 5, 2))
    guided = photo.pair_penalty(jnp.asarray(log_e, jnp.float32), jnp.asarray(weights, jnp.float32), jnp.asarray(hit),
                                "l2", jnp.asarray(guide, jnp.float32))
    want = np.zeros(2)
    for b in range(2):
        for y in range(4):
            for x in range(5):
                for dy, dx, ch in ((0, 1, 0), (1, 0, 1)):
                    yy, xx = y + dy, x + dx
                    if yy < 4 and xx < 5 and hit[b, y, x] and hit[b, yy, xx]:
                        wpair = 0.5 * (weights[b, y, x] + weights[b, yy, xx]) * guide[b, y, x, ch]
                        want[b] += wpair * np.sum((log_e[b, yy, xx] - log_e[b, y, x]) ** 2)
    assert_close(np.asarray(guided), want, rtol=2e-5)


def test_the_chroma_guide_lets_colour_edges_through_and_smooths_light_edges():
    """A brightness step at constant colour (a shadow edge) keeps the albedo pair's full weight; a
    step of colour at constant brightness drops it to ~0; unusable pixels and the border give 0;
    the weight is exp(-|Δc|^2 / (2 σ^2)) of the 3 x 3 box-filtered chromaticity (by hand)."""
    h, w = 6, 8
    colour = np.array([0.6, 0.3, 0.1])
    shadow = np.ones((h, w, 3)) * colour
    shadow[:, 4:] *= 0.2                                  # the right half in shadow: same chromaticity
    g = photo.chroma_guide(shadow)
    assert g.shape == (h, w, 2) and g.dtype == np.float32
    assert_close(g[:, :-1, 0], np.ones((h, w - 1)), rtol=1e-4)        # 1 up to CHROMA_FLOOR
    assert np.all(g[:, -1, 0] == 0) and np.all(g[-1, :, 1] == 0)
    paint = np.ones((h, w, 3)) * colour
    paint[:, 4:] = np.array([0.1, 0.3, 0.6]) * (colour.sum() / 1.0)   # the same brightness, another colour
    g = photo.chroma_guide(paint)
    assert np.all(g[:, 2:5, 0] < 1e-6) and np.all(g[:, :2, 0] > 0.999)
    usable = np.ones((h, w), bool)
    usable[2, 3] = False
    g = photo.chroma_guide(shadow, usable)
    assert g[2, 2, 0] == 0 and g[2, 3, 0] == 0 and g[1, 3, 1] == 0 and g[2, 3, 1] == 0 and g[2, 1, 0] > 0.999
    rng = np.random.default_rng(2)
    noisy = rng.uniform(0.1, 1.0, (h, w, 3))
    pad = np.pad(noisy, ((1, 1), (1, 1), (0, 0)), mode="edge")
    box = np.zeros_like(noisy)
    for y in range(h):
        for x in range(w):
            box[y, x] = pad[y:y + 3, x:x + 3].mean(axis=(0, 1))
    c = box / (box.sum(-1, keepdims=True) + photo.CHROMA_FLOOR * noisy.mean() * 3)
    want = np.exp(-np.sum((c[:, 1:] - c[:, :-1]) ** 2, -1) / (2 * photo.CHROMA_SIGMA ** 2))
    assert_close(photo.chroma_guide(noisy)[:, :-1, 0], want, rtol=1e-5)


# ----------------------------------------------------------------------------- in the step


def photo_problem(scene, tmp_path, **kw):
    config = tiny_config(scene, tmp_path / "out", photo_weight=1.0, **kw)
    return config, build_problem(config)


def test_the_gradient_reaches_albedo_and_irradiance_only_where_the_views_see_them(tiny_scene, tmp_path):
    config, problem = photo_problem(tiny_scene, tmp_path, photo_scale="none")   # a fitted scale is held fixed
    settings = loop.step_settings(config, problem)
    ids = np.array([0, 2])
    batch = problem.batch(ids)
    rng = np.random.default_rng(0)
    texels = jnp.asarray(problem.initial_texels() + rng.uniform(-0.3, 0.3, (problem.space.num_texels,
                                                                              problem.channels.num_channels)),
                         jnp.float32)
    (value, _), grad = jax.value_and_grad(_photo_fn(settings, batch, problem.frozen), has_aux=True)(texels)
    grad = np.asarray(grad)
    channels = problem.channels
    moved = np.abs(grad) > 0
    for m in channels.maps:
        if m not in ("albedo", "irradiance"):
            assert not moved[:, channels.slice(m)].any(), f"the photo term moved {m}"
    # the texels any tap of the batch's photo plans reads with a non-zero weight, at mip level 0
    # or (trilinear) above it: nothing outside them gets a gradient, and most of them do
    index = np.asarray(batch["photo_index"]).reshape(-1)
    tap = (np.asarray(batch["photo_tap_weight"]).reshape(-1) > 0) & np.repeat(
        np.asarray(batch["photo_hit"]).reshape(-1), batch["photo_index"].shape[-1])
    read = np.zeros(problem.space.pyramid_size, bool)
    read[index[tap]] = True
    level0 = read[:problem.space.num_texels]
    colour = moved[:, channels.slice("albedo")].any(axis=1) | moved[:, channels.slice("irradiance")].any(axis=1)
    if problem.space.pyramid_size == problem.space.num_texels:     # bilinear: no mips above level 0
        assert not (colour & ~level0).any()
        assert colour[level0].mean() > 0.9
    # a view outside the batch adds nothing: the gradient of the other two views differs
    (_, _), other = jax.value_and_grad(_photo_fn(settings, problem.batch(np.array([1, 3])), problem.frozen),
                                       has_aux=True)(texels)
    assert not np.allclose(np.asarray(other), grad)
    # one texel against a central finite difference (a step large enough for float32)
    t = int(np.argmax(np.abs(grad[:, channels.slice("albedo").start])))
    c = channels.slice("albedo").start
    h = 3e-3

    def value_at(delta):
        moved_texels = texels.at[t, c].add(delta)
        return float(_photo_fn(settings, batch, problem.frozen)(moved_texels)[0])

    finite_difference = (value_at(h) - value_at(-h)) / (2 * h)
    assert_close(finite_difference, grad[t, c], rtol=0.05)
    assert np.isfinite(float(value))


def test_the_step_adds_the_photo_gradient_to_the_sds_gradient_on_one_shared_pyramid(tiny_scene, tmp_path):
    """The step builds one mip pyramid for the renders and the photos and transposes it once: its
    jaxpr concatenates a pyramid's levels above the texels once (the split pyramid: the texels are
    never copied into it) and gathers from the texels once for both, and its gradient (read off an SGD step) is the SDS step's
    gradient plus the weighted gradient of `_photo_fn`, which builds its own pyramid from the texels."""
    import optax

    config, problem = photo_problem(tiny_scene, tmp_path, photo_scale="none", sampler="trilinear",
                                    irradiance_smoothness=0.5, albedo_smoothness=0.5)
    assert problem.space.pyramid_size > problem.space.num_texels        # there are mip levels to share
    settings = dataclasses.replace(loop.step_settings(config, problem), split_pyramid=True)   # as on the CPU
    assert settings.photo_weight == 1.0
    batch = problem.batch(np.array([0, 2]))
    rng = np.random.default_rng(1)
    texels = (problem.initial_texels()
              + rng.uniform(-0.3, 0.3, (problem.space.num_texels, problem.channels.num_channels))).astype(np.float32)
    rate = 1e4            # the update dwarfs the texels: (texels - new) / rate is the gradient to float32 rounding

    def gradient(step_settings):
        step = make_step(problem.prior, step_settings, optax.sgd(rate))
        state, metrics = jax.jit(step)(init_state(texels, optax.sgd(rate), 0), batch, problem.frozen)
        assert int(metrics["finite"]) == 1
        return (texels.astype(np.float64) - np.asarray(state.texels, np.float64)) / rate, step

    weight = 0.7
    both, step = gradient(dataclasses.replace(settings, photo_weight=weight))
    sds, _ = gradient(dataclasses.replace(settings, photo_weight=0.0))
    (_, _), photo_grad = jax.value_and_grad(_photo_fn(settings, batch, problem.frozen), has_aux=True)(
        jnp.asarray(texels))
    expected = sds + weight * np.asarray(photo_grad, np.float64)
    assert np.abs(weight * np.asarray(photo_grad)).max() > 1e-2 * np.abs(expected).max()   # there to be added
    assert_close(both, expected, rtol=1e-4, floor=1e-5)
    jaxpr = jax.make_jaxpr(step)(init_state(texels, optax.sgd(rate), 0), batch, problem.frozen)
    rows = [e.outvars[0].aval.shape[0] for e in jaxpr.eqns if e.primitive.name == "concatenate"]
    space = problem.space                        # one pyramid, split: its levels above the texels concatenated
    assert rows.count(space.pyramid_size - space.num_texels) == 1 and space.pyramid_size not in rows   # once
    # the renders' and the photos' taps read by one gather from the texels (`sampler.sample_many`)
    gathers = [e for e in jaxpr.eqns if e.primitive.name == "gather" and e.invars[0].aval.shape == texels.shape]
    assert len(gathers) == 1


def test_photo_weight_zero_is_todays_step_exactly(tiny_scene, tmp_path):
    """--photo_weight=0 traces the very program today's step traces (the same jaxpr: the same
    XLA computation, bit for bit), batches carry no photo arrays, and whole runs with the other
    photo flags changed write identical texels and metrics."""
    config = tiny_config(tiny_scene, tmp_path / "a")
    problem = build_problem(config)
    assert problem.photos is None and problem.photo_shape == (0, 0)
    batch = problem.batch(np.array([0, 1]))
    assert not any(k.startswith("photo") for k in batch)
    before = StepSettings(channels=problem.channels, height=problem.height, width=problem.width,
                          total_steps=config.steps, t_min=config.t_min, t_max=config.t_max, anneal=config.anneal,
                          t_weighting=config.t_weighting, p_keep=config.p_keep,
                          num_train_timesteps=1000, reuse_steps=config.reuse_steps, align=config.align,
                          align_strength=config.align_strength)       # how the loop built it before the term
    odd = dataclasses.replace(config, photo_space="linear", photo_loss="l2", photo_scale="none",
                              irradiance_smoothness=2.0, photo_size=16, albedo_smoothness=3.0)
    now = loop.step_settings(odd, problem)
    optimizer = make_optimizer(config.lr, 0.0)
    state = init_state(problem.initial_texels(), optimizer, 0)

    def jaxpr(settings):
        return str(jax.make_jaxpr(make_step(problem.prior, settings, optimizer))(state, batch, problem.frozen))

    assert jaxpr(now) == jaxpr(before)
    first = pipeline.run(config, progress=False)
    second = pipeline.run(dataclasses.replace(odd, out_dir=str(tmp_path / "b")), progress=False)
    assert first["history"]["loss"] == second["history"]["loss"]
    assert first["ours"] == second["ours"]
    a = np.load(tmp_path / "a" / "texel_space.npz")
    b = np.load(tmp_path / "b" / "texel_space.npz")
    assert all(np.array_equal(a[k], b[k]) for k in a.files if k != "config")


def test_the_photo_scale_auto_resolves_by_the_scenes_photos(tiny_scene, tmp_path):
    """HDR photos (the tiny scene's EXRs) get one scale per batch; an LDR copy of the scene
    (PNGs, a phone's per-shot exposure and white balance) a gain per view and channel."""
    from jaxdistill.datasets.ldr import write_ldr_scene
    config, problem = photo_problem(tiny_scene, tmp_path / "hdr")
    assert config.photo_scale == "auto" and problem.photos.scale == "batch"
    assert loop.step_settings(config, problem).photo_scale == "batch"
    write_ldr_scene(tiny_scene, tmp_path / "ldr_scene", exposure_jitter=1.0, white_balance_jitter=0.1)
    config, problem = photo_problem(tmp_path / "ldr_scene", tmp_path / "ldr")
    assert problem.photos.scale == "view_rgb" and loop.step_settings(config, problem).photo_scale == "view_rgb"
    config, problem = photo_problem(tmp_path / "ldr_scene", tmp_path / "ldr_view", photo_scale="view")
    assert problem.photos.scale == "view"


def test_a_run_with_the_term_explains_its_photos_better_and_says_so(tiny_scene, tmp_path):
    """metrics.json's `rerender` (every view re-rendered as albedo x irradiance, PSNR against the
    photo) is reported with and without the term, and the term raises it."""
    off = pipeline.run(tiny_config(tiny_scene, tmp_path / "off", steps=8), progress=False)
    on = pipeline.run(tiny_config(tiny_scene, tmp_path / "on", steps=8, photo_weight=1.0, irradiance_smoothness=0.1),
                      progress=False)
    assert on["config"]["photo_weight"] == 1.0 and all(np.isfinite(on["history"]["loss"]))
    for summary in (off, on):
        scores = summary["rerender"]
        assert set(scores["per_view"]) == {"v0", "v1", "v2", "v3"}
        assert_close(scores["psnr_db"], np.mean(list(scores["per_view"].values())), rtol=1e-9)
    assert on["rerender"]["psnr_db"] > off["rerender"]["psnr_db"] + 1.0


def test_the_noise_estimate_reads_gaussian_log_noise_and_ignores_edges_and_texture():
    """`log_noise` against a known σ: a flat photo with Gaussian noise in log units reads σ within
    3 % (90 000 pairs; the MAD's own error is about 0.5 %), a clean photo of stripes (a third
    of the x pairs on an edge) reads 0, and wider stripes with noise read the noise."""
    rng = np.random.default_rng(0)
    h, w = 150, 300
    for sigma in (0.05, 0.3, 0.8):
        log_grey = np.log(0.4 + photo.PHOTO_EPS) + rng.normal(0.0, sigma, (h, w))
        image = np.repeat((np.exp(log_grey) - photo.PHOTO_EPS)[..., None], 3, axis=-1)
        assert_close(photo.log_noise(image), sigma, rtol=0.03)
    stripes = np.where((np.arange(w) // 3) % 2 == 0, 0.8, 0.1)[None, :, None] * np.ones((h, w, 3))
    stripes[:, :, 1] *= 0.5                                     # colour: the estimate reads brightness
    assert photo.log_noise(stripes) == 0.0
    wide = np.where((np.arange(w) // 8) % 2 == 0, 0.8, 0.1)[None, :, None] * np.ones((h, w, 3))
    noisy = wide * np.exp(rng.normal(0.0, 0.2, (h, w, 1)))
    assert_close(photo.log_noise(noisy), 0.2, rtol=0.1)         # edges (1/16 of the pairs) raise the median ~6 %
    usable = np.zeros((h, w), np.float32)
    usable[:4, :4] = 1                                          # 24 pairs: too few to say
    assert photo.log_noise(noisy, usable) == 0.0


def test_the_noise_weight_is_inverse_variance_above_the_reference_and_one_below():
    assert photo.noise_weight(0.6, 0.3) == pytest.approx(0.25, rel=1e-12)
    assert photo.noise_weight(0.2, 0.3) == 1.0 and photo.noise_weight(0.3, 0.3) == 1.0
    assert photo.noise_weight(5.0, 0.0) == 1.0 and photo.noise_weight(0.0, 0.3) == 1.0


def test_photo_noise_ref_weighs_each_views_pixels_by_its_photos_noise(tiny_scene, tmp_path):
    """--photo_noise_ref scales every pixel weight of a view by noise_weight(σ_v) of its own photo
    and nothing else; metrics.json records each view's σ and weight."""
    _, plain = photo_problem(tiny_scene, tmp_path / "plain")
    sigma = plain.photos.noise
    assert sigma.shape == (4,) and np.all(sigma >= 0) and np.all(plain.photos.noise_weight == 1.0)
    ref = float(np.median(sigma[sigma > 0])) if np.any(sigma > 0) else 1.0
    _, guarded = photo_problem(tiny_scene, tmp_path / "guarded", photo_noise_ref=ref)
    expected = np.array([photo.noise_weight(s, ref) for s in sigma])
    assert np.any(expected < 1.0)
    assert_close(guarded.photos.noise_weight, expected, rtol=1e-12)
    assert_close(guarded.photos.pixel_weight, plain.photos.pixel_weight * expected[:, None, None].astype(np.float32),
                 rtol=1e-6)
    assert np.array_equal(guarded.photos.photos, plain.photos.photos)
    summary = pipeline.run(tiny_config(tiny_scene, tmp_path / "run", photo_weight=1.0, photo_noise_ref=ref),
                           progress=False)
    assert summary["photo_noise"]["ref"] == ref
    assert_close(np.array(list(summary["photo_noise"]["weight"].values())), expected, rtol=1e-3)


# ----------------------------------------------------------------------------- photos


def srgb_decode(v):
    """IEC 61966-2-1, written independently of the package."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def test_an_ldr_photo_is_decoded_and_its_clipped_pixels_dropped(tmp_path):
    values = np.full((8, 10, 3), 0.5, np.float32)
    values[2, 3] = [1.0, 0.2, 0.2]                # one clipped channel
    values[6, 8] = [0.3, 0.3, 0.3]
    path = tmp_path / "photo.png"
    imageio.write_image(path, values, encode_srgb=False)
    stored = imageio.read_image(path, linear=False)
    linear, usable = read_photo_linear(path, 1.0, 8, 10)
    assert_close(linear, 2.0 * srgb_decode(stored), rtol=1e-5)
    assert usable[2, 3] == 0 and usable.sum() == 8 * 10 - 1
    small, usable_small = read_photo_linear(path, 0.0, 4, 5)
    rows, cols = np.nonzero(usable_small == 0)       # the pixels whose filter footprint holds it, and only those
    assert usable_small[1, 1] == 0 and set(rows) <= {0, 1, 2} and set(cols) <= {1, 2} and usable_small.sum() >= 15


def test_an_hdr_photo_is_exposed_and_its_negatives_clamped(tmp_path):
    values = np.full((4, 4, 3), 0.25, np.float32)
    values[0, 0] = [-0.01, 2.0, 0.5]
    path = tmp_path / "photo.exr"
    imageio.write_image(path, values)
    linear, usable = read_photo_linear(path, -1.0, 4, 4)
    assert_close(linear[0, 0], [0.0, 1.0, 0.25], rtol=1e-6)
    assert usable.all()


def test_a_black_photo_is_refused_before_compute_naming_the_file(tmp_path, monkeypatch):
    scene = write_tiny_scene(tmp_path / "scene")
    photo_path = sorted((tmp_path / "scene" / "photos").glob("*.exr"))[0]
    shape = imageio.read_image(photo_path).shape
    imageio.write_image(photo_path, np.zeros(shape, np.float32))
    monkeypatch.setattr(pipeline, "run_record", lambda *a, **k: pytest.fail("computed before refusing"))
    with pytest.raises(InputError, match=rf"{photo_path.name}.*no pixel above zero"):
        pipeline.run(tiny_config(scene, tmp_path / "out", photo_weight=1.0), progress=False)
    broken = np.full(shape, -0.5, np.float32)
    broken[: shape[0] // 4] = 0.5                 # a quarter above zero, the rest negative
    imageio.write_image(photo_path, broken)
    with pytest.raises(InputError, match=r"more pixels below zero .* than above"):
        pipeline.run(tiny_config(scene, tmp_path / "out2"), progress=False)


def test_the_photo_flags_are_checked_naming_the_flag(tiny_scene, tmp_path):
    with pytest.raises(InputError, match=r"--photo_weight.*lacks irradiance"):
        tiny_config(tiny_scene, tmp_path / "o", maps=("albedo", "normal"), photo_weight=1.0)
    with pytest.raises(InputError, match=r"--photo_weight: must be >= 0"):
        tiny_config(tiny_scene, tmp_path / "o", photo_weight=-1.0)
    with pytest.raises(InputError, match=r"--photo_size"):
        tiny_config(tiny_scene, tmp_path / "o", photo_size=4)
    for name in ("irradiance_smoothness", "albedo_smoothness"):     # no silent no-op without the term
        with pytest.raises(InputError, match=rf"--{name}: is part of the re-rendering term"):
            tiny_config(tiny_scene, tmp_path / "o", **{name: 1.0})
    assert tiny_config(tiny_scene, tmp_path / "o", photo_noise_ref=0.3).photo_weight == 0   # shapes the term only
    with pytest.raises(InputError, match=r"--photo_noise_ref: must be >= 0"):
        tiny_config(tiny_scene, tmp_path / "o", photo_weight=1.0, photo_noise_ref=-0.1)
    with pytest.raises(InputError, match=r"--albedo_smoothness: must be >= 0"):
        tiny_config(tiny_scene, tmp_path / "o", photo_weight=1.0, albedo_smoothness=-1.0)
    with pytest.raises(InputError, match=r"--irradiance_sds_weight: must be >= 0"):
        tiny_config(tiny_scene, tmp_path / "o", irradiance_sds_weight=-0.5)


def test_evaluation_reuses_the_photo_plans_it_would_otherwise_build_again(tiny_scene, tmp_path):
    """Renders at 16 px, photos re-rendered at their own size: the evaluation's native-size plans
    are the re-rendering term's, identical to the plans built from the native fragments."""
    from jaxdistill.evaluate.scoring import evaluation_context
    from jaxdistill.render.gather_plan import build_gather_plans

    config = tiny_config(tiny_scene, tmp_path / "out", render_size=16, photo_weight=1.0)
    problem = build_problem(config)
    assert problem.height != problem.photos.height
    plan = evaluation_context(config, problem).plan
    built = build_gather_plans(problem.native_fragments, problem.space, config.sampler)
    assert plan.index is problem.photos.index
    for name in ("index", "weight", "hit"):
        assert np.array_equal(np.asarray(getattr(plan, name)), np.asarray(getattr(built, name))), name
    assert (plan.height, plan.width) == (built.height, built.width)
