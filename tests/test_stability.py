"""Numerical stability on hard cases (docs/benchmarks.md §4): 16-bit floats, the ends of the noise
schedule, never-observed texels, degenerate geometry, huge textures, dropout extremes and
non-finite input files. Every test compares against an independent expectation (a NumPy
formula, analytic geometry, a brute-force count); cases an existing test already covers are
named in a comment instead of repeated.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from conftest import look_at_camera
from jaxdistill.engine import config as config_lib
from jaxdistill.io import images as imageio
from jaxdistill.scene import shapes as synthetic
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.step import StepSettings, init_state, make_optimizer, make_step
from jaxdistill.errors import InputError
from jaxdistill.models import scheduler as sch
from jaxdistill.engine.problem import build_problem
from jaxdistill.render import fragments as fr
from jaxdistill.render.gather_plan import build_gather_plans, build_texel_space
from jaxdistill.render.layout import TextureLayout
from jaxdistill.render.sampler import render
from jaxdistill.render.visibility import pixel_weights
from jaxdistill.scene.model import Mesh
from tiny_scene import write_tiny_scene
from tolerance import assert_close

ADAM_EPS = 1e-8          # optax.adamw's default eps


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    """The tiny box-room scene (4 views of 32x24, PNG targets, EXR photos)."""
    return write_tiny_scene(tmp_path_factory.mktemp("stability_scene"), views=4, gt=False)


@pytest.fixture(scope="module")
def views_problem(scene_path, tmp_path_factory):
    """The views prior rendered at 16x12: the texel space also holds the texels that only the
    evaluation renders at the photos' 32x24 read, which no training plan ever reads."""
    config = DistillConfig(scene=str(scene_path), out_dir="unused", maps=("albedo", "roughness"), prior="views",
                           render_size=16)
    return build_problem(config, cache_dir=tmp_path_factory.mktemp("cache_views"))


def with_gradient(optimizer: optax.GradientTransformation) -> optax.GradientTransformation:
    """`optimizer` behind a pass-through stage whose state is the last raw texel gradient, so a
    test reads the exact float32 gradient of a step in `state.opt_state[0]`."""
    capture = optax.GradientTransformation(init=jnp.zeros_like, update=lambda g, state, params=None: (g, g))
    return optax.chain(capture, optimizer)


def one_step(problem, settings, optimizer, texels, view_ids, seed=0):
    """(new state, metrics) of one jitted step from `texels`."""
    state = init_state(texels, optimizer, seed)
    step = jax.jit(make_step(problem.prior, settings, optimizer))
    new, metrics = step(state, problem.batch(np.asarray(view_ids)), problem.frozen)
    return new, jax.device_get(metrics)


def settings_for(problem, **kw) -> StepSettings:
    return StepSettings(channels=problem.channels, height=problem.height, width=problem.width, total_steps=1, **kw)


def adamw_first_step(texels, grad, lr, wd):
    """AdamW's first update in float64: bias-corrected m = g, v = g², so θ − lr (g / (|g| + eps) + wd θ)."""
    t, g = texels.astype(np.float64), grad.astype(np.float64)
    return t - lr * (g / (np.abs(g) + ADAM_EPS) + wd * t)


# ============================================================================ 1. bf16 networks, fp32 texels

MICRO_UNET = dict(layers_per_block=1, block_out_channels=(8,), norm_num_groups=4, attention_head_dim=(2,),
                  cross_attention_dim=16, down_block_types=("CrossAttnDownBlock2D",),
                  up_block_types=("CrossAttnUpBlock2D",))
MICRO_VAE = dict(layers_per_block=1, block_out_channels=(8,), norm_num_groups=4,
                 down_block_types=("DownEncoderBlock2D",), up_block_types=("UpDecoderBlock2D",))
MICRO_TEXT = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2, projection_dim=16)


@pytest.fixture(scope="module")
def bf16_problem(scene_path, tmp_path_factory):
    """The rgbx prior at --prior_dtype=bfloat16, from a one-block random RGB<->X folder in the real
    diffusers format (the tiny conftest model compiles ~3x slower; the dtype path is the same)."""
    pytest.importorskip("torch")
    from tiny_rgbx import TINY_TEXT, TINY_UNET, TINY_VAE, write_tiny_rgbx

    folder = write_tiny_rgbx(tmp_path_factory.mktemp("micro_rgbx") / "rgb-to-x", unet={**TINY_UNET, **MICRO_UNET},
                             vae={**TINY_VAE, **MICRO_VAE}, text={**TINY_TEXT, **MICRO_TEXT})
    config = DistillConfig(scene=str(scene_path), out_dir="unused", maps=("albedo",), prior="rgbx",
                           rgbx_dir=str(folder), prior_dtype="bfloat16")
    return build_problem(config, cache_dir=tmp_path_factory.mktemp("cache_rgbx"))


def test_a_1e4_update_is_not_swallowed_by_16_bit_floats():
    """Why texels stay float32: 0.5 + 1e-4 is a new float32, but rounds back to 0.5 in float16
    (spacing 2^-11 at 0.5) and bfloat16 (spacing 2^-8)."""
    half, step = 0.5, 1e-4
    assert np.float32(half) + np.float32(step) != np.float32(half)
    assert np.float32(half) + np.float32(step) - np.float32(half) == pytest.approx(step, rel=1e-3)
    for dtype in (np.float16, jnp.bfloat16):
        assert np.asarray(half + step, dtype) == np.asarray(half, dtype), dtype
        assert np.asarray(half, dtype) + np.asarray(step, dtype) == np.asarray(half, dtype), dtype


def test_bf16_networks_move_fp32_texels_by_1e4(bf16_problem):
    """One AdamW step of lr 1e-4 from texels at 0.5, the bf16 prior at t = T − 1 (ᾱ = 0 with the
    demo's zero-terminal-SNR schedule): texels, gradient and optimizer state stay float32 and every
    observed texel moves by AdamW's NumPy update, |Δ| ≈ 1e-4, although in bfloat16 the new texels
    would round back to 0.5."""
    problem = bf16_problem
    assert problem.prior.networks.unet.dtype == jnp.bfloat16 and problem.prior.networks.vae.dtype == jnp.bfloat16
    assert float(sch.alphas_cumprod(problem.prior.scheduler)[999]) == 0.0
    lr = 1e-4
    optimizer = with_gradient(make_optimizer(lr, 0.0))
    texels = np.full((problem.space.num_texels, problem.channels.num_channels), 0.5, np.float32)
    state, metrics = one_step(problem, settings_for(problem, t_min=1.0, t_max=1.0), optimizer, texels,
                              np.arange(problem.num_views))
    assert metrics["finite"] == 1 and np.isfinite(metrics["loss"]) and metrics["t_mean"] == 999
    grad = np.asarray(state.opt_state[0])
    new = np.asarray(state.texels)
    assert new.dtype == np.float32 and grad.dtype == np.float32
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(state.opt_state[1]) if leaf.ndim)
    assert_close(new, adamw_first_step(texels, grad, lr, 0.0), rtol=1e-6, floor=1e-7)
    moved = np.abs(new - texels)
    observed = problem.counts > 0
    assert observed.all()                                       # render size = photo size: all texels are read
    assert (moved[observed] > 0.99 * lr).mean() > 0.99 and moved.max() <= lr * (1 + 1e-3)
    assert np.all(np.asarray(new, jnp.bfloat16) == np.asarray(texels, jnp.bfloat16))   # bf16 would lose the step


# ============================================================================ 2. 16-bit texels are refused


@pytest.mark.parametrize("dtype", [np.float16, jnp.bfloat16], ids=["float16", "bfloat16"])
def test_16_bit_texels_are_refused_with_a_clear_message(dtype):
    """init_state, the boundary where texels enter the step, refuses 16-bit floats (numpy or jax)
    naming the dtype and the reason, instead of silently casting them."""
    optimizer = make_optimizer(0.01, 0.0)
    for texels in (np.zeros((4, 3), dtype), jnp.zeros((4, 3), dtype)):
        with pytest.raises(ValueError, match=rf"texels are {np.dtype(dtype).name}, but texels must be float32: "
                                             r"AdamW updates of ~1e-4 vanish in 16-bit floats"):
            init_state(texels, optimizer, 0)


def test_float32_texels_are_accepted_and_wider_inputs_cast(views_problem):
    """Every caller's texels are float32 (problem.initial_texels), and float64 is still cast."""
    optimizer = make_optimizer(0.01, 0.0)
    assert views_problem.initial_texels().dtype == np.float32
    assert init_state(views_problem.initial_texels(), optimizer, 0).texels.dtype == jnp.float32
    assert init_state(np.zeros((4, 3), np.float64), optimizer, 0).texels.dtype == jnp.float32


# ============================================================================ 3. t at the ends of the range


def numpy_alphas_cumprod(zero_snr: bool) -> np.ndarray:
    """ᾱ_t in float64 for RGB<->X's scaled_linear β 0.00085–0.012, T = 1000, optionally rescaled
    to zero terminal SNR (Lin et al. 2024, Alg. 1: shift sqrt(ᾱ) to end at 0, keep sqrt(ᾱ_0))."""
    betas = np.linspace(0.00085 ** 0.5, 0.012 ** 0.5, 1000) ** 2
    alpha_bar = np.cumprod(1.0 - betas)
    if zero_snr:
        root = np.sqrt(alpha_bar)
        root = (root - root[-1]) * root[0] / (root[0] - root[-1])
        alpha_bar = root ** 2
    return alpha_bar


# Finiteness at ᾱ = 0 and ᾱ = 1 for every prediction type in float32 is tests/test_scheduler.py::
# test_zero_snr_first_step_finite; here: the values at the schedule's ends, and 16-bit inputs.
@pytest.mark.parametrize("zero_snr", [False, True], ids=["plain", "zero-snr"])
@pytest.mark.parametrize("t", [0, 999])
def test_x0_at_the_ends_of_the_schedule_matches_numpy(zero_snr, t):
    """x̂0 at t = 0 and t = T − 1: v-prediction sqrt(ᾱ) x − sqrt(1 − ᾱ) v̂ and epsilon
    (x − sqrt(1 − ᾱ) ε̂) / sqrt(ᾱ) as in NumPy; at ᾱ = 0 (zero SNR, t = T − 1) the epsilon
    division is guarded: finite, (x − ε̂) / sqrt(ALPHA_BAR_FLOOR)."""
    config = sch.SchedulerConfig(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012,
                                 rescale_betas_zero_snr=zero_snr)
    alpha = float(sch.alphas_cumprod(config)[t])
    want = numpy_alphas_cumprod(zero_snr)[t]
    assert alpha == pytest.approx(want, rel=1e-5, abs=1e-9)
    assert (want == 0.0) == (zero_snr and t == 999) and (alpha == 0.0) == (want == 0.0)
    rng = np.random.default_rng(t + zero_snr)
    x, pred = rng.standard_normal((2, 2, 4, 3, 4))
    a = np.float64(alpha)
    v_x0 = np.asarray(sch.x0_from_prediction(jnp.asarray(pred, jnp.float32), jnp.asarray(x, jnp.float32), alpha,
                                             "v_prediction"))
    np.testing.assert_allclose(v_x0, np.sqrt(a) * x - np.sqrt(1 - a) * pred, rtol=1e-5, atol=1e-5)
    eps_x0 = np.asarray(sch.x0_from_prediction(jnp.asarray(pred, jnp.float32), jnp.asarray(x, jnp.float32), alpha,
                                               "epsilon"))
    assert np.isfinite(eps_x0).all()
    denominator = np.sqrt(max(a, sch.ALPHA_BAR_FLOOR))                 # = sqrt(a) wherever a > 0
    assert (denominator == np.sqrt(a)) == (a > 0)
    # x̂0 · denominator against the numerator: x̂0 reaches 1e6 at ᾱ = 0, where float32 keeps ~7 digits
    np.testing.assert_allclose(eps_x0 * denominator, x - np.sqrt(1 - a) * pred, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kind", sch.PREDICTION_TYPES)
def test_x0_from_bf16_network_outputs_at_alpha_bar_0_and_1_is_finite(kind):
    """A bf16 prior's outputs at ᾱ = 0 and ᾱ = 1 give finite float32 x̂0 and ε̂ (the floored
    division is done in float32, not in the network's 16-bit dtype)."""
    rng = np.random.default_rng(0)
    x, pred = (jnp.asarray(a, jnp.bfloat16) for a in rng.standard_normal((2, 2, 4, 4)))
    for alpha_bar in (0.0, 1.0):
        x0 = sch.x0_from_prediction(pred, x, alpha_bar, kind)
        eps = sch.eps_from_prediction(pred, x, alpha_bar, kind)
        assert jnp.isfinite(x0).all() and jnp.isfinite(eps).all(), (kind, alpha_bar)


# ============================================================================ 4. never-observed texels, visibility


@pytest.mark.parametrize("wd", [0.0, 0.05])
def test_unobserved_texels_get_zero_gradient_and_only_weight_decay(views_problem, wd):
    """A step on views {0, 1}: texels no tap of theirs reads (an independent set from the batch's
    index/weight arrays) get a gradient of exactly 0. Without weight decay they keep their value
    bit for bit; with it, AdamW's decoupled decay still shrinks them, θ (1 − lr·wd), as it does
    every parameter (the truth of the code; export fills never-observed texels anyway). That
    includes the texels that no view's training plan reads at all (count 0: only the
    evaluation renders at the photos' size read them)."""
    problem = views_problem
    never = problem.counts == 0
    assert never.sum() > 10
    lr, ids = 0.01, np.array([0, 1])
    rng = np.random.default_rng(1)
    texels = rng.uniform(-0.8, 0.8, (problem.space.num_texels, problem.channels.num_channels)).astype(np.float32)
    state, metrics = one_step(problem, settings_for(problem), with_gradient(make_optimizer(lr, wd)), texels, ids)
    batch = problem.batch(ids)
    read = np.zeros(problem.space.num_texels, bool)
    read[np.unique(batch["index"][batch["weight"] > 0])] = True
    assert read.any() and (~read).sum() > never.sum() and not (read & never).any()
    grad = np.asarray(state.opt_state[0])
    new = np.asarray(state.texels)
    assert metrics["finite"] == 1
    assert np.all(grad[~read] == 0.0) and np.all(np.abs(grad[read]).max(axis=1) > 0)
    if wd == 0.0:
        np.testing.assert_array_equal(new[~read], texels[~read])
    else:
        assert_close(new[~read], texels[~read] * (1 - lr * wd), rtol=1e-6, floor=1e-7)
        assert np.all(new[~read] != texels[~read])
    assert_close(new, adamw_first_step(texels, grad, lr, wd), rtol=1e-6, floor=2e-7)


# W = clip(1 / (2 clip(V, 1, 6)), 0.1, 10) at V = 0, 1, 6, 7, 10 000 and 1e30 is
# tests/test_visibility.py::test_weight_formula_and_extremes; here: the per-pixel lookup through a plan.
def test_pixel_weights_at_extreme_view_counts(views_problem):
    """Through the views' own gather plans, counts of 1 and 10 000 everywhere give hit pixels
    W = 0.5 and W = 0.1 (from 1/12, clipped) and missed pixels 0: finite, nothing divides by V."""
    from jaxdistill.render.gather_plan import GatherPlan

    problem = views_problem
    plan = GatherPlan(index=problem.plan_index, weight=problem.plan_weight, hit=problem.plan_hit,
                      chain=problem.frozen["chain"], height=problem.height, width=problem.width)
    hit = problem.plan_hit.reshape(problem.num_views, problem.height, problem.width)
    for count, expected in ((1, 0.5), (10_000, 0.1)):
        counts = np.full(problem.space.num_texels, count, np.int32)
        weights = np.asarray(pixel_weights(plan, counts))
        assert np.isfinite(weights).all()
        np.testing.assert_allclose(weights[hit], expected, rtol=1e-6)
        assert np.all(weights[~hit] == 0.0)


# ============================================================================ 5. degenerate geometry


def quarter_fan(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of the unit square [0, 1]² (x, z at y = 0) cut into n slivers fanning from
    the corner (0, 0): triangle k spans the angles [k, k + 1]·(π/2)/n (n even, so (1, 1) is a vertex)."""
    theta = np.linspace(0.0, np.pi / 2, n + 1)
    theta[n // 2] = np.pi / 4
    with np.errstate(divide="ignore"):
        rim = np.where(theta[:, None] <= np.pi / 4, np.stack([np.ones_like(theta), np.tan(theta)], 1),
                       np.stack([1.0 / np.tan(theta), np.ones_like(theta)], 1))
    xz = np.concatenate([[[0.0, 0.0]], np.clip(rim, 0.0, 1.0)])
    vertices = np.stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]], axis=1)
    k = np.arange(n)
    return vertices, np.stack([np.zeros(n, np.int64), k + 1, k + 2], axis=1)


def square_mesh(vertices, faces, extra_faces=()) -> Mesh:
    """A one-object mesh on the unit square with u = x, v = 1 − z (the same affine UV map for any
    triangulation), plus `extra_faces` (e.g. zero-area ones)."""
    faces = np.concatenate([faces, np.asarray(extra_faces, np.int64).reshape(-1, 3)])
    uv = np.stack([vertices[:, 0], 1.0 - vertices[:, 2]], axis=1)
    return Mesh(vertices=vertices, faces=faces, uv=uv[faces], face_object=np.zeros(len(faces), np.int32),
                object_names=("square",))


def ray_plane_hits(camera, height=0.0):
    """(t (H, W), hit point (H, W, 3)) of every pixel ray with the plane y = height, analytically."""
    d = camera.pixel_directions().reshape(camera.height, camera.width, 3)
    o = camera.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (height - o[1]) / d[..., 1]
    return t, o + t[..., None] * d


@jax.jit
def render_and_gradient(texels, plan, cotangent):
    """(render(texels, plan), its vjp with `cotangent`): one compiled program, not op by op."""
    image, pullback = jax.vjp(lambda t: render(t, plan), texels)
    return image, pullback(cotangent)[0]


def check_plans_and_render(frags, layout_sizes, object_page, atol_sum=1e-5):
    """Fragment buffers finite; bilinear and trilinear plans with finite weights summing to 1 on
    hit pixels (0 on misses); render and its gradient finite. Returns the bilinear renders."""
    for frag in frags:
        hit = frag.hit
        assert np.isfinite(frag.barycentric).all() and np.isfinite(frag.uv).all() and np.isfinite(frag.uv_grad).all()
        assert np.isfinite(frag.depth[hit]).all() and np.all(np.isinf(frag.depth[~hit]))
        assert np.all((frag.uv >= 0) & (frag.uv <= 1))
    images = None
    for sampler, tile in (("bilinear", 1), ("trilinear", 16)):
        layout = TextureLayout(page_sizes=layout_sizes, object_page=object_page, mipmaps=sampler == "trilinear",
                               tile_size=tile)
        space = build_texel_space(frags, layout, sampler)
        plan = build_gather_plans(frags, space, sampler)
        weight, hit = np.asarray(plan.weight), np.asarray(plan.hit)
        assert np.isfinite(weight).all() and weight.min() >= 0
        np.testing.assert_allclose(weight.sum(-1)[hit], 1.0, atol=atol_sum)
        assert np.all(weight.sum(-1)[~hit] == 0)
        rng = np.random.default_rng(0)
        texels = rng.uniform(-1, 1, (space.num_texels, 3)).astype(np.float32)
        cotangent = rng.standard_normal((len(frags), *frags[0].shape, 3)).astype(np.float32)
        image, grad = render_and_gradient(texels, plan, cotangent)
        assert np.isfinite(np.asarray(image)).all() and np.isfinite(np.asarray(grad)).all()
        if sampler == "bilinear":
            images = np.asarray(image)
    return images


def test_sliver_and_zero_area_triangles_give_the_planes_uvs_and_derivatives():
    """The unit square as 20 000 slivers (aspect ratio up to ~13 000) plus zero-area triangles
    (repeated and collinear vertices) renders like the same square as two triangles: triangle ids
    follow the analytic fan angle, UVs the analytic ray-plane hit, UV derivatives the two-triangle
    mesh's (the UV map is the same affine function), plans and renders agree. Float32 Embree
    barycentrics alone are off by 5e-4 in UV here (eps32 x the aspect ratio). Zero-area triangles
    are never hit (tests/test_fragments.py checks them alone)."""
    n = 20_000
    vertices, faces = quarter_fan(n)
    vertices = np.concatenate([vertices, 0.5 * vertices[n // 3][None]])   # halfway along the fan edge n // 3
    # zero area: repeated vertices, collinear on the rim x = 1, collinear across the square's interior
    zero_area = [[1, 1, 2], [0, n // 4, n // 4], [1, 2, 3], [0, n + 2, n // 3]]
    slivers = square_mesh(vertices, faces, zero_area)
    corners = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    quad = square_mesh(corners, np.array([[0, 1, 2], [0, 2, 3]]))
    camera = look_at_camera((0.45, 1.1, 0.35), (0.5, 0.0, 0.5), width=64, height=48, fx=45.0)
    (a,) = fr.compute_fragments(slivers, [camera], cache_dir=False, progress=False)
    (b,) = fr.compute_fragments(quad, [camera], cache_dir=False, progress=False)
    t, point = ray_plane_hits(camera)
    inside = (t > 0) & (point[..., 0] >= 0) & (point[..., 0] <= 1) & (point[..., 2] >= 0) & (point[..., 2] <= 1)
    both = a.hit & b.hit
    assert (a.hit == inside).mean() > 0.999 and (a.hit == b.hit).mean() > 0.999 and both.sum() > 1000
    assert not np.isin(a.triangle, np.arange(n, n + len(zero_area))).any()
    angle = np.arctan2(point[..., 2], point[..., 0])
    expected_id = np.clip(np.floor(angle / (np.pi / 2 / n)), 0, n - 1)
    assert (a.triangle[both] == expected_id[both]).mean() > 0.99
    assert np.abs(a.triangle[both] - expected_id[both]).max() <= 1
    analytic_uv = np.stack([point[..., 0], 1.0 - point[..., 2]], -1)
    np.testing.assert_allclose(a.uv[both], analytic_uv[both], atol=2e-6)
    np.testing.assert_allclose(a.uv[both], b.uv[both], atol=2e-6)
    np.testing.assert_allclose(a.uv_grad[both], b.uv_grad[both], rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(a.depth[both], b.depth[both], rtol=1e-5)
    images_a = check_plans_and_render([a], (64,), (0,))
    images_b = check_plans_and_render([b], (64,), (0,))
    np.testing.assert_allclose(images_a[0][both], images_b[0][both], atol=1e-3)


@pytest.mark.parametrize("height", [1e-3, 1e-4])
def test_grazing_view_along_a_floor(height):
    """A camera `height` above the 20 m floor of a 7 m high hall, looking at the horizon, its rows
    0.4·height/16 rad apart (fy = 40 / height): rays meet the floor at 5e-5 to 4e-4 rad (1 mm)
    and 5e-6 to 4e-5 rad (0.1 mm). The floor is not at the centre of the mesh's bounding box (where
    float32 would be exact), yet UVs and depth match the analytic ray-plane hit (float32 Embree
    alone is off by 1e-4 and 1.3e-3 in UV here); every buffer, plan weight, render and gradient is
    finite, and the trilinear plan reads coarse mip levels."""
    size, half = 20.0, 10.0
    mesh = synthetic.mesh_from_patches([("floor", (-half, 0.0, half), (size, 0, 0), (0, 0, -size), 4),
                                        ("ceiling", (-half, 7.0, half), (size, 0, 0), (0, 0, -size), 1)])
    camera = look_at_camera((0.0, height, 9.9), (0.0, height, -10.1), width=48, height=32, fx=40.0,
                            fy=40.0 / height)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
    t, point = ray_plane_hits(camera)
    inside = (t > 0) & (np.abs(point[..., 0]) <= half) & (np.abs(point[..., 2]) <= half)
    floor = frag.object_id == 0
    assert inside.sum() > 400 and (floor == inside).mean() > 0.99
    both = floor & inside
    analytic_uv = np.stack([(point[..., 0] + half) / size, (half - point[..., 2]) / size], -1)
    np.testing.assert_allclose(frag.uv[both], analytic_uv[both], atol=2e-6)
    depth = t * (camera.pixel_directions().reshape(*t.shape, 3) @ camera.c2w[:3, 2])
    np.testing.assert_allclose(frag.depth[both], depth[both], rtol=1e-5)
    check_plans_and_render([frag], (256, 16), (0, 1))
    layout = TextureLayout(page_sizes=(256, 16), object_page=(0, 1), mipmaps=True, tile_size=16)
    space = build_texel_space([frag], layout, "trilinear")
    plan = build_gather_plans([frag], space, "trilinear")
    reads = np.asarray(plan.index)[0][both.ravel()][np.asarray(plan.weight)[0][both.ravel()] > 0]
    assert (reads >= space.num_texels).mean() > 0.5            # most floor taps read mip levels above level 0


def test_camera_inside_a_closed_millimetre_box():
    """A camera inside a closed 2 mm box that stands in a 4 m room: every ray hits the box (never
    the room behind it), on the analytic face, at the analytic exit distance to 1e-6 (float32
    Embree alone gives 3e-5 here: the box is 1 m from the centre of the mesh's bounding box)."""
    eye = np.array([1.0, 1.2, 0.8])
    half = 1e-3
    lo, hi = eye - half * np.array([1.0, 0.7, 1.3]), eye + half * np.array([1.2, 1.0, 0.9])
    patches = synthetic.box_patches("room", (0, 0, 0), (4.0, 2.5, 3.0), 1) + synthetic.box_patches("box", lo, hi, 1)
    mesh = synthetic.mesh_from_patches(patches)
    camera = look_at_camera(eye, (3.5, 0.7, 2.6), width=40, height=30, fx=18.0)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
    assert frag.hit.all() and frag.object_id.min() >= 6          # objects 6..11 are the box's faces
    d = camera.pixel_directions()
    with np.errstate(divide="ignore"):
        t_exit = np.where(d > 0, (hi - eye) / d, (lo - eye) / d)
    axis = np.argmin(t_exit, axis=1)
    positive = np.take_along_axis(d, axis[:, None], 1)[:, 0] > 0
    expected = 6 + np.select([(axis == 1) & ~positive, (axis == 1) & positive, (axis == 2) & ~positive,
                              (axis == 2) & positive, (axis == 0) & ~positive], [0, 1, 2, 3, 4], 5)
    assert (expected.reshape(frag.shape) == frag.object_id).mean() > 0.98
    np.testing.assert_allclose(frag.depth.ravel(), np.min(t_exit, 1) * (d @ camera.c2w[:3, 2]), rtol=1e-6)
    check_plans_and_render([frag], (64,) * 12, tuple(range(12)))


# Triangle ids, UVs and depth of a plane at 1e-3 and 1e3 are tests/test_fragments.py::
# test_scale_invariance_mm_and_km; here: a closed room, barycentrics, UV derivatives and plans.
@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_room_in_millimetres_and_kilometres_gives_the_same_fragments_and_plans(scale):
    """The furnished room seen from inside, scaled by 1e-3 and 1e3 (camera too): same triangle
    ids, barycentrics and UVs; d(uv)/d(pixel) is scale-free, so UV derivatives are equal; depth
    scales by the factor; the trilinear gather plans (which use the derivatives) are equal."""
    mesh = synthetic.box_room((4.0, 2.5, 3.0), subdivisions=2, furniture=True)
    cameras = [look_at_camera((1.0, 1.4, 0.7), (3.5, 0.4, 2.6), 40, 30, fx=22.0),
               look_at_camera((3.2, 1.0, 2.5), (0.5, 0.9, 0.4), 40, 30, fx=30.0)]
    scaled_mesh = Mesh(vertices=mesh.vertices * scale, faces=mesh.faces, uv=mesh.uv, face_object=mesh.face_object,
                       object_names=mesh.object_names)
    scaled_cameras = []
    for cam in cameras:
        c2w = cam.c2w.copy()
        c2w[:3, 3] *= scale
        scaled_cameras.append(type(cam)(K=cam.K, c2w=c2w, width=cam.width, height=cam.height))
    unit = fr.compute_fragments(mesh, cameras, cache_dir=False, progress=False)
    scaled = fr.compute_fragments(scaled_mesh, scaled_cameras, cache_dir=False, progress=False)
    for a, b in zip(unit, scaled):
        same = a.triangle == b.triangle
        assert same.mean() > 0.999 and a.hit.all() and b.hit.all()
        np.testing.assert_allclose(a.barycentric[same], b.barycentric[same], atol=1e-6)
        np.testing.assert_allclose(a.uv[same], b.uv[same], atol=1e-6)
        np.testing.assert_allclose(a.uv_grad[same], b.uv_grad[same], rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(a.depth * scale, b.depth, rtol=1e-5)
    pages = (32,) * len(mesh.object_names)
    layout = TextureLayout(page_sizes=pages, object_page=tuple(range(len(pages))), mipmaps=True, tile_size=4)
    plans = [build_gather_plans(f, build_texel_space(f, layout, "trilinear"), "trilinear") for f in (unit, scaled)]
    same = np.stack([a.triangle == b.triangle for a, b in zip(unit, scaled)]).reshape(len(cameras), -1)
    np.testing.assert_array_equal(np.asarray(plans[0].index)[same], np.asarray(plans[1].index)[same])
    np.testing.assert_allclose(np.asarray(plans[0].weight)[same], np.asarray(plans[1].weight)[same], atol=1e-4)
    check_plans_and_render(scaled, pages, tuple(range(len(pages))))


# ============================================================================ 6. very large textures


def test_8192_pages_allocate_only_the_tiles_views_read():
    """Six 8192² pages (2.4 GB as dense float32 RGB), two close-ups 25–30 cm from two walls: the
    compact texel space holds exactly the 16 x 16 tiles that some bilinear tap reads (counted
    here from the fragments' UVs), at most 256 x 4 x the hit pixels, under 0.1 % of the pages.
    Trilinear taps (footprints of <= 16 texels here: only in-tile mip levels) stay within
    256 x 8 x the hit pixels. Counts only. (Tile 1, the bilinear default, is as compact in
    parameters; its tile grids are then held as sorted keys, tests/test_sampler.py.)"""
    mesh = synthetic.box_room((4.0, 2.5, 3.0), subdivisions=1)
    cameras = [look_at_camera((2.0, 1.2, 2.75), (2.0, 1.1, 3.0), 32, 24, fx=80.0),
               look_at_camera((0.3, 1.0, 1.0), (0.0, 0.95, 1.1), 32, 24, fx=80.0)]
    frags = fr.compute_fragments(mesh, cameras, cache_dir=False, progress=False)
    size, tile = 8192, 16
    num_pages = len(mesh.object_names)
    full = num_pages * size * size
    hits = sum(int(f.hit.sum()) for f in frags)
    tiles = set()
    for frag in frags:      # bilinear taps: 2 x 2 texels around u S − 0.5, (1 − v) S − 0.5, clamped
        page = frag.object_id[frag.hit]
        uv = frag.uv[frag.hit].astype(np.float64)
        x, y = uv[:, 0] * size - 0.5, (1.0 - uv[:, 1]) * size - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        for dx, wx in ((0, 1 - (x - x0)), (1, x - x0)):
            for dy, wy in ((0, 1 - (y - y0)), (1, y - y0)):
                used = wx * wy > 0
                col = np.clip(x0 + dx, 0, size - 1).astype(np.int64)[used]
                row = np.clip(y0 + dy, 0, size - 1).astype(np.int64)[used]
                tiles |= set(zip(page[used].tolist(), (row // tile).tolist(), (col // tile).tolist()))
    for sampler, taps in (("bilinear", 4), ("trilinear", 8)):
        layout = TextureLayout(page_sizes=(size,) * num_pages, object_page=tuple(range(num_pages)),
                               mipmaps=sampler == "trilinear", tile_size=tile)
        space = build_texel_space(frags, layout, sampler)
        assert 0 < space.num_texels <= tile * tile * taps * hits and space.num_texels < 1e-3 * full
        plan = build_gather_plans(frags, space, sampler)
        reads = np.asarray(plan.index)[np.asarray(plan.weight) > 0]
        if sampler == "bilinear":
            assert space.num_texels == len(tiles) * tile * tile
            assert set(zip(space.tile_page.tolist(), space.tile_row.tolist(), space.tile_col.tolist())) == tiles
            assert reads.max() < space.num_texels
        else:
            assert reads.max() < space.level_offset(space.in_tile_levels)      # no coarse entry is read


# ============================================================================ 7. p_keep 0 and 1


# --p_keep=0 named in the flag errors is tests/test_main.py::test_bad_flags_are_named_before_any_compute;
# p_keep = 1 against the NumPy loss and AdamW is tests/test_distill.py::test_one_step_matches_numpy_...
def test_p_keep_bounds_in_the_config():
    """validate() refuses 0 with the flag and the allowed range in the message, and accepts 1."""
    with pytest.raises(InputError, match=r"--p_keep: must be in \(0, 1\], got 0.0"):
        config_lib.validate(DistillConfig(scene="s", out_dir="o", p_keep=0.0))
    assert config_lib.validate(DistillConfig(scene="s", out_dir="o", p_keep=1.0)).p_keep == 1.0


def test_p_keep_0_step_is_finite_and_changes_nothing(views_problem):
    """The step itself with p_keep = 0 drops every pixel: a finite loss of exactly 0, a zero
    gradient and (no weight decay) texels unchanged bit for bit: nothing divides by the kept count."""
    problem = views_problem
    texels = np.random.default_rng(2).uniform(-0.8, 0.8, (problem.space.num_texels, 3)).astype(np.float32)
    state, metrics = one_step(problem, settings_for(problem, p_keep=0.0), make_optimizer(0.01, 0.0), texels,
                              np.arange(problem.num_views))
    assert metrics["finite"] == 1 and metrics["loss"] == 0.0 and metrics["grad_norm"] == 0.0
    np.testing.assert_array_equal(np.asarray(state.texels), texels)
    assert int(state.step) == 1


def test_p_keep_just_below_1_runs_dropout_and_equals_no_dropout(views_problem):
    """p_keep = 1 − 1e-6 takes the dropout branch (p_keep < 1) yet keeps every pixel here: loss and
    texels equal the no-dropout step's (p_keep = 1), so the kept loss is never rescaled by 1/p_keep."""
    problem = views_problem
    texels = np.random.default_rng(3).uniform(-0.8, 0.8, (problem.space.num_texels, 3)).astype(np.float32)
    ids = np.arange(problem.num_views)
    optimizer = make_optimizer(0.01, 0.0)
    full, m_full = one_step(problem, settings_for(problem, p_keep=1.0), optimizer, texels, ids)
    kept, m_kept = one_step(problem, settings_for(problem, p_keep=1.0 - 1e-6), optimizer, texels, ids)
    assert m_full["loss"] > 0 and m_kept["loss"] == pytest.approx(float(m_full["loss"]), rel=1e-6)
    assert_close(np.asarray(kept.texels), np.asarray(full.texels), rtol=1e-6, floor=1e-7)


# ============================================================================ 8. NaN / inf in input images


# A NaN pixel in an EXR photo reported by read_scene is tests/test_scene.py::test_nan_photo_and_missing_fields;
# here: the run's entry point (build_problem) for a photo and for a target image.
@pytest.mark.parametrize("field,bad", [("photo", np.nan), ("targets.albedo", np.inf)])
def test_non_finite_exr_input_is_named_before_any_compute(tmp_path, field, bad):
    """build_problem refuses an EXR photo with NaN pixels, and an EXR target (which read_target
    would read for the views prior) with inf pixels, with an InputError naming scene.json, the
    view's field, the image file and the first bad pixel."""
    scene = write_tiny_scene(tmp_path / "scene", views=2, gt=False)
    image = tmp_path / "scene" / "bad" / "v1.exr"
    pixels = np.full((24, 32, 3), 0.5, np.float32)
    pixels[3, 11, 0] = bad
    imageio.write_image(image, pixels)
    doc = json.loads(scene.read_text())
    if field == "photo":
        doc["views"][1]["photo"] = "bad/v1.exr"
    else:
        doc["views"][1]["targets"]["albedo"] = "bad/v1.exr"
    scene.write_text(json.dumps(doc))
    config = DistillConfig(scene=str(scene), out_dir="unused", maps=("albedo",), prior="views")
    with pytest.raises(InputError) as err:
        build_problem(config, cache_dir=tmp_path / "cache")
    assert [(f, p) for f, p, _ in err.value.problems] == [(str(scene), f"views[1].{field}")]
    assert f"{image} has 1 NaN/inf pixels (first at row 3, column 11)" in str(err.value)
