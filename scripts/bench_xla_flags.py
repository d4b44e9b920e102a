"""The package's XLA flags (`jaxdistill/xla_flags.py`) against jaxlib's own defaults, side by side.

    python scripts/bench_xla_flags.py [--rgbx_dir=DIR] [--batches=16,40] [--networks=unet,decode,encode]
        [--repeats=3] [--step] [--json=FILE]

Each case runs in a child process, since XLA reads its flags once per process: with the package's
flags (as `import jaxdistill` sets them) and with none (`JAXDISTILL_XLA_FLAGS=0`), the two
alternated `--repeats` times. A child times the model's networks at the shapes the default run
gives them (default: the shipped model; 128×96 images, 16×12 latents): the UNet's pass at each
batch of `--batches` (16: one sampling call of the per-view estimates, 40: a step's 8 views × 5
maps), the VAE decode and encode at the largest batch (`--networks` picks among the three), each
the median of 5 calls after a
compiling one. With `--step` it also builds `configs/bedroom.cfg`'s problem and step (as
`scripts/bench_photo.py` does) and times steps with the prior's pass (even) and without (odd,
x̂0 reused), 4 of each. Prints the medians per setting and their ratio, flags / defaults.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

GIVEN_XLA_FLAGS = os.environ.get("XLA_FLAGS")   # before `import jaxdistill` appends the package's flags to them

from jaxdistill.xla_flags import FLAGS  # noqa: E402

NETWORKS = ("unet", "decode", "encode")


def time_calls(fn, *args, calls: int = 5) -> float:
    """Median seconds of `calls` calls after one that compiles."""
    import jax
    jax.block_until_ready(fn(*args))
    seconds = []
    for _ in range(calls):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def networks(rgbx_dir: str | None, batches: list[int], which: tuple[str, ...] = NETWORKS) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxdistill.models import convert
    from jaxdistill.models.shipped import shipped_folder

    loaded = convert.load_rgbx(rgbx_dir or shipped_folder())
    nets, params = loaded.networks, loaded.params
    factor = nets.vae.config.downsampling_factor
    height, width = 96, 128
    latent = (height // factor, width // factor)
    unet = jax.jit(lambda p, x, c: nets.unet.apply(p, x, jnp.full((x.shape[0],), 500), c))
    decode = jax.jit(lambda p, z: nets.vae.apply(p, z, method="decode"))
    encode = jax.jit(lambda p, x: nets.vae.apply(p, x, method="encode"))
    row = {}
    for b in (batches if "unet" in which else []):
        context = jnp.ones((b, 77, nets.unet.config.cross_attention_dim))
        row[f"unet_b{b}_s"] = time_calls(unet, params["unet"], jnp.ones((b, *latent, nets.unet.config.in_channels)),
                                         context)
    b = max(batches)
    if "decode" in which:
        row[f"vae_decode_b{b}_s"] = time_calls(decode, params["vae"], jnp.ones((b, *latent, 4)))
    if "encode" in which:
        row[f"vae_encode_b{b}_s"] = time_calls(encode, params["vae"], jnp.ones((b, height, width, 3)))
    return row


def default_step(repeats: int = 4) -> dict:
    import jax
    from absl import flags

    from jaxdistill.engine import config as config_lib
    from jaxdistill.engine.loop import batch_views, step_settings
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.engine.step import data_mesh, init_state, initial_reused, jit_step, make_optimizer, make_step

    fv = flags.FlagValues()
    config_lib.define_flags(fv)
    fv(["bench", "--flagfile=configs/bedroom.cfg", "--out_dir=out/bench_xla_flags"])
    config = config_lib.config_from_flags(fv)
    problem = build_problem(config)
    optimizer = make_optimizer(config.lr, config.weight_decay, config.lr_schedule, config.steps)
    settings = step_settings(config, problem)
    first = problem.batch(batch_views(problem, config, 0))
    texels = problem.initial_texels()
    state = init_state(texels, optimizer, config.seed,
                       reused=initial_reused(problem.prior, settings, texels, first, problem.frozen))
    step, _ = jit_step(make_step(problem.prior, settings, optimizer), data_mesh(), first, state, problem.frozen)
    frozen = jax.device_put(problem.frozen)
    start = time.perf_counter()
    state, _ = step(state, first, frozen)
    jax.block_until_ready(state.texels)
    compile_s = time.perf_counter() - start
    if config.reuse_steps < 2:
        raise SystemExit(f"configs/bedroom.cfg: --reuse_steps={config.reuse_steps}; the step is timed with and "
                         "without the prior's pass, which needs --reuse_steps >= 2")
    seconds = {"prior": [], "reused": []}
    for i in range(1, config.reuse_steps * repeats + 1):
        batch = problem.batch(batch_views(problem, config, i))
        start = time.perf_counter()
        state, _ = step(state, batch, frozen)
        jax.block_until_ready(state.texels)
        seconds["prior" if i % config.reuse_steps == 0 else "reused"].append(time.perf_counter() - start)
    return {"step_compile_s": compile_s, "step_prior_s": statistics.median(seconds["prior"]),
            "step_reused_s": statistics.median(seconds["reused"])}


def child(args) -> dict:
    from jaxdistill import xla_flags  # noqa: F401  (imported first: the flags, or none, before JAX starts)
    row = {"xla_flags": os.environ.get("XLA_FLAGS", "")}
    row.update(networks(args.rgbx_dir, [int(b) for b in args.batches.split(",")], tuple(args.networks.split(","))))
    if args.step:
        row.update(default_step())
    return row


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rgbx_dir", default=None, help="model folder (default: the shipped model)")
    parser.add_argument("--batches", default="16,40")
    parser.add_argument("--networks", default=",".join(NETWORKS), help="which of unet, decode, encode to time")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--step", action="store_true", help="also the default run's step (about 2 min a child)")
    parser.add_argument("--json", default=None)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print("ROW " + json.dumps(child(args)), flush=True)
        return 0
    named = [f.split("=", 1)[0] for f in (GIVEN_XLA_FLAGS or "").split()]
    clash = [f for f in FLAGS if f.split("=", 1)[0] in named]
    if clash:
        parser.error(f"XLA_FLAGS names {', '.join(clash)} already: both settings would run it; unset it to compare")
    unknown = set(args.networks.split(",")) - set(NETWORKS)
    if unknown:
        parser.error(f"--networks: unknown {', '.join(sorted(unknown))}; choose among {', '.join(NETWORKS)}")
    cmd = [sys.executable, os.path.abspath(__file__), "--child", f"--batches={args.batches}", f"--networks={args.networks}"]
    cmd += ([f"--rgbx_dir={args.rgbx_dir}"] if args.rgbx_dir else []) + (["--step"] if args.step else [])
    rows = {"flags": [], "defaults": []}
    for _ in range(args.repeats):
        for setting in ("defaults", "flags"):
            env = dict(os.environ)           # XLA_FLAGS as given (a child's import appends the package's)
            env.pop("XLA_FLAGS", None)
            if GIVEN_XLA_FLAGS is not None:
                env["XLA_FLAGS"] = GIVEN_XLA_FLAGS
            if setting == "defaults":
                env["JAXDISTILL_XLA_FLAGS"] = "0"
            else:
                env.pop("JAXDISTILL_XLA_FLAGS", None)
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
            if proc.returncode:
                raise SystemExit(f"the {setting} child failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
            out = proc.stdout
            rows[setting].append(json.loads(next(line for line in out.splitlines() if line.startswith("ROW "))[4:]))
            print(setting, {k: round(v, 3) for k, v in rows[setting][-1].items() if k.endswith("_s")}, flush=True)
    keys = [k for k in rows["flags"][0] if k.endswith("_s")]
    medians = {s: {k: statistics.median(r[k] for r in rows[s]) for k in keys} for s in rows}
    ratios = {k: medians["flags"][k] / medians["defaults"][k] for k in keys}
    print(f"{'case':<22} {'defaults s':>10} {'flags s':>8} {'ratio':>6}")
    for k in keys:
        print(f"{k:<22} {medians['defaults'][k]:>10.3f} {medians['flags'][k]:>8.3f} {ratios[k]:>6.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "medians": medians, "ratios_flags_over_defaults": ratios,
                       "repeats": args.repeats, "cpu_count": os.cpu_count()}, f, indent=1)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
