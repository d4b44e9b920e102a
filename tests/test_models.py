"""Flax UNet / VAE / CLIP text encoder against diffusers and transformers (fp32, tiny, random).

A tiny random RGB↔X folder is written once per session with `save_pretrained` (safetensors,
the real layout); our converter loads it, and every output must equal PyTorch's within 1e-5
relative (max |ours − ref| / max |ref|).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

torch = pytest.importorskip("torch")
diffusers = pytest.importorskip("diffusers")
transformers = pytest.importorskip("transformers")

from jaxdistill.errors import InputError  # noqa: E402
from jaxdistill.models import convert, layers  # noqa: E402
from jaxdistill.models.tokenizer import MAP_PROMPTS, load_tokenizer  # noqa: E402
from tiny_rgbx import nchw, nhwc, rel_err  # noqa: E402
from tolerance import assert_close  # noqa: E402

TOL = 1e-5


@pytest.mark.parametrize("height,width", [(16, 16), (30, 40)])
def test_unet_matches_diffusers(loaded, torch_models, height, width):
    """Several timesteps, batch 2, a latent size that needs diffusers' forwarded upsample sizes."""
    unet_ref = torch_models[0]
    rng = np.random.default_rng(height)
    sample = rng.standard_normal((2, 8, height, width)).astype(np.float32)
    context = rng.standard_normal((2, 77, 32)).astype(np.float32)
    apply = jax.jit(loaded.networks.unet.apply)
    for t in (0, 37, 500, 999):
        with torch.no_grad():
            ref = unet_ref(torch.from_numpy(sample), t, encoder_hidden_states=torch.from_numpy(context)).sample
        ours = apply(loaded.params["unet"], nhwc(sample), jnp.full((2,), t), context)
        assert rel_err(nchw(ours), ref.numpy()) < TOL, t


def test_vae_matches_diffusers(loaded, torch_models):
    vae_ref = torch_models[1]
    image = np.random.default_rng(1).uniform(-1, 1, (2, 3, 48, 64)).astype(np.float32)
    with torch.no_grad():
        dist = vae_ref.encode(torch.from_numpy(image)).latent_dist
        latent = dist.mode()
        decoded = vae_ref.decode(latent).sample
    vae = loaded.networks.vae
    mean, logvar = jax.jit(lambda p, x: vae.apply(p, x, method="encode"))(loaded.params["vae"], nhwc(image))
    assert rel_err(nchw(mean), latent.numpy()) < TOL
    assert rel_err(nchw(logvar), dist.logvar.numpy()) < TOL
    ours = jax.jit(lambda p, z: vae.apply(p, z, method="decode"))(loaded.params["vae"], nhwc(latent.numpy()))
    assert rel_err(nchw(ours), decoded.numpy()) < TOL


def test_text_encoder_and_tokenizer_match_transformers(loaded, torch_models, rgbx_dir):
    from transformers import CLIPTokenizer

    prompts = list(MAP_PROMPTS.values()) + ["", "a wooden table by the window, in the afternoon light"]
    ids = load_tokenizer(rgbx_dir / "tokenizer").encode(prompts)
    ref_ids = CLIPTokenizer.from_pretrained(rgbx_dir / "tokenizer")(
        prompts, padding="max_length", max_length=77, truncation=True, return_tensors="np").input_ids
    np.testing.assert_array_equal(ids, ref_ids)
    with torch.no_grad():
        ref = torch_models[2](torch.from_numpy(ref_ids.astype(np.int64))).last_hidden_state.numpy()
    ours = jax.jit(loaded.networks.text_encoder.apply)(loaded.params["text_encoder"], jnp.asarray(ids))
    assert rel_err(ours, ref) < TOL


def test_bfloat16_activations_stay_close(rgbx_dir, loaded, torch_models):
    """bf16 activations (fp32 params, norms and softmax): about 1e-2 relative, not garbage."""
    bf16 = convert.build_networks(rgbx_dir, dtype=jnp.bfloat16)
    rng = np.random.default_rng(2)
    sample = rng.standard_normal((1, 8, 16, 16)).astype(np.float32)
    context = rng.standard_normal((1, 77, 32)).astype(np.float32)
    with torch.no_grad():
        ref = torch_models[0](torch.from_numpy(sample), 500, encoder_hidden_states=torch.from_numpy(context)).sample
    ours = jax.jit(bf16.unet.apply)(loaded.params["unet"], nhwc(sample), 500, context)
    assert ours.dtype == jnp.float32
    assert 1e-4 < rel_err(nchw(ours), ref.numpy()) < 0.05


def test_chunked_attention_equals_full_attention():
    rng = np.random.default_rng(3)
    q, k, v = (rng.standard_normal((2, 150, 16)).astype(np.float32) for _ in range(3))
    full = layers.dot_product_attention(q, k, v, 2, chunk_size=1024)
    chunked = layers.dot_product_attention(q, k, v, 2, chunk_size=32)   # 5 chunks, last one padded
    assert_close(chunked, full, rtol=1e-5, floor=1e-6)              # other matmul shapes: other rounding
    # against a NumPy reference
    qh, kh, vh = (x.reshape(2, 150, 2, 8) for x in (q, k, v))
    s = np.einsum("bqhd,bkhd->bhqk", qh, kh) / np.sqrt(8)
    w = np.exp(s - s.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    ref = np.einsum("bhqk,bkhd->bqhd", w, vh).reshape(2, 150, 16)
    assert_close(full, ref, rtol=1e-5, floor=1e-5)


def test_fused_cudnn_attention_is_refused_where_cudnn_cannot_run(rgbx_dir):
    """FUSED_CUDNN needs bf16/fp16, head size a multiple of 8 up to 128, no mask: anything else is
    refused by name (it is never silently computed another way); only the UNet gets it, since the
    VAE's single head is as wide as its last block. (The fused kernel itself runs only on an
    NVIDIA GPU: scripts/bench_gpu_unet.sh checks it against the chunked attention there.)"""
    q = np.zeros((1, 8, 16), np.float32)
    with pytest.raises(ValueError, match="got float32"):
        layers.dot_product_attention(q, q, q, 2, chunk_size=layers.FUSED_CUDNN)
    for channels, heads, problem in ((512, 1, "head size 512"), (24, 2, "head size 12")):
        x = jnp.zeros((1, 8, channels), jnp.bfloat16)
        with pytest.raises(ValueError, match=problem):
            layers.dot_product_attention(x, x, x, heads, chunk_size=layers.FUSED_CUDNN)
    x = jnp.zeros((1, 8, 16), jnp.bfloat16)
    with pytest.raises(ValueError, match="mask True"):
        layers.dot_product_attention(x, x, x, 2, mask=np.tril(np.ones((8, 8), bool)), chunk_size=layers.FUSED_CUDNN)
    nets = convert.build_networks(rgbx_dir, dtype=jnp.bfloat16, chunk_size=layers.FUSED_CUDNN)
    assert nets.unet.chunk_size == layers.FUSED_CUDNN
    assert nets.vae.chunk_size == layers.DEFAULT_ATTENTION_CHUNK


def test_fused_attention_problems_are_read_from_the_unet_config(tmp_path):
    """The main job refuses --prior_attention=cudnn before any set-up when a UNet's heads do not
    fit cuDNN (`convert.fused_attention_problems`, called by `loop.check_before_compute` on a GPU):
    head sizes from block_out_channels / heads, for the attention blocks and the mid block only."""
    shipped = json.loads((Path(convert.__file__).parent / "rgbx_rooms" / "unet" / "config.json").read_text())
    real = {**shipped, "block_out_channels": [320, 640, 1280, 1280], "attention_head_dim": [5, 10, 20, 20]}
    cases = (({}, []),                                              # the shipped model: heads of 16
             ({"attention_head_dim": [32, 4, 4, 4]}, ["down_block_types[0]: 32 heads of 1 channels"]),
             ({"attention_head_dim": [2, 4, 4, 64]}, ["the mid block: 64 heads of 1 channels"]),   # block 3: no attention
             (real, []))                                            # RGB<->X's own: heads of 64
    for i, (change, expected) in enumerate(cases):
        folder = tmp_path / str(i)
        (folder / "unet").mkdir(parents=True)
        (folder / "unet" / "config.json").write_text(json.dumps({**shipped, **change}))
        assert convert.fused_attention_problems(folder) == expected, change


def test_vae_chunked_mid_attention_matches(rgbx_dir, loaded):
    """The VAE with query chunks of 4 tokens (64 latent tokens here) equals the unchunked one."""
    chunked = convert.build_networks(rgbx_dir, chunk_size=4).vae
    image = np.random.default_rng(4).uniform(-1, 1, (1, 64, 64, 3)).astype(np.float32)
    ref = jax.jit(loaded.networks.vae.apply)(loaded.params["vae"], image)
    assert_close(jax.jit(chunked.apply)(loaded.params["vae"], image), ref, rtol=1e-5, floor=1e-5)


def test_conversion_cache_round_trip(rgbx_dir, loaded, tmp_path):
    first = convert.load_rgbx(rgbx_dir, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.safetensors"))) == 3
    second = convert.load_rgbx(rgbx_dir, cache_dir=tmp_path)
    for part in ("unet", "vae", "text_encoder"):
        jax.tree.map(np.testing.assert_array_equal, second.params[part], loaded.params[part])
        jax.tree.map(np.testing.assert_array_equal, first.params[part], loaded.params[part])
    assert set(second.seconds) == {"unet", "vae", "text_encoder", "total"}


def test_old_attention_names_and_text_model_prefix(loaded, torch_models):
    """Pre-0.14 VAE attention names (query/key/value/proj_attn) and transformers 4's
    `text_model.` prefix with a saved `position_ids` buffer convert to the same leaves."""
    shapes = convert.abstract_params(loaded.networks)
    vae_state = {k: v.numpy() for k, v in torch_models[1].state_dict().items()}
    renamed = {}
    for key, value in vae_state.items():
        for new, old in (("to_q", "query"), ("to_k", "key"), ("to_v", "value"), ("to_out.0", "proj_attn")):
            if "mid_block.attentions" in key and f".{new}." in key:
                key = key.replace(f".{new}.", f".{old}.")
                value = value[:, :, None, None] if value.ndim == 2 else value   # stored as 1×1 convs
        renamed[key] = value
    params = convert.convert_state_dict(renamed, shapes["vae"], "vae")
    jax.tree.map(np.testing.assert_array_equal, params, loaded.params["vae"]["params"])
    text_state = {f"text_model.{k}": v.numpy() for k, v in torch_models[2].state_dict().items()}
    text_state["text_model.embeddings.position_ids"] = np.arange(77)[None]
    params = convert.convert_state_dict(text_state, shapes["text_encoder"], "text_encoder")
    jax.tree.map(np.testing.assert_array_equal, params, loaded.params["text_encoder"]["params"])


def test_converter_names_unexpected_missing_and_misshaped_keys(loaded, torch_models):
    shapes = convert.abstract_params(loaded.networks)
    state = {k: v.numpy() for k, v in torch_models[0].state_dict().items()}
    state["mid_block.extra.weight"] = np.zeros(3, np.float32)
    del state["conv_in.bias"]
    state["conv_out.weight"] = np.zeros((4, 32, 1, 1), np.float32)
    with pytest.raises(InputError) as err:
        convert.convert_state_dict(state, shapes["unet"], "rgb-to-x/unet")
    text = str(err.value)
    assert "mid_block.extra.weight: no matching parameter" in text
    assert "conv_in/bias" in text and "missing" in text
    assert "conv_out.weight: shape (1, 1, 32, 4)" in text and "expects (3, 3, 32, 4)" in text


def _copy(rgbx_dir, tmp_path):
    return shutil.copytree(rgbx_dir, tmp_path / "copy")


def test_folder_errors(rgbx_dir, tmp_path):
    with pytest.raises(InputError, match="not found.*huggingface-cli download zheng95z/rgb-to-x"):
        convert.load_rgbx(tmp_path / "nowhere")
    folder = _copy(rgbx_dir, tmp_path)
    shutil.rmtree(folder / "vae")
    with pytest.raises(InputError, match=r"vae/: missing"):
        convert.load_rgbx(folder)


def test_bin_only_folder_says_how_to_convert(rgbx_dir, tmp_path):
    folder = _copy(rgbx_dir, tmp_path)
    weights = folder / "unet" / "diffusion_pytorch_model.safetensors"
    weights.rename(folder / "unet" / "diffusion_pytorch_model.bin")
    with pytest.raises(InputError, match=r"only has PyTorch pickles.*save_pretrained.*safe_serialization=True"):
        convert.load_rgbx(folder)


def test_not_an_rgbx_unet_and_bad_config(rgbx_dir, tmp_path):
    folder = _copy(rgbx_dir, tmp_path)
    config_file = folder / "unet" / "config.json"
    config = json.loads(config_file.read_text())
    config_file.write_text(json.dumps(dict(config, in_channels=4)))
    with pytest.raises(InputError, match=r"unet/config.json: in_channels: is 4.*not an RGB→X model; point "
                       r"--rgbx_dir at"):
        convert.load_rgbx(folder)
    # each program names its own flag: the estimate command's is --prior_dir
    from jaxdistill import estimate

    photo = tmp_path / "photo.png"
    photo.write_bytes(b"not read: the folder is refused first")
    with pytest.raises(InputError, match=r"in_channels: is 4.*point --prior_dir at"):
        estimate.run(estimate.EstimateConfig(prior_dir=str(folder), out_dir=str(tmp_path / "o"), photo=str(photo)))
    config_file.write_text(json.dumps(dict(config, act_fn="gelu", up_block_types=["UpBlock2D", "Fancy"] * 2)))
    with pytest.raises(InputError) as err:
        convert.load_rgbx(folder)
    assert "act_fn: is 'gelu'" in str(err.value) and "up_block_types: unsupported block types ['Fancy'" in str(err.value)
    config_file.write_text("{ not json")
    with pytest.raises(InputError, match=r"config.json: line 1: not valid JSON"):
        convert.load_rgbx(folder)


def _damage(path, how: str) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2] if how == "truncated" else b"<html>503 Service Unavailable</html>" * 40)


def test_damaged_safetensors_name_the_file_and_the_part(rgbx_dir, tmp_path, monkeypatch):
    """A truncated UNet file and a text encoder file that is not safetensors at all (an HTML error
    page saved by a failed download): both named, with the part and the command that fetches the
    file again, before any network is converted."""
    folder = _copy(rgbx_dir, tmp_path)
    unet = folder / "unet" / "diffusion_pytorch_model.safetensors"
    text = folder / "text_encoder" / "model.safetensors"
    _damage(unet, "truncated")
    _damage(text, "garbage")
    monkeypatch.setattr(convert, "convert_state_dict", lambda *a, **k: pytest.fail("converted a damaged folder"))
    with pytest.raises(InputError) as err:
        convert.load_rgbx(folder)
    lines = str(err.value).splitlines()[1:]
    assert len(lines) == 2, err.value
    assert lines[0].strip().startswith(f"{unet}: unet weights: damaged or incomplete safetensors file")
    assert lines[1].strip().startswith(f"{text}: text_encoder weights: damaged or incomplete safetensors file")
    assert "incomplete metadata" in lines[0] and "header too large" in lines[1]      # safetensors' own words
    assert (f"huggingface-cli download zheng95z/rgb-to-x unet/diffusion_pytorch_model.safetensors "
            f"--local-dir {folder}") in lines[0]
    assert f"zheng95z/rgb-to-x text_encoder/model.safetensors --local-dir {folder}" in lines[1]
    # the same file read directly (a caller skipping the header check) is named the same way
    with pytest.raises(InputError, match=r"diffusion_pytorch_model.safetensors: unet weights: damaged"):
        convert.read_safetensors(folder / "unet", "diffusion_pytorch_model")


def test_damaged_conversion_cache_is_converted_again(rgbx_dir, loaded, tmp_path, caplog):
    cache = tmp_path / "cache"
    convert.load_rgbx(rgbx_dir, cache_dir=cache)
    files = sorted(cache.glob("*.safetensors"))
    assert len(files) == 3
    for f in files:
        _damage(f, "truncated")
    with caplog.at_level("WARNING", logger=convert.__name__):
        again = convert.load_rgbx(rgbx_dir, cache_dir=cache)
    assert sum("the cached conversion is damaged" in r.getMessage() for r in caplog.records) == 3
    for part in ("unet", "vae", "text_encoder"):
        jax.tree.map(np.testing.assert_array_equal, again.params[part], loaded.params[part])
    assert all(convert.damaged_weights(f) is None for f in files)        # rewritten whole
