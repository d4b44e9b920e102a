"""Parity and speed of our Flax UNet / VAE / CLIP text encoder against PyTorch, random weights.

    python scripts/check_parity.py --size={tiny,full} [--json] [--resolution=256] [--repeats=3] [--threads=N]

For each network (UNet at resolution/8 with batch 1, t=500 and a random 77-token context; VAE
encode (mode) at resolution²; VAE decode at resolution/8; CLIP text encoder on 77 ids) it builds
the PyTorch model (diffusers / transformers, every parameter random and seeded, nothing
downloaded; `--size full` uses the real RGB↔X sizes), converts its state dict in memory with
`jaxdistill.models.convert` (`abstract_params` + `convert_state_dict`) and reports:

  * max abs and max relative error (max |ours - ref| / max |ref|) against PyTorch fp32, for our
    fp32 activations and for our bf16 activations (fp32 params, bf16 compute);
  * the forward time of each framework here: JAX jitted, after a warm-up (compile time apart),
    and torch under `inference_mode`, both medians of `--repeats`, with the same thread count
    (torch.set_num_threads; XLA uses the CPUs the process may run on, so `--threads` below the
    CPU count pins the process to that many CPUs before JAX starts), and the ratio jax/torch.

Output: an aligned table, or with `--json` one JSON object (all figures plus machine info).
The LAST line is always a one-line summary, `PASS: ...` or `FAIL: ...`, against 1e-4 max
relative error for fp32 on every network; the exit code is 0 on pass and 1 on fail. In --json
mode the summary follows the JSON, so `... --json | head -n -1 | python -m json.tool` works.
Progress goes to stderr. `--size tiny` takes under a minute here; `--size full` about 2.5 minutes
at 256² with a peak RSS of about 9 GB (one network is held at a time).

Timings from a shared 2-core CPU are noisy: compare ratios and repeat before trusting them.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import time
import traceback

import numpy as np

from jaxdistill.models.training import random_model
from jaxdistill.models.training.random_model import RGBX_TEXT, RGBX_UNET, RGBX_VAE, nchw, nhwc

TOLERANCE = 1e-4
NETWORKS = ("unet", "vae_encode", "vae_decode", "text_encoder")

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", choices=("tiny", "full"), default="tiny")
    p.add_argument("--json", action="store_true", help="print one JSON object (then the summary line)")
    p.add_argument("--resolution", type=int, default=256, help="image side in pixels (multiple of 8)")
    p.add_argument("--repeats", type=int, default=3, help="timed forwards per framework (median)")
    p.add_argument("--threads", type=int, default=os.cpu_count(), help="CPU threads for each framework")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.resolution <= 0 or args.resolution % 8:
        p.error(f"--resolution must be a positive multiple of 8, got {args.resolution}")
    if args.repeats < 1 or args.threads < 1:
        p.error("--repeats and --threads must be >= 1")
    return args


def limit_threads(threads: int) -> str:
    """Pin the process to `threads` CPUs (before JAX starts: XLA sizes its pool from the affinity)."""
    if not hasattr(os, "sched_getaffinity"):
        return "affinity not supported here; XLA uses its default thread pool"
    cpus = sorted(os.sched_getaffinity(0))
    if threads < len(cpus):
        os.sched_setaffinity(0, cpus[:threads])
        return f"process pinned to CPUs {cpus[:threads]}"
    if threads > len(cpus):
        return f"only {len(cpus)} CPUs available: XLA uses {len(cpus)} threads, torch {threads}"
    return f"{len(cpus)} CPUs available"


_T0 = time.perf_counter()


def progress(msg: str) -> None:
    print(f"[{time.perf_counter() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def peak_rss_gib() -> float:
    try:
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20   # KiB on Linux
    except (ImportError, OSError):
        return float("nan")


def rss_gib() -> float:
    """Current resident memory (GiB), from /proc where available."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**30
    except (OSError, ValueError):
        return float("nan")


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def errors(ours, ref) -> tuple[float, float]:
    """(max |ours - ref|, that divided by max |ref|), in float64."""
    ours, ref = np.asarray(ours, np.float64), np.asarray(ref, np.float64)
    if ours.shape != ref.shape:
        raise ValueError(f"output shapes differ: ours {ours.shape}, reference {ref.shape}")
    diff = float(np.abs(ours - ref).max())
    return diff, diff / float(np.abs(ref).max())


def flax_config(part: str, model):
    """Our config for `part`, parsed from the PyTorch model's config (what config.json would hold)."""
    from jaxdistill.models.clip import CLIPTextConfig
    from jaxdistill.models.unet import UNetConfig
    from jaxdistill.models.vae import VAEConfig

    if part == "unet":
        return UNetConfig.from_dict(dict(model.config))
    if part == "vae":
        return VAEConfig.from_dict(dict(model.config))
    return CLIPTextConfig.from_dict(model.config.to_dict())


class Checker:
    """Builds, converts, runs and times one part at a time, freeing each framework's copy after use."""

    def __init__(self, args):
        import jax
        import jax.numpy as jnp
        import torch

        from jaxdistill.models import convert
        from jaxdistill.models.clip import CLIPTextTransformer
        from jaxdistill.models.unet import UNet2DCondition
        from jaxdistill.models.vae import AutoencoderKL

        self.args, self.jax, self.torch, self.tiny = args, jax, torch, random_model
        torch.set_num_threads(args.threads)
        full = args.size == "full"
        self.sizes = {"unet": RGBX_UNET if full else random_model.TINY_UNET,
                      "vae": RGBX_VAE if full else random_model.TINY_VAE,
                      "text": RGBX_TEXT if full else dict(random_model.TINY_TEXT, vocab_size=600)}
        self.bos_eos = (49406, 49407) if full else (2, 2)
        # configs from weightless (meta-device) PyTorch models: one `abstract_params` for all parts
        with torch.device("meta"):
            self.configs = {part: flax_config(part, m) for part, m in self.torch_models().items()}
        self.networks = {
            dtype.__name__: convert.RgbxNetworks(
                unet=UNet2DCondition(self.configs["unet"], dtype=dtype),
                vae=AutoencoderKL(self.configs["vae"], dtype=dtype),
                text_encoder=CLIPTextTransformer(self.configs["text_encoder"], dtype=dtype))
            for dtype in (jnp.float32, jnp.bfloat16)}
        progress("abstract parameter shapes (jax.eval_shape of each init)")
        self.shapes = convert.abstract_params(self.networks["float32"])
        self.results: list[dict] = []

    def torch_models(self) -> dict:
        """The three PyTorch models (unet, vae, text_encoder) at --size, default init (use on meta)."""
        from diffusers import AutoencoderKL, UNet2DConditionModel
        from transformers import CLIPTextConfig, CLIPTextModel

        sizes = self.sizes
        bos, eos = self.bos_eos
        return {"unet": UNet2DConditionModel(**sizes["unet"]), "vae": AutoencoderKL(**sizes["vae"]),
                "text_encoder": CLIPTextModel(CLIPTextConfig(**sizes["text"], bos_token_id=bos, eos_token_id=eos,
                                                             pad_token_id=eos))}

    # ---- PyTorch side -------------------------------------------------------------------------
    def build_torch(self, part: str):
        """The random PyTorch model of `part` at the chosen size, via `random_model.build_tiny_models`
        (1/sqrt(fan_in) weights; the other two parts are built tiny and dropped at once)."""
        t = self.tiny
        start = time.perf_counter()
        key = "text" if part == "text_encoder" else part
        sizes = dict(unet=t.TINY_UNET, vae=t.TINY_VAE, text=dict(t.TINY_TEXT, vocab_size=600))
        sizes[key] = self.sizes[key]
        bos, eos = self.bos_eos if part == "text_encoder" else (2, 2)     # the tiny text model's ids
        built = t.build_tiny_models(self.args.seed, bos=bos, eos=eos, **sizes)
        models = dict(zip(("unet", "vae", "text_encoder"), built))
        del built
        model = models[part]
        del models
        gc.collect()
        if flax_config(part, model) != self.configs[part]:
            raise RuntimeError(f"{part}: the built model's config differs from the one the shapes came from")
        return model, time.perf_counter() - start

    def time_torch(self, fn):
        """(first output as NumPy, median seconds of `repeats` further calls) under inference_mode."""
        with self.torch.inference_mode():
            out = fn().numpy().copy()
            seconds = median_seconds(fn, self.args.repeats)
        return out, seconds

    # ---- Flax side ----------------------------------------------------------------------------
    def convert(self, part: str, model: list):
        """Torch state dict → Flax params on the JAX device. `model` is a one-item list that is
        emptied once the state dict is converted, so the PyTorch copy is freed before the JAX one
        is made; the host copy is then moved leaf by leaf (peak: about two copies, not three)."""
        from flax import traverse_util

        from jaxdistill.models import convert

        start = time.perf_counter()
        state = {k: v.detach().numpy() for k, v in model[0].state_dict().items()}
        host = convert.convert_state_dict(state, self.shapes[part], f"random {self.args.size} {part}")
        del state
        model.clear()
        gc.collect()
        flat = traverse_util.flatten_dict(host)
        del host
        params = {}
        for key in list(flat):
            params[key] = self.jax.device_put(flat.pop(key))
        params = {"params": traverse_util.unflatten_dict(params)}
        self.jax.block_until_ready(params)
        return params, time.perf_counter() - start

    def time_jax(self, fn, params, inputs):
        """(output as NumPy, compile seconds, median seconds) of jit(fn)(params, *inputs)."""
        jax = self.jax
        start = time.perf_counter()
        compiled = jax.jit(fn).lower(params, *inputs).compile()
        compile_s = time.perf_counter() - start
        out = jax.block_until_ready(compiled(params, *inputs))     # warm-up, also the output
        seconds = median_seconds(lambda: jax.block_until_ready(compiled(params, *inputs)), self.args.repeats)
        return self.jax.device_get(out), compile_s, seconds

    # ---- one network --------------------------------------------------------------------------
    def record(self, name, shape, ref, ours32, ours16, torch_s, jax_s, compile_s, compile16_s, extra):
        abs32, rel32 = errors(ours32, ref)
        abs16, rel16 = errors(ours16, ref)
        row = dict(network=name, input_shape=list(shape), output_shape=list(np.shape(ref)),
                   ref_max_abs=float(np.abs(ref).max()), ref_std=float(np.std(ref)),
                   fp32_max_abs=abs32, fp32_max_rel=rel32, bf16_max_abs=abs16, bf16_max_rel=rel16,
                   jax_ms=1e3 * jax_s, torch_ms=1e3 * torch_s, ratio=jax_s / torch_s,
                   jax_compile_s=compile_s, jax_bf16_compile_and_run_s=compile16_s, **extra)
        self.results.append(row)
        progress(f"{name}: fp32 max rel {rel32:.2e}, bf16 max rel {rel16:.2e}, "
                 f"JAX {row['jax_ms']:.0f} ms, torch {row['torch_ms']:.0f} ms (max |ref| {row['ref_max_abs']:.3g})")

    def run_part(self, part: str):
        import jax.numpy as jnp

        torch, args = self.torch, self.args
        rng = np.random.default_rng([args.seed, ("unet", "vae", "text_encoder").index(part)])
        progress(f"{part}: building the random PyTorch model ({args.size})")
        model, build_s = self.build_torch(part)
        n_params = sum(p.numel() for p in model.parameters())
        progress(f"{part}: {n_params / 1e6:.1f} M parameters, built in {build_s:.1f} s; RSS {rss_gib():.1f} GiB")

        # inputs (NCHW for torch, NHWC for us) and the PyTorch forwards
        lat = args.resolution // 8
        if part == "unet":
            cfg = model.config
            sample = rng.standard_normal((1, cfg.in_channels, lat, lat)).astype(np.float32)
            context = rng.standard_normal((1, 77, cfg.cross_attention_dim)).astype(np.float32)
            t = 500
            ts, tc = torch.from_numpy(sample), torch.from_numpy(context)
            progress(f"unet: timing PyTorch ({args.repeats}+1 forwards)")
            ref, torch_s = self.time_torch(lambda: model(ts, t, encoder_hidden_states=tc).sample)
            torch_runs = {"unet": (ref, torch_s, sample.shape)}
        elif part == "vae":
            side = args.resolution
            image = rng.uniform(-1, 1, (1, model.config.in_channels, side, side)).astype(np.float32)
            latent = rng.standard_normal((1, model.config.latent_channels, lat, lat)).astype(np.float32)
            ti, tl = torch.from_numpy(image), torch.from_numpy(latent)
            progress(f"vae_encode: timing PyTorch ({args.repeats}+1 forwards)")
            ref_e, te = self.time_torch(lambda: model.encode(ti).latent_dist.mode())
            progress(f"vae_decode: timing PyTorch ({args.repeats}+1 forwards)")
            ref_d, td = self.time_torch(lambda: model.decode(tl).sample)
            torch_runs = {"vae_encode": (ref_e, te, image.shape), "vae_decode": (ref_d, td, latent.shape)}
        else:
            ids = rng.integers(0, model.config.vocab_size, (1, model.config.max_position_embeddings))
            tids = torch.from_numpy(ids.astype(np.int64))
            progress(f"text_encoder: timing PyTorch ({args.repeats}+1 forwards)")
            ref, torch_s = self.time_torch(lambda: model(tids).last_hidden_state)
            torch_runs = {"text_encoder": (ref, torch_s, ids.shape)}

        progress(f"{part}: converting the state dict")
        nets32, nets16 = self.networks["float32"], self.networks["bfloat16"]
        holder = [model]
        del model       # the closures above hold it through this name: drop it, convert frees the rest
        params, convert_s = self.convert(part, holder)
        progress(f"{part}: converted in {convert_s:.1f} s, PyTorch model freed; RSS {rss_gib():.1f} GiB")
        extra = dict(parameters=int(n_params), build_s=build_s, convert_s=convert_s)

        # our forwards: fp32 (compiled, warmed up, timed) and bf16 activations (compiled, run once)
        if part == "unet":
            jobs = [("unet", lambda n: (lambda p, x, c: n.unet.apply(p, x, jnp.full((1,), t), c)),
                     (nhwc(sample), context), nchw)]
        elif part == "vae":
            jobs = [("vae_encode", lambda n: (lambda p, x: n.vae.apply(p, x, method="encode")[0]),
                     (nhwc(image),), nchw),
                    ("vae_decode", lambda n: (lambda p, z: n.vae.apply(p, z, method="decode")),
                     (nhwc(latent),), nchw)]
        else:
            jobs = [("text_encoder", lambda n: n.text_encoder.apply, (ids.astype(np.int32),), np.asarray)]
        for name, make, inputs, to_ref_layout in jobs:
            ref, torch_s, shape = torch_runs[name]
            inputs = tuple(self.jax.device_put(x) for x in inputs)
            progress(f"{name}: compiling and timing JAX fp32 ({args.repeats}+1 forwards)")
            out32, compile_s, jax_s = self.time_jax(make(nets32), params, inputs)
            progress(f"{name}: JAX fp32 compiled in {compile_s:.1f} s; compiling and running bf16")
            start = time.perf_counter()
            out16 = self.jax.device_get(self.jax.block_until_ready(self.jax.jit(make(nets16))(params, *inputs)))
            compile16_s = time.perf_counter() - start
            self.record(name, shape, ref, to_ref_layout(out32), to_ref_layout(out16), torch_s, jax_s,
                        compile_s, compile16_s, extra)
        del params
        self.jax.clear_caches()
        gc.collect()

    def run(self):
        for part in ("unet", "vae", "text_encoder"):
            try:
                self.run_part(part)
            except Exception as err:   # keep going: report the others, then FAIL
                traceback.print_exc()
                names = ("vae_encode", "vae_decode") if part == "vae" else (part,)
                done = {r["network"] for r in self.results}
                for name in names:
                    if name not in done:
                        self.results.append(dict(network=name, error=f"{type(err).__name__}: {err}"))
                gc.collect()
        return self.results


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info(args, threads_note: str) -> dict:
    import diffusers
    import jax
    import torch
    import transformers

    dev = jax.devices()[0]
    return dict(jax=jax.__version__, jax_backend=jax.default_backend(), device_kind=dev.device_kind,
                torch=torch.__version__, diffusers=diffusers.__version__, transformers=transformers.__version__,
                threads=args.threads, torch_threads=torch.get_num_threads(), threads_note=threads_note,
                cpu=cpu_name(), cpus_available=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                else os.cpu_count(), python=platform.python_version(),
                resolution=args.resolution, size=args.size, repeats=args.repeats, seed=args.seed)


def summary(results: list[dict]) -> tuple[bool, str]:
    names = ", ".join(r["network"] for r in results)
    broken = [r for r in results if "error" in r]
    bad = [r for r in results if "error" not in r and not r["fp32_max_rel"] <= TOLERANCE]
    worst = max((r["fp32_max_rel"] for r in results if "error" not in r), default=float("nan"))
    if not broken and not bad and len(results) == len(NETWORKS):
        return True, f"PASS: fp32 max rel err {worst:.1e} <= {TOLERANCE:g} on {names}"
    parts = [f"{r['network']} {r['fp32_max_rel']:.1e}" for r in bad] + [f"{r['network']} errored" for r in broken]
    parts += [f"{n} missing" for n in NETWORKS if n not in {r["network"] for r in results}]
    return False, f"FAIL: fp32 max rel err > {TOLERANCE:g} or error on {', '.join(parts)} (checked: {names})"


def table(results: list[dict], info: dict) -> str:
    head = ("network", "shape", "fp32 max abs", "fp32 max rel", "bf16 max rel", "JAX ms", "torch ms", "ratio",
            "JAX compile s")
    rows = []
    for r in results:
        if "error" in r:
            rows.append((r["network"], "-", "error: " + r["error"][:60], "", "", "", "", "", ""))
            continue
        rows.append((r["network"], "×".join(map(str, r["input_shape"])), f"{r['fp32_max_abs']:.2e}",
                     f"{r['fp32_max_rel']:.2e}", f"{r['bf16_max_rel']:.2e}", f"{r['jax_ms']:.1f}",
                     f"{r['torch_ms']:.1f}", f"{r['ratio']:.2f}", f"{r['jax_compile_s']:.1f}"))
    widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(head)]
    fmt = lambda row: "  ".join(c.ljust(w) if i < 2 else c.rjust(w)  # noqa: E731
                                for i, (c, w) in enumerate(zip(row, widths)))
    lines = [f"check_parity: size {info['size']}, resolution {info['resolution']}, median of {info['repeats']}, "
             f"{info['threads']} threads; jax {info['jax']} ({info['jax_backend']}, {info['device_kind']}), "
             f"torch {info['torch']}",
             fmt(head), fmt(tuple("-" * w for w in widths))] + [fmt(r) for r in rows]
    lines.append("shapes are PyTorch-layout inputs; rel = max |ours - torch fp32| / max |torch fp32|; "
                 "ratio = JAX / torch time (fp32)")
    lines.append(f"{info['cpu']}, {info['cpus_available']} CPUs; total {info['wall_s']:.0f} s, "
                 f"peak RSS {info['peak_rss_gib']:.1f} GiB")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    threads_note = limit_threads(args.threads)
    progress(f"size {args.size}, resolution {args.resolution}, {args.threads} threads ({threads_note})")
    checker = Checker(args)
    results = checker.run()
    info = machine_info(args, threads_note)
    info["peak_rss_gib"] = round(peak_rss_gib(), 2)
    info["wall_s"] = round(time.perf_counter() - _T0, 1)
    ok, line = summary(results)
    if args.json:
        print(json.dumps(dict(machine=info, tolerance=TOLERANCE, passed=ok, networks=results), indent=2))
    else:
        print(table(results, info))
    print(line, flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
