"""A scene's `gt.json` (format "jaxdistill-gt": per-object ground-truth texture pages, normals
from the geometry, objects left out of the metrics), read and checked, and which ground-truth
maps a scene's views have, known before any compute (`ground_truth_maps`: what the evaluation's
files of them take). `evaluate.ground_truth` makes the per-view maps from them."""

from __future__ import annotations

from pathlib import Path

from jaxdistill.errors import InputError, ProblemList, read_json
from jaxdistill.scene.maps import CHANNELS
from jaxdistill.scene.model import Scene, image_problems

GT_FORMAT = "jaxdistill-gt"


def read_gt_document(root: Path | None) -> dict | None:
    """The parsed `root/gt.json` when it is in our format (else None); InputError naming the
    file and field when it cannot be ground truth (no map in it, unknown maps, not an object).
    Needs no scene: `train.run` calls it before any compute."""
    if root is None or not (Path(root) / "gt.json").is_file():
        return None
    path = Path(root) / "gt.json"
    doc = read_json(path, "missing")
    if not isinstance(doc, dict) or doc.get("format") != GT_FORMAT:
        return None
    textures = doc.get("textures", {})
    if not isinstance(textures, dict) or not all(isinstance(v, dict) for v in textures.values()):
        raise InputError.single(path, "textures", "expected {map: {object: image path}}")
    if not textures and doc.get("normal") != "geometry":
        raise InputError.single(path, "textures", "no ground-truth texture for any map (and \"normal\" is not "
                                "\"geometry\"): add textures, or delete gt.json so that the views' ground_truth "
                                "images are used")
    for name in textures:
        if name not in CHANNELS or name == "normal":
            raise InputError.single(path, f"textures.{name}", "GT textures can be albedo, roughness, metallic or "
                                    "irradiance (normals come from the geometry with \"normal\": \"geometry\")")
    return doc


def ground_truth_maps(scene: Scene) -> dict[str, int]:
    """{map: channels} of every map some view's ground truth has (those of
    `evaluate.ground_truth.view_ground_truth`, without reading an image): gt.json's textures and
    geometry normals, and the views' `ground_truth` images; {} without ground truth. What the
    evaluation's `view_rows.MapRows` files hold, sized before compute."""
    doc = read_gt_document(scene.root)
    names = set(doc.get("textures", {})) | ({"normal"} if doc.get("normal") == "geometry" else set()) if doc else set()
    names |= {m for v in scene.views for m in v.ground_truth}
    return {m: CHANNELS[m] for m in sorted(names)}


def check_gt_textures(scene: Scene) -> None:
    """InputError naming gt.json and each texture's field, before any compute, when a texture it
    names is missing, unreadable or has channels its map cannot use (a grey albedo or irradiance is
    used as R = G = B, as targets are; 2 channels are refused); headers only, no pixel read. Nothing
    without a gt.json in our format."""
    doc = read_gt_document(scene.root)
    if doc is None:
        return
    problems = ProblemList()
    for name, per_object in doc.get("textures", {}).items():
        for obj, rel in per_object.items():
            if not isinstance(rel, str):
                problems.add(str(scene.root / "gt.json"), f"textures.{name}.{obj}", "expected an image path")
                continue
            image_problems(scene.root / rel, f"textures.{name}.{obj}", None, str(scene.root / "gt.json"), problems,
                           check_pixels=False, role=name)
    problems.raise_if_any()
