"""Write a capture-sized synthetic room: a ~1M-face mesh and a walk of N views at a chosen size.

    python scripts/make_capture_scene.py --out=DIR [--faces_per_side=300] [--views=50] \\
        [--width=876] [--height=584] [--seed=0]

The scene of scale benchmarks (`jaxdistill.datasets.synthetic_capture`): photos and per-view
target maps come from our own ray casts (no path tracer), so even hundreds of full-size views are
written in minutes. Then, for example:

    python -m jaxdistill.main --scene=DIR --prior=views --steps=20 --out_dir=out/capture
"""

from __future__ import annotations

import argparse
import json
import time


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="the scene folder to write")
    p.add_argument("--faces_per_side", type=int, default=300, help="wall subdivisions; 300 gives 1.13M faces")
    p.add_argument("--views", type=int, default=50)
    p.add_argument("--width", type=int, default=876)
    p.add_argument("--height", type=int, default=584)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    for name in ("faces_per_side", "views", "width", "height"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    from jaxdistill.datasets.synthetic_capture import write_capture_room

    start = time.perf_counter()
    summary = write_capture_room(args.out, faces_per_side=args.faces_per_side, views=args.views, width=args.width,
                                 height=args.height, seed=args.seed)
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start, 1), "out": args.out}))


if __name__ == "__main__":
    main()
