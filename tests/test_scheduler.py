"""DDIM maths against diffusers' DDIMScheduler (fp32), plus config reading and edge cases."""

from __future__ import annotations

import inspect
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill.errors import InputError
from jaxdistill.models import scheduler as sch

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")

TOL = 1e-5
SD = dict(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012)
# the RGB<->X demo setting (SD 2.1 scheduler with the zero-SNR / trailing overrides)
RGBX = dict(SD, prediction_type="v_prediction", num_train_timesteps=1000, set_alpha_to_one=False,
            steps_offset=1, rescale_betas_zero_snr=True, timestep_spacing="trailing",
            clip_sample=False)


def rel_err(a, b) -> float:
    """max|a - b| / max|b|."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / np.abs(b).max())


def pair(**kw):
    """(our SchedulerConfig, diffusers DDIMScheduler) with the same settings."""
    return sch.SchedulerConfig(**kw), diffusers.DDIMScheduler(**kw)


def rng_arrays(*shapes, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.standard_normal(s).astype(np.float32) for s in shapes]


# ----------------------------------------------------------------------------- schedule


@pytest.mark.parametrize("zero_snr", [False, True])
@pytest.mark.parametrize("schedule", [dict(SD), dict(beta_schedule="linear")])
def test_betas_and_alphas_cumprod(schedule, zero_snr):
    ours, ref = pair(**schedule, rescale_betas_zero_snr=zero_snr)
    assert rel_err(sch.betas(ours), ref.betas.numpy()) <= TOL
    a = sch.alphas_cumprod(ours)
    assert a.dtype == jnp.float32 and rel_err(a, ref.alphas_cumprod.numpy()) <= TOL
    assert (float(a[-1]) == 0.0) == zero_snr
    for one in (True, False):
        cfg, r = pair(**schedule, rescale_betas_zero_snr=zero_snr, set_alpha_to_one=one)
        assert float(sch.final_alpha_cumprod(cfg, a)) == pytest.approx(float(r.final_alpha_cumprod))


@pytest.mark.parametrize("spacing", sch.TIMESTEP_SPACINGS)
@pytest.mark.parametrize("steps", [50, 20, 10, 1])
def test_timesteps(spacing, steps):
    ours, ref = pair(timestep_spacing=spacing, steps_offset=1)
    ref.set_timesteps(steps)
    got = sch.ddim_timesteps(ours, steps)
    assert got.dtype == np.int64 and got.tolist() == ref.timesteps.tolist()
    prev = sch.ddim_prev_timesteps(ours, steps)
    assert (got - prev == 1000 // steps).all()


def test_timesteps_all_step_counts():
    """Every n in [1, 1000]; where diffusers' trailing float arange gives n + 1 timesteps (the
    extra one is -1) ours are its first n."""
    extra = 0
    for spacing in sch.TIMESTEP_SPACINGS:
        ours, ref = pair(timestep_spacing=spacing)
        for n in range(1, 1001):
            ref.set_timesteps(n)
            want = ref.timesteps.tolist()
            extra += len(want) - n
            assert sch.ddim_timesteps(ours, n).tolist() == want[:n], (spacing, n)
    assert extra == 62  # e.g. n = 61 (diffusers then indexes alphas_cumprod[-1])


def test_timesteps_errors():
    cfg = sch.SchedulerConfig()
    for n in (0, 1001, 2.0):
        with pytest.raises(InputError, match="num_inference_steps"):
            sch.ddim_timesteps(cfg, n)
    with pytest.raises(InputError, match="reach timestep 1000"):
        sch.ddim_timesteps(sch.SchedulerConfig(steps_offset=1), 1000)


# ----------------------------------------------------------------------------- single steps


def ref_step(ref, n, out, t, x, **kw):
    ref.set_timesteps(n)
    r = ref.step(torch.from_numpy(out), t, torch.from_numpy(x), **kw)
    return r.prev_sample.numpy(), r.pred_original_sample.numpy()


@pytest.mark.parametrize("zero_snr", [False, True])
@pytest.mark.parametrize("prediction", ["v_prediction", "epsilon", "sample"])
@pytest.mark.parametrize("spacing, t", [("trailing", 999), ("trailing", 499), ("leading", 501),
                                        ("leading", 21), ("leading", 1)])
def test_single_step(prediction, zero_snr, spacing, t):
    n = 50
    if prediction == "epsilon" and zero_snr and t == 999:
        pytest.skip("diffusers divides by sqrt(ᾱ_999) = 0 here (see test_zero_snr_first_step_finite)")
    kw = dict(SD, prediction_type=prediction, rescale_betas_zero_snr=zero_snr, steps_offset=1,
              timestep_spacing=spacing, set_alpha_to_one=False, clip_sample=prediction == "sample")
    ours, ref = pair(**kw)
    out, x = rng_arrays((2, 4, 8, 8), (2, 4, 8, 8))
    want_prev, want_x0 = ref_step(ref, n, out, t, x)
    prev, x0 = sch.ddim_step(ours, sch.alphas_cumprod(ours), jnp.asarray(out), t, t - 1000 // n,
                             jnp.asarray(x))
    assert rel_err(prev, want_prev) <= TOL and rel_err(x0, want_x0) <= TOL


@pytest.mark.parametrize("prediction", ["v_prediction", "epsilon"])
def test_single_step_eta(prediction):
    ours, ref = pair(**SD, prediction_type=prediction, clip_sample=False, set_alpha_to_one=False)
    out, x, noise = rng_arrays((1, 4, 8, 8), (1, 4, 8, 8), (1, 4, 8, 8), seed=1)
    want, _ = ref_step(ref, 20, out, 451, x, eta=0.7, variance_noise=torch.from_numpy(noise))
    got, _ = sch.ddim_step(ours, sch.alphas_cumprod(ours), out, 451, 401, x, eta=0.7, noise=noise)
    assert rel_err(got, want) <= TOL
    with pytest.raises(ValueError, match="needs `noise`"):
        sch.ddim_step(ours, sch.alphas_cumprod(ours), out, 451, 401, x, eta=0.7)


def test_zero_snr_first_step_finite():
    """At ᾱ = 0 (t = 999, zero SNR) and ᾱ = 1 every conversion and step stays finite."""
    x, out = (jnp.asarray(a) for a in rng_arrays((4, 8), (4, 8)))
    for alpha_bar in (0.0, 1.0):
        for kind in sch.PREDICTION_TYPES:
            assert jnp.isfinite(sch.x0_from_prediction(out, x, alpha_bar, kind)).all()
            assert jnp.isfinite(sch.eps_from_prediction(out, x, alpha_bar, kind)).all()
        assert jnp.isfinite(sch.v_from_x0_eps(x, out, alpha_bar)).all()
        assert jnp.isfinite(sch.add_noise(x, out, alpha_bar)).all()
    for kind in sch.PREDICTION_TYPES:
        cfg = sch.SchedulerConfig(**{**RGBX, "prediction_type": kind})
        a = sch.alphas_cumprod(cfg)
        assert float(a[999]) == 0.0
        prev, x0 = sch.ddim_step(cfg, a, out, 999, 899, x, eta=1.0, noise=out)
        assert jnp.isfinite(prev).all() and jnp.isfinite(x0).all()


def test_conversions_round_trip():
    x0, eps = (jnp.asarray(a) for a in rng_arrays((3, 5, 2), (3, 5, 2), seed=2))
    alpha_bar = jnp.asarray([0.9, 0.3, 0.01], jnp.float32)  # per batch element
    x_t = sch.add_noise(x0, eps, alpha_bar)
    for kind in sch.PREDICTION_TYPES:
        pred = sch.prediction_from_x0_eps(x0, eps, alpha_bar, kind)
        np.testing.assert_allclose(sch.x0_from_prediction(pred, x_t, alpha_bar, kind), x0, atol=2e-4)
        np.testing.assert_allclose(sch.eps_from_prediction(pred, x_t, alpha_bar, kind), eps, atol=2e-4)
    ref = diffusers.DDIMScheduler()
    t = torch.tensor([10, 500, 990])
    a = sch.alphas_cumprod(sch.SchedulerConfig())[t.numpy()]
    x0_t, eps_t = torch.tensor(np.array(x0)), torch.tensor(np.array(eps))
    want_v, want_x = ref.get_velocity(x0_t, eps_t, t), ref.add_noise(x0_t, eps_t, t)
    assert rel_err(sch.v_from_x0_eps(x0, eps, a), want_v.numpy()) <= TOL
    assert rel_err(sch.add_noise(x0, eps, a), want_x.numpy()) <= TOL


# ----------------------------------------------------------------------------- trajectories


def linear_model(sample, t):
    """A fixed model_fn, the same formula in torch and jax: a(t) sample + b(t)."""
    tf = t / 1000.0
    return sample * (0.4 + 0.5 * tf) - 0.1 * tf + 0.05


def ref_sample(ref, x_T, n):
    ref.set_timesteps(n)
    x = torch.from_numpy(x_T)
    for t in ref.timesteps:
        x = ref.step(linear_model(x, t.to(torch.float32)), t, x).prev_sample
    return x.numpy()


@pytest.mark.parametrize("case", [
    dict(RGBX),
    dict(RGBX, rescale_betas_zero_snr=False),
    dict(RGBX, timestep_spacing="leading"),
    dict(RGBX, timestep_spacing="leading", rescale_betas_zero_snr=False),
    dict(RGBX, timestep_spacing="linspace"),
    dict(RGBX, prediction_type="epsilon", rescale_betas_zero_snr=False),
    dict(RGBX, prediction_type="epsilon", timestep_spacing="leading"),
], ids=["rgbx", "trailing", "leading-zsnr", "leading", "linspace-zsnr", "eps-trailing", "eps-leading-zsnr"])
def test_trajectory(case):
    n = 10
    ours, ref = pair(**case)
    (x_T,) = rng_arrays((1, 4, 8, 8), seed=3)
    want = ref_sample(ref, x_T, n)
    run = jax.jit(sch.ddim_sample, static_argnums=(0, 2, 3))
    model = lambda x, t: linear_model(x, t.astype(jnp.float32))  # noqa: E731
    got = run(model, jnp.asarray(x_T), ours, n)
    assert got.shape == x_T.shape and got.dtype == jnp.float32
    assert rel_err(got, want) <= TOL


def test_sample_with_eta_needs_key_and_is_seeded():
    cfg = sch.SchedulerConfig(**RGBX)
    x = jnp.ones((2, 3))
    model = lambda s, t: 0.1 * s  # noqa: E731
    with pytest.raises(ValueError, match="PRNG key"):
        sch.ddim_sample(model, x, cfg, 4, eta=1.0)
    run = jax.jit(sch.ddim_sample, static_argnums=(0, 2, 3, 4))
    a, b, c = (run(model, x, cfg, 4, 1.0, jax.random.key(seed)) for seed in (0, 0, 1))
    assert jnp.isfinite(a).all() and (a == b).all() and (a != c).any()


# ----------------------------------------------------------------------------- config files


def write_config(tmp_path, **values):
    folder = tmp_path / "scheduler"
    folder.mkdir(exist_ok=True)
    base = {"_class_name": "DDIMScheduler", "_diffusers_version": "0.8.0", "beta_end": 0.012,
            "beta_schedule": "scaled_linear", "beta_start": 0.00085, "clip_sample": False,
            "num_train_timesteps": 1000, "prediction_type": "v_prediction",
            "set_alpha_to_one": False, "skip_prk_steps": True, "steps_offset": 1,
            "trained_betas": None}
    (folder / "scheduler_config.json").write_text(json.dumps(base | values))
    return folder / "scheduler_config.json"


def test_read_config_matches_diffusers(tmp_path):
    path = write_config(tmp_path)
    cfg = sch.read_scheduler_config(tmp_path, rescale_betas_zero_snr=True, timestep_spacing="trailing")
    assert cfg == sch.SchedulerConfig(**RGBX)
    assert sch.read_scheduler_config(path.parent) == sch.read_scheduler_config(path)
    # what DDIMScheduler.from_config keeps: its own settings, defaults for the absent ones
    known = inspect.signature(diffusers.DDIMScheduler).parameters
    ref = diffusers.DDIMScheduler(**{k: v for k, v in json.loads(path.read_text()).items() if k in known})
    mine = sch.read_scheduler_config(tmp_path)
    assert {k: ref.config[k] for k in sch._FIELDS} == vars(mine)


@pytest.mark.parametrize("field, value, message", [
    ("beta_schedule", "squaredcos_cap_v2", "beta_schedule: must be one of linear, scaled_linear"),
    ("prediction_type", "flow", "prediction_type: must be one of"),
    ("thresholding", True, "thresholding: dynamic thresholding is not supported"),
    ("timestep_spacing", "karras", "timestep_spacing: must be one of"),
    ("trained_betas", [0.1, 0.2], "trained_betas: explicit trained_betas"),
    ("steps_offset", -1, "steps_offset: must be an integer"),
])
def test_read_config_errors(tmp_path, field, value, message):
    path = write_config(tmp_path, **{field: value})
    with pytest.raises(InputError, match=message) as err:
        sch.read_scheduler_config(tmp_path)
    assert err.value.problems[0][0] == str(path)


def test_read_config_missing_and_bad_json(tmp_path):
    with pytest.raises(InputError, match="scheduler_config.json.*missing"):
        sch.read_scheduler_config(tmp_path)
    write_config(tmp_path).write_text("{")
    with pytest.raises(InputError, match="not valid JSON"):
        sch.read_scheduler_config(tmp_path)
    write_config(tmp_path)
    with pytest.raises(InputError, match="overrides: timestep_spacing"):
        sch.read_scheduler_config(tmp_path, timestep_spacing="middle")
    with pytest.raises(TypeError, match="unknown scheduler setting"):
        sch.read_scheduler_config(tmp_path, spacing="trailing")
