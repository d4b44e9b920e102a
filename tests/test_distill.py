"""The distillation step against a NumPy reference, its randomness, and what it differentiates."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.step import (StepSettings, TraceCounter, data_mesh, init_state, initial_reused, jit_step,
                                make_optimizer, make_step, sample_timesteps, t_weights, upper_t)
from jaxdistill.scene.maps import MapChannels
from jaxdistill.engine.problem import build_problem
from tiny_scene import write_tiny_scene
from tolerance import assert_close

MAPS = ("albedo", "normal", "roughness")


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return write_tiny_scene(tmp_path_factory.mktemp("tiny_scene"))


@pytest.fixture(scope="module")
def problem(tiny_scene, tmp_path_factory):
    config = DistillConfig(scene=str(tiny_scene), out_dir="unused", maps=MAPS, prior="views")
    return build_problem(config, cache_dir=tmp_path_factory.mktemp("cache"))


def settings_for(problem, **kw):
    return StepSettings(channels=problem.channels, height=problem.height, width=problem.width, total_steps=10, **kw)


def run_steps(problem, settings, optimizer, view_ids_per_step, seed=0, texels=None):
    state = init_state(problem.initial_texels() if texels is None else texels, optimizer, seed)
    step = jax.jit(make_step(problem.prior, settings, optimizer))
    metrics = []
    for ids in view_ids_per_step:
        state, m = step(state, problem.batch(ids), problem.frozen)
        metrics.append(jax.device_get(m))
    return state, metrics


def numpy_render(problem, texels, ids):
    """(B, P, C) float64 renders of the views `ids`, normals rotated into camera space."""
    batch = problem.batch(ids)
    index, weight = batch["index"], batch["weight"].astype(np.float64)
    images = np.einsum("bpt,bptc->bpc", weight, texels.astype(np.float64)[index])          # (B, P, C)
    rot = batch["normal_rotation"].astype(np.float64)
    normal = problem.channels.slice("normal")
    images[..., normal] = np.einsum("bpi,bij->bpj", images[..., normal], rot)
    return images


def numpy_loss_and_grad(problem, texels, ids, target=None):
    """Image-space loss (1/B) Σ W Σ_c (render − target)² and its texel gradient, in float64 NumPy
    (target: (B, P, C) model-space images, default the views prior's targets)."""
    batch = problem.batch(ids)
    index, weight = batch["index"], batch["weight"].astype(np.float64)
    images = numpy_render(problem, texels, ids)
    rot = batch["normal_rotation"].astype(np.float64)
    normal = problem.channels.slice("normal")
    if target is None:
        target = batch["prior"]["target"].reshape(images.shape).astype(np.float64)
    w = batch["pixel_weight"].reshape(images.shape[:2]).astype(np.float64)
    b = len(ids)
    loss = np.sum(w[..., None] * (images - target) ** 2) / b
    g_img = 2.0 * w[..., None] * (images - target) / b
    g_img[..., normal] = np.einsum("bpj,bij->bpi", g_img[..., normal], rot)                  # back to world space
    grad = np.zeros(texels.shape, np.float64)
    np.add.at(grad, index.reshape(-1), (weight[..., None] * g_img[:, :, None, :]).reshape(-1, texels.shape[1]))
    return loss, grad


def test_one_step_matches_numpy_render_loss_gradient_and_adamw(problem):
    rng = np.random.default_rng(0)
    texels = rng.uniform(-0.8, 0.8, (problem.space.num_texels, problem.channels.num_channels)).astype(np.float32)
    lr, wd, ids = 0.01, 0.05, np.array([0, 2])
    optimizer = make_optimizer(lr, wd)
    state, (metrics,) = run_steps(problem, settings_for(problem), optimizer, [ids], texels=texels)
    loss, grad = numpy_loss_and_grad(problem, texels, ids)
    assert metrics["finite"] == 1 and np.isclose(metrics["loss"], loss, rtol=1e-5)
    assert np.isclose(metrics["grad_norm"], np.linalg.norm(grad), rtol=1e-5)
    # AdamW's first step: bias-corrected m = g, v = g^2, so the update is -lr (g / (|g| + eps) + wd theta).
    expected = texels - lr * (grad / (np.abs(grad) + 1e-8) + wd * texels)
    assert_close(np.asarray(state.texels), expected, rtol=2e-6, floor=1e-6)
    assert int(state.step) == 1


def test_value_spaces_and_the_camera_rotation_of_normals():
    from jaxdistill.scene.cameras import rgbx_camera_rotation
    from jaxdistill.scene.maps import file_to_model, model_to_file

    rot = rgbx_camera_rotation(np.eye(4))          # OpenCV camera at the origin looking down +z
    np.testing.assert_allclose(np.array([0.0, 0.0, -1.0]) @ rot, [0, 0, 1])   # facing the camera: +z
    np.testing.assert_allclose(np.array([0.0, -1.0, 0.0]) @ rot, [0, 1, 0])   # world up (-y in OpenCV): +y
    np.testing.assert_allclose(np.array([1.0, 0.0, 0.0]) @ rot, [1, 0, 0])    # right stays right
    grey = np.full((2, 2, 3), 0.25, np.float32)
    assert file_to_model("roughness", grey).shape == (2, 2, 1) and np.allclose(file_to_model("roughness", grey), -0.5)
    colour = np.random.default_rng(0).uniform(0, 1, (2, 2, 3)).astype(np.float32)
    np.testing.assert_allclose(model_to_file("albedo", file_to_model("albedo", colour)), colour, atol=1e-7)
    n = np.array([[[0.0, 0.0, 2.0], [0.0, 0.0, 0.0]]], np.float32)
    np.testing.assert_allclose(model_to_file("normal", n), [[[0, 0, 1], [0, 0, 0]]])


def test_per_map_losses_sum_to_the_loss_and_initial_values_follow_the_thesis(problem):
    channels = MapChannels(("albedo", "normal", "roughness", "metallic", "irradiance"))
    row = channels.initial_texels(1)[0]
    assert row.tolist() == [0, 0, 0, 0, 0, 0, 1, -1, 0, 0, 0]
    _, (m,) = run_steps(problem, settings_for(problem), make_optimizer(0.01, 0.0), [np.array([1, 3])])
    assert np.isclose(sum(m[f"loss_{k}"] for k in MAPS), m["loss"], rtol=1e-5, atol=0)   # float32 sums, two orders


def test_a_run_is_a_function_of_its_seed(problem):
    settings = settings_for(problem, p_keep=0.5)
    optimizer = make_optimizer(0.01, 0.0)
    steps = [np.array([0, 1]), np.array([2, 3]), np.array([1, 2])]
    a, ma = run_steps(problem, settings, optimizer, steps, seed=3)
    b, mb = run_steps(problem, settings, optimizer, steps, seed=3)
    c, _ = run_steps(problem, settings, optimizer, steps, seed=4)
    assert np.array_equal(np.asarray(a.texels), np.asarray(b.texels))
    assert [m["loss"] for m in ma] == [m["loss"] for m in mb]
    assert not np.array_equal(np.asarray(a.texels), np.asarray(c.texels))      # the dropout masks differ


def test_dropout_keeps_about_p_keep_of_the_loss(problem):
    ids = [np.array([0, 1, 2, 3])]
    optimizer = make_optimizer(0.01, 0.0)
    _, (full,) = run_steps(problem, settings_for(problem), optimizer, ids)
    for p_keep in (0.25, 0.75):
        _, (kept,) = run_steps(problem, settings_for(problem, p_keep=p_keep), optimizer, ids)
        assert abs(kept["loss"] / full["loss"] - p_keep) < 0.1


def test_timesteps_stay_in_range_and_annealing_shrinks_the_upper_end():
    channels = MapChannels(("albedo",))
    flat = StepSettings(channels=channels, height=1, width=1, total_steps=101, t_min=0.2, t_max=0.98)
    t = np.asarray(sample_timesteps(jax.random.PRNGKey(0), jnp.int32(0), (4000,), flat))
    assert t.min() >= 200 and t.max() <= 980 and t.min() < 220 and t.max() > 960
    for anneal in ("linear", "sqrt"):
        s = StepSettings(channels=channels, height=1, width=1, total_steps=101, anneal=anneal)
        uppers = [float(upper_t(jnp.int32(i), s)) for i in (0, 25, 50, 100)]
        assert uppers[0] == pytest.approx(0.98) and uppers[-1] == pytest.approx(0.2)
        assert all(a > b for a, b in zip(uppers, uppers[1:]))
        late = np.asarray(sample_timesteps(jax.random.PRNGKey(1), jnp.int32(100), (100,), s))
        assert np.all(late == 200)
    assert float(upper_t(jnp.int32(50), StepSettings(channels=channels, height=1, width=1, total_steps=101,
                                                     anneal="sqrt"))) < 0.98 - 0.78 * 0.5
    alphas = jnp.linspace(1.0, 0.0, 1000)
    sds = StepSettings(channels=channels, height=1, width=1, total_steps=1, t_weighting="sds")
    tt = jnp.array([[0, 500, 999]])
    np.testing.assert_allclose(np.asarray(t_weights(tt, alphas, sds)), 1.0 - np.asarray(alphas)[[0, 500, 999]][None])
    assert np.all(np.asarray(t_weights(tt, alphas, flat)) == 1.0)


def test_a_non_finite_step_leaves_the_state_unchanged(problem):
    optimizer = make_optimizer(0.01, 0.0)
    texels = problem.initial_texels()
    texels[5, 0] = np.nan
    state, (m,) = run_steps(problem, settings_for(problem), optimizer, [np.arange(4)], texels=texels)
    assert m["finite"] == 0 and int(state.step) == 0 and bool(state.halted)
    np.testing.assert_array_equal(np.asarray(state.texels), texels)
    step = jax.jit(make_step(problem.prior, settings_for(problem), optimizer))
    state = state.replace(texels=jnp.asarray(problem.initial_texels()))   # finite again, but the run halted
    after, m = step(state, problem.batch(np.arange(4)), problem.frozen)
    assert m["finite"] == 0 and int(after.step) == 0
    np.testing.assert_array_equal(np.asarray(after.texels), problem.initial_texels())


def test_the_jitted_step_compiles_once_and_reports_retraces(problem):
    optimizer = make_optimizer(0.01, 0.0)
    mesh = data_mesh()
    first = problem.batch(np.array([0, 1]))
    state = init_state(problem.initial_texels(), optimizer, 0)
    step, traces = jit_step(make_step(problem.prior, settings_for(problem), optimizer), mesh, first, state,
                            problem.frozen)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    state = jax.device_put(state, replicated)
    for ids in ([0, 1], [2, 3], [3, 1]):
        state, _ = step(state, problem.batch(np.array(ids)), problem.frozen)
    traces.check(1)
    assert traces.traces == 1
    state, _ = step(state, problem.batch(np.array([0, 1, 2])), problem.frozen)     # a new batch shape
    with pytest.raises(AssertionError, match="traced 2 times"):
        traces.check(1)


def test_trace_counter_counts_python_calls():
    counter = TraceCounter(lambda x: x + 1)
    f = jax.jit(counter)
    f(1.0), f(2.0), f(jnp.ones(3))
    assert counter.traces == 2


# ----------------------------------------------------------------------------- the rgbx prior


def count_primitive(jaxpr, name: str) -> int:
    """Occurrences of primitive `name` in a jaxpr and every sub-jaxpr (pjit, scan, custom_vjp...)."""
    total = 0
    for eqn in jaxpr.eqns:
        total += eqn.primitive.name == name
        for param in eqn.params.values():
            subs = param if isinstance(param, (list, tuple)) else [param]
            for sub in subs:
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    total += count_primitive(getattr(inner, "jaxpr", inner), name)
                elif hasattr(sub, "eqns"):
                    total += count_primitive(sub, name)
    return total


@pytest.fixture(scope="module")
def rgbx_problems(tiny_scene, run_rgbx_dir, tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache_rgbx")
    out = {}
    for space in ("image", "latent"):
        config = DistillConfig(scene=str(tiny_scene), out_dir="unused", maps=("albedo", "roughness"), prior="rgbx",
                               rgbx_dir=str(run_rgbx_dir), loss_space=space)
        out[space] = build_problem(config, cache_dir=cache)
    return out


def test_rgbx_step_runs_the_networks_forward_only(rgbx_problems):
    """The step's program has exactly the convolutions of one prior forward pass (VAE encode, UNet,
    VAE decode): a backward pass through any network would add the transposed convolutions. The
    latent-space ablation, which does differentiate the encoder, shows the count would change."""
    counts = {}
    for space, problem in rgbx_problems.items():
        settings = settings_for(problem)
        optimizer = make_optimizer(0.01, 0.0)
        state = init_state(problem.initial_texels(), optimizer, 0)
        batch = problem.batch(np.array([0, 1]))
        step_jaxpr = jax.make_jaxpr(make_step(problem.prior, settings, optimizer))(state, batch, problem.frozen)
        images = {m: jnp.zeros((2, problem.height, problem.width, 3 if m == "albedo" else 1)) for m in ("albedo", "roughness")}
        prior = problem.prior
        features = jax.eval_shape(lambda im: prior.features(problem.frozen["prior"], im, jax.random.PRNGKey(0)), images)
        features = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), features)
        t = jnp.full((2, 2), 500, jnp.int32)
        forward = jax.make_jaxpr(lambda f: prior.targets(problem.frozen["prior"], f, batch["prior"], t,
                                                         jax.random.PRNGKey(0)))(features)
        encode = jax.make_jaxpr(lambda im: prior.features(problem.frozen["prior"], im, jax.random.PRNGKey(0)))(images)
        counts[space] = (count_primitive(step_jaxpr.jaxpr, "conv_general_dilated"),
                         count_primitive(forward.jaxpr, "conv_general_dilated"),
                         count_primitive(encode.jaxpr, "conv_general_dilated"))
    step_convs, forward_convs, _ = counts["image"]
    assert forward_convs > 20 and step_convs == forward_convs
    step_convs, forward_convs, encoder_convs = counts["latent"]
    assert encoder_convs > 0 and step_convs == forward_convs + 2 * encoder_convs    # encoder forward + its transpose


def test_rgbx_step_is_finite_and_moves_the_texels(rgbx_problems):
    problem = rgbx_problems["image"]
    optimizer = make_optimizer(0.01, 0.0)
    state, metrics = run_steps(problem, settings_for(problem), optimizer, [np.array([0, 1]), np.array([2, 3])])
    assert all(m["finite"] == 1 and np.isfinite(m["loss"]) and m["loss"] > 0 for m in metrics)
    assert 200 <= metrics[0]["t_mean"] <= 980
    moved = np.abs(np.asarray(state.texels) - problem.initial_texels()).max()
    assert 0.0 < moved <= 2 * 0.01 + 1e-6                                            # two Adam steps of lr 0.01


class HalfwayPrior:
    """A prior whose x_pred depends on the render, as a learned prior's does: x_pred = render / 2 + 0.1."""

    latent_space = False

    def __init__(self, channels):
        self.channels = channels

    def view_data(self, view_ids):
        return {}

    def features(self, frozen, images, key):
        return images

    def targets(self, frozen, features, data, t, key):
        return {m: 0.5 * f + 0.1 for m, f in features.items()}

    def target_struct(self, features):
        return {m: jax.ShapeDtypeStruct(f.shape, jnp.float32) for m, f in features.items()}


def test_reuse_steps_takes_k_adamw_steps_towards_one_x_pred(problem):
    """With reuse_steps = 2 the prior's x_pred of steps 0 and 2 are what steps 1 and 3 move towards
    (the texels moved in between, so reusing differs from recomputing); against NumPy renders,
    loss and gradient, with optax's AdamW fed the NumPy gradients."""
    import optax

    prior = HalfwayPrior(problem.channels)
    settings = settings_for(problem, reuse_steps=2)
    optimizer = make_optimizer(0.05, 0.0)
    batch0 = problem.batch(np.array([0, 2]))
    texels0 = problem.initial_texels()
    reused = initial_reused(prior, settings, texels0, batch0, problem.frozen)
    assert reused["targets"]["albedo"].shape == (2, problem.height, problem.width, 3)
    state = init_state(texels0, optimizer, 0, reused)
    step = jax.jit(make_step(prior, settings, optimizer))
    schedule = [np.array([0, 2]), np.array([0, 2]), np.array([1, 3]), np.array([1, 3])]
    losses = []
    for ids in schedule:
        state, m = step(state, problem.batch(ids), problem.frozen)
        losses.append(float(m["loss"]))
    # the reference: x_pred recomputed on even steps only
    texels = texels0.astype(np.float32)
    ref_opt = optax.adamw(0.05, weight_decay=0.0)
    opt_state = ref_opt.init(texels)
    ref_losses = []
    for s, ids in enumerate(schedule):
        if s % 2 == 0:
            target = 0.5 * numpy_render(problem, texels, ids) + 0.1
        loss, grad = numpy_loss_and_grad(problem, texels, ids, target)
        ref_losses.append(loss)
        updates, opt_state = ref_opt.update(grad.astype(np.float32), opt_state, texels)
        texels = np.asarray(optax.apply_updates(texels, updates))
    assert_close(np.array(losses), np.array(ref_losses), rtol=1e-4)
    assert_close(np.asarray(state.texels), texels, rtol=1e-4, floor=1e-5)
    # recomputing x_pred on every step is a different run (so the comparison above can fail)
    fresh = init_state(texels0, optimizer, 0)
    fresh_step = jax.jit(make_step(prior, settings_for(problem), optimizer))
    for ids in schedule:
        fresh, _ = fresh_step(fresh, problem.batch(ids), problem.frozen)
    assert np.abs(np.asarray(fresh.texels) - np.asarray(state.texels)).max() > 1e-3


def test_the_views_priors_target_struct_is_its_targets(problem):
    """The views prior's targets (the scene's per-view images) shaped as `target_struct` says."""
    prior = problem.prior
    batch = problem.batch(np.array([0, 1]))
    columns = {m: problem.channels.slice(m) for m in problem.channels.maps}
    images = {m: jax.ShapeDtypeStruct((2, problem.height, problem.width, c.stop - c.start), jnp.float32)
              for m, c in columns.items()}
    traced = jax.eval_shape(lambda f: prior.targets(problem.frozen["prior"], f, batch["prior"], None, None), images)
    assert prior.target_struct(images) == traced


def test_target_struct_is_what_the_prior_pass_returns(rgbx_problems, run_rgbx_dir):
    """`Prior.target_struct` (what --reuse_steps keeps between prior passes is shaped by it, and
    `lax.cond` needs it exact) against the shapes and dtypes of a traced prior pass: both loss
    spaces, float32 and bfloat16 activations, a colour and a grey map."""
    from jaxdistill.models import convert

    # the same networks with bfloat16 activations (the weights stay float32: the same frozen arrays)
    bf16 = convert.build_networks(run_rgbx_dir, jnp.bfloat16, "default", None, True, "--rgbx_dir")
    priors = {name: problem.prior for name, problem in rgbx_problems.items()}
    priors.update({f"{name}_bf16": dataclasses.replace(problem.prior, networks=bf16)
                   for name, problem in rgbx_problems.items()})
    for name, prior in priors.items():
        problem = rgbx_problems[name.split("_")[0]]
        frozen = problem.frozen["prior"]
        images = {m: jax.ShapeDtypeStruct((2, problem.height, problem.width, 3 if m == "albedo" else 1), jnp.float32)
                  for m in ("albedo", "roughness")}
        features = jax.eval_shape(lambda im: prior.features(frozen, im, jax.random.PRNGKey(0)), images)
        t = jax.ShapeDtypeStruct((2, 2), jnp.int32)
        traced = jax.eval_shape(lambda f, t: prior.targets(frozen, f, problem.batch(np.array([0, 1]))["prior"], t,
                                                           jax.random.PRNGKey(0)), features, t)
        assert prior.target_struct(features) == traced, name
        assert jax.tree.map(lambda s: s.shape, traced) == jax.tree.map(lambda s: s.shape, features), name


def test_reuse_steps_with_the_rgbx_prior_keeps_t_and_runs_one_prior_pass(rgbx_problems):
    """The rgbx step with reuse_steps = 3: the reused steps report the t of the step that ran the
    prior, and the program still holds one prior forward pass (inside the cond's refresh branch)."""
    problem = rgbx_problems["image"]
    settings = settings_for(problem, reuse_steps=3)
    optimizer = make_optimizer(0.01, 0.0)
    batch = problem.batch(np.array([0, 1]))
    state = init_state(problem.initial_texels(), optimizer, 0,
                       initial_reused(problem.prior, settings, problem.initial_texels(), batch, problem.frozen))
    step = jax.jit(make_step(problem.prior, settings, optimizer))
    t_means = []
    for ids in ([0, 1], [0, 1], [0, 1], [2, 3], [2, 3]):
        state, m = step(state, problem.batch(np.array(ids)), problem.frozen)
        assert m["finite"] == 1
        t_means.append(float(m["t_mean"]))
    assert t_means[0] == t_means[1] == t_means[2] and t_means[3] == t_means[4] and t_means[3] != t_means[0]
    jaxpr = jax.make_jaxpr(make_step(problem.prior, settings, optimizer))(
        init_state(problem.initial_texels(), optimizer, 0,
                   initial_reused(problem.prior, settings, problem.initial_texels(), batch, problem.frozen)),
        batch, problem.frozen)
    plain = jax.make_jaxpr(make_step(problem.prior, settings_for(problem), optimizer))(
        init_state(problem.initial_texels(), optimizer, 0), batch, problem.frozen)
    assert count_primitive(jaxpr.jaxpr, "conv_general_dilated") == count_primitive(plain.jaxpr, "conv_general_dilated")
