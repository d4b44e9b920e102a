"""The distillation step: one pure, jitted function (state, batch, frozen) → (state, metrics).

Per step, for a batch of B views and the M requested maps (thesis §4.2, docs/design.md §4):
1. gather-render the current texels for all views and maps at once (`render`, one gather);
   normals are rotated from world to each view's RGB<->X camera space;
2. `features` = the renders (image-space loss) or their VAE latents (latent-space loss);
3. x_pred = prior.targets(stop_gradient(features), t, ...) — forward only: the networks are
   never differentiated (image space); t ~ U[t_min, upper(step)]·1000 per view and map;
4. loss = (1/B) Σ_b Σ_m w(t_bm) Σ_pixels W ⊙ keep ⊙ Σ_c (features − x_pred)², W the visibility
   weights (or the hit mask), keep a Bernoulli(p_keep) image-space dropout mask;
5. the gradient reaches the texels through the transpose of the gather (a scatter-add), and
   optax AdamW updates them.
With `reuse_steps` K > 1 the prior runs only on every K-th step; the K - 1 steps after it take
AdamW steps towards the same x_pred (and w(t)) on the same views (the caller repeats the batch),
kept in the state: Instruct-NeRF2NeRF's "iterative dataset update" in SDS form, at 1/K of the
prior's cost per step. A step whose loss or gradient is not finite leaves the state as it
   was, reports `finite = 0` and halts the state (later steps change nothing), so the caller can
   stop with the last good state even when it fetches metrics only every few steps.

The PRNG key of a step is fold_in(state.key, state.step): a run is a function of its seed.
Texels, loss and optimizer state are float32 whatever the prior's activation dtype.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxdistill.engine import gains as align_lib, photo as photo_lib
from jaxdistill.engine.config import DistillConfig
from jaxdistill.engine.optimizer import gated_step, learning_rate, make_optimizer  # noqa: F401 (the step's API)
from jaxdistill.engine.priors import Prior
from jaxdistill.scene.maps import MapChannels
from jaxdistill.render.gather_plan import GatherPlan
from jaxdistill.render.sampler import build_pyramid, render, sample_many


@flax.struct.dataclass
class DistillState:
    """texels (N, C) float32 in model space; opt_state (AdamW); step () int32; key (2,) uint32;
    halted () bool: a step was not finite, and every later step leaves the state as it is."""

    texels: jax.Array
    opt_state: Any
    step: jax.Array
    key: jax.Array
    halted: jax.Array
    reused: Any = None      # reuse_steps > 1: {"targets", "sample_weights", "t"} of the last prior call
    align: Any = None       # align = "gain": {"log_gains": (V, G) float32, "opt": their Adam state} (align.py)


@dataclasses.dataclass(frozen=True)
class StepSettings:
    """Static settings of the step (hashable; part of the jit cache key). Defaults are the flags'."""

    channels: MapChannels
    height: int
    width: int
    total_steps: int
    t_min: float = DistillConfig.t_min
    t_max: float = DistillConfig.t_max
    anneal: str = DistillConfig.anneal
    t_weighting: str = DistillConfig.t_weighting
    p_keep: float = DistillConfig.p_keep
    reuse_steps: int = DistillConfig.reuse_steps
    align: str = DistillConfig.align
    align_strength: float = DistillConfig.align_strength
    num_train_timesteps: int = 1000
    latent_factor: int = 8
    photo_weight: float = 0.0          # the re-rendering term (photo.py); 0: off, nothing of it is traced
    photo_space: str = DistillConfig.photo_space
    photo_loss: str = DistillConfig.photo_loss
    photo_scale: str = "batch"          # resolved (photo.resolve_scale: from_config turns "auto" into a mode)
    irradiance_smoothness: float = 0.0
    irradiance_sds_weight: float = 1.0    # scales the irradiance map's SDS term (1: untouched, not traced)
    albedo_smoothness: float = 0.0         # the photo-guided albedo smoothness (photo.py); needs batch["photo_guide"]
    photo_height: int = 0
    photo_width: int = 0
    split_pyramid: bool = True             # the pyramid as `sampler.SplitPyramid` (False: concatenated; loop.step_settings)

    @classmethod
    def from_config(cls, config: DistillConfig, channels: MapChannels, height: int, width: int,
                    num_train_timesteps: int, photo_shape: tuple[int, int] = (0, 0),
                    photo_scale: str | None = None) -> "StepSettings":
        """The step's settings: every field the config shares by name, plus the problem's shapes
        (renders; photos for the re-rendering term), the photo scale --photo_scale resolved to
        (`PhotoData.scale`; "auto" alone resolves as HDR) and the prior's number of diffusion
        timesteps (`Prior.num_train_timesteps`)."""
        shared = {f.name: getattr(config, f.name) for f in dataclasses.fields(cls) if hasattr(config, f.name)}
        shared["photo_scale"] = photo_lib.resolve_scale(photo_scale or config.photo_scale, ldr=False)
        return cls(channels=channels, height=height, width=width, total_steps=config.steps,
                   num_train_timesteps=num_train_timesteps, photo_height=photo_shape[0], photo_width=photo_shape[1],
                   **shared)


def init_state(texels: np.ndarray, optimizer: optax.GradientTransformation, seed: int,
               reused: Any = None, align: Any = None) -> DistillState:
    """Step-0 state: the given initial texels (float32), fresh AdamW state, key PRNGKey(seed).

    Floating texels narrower than float32 (float16, bfloat16) are refused with a ValueError:
    small AdamW updates (~1e-4, e.g. late in a cosine schedule) vanish in 16-bit floats (the
    thesis: fp16 made gradients vanish). Wider or integer inputs are cast to float32."""
    dtype = np.dtype(texels.dtype if hasattr(texels, "dtype") else np.asarray(texels).dtype)
    if jnp.issubdtype(dtype, jnp.floating) and dtype.itemsize < 4:
        raise ValueError(f"texels are {dtype.name}, but texels must be float32: AdamW updates of ~1e-4 vanish in "
                         "16-bit floats (0.5 + 1e-4 rounds back to 0.5 in float16 and bfloat16); keep texels, "
                         "loss and optimizer state in float32 (only the frozen networks may run in bfloat16, "
                         "--prior_dtype)")
    texels = jnp.asarray(texels, jnp.float32)
    return DistillState(texels=texels, opt_state=optimizer.init(texels), step=jnp.zeros((), jnp.int32),
                        key=jax.random.PRNGKey(seed), halted=jnp.zeros((), bool), reused=reused, align=align)


def initial_align(num_views: int, channels: MapChannels, align_optimizer: optax.GradientTransformation | None):
    """The per-view log-gains (all 0: gains 1) and their optimizer state, or None without alignment."""
    if align_optimizer is None:
        return None
    log_gains = jnp.asarray(align_lib.initial_log_gains(num_views, channels))
    return {"log_gains": log_gains, "opt": align_optimizer.init(log_gains)}


def render_maps(texels, plan: GatherPlan, normal_rotation, channels: MapChannels) -> dict:
    """{map: (B, H, W, C_map)} model-space renders; normals as n_world @ normal_rotation[b]."""
    return _rotated_maps(render(texels, plan), normal_rotation, channels)


def _rotated_maps(image, normal_rotation, channels: MapChannels) -> dict:
    """`render_maps` of a rendered (B, H, W, C) image."""
    images = channels.split(image)
    if "normal" in images:
        images["normal"] = jnp.einsum("bhwi,bij->bhwj", images["normal"], normal_rotation)
    return images


def upper_t(step, settings: StepSettings):
    """Upper end of the t range at `step` (fraction of T): t_max, or annealed towards t_min."""
    if settings.anneal == "none":
        return jnp.float32(settings.t_max)
    frac = jnp.clip(step.astype(jnp.float32) / max(settings.total_steps - 1, 1), 0.0, 1.0)
    if settings.anneal == "sqrt":
        frac = jnp.sqrt(frac)
    return settings.t_max - (settings.t_max - settings.t_min) * frac


def sample_timesteps(key, step, shape, settings: StepSettings):
    """(shape) int32 timesteps, uniform in [t_min, upper_t(step)] · T, within [0, T - 1]."""
    u = jax.random.uniform(key, shape, jnp.float32)
    lo, hi = settings.t_min, upper_t(step, settings)
    t = jnp.round((lo + (hi - lo) * u) * settings.num_train_timesteps)
    return jnp.clip(t, 0, settings.num_train_timesteps - 1).astype(jnp.int32)


def t_weights(t, alphas_cumprod, settings: StepSettings):
    """(B, M) w(t): 1, or 1 - alpha_bar_t (DreamFusion's sigma_t^2) for t_weighting='sds'."""
    if settings.t_weighting == "none" or alphas_cumprod is None:
        return jnp.ones(t.shape, jnp.float32)
    return 1.0 - alphas_cumprod[t]


def pool_weights(weights, factor: int):
    """(B, H, W) pixel weights → (B, H/f, W/f) means over f x f blocks (latent resolution)."""
    b, h, w = weights.shape
    return weights.reshape(b, h // factor, factor, w // factor, factor).mean(axis=(2, 4))


def weighted_square_error(features: dict, targets: dict, weights, sample_weights, maps, map_weights=None):
    """(loss, {map: its term}): loss = (1/B) Σ_b Σ_m λ_m w_bm Σ_hw weights_bhw Σ_c (features − targets)²,
    weights (B, h, w), w (B, M), λ_m = map_weights.get(m, 1) (a weight of exactly 1 is not
    multiplied in); the per-map terms sum to the loss."""
    terms = {}
    for i, m in enumerate(maps):
        sq = jnp.sum(jnp.square(features[m].astype(jnp.float32) - targets[m].astype(jnp.float32)), axis=-1)
        terms[m] = jnp.sum(sample_weights[:, i] * jnp.sum(weights * sq, axis=(1, 2))) / weights.shape[0]
        if map_weights and map_weights.get(m, 1.0) != 1.0:
            terms[m] = map_weights[m] * terms[m]
    return sum(terms.values()), terms


def make_step(prior: Prior, settings: StepSettings, optimizer: optax.GradientTransformation,
              align_optimizer: optax.GradientTransformation | None = None) -> Callable:
    """The pure step: (state, batch, frozen) → (state, metrics). Not jitted (see `jit_step`).

    batch: index (B, P, T) int32, weight (B, P, T) float32, hit (B, P) bool (the views' gather
    plans), pixel_weight (B, H, W) float32, normal_rotation (B, 3, 3) float32, view (B,) int32
    the views' indices (per-view gains, `align.py`), prior: the prior's per-view data.
    frozen: {"chain": MipChain, "prior": the prior's constants, "alphas_cumprod": (T,) float32 or
    None}. `align_optimizer` updates the per-view log-gains when settings.align == "gain".
    """
    maps = settings.channels.maps

    def step(state: DistillState, batch: dict, frozen: dict):
        key = jax.random.fold_in(state.key, state.step)
        k_features, k_t, k_prior, k_keep = jax.random.split(key, 4)
        # one mip pyramid for the renders and the photos, so one transpose of it in the gradient; split
        # (texels + the entries above them, `SplitPyramid`): no copy of the texels, and its cotangent's
        # level 0 is their gradient, one texel array less in the step's memory than a concatenated
        # pyramid, and on the CPU no slower (docs/benchmarks.md §10; `loop.step_settings`). The renders'
        # and the photos' taps are read by one gather, so their gradient is one scatter-add
        # (`sample_many`; docs/benchmarks.md §7)
        pyramid, pyramid_pullback = jax.vjp(
            lambda x: build_pyramid(x, frozen["chain"], split=settings.split_pyramid), state.texels)
        plans = [_render_plan(settings, batch, frozen)]
        if settings.photo_weight > 0:
            plans.append(_photo_plan(settings, batch, frozen))
        images, images_pullback = jax.vjp(lambda p: sample_many(p, plans), pyramid)
        features_of = _features_fn(prior, settings, batch, frozen, k_features)
        features, pullback = jax.vjp(features_of, images[0])
        num_views = batch["pixel_weight"].shape[0]

        def fresh(_):
            t = sample_timesteps(k_t, state.step, (num_views, len(maps)), settings)
            targets = jax.lax.stop_gradient(
                prior.targets(frozen["prior"], jax.lax.stop_gradient(features), batch["prior"], t, k_prior))
            return {"targets": targets, "sample_weights": t_weights(t, frozen.get("alphas_cumprod"), settings), "t": t}

        if settings.reuse_steps > 1:      # the prior runs on every reuse_steps-th step only
            reused = jax.lax.cond(state.step % settings.reuse_steps == 0, fresh, lambda _: state.reused, None)
        else:
            reused = fresh(None)
        targets, sample_weights, t = reused["targets"], reused["sample_weights"], reused["t"]
        weights = batch["pixel_weight"]
        if prior.latent_space:
            weights = pool_weights(weights, settings.latent_factor)
        if settings.p_keep < 1.0:
            weights = weights * jax.random.bernoulli(k_keep, settings.p_keep, weights.shape).astype(jnp.float32)
        aligned = settings.align == "gain"
        log_gains = state.align["log_gains"] if aligned else jnp.zeros((), jnp.float32)

        def objective(features, log_gains):
            compared, ridge = targets, 0.0
            if aligned:
                compared = align_lib.apply_gains(targets, log_gains, batch["view"], settings.channels)
                ridge = align_lib.ridge(log_gains, batch["view"], weights, settings.align_strength)
            loss, terms = weighted_square_error(features, compared, weights, sample_weights, maps,
                                                {"irradiance": settings.irradiance_sds_weight})
            return loss + ridge, terms

        (loss, terms), (grad_features, grad_gains) = jax.value_and_grad(objective, argnums=(0, 1), has_aux=True)(
            features, log_gains)
        grads = list(pullback(grad_features))
        photo_metrics = {}
        if settings.photo_weight > 0:       # the photos re-rendered from the texels (photo.py)
            with jax.named_scope("photo_term"):
                (photo_value, photo_metrics), photo_grad = jax.value_and_grad(
                    _photo_of_image(settings, batch), has_aux=True)(images[1])
            loss = loss + settings.photo_weight * photo_value
            grads.append(settings.photo_weight * photo_grad)
        (grad,) = images_pullback(tuple(grads))
        (grad,) = pyramid_pullback(grad)
        with jax.named_scope("update"):        # the finite gate and AdamW (a stage of scripts/bench_profile.py)
            finite = jnp.isfinite(loss) & jnp.all(jnp.isfinite(grad)) & jnp.all(jnp.isfinite(grad_gains))
            ok = finite & ~state.halted            # after a non-finite step, nothing moves any more
            texels, opt_state = gated_step(optimizer, grad, state.opt_state, state.texels, ok)
        keep_new = functools.partial(jnp.where, ok)
        new_align = state.align
        if aligned:
            gain_updates, gain_opt = align_optimizer.update(grad_gains, state.align["opt"], log_gains)
            new_align = jax.tree.map(keep_new, {"log_gains": optax.apply_updates(log_gains, gain_updates),
                                                "opt": gain_opt}, state.align)
        new_state = DistillState(texels=texels, opt_state=opt_state,
                                 step=state.step + ok.astype(jnp.int32), key=state.key,
                                 halted=state.halted | ~finite,
                                 reused=(jax.tree.map(keep_new, reused, state.reused) if settings.reuse_steps > 1
                                         else state.reused), align=new_align)
        per_map = {f"loss_{m}": term for m, term in terms.items()}
        with jax.named_scope("metrics"):
            metrics = {"loss": loss, "finite": ok.astype(jnp.int32), "grad_norm": optax.tree.norm(grad),
                       "t_mean": jnp.mean(t.astype(jnp.float32)), **per_map, **photo_metrics}
        if aligned:
            metrics["gain_spread"] = jnp.std(align_lib.centred(new_align["log_gains"]))
        return new_state, metrics

    return step


def _render_plan(settings: StepSettings, batch: dict, frozen: dict) -> GatherPlan:
    """The gather plans of the batch's views at the render size."""
    return GatherPlan(index=batch["index"], weight=batch["weight"], hit=batch["hit"], chain=frozen["chain"],
                      height=settings.height, width=settings.width)


def _photo_plan(settings: StepSettings, batch: dict, frozen: dict) -> GatherPlan:
    """The gather plans of the batch's photos at the photo size."""
    return GatherPlan(index=batch["photo_index"], weight=batch["photo_tap_weight"], hit=batch["photo_hit"],
                      chain=frozen["chain"], height=settings.photo_height, width=settings.photo_width)


def _features_fn(prior, settings: StepSettings, batch: dict, frozen: dict, key) -> Callable:
    """renders (B, H, W, C) of the batch's views → the prior's features (the renders' maps, or
    their latents)."""
    def features_of(image):
        return prior.features(frozen["prior"], _rotated_maps(image, batch["normal_rotation"], settings.channels), key)

    return features_of


def _photo_fn(settings: StepSettings, batch: dict, frozen: dict) -> Callable:
    """texels → (L_photo, metrics) of the batch's photos (`photo.photo_loss`), rendered through
    the photo-sized gather plans."""
    photo_of, plan = _photo_of_image(settings, batch), _photo_plan(settings, batch, frozen)
    return lambda texels: photo_of(render(texels, plan))


def _photo_of_image(settings: StepSettings, batch: dict) -> Callable:
    """`_photo_fn` of the photos rendered (B, H_photo, W_photo, C). Every channel is sampled and the
    photo's maps taken from the images: the photos' taps read whole pyramid rows either way, and a
    column subset of the pyramid (or the texels) would cost a gather and its scatter-add over every row."""
    hit = batch["photo_hit"].reshape(-1, settings.photo_height, settings.photo_width)
    ratio = settings.height * settings.width / (settings.photo_height * settings.photo_width)
    used = [m for m in ("albedo", "irradiance", "metallic") if m in settings.channels.maps]

    def photo_of(image):
        rendered = settings.channels.split(image)
        images = {m: rendered[m] for m in used}          # only the maps the photo is made of
        return photo_lib.photo_loss(images, batch["photo"], batch["photo_pixel_weight"], hit,
                                    loss=settings.photo_loss, space=settings.photo_space, scale=settings.photo_scale,
                                    pixel_ratio=ratio, smooth=settings.irradiance_smoothness,
                                    albedo_smooth=settings.albedo_smoothness, guide=batch.get("photo_guide"))

    return photo_of


def initial_reused(prior, settings: StepSettings, texels, batch: dict, frozen: dict) -> Any:
    """Zeros shaped like what a step keeps for `reuse_steps` > 1 (x_pred, w(t), t of a batch), or
    None when every step calls the prior. Shapes only: nothing is computed, and the prior's pass
    is not traced either (`Prior.target_struct`; only the features are, the renders and, in
    latent space, their encoding)."""
    if settings.reuse_steps <= 1:
        return None
    features_of = _features_fn(prior, settings, batch, frozen, jax.random.PRNGKey(0))
    plan = _render_plan(settings, batch, frozen)
    features = jax.eval_shape(lambda x: features_of(render(x, plan)), jax.ShapeDtypeStruct(texels.shape, texels.dtype))
    t = jax.ShapeDtypeStruct((batch["pixel_weight"].shape[0], len(settings.channels.maps)), jnp.int32)
    reused = {"targets": prior.target_struct(features), "sample_weights": jax.ShapeDtypeStruct(t.shape, jnp.float32),
              "t": t}
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), reused)


class TraceCounter:
    """Wraps a function to count how often JAX traces it; `check(max_traces)` raises beyond it
    (as big_vision's chex.assert_max_traces: a retrace means a shape or a static changed)."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self.traces = 0
        functools.update_wrapper(self, fn)

    def __call__(self, *args, **kwargs):
        self.traces += 1
        return self.fn(*args, **kwargs)

    def check(self, max_traces: int = 1) -> None:
        if self.traces > max_traces:
            raise AssertionError(f"the step was traced {self.traces} times (at most {max_traces} expected): "
                                 "a batch shape, dtype or static setting changed between steps")


def jit_step(step: Callable, mesh: jax.sharding.Mesh, batch_example: dict, state_example: DistillState,
             frozen_example: dict) -> tuple[Callable, TraceCounter]:
    """(jitted step, its trace counter): batch sharded over the mesh's "data" axis (leading
    dimension), state and frozen constants replicated; the state is donated."""
    counter = TraceCounter(step)
    replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    by_view = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    state_sharding = jax.tree.map(lambda _: replicated, state_example)
    batch_sharding = jax.tree.map(lambda _: by_view, batch_example)
    frozen_sharding = jax.tree.map(lambda _: replicated, frozen_example)
    jitted = jax.jit(counter, in_shardings=(state_sharding, batch_sharding, frozen_sharding),
                     out_shardings=(state_sharding, replicated), donate_argnums=(0,))
    return jitted, counter


def data_mesh(devices=None) -> jax.sharding.Mesh:
    """A 1-D mesh over all (or the given) devices with axis "data"."""
    devices = np.asarray(jax.devices() if devices is None else devices)
    return jax.sharding.Mesh(devices, ("data",))

