"""The exported pages' push-pull fill (`render.sampler.push_pull`), this checkout's against another
revision's, side by side on the pages of a finished run (docs/benchmarks.md section 10):

    python scripts/bench_push_pull.py --run=OUT_DIR --against=HEAD~1 --map=albedo --repeats=3

The pages are those `maps/` was written from: the run's texel space (`texel_space.npz`), the
texels of its last checkpoint and each texel's trust, expanded to full pages (`run_dir.map_pages`
before its fill). Prints, for the largest page and the one nearest 512² (the default run's cap), the median seconds of
each side, their ratio and the largest difference between the two results.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

from jaxdistill.engine.problem import initial_file_values
from jaxdistill.export import run_dir
from jaxdistill.io.checkpoint import CheckpointStore
from jaxdistill.render import sampler
from jaxdistill.scene.maps import model_to_file

REPO = Path(__file__).resolve().parents[1]


def sampler_at(revision: str):
    """`jaxdistill/render/sampler.py` as it was at `revision`, loaded as its own module."""
    source = subprocess.run(["git", "show", f"{revision}:jaxdistill/render/sampler.py"], cwd=REPO, check=True,
                            capture_output=True, text=True).stdout
    module = types.ModuleType("sampler_then")
    exec(compile(source, f"{revision}:jaxdistill/render/sampler.py", "exec"), module.__dict__)
    return module


def run_pages(run: Path, name: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(page, weight) of every page of map `name`, before the fill."""
    saved = run_dir.read_texel_space(run)
    if name not in saved.channels.maps:
        sys.exit(f"--map={name}: the run distilled {', '.join(saved.channels.maps)}")
    texels = CheckpointStore(run / "checkpoints").read_texels()
    values = model_to_file(name, texels[:, saved.channels.slice(name)])
    pages = sampler.expand(values, saved.space, initial_file_values([name])[name], dilation=0)
    weights = sampler.expand(saved.trust.astype(np.float32)[:, None], saved.space, 0.0, dilation=0)
    return [(p, w[..., 0]) for p, w in zip(pages, weights)]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a finished run's out_dir")
    parser.add_argument("--against", default="HEAD~1", help="the git revision to compare with")
    parser.add_argument("--map", default="albedo")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    then = sampler_at(args.against)
    pages = sorted(run_pages(args.run, args.map), key=lambda pw: pw[0].shape[0])
    small = min(pages, key=lambda pw: abs(pw[0].shape[0] - 512))        # the bedroom's page size
    for label, (page, weight) in (("largest", pages[-1]), ("nearest 512", small)):
        before, after = [], []
        for _ in range(args.repeats):           # alternated, so both sides see the same machine
            t = time.perf_counter()
            old = then.push_pull(page, weight)
            before.append(time.perf_counter() - t)
            t = time.perf_counter()
            new = sampler.push_pull(page, weight)
            after.append(time.perf_counter() - t)
        b, a = statistics.median(before), statistics.median(after)
        print(f"{label} page {page.shape[0]}x{page.shape[1]}x{page.shape[2]}: {args.against} {b:.2f} s, "
              f"this checkout {a:.2f} s, ratio {b / a:.2f}x, max |difference| {np.abs(old - new).max():.2e}")


if __name__ == "__main__":
    main()
