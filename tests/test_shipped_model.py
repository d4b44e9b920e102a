"""The RGB<->X-family model shipped in the package (jaxdistill/models/rgbx_rooms): a diffusers
folder that diffusers and transformers load to the networks ours computes, small, documented,
and better than the trivial baseline on a held-out room it never saw."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdistill.models import convert, shipped
from jaxdistill.models import prior as rgbx
from jaxdistill.models.tokenizer import MAP_PROMPTS

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "tests" / "data" / "rgbx_heldout_sample.npz"      # 4 images of 2 held-out rooms (make_rgbx_data)


@pytest.fixture(scope="module")
def folder():
    folder = shipped.shipped_folder()
    assert folder is not None, "the package must ship jaxdistill/models/rgbx_rooms (scripts/train_rgbx.py)"
    return folder


@pytest.fixture(scope="module")
def loaded(folder):
    return convert.load_rgbx(folder)


def test_the_shipped_folder_is_small_and_documented(folder):
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    assert size < 8 * 2**20, f"{size / 2**20:.1f} MiB"
    info = json.loads((folder / shipped.INFO_FILE).read_text())
    assert info["name"] == "jaxdistill-rgbx-rooms" and info["command"].startswith("python scripts/train_rgbx.py")
    card = (folder / "README.md").read_text()
    for needed in ("scripts/make_rgbx_data.py", "scripts/train_rgbx.py", "held-out", "not a general estimator"):
        assert needed in card
    assert shipped.model_info(folder)["source"] == "shipped"


def test_parameter_shapes_are_read_from_a_file_keyed_by_the_networks(folder, tmp_path, monkeypatch):
    """`convert.abstract_params` traces the three inits once per machine: a new process reads the
    shapes from a file whose name follows the networks' configuration (and sources, JAX and
    Flax), beside JAX's compilation cache or else in $JAXDISTILL_CACHE/param_shapes; a damaged file
    is traced again and replaced."""
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path))
    previous = jax.config.jax_compilation_cache_dir
    try:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "xla"))
        assert convert.shapes_folder() == tmp_path / "xla" / "jaxdistill-param-shapes"
        jax.config.update("jax_compilation_cache_dir", None)
        assert convert.shapes_folder() == tmp_path / "param_shapes"
        _shapes_are_read_from_their_file(folder, tmp_path, monkeypatch)
    finally:
        jax.config.update("jax_compilation_cache_dir", previous)


def _shapes_are_read_from_their_file(folder, tmp_path, monkeypatch):
    networks = convert.build_networks(folder)
    path = convert._shapes_file(networks, False)
    assert path.parent == tmp_path / "param_shapes" and not path.exists()
    convert._abstract_params.cache_clear()                 # as a new process
    traced = convert.abstract_params(networks)             # traced (no file yet), and written
    assert path.is_file()

    def same(tree):
        return jax.tree.structure(tree) == jax.tree.structure(traced) and all(
            (a.shape, a.dtype) == (b.shape, b.dtype) for a, b in zip(jax.tree.leaves(tree), jax.tree.leaves(traced)))

    def poisoned(_):
        raise AssertionError("traced although the shapes were in the file")

    with monkeypatch.context() as m:
        m.setattr(convert, "_trace_params", poisoned)
        convert._abstract_params.cache_clear()
        assert same(convert.abstract_params(networks))
    assert len({path, convert._shapes_file(networks, True), convert._shapes_file(convert.build_networks(
        folder, dtype=jnp.bfloat16), False)}) == 3
    with monkeypatch.context() as m:
        m.setattr(convert, "_NETWORK_SOURCES", convert._NETWORK_SOURCES[:-1])
        assert convert._shapes_file(networks, False) != path
    for damaged in ('{"unet": null}', '[[1], "float32"]', '{"unet": {}, "vae": {}}'):       # parse, but wrong
        path.write_text(damaged)
        assert convert._read_shapes(path) is None
    path.write_text('{"unet": [')
    convert._abstract_params.cache_clear()
    assert same(convert.abstract_params(networks)) and same(convert._read_shapes(path))
    convert._abstract_params.cache_clear()


def test_shapes_traced_ahead_are_traced_once_and_a_bad_folder_is_left_to_the_loader(folder, tmp_path, monkeypatch):
    """`convert.trace_ahead` traces in a thread of its own; `abstract_params` of the same networks
    waits for that trace instead of tracing again, and gets the same shapes; a folder that cannot be
    read raises nothing in the thread (`load_rgbx` checks it and says what is wrong)."""
    import threading

    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path))
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)        # the shapes' file in tmp_path, not there yet
    traces, started, release = [], threading.Event(), threading.Event()
    escaped = []                               # an exception out of the thread (pytest only warns of those)
    monkeypatch.setattr(threading, "excepthook", lambda args: escaped.append(args.exc_value))
    trace = convert._trace_params

    def slow_trace(networks):
        traces.append(threading.current_thread().name)
        started.set()
        release.wait(30)                       # the loader asks while the thread still traces
        return trace(networks)

    monkeypatch.setattr(convert, "_trace_params", slow_trace)
    convert._abstract_params.cache_clear()
    try:
        thread = convert.trace_ahead(folder)
        assert started.wait(30)
        asked = threading.Timer(0.2, release.set)
        asked.start()
        shapes = convert.abstract_params(convert.build_networks(folder))
        thread.join(30)
        assert traces == ["trace-param-shapes"]                       # once, in the thread
        assert jax.tree.structure(shapes) == jax.tree.structure(trace(convert.build_networks(folder)))
        bad = convert.trace_ahead(tmp_path / "no_such_folder")
        bad.join(30)
        assert not bad.is_alive() and traces == ["trace-param-shapes"] and not escaped
    finally:
        release.set()
        jax.config.update("jax_compilation_cache_dir", previous)
        convert._abstract_params.cache_clear()


def test_diffusers_and_transformers_agree_with_ours_on_the_shipped_folder(folder, loaded):
    torch = pytest.importorskip("torch")
    diffusers = pytest.importorskip("diffusers")
    transformers = pytest.importorskip("transformers")
    from tiny_rgbx import nchw, nhwc, rel_err

    nets, params = loaded.networks, loaded.params
    rng = np.random.default_rng(0)
    sample = rng.standard_normal((2, 12, 16, 8)).astype(np.float32)
    t = np.array([20.0, 950.0], np.float32)
    context = rng.standard_normal((2, 77, nets.unet.config.cross_attention_dim)).astype(np.float32)
    unet = diffusers.UNet2DConditionModel.from_pretrained(folder / "unet", torch_dtype=torch.float32).eval()
    with torch.no_grad():
        ref = unet(torch.from_numpy(nchw(sample)), torch.from_numpy(t), torch.from_numpy(context)).sample.numpy()
    assert rel_err(jax.jit(nets.unet.apply)(params["unet"], sample, t, context), nhwc(ref)) < 1e-5

    images = rng.uniform(-1, 1, (1, 96, 128, 3)).astype(np.float32)
    vae = diffusers.AutoencoderKL.from_pretrained(folder / "vae", torch_dtype=torch.float32).eval()
    with torch.no_grad():
        mean_ref = vae.encode(torch.from_numpy(nchw(images))).latent_dist.mean
        decoded_ref = vae.decode(mean_ref).sample.numpy()
    mean, _ = jax.jit(partial(nets.vae.apply, method="encode"))(params["vae"], images)
    assert rel_err(mean, nhwc(mean_ref.numpy())) < 1e-5
    assert rel_err(jax.jit(partial(nets.vae.apply, method="decode"))(params["vae"], mean), nhwc(decoded_ref)) < 1e-5

    model = rgbx.load_prior(loaded)
    prompts = list(MAP_PROMPTS.values())
    ids = model.tokenizer.encode(prompts)
    tok = transformers.CLIPTokenizer.from_pretrained(folder / "tokenizer")
    assert tok(prompts, padding="max_length", max_length=77).input_ids == np.asarray(ids).tolist()
    text = transformers.CLIPTextModel.from_pretrained(folder / "text_encoder", torch_dtype=torch.float32).eval()
    with torch.no_grad():
        hidden = text(torch.from_numpy(np.asarray(ids, np.int64))).last_hidden_state.numpy()
    assert rel_err(jax.jit(nets.text_encoder.apply)(params["text_encoder"], jnp.asarray(ids)), hidden) < 1e-5
    # the five prompts and "" must be told apart, or text guidance (eq. 4.2) means nothing
    emb = np.stack([np.asarray(model.text[m].prompt[0]) for m in MAP_PROMPTS] + [np.asarray(model.text["albedo"].empty[0])])
    dist = np.linalg.norm((emb[:, None] - emb[None]).reshape(6, 6, -1), axis=-1)
    assert dist[~np.eye(6, dtype=bool)].min() > 1e-3 * np.abs(emb).max()


def test_estimates_beat_the_trivial_baseline_on_held_out_rooms(loaded):
    """On rooms the model never saw, its per-view estimates (the demo's 50 DDIM steps) beat the
    photo taken as albedo in PSNR and facing-the-camera normals in angle. (The shipped v1 measures
    +1.0 dB over the photo in albedo on 40 held-out images, see its card.)"""
    from jaxdistill.evaluate import metrics
    from jaxdistill.models.training.heldout import shard_ground_truth, to_file_space, trivial

    model = rgbx.load_prior(loaded)
    with np.load(SAMPLE) as z:
        photos = z["photo"].astype(np.float32) / 255.0
        gts = [shard_ground_truth(z, i) for i in range(len(photos))]
        valid = z["valid"][..., 0] > 0
    latents = np.concatenate([np.asarray(rgbx.encode_photo(model, p)) for p in photos])
    key = jax.random.key(0)
    ours, base = [], []
    pred = {}
    for m in ("albedo", "normal"):
        noise = np.concatenate([np.asarray(jax.random.normal(rgbx.view_map_key(key, f"{i}", m), (1,) + latents.shape[1:]))
                                for i in range(len(photos))])
        pred[m] = [to_file_space(m, x) for x in rgbx.estimate_batch(model, latents, m, noise, 50, gamma=False)]
    for i, gt in enumerate(gts):
        gt = {m: gt[m] for m in ("albedo", "normal")}
        ours.append(metrics.evaluate_view({m: pred[m][i] for m in gt}, gt, valid[i]))
        base.append(metrics.evaluate_view({m: trivial(photos[i])[m] for m in gt}, gt, valid[i]))
    ours, base = metrics.aggregate(ours), metrics.aggregate(base)
    assert ours["albedo_psnr"] > base["albedo_psnr"], (ours["albedo_psnr"], base["albedo_psnr"])
    assert ours["normal_angular_deg"] < base["normal_angular_deg"], (ours, base)
