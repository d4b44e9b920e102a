"""Write a random-weight RGB↔X folder in the real diffusers format (nothing downloaded).

    python scripts/make_random_rgbx.py --size={tiny,full} --out=DIR [--seed=0]

`full` has the real RGB↔X architecture (UNet 865M, VAE 84M, CLIP text 340M parameters,
about 5 GB of fp32 safetensors) with random weights: use it to time loading, estimation and
distillation at real size without the licensed weights. Its outputs are meaningless images.
The tokenizer is the prior's tiny CLIP BPE vocabulary. The folder is written by
`jaxdistill.models.training.random_model`. Needs the test extras (torch, diffusers, transformers).
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=("tiny", "full"), default="tiny")
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from jaxdistill.models.training import random_model

    start = time.perf_counter()
    sizes = dict(unet=random_model.RGBX_UNET, vae=random_model.RGBX_VAE, text=random_model.RGBX_TEXT) if args.size == "full" else {}
    folder = random_model.write_tiny_rgbx(args.out, seed=args.seed, **sizes)
    total = sum(p.stat().st_size for p in folder.rglob("*.safetensors"))
    print(f"wrote {folder} ({total / 2**30:.2f} GiB of safetensors) in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
