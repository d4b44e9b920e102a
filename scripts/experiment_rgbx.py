"""The distillation experiment with a learned prior (the thesis's Table 5.1), on CPU.

    python scripts/experiment_rgbx.py --scenes=bedroom,data/heldout_scenes/room_0 --out=out/experiment
    python scripts/experiment_rgbx.py ... --runs=sds_thesis --set=sds_thesis:steps=200    # one row, changed

For every scene, with one RGB<->X-family model (default: the model shipped in the package), the
rows of one table, every one scored against the scene's ground truth at the photos' size by
the main job's own evaluation (`jaxdistill.evaluate.ground_truth`):

- `trivial`: the photo as albedo (linear, clipped), the training data's mean roughness and
  metallic, normals facing the camera, the photo's luminance as irradiance;
- `estimates`: the model's per-view estimates (`model_estimates`: the demo's 50 DDIM steps at
  the render size), each view on its own;
- `estimates_mean`: the same with 1 DDIM step from t = 999, i.e. the model's conditional mean
  (zero terminal SNR), not a draw from its posterior;
- `fusion`: those estimates fused by the `views` prior (the scene with the estimates as its
  per-view targets);
- `sds_*`: score distillation with the model through the rgbx prior, at the settings of
  `RUNS` (thesis: its settings except the number of steps; default: configs/bedroom.cfg's);
  ablations are more entries of `RUNS` or `--set`.

Every run writes OUT/<scene>/<run>/metrics.json, recording the row's settings (scene, model,
the run's settings) and the code version (a digest of the package's and this script's source;
the git commit beside it, for reading). A row that has one is reused, so the script resumes,
but only when both equal the current run's: otherwise the script stops, naming the row file
and what differs (delete the file, or give another --out, to compute the row again).
OUT/table.json and OUT/table.md gather the rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import jaxdistill
from jaxdistill.io import checkpoint, images as imageio
from jaxdistill.evaluate import ground_truth as evaluation
from jaxdistill.export.run_dir import json_safe
from jaxdistill.models import estimates as model_estimates
from jaxdistill import pipeline
from jaxdistill.engine.config import DistillConfig, validate
from jaxdistill.datasets import ImportOptions, open_scene
from jaxdistill.models import convert
from jaxdistill.models import prior as rgbx
from jaxdistill.models.shipped import model_info, shipped_folder
from jaxdistill.models.training.heldout import trivial_linear
from jaxdistill.engine.problem import render_shape
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import write_scene
from jaxdistill.io.view_images import read_target, resize

MAPS = ("albedo", "normal", "roughness", "metallic", "irradiance")
RENDER_SIZE = 128

# main-job settings shared by the rows (configs/bedroom.cfg's, at the model's resolution)
COMMON = dict(maps=MAPS, render_size=RENDER_SIZE, texture_size="auto", max_texture_size=512, sampler="trilinear",
              log_every=10, eval_every=0, renders=False, contact_views=4, ckpt_every=0,
              estimate_steps=model_estimates.ESTIMATE_STEPS)   # the table's 50, as its estimates row
RUNS = {
    "fusion": dict(prior="views", steps=100, views_per_step=32, lr=0.05, lr_schedule="cosine"),
    # the thesis's settings (configs/thesis.cfg) but for the number of steps: batch 1, lr 0.01
    # constant, weight decay 0.01, t in [0.2, 0.98], w_t = w_i = 1, image-space loss, visibility
    "sds_thesis": dict(prior="rgbx", steps=800, views_per_step=1, lr=0.01, lr_schedule="constant", weight_decay=0.01,
                       t_min=0.2, t_max=0.98, anneal="none", w_t=1.0, w_i=1.0, loss_space="image",
                       visibility_weighting=True, sampler="bilinear"),
    "sds": dict(prior="rgbx", steps=100, views_per_step=16, lr=0.05, lr_schedule="cosine", t_min=0.2, t_max=0.98),
    # the ablations' base: sds at half the steps and views (a quarter of the time); vary it with
    # --set=abl+NAME:field=value (e.g. abl+latent:loss_space=latent)
    "abl": dict(prior="rgbx", steps=50, views_per_step=8, lr=0.05, lr_schedule="cosine", t_min=0.2, t_max=0.98),
}


def score(scene, per_view: list[dict]) -> dict:
    """Mean metrics over views of per-view file-space maps (native size) against the scene's GT."""
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], progress=False)
    gt, gt_maps = evaluation.view_ground_truth(scene, frags)
    if gt_maps is None:
        raise SystemExit(f"{scene.root}: no ground truth (gt.json or views' ground_truth): nothing to score")
    return evaluation.evaluate(per_view, gt_maps, evaluation.evaluation_masks(gt, scene, frags))


def trivial_maps(scene) -> list[dict]:
    return [trivial_linear(np.clip(imageio.read_image(v.photo)[..., :3] * 2.0 ** v.exposure, 0.0, 1.0))
            for v in scene.views]


def estimates_folder(scene, model_dir: Path, steps: int = model_estimates.ESTIMATE_STEPS) -> Path:
    model = rgbx.load_prior(convert.load_rgbx(model_dir))
    h, w = render_shape(scene, RENDER_SIZE, 8)
    return model_estimates.cached_estimates(model, [(v.name, v.photo, v.exposure) for v in scene.views], MAPS, h, w,
                                            steps=steps)


def fusion_scene(scene, folder: Path, out: Path) -> Path:
    """A copy of scene.json (same mesh, photos, GT) whose per-view targets are the estimates,
    resampled to the photos' size (targets must match their view) in the scene-target encoding."""
    views = []
    for v in scene.views:
        targets = {}
        for m in MAPS:
            values = resize(read_target(m, folder / m / f"{v.name}.png"), v.camera.height, v.camera.width)
            if m == "normal":
                values = (values + 1.0) / 2.0
            targets[m] = out / "targets" / m / f"{v.name}.png"
            imageio.write_image(targets[m], np.clip(values, 0.0, 1.0), encode_srgb=m in rgbx.GAMMA_MAPS)
        views.append(dataclasses.replace(v, targets=targets))
    views = tuple(views)
    write_scene(dataclasses.replace(scene, views=views), out)
    gt = Path(scene.root) / "gt.json"
    if gt.is_file():       # gt.json names its textures relative to its folder: point them back at the scene
        doc = json.loads(gt.read_text())
        for m, per_object in doc.get("textures", {}).items():
            doc["textures"][m] = {o: str((Path(scene.root) / p).resolve()) for o, p in per_object.items()}
        (out / "gt.json").write_text(json.dumps(doc, indent=1))
    return out


def run_main(scene_path: Path, out: Path, model_dir: Path, settings: dict) -> dict:
    """One main-job row; a row an earlier sitting stopped (SIGINT/SIGTERM: checkpoint saved) resumes."""
    resume = (out / "checkpoints").is_dir() and checkpoint.CheckpointStore(out / "checkpoints").latest_step() is not None
    config = validate(DistillConfig(scene=str(scene_path), out_dir=str(out), rgbx_dir=str(model_dir),
                                    allow_outside_paths=True, resume=resume, **{**COMMON, **settings}))
    start = time.perf_counter()
    result = pipeline.run(config)
    result["experiment_wall_seconds"] = time.perf_counter() - start
    return result


def code_version() -> dict:
    """This code's version: `source_sha256`, a digest of every .py file of the package and of this
    script (names and bytes), which rows are compared on; the package version and the git commit
    (None outside a checkout) only for reading."""
    package = Path(jaxdistill.__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")) + [Path(__file__).resolve()]:
        name = path.relative_to(package.parent) if package.parent in path.parents else path.name
        digest.update(f"{Path(name).as_posix()}\0".encode() + path.read_bytes() + b"\0")
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=package.parent, capture_output=True, text=True,
                                timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    return {"source_sha256": digest.hexdigest(), "package": jaxdistill.__version__, "git_commit": commit}


def row_settings(run: str, scene, model_dir: Path, runs: dict) -> dict:
    """What a row's figures depend on, besides the code: the scene and, but for `trivial`, the
    model and the run's settings (estimates: DDIM steps at the render size; main-job rows: the
    DistillConfig fields this script sets)."""
    settings = {"run": run, "scene": str(Path(scene.root).resolve())}
    if run == "trivial":
        return settings
    settings["model"] = model_info(Path(model_dir).resolve())
    if run in ("estimates", "estimates_mean"):
        steps = 1 if run == "estimates_mean" else model_estimates.ESTIMATE_STEPS
        return {**settings, "maps": list(MAPS), "render_size": RENDER_SIZE, "ddim_steps": steps}
    config = {**COMMON, **runs[run], "views_per_step": min(runs[run]["views_per_step"], len(scene.views))}
    if config["prior"] == "views":      # fused: the targets are the model's estimates
        settings["estimates"] = {"render_size": RENDER_SIZE, "ddim_steps": model_estimates.ESTIMATE_STEPS}
    return {**settings, "config": config}


def differences(recorded, current, where: str = "") -> list[str]:
    """'key: <recorded> in the row, <current> now' for every leaf where two JSON documents differ."""
    if isinstance(recorded, dict) and isinstance(current, dict):
        return [line for key in sorted(set(recorded) | set(current), key=str)
                for line in differences(recorded.get(key, "(absent)"), current.get(key, "(absent)"),
                                        f"{where}.{key}" if where else str(key))]
    return [] if recorded == current else [f"{where}: {json.dumps(recorded)} in the row, {json.dumps(current)} now"]


def check_reusable(path: Path, row_doc: dict, settings: dict, code: dict) -> None:
    """SystemExit naming `path` and what differs, unless the row was made with these settings by
    this code (the same source digest)."""
    current = json.loads(json.dumps(json_safe(settings)))
    if "code_version" not in row_doc or not isinstance(row_doc.get("settings"), dict):
        problems = ["it records no settings and code version (written before rows recorded them)"]
    else:
        problems = differences(row_doc["settings"], current, "settings")
        made_by = row_doc["code_version"].get("source_sha256")
        if made_by != code["source_sha256"]:
            problems.append(f"code version: source sha256 {made_by} (git {row_doc['code_version'].get('git_commit')}) "
                            f"in the row, {code['source_sha256']} (git {code['git_commit']}) now")
    if problems:
        raise SystemExit(f"{path}: not reused, it was not made by this run's settings and code:\n  "
                         + "\n  ".join(problems) + f"\ndelete {path} (or give another --out) to compute the row again")


def row(metrics: dict | None) -> dict:
    keys = ("albedo_psnr", "albedo_ssim", "albedo_si_psnr", "albedo_si_ssim", "normal_angular_deg", "roughness_mse",
            "metallic_mse", "irradiance_si_psnr", "albedo_shading_leak")
    return {k: metrics.get(k) for k in keys} if metrics else {}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", required=True, help="comma-separated scene folders ('bedroom' = embedded)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--rgbx_dir", type=Path, default=None, help="model folder (default: the shipped model)")
    parser.add_argument("--runs", default="trivial,estimates,fusion,sds_thesis,sds",
                        help=f"rows: trivial, estimates, estimates_mean and any of {', '.join(RUNS)}")
    parser.add_argument("--set", action="append", default=[], help="RUN:field=value (a DistillConfig field); "
                        "RUN = BASE+NAME starts from BASE's settings")
    args = parser.parse_args(argv)
    model_dir = args.rgbx_dir or shipped_folder()
    if model_dir is None:
        raise SystemExit("--rgbx_dir: no model given and none shipped in this installation")
    runs = {k: dict(v) for k, v in RUNS.items()}
    for item in args.set:
        name, _, assignment = item.partition(":")
        field, _, value = assignment.partition("=")
        base = runs.setdefault(name, dict(runs.get(name.split("+")[0], {})))
        kind = type(DistillConfig.__dataclass_fields__[field].default)
        base[field] = (value.lower() in ("1", "true", "yes")) if kind is bool else kind(value)
    table, code = {}, code_version()
    for spec in args.scenes.split(","):
        scene = open_scene(spec, ImportOptions(allow_outside_paths=True))
        name = Path(spec).name
        folder = args.out / name
        folder.mkdir(parents=True, exist_ok=True)
        rows = table.setdefault(name, {})
        for run in args.runs.split(","):
            if run not in ("trivial", "estimates", "estimates_mean") and run not in runs:
                raise SystemExit(f"--runs: unknown run {run!r}")
            path = folder / run / "metrics.json"
            settings = row_settings(run, scene, model_dir, runs)
            if path.is_file():
                check_reusable(path, json.loads(path.read_text()), settings, code)
            else:
                print(f"== {name}: {run}", flush=True)
                start = time.perf_counter()
                if run == "trivial":
                    result = {"ours": score(scene, trivial_maps(scene))}
                elif run in ("estimates", "estimates_mean"):
                    est = estimates_folder(scene, model_dir, 1 if run == "estimates_mean" else model_estimates.ESTIMATE_STEPS)
                    shapes = [(v.camera.height, v.camera.width) for v in scene.views]
                    result = {"ours": score(scene, model_estimates.read_estimates(
                        est, [v.name for v in scene.views], MAPS, shapes)), "folder": str(est)}
                else:
                    scene_path = Path(scene.root)
                    if runs[run]["prior"] == "views":
                        scene_path = fusion_scene(scene, estimates_folder(scene, model_dir), folder / "fusion_scene")
                    result = run_main(scene_path, folder / run, model_dir, settings["config"])
                    if result.get("stopped_by"):       # SIGINT/SIGTERM: checkpoint saved, the row is not done
                        print(f"== {name}: {run} stopped by {result['stopped_by']}; rerun to resume it", flush=True)
                        return result["exit_status"]
                result["seconds"] = time.perf_counter() - start
                result["settings"], result["code_version"] = settings, code
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(json_safe(result), indent=1))
            result = json.loads(path.read_text())
            rows[run] = dict(row(result.get("ours")), seconds=result.get("seconds"),
                             rerender_psnr=(result.get("rerender") or {}).get("psnr_db"))
    doc = {"model": model_info(model_dir), "table": table}
    (args.out / "table.json").write_text(json.dumps(doc, indent=1))
    (args.out / "table.md").write_text(markdown(table))
    plot(table, args.out / "speed_vs_error.png")
    print(markdown(table))
    return 0


def plot(table: dict, path: Path) -> None:
    """Albedo PSNR against wall time, one marker per row and scene (the speed-against-error view)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for scene, rows in table.items():
        points = [(v["seconds"], v["albedo_psnr"], run) for run, v in rows.items()
                  if v.get("seconds") and v.get("albedo_psnr") is not None]
        if not points:
            continue
        ax.scatter([p[0] for p in points], [p[1] for p in points], label=scene)
        for x, y, run in points:
            ax.annotate(run, (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("wall time of the row (s, 2-core CPU)")
    ax.set_ylabel("albedo PSNR vs GT (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def markdown(table: dict) -> str:
    cols = [("albedo_psnr", "albedo PSNR"), ("albedo_si_psnr", "si-PSNR"), ("albedo_ssim", "SSIM"),
            ("albedo_si_ssim", "si-SSIM"), ("normal_angular_deg", "normal °"), ("roughness_mse", "rough. L2"),
            ("metallic_mse", "metal. L2"), ("irradiance_si_psnr", "irr. si-PSNR"), ("albedo_shading_leak", "shading leak β"),
            ("seconds", "wall s")]
    lines = ["| scene | row | " + " | ".join(c for _, c in cols) + " |", "|" + "---|" * (len(cols) + 2)]
    for scene, rows in table.items():
        for run, values in rows.items():
            cells = [("—" if values.get(k) is None else f"{values[k]:.3f}" if "mse" in k or "ssim" in k
                      else f"{values[k]:.2f}") for k, _ in cols]
            lines.append(f"| {scene} | {run} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
