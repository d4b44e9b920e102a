"""Which rgbx weights a run uses (the user's, else the shipped model) and the model's own
per-view estimates that an rgbx run is scored against (batched, cached)."""

from __future__ import annotations

import hashlib
import json

import jax
import numpy as np
import pytest

from jaxdistill import estimate
from jaxdistill.io import images as imageio
from jaxdistill.models import estimates as model_estimates
from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.models import convert, layers, shipped
from jaxdistill.models import prior as rgbx
from jaxdistill.engine.problem import choose_prior
from jaxdistill.scene.model import read_scene
from tiny_scene import write_tiny_scene


@pytest.fixture
def no_env(monkeypatch):
    monkeypatch.delenv("JAXDISTILL_RGBX_DIR", raising=False)


def test_user_weights_come_first_then_the_shipped_model(rgbx_dir, tmp_path, monkeypatch, no_env):
    fake = tmp_path / "shipped"
    fake.mkdir()
    (fake / "model_index.json").write_text("{}")
    monkeypatch.setattr(shipped, "SHIPPED_DIR", fake)
    for prior in ("auto", "rgbx"):
        choice = choose_prior(DistillConfig(scene="s", out_dir="o", prior=prior, rgbx_dir=str(rgbx_dir)))
        assert (choice.kind, choice.folder) == ("rgbx", str(rgbx_dir))
        choice = choose_prior(DistillConfig(scene="s", out_dir="o", prior=prior))
        assert (choice.kind, choice.folder) == ("rgbx", str(fake))
        assert "shipped" in choice.reason and "huggingface-cli download zheng95z/rgb-to-x" in choice.reason
    assert choose_prior(DistillConfig(scene="s", out_dir="o", prior="views", rgbx_dir=str(rgbx_dir))).kind == "views"
    with pytest.raises(InputError, match="--rgbx_dir.*does not exist"):      # never a silent fallback
        choose_prior(DistillConfig(scene="s", out_dir="o", rgbx_dir=str(tmp_path / "nowhere")))


def test_without_a_shipped_model_auto_fuses_views_and_rgbx_says_how_to_get_weights(tmp_path, monkeypatch, no_env):
    monkeypatch.setattr(shipped, "SHIPPED_DIR", tmp_path / "absent")
    assert shipped.shipped_folder() is None
    assert choose_prior(DistillConfig(scene="s", out_dir="o")).kind == "views"
    with pytest.raises(InputError, match="--prior=rgbx.*no shipped model.*huggingface-cli download"):
        choose_prior(DistillConfig(scene="s", out_dir="o", prior="rgbx"))


def test_model_info_names_user_and_shipped_weights(rgbx_dir):
    assert shipped.model_info(rgbx_dir) == {"name": "rgb-to-x", "source": "user", "folder": str(rgbx_dir)}
    folder = shipped.shipped_folder()
    if folder is not None:
        info = shipped.model_info(folder)
        assert info["source"] == "shipped" and info["name"] and info["version"]


def test_batched_cached_estimates_equal_the_estimate_command(run_rgbx_dir, tmp_path, monkeypatch):
    """The baseline of an rgbx run is what `python -m jaxdistill.estimate` writes for each view
    (same noise per view and map), computed once per (weights, photos, size, settings). On the run-sized
    tiny model: what is tested is the batching and the cache, not the networks' structure."""
    scene = read_scene(write_tiny_scene(tmp_path / "scene", views=3, width=32, height=24))
    photos = [(v.name, v.photo, v.exposure) for v in scene.views]
    maps = ("albedo", "normal", "roughness")
    model = rgbx.load_prior(convert.load_rgbx(run_rgbx_dir))
    cache = tmp_path / "cache"
    folder = model_estimates.cached_estimates(model, photos, maps, 24, 32, steps=4, seed=3, cache_dir=cache,
                                              progress=False)
    reference = tmp_path / "cli"
    estimate.run(estimate.EstimateConfig(prior_dir=str(run_rgbx_dir), out_dir=str(reference), scene=str(scene.root),
                                         maps=maps, steps=4, seed=3))
    for name, _, _ in photos:
        for m in maps:
            ours = imageio.read_image(folder / m / f"{name}.png", linear=False)
            theirs = imageio.read_image(reference / m / f"{name}.png", linear=False)
            assert ours.shape == theirs.shape == (24, 32, 3)
            # batch of 3 vs batch of 1: float differences may flip a few 8-bit roundings
            assert np.max(np.abs(ours - theirs)) <= 2.5 / 255 and np.mean(np.abs(ours - theirs)) < 0.1 / 255
    read = model_estimates.read_estimates(folder, [p[0] for p in photos], maps, [(48, 64)] * 3)
    assert read[0]["albedo"].shape == (48, 64, 3) and read[0]["roughness"].shape == (48, 64, 1)
    # normals come back as vectors (files hold (n + 1) / 2), as the scene's targets do
    assert read[1]["normal"].min() >= -1.0 and read[1]["normal"].max() <= 1.0 and read[1]["normal"].min() < 0.0

    def recompute(*args, **kwargs):
        raise AssertionError("the cached estimates were computed again")

    monkeypatch.setattr(model_estimates, "estimate_views", recompute)
    again = model_estimates.cached_estimates(model, photos, maps[:2], 24, 32, steps=4, seed=3, cache_dir=cache,
                                             progress=False)
    assert again == folder
    with pytest.raises(AssertionError, match="computed again"):      # another seed is another baseline
        model_estimates.cached_estimates(model, photos, maps, 24, 32, steps=4, seed=4, cache_dir=cache, progress=False)


def test_estimates_in_padded_batches_of_mixed_maps_equal_one_batch_of_each_map(run_rgbx_dir, tmp_path, monkeypatch):
    """The (map, view) pairs go through the sampler in batches of one size that mix maps (each
    sample with its own prompt), the last batch padded: every call has the same shapes, so one
    compiled program, and each view's estimate of each map is the one a batch of that map alone
    gives (through the same list-of-names call; the single-name call is compared with the CLI's
    estimates above)."""
    scene = read_scene(write_tiny_scene(tmp_path / "scene", views=3, width=32, height=24))
    photos = [(v.name, v.photo, v.exposure) for v in scene.views]
    maps = ("albedo", "roughness", "irradiance")
    model = rgbx.load_prior(convert.load_rgbx(run_rgbx_dir))
    latents = np.concatenate([np.asarray(rgbx.encode_photo(model, imageio.read_photo_srgb(p, e))) for _, p, e in photos])
    calls, sample = [], rgbx.estimate_batch

    def spy(prior, image_latents, map_name, x_T, *args, **kwargs):
        calls.append((len(x_T), list(map_name)))
        return sample(prior, image_latents, map_name, x_T, *args, **kwargs)

    monkeypatch.setattr(rgbx, "estimate_batch", spy)
    model_estimates.estimate_views(model, photos, maps, 24, 32, tmp_path / "est", steps=2, seed=3, progress=False,
                                   max_batch=5)
    # 9 pairs, at most 5 a call: two calls of 5, the maps meeting inside each, the last repeating its last pair
    assert calls == [(5, ["albedo"] * 3 + ["roughness"] * 2), (5, ["roughness"] + ["irradiance"] * 4)]
    key = jax.random.key(3)
    for m in maps:      # the reference: one call per map, its views padded to the same 5 (one program)
        noise = np.concatenate([np.asarray(jax.random.normal(rgbx.view_map_key(key, n, m), (1,) + latents.shape[1:]))
                                for n, _, _ in photos])
        rows = [0, 1, 2, 2, 2]
        alone = sample(model, latents[rows], [m] * 5, noise[rows], 2, gamma=False)[:3]
        for (name, _, _), image in zip(photos, alone):
            ours = imageio.read_image(tmp_path / "est" / m / f"{name}.png", linear=False)
            theirs = imageio.linear_to_srgb(image) if m in rgbx.GAMMA_MAPS else image
            assert ours.shape == (24, 32, 3)
            # 8-bit files against floats: half a level, plus a level where batching flips a rounding
            assert np.max(np.abs(ours - theirs)) <= 1.5 / 255, (m, name)
    # a wrong prompt would show: the same photos and noise under two prompts that convert alike differ
    # by far more than the tolerance
    rows, noise = [0, 1, 2, 2, 2], np.asarray(jax.random.normal(key, (5,) + latents.shape[1:]))
    by_prompt = [sample(model, latents[rows], [m] * 5, noise, 2, gamma=False) for m in ("albedo", "irradiance")]
    assert np.max(np.abs(by_prompt[0] - by_prompt[1])) > 6 / 255          # 20 / 255 here


def test_programs_compiled_ahead_are_the_ones_the_estimates_run(run_rgbx_dir, tmp_path):
    """`compile_ahead` (run in a thread beside the loop) lowers the sampling and decoding programs
    with arguments of the kinds `estimate_views` passes: the estimates then compile neither (JAX's
    backend-compile events, by program), while another batch size compiles both. JAX's caches are
    cleared first: another test of this process may have compiled the same programs."""
    scene = read_scene(write_tiny_scene(tmp_path / "scene", views=3, width=32, height=24))
    photos = [(v.name, v.photo, v.exposure) for v in scene.views]
    maps = ("albedo", "irradiance")
    model = rgbx.load_prior(convert.load_rgbx(run_rgbx_dir))
    compiled = []

    def listen(event, seconds, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.extend(name for name in ("_sample", "decode_latents") if name in kwargs.get("fun_name", ""))

    jax.clear_caches()
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        model_estimates.compile_ahead(model, maps, len(photos), 24, 32, steps=2, max_batch=4)
        assert sorted(compiled) == ["_sample", "decode_latents"]
        compiled.clear()
        model_estimates.estimate_views(model, photos, maps, 24, 32, tmp_path / "est", steps=2, progress=False,
                                       max_batch=4)
        assert compiled == []                                    # found in the cache
        model_estimates.estimate_views(model, photos, maps, 24, 32, tmp_path / "est6", steps=2, progress=False,
                                       max_batch=6)        # one call of 6 pairs, not two of 3
        assert sorted(compiled) == ["_sample", "decode_latents"]     # the check can fail
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_estimate_batches_are_as_few_and_as_even_as_the_cap_allows():
    """The shipped model's 16 x 12 latents: 48 pairs a call (the bedroom's 48 views x 5 maps in 5
    calls), 24 views x 5 maps in 3 calls of 40 (not 48 + 48 + 24 padded to 48), fewer pairs in
    one call; large latents at least 16 a call (the earlier fixed batch)."""
    size = model_estimates.batch_size
    assert [size(16 * 12, n) for n in (240, 120, 50, 20, 1)] == [48, 40, 25, 20, 1]
    assert size(64 * 48, 240) == size(32 * 24, 240) == 16 and size(64 * 48, 20) == 10
    assert size(16 * 12, 9, cap=5) == 5 and size(16 * 12, 240, cap=16) == 16      # a cap given: 2 calls; 15 calls


def test_concurrent_runs_sharing_the_cache_never_mix_their_folders(tmp_path, monkeypatch):
    """Each run writes its estimates into a folder of its own (named by its pid) and renames it
    into place: a run that finds the same entry finished by another run meanwhile keeps that
    one; an entry holding fewer maps is replaced whole; no temporary folder is left behind."""
    import json
    import os
    import types

    weights = tmp_path / "model"
    weights.mkdir()
    (weights / "model_index.json").write_text("{}")
    photo = tmp_path / "view_0.png"
    photo.write_bytes(b"not read by the fake")
    photos = [("view_0", photo, 0.0)]
    unet = types.SimpleNamespace(chunk_size=layers.DEFAULT_ATTENTION_CHUNK)         # what the cache key reads
    networks = types.SimpleNamespace(unet=unet)
    model = types.SimpleNamespace(loaded=types.SimpleNamespace(folder=weights, networks=networks))
    cache = tmp_path / "cache"
    calls = []

    def fake_estimate_views(model, photos, maps, height, width, folder, **kwargs):
        assert folder.name.endswith(f".{os.getpid()}.tmp")
        folder.mkdir(parents=True)
        (folder / "estimate.json").write_text(json.dumps({"maps": list(maps), "by": "this run"}))
        calls.append(tuple(maps))
        if other is not None:           # another run renames its finished entry into place meanwhile
            final = cache / folder.name.split(".")[0]
            final.mkdir(parents=True)
            (final / "estimate.json").write_text(json.dumps({"maps": list(other), "by": "the other run"}))
        return {"seconds": 0.0}

    monkeypatch.setattr(model_estimates, "estimate_views", fake_estimate_views)
    other = ("albedo", "normal")
    folder = model_estimates.cached_estimates(model, photos, ["albedo"], 24, 32, cache_dir=cache, progress=False)
    assert json.loads((folder / "estimate.json").read_text())["by"] == "the other run"
    other = None                        # a later run wants one more map than the entry has: replaced whole
    again = model_estimates.cached_estimates(model, photos, ["albedo", "roughness"], 24, 32, cache_dir=cache,
                                             progress=False)
    assert again == folder and json.loads((folder / "estimate.json").read_text()) == {
        "maps": ["albedo", "roughness"], "by": "this run"}
    assert calls == [("albedo",), ("albedo", "roughness")]
    assert sorted(p.name for p in cache.iterdir()) == [folder.name]


def test_cache_key_names_the_fused_attention_only_when_it_is_used(tmp_path):
    """Estimates made with cuDNN's fused attention differ from the chunked ones by bf16 rounding, so
    they get their own key; the chunked key is the one made before that option existed."""
    weights = tmp_path / "weights"
    weights.mkdir()
    (weights / "model_index.json").write_text("{}")
    photo = tmp_path / "view_0.png"
    photo.write_bytes(b"x")
    args = (weights, [("view_0", photo, 0.0)], 24, 32, 4, 3, "bfloat16")
    chunked = model_estimates.cache_key(*args)
    assert model_estimates.cache_key(*args, "chunked") == chunked != model_estimates.cache_key(*args, "cudnn")
    settings = {"v": 1, "size": [24, 32], "steps": 4, "seed": 3, "dtype": "bfloat16"}      # the key's first bytes
    h = hashlib.sha256(json.dumps(settings).encode())
    st = (weights / "model_index.json").stat()
    h.update(f"model_index.json:{st.st_size}:{st.st_mtime_ns}".encode())
    st = photo.stat()
    h.update(f"view_0:{photo.resolve()}:{st.st_size}:{st.st_mtime_ns}:0.0".encode())
    assert chunked == h.hexdigest()[:20]


def test_auto_estimate_steps_are_the_shipped_models_own_and_the_demos_otherwise(tmp_path):
    """--estimate_steps=0 (auto): 10 for the shipped model (chosen on the validation rooms), the
    RGB↔X demo's 50 for weights a user brings and for a model a user trained with our scripts
    (its info file, in another folder): nothing was measured for those."""
    import shutil

    from jaxdistill.models import shipped

    assert model_estimates.default_steps(shipped.SHIPPED_DIR) == model_estimates.SHIPPED_ESTIMATE_STEPS == 10
    assert model_estimates.default_steps(tmp_path) == model_estimates.ESTIMATE_STEPS == 50      # user weights
    assert model_estimates.default_steps(None) == 50
    trained = tmp_path / "trained"
    trained.mkdir()
    shutil.copy(shipped.SHIPPED_DIR / shipped.INFO_FILE, trained / shipped.INFO_FILE)
    assert json.loads((trained / shipped.INFO_FILE).read_text())["name"]
    assert model_estimates.default_steps(trained) == 50
