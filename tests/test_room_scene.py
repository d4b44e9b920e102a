"""scripts/make_room_scene.py end to end on a tiny held-out room: the folder loads with our own
loader, its ground truth covers the five maps, photo = albedo x irradiance on diffuse pixels,
it regenerates identically, --targets_from relinks the targets, bad arguments are refused."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from jaxdistill.io import images as imageio
from jaxdistill.evaluate.ground_truth import evaluation_masks, read_ground_truth, view_ground_truth  # noqa: E402
from jaxdistill.render import fragments as fr  # noqa: E402
from jaxdistill.scene.model import read_scene  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

import make_room_scene  # noqa: E402

ARGS = ["--split=heldout", "--index=0", "--views=2", "--width=32", "--height=24", "--spp=16", "--variant=scalar_rgb"]


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    out = tmp_path_factory.mktemp("room") / "room_0"
    assert make_room_scene.main(ARGS + [f"--out={out}"]) == 0
    return out


def test_scene_loads_with_five_gt_maps_and_photo_is_albedo_times_irradiance(room):
    scene = read_scene(room)
    assert len(scene.views) == 2 and scene.name == "room_1000000"
    gt_doc = read_ground_truth(scene)
    assert set(gt_doc.pages) == {"albedo", "roughness", "metallic"} and gt_doc.geometry_normals
    assert all("bulb" in o or "light" in o for o in gt_doc.exclude_objects)
    frags = fr.compute_fragments(scene.mesh, [v.camera for v in scene.views], cache_dir=False)
    _, gt = view_ground_truth(scene, frags)
    masks = evaluation_masks(gt_doc, scene, frags)
    assert all(set(g) == {"albedo", "normal", "roughness", "metallic", "irradiance"} for g in gt)
    info = json.loads((room / "room.json").read_text())
    assert info["seed"] == 1_000_000 and all(v.exposure == info["exposure_stops"] for v in scene.views)

    # independently of the script's own figure: the files, our GT sampler at pixel centres
    photos = [imageio.read_image(v.photo)[..., :3] for v in scene.views]
    diffuse = [make_room_scene.diffuse_mask(m, g["roughness"], g["metallic"], make_room_scene.view_cosine(v.camera, g["normal"]))
               for m, g, v in zip(masks, gt, scene.views)]
    check = make_room_scene.consistency(photos, [g["albedo"] for g in gt], [g["irradiance"] for g in gt], diffuse)
    assert check["pixels"] > 100
    assert 0.85 < check["median_ratio"] < 1.15, check      # 16 spp and pixel-centre albedo: noisy, not biased
    assert 0.8 < info["consistency"]["diffuse"]["median_ratio"] < 1.2
    assert (room / "preview.jpg").is_file() and "seed 1000000" in (room / "README.md").read_text()


def test_regenerates_identically_and_relinks_estimates(room, tmp_path):
    again = tmp_path / "again"
    assert make_room_scene.main(ARGS + [f"--out={again}"]) == 0
    for rel in ("scene.json", "gt.json", "photos/view_001.exr", "ground_truth/irradiance/view_000.exr",
                "gt/textures/albedo/floor.png", "targets/albedo/view_000.png"):
        assert (again / rel).read_bytes() == (room / rel).read_bytes(), rel

    estimates = tmp_path / "est"                     # what jaxdistill.estimate writes: OUT/<map>/<view>.png
    for name in ("view_000", "view_001"):
        imageio.write_image(estimates / "albedo" / f"{name}.png", np.full((24, 32, 3), 0.5))
        imageio.write_image(estimates / "normal" / f"{name}.png", np.full((24, 32, 3), 0.5), encode_srgb=False)
    photo = (again / "photos" / "view_000.exr").read_bytes()
    assert make_room_scene.main(ARGS + [f"--out={again}", f"--targets_from={estimates}"]) == 0
    assert (again / "photos" / "view_000.exr").read_bytes() == photo            # relinked, not re-rendered
    scene = read_scene(again)
    assert {m: p.relative_to(again).as_posix() for m, p in scene.views[1].targets.items()} == {
        "albedo": "estimates/albedo/view_001.png", "normal": "estimates/normal/view_001.png"}
    assert json.loads((again / "room.json").read_text())["targets"]["maps"] == ["albedo", "normal"]

    (estimates / "normal" / "view_001.png").unlink()
    assert make_room_scene.main(ARGS + [f"--out={again}", f"--targets_from={estimates}"]) == 2


@pytest.mark.parametrize("extra, message", [
    (["--index=-1"], "outside the heldout split's range"),
    (["--index=1000000"], "outside the heldout split's range"),
    (["--split=train"], "held-out rooms only"),
    (["--width=30"], "multiple of 8"),
    (["--spp=0"], "--spp must be >= 1"),
])
def test_bad_arguments_are_refused(tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit):
        make_room_scene.main(ARGS + [f"--out={tmp_path / 'x'}"] + extra)
    assert message in capsys.readouterr().err


def test_refuses_a_folder_it_did_not_make(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit):
        make_room_scene.main(ARGS + [f"--out={tmp_path}"])
    assert "not a scene this script made" in capsys.readouterr().err and (tmp_path / "notes.txt").exists()
