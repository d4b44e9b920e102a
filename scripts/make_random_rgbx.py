"""Write a random-weight RGB↔X folder in the real diffusers format (nothing downloaded).

    python scripts/make_random_rgbx.py --size={tiny,full} --out=DIR [--seed=0]

`full` has the real RGB↔X architecture (UNet 865M, VAE 84M, CLIP text 340M parameters,
about 5 GB of fp32 safetensors) with random weights: use it to time loading, estimation and
distillation at real size without the licensed weights. Its outputs are meaningless images.
The tokenizer is a tiny CLIP BPE vocabulary. Needs the test extras (torch, diffusers,
transformers).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=("tiny", "full"), default="tiny")
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    import tiny_rgbx

    start = time.perf_counter()
    sizes = dict(unet=tiny_rgbx.RGBX_UNET, vae=tiny_rgbx.RGBX_VAE, text=tiny_rgbx.RGBX_TEXT) if args.size == "full" else {}
    folder = tiny_rgbx.write_tiny_rgbx(args.out, seed=args.seed, **sizes)
    total = sum(p.stat().st_size for p in folder.rglob("*.safetensors"))
    print(f"wrote {folder} ({total / 2**30:.2f} GiB of safetensors) in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
