"""The LDR copy of a scene: 8-bit sRGB photos of the exposed, clipped linear photos; all else the same."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxdistill.datasets.ldr import write_ldr_scene
from jaxdistill.evaluate.ground_truth import read_ground_truth
from jaxdistill.io import images as imageio
from jaxdistill.scene.model import read_scene
from tiny_scene import write_tiny_scene


def srgb_codes(linear, stops):
    """8-bit codes of IEC 61966-2-1 sRGB of the linear photo x 2**stops clipped to [0, 1], written out here."""
    x = np.clip(np.asarray(linear, np.float64) * 2.0 ** stops, 0.0, 1.0)
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.round(encoded * 255.0)


@pytest.fixture()
def tiny(tmp_path):
    source = tmp_path / "tiny"
    write_tiny_scene(source, views=3)
    doc = json.loads((source / "scene.json").read_text())
    for k, entry in enumerate(doc["views"]):       # exposures of both signs, and one that clips a lot
        entry["exposure"] = [0.5, -1.0, 1.5][k]
    (source / "scene.json").write_text(json.dumps(doc))
    return source


def test_ldr_copy_photos_are_srgb_codes_of_the_exposed_clipped_photo(tiny, tmp_path):
    out = tmp_path / "ldr"
    write_ldr_scene(tiny, out)
    source, copy = read_scene(tiny), read_scene(out)
    clipped = 0.0
    for a, b in zip(source.views, copy.views):
        assert b.exposure == 0.0 and a.exposure != 0.0
        assert b.photo.suffix == ".png" and b.photo.parent == out / "photos"
        want = srgb_codes(imageio.read_image(a.photo)[..., :3], a.exposure)
        got = np.round(imageio.read_image(b.photo, linear=False)[..., :3] * 255.0)
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= 1                     # float32 vs float64 at rounding ties
        assert np.mean(got == want) > 0.999
        clipped = max(clipped, float(np.mean(want == 255)))
        np.testing.assert_array_equal(a.camera.K, b.camera.K)
        np.testing.assert_array_equal(a.camera.c2w, b.camera.c2w)
        assert set(a.targets) == set(b.targets)
        for m in a.targets:
            assert a.targets[m].read_bytes() == b.targets[m].read_bytes()
            assert b.targets[m].is_relative_to(out)
    assert clipped > 0.01                                      # the test exposes some pixels past 1
    np.testing.assert_array_equal(source.mesh.vertices, copy.mesh.vertices)
    np.testing.assert_array_equal(source.mesh.uv, copy.mesh.uv)
    gt_a, gt_b = read_ground_truth(source), read_ground_truth(copy)
    assert set(gt_a.pages) == set(gt_b.pages) == {"albedo", "roughness", "metallic"}
    for m in gt_a.pages:
        for x, y in zip(gt_a.pages[m], gt_b.pages[m]):
            np.testing.assert_array_equal(x, y)
    assert gt_a.geometry_normals == gt_b.geometry_normals and gt_a.exclude_objects == gt_b.exclude_objects
    record = json.loads((out / "ldr.json").read_text())
    assert set(record["views"]) == {v.name for v in source.views}


def test_ldr_copy_refuses_a_folder_in_use(tiny, tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "x.txt").write_text("x")
    with pytest.raises(ValueError, match="not empty"):
        write_ldr_scene(tiny, out)


def test_jittered_ldr_copy_applies_each_views_recorded_exposure_and_white_balance(tiny, tmp_path):
    out = tmp_path / "phone"
    write_ldr_scene(tiny, out, exposure_jitter=1.0, white_balance_jitter=0.1, seed=3)
    record = json.loads((out / "ldr.json").read_text())
    assert record["exposure_jitter"] == 1.0 and record["white_balance_jitter"] == 0.1 and record["seed"] == 3
    source, copy = read_scene(tiny), read_scene(out)
    offsets = []
    for a, b in zip(source.views, copy.views):
        entry = record["views"][a.name]
        offset, balance = entry["exposure_offset"], np.asarray(entry["white_balance"])
        assert -1.0 <= offset <= 1.0
        assert np.prod(balance) == pytest.approx(1.0, rel=1e-5)           # a cast, not a brightness change
        assert np.abs(np.log(balance)).max() > 1e-3
        offsets.append(offset)
        linear = imageio.read_image(a.photo)[..., :3].astype(np.float64) * balance
        want = srgb_codes(linear, a.exposure + offset)
        got = np.round(imageio.read_image(b.photo, linear=False)[..., :3] * 255.0)
        assert np.abs(got - want).max() <= 1
        assert np.mean(got == want) > 0.999
    assert len(set(offsets)) == len(offsets)                               # each view its own exposure
    again = tmp_path / "phone_again"
    write_ldr_scene(tiny, again, exposure_jitter=1.0, white_balance_jitter=0.1, seed=3)
    assert json.loads((again / "ldr.json").read_text())["views"] == record["views"]   # the seed decides


@pytest.mark.parametrize("field", ["exposure_jitter", "white_balance_jitter"])
def test_ldr_copy_refuses_a_negative_jitter(tiny, tmp_path, field):
    with pytest.raises(ValueError, match=field):
        write_ldr_scene(tiny, tmp_path / "x", **{field: -0.5})
