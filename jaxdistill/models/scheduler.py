"""DDIM noise schedule and sampler as pure functions (the maths of diffusers' DDIMScheduler).

Conventions: `alpha_bar` is ᾱ_t = prod_{s<=t} (1 - beta_s) in [0, 1], float32. A noisy sample is
x_t = sqrt(ᾱ) x0 + sqrt(1 - ᾱ) ε; the v target is v = sqrt(ᾱ) ε - sqrt(1 - ᾱ) x0. Timesteps are
integers in [0, num_train_timesteps). Where an `alpha_bar` meets a sample it is a scalar or has
the sample's leading (batch) dims, and is broadcast over the remaining ones.

The schedule depends only on the (static, hashable) `SchedulerConfig`; under `jax.jit` pass the
config as a static argument, so the schedule arrays become compile-time constants.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.errors import InputError, ProblemList, read_json

# Floor for sqrt(ᾱ) and sqrt(1 - ᾱ) denominators. It is below every non-zero ᾱ and 1 - ᾱ of the
# usual schedules (the smallest is ᾱ_998 ≈ 4e-9 for a linear schedule rescaled to zero terminal
# SNR), so it only acts at exactly ᾱ = 0 (the last zero-terminal-SNR timestep) or ᾱ = 1, where it
# turns 0/0 or x/0 into a large but finite value (at most 1e6 times the numerator).
ALPHA_BAR_FLOOR = 1e-12

BETA_SCHEDULES = ("linear", "scaled_linear")
PREDICTION_TYPES = ("epsilon", "v_prediction", "sample")
TIMESTEP_SPACINGS = ("leading", "trailing", "linspace")


@dataclasses.dataclass(frozen=True)
class SchedulerConfig:
    """DDIM settings with diffusers' DDIMScheduler defaults (frozen and hashable: jit-static)."""

    num_train_timesteps: int = 1000
    beta_start: float = 0.0001
    beta_end: float = 0.02
    beta_schedule: str = "linear"
    prediction_type: str = "epsilon"
    set_alpha_to_one: bool = True
    steps_offset: int = 0
    rescale_betas_zero_snr: bool = False
    timestep_spacing: str = "leading"
    clip_sample: bool = True
    clip_sample_range: float = 1.0

    def __post_init__(self):
        problems = config_problems(dataclasses.asdict(self))
        if problems:
            raise InputError([("SchedulerConfig", field, msg) for field, msg in problems])


_FIELDS = tuple(f.name for f in dataclasses.fields(SchedulerConfig))


def _is_int(v) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
        and bool(np.isfinite(v))


def config_problems(values: dict) -> list[tuple[str, str]]:
    """[(field, what is wrong)] for scheduler settings (diffusers config keys); [] when usable."""
    problems = []

    def check(field, ok, message):
        if field in values and not ok(values[field]):
            problems.append((field, f"{message}, got {values[field]!r}"))

    check("num_train_timesteps", lambda v: _is_int(v) and v >= 2, "must be an integer >= 2")
    check("beta_start", lambda v: _is_number(v) and 0 < v < 1, "must be a number in (0, 1)")
    check("beta_end", lambda v: _is_number(v) and 0 < v < 1, "must be a number in (0, 1)")
    check("beta_schedule", lambda v: v in BETA_SCHEDULES,
          f"must be one of {', '.join(BETA_SCHEDULES)} (other schedules are not supported)")
    check("prediction_type", lambda v: v in PREDICTION_TYPES,
          f"must be one of {', '.join(PREDICTION_TYPES)}")
    check("timestep_spacing", lambda v: v in TIMESTEP_SPACINGS,
          f"must be one of {', '.join(TIMESTEP_SPACINGS)}")
    for field in ("set_alpha_to_one", "rescale_betas_zero_snr", "clip_sample"):
        check(field, lambda v: isinstance(v, bool), "must be true or false")
    check("steps_offset", lambda v: _is_int(v) and v >= 0, "must be an integer >= 0")
    check("clip_sample_range", lambda v: _is_number(v) and v > 0, "must be a number > 0")
    check("thresholding", lambda v: v in (False, None), "dynamic thresholding is not supported; "
          "set it to false")
    check("trained_betas", lambda v: v is None, "explicit trained_betas are not supported; use "
          "beta_start/beta_end/beta_schedule and set trained_betas to null")
    return problems


def _config_file(folder: Path) -> Path:
    """The scheduler_config.json for a model folder, its scheduler/ folder, or the file itself."""
    if folder.is_file():
        return folder
    if (folder / "scheduler_config.json").is_file():
        return folder / "scheduler_config.json"
    return folder / "scheduler" / "scheduler_config.json"


def read_scheduler_config(folder, **overrides) -> SchedulerConfig:
    """Reads diffusers' scheduler/scheduler_config.json; `overrides` replace its values.

    `folder` is the model folder, its scheduler/ subfolder, or the JSON file. Keys absent from the
    file take DDIMScheduler's defaults; keys that are not DDIM settings (other schedulers' options,
    `_class_name`, ...) are ignored, as `DDIMScheduler.from_config` does.
    e.g. RGB->X: `read_scheduler_config(root, rescale_betas_zero_snr=True, timestep_spacing="trailing")`.
    """
    unknown = sorted(set(overrides) - set(_FIELDS))
    if unknown:
        raise TypeError(f"unknown scheduler setting(s) {unknown}; known: {list(_FIELDS)}")
    path = _config_file(Path(folder))
    data = read_json(path, "missing: the model folder needs scheduler/scheduler_config.json "
                     "(copy the model completely)")
    if not isinstance(data, dict):
        raise InputError.single(path, "(root)", "must be a JSON object")
    used_defaults = data.get("_use_default_values") or []
    data = {k: v for k, v in data.items() if k not in used_defaults}
    problems = ProblemList()
    for field, message in config_problems(data):
        problems.add(path, field, message)
    for field, message in config_problems(overrides):
        problems.add("overrides", field, message)
    problems.raise_if_any()
    values = {k: data[k] for k in _FIELDS if k in data} | overrides
    values = {k: int(v) if _is_int(v) else v for k, v in values.items()}
    return SchedulerConfig(**values)


# ----------------------------------------------------------------------------- schedule


def betas(config: SchedulerConfig) -> jax.Array:
    """(T,) float32 betas (rescaled to zero terminal SNR when the config asks)."""
    t = config.num_train_timesteps
    if config.beta_schedule == "linear":
        b = jnp.linspace(config.beta_start, config.beta_end, t, dtype=jnp.float32)
    else:  # scaled_linear: linear in sqrt(beta)
        b = jnp.linspace(config.beta_start ** 0.5, config.beta_end ** 0.5, t, dtype=jnp.float32) ** 2
    return rescale_zero_terminal_snr(b) if config.rescale_betas_zero_snr else b


def rescale_zero_terminal_snr(betas: jax.Array) -> jax.Array:
    """(T,) betas whose sqrt(ᾱ) is shifted to end at exactly 0 and rescaled to keep sqrt(ᾱ_0)
    (Lin et al. 2024, "Common diffusion noise schedules and sample steps are flawed", Alg. 1).
    The last beta becomes 1, so the last ᾱ is 0: pure noise."""
    root = jnp.sqrt(jnp.cumprod(1.0 - betas))
    first, last = root[0], root[-1]
    root = (root - last) * (first / (first - last))
    alpha_bar = root ** 2
    alphas = jnp.concatenate([alpha_bar[:1], alpha_bar[1:] / alpha_bar[:-1]])
    return 1.0 - alphas


def alphas_cumprod(config: SchedulerConfig) -> jax.Array:
    """(T,) float32 ᾱ_t, decreasing from ≈1 (t=0) to ≈0 (exactly 0 with zero terminal SNR)."""
    return jnp.cumprod(1.0 - betas(config))


def final_alpha_cumprod(config: SchedulerConfig, alphas_cumprod: jax.Array) -> jax.Array:
    """Scalar ᾱ used after the last step (prev_t < 0): 1 if set_alpha_to_one, else ᾱ_0."""
    return jnp.float32(1.0) if config.set_alpha_to_one else alphas_cumprod[0]


# ----------------------------------------------------------------------------- conversions


def _expand(alpha_bar, like: jax.Array) -> jax.Array:
    """ᾱ (scalar or the leading dims of `like`) reshaped to broadcast against `like`."""
    a = jnp.asarray(alpha_bar, jnp.float32)
    return a.reshape(a.shape + (1,) * (jnp.ndim(like) - a.ndim))


def _roots(alpha_bar, like) -> tuple[jax.Array, jax.Array]:
    """(sqrt(ᾱ), sqrt(1 - ᾱ)) broadcastable against `like` (ᾱ clipped to [0, 1])."""
    a = jnp.clip(_expand(alpha_bar, like), 0.0, 1.0)
    return jnp.sqrt(a), jnp.sqrt(1.0 - a)


def _safe_root(x: jax.Array) -> jax.Array:
    """sqrt(max(x, ALPHA_BAR_FLOOR)): a denominator that never reaches 0."""
    return jnp.sqrt(jnp.maximum(x, ALPHA_BAR_FLOOR))


def add_noise(x0: jax.Array, noise: jax.Array, alpha_bar) -> jax.Array:
    """x_t = sqrt(ᾱ) x0 + sqrt(1 - ᾱ) noise, same shape as x0."""
    s, r = _roots(alpha_bar, x0)
    return s * x0 + r * noise


def v_from_x0_eps(x0: jax.Array, eps: jax.Array, alpha_bar) -> jax.Array:
    """v = sqrt(ᾱ) ε - sqrt(1 - ᾱ) x0 (the v-prediction target)."""
    s, r = _roots(alpha_bar, x0)
    return s * eps - r * x0


def prediction_from_x0_eps(x0: jax.Array, eps: jax.Array, alpha_bar,
                           prediction_type: str) -> jax.Array:
    """The model target for `prediction_type` ("epsilon", "v_prediction", "sample")."""
    _check_prediction_type(prediction_type)
    if prediction_type == "epsilon":
        return eps
    if prediction_type == "sample":
        return x0
    return v_from_x0_eps(x0, eps, alpha_bar)


def x0_from_prediction(prediction: jax.Array, sample: jax.Array, alpha_bar,
                       prediction_type: str) -> jax.Array:
    """x̂0 from a model output at noisy `sample` x_t.

    epsilon: (x_t - sqrt(1-ᾱ) ε̂) / sqrt(ᾱ), with sqrt(ᾱ) floored (finite at ᾱ = 0, where an
    epsilon model cannot tell x0 at all); v_prediction: sqrt(ᾱ) x_t - sqrt(1-ᾱ) v̂; sample: as is.
    """
    _check_prediction_type(prediction_type)
    if prediction_type == "sample":
        return prediction
    a = jnp.clip(_expand(alpha_bar, sample), 0.0, 1.0)
    if prediction_type == "v_prediction":
        return jnp.sqrt(a) * sample - jnp.sqrt(1.0 - a) * prediction
    return (sample - jnp.sqrt(1.0 - a) * prediction) / _safe_root(a)


def eps_from_prediction(prediction: jax.Array, sample: jax.Array, alpha_bar,
                        prediction_type: str) -> jax.Array:
    """ε̂ from a model output at noisy `sample` x_t.

    epsilon: as is; v_prediction: sqrt(ᾱ) v̂ + sqrt(1-ᾱ) x_t; sample: (x_t - sqrt(ᾱ) x̂0) /
    sqrt(1-ᾱ), with sqrt(1-ᾱ) floored (finite at ᾱ = 1).
    """
    _check_prediction_type(prediction_type)
    if prediction_type == "epsilon":
        return prediction
    a = jnp.clip(_expand(alpha_bar, sample), 0.0, 1.0)
    if prediction_type == "v_prediction":
        return jnp.sqrt(a) * prediction + jnp.sqrt(1.0 - a) * sample
    return (sample - jnp.sqrt(a) * prediction) / _safe_root(1.0 - a)


def _check_prediction_type(prediction_type: str) -> None:
    if prediction_type not in PREDICTION_TYPES:
        raise ValueError(f"prediction_type must be one of {PREDICTION_TYPES}, got {prediction_type!r}")


# ----------------------------------------------------------------------------- DDIM


def ddim_timesteps(config: SchedulerConfig, num_inference_steps: int) -> np.ndarray:
    """(num_inference_steps,) int64 timesteps, decreasing, as DDIMScheduler.set_timesteps gives.

    leading: multiples of T // n plus steps_offset; trailing: round(T - i T/n) - 1 (starts at
    T - 1); linspace: round(linspace(0, T - 1, n)) reversed. For the step counts where diffusers'
    float `arange` yields one extra trailing timestep (-1; e.g. n = 61 of 1000) the first n are
    returned.
    """
    total, n = config.num_train_timesteps, num_inference_steps
    if not _is_int(n) or not 1 <= n <= total:
        raise InputError.single("scheduler", "num_inference_steps", f"must be an integer in [1, "
                                f"{total}] (the model's num_train_timesteps), got {n!r}")
    if config.timestep_spacing == "leading":
        steps = np.arange(n, dtype=np.int64)[::-1] * (total // n) + config.steps_offset
        if steps[0] >= total:
            raise InputError.single("scheduler", "num_inference_steps", f"{n} steps with "
                                    f"steps_offset {config.steps_offset} reach timestep {steps[0]} "
                                    f">= {total}; use fewer steps or 'trailing' spacing")
        return steps
    if config.timestep_spacing == "trailing":
        return np.round(np.arange(total, 0, -total / n))[:n].astype(np.int64) - 1
    return np.linspace(0, total - 1, n).round()[::-1].astype(np.int64)


def ddim_prev_timesteps(config: SchedulerConfig, num_inference_steps: int) -> np.ndarray:
    """(n,) int64 timestep each DDIM step goes to: t - T // n, as DDIMScheduler.step computes it
    (negative after the last step -> the final ᾱ). With linspace spacing, or trailing when n does
    not divide T, this is not always the next entry of `ddim_timesteps`; diffusers does the same."""
    steps = ddim_timesteps(config, num_inference_steps)
    return steps - config.num_train_timesteps // num_inference_steps


def ddim_step(config: SchedulerConfig, alphas_cumprod: jax.Array, model_output: jax.Array, t,
              prev_t, sample: jax.Array, eta: float = 0.0,
              noise: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """One DDIM update x_t -> x_prev_t; returns (prev_sample, x̂0), both like `sample`.

    `t`, `prev_t`: int scalars (or traced; prev_t < 0 uses the final ᾱ). `eta` in [0, 1] (a
    Python float: 0 = deterministic DDIM, 1 = DDPM-like); eta > 0 needs standard normal `noise`
    shaped like `sample`. x̂0 is clipped to ±clip_sample_range when config.clip_sample.
    """
    if eta > 0 and noise is None:
        raise ValueError("ddim_step with eta > 0 needs `noise` (standard normal, like sample)")
    a_t = alphas_cumprod[t]
    prev_t = jnp.asarray(prev_t)
    a_prev = jnp.where(prev_t >= 0, alphas_cumprod[jnp.maximum(prev_t, 0)],
                       final_alpha_cumprod(config, alphas_cumprod))
    x0 = x0_from_prediction(model_output, sample, a_t, config.prediction_type)
    eps = eps_from_prediction(model_output, sample, a_t, config.prediction_type)
    if config.clip_sample:
        x0 = jnp.clip(x0, -config.clip_sample_range, config.clip_sample_range)
    # σ_t² = (1 - ᾱ_prev) / (1 - ᾱ_t) * (1 - ᾱ_t / ᾱ_prev)   (DDIM eq. 16)
    variance = (1.0 - a_prev) / jnp.maximum(1.0 - a_t, ALPHA_BAR_FLOOR) \
        * (1.0 - a_t / jnp.maximum(a_prev, ALPHA_BAR_FLOOR))
    sigma2 = eta ** 2 * variance
    direction = jnp.sqrt(jnp.maximum(_expand(1.0 - a_prev - sigma2, sample), 0.0)) * eps
    prev = jnp.sqrt(_expand(a_prev, sample)) * x0 + direction
    if eta > 0:
        prev = prev + jnp.sqrt(_expand(sigma2, sample)) * noise
    return prev.astype(sample.dtype), x0.astype(sample.dtype)


def ddim_sample(model_fn: Callable[[jax.Array, jax.Array], jax.Array], x_T: jax.Array,
                config: SchedulerConfig, num_inference_steps: int, eta: float = 0.0,
                key: jax.Array | None = None) -> jax.Array:
    """Runs DDIM from noise `x_T` for `num_inference_steps`; returns the final sample like x_T.

    `model_fn(sample, t)` -> model output like sample, with `t` a traced int32 scalar. The loop
    is one `jax.lax.scan` over the precomputed (t, prev_t) pairs, so it jits; `model_fn`,
    `config`, `num_inference_steps` and `eta` are static (e.g. `jax.jit(ddim_sample,
    static_argnums=(0, 2, 3, 4))`), `x_T` and `key` are traced. eta > 0 needs a PRNG `key`.
    """
    if eta > 0 and key is None:
        raise ValueError("ddim_sample with eta > 0 needs a PRNG key")
    schedule = alphas_cumprod(config)
    steps = jnp.asarray(ddim_timesteps(config, num_inference_steps), jnp.int32)
    prevs = jnp.asarray(ddim_prev_timesteps(config, num_inference_steps), jnp.int32)
    keys = jax.random.split(key, num_inference_steps) if eta > 0 else jnp.zeros(
        (num_inference_steps,), jnp.uint32)

    def body(sample, inputs):
        t, prev_t, step_key = inputs
        noise = jax.random.normal(step_key, sample.shape, sample.dtype) if eta > 0 else None
        prev, _ = ddim_step(config, schedule, model_fn(sample, t), t, prev_t, sample, eta, noise)
        return prev, None

    final, _ = jax.lax.scan(body, x_T, (steps, prevs, keys))
    return final
