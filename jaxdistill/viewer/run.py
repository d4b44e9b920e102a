"""A run's out_dir as the viewer reads it, finished or still running (no viser here).

A finished run (metrics.json written) shows its `maps/` EXR pages and `evidence/`; a running
one shows the texels of its newest committed checkpoint, turned into the same pages with
`texel_space.npz` (`run_files`), or the initial texels before the first checkpoint. The scene
(mesh, views, ground truth) is read again from the run's `--scene` (or the viewer's `--scene`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
import numpy as np

from jaxdistill import MAP_NAMES
from jaxdistill.io import checkpoint, images as imageio
from jaxdistill.evaluate import ground_truth as evaluation, metrics
from jaxdistill.export import pages as page_files, run_dir as run_files
from jaxdistill.errors import InputError
from jaxdistill.scene.maps import MapChannels
from jaxdistill.scene.model import Scene

EVIDENCE_KINDS = ("visibility", "disagreement")


@dataclasses.dataclass(frozen=True)
class Snapshot:
    """The maps as of one moment of the run: file-space pages per map, where they come from."""

    pages: dict            # map -> list of (S, S, C) float32 pages
    source: str            # e.g. "maps/ (finished run)", "checkpoint of step 40"
    step: int | None
    finished: bool


def committed_steps(directory: Path) -> list[int]:
    """Steps of the committed checkpoints in `directory` (none while it does not exist)."""
    if not directory.is_dir():
        return []
    return sorted(int(p.name) for p in directory.iterdir() if p.name.isdigit() and checkpoint.is_committed(p))


class RunDir:
    """An out_dir of `python -m jaxdistill.main`; InputError (naming the folder or file and what
    to do) when it is not one."""

    def __init__(self, out_dir, scene: str | None = None):
        self.out = Path(out_dir)
        if not self.out.is_dir():
            raise InputError.single(self.out, "OUT_DIR", "no such folder; give the --out_dir of a run of "
                                    "python -m jaxdistill.main (finished or running)")
        metrics_doc = self._metrics()
        live = run_files.read_texel_space(self.out) if (self.out / run_files.TEXEL_SPACE_FILE).is_file() else None
        if metrics_doc is None and live is None:
            raise InputError.single(self.out, "OUT_DIR", "not a run's out_dir yet: it has neither metrics.json nor "
                                    f"{run_files.TEXEL_SPACE_FILE}; start the run (python -m jaxdistill.main "
                                    f"--out_dir={self.out}) and point the viewer at it once its set-up is done")
        self.live = live
        self.config = dict(metrics_doc["config"]) if metrics_doc else dict(live.config)
        self.maps = [m for m in MAP_NAMES if m in self.config["maps"]]
        self.channels = MapChannels(tuple(self.maps))
        self.scene = self._read_scene(scene)
        if live is not None:
            self.object_page = list(live.space.layout.object_page)
        else:
            self.object_page = (list(range(self.scene.num_objects)) if self.scene.texture_layout == "pages"
                                else [0] * self.scene.num_objects)
        self.stems = page_files.page_names(self.scene.mesh.object_names, self.object_page)
        self._fragments = {}

    # -- what the run has written --------------------------------------------------------------

    def _metrics(self) -> dict | None:
        path = self.out / "metrics.json"
        if not path.is_file():
            return None
        try:
            return json.loads(path.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, OSError):     # being written right now: read it next time
            return None

    def _read_scene(self, override: str | None) -> Scene:
        from jaxdistill.datasets import open_scene
        from jaxdistill.engine.config import import_options

        spec = override or self.config["scene"]
        try:     # the run's own dataset flags (--mesh, --exposure, ...): the scene it distilled
            return open_scene(spec, import_options(self.config))
        except InputError as err:
            raise InputError(err.problems + [(str(self.out), "--scene", f"the run's scene {spec!r} does not read "
                                              "from here; run the viewer from the run's folder or give --scene")]) \
                from None

    def finished(self) -> bool:
        return self._metrics() is not None

    def version(self) -> tuple:
        """Changes whenever the maps or the history the viewer shows may have changed."""
        def stamp(path: Path):
            return path.stat().st_mtime_ns if path.exists() else None

        steps = committed_steps(self.out / "checkpoints")
        return (stamp(self.out / "metrics.json"), steps[-1] if steps else None,
                stamp(self.out / "checkpoints" / "history.json"))

    def snapshot(self) -> Snapshot:
        """The newest maps: `maps/` of a finished run, else the newest checkpoint's texels."""
        doc = self._metrics()
        if doc is not None:
            pages = {m: self._read_pages(self.out / "maps", m) for m in self.maps}
            return Snapshot(pages, "maps/ (finished run)", doc.get("steps"), True)
        live = self.live or run_files.read_texel_space(self.out)
        steps = committed_steps(self.out / "checkpoints")
        if steps:
            with checkpoint.CheckpointStore(self.out / "checkpoints") as store:
                texels = store.read_texels(steps[-1])
            source, step = f"checkpoint of step {steps[-1]}", steps[-1]
        else:
            texels = live.channels.initial_texels(live.space.num_texels)
            source, step = "initial texels (no checkpoint yet; set --ckpt_every to see progress)", 0
        pages = {m: run_files.map_pages(m, texels, live.channels, live.space, live.trust) for m in self.maps}
        return Snapshot(pages, source, step, False)

    def _read_pages(self, root: Path, name: str) -> list[np.ndarray]:
        pages = []
        for p in range(len(self.stems)):
            path = page_files.page_file(root, name, self.stems, p, ".exr")
            if not path.is_file():
                raise InputError.single(path, "(file)", f"missing: the run's {name} map is not there (was the "
                                        "out_dir moved or cleaned?); rerun the distillation")
            pages.append(imageio.read_image(path))
        return pages

    def evidence(self, kind: str, name: str) -> list[np.ndarray] | None:
        """Pages of `evidence/visibility` or `evidence/disagreement_<name>`, None when the run
        has not written them (still running, or no per-view estimates)."""
        stem = "visibility" if kind == "visibility" else f"disagreement_{name}"
        root = self.out / page_files.EVIDENCE_DIR
        if not page_files.page_file(root, stem, self.stems, 0, ".exr").is_file():
            return None
        return self._read_pages(root, stem)

    def history(self) -> dict | None:
        """The loss and albedo PSNR history: metrics.json's, else the newest checkpoint's."""
        doc = self._metrics()
        if doc is not None and doc.get("history"):
            return doc["history"]
        path = self.out / "checkpoints" / "history.json"
        try:
            return json.loads(path.read_text()) if path.is_file() else None
        except json.JSONDecodeError:
            return None

    def summary(self) -> dict:
        """metrics.json's aggregate metrics of ours and of the per-view estimates ({} while running)."""
        doc = self._metrics() or {}
        return {k: doc[k] for k in ("ours", "baseline_per_view_estimates", "baseline_source", "steps",
                                    "wall_seconds", "prior") if k in doc}

    # -- one view ----------------------------------------------------------------------------

    def one_view(self, index: int) -> Scene:
        """The scene with view `index` alone (evaluation pairs a scene's views with fragments)."""
        return dataclasses.replace(self.scene, views=(self.scene.views[index],))

    def fragments(self, index: int):
        if index not in self._fragments:
            from jaxdistill.render.fragments import compute_fragments

            self._fragments[index] = compute_fragments(self.scene.mesh, [self.scene.views[index].camera],
                                                       progress=False)[0]
        return self._fragments[index]

    def view_images(self, index: int, pages: dict) -> dict[str, dict[str, np.ndarray | None]]:
        """For view `index`, per map, the file-space images (at the photo's size) of the per-view
        estimate, ours (the pages sampled through the view, normals in RGB<->X camera space as
        the estimates have them) and GT (None where the run has none)."""
        from jaxdistill.scene.cameras import rgbx_camera_rotation
        from jaxdistill.render.sampler import sample_pages

        view = self.scene.views[index]
        frag = self.fragments(index)
        stacked = [np.concatenate([pages[m][p] for m in self.maps], axis=-1) for p in range(len(self.stems))]
        ours = self.channels.split(sample_pages(stacked, [frag], self.object_page)[0])
        if "normal" in ours:
            ours["normal"] = ours["normal"] @ rgbx_camera_rotation(view.camera.c2w).astype(np.float32)
        ours = {m: np.where(frag.hit[..., None], x, 0.0) for m, x in ours.items()}
        _, gt = evaluation.view_ground_truth(self.one_view(index), [frag])
        estimates = self._estimates(index, frag.shape)
        return {m: {"estimate": None if estimates is None else estimates.get(m), "ours": ours[m],
                    "gt": None if gt is None else gt[0].get(m)} for m in self.maps}

    def _estimates(self, index: int, shape: tuple[int, int]) -> dict | None:
        doc = self._metrics() or {}
        if doc.get("estimates_folder"):
            from jaxdistill.models.estimates import read_estimates

            folder = Path(doc["estimates_folder"])
            name = self.scene.views[index].name
            if all((folder / m / f"{name}.png").is_file() for m in self.maps):
                return read_estimates(folder, [name], self.maps, [shape])[0]
            return None
        if self.config.get("prior_kind") == "rgbx":
            return None                       # the model's estimates are made at the end of the run
        baseline = evaluation.read_baseline(self.one_view(index), self.maps, [shape])
        return None if baseline is None else baseline[0]

    def view_metrics(self, index: int, images: dict) -> dict[str, dict[str, float]]:
        """{"ours": metrics, "estimate": metrics} of view `index` against its GT ({} without GT)."""
        gt = {m: v["gt"] for m, v in images.items() if v["gt"] is not None}
        if not gt:
            return {}
        scene_gt = evaluation.read_ground_truth(self.scene)
        mask = evaluation.evaluation_masks(scene_gt, self.one_view(index), [self.fragments(index)])[0]
        out = {"ours": metrics.evaluate_view({m: v["ours"] for m, v in images.items()}, gt, mask)}
        if all(v["estimate"] is not None for v in images.values()):
            out["estimate"] = metrics.evaluate_view({m: v["estimate"] for m, v in images.items()}, gt, mask)
        return out


def photo(scene: Scene, index: int) -> np.ndarray:
    """(H, W, 3) sRGB display values of view `index`'s photo."""
    view = scene.views[index]
    return imageio.read_photo_srgb(view.photo, view.exposure)

