"""The networks' layers on XLA's CPU backend: each of our formulations against the plain one it
replaces, side by side in one process, at the shapes of the full-size RGB↔X and of the shipped
model (docs/benchmarks.md section 1, "The layers on the CPU"):

    python scripts/bench_layers.py --repeats=5 --json=docs/data/bench_layers.json

- 3×3 convolution: `layers.convolve_valid` (a product of patches, Winograd's F(2×2, 3×3) or XLA's
  convolution, chosen by shape) against `lax.conv_general_dilated`, as `nn.Conv`;
- GroupNorm: `layers.group_norm` (per-channel sums, then per group) against the statistics taken
  over (H, W, C / G) of the grouped array, as before;
- nearest ×2 upsampling and a 3×3 convolution: `layers.UpsampleConv` (four 2×2 phase convolutions
  of the input) against the upsampled image convolved;
- `winograd`: `layers.winograd_3x3` forced at shapes below its thresholds, against XLA's convolution;
- `resize_then_conv`: the upsampled image convolved by `convolve_valid` (Winograd where it applies)
  against XLA's convolution of it.

Each case is jitted, run once, then timed `--repeats` times per side, the two sides alternating;
prints the medians, their ratio (ours / plain) and the largest difference relative to the plain
result's largest value. `--quick` runs small shapes (a check that the script works, not a figure);
`--cases` picks cases by kind or place.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.models import layers

# (kind, where the shape occurs, shape (B, H, W, C), output channels (GroupNorm: groups))
CASES = [
    ("conv3x3", "RGB↔X UNet, 3×4 latent", (1, 3, 4, 2560), 1280),
    ("conv3x3", "RGB↔X UNet, 6×8 latent", (1, 6, 8, 2560), 1280),
    ("conv3x3", "RGB↔X UNet, 12×16 latent", (1, 12, 16, 1280), 640),
    ("conv3x3", "RGB↔X UNet, 24×32 latent", (1, 24, 32, 640), 320),
    ("conv3x3", "RGB↔X VAE, 64×48", (1, 48, 64, 512), 512),
    ("conv3x3", "RGB↔X VAE, 128×96", (1, 96, 128, 512), 256),
    ("conv3x3", "RGB↔X VAE, 128×96", (1, 96, 128, 256), 256),
    ("conv3x3", "RGB↔X VAE, 256×192", (1, 192, 256, 128), 128),
    ("conv3x3", "shipped VAE, 40 × 128×96", (40, 96, 128, 32), 16),
    ("conv3x3", "shipped VAE, 40 × 32×24", (40, 24, 32, 64), 64),
    ("conv3x3", "shipped VAE, 40 × 16×12", (40, 12, 16, 64), 64),
    ("conv3x3", "shipped UNet, 40 × 8×6", (40, 6, 8, 64), 64),
    ("conv3x3", "shipped VAE, 16 × 32×24 (estimates)", (16, 24, 32, 64), 64),
    ("group_norm", "shipped VAE, 40 × 128×96", (40, 96, 128, 32), 16),
    ("group_norm", "shipped VAE, 40 × 64×48", (40, 48, 64, 64), 16),
    ("group_norm", "RGB↔X VAE, 256×192", (1, 192, 256, 128), 32),
    ("group_norm", "RGB↔X VAE, 128×96", (1, 96, 128, 256), 32),
    ("upsample", "RGB↔X VAE, 32×24 → 64×48", (1, 24, 32, 512), 512),
    ("upsample", "RGB↔X VAE, 64×48 → 128×96", (1, 48, 64, 512), 512),
    ("upsample", "RGB↔X VAE, 128×96 → 256×192", (1, 96, 128, 256), 256),
    ("upsample", "shipped VAE, 40 × 16×12 → 32×24", (40, 12, 16, 64), 64),
    ("upsample", "shipped VAE, 40 × 64×48 → 128×96", (40, 48, 64, 32), 32),
    # Winograd forced where its thresholds keep it off (why they are where they are), and the ×2
    # upsampling convolved after the resize by `convolve_valid` (Winograd where it applies)
    ("winograd", "RGB↔X VAE, 32×24 (768 pixels)", (1, 24, 32, 512), 512),
    ("winograd", "shipped VAE, 40 × 64×48, 64 → 32", (40, 48, 64, 64), 32),
    ("winograd", "shipped VAE, 40 × 128×96, 32 → 16", (40, 96, 128, 32), 16),
    ("winograd", "shipped UNet, 40 × 16×12, 32", (40, 12, 16, 32), 32),
    ("resize_then_conv", "RGB↔X VAE, 32×24 → 64×48", (1, 24, 32, 512), 512),
    ("resize_then_conv", "RGB↔X VAE, 64×48 → 128×96", (1, 48, 64, 512), 512),
    ("resize_then_conv", "RGB↔X VAE, 128×96 → 256×192", (1, 96, 128, 256), 256),
    ("resize_then_conv", "shipped VAE, 40 × 16×12 → 32×24", (40, 12, 16, 64), 64),
]
QUICK = [
    ("conv3x3", "patches", (1, 2, 3, 64), 128), ("conv3x3", "direct", (2, 8, 8, 8), 8),
    ("group_norm", "small", (2, 8, 8, 16), 4), ("upsample", "small", (2, 4, 4, 8), 8),
    ("winograd", "small", (1, 8, 8, 8), 8), ("resize_then_conv", "small", (1, 4, 4, 8), 8),
]


def _direct(image, kernel):
    return jax.lax.conv_general_dilated(image, kernel, (1, 1), ((1, 1), (1, 1)),
                                        dimension_numbers=("NHWC", "HWIO", "NHWC"))


def _grouped_norm(x, scale, bias, groups):
    """GroupNorm with the statistics over (H, W, C / G) of the (B, H, W, G, C / G) array (the plain form)."""
    grouped = x.reshape(x.shape[:-1] + (groups, x.shape[-1] // groups))
    axes = tuple(range(1, grouped.ndim - 2)) + (grouped.ndim - 1,)
    mean = grouped.mean(axis=axes, keepdims=True)
    var = jnp.square(grouped - mean).mean(axis=axes, keepdims=True)
    return ((grouped - mean) * jax.lax.rsqrt(var + 1e-6)).reshape(x.shape) * scale + bias


def sides(kind: str, shape: tuple, size: int, rng: np.random.Generator):
    """(ours, plain, arguments) of one case."""
    x = rng.normal(size=shape).astype(np.float32)
    if kind == "group_norm":
        channels = shape[-1]
        scale, bias = rng.uniform(0.5, 1.5, channels).astype(np.float32), rng.normal(size=channels).astype(np.float32)
        return (lambda x, s, b: layers.group_norm(x, s, b, size, 1e-6),
                lambda x, s, b: _grouped_norm(x, s, b, size), (x, scale, bias))
    kernel = (rng.normal(size=(3, 3, shape[-1], size)) / np.sqrt(9 * shape[-1])).astype(np.float32)
    upsampled = lambda image: jnp.repeat(jnp.repeat(image, 2, axis=1), 2, axis=2)  # noqa: E731
    if kind == "conv3x3":
        return (lambda x, k: layers.convolve_valid(layers.pad_one(x), k), _direct, (x, kernel))
    if kind == "winograd":
        return (lambda x, k: layers.winograd_3x3(layers.pad_one(x), k), _direct, (x, kernel))
    if kind == "resize_then_conv":
        return (lambda x, k: layers.convolve_valid(layers.pad_one(upsampled(x)), k), lambda x, k: _direct(upsampled(x), k),
                (x, kernel))
    params = {"params": {"kernel": kernel, "bias": np.zeros(size, np.float32)}}
    module = layers.UpsampleConv(size)
    return (lambda x, p: module.apply(p, x),
            lambda x, p: _direct(upsampled(x), p["params"]["kernel"]), (x, params))


def time_case(kind: str, shape: tuple, size: int, repeats: int) -> dict:
    ours, plain, args = sides(kind, shape, size, np.random.default_rng(0))
    ours, plain = jax.jit(ours), jax.jit(plain)
    got, want = np.asarray(ours(*args)), np.asarray(plain(*args))
    seconds = {"ours": [], "plain": []}
    for _ in range(repeats):
        for name, fn in (("plain", plain), ("ours", ours)):
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            seconds[name].append(time.perf_counter() - start)
    medians = {name: statistics.median(s) for name, s in seconds.items()}
    return {"kind": kind, "shape": list(shape), "out": size, "plain_s": medians["plain"], "ours_s": medians["ours"],
            "ratio": medians["ours"] / medians["plain"],
            "max_rel_diff": float(np.abs(got - want).max() / np.abs(want).max())}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="small shapes: checks the script, measures nothing")
    parser.add_argument("--json", type=Path, help="write the rows here")
    parser.add_argument("--cases", default="", help="comma-separated substrings: only the cases whose 'kind place' "
                        "holds one of them (e.g. 'RGB↔X UNet,group_norm'); default: all")
    args = parser.parse_args(argv)
    wanted = [c for c in args.cases.split(",") if c]
    cases = [c for c in (QUICK if args.quick else CASES) if not wanted or any(w in f"{c[0]} {c[1]}" for w in wanted)]
    if not cases:
        parser.error(f"--cases={args.cases}: no case matches")
    if jax.default_backend() != "cpu":
        parser.error(f"the choices measured here are the CPU backend's; JAX runs on {jax.default_backend()}")
    rows = []
    print(f"{'kind':<11} {'where':<34} {'shape':<22} {'out/G':>5} {'plain ms':>9} {'ours ms':>8} {'ratio':>6} {'rel diff':>9}")
    for kind, where, shape, size in cases:
        row = {"where": where, **time_case(kind, shape, size, args.repeats)}
        rows.append(row)
        print(f"{kind:<11} {where:<34} {'x'.join(map(str, shape)):<22} {size:>5} {1e3 * row['plain_s']:>9.1f} "
              f"{1e3 * row['ours_s']:>8.1f} {row['ratio']:>6.2f} {row['max_rel_diff']:>9.1e}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "repeats": args.repeats, "cpu_count": os.cpu_count(),
                                         "platform": platform.platform()}, indent=1) + "\n")
    return rows


if __name__ == "__main__":
    main()
