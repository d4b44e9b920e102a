"""Per-view photometric gains (--align=gain) against NumPy formulas and a case with known gains."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill.engine import gains as align
from jaxdistill.export import anchor
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.step import StepSettings, init_state, initial_align, make_optimizer, make_step
from jaxdistill.scene.maps import MapChannels
from jaxdistill.engine.priors import ViewsPrior
from jaxdistill.engine.problem import build_problem
from jaxdistill.render.gather_plan import GatherPlan
from jaxdistill.render.sampler import render
from tiny_scene import write_tiny_scene
from tolerance import assert_close


def test_gains_and_ridge_follow_their_formulas():
    rng = np.random.default_rng(0)
    channels = MapChannels(("albedo", "normal", "roughness", "irradiance"))
    assert align.aligned_maps(channels) == ("albedo", "irradiance") and align.num_gains(channels) == 6
    log_gains = rng.normal(0, 0.2, (5, 6)).astype(np.float32)
    views = np.array([3, 0], np.int32)
    targets = {m: rng.uniform(-1, 1, (2, 4, 6, c)).astype(np.float32)
               for m, c in (("albedo", 3), ("normal", 3), ("roughness", 1), ("irradiance", 3))}
    out = align.apply_gains(targets, jnp.asarray(log_gains), views, channels)
    g = np.exp(log_gains - log_gains.mean(axis=0))[views]                  # geometric mean 1 per channel
    assert_close(np.prod(np.exp(log_gains - log_gains.mean(axis=0)), axis=0), np.ones(6), rtol=1e-5)
    lin = (targets["albedo"] + 1) / 2
    assert_close(np.asarray(out["albedo"]), 2 * g[:, None, None, :3] * lin - 1, rtol=1e-5, floor=1e-6)
    lin = (targets["irradiance"] + 1) / 2
    assert_close(np.asarray(out["irradiance"]), 2 * g[:, None, None, 3:] * lin - 1, rtol=1e-5, floor=1e-6)
    for m in ("normal", "roughness"):
        np.testing.assert_array_equal(np.asarray(out[m]), targets[m])
    weights = rng.uniform(0, 1, (2, 4, 6)).astype(np.float32)
    a = (log_gains - log_gains.mean(axis=0))[views]
    expected = 0.3 * np.sum(weights.sum(axis=(1, 2)) * np.sum(a ** 2, axis=1)) / 2
    assert_close(float(align.ridge(jnp.asarray(log_gains), views, weights, 0.3)), expected, rtol=1e-5)


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    scene = write_tiny_scene(tmp_path_factory.mktemp("align_scene"), views=8, targets=True, gt=False)
    config = DistillConfig(scene=str(scene), out_dir="unused", maps=("albedo",), prior="views")
    return build_problem(config, cache_dir=tmp_path_factory.mktemp("cache"))


def scaled_targets(problem, truth, gains):
    """(V, H, W, 3) model-space targets: the renders of the texels `truth` (linear albedo),
    each view's scaled by its gains (V, 3), as a per-image estimator's arbitrary scale would."""
    batch = problem.batch(np.arange(problem.num_views))
    plan = GatherPlan(index=batch["index"], weight=batch["weight"], hit=batch["hit"], chain=problem.frozen["chain"],
                      height=problem.height, width=problem.width)
    lin = np.asarray(render(jnp.asarray(truth, jnp.float32), plan)) * gains[:, None, None, :]   # sampler: test_sampler
    hit = batch["hit"].reshape(problem.num_views, problem.height, problem.width, 1)
    return np.where(hit, 2 * lin - 1, 0.0).astype(np.float32)


def run(problem, prior, settings, steps, lr=0.05):
    optimizer = make_optimizer(lr, 0.0, "cosine", steps)
    gain_optimizer = make_optimizer(lr, 0.0, "cosine", steps) if settings.align == "gain" else None
    state = init_state(problem.initial_texels(), optimizer, 0,
                       align=initial_align(problem.num_views, problem.channels, gain_optimizer))
    step = jax.jit(make_step(prior, settings, optimizer, gain_optimizer))
    problem = dataclasses.replace(problem, prior=prior)           # batches carry this prior's targets
    rng = np.random.default_rng(1)
    for _ in range(steps):
        state, metrics = step(state, problem.batch(rng.choice(problem.num_views, 4, replace=False)), problem.frozen)
        assert metrics["finite"] == 1
    return state


def test_known_per_view_gains_are_recovered_and_the_texture_keeps_their_mean_scale(problem):
    """Targets = renders of a texture x per-view gains g_v: --align=gain learns the gains that undo
    them, geomean(g) / g_v (the targets' own geometric-mean scale is kept: the anchoring), and the
    texture becomes truth x geomean(g); without alignment the views' disagreement stays in the texels."""
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.2, 0.6, (problem.space.num_texels, 3))
    gains = np.exp(rng.normal(0, 0.15, (problem.num_views, 3)))
    prior = ViewsPrior(problem.channels, scaled_targets(problem, truth, gains))
    base = StepSettings(channels=problem.channels, height=problem.height, width=problem.width, total_steps=400)
    aligned = run(problem, prior, dataclasses.replace(base, align="gain", align_strength=1e-4), 400)
    plain = run(problem, prior, base, 400)

    learned = np.exp(np.asarray(align.centred(aligned.align["log_gains"])))
    geomean = np.exp(np.log(gains).mean(axis=0))
    assert_close(learned, geomean / gains, rtol=0.02)
    seen = problem.evidence >= 1.0               # well observed: a texel's summed tap weight over the views
    expected = 2 * truth * geomean - 1
    err_aligned = np.abs(np.asarray(aligned.texels)[seen] - expected[seen]).mean()
    err_plain = np.abs(np.asarray(plain.texels)[seen] - expected[seen]).mean()
    assert err_aligned < 0.02 < err_plain
    assert err_aligned < err_plain / 4


def test_with_zero_strength_and_unit_gains_the_first_step_equals_the_plain_step(problem):
    """Gains start at 1, so the first aligned step's loss and texels equal the plain step's."""
    rng = np.random.default_rng(3)
    prior = ViewsPrior(problem.channels, scaled_targets(problem, rng.uniform(0.2, 0.6, (problem.space.num_texels, 3)),
                                                        np.ones((problem.num_views, 3))))
    base = StepSettings(channels=problem.channels, height=problem.height, width=problem.width, total_steps=1)
    a = run(problem, prior, dataclasses.replace(base, align="gain", align_strength=0.5), 1)
    b = run(problem, prior, base, 1)
    np.testing.assert_array_equal(np.asarray(a.texels), np.asarray(b.texels))


def srgb_mean(x):
    """Mean of the IEC 61966-2-1 sRGB encoding of linear values clipped to [0, 1], per channel."""
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055).mean(axis=0)


def test_anchor_gains_give_the_renders_the_estimates_mean_in_srgb(monkeypatch):
    rng = np.random.default_rng(2)
    hits = [rng.uniform(size=(5, 7)) > 0.3 for _ in range(3)]
    renders = [{m: rng.uniform(0, 0.8, (5, 7, c)).astype(np.float32) for m, c in
                (("albedo", 3), ("irradiance", 3), ("roughness", 1))} for _ in range(3)]
    renders[0]["irradiance"][..., 2] = 0.0                    # a channel that renders black everywhere
    for r in renders[1:]:
        r["irradiance"][..., 2] = 0.0
    estimates = [{m: rng.uniform(0, 1, (5, 7, c)).astype(np.float32) for m, c in
                  (("albedo", 3), ("irradiance", 3), ("roughness", 1))} for _ in range(3)]
    gains = anchor.anchor_gains(renders, estimates, hits, ("albedo", "roughness", "irradiance", "normal"))
    assert sorted(gains) == ["albedo", "irradiance"]          # roughness has no per-image scale; normal no estimate
    for m in gains:
        est = np.concatenate([e[m][h] for e, h in zip(estimates, hits)])
        ren = np.concatenate([r[m][h] for r, h in zip(renders, hits)])
        live = ren.max(axis=0) > 0
        assert_close(srgb_mean(gains[m] * ren)[live], srgb_mean(est)[live], rtol=1e-6)
        assert (np.abs(gains[m][live] - 1) > 0.05).all()        # the renders were darker: not trivially 1
    assert gains["irradiance"][2] == 1.0
    # the sRGB means taken a few pixels at a time (a capture's billions of pixels): the same gains
    monkeypatch.setattr(anchor, "GAIN_CHUNK", 7)
    chunked = anchor.anchor_gains(renders, estimates, hits, ("albedo", "irradiance"))
    for m in gains:
        assert_close(chunked[m], gains[m], rtol=1e-12)
    monkeypatch.undo()
    # a gain that clips: the mean is reached through the clipped values (the bright half saturates)
    ren = np.concatenate([np.full(50, 0.5), np.full(50, 0.05)])[:, None]
    est = np.full((100, 1), 0.9)
    g = anchor.anchor_gains([{"albedo": ren.repeat(3, -1)}], [{"albedo": est.repeat(3, -1)}],
                           [np.ones(100, bool)], ["albedo"])["albedo"]
    assert_close(srgb_mean(g * ren.repeat(3, -1)), srgb_mean(est.repeat(3, -1)), rtol=1e-6)
    assert (g > 2).all()
    # targets out of reach inside ANCHOR_GAIN_RANGE get the range's ends
    low, high = anchor.ANCHOR_GAIN_RANGE
    for value, target, end in ((1e-4, 0.999, high), (0.9, 1e-5, low)):
        g = anchor.anchor_gains([{"albedo": np.full((10, 10, 3), value, np.float32)}],
                                [{"albedo": np.full((10, 10, 3), target, np.float32)}], [np.ones((10, 10), bool)],
                                ["albedo"])["albedo"]
        assert_close(g, np.full(3, end), rtol=1e-6)


def test_anchored_texels_scale_the_colour_maps_in_linear_light_and_leave_the_rest(problem):
    """Renders of the anchored texture have the baseline's sRGB mean per channel (no texel clips here)."""
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export.anchor import anchor_to_baseline

    channels = MapChannels(("albedo", "roughness"))
    texels = np.random.default_rng(3).uniform(-0.9, -0.5, (problem.space.num_texels, 4)).astype(np.float32)
    prob = dataclasses.replace(problem, channels=channels)
    config = DistillConfig(scene="unused", out_dir="unused", maps=channels.maps, prior="views", anchor="estimates")
    ctx = evaluation_context(config, prob)
    baseline = per_view_baseline(config, prob, ctx.shapes)
    anchored, record = anchor_to_baseline(config, prob, texels, ctx, baseline)
    assert list(record["gains"]) == ["albedo"] and "target" in record["to"]
    assert (np.abs(np.asarray(record["gains"]["albedo"]) - 1) > 0.2).all()         # the texture was too dark
    np.testing.assert_array_equal(anchored[:, 3], texels[:, 3])                     # roughness untouched
    g = np.asarray(record["gains"]["albedo"], np.float32)
    assert_close((anchored[:, :3] + 1) / 2, g * (texels[:, :3] + 1) / 2, rtol=1e-4)  # file values x g
    from jaxdistill.evaluate.ground_truth import render_views

    hits = np.asarray(ctx.plan.hit).reshape(-1, ctx.plan.height, ctx.plan.width)
    renders = render_views(anchored, ctx.plan, ctx.cameras, channels)
    ours = srgb_mean(np.concatenate([r["albedo"][h] for r, h in zip(renders, hits)]))
    target = srgb_mean(np.concatenate([b["albedo"][h] for b, h in zip(baseline.views, hits)]))
    assert (np.abs(anchored[:, :3]) < 1).all()                                      # nothing clipped
    assert_close(ours, target, rtol=1e-3)
    for mode in ("none", "auto"):                           # auto: none with the views prior
        unchanged, none = anchor_to_baseline(dataclasses.replace(config, anchor=mode), prob, texels, ctx, baseline)
        assert none is None and unchanged is texels


def test_the_anchor_renders_only_the_maps_it_measures_and_they_are_the_full_renders_bit_for_bit(problem, monkeypatch):
    """The anchor renders the aligned maps (estimates) or the albedo (the photos' trace) alone: per
    channel the same values as rendering every map, so the same gains, in less time."""
    from jaxdistill.evaluate import ground_truth
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export import anchor as anchor_module

    channels = MapChannels(("albedo", "normal", "roughness", "irradiance"))
    texels = np.random.default_rng(5).uniform(-1.2, 1.2, (problem.space.num_texels, 10)).astype(np.float32)
    prob = dataclasses.replace(problem, channels=channels)
    config = DistillConfig(scene="unused", out_dir="unused", maps=channels.maps, prior="views", anchor="estimates")
    ctx = evaluation_context(config, prob)
    full = ground_truth.render_views(np.clip(texels, -1.0, 1.0), ctx.plan, ctx.cameras, channels)
    for maps, expected in ((anchor_module.ALIGNED_MAPS, ("albedo", "irradiance")), (("albedo",), ("albedo",))):
        alone = anchor_module._renders(prob, texels, ctx, maps)
        for one, every in zip(alone, full, strict=True):
            assert tuple(one) == expected
            for m in expected:
                np.testing.assert_array_equal(one[m], every[m])
    asked = []
    real = ground_truth.render_views
    monkeypatch.setattr(ground_truth, "render_views", lambda t, plan, cams, ch, **kw: asked.append(ch.maps) or
                        real(t, plan, cams, ch, **kw))
    baseline = per_view_baseline(config, prob, ctx.shapes)
    anchor_module.anchor_to_baseline(config, prob, texels, ctx, baseline)
    assert asked == [("albedo", "irradiance")]


def test_an_anchor_gain_at_the_end_of_its_range_is_reported(problem, caplog):
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export.anchor import anchor_to_baseline

    config = DistillConfig(scene="unused", out_dir="unused", maps=problem.channels.maps, prior="views",
                           anchor="estimates")
    ctx = evaluation_context(config, problem)
    baseline = per_view_baseline(config, problem, ctx.shapes)
    texels = np.full((problem.space.num_texels, 3), -0.9999, np.float32)      # file value 5e-5: far too dark
    with caplog.at_level("WARNING"):
        _, record = anchor_to_baseline(config, problem, texels, ctx, baseline)
    assert max(record["gains"]["albedo"]) == pytest.approx(anchor.ANCHOR_GAIN_RANGE[1], rel=1e-3)
    assert "reached the end of the gain range" in caplog.text and "albedo[0]" in caplog.text


def test_anchor_estimates_without_a_colour_map_says_so(problem, caplog):
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export.anchor import anchor_to_baseline

    prob = dataclasses.replace(problem, channels=MapChannels(("roughness",)))
    config = DistillConfig(scene="unused", out_dir="unused", maps=("roughness",), prior="views", anchor="estimates")
    ctx = evaluation_context(config, prob)
    baseline = per_view_baseline(config, prob, ctx.shapes)
    texels = np.zeros((prob.space.num_texels, 1), np.float32)
    with caplog.at_level("WARNING"):
        out, record = anchor_to_baseline(config, prob, texels, ctx, baseline)
    assert record is None and out is texels
    assert "nothing to anchor" in caplog.text and "albedo or irradiance" in caplog.text


def test_srgb_slope_is_x_times_the_encodings_derivative():
    from jaxdistill.io.images import linear_to_srgb, linear_to_srgb_and_slope

    x = np.concatenate([np.linspace(-0.1, 1.2, 2001), [0.0031308, 1.0]]).astype(np.float32)
    value, slope = linear_to_srgb_and_slope(x)
    assert_close(value, linear_to_srgb(x), rtol=1e-6)            # float32, to an ulp
    inside = (x > 1e-3) & (x < 0.98) & (np.abs(x - 0.0031308) > 1e-4)
    xd = x[inside].astype(np.float64)
    exact = np.where(xd <= 0.0031308, 12.92, 1.055 / 2.4 * xd ** (1 / 2.4 - 1)) * xd
    assert_close(slope[inside], exact, rtol=1e-5)
    assert (slope[(x <= 0) | (x >= 1)] == 0).all()


def test_anchor_traced_says_when_the_photos_show_too_little_of_the_light(problem, caplog):
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export.anchor import anchor_to_baseline

    # the tiny room's views circle at eye height: no photo shows its ceiling, so a quarter of every
    # point's hemisphere has no known radiance (the gain itself: tests/test_light_trace.py's furnace)
    config = DistillConfig(scene="unused", out_dir="unused", maps=problem.channels.maps, prior="views",
                           anchor="traced")
    ctx = evaluation_context(config, problem)
    baseline = per_view_baseline(config, problem, ctx.shapes)
    texels = np.full((problem.space.num_texels, 3), -0.6, np.float32)
    with caplog.at_level("WARNING"):
        out, record = anchor_to_baseline(config, problem, texels, ctx, baseline)
    assert record is None and out is texels
    assert "too few surface points have a known light" in caplog.text and "--anchor=estimates" in caplog.text


def test_anchor_auto_with_the_rgbx_prior_takes_the_photos_light_only_where_it_can_be_trusted(problem, caplog):
    from jaxdistill.evaluate.scoring import evaluation_context
    from jaxdistill.export.anchor import ESCAPED_WARNING, anchor_mode, anchor_to_photos, trace_trusted

    config = DistillConfig(scene="unused", out_dir="unused", maps=problem.channels.maps, prior="views")
    rgbx = dataclasses.replace(problem, rgbx_model=object())
    assert anchor_mode(config, problem) == "none" and anchor_mode(config, rgbx) == "photos"      # HDR photos
    ldr = dataclasses.replace(rgbx, scene=dataclasses.replace(rgbx.scene, views=tuple(
        dataclasses.replace(v, photo=v.photo.with_suffix(".png")) for v in rgbx.scene.views)))
    assert anchor_mode(config, ldr) == "estimates"                      # LDR: their lights are clipped
    assert trace_trusted({"escaped_unseen": ESCAPED_WARNING, "albedo_above_one": 0.1})
    assert not trace_trusted({"escaped_unseen": 0.01, "albedo_above_one": 0.0})
    assert not trace_trusted({"escaped_unseen": 0.0, "albedo_above_one": 0.11})
    # the tiny room's ceiling is in no photo: an untrusted trace hands over to the estimates
    ctx = evaluation_context(config, problem)
    texels = np.full((problem.space.num_texels, 3), -0.6, np.float32)
    with caplog.at_level("INFO"):
        assert anchor_to_photos(config, rgbx, texels, ctx, trusted_only=True) is None
    assert "--anchor=auto: the photos' traced light is not used (too few points with a known light)" in caplog.text


def test_a_trusted_trace_scales_the_albedo_by_its_gain(problem, monkeypatch):
    from jaxdistill.evaluate.scoring import evaluation_context, per_view_baseline
    from jaxdistill.export import anchor as anchor_lib

    # the gain's own estimator is tested against analytic light in tests/test_light_trace.py
    record = {"escaped_unseen": 0.0, "counted": 500, "points": 512}
    monkeypatch.setattr(anchor_lib, "traced_albedo_gain", lambda *a, **k: (np.array([2.0, 1.5, 0.5]), record))
    config = DistillConfig(scene="unused", out_dir="unused", maps=problem.channels.maps, prior="views", anchor="auto")
    rgbx = dataclasses.replace(problem, rgbx_model=object())
    ctx = evaluation_context(config, rgbx)
    baseline = per_view_baseline(config, problem, ctx.shapes)
    texels = np.full((problem.space.num_texels, 3), -0.6, np.float32)           # albedo 0.2
    out, done = anchor_lib.anchor_to_baseline(config, rgbx, texels, ctx, baseline)
    assert done["to"] == "the irradiance traced from the photos" and done["trace"] is record
    assert_close(np.asarray(done["gains"]["albedo"]), np.array([2.0, 1.5, 0.5]), rtol=1e-12)
    assert_close(out, np.broadcast_to(np.array([0.4, 0.3, 0.1]) * 2 - 1, out.shape), rtol=1e-6, floor=1e-6)
    assert done["trace"]["albedo_above_one"] == 0.0
    record["escaped_unseen"] = 0.01                                              # untrusted: the estimates anchor
    out, done = anchor_lib.anchor_to_baseline(config, rgbx, texels, ctx, baseline)
    assert done["to"] == baseline.source
    # a gain that makes albedo brighter than any surface (0.2 × 6 > 1): light the photos do not show
    record["escaped_unseen"] = 0.0
    monkeypatch.setattr(anchor_lib, "traced_albedo_gain", lambda *a, **k: (np.array([6.0, 1.0, 1.0]), record))
    out, done = anchor_lib.anchor_to_baseline(config, rgbx, texels, ctx, baseline)
    assert done["to"] == baseline.source and record["albedo_above_one"] == 1.0


def test_albedo_above_one_counts_the_texels_a_gain_pushes_past_white():
    from jaxdistill.export.anchor import albedo_above_one

    channels = MapChannels(("albedo", "roughness"))
    albedo = np.array([[0.1, 0.1, 0.1], [0.5, 0.2, 0.2], [0.2, 0.2, 0.6], [0.9, 0.9, 0.9]])
    texels = np.concatenate([albedo * 2 - 1, np.zeros((4, 1))], axis=1).astype(np.float32)
    assert albedo_above_one(texels, np.array([2.5, 1.0, 1.0]), channels) == 0.5     # 1.25 and 2.25 in red
    assert albedo_above_one(texels, np.array([1.0, 1.0, 1.0]), channels) == 0.0
    assert albedo_above_one(texels, np.array([1.0, 1.0, 2.0]), channels) == 0.5     # 1.2 and 1.8 in blue
