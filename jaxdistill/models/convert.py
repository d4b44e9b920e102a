"""Load a diffusers-format RGB↔X folder into Flax parameter pytrees (no torch at runtime).

The folder is laid out like `zheng95z/rgb-to-x`: `model_index.json`, `unet/`, `vae/`,
`text_encoder/`, `tokenizer/`, `scheduler/`, weights as `.safetensors` (read with the
safetensors NumPy API). Every PyTorch key maps by rule to one Flax leaf:

  `down_blocks.0.resnets.1.conv1.weight` → `down_blocks_0/resnets_1/conv1/kernel`
  conv weight OIHW → kernel HWIO · linear weight (out, in) → kernel (in, out)
  norm weight → scale · embedding weight → embedding · bias → bias

and every shape is checked against `jax.eval_shape` of the Flax init. A key without a leaf,
or a leaf without a key, is an error naming it. Optionally the converted pytrees are cached
(`cache_dir`) as flat safetensors so a second load skips conversion.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from jaxdistill.errors import InputError
from jaxdistill.io.cache import default_cache_dir
from jaxdistill.models.clip import CLIPTextConfig, CLIPTextTransformer
from jaxdistill.models.unet import UNet2DCondition, UNetConfig
from jaxdistill.models.vae import AutoencoderKL, VAEConfig
from jaxdistill.models.layers import DEFAULT_ATTENTION_CHUNK, FUSED_CUDNN, fused_head_fits

log = logging.getLogger(__name__)

CONVERTER_VERSION = 1
RGBX_IN_CHANNELS = 8
PARTS = ("unet", "vae", "text_encoder", "tokenizer", "scheduler")
MODEL_INDEX = {   # zheng95z/rgb-to-x's model_index.json: what writers of such folders put there
    "_class_name": "StableDiffusionAOVMatEstPipeline", "_diffusers_version": "0.20.0",
    "scheduler": ["diffusers", "DDIMScheduler"], "text_encoder": ["transformers", "CLIPTextModel"],
    "tokenizer": ["transformers", "CLIPTokenizer"], "unet": ["diffusers", "UNet2DConditionModel"],
    "vae": ["diffusers", "AutoencoderKL"]}
_WEIGHT_STEMS = {"unet": "diffusion_pytorch_model", "vae": "diffusion_pytorch_model", "text_encoder": "model"}
# the PyTorch class of each part, for the .bin → safetensors conversion hint
_TORCH_CLASSES = {"unet": ("diffusers", "UNet2DConditionModel"), "vae": ("diffusers", "AutoencoderKL"),
                  "text_encoder": ("transformers", "CLIPTextModel")}
# PyTorch buffers that are not parameters (older transformers saved CLIP's position ids)
_IGNORED_KEYS = {"embeddings.position_ids"}
# pre-0.14 diffusers VAE attention names → current ones
_ALIASES = {"query": "to_q", "key": "to_k", "value": "to_v", "proj_attn": "to_out.0"}
_DOWNLOAD_HINT = ("download it with `huggingface-cli download zheng95z/rgb-to-x --local-dir DIR` "
                  "on a machine with internet (Adobe Research License: never commit the weights)")


def flax_path(torch_key: str) -> tuple[str, ...]:
    """`a.b.0.c.weight` → ('a', 'b_0', 'c', 'weight'): list indices fold into the preceding name."""
    out: list[str] = []
    for part in torch_key.split("."):
        if part.isdigit() and out:
            out[-1] = f"{out[-1]}_{part}"
        else:
            out.append(part)
    return tuple(out)


def _normalise_key(key: str) -> str:
    if key.startswith("text_model."):
        key = key[len("text_model."):]
    parts = key.split(".")
    if len(parts) >= 2 and parts[-2] in _ALIASES:
        parts[-2] = _ALIASES[parts[-2]]
    return ".".join(parts)


def convert_state_dict(state: dict[str, np.ndarray], abstract: dict, source: str, consume: bool = False) -> dict:
    """PyTorch state dict (name → array) → Flax params shaped like `abstract` (eval_shape output,
    the dict under 'params'). All unmapped keys, missing leaves and shape mismatches are
    reported together in one InputError naming them. `consume` empties `state` as it goes, so
    peak memory is about one copy of the weights, not two."""
    want = traverse_util.flatten_dict(abstract)
    leaves_of: dict[tuple, set[str]] = {}
    for path in want:
        leaves_of.setdefault(path[:-1], set()).add(path[-1])
    out: dict[tuple, np.ndarray] = {}
    problems: list[tuple[str, str, str]] = []
    seen: set[tuple] = set()
    for key in list(state):
        array = state.pop(key) if consume else state[key]
        norm = _normalise_key(key)
        if norm in _IGNORED_KEYS:
            continue
        path = flax_path(norm)
        module, leaf = path[:-1], path[-1]
        names = leaves_of.get(module, set())
        if leaf == "weight":
            leaf = next((n for n in ("kernel", "scale", "embedding") if n in names), None)
        elif leaf != "bias":
            leaf = None
        if leaf is None or leaf not in names:
            problems.append((source, key, "no matching parameter in the Flax model (unexpected key)"))
            continue
        array = np.asarray(array)
        if leaf == "kernel":
            target_ndim = len(want[module + (leaf,)].shape)
            if target_ndim == 2 and array.ndim == 4 and array.shape[2:] == (1, 1):
                array = array[:, :, 0, 0]  # old VAE attention stored as 1×1 convolutions
            array = array.transpose(2, 3, 1, 0) if array.ndim == 4 else array.T
        target = want[module + (leaf,)]
        seen.add(module + (leaf,))
        if tuple(array.shape) != tuple(target.shape):
            problems.append((source, key, f"shape {tuple(array.shape)} (after conversion) but the model "
                             f"expects {tuple(target.shape)} at {'/'.join(module + (leaf,))}"))
            continue
        out[module + (leaf,)] = np.ascontiguousarray(array, dtype=np.float32)
    for path in want:
        if path not in seen:
            problems.append((source, "/".join(path), "Flax parameter with no key in the checkpoint (missing)"))
    if problems:
        shown = problems[:25]
        if len(problems) > len(shown):
            shown.append((source, "...", f"and {len(problems) - len(shown)} more problems"))
        raise InputError(shown)
    return traverse_util.unflatten_dict(out)


def weight_files(folder: Path, stem: str) -> list[Path]:
    """The `.safetensors` files holding `<stem>` (one file, or the shards its index lists);
    InputError naming what is missing, and how to get or convert it."""
    single = folder / f"{stem}.safetensors"
    index = folder / f"{stem}.safetensors.index.json"
    if single.exists():
        return [single]
    if index.exists():
        try:
            shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        except (json.JSONDecodeError, KeyError, AttributeError, TypeError) as err:
            raise InputError.single(index, "weight_map", f"unreadable shard index: {err!r}; "
                                    f"{_redownload(folder, index.name)}") from None
        missing = [s for s in shards if not (folder / s).exists()]
        if missing:
            raise InputError.single(index, "weight_map", f"lists shards {missing} which are missing; "
                                    f"{_redownload(folder, missing[0])}")
        return [folder / s for s in shards]
    bins = sorted(p.name for p in folder.glob("*.bin"))
    others = sorted(p.name for p in folder.glob("*.safetensors"))
    if bins:
        library, model_class = _TORCH_CLASSES.get(folder.name, ("diffusers", "UNet2DConditionModel"))
        raise InputError.single(folder, f"{stem}.safetensors", (
            f"missing; the folder only has PyTorch pickles {bins}. jaxdistill reads safetensors only "
            "(no torch at runtime). Convert once, where torch and diffusers/transformers are installed: "
            f"`python -c \"from {library} import {model_class} as M; "
            f"M.from_pretrained('{folder}').save_pretrained('{folder}', safe_serialization=True)\"`"))
    hint = f" (found {others}; a variant such as fp16 is not read — save the fp32 weights)" if others else ""
    raise InputError.single(folder, f"{stem}.safetensors", f"missing{hint}; {_DOWNLOAD_HINT}")


def _redownload(folder: Path, name: str) -> str:
    """How to fetch one file of a part again (`folder` is the part's folder, e.g. DIR/unet)."""
    return (f"re-download it: `huggingface-cli download zheng95z/rgb-to-x {folder.name}/{name} "
            f"--local-dir {folder.parent}` (Adobe Research License: never commit the weights)")


def damaged_weights(path: Path) -> str | None:
    """Why the safetensors file `path` cannot be read (truncated, not safetensors), or None when
    its header parses and covers the whole file. Reads the header only (the data is mapped)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="np") as f:
            f.keys()
    except (SafetensorError, OSError) as err:
        return f"{err}".strip() or type(err).__name__
    return None


def _weights_problem(path: Path, part: str, reason: str) -> tuple[str, str, str]:
    size = path.stat().st_size if path.exists() else 0
    return (str(path), f"{part} weights", f"damaged or incomplete safetensors file ({size:,} bytes; "
            f"safetensors: {reason}); {_redownload(path.parent, path.name)}")


def read_safetensors(folder: Path, stem: str) -> dict[str, np.ndarray]:
    """All tensors of `<stem>.safetensors` (or its sharded index) as NumPy arrays; InputError
    naming the file and the part (the folder's name) when one is damaged."""
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    state: dict[str, np.ndarray] = {}
    for path in weight_files(folder, stem):
        try:
            state.update(load_file(str(path)))
        except SafetensorError as err:
            raise InputError([_weights_problem(path, folder.name, str(err))]) from None
    return state


def check_weights(folder: Path) -> None:
    """InputError naming every weights file of unet/vae/text_encoder that is missing, damaged
    or truncated (headers only: cheap, run before any compute)."""
    problems: list[tuple[str, str, str]] = []
    for part, stem in _WEIGHT_STEMS.items():
        try:
            paths = weight_files(folder / part, stem)
        except InputError as err:
            problems += err.problems
            continue
        for path in paths:
            reason = damaged_weights(path)
            if reason is not None:
                problems.append(_weights_problem(path, part, reason))
    if problems:
        raise InputError(problems)


def _digest(folder: Path, stem: str, extra: str) -> str:
    h = hashlib.sha256(f"v{CONVERTER_VERSION}:{extra}".encode())
    h.update((folder / "config.json").read_bytes())
    for p in sorted(folder.glob(f"{stem}*.safetensors")):
        st = p.stat()
        h.update(f"{p.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:20]


def _load_part(folder: Path, stem: str, abstract: dict, cache_dir: Path | None, tag: str) -> dict:
    """Converted params of one network, through the cache when one is given."""
    from safetensors.numpy import load_file, save_file

    cache_file = None
    if cache_dir is not None:
        cache_file = Path(cache_dir) / f"{folder.name}-{_digest(folder, stem, tag)}.safetensors"
        damage = damaged_weights(cache_file) if cache_file.exists() else None
        if damage is not None:
            log.warning("%s: converting %s again: the cached conversion is damaged (%s)", cache_file, tag, damage)
        elif cache_file.exists():
            flat = load_file(str(cache_file))
            params = traverse_util.unflatten_dict({tuple(k.split("/")): v for k, v in flat.items()})
            # a cache written by another layout must not slip through: re-check every leaf
            expected = {k: v.shape for k, v in traverse_util.flatten_dict(abstract).items()}
            got = {k: v.shape for k, v in traverse_util.flatten_dict(params).items()}
            if expected == got:
                return params
            log.warning("ignoring stale cache %s", cache_file)
    params = convert_state_dict(read_safetensors(folder, stem), abstract, str(folder), consume=True)
    if cache_file is not None:
        cache_file.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache_file.with_suffix(f".{os.getpid()}.tmp")      # concurrent runs never share a partial file
        save_file({"/".join(k): v for k, v in traverse_util.flatten_dict(params).items()}, str(tmp))
        tmp.replace(cache_file)
    return params


@dataclasses.dataclass(frozen=True)
class RgbxNetworks:
    """The three networks (static Flax modules) of an RGB↔X folder, with their configs."""

    unet: UNet2DCondition
    vae: AutoencoderKL
    text_encoder: CLIPTextTransformer


@dataclasses.dataclass
class LoadedRgbx:
    """Networks, parameters (plain pytrees, float32), tokenizer folder and load timings."""

    folder: Path
    networks: RgbxNetworks
    params: dict[str, Any]          # {"unet": ..., "vae": ..., "text_encoder": ...}, each {"params": ...}
    seconds: dict[str, float]       # load time per part, and "total"


def check_folder(folder: str | Path) -> Path:
    """The folder as a Path, after checking it is laid out like zheng95z/rgb-to-x."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise InputError.single(folder, "(folder)", f"not found; {_DOWNLOAD_HINT}")
    if not (folder / "model_index.json").exists():
        raise InputError.single(folder, "model_index.json", "missing: not a diffusers pipeline folder "
                                f"(expected model_index.json, {', '.join(p + '/' for p in PARTS)}); {_DOWNLOAD_HINT}")
    problems = [(str(folder), f"{part}/", "missing") for part in PARTS if not (folder / part).is_dir()]
    for part in ("unet", "vae", "text_encoder"):
        if (folder / part).is_dir() and not (folder / part / "config.json").exists():
            problems.append((str(folder / part), "config.json", "missing"))
    if problems:
        raise InputError(problems + [(str(folder), "(layout)", f"expected the zheng95z/rgb-to-x layout; {_DOWNLOAD_HINT}")])
    return folder


def _unet_config(folder: Path, require_rgbx: bool, flag: str) -> UNetConfig:
    """The UNet's config; InputError when an RGB→X UNet is required and this is not one."""
    unet_cfg = UNetConfig.from_json(folder / "unet" / "config.json")
    if require_rgbx and unet_cfg.in_channels != RGBX_IN_CHANNELS:
        raise InputError.single(folder / "unet" / "config.json", "in_channels", (
            f"is {unet_cfg.in_channels}, but an RGB→X UNet takes {RGBX_IN_CHANNELS} (noisy latent + photo "
            f"latent). This is not an RGB→X model; point {flag} at zheng95z/rgb-to-x."))
    return unet_cfg


def check_rgbx_folder(folder: str | Path, flag: str = "--rgbx_dir", require_rgbx: bool = True) -> Path:
    """Everything about an RGB↔X folder that can be checked without converting it, for callers
    to run before any compute: the layout, the UNet's in_channels and every weights file's
    header. `flag` is the option that named the folder, for the messages."""
    folder = check_folder(folder)
    _unet_config(folder, require_rgbx, flag)
    check_weights(folder)
    return folder


def fused_attention_problems(folder: str | Path) -> list[str]:
    """Why cuDNN's fused attention (`layers.FUSED_CUDNN`) cannot run this folder's UNet, from its
    config alone: each attention whose head size is not a multiple of 8 up to 128 (none: it can)."""
    cfg = UNetConfig.from_json(Path(folder).expanduser() / "unet" / "config.json")
    blocks = [(f"down_block_types[{i}]", i) for i, kind in enumerate(cfg.down_block_types) if "CrossAttn" in kind]
    blocks.append(("the mid block", len(cfg.block_out_channels) - 1))
    problems = []
    for where, i in blocks:
        size = cfg.block_out_channels[i] // cfg.num_heads[i]
        if not fused_head_fits(size):
            problems.append(f"{where}: {cfg.num_heads[i]} heads of {size} channels")
    return problems


def build_networks(folder: str | Path, dtype: Any = jnp.float32, precision: str = "default",
                   chunk_size: int | None = None, require_rgbx: bool = True,
                   flag: str = "--rgbx_dir") -> RgbxNetworks:
    """Flax modules configured from the folder's config.json files (no weights read).
    `chunk_size`: the attention's query chunk (`layers.dot_product_attention`); `layers.FUSED_CUDNN`
    gives the UNet cuDNN's fused attention (GPU, bfloat16/float16) and leaves the VAE chunked."""
    folder = check_folder(folder)
    unet_cfg = _unet_config(folder, require_rgbx, flag)
    opts = dict(dtype=dtype, precision=precision)
    if chunk_size is not None:
        opts["chunk_size"] = chunk_size
    # cuDNN's fused attention takes heads of at most 128 channels: the VAE's one attention head is as
    # wide as its last block (512 in RGB<->X), so with FUSED_CUDNN the VAE keeps the chunked attention
    vae_opts = {**opts, "chunk_size": DEFAULT_ATTENTION_CHUNK} if chunk_size == FUSED_CUDNN else opts
    text_opts = dict(dtype=dtype, precision=precision)
    return RgbxNetworks(
        unet=UNet2DCondition(unet_cfg, **opts),
        vae=AutoencoderKL(VAEConfig.from_json(folder / "vae" / "config.json"), **vae_opts),
        text_encoder=CLIPTextTransformer(CLIPTextConfig.from_json(folder / "text_encoder" / "config.json"),
                                         **text_opts),
    )


def abstract_params(networks: RgbxNetworks) -> dict[str, dict]:
    """Shapes of every parameter (`jax.eval_shape` of each init, no memory allocated). Tracing
    the three inits takes seconds; a process that loads the same networks again (an experiment's
    rows, a test's runs) gets them from a cache keyed by the modules' configuration, and a new
    process from a file keyed by that configuration, the networks' source files and the JAX and
    Flax versions (`shapes_folder`)."""
    with _TRACING:              # one trace per networks: a caller waits for a trace under way (`trace_ahead`)
        cached = _abstract_params(networks, bool(jax.config.jax_enable_x64))
    return jax.tree.map(lambda x: x, cached)         # a fresh tree: callers own what they get


_TRACING = threading.Lock()


def trace_ahead(folder: str | Path, dtype: Any = jnp.float32, precision: str = "default",
                chunk_size: int | None = None) -> threading.Thread:
    """Starts `abstract_params` of the folder's networks (as `load_rgbx` builds them with the same
    arguments) in a thread of its own, for a caller with other set-up to do before it loads the
    weights: a cold trace takes seconds of Python, and `load_rgbx` then waits for it (or finds its
    shapes cached) instead of tracing. Nothing is raised there: a folder that cannot be read is left
    to `load_rgbx`, which checks it and says what is wrong."""
    def trace():
        try:
            abstract_params(build_networks(folder, dtype, precision, chunk_size))
        except Exception as err:        # noqa: BLE001 -- load_rgbx checks the folder and reports it
            log.debug("parameter shapes not traced ahead (%s: %s)", type(err).__name__, err)

    thread = threading.Thread(target=trace, name="trace-param-shapes", daemon=True)
    thread.start()
    return thread


# what the inits' shapes follow from: the networks, their layers, and this module's `_trace_params`
_NETWORK_SOURCES = ("unet.py", "vae.py", "clip.py", "layers.py", "convert.py")


def shapes_folder() -> Path:
    """Where the parameter shapes' files are: beside JAX's persistent compilation cache when one
    is set (`jax_compilation_cache_dir`; like its programs, they follow from the code alone, and a
    run that reads its programs from there reads its shapes too), else `$JAXDISTILL_CACHE/param_shapes`."""
    compiled = jax.config.jax_compilation_cache_dir
    local = compiled and "://" not in compiled           # not a bucket (gs://...), which JAX also takes
    return Path(compiled) / "jaxdistill-param-shapes" if local else default_cache_dir() / "param_shapes"


def _shapes_file(networks: RgbxNetworks, x64: bool) -> Path:
    import flax

    h = hashlib.sha256(f"{networks!r}|x64={x64}|jax={jax.__version__}|flax={flax.__version__}".encode())
    for name in _NETWORK_SOURCES:
        h.update((Path(__file__).parent / name).read_bytes())
    return shapes_folder() / f"{h.hexdigest()[:24]}.json"


def _read_shapes(path: Path) -> dict | None:
    """The tree `_write_shapes` wrote, or None when the file is missing or unreadable."""
    def leaf(x):
        return jax.ShapeDtypeStruct(tuple(x[0]), jnp.dtype(x[1])) if isinstance(x, list) else \
            {k: leaf(v) for k, v in x.items()}

    try:
        shapes = leaf(json.loads(path.read_text()))
        if not isinstance(shapes, dict) or set(shapes) != set(_WEIGHT_STEMS):
            raise ValueError(f"not the parts {sorted(_WEIGHT_STEMS)}")
        return shapes
    except FileNotFoundError:
        return None
    except (OSError, ValueError, TypeError, KeyError, IndexError, AttributeError) as err:
        log.info("parameter shapes in %s unreadable (%s): traced again", path, err)
        return None


def _write_shapes(path: Path, shapes: dict) -> None:
    def plain(x):
        return [list(x.shape), str(x.dtype)] if isinstance(x, jax.ShapeDtypeStruct) else \
            {k: plain(v) for k, v in x.items()}

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.tmp")     # unique across processes and hosts
        tmp.write_text(json.dumps(plain(shapes)))
        os.replace(tmp, path)                        # whole or not at all, with processes writing at once
    except OSError as err:                           # a read-only cache costs the tracing, nothing else
        log.info("parameter shapes not cached in %s (%s)", path.parent, err)


@functools.lru_cache(maxsize=8)
def _abstract_params(networks: RgbxNetworks, x64: bool) -> dict[str, dict]:
    path = _shapes_file(networks, x64)
    shapes = _read_shapes(path)
    if shapes is None:
        shapes = _trace_params(networks)
        _write_shapes(path, shapes)
    return shapes


def _trace_params(networks: RgbxNetworks) -> dict[str, dict]:
    key = jax.random.key(0)
    u, v, t = networks.unet, networks.vae, networks.text_encoder
    f = v.config.downsampling_factor
    unet_shapes = jax.eval_shape(u.init, key, jnp.zeros((1, 8, 8, u.config.in_channels)), jnp.zeros((1,)),
                                 jnp.zeros((1, 4, u.config.cross_attention_dim)))
    vae_shapes = jax.eval_shape(v.init, key, jnp.zeros((1, 2 * f, 2 * f, v.config.in_channels)))
    text_shapes = jax.eval_shape(t.init, key, jnp.zeros((1, t.config.max_position_embeddings), jnp.int32))
    return {"unet": unet_shapes["params"], "vae": vae_shapes["params"], "text_encoder": text_shapes["params"]}


def load_rgbx(folder: str | Path, dtype: Any = jnp.float32, precision: str = "default",
              cache_dir: str | Path | None = None, chunk_size: int | None = None,
              require_rgbx: bool = True, flag: str = "--rgbx_dir") -> LoadedRgbx:
    """Read and convert all three networks of an RGB↔X folder; params stay float32 on the host.
    Every file is checked (`check_rgbx_folder`) before the first network is converted; `flag`
    is the option that named the folder, for the messages."""
    start = time.perf_counter()
    check_rgbx_folder(folder, flag, require_rgbx)
    networks = build_networks(folder, dtype, precision, chunk_size, require_rgbx, flag)
    folder = Path(folder).expanduser()
    shapes = abstract_params(networks)
    params, seconds = {}, {}
    for part, stem in _WEIGHT_STEMS.items():
        t0 = time.perf_counter()
        params[part] = {"params": _load_part(folder / part, stem, shapes[part], cache_dir, part)}
        seconds[part] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - start
    log.info("loaded RGB↔X from %s in %.1f s (%s)", folder, seconds["total"],
             ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items() if k != "total"))
    return LoadedRgbx(folder, networks, params, seconds)
