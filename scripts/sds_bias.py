"""Where the prior's SDS targets pull a *perfect* texture: x̂0 of ground-truth renders, per t.

    python scripts/sds_bias.py --scenes=bedroom,data/heldout_scenes/room_0 [--out=docs/data/sds_bias.json]
        [--plot=docs/img/sds_bias.png]

SDS moves each render towards x_pred = decode(x̂0(noise_t(encode(render)), photo)). At the
ground truth, an unbiased prior would return the ground truth on average; what it returns
instead is the pull SDS applies to a texture that is already right. At t = 999 (zero terminal SNR:
no trace of the render is left) x̂0 is the model's conditional mean of the map given the photo,
the best single guess in PSNR terms, to compare with its 50-step samples (the estimates). For each scene, its views
at the model's render size (the main job's `render_shape`), ground-truth albedo from the
evaluation's own sources, and each t of a grid (plus t = 0: the VAE round trip alone), this
prints and writes:

- `scale`: mean over valid pixels of x_pred / mean of GT (linear albedo, all channels): below 1
  the prior darkens a correct texture, above 1 it brightens it;
- `psnr`: albedo PSNR of x_pred against GT, as the main job scores albedo (sRGB, data range 1);
- the same two for the model's own estimates (50 DDIM steps) and for the photo as albedo.

Noise is drawn per view from --seed; the guidance is eq. 4.2's with the given weights.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxdistill.io import images as imageio
from jaxdistill.evaluate import metrics
from jaxdistill.models import estimates as model_estimates
from jaxdistill.datasets import ImportOptions, open_scene
from jaxdistill.evaluate.ground_truth import evaluation_masks, view_ground_truth
from jaxdistill.models import convert
from jaxdistill.models import prior as rgbx
from jaxdistill.models import scheduler as sched
from jaxdistill.models.shipped import shipped_folder
from jaxdistill.engine.problem import render_shape
from jaxdistill.render import fragments as fr
from jaxdistill.io.view_images import resize

T_GRID = (0, 100, 200, 350, 500, 650, 800, 900, 980, 999)


def scene_arrays(spec: str, render_size: int):
    """(photos sRGB (V, h, w, 3), GT linear albedo (V, h, w, 3), masks (V, h, w) bool, scene) at the render size."""
    scene = open_scene(spec, ImportOptions(allow_outside_paths=True))
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], progress=False)
    gt, gt_maps = view_ground_truth(scene, frags)
    if gt_maps is None or "albedo" not in gt_maps[0]:
        raise SystemExit(f"{spec}: no albedo ground truth")
    masks = evaluation_masks(gt, scene, frags)
    h, w = render_shape(scene, render_size, 8)
    photos = np.stack([resize(imageio.read_photo_srgb(v.photo, v.exposure), h, w) for v in scene.views])
    albedo = np.stack([resize(g["albedo"], h, w) for g in gt_maps])
    keep = np.stack([resize(m[..., None].astype(np.float32), h, w)[..., 0] > 0.999 for m in masks])
    return np.clip(photos, 0, 1), np.clip(albedo, 0, 1), keep, scene


def stats(pred_linear: np.ndarray, gt_linear: np.ndarray, masks: np.ndarray) -> dict:
    """Mean scale ratio and albedo PSNR (the main job's metric) over views."""
    scale = float(np.mean([p[m].mean() / max(g[m].mean(), 1e-6) for p, g, m in zip(pred_linear, gt_linear, masks)]))
    psnr = float(np.mean([metrics.evaluate_view({"albedo": p}, {"albedo": g}, m)["albedo_psnr"]
                          for p, g, m in zip(pred_linear, gt_linear, masks)]))
    return {"scale": round(scale, 4), "psnr": round(psnr, 3)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", required=True)
    parser.add_argument("--rgbx_dir", type=Path, default=None)
    parser.add_argument("--render_size", type=int, default=128)
    parser.add_argument("--w_t", type=float, default=1.0)
    parser.add_argument("--w_i", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--plot", type=Path, default=None, help="PNG of scale and PSNR over t")
    args = parser.parse_args(argv)
    folder = args.rgbx_dir or shipped_folder()
    model = rgbx.load_prior(convert.load_rgbx(folder))
    vae, unet = model.networks.vae, model.networks.unet
    guidance = rgbx.Guidance(args.w_t, args.w_i)
    alphas = sched.alphas_cumprod(model.scheduler)
    text = model.text["albedo"]
    x0_fn = jax.jit(lambda z_t, t, photo: rgbx.predict_x0(unet, model.scheduler, model.params["unet"], z_t, t, photo,
                                                            text, guidance))
    doc = {"guidance": [args.w_t, args.w_i], "t": list(T_GRID), "scenes": {}}
    for spec in args.scenes.split(","):
        photos, gt, masks, scene = scene_arrays(spec, args.render_size)
        v, h, w = gt.shape[:3]
        photo_lat = rgbx.encode_images(vae, model.params["vae"], rgbx.photo_to_model_space(photos))
        z0 = rgbx.encode_images(vae, model.params["vae"], jnp.asarray(2.0 * gt - 1.0))
        rows = {}
        for t in T_GRID:
            if t == 0:
                x0 = z0
            else:
                noise = jax.random.normal(jax.random.fold_in(jax.random.key(args.seed), t), z0.shape)
                z_t = sched.add_noise(z0, noise, alphas[t])
                x0 = x0_fn(z_t, jnp.full((v,), t, jnp.int32), photo_lat)
            pred = (np.asarray(rgbx.decode_latents(vae, model.params["vae"], x0)) + 1.0) / 2.0
            rows[str(t)] = stats(pred, gt, masks)
            print(f"{Path(spec).name}: t={t:4d}  x_pred/GT mean {rows[str(t)]['scale']:.3f}  "
                  f"PSNR {rows[str(t)]['psnr']:.2f} dB", flush=True)
        est_folder = model_estimates.cached_estimates(model, [(x.name, x.photo, x.exposure) for x in scene.views],
                                                      ("albedo",), h, w)
        est = np.stack([e["albedo"] for e in model_estimates.read_estimates(
            est_folder, [x.name for x in scene.views], ("albedo",), [(h, w)] * v)])
        entry = {"x_pred_at_gt": rows, "estimates": stats(est, gt, masks),
                 "photo_as_albedo": stats(imageio.srgb_to_linear(photos), gt, masks), "views": v, "size": [h, w]}
        print(f"{Path(spec).name}: estimates {entry['estimates']}  photo as albedo {entry['photo_as_albedo']}")
        doc["scenes"][Path(spec).name] = entry
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=1))
    if args.plot:
        plot(doc, args.plot)
    return 0


def plot(doc: dict, path: Path) -> None:
    """Two panels over t: x_pred's mean scale against GT, and its albedo PSNR; the estimates as
    dashed lines (drawn at t = 1000, where sampling starts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for name, entry in doc["scenes"].items():
        ts = [int(t) for t in entry["x_pred_at_gt"]]
        line, = a.plot(ts, [r["scale"] for r in entry["x_pred_at_gt"].values()], marker="o", label=name)
        b.plot(ts, [r["psnr"] for r in entry["x_pred_at_gt"].values()], marker="o", color=line.get_color())
        a.axhline(entry["estimates"]["scale"], ls="--", lw=0.8, color=line.get_color())
        b.axhline(entry["estimates"]["psnr"], ls="--", lw=0.8, color=line.get_color())
    a.axhline(1.0, color="k", lw=0.6)
    a.set(xlabel="t (x_pred of the noised GT render)", ylabel="mean x_pred / mean GT (linear albedo)",
          title="scale SDS pulls a correct texture to")
    b.set(xlabel="t", ylabel="albedo PSNR of x_pred vs GT (dB)", title="x_pred's error (dashed: 50-step estimates)")
    a.legend(fontsize=8)
    for ax in (a, b):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
