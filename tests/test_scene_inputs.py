"""Bad scene inputs stop when the scene is read, before any compute, naming file and field:
non-object scene.json, truncated images, channels an image's role cannot use, non-finite or
negative linear photos; and every image is decoded once."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

import dataset_fixtures as fx
from jaxdistill import datasets
from jaxdistill.io import images as imageio
from jaxdistill.datasets.common import ImportOptions
from jaxdistill.errors import InputError
from jaxdistill.engine.problem import read_target
from jaxdistill.scene.model import read_scene
from tiny_scene import write_tiny_scene


@pytest.fixture
def scene(tmp_path):
    return write_tiny_scene(tmp_path / "tiny", views=2, gt=False)


@pytest.mark.parametrize("doc, kind", [([{"format": "jaxdistill-scene"}], "a list (of 1 items)"),
                                       ("scene", "a string"), (3, "a number"), (None, "null")])
def test_a_scene_json_that_is_not_an_object_is_named(tmp_path, doc, kind):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        read_scene(path)
    assert str(err.value).endswith(f"{path}: (top level): expected a JSON object {{\"format\": \"jaxdistill-scene\", "
                                   f"\"version\": 1, \"mesh\": ..., \"views\": [...]}}, got {kind}; see the scene "
                                   "format in README.md (Inputs)")


def truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_truncated_images_are_named_when_the_scene_is_read(scene):
    root = scene.parent
    truncate(root / "targets" / "albedo" / "v0.png")
    truncate(root / "photos" / "v1.exr")
    with pytest.raises(InputError) as err:
        read_scene(scene)
    text = str(err.value)
    assert "invalid input (2 problems)" in text
    assert (f"{scene}: views[0].targets.albedo: {root}/targets/albedo/v0.png: cannot read pixels (truncated or "
            "damaged file?): ") in text
    assert f"{scene}: views[1].photo: {root}/photos/v1.exr: cannot read pixels (truncated or damaged file?)" in text
    assert text.count("re-export or re-download it") == 2


def test_a_truncated_jpeg_that_decodes_with_a_warning_is_refused(tmp_path):
    path = tmp_path / "a.jpg"
    imageio.write_image(path, np.random.default_rng(0).uniform(size=(48, 64, 3)))
    truncate(path)
    with pytest.raises(OSError, match=r"a\.jpg: cannot read pixels \(truncated or damaged file\?\): JPEG error: "
                                      r"Premature end of JPEG file"):
        imageio.read_image(path)


def set_image(scene, view, field, name, pixels, **kw):
    doc = json.loads(scene.read_text())
    path = scene.parent / name
    imageio.write_image(path, pixels, **kw)
    entry = doc["views"][view]
    if "." in field:
        key, map_name = field.split(".")
        entry[key][map_name] = name
    else:
        entry[field] = name
    scene.write_text(json.dumps(doc))
    return path


def test_grey_alpha_targets_grey_normals_and_grey_photos_are_refused(scene):
    grey_alpha = np.full((24, 32, 2), 0.5, np.float32)
    set_image(scene, 0, "targets.albedo", "albedo_ga.png", grey_alpha)
    set_image(scene, 0, "targets.roughness", "rough_ga.png", grey_alpha, encode_srgb=False)
    set_image(scene, 1, "targets.normal", "normal_grey.png", np.full((24, 32, 1), 0.5), encode_srgb=False)
    set_image(scene, 1, "photo", "photo_grey.exr", np.full((24, 32, 1), 0.5))
    with pytest.raises(InputError) as err:
        read_scene(scene)
    lines = str(err.value).splitlines()[1:]
    root = scene.parent
    assert sorted(line.strip() for line in lines) == sorted([
        f"{scene}: views[0].targets.albedo: {root}/albedo_ga.png has 2 channels (grey + alpha): its use is "
        "ambiguous; save it without alpha, as RGB or grey",
        f"{scene}: views[0].targets.roughness: {root}/rough_ga.png has 2 channels (grey + alpha): its use is "
        "ambiguous; save it without alpha, as grey",
        f"{scene}: views[1].targets.normal: {root}/normal_grey.png is grey (1 channel); a normal map needs 3 "
        "channels, (n + 1) / 2 as RGB: save it as RGB",
        f"{scene}: views[1].photo: {root}/photo_grey.exr has 1 channel (grey); RGB↔X needs a colour photo: save it "
        "as RGB"])


def test_a_grey_albedo_target_is_used_as_rgb_and_said_so(scene, caplog):
    grey = np.random.default_rng(1).uniform(0.1, 0.9, (24, 32, 1)).astype(np.float32)
    grey_path = set_image(scene, 0, "targets.albedo", "albedo_grey.png", grey, encode_srgb=False)  # codes = grey
    rgb_path = scene.parent / "albedo_rgb.png"
    imageio.write_image(rgb_path, np.repeat(grey, 3, axis=-1), encode_srgb=False)
    with caplog.at_level(logging.INFO):
        read_scene(scene)
    notes = [(r.levelno, r.getMessage()) for r in caplog.records]
    assert notes == [(logging.INFO, f"{scene}: views[0].targets.albedo: grey image used as R = G = B (albedo_grey.png)")]
    values = read_target("albedo", grey_path)
    assert values.shape == (24, 32, 3)
    np.testing.assert_array_equal(values, read_target("albedo", rgb_path))   # the same file saved as RGB
    code = np.round(grey * 255) / 255                                          # 8-bit sRGB code values
    reference = np.where(code <= 0.04045, code / 12.92, ((code + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(values, np.repeat(reference, 3, axis=-1), rtol=1e-3, atol=1e-3)


def test_notes_of_many_views_are_one_line(tmp_path, caplog):
    scene = write_tiny_scene(tmp_path / "s", views=3, gt=False)
    for v in range(3):
        set_image(scene, v, "targets.irradiance", f"irr_{v}.png", np.full((24, 32, 1), 0.5))
    with caplog.at_level(logging.INFO):
        read_scene(scene)
    assert [r.getMessage() for r in caplog.records] == [
        f"{scene}: views[*].targets.irradiance (3 views): grey image used as R = G = B (irr_0.png; irr_1.png; irr_2.png)"]


def test_linear_photos_non_finite_refused_negative_clamped_with_a_warning(scene, caplog):
    photo = imageio.read_image(scene.parent / "photos" / "v0.exr")
    negative = photo.copy()
    negative[2, 3, 0], negative[5, 7] = -0.25, -0.01
    set_image(scene, 0, "photo", "photos/v0_negative.exr", negative)
    noise = photo.copy()
    noise[1, 1, 1] = -1e-6 * np.percentile(photo, 99)                          # a renderer's rounding
    set_image(scene, 1, "photo", "photos/v1_noise.exr", noise)
    with caplog.at_level(logging.INFO):
        loaded = read_scene(scene)
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.WARNING, f"{scene}: views[0].photo: negative values clamped to 0, as RGB↔X sees the photo x "
                          "2**exposure clipped to [0, 1] (v0_negative.exr: 4, min -0.25)"),
        (logging.INFO, f"{scene}: views[1].photo: negative values at noise level (above -0.001 x the photo's 99th "
                       f"percentile) clamped to 0 (v1_noise.exr: 1, min {noise.min():.3g})")]
    assert imageio.read_photo_srgb(loaded.views[0].photo)[2, 3, 0] == 0.0
    broken = photo.copy()
    broken[4, 6, 1], broken[9, 1, 2] = np.nan, np.inf
    set_image(scene, 1, "photo", "photos/v1_nan.exr", broken)
    with pytest.raises(InputError) as err:
        read_scene(scene)
    assert str(err.value).endswith(f"{scene}: views[1].photo: {scene.parent}/photos/v1_nan.exr has 2 NaN/inf pixels "
                                   "(first at row 4, column 6); fix or re-render the image")


def test_dataset_imports_decode_every_photo_before_any_compute(tmp_path):
    cams = fx.ground_truth_cameras(3)
    root = fx.write_fipt(tmp_path / "fipt", cams, ldr=True)
    photo = sorted((root / "train" / "Image").glob("*.png"))[1]
    truncate(photo)
    with pytest.raises(InputError, match=r"transforms\.json: view 001_0001\.photo: .*001_0001\.png: cannot read pixels \(truncated or damaged file\?\)"):
        datasets.load("iris", root, ImportOptions(work_dir=str(tmp_path / "work"), progress=False))


def test_cached_reads_decode_each_file_once_and_hand_out_private_copies(tmp_path, monkeypatch):
    path = tmp_path / "a.png"
    imageio.write_image(path, np.full((4, 5, 3), 0.5), encode_srgb=False)      # code value 128
    calls = []
    decode = imageio._decode
    monkeypatch.setattr(imageio, "_decode", lambda p: calls.append(p) or decode(p))
    with imageio.cached_reads():
        first = imageio.read_image(path, linear=False)
        first[:] = 0.0                                              # the caller's copy
        again = imageio.read_image(path)                            # linear: decoded from the cached values
        with imageio.cached_reads():                                # nested: the same cache
            imageio.read_image(path)
    assert len(calls) == 1
    np.testing.assert_allclose(again, imageio.srgb_to_linear(np.full((4, 5, 3), 128 / 255)), rtol=1e-6)
    imageio.read_image(path)
    assert len(calls) == 2                                          # no cache outside the block


def hypersim_stops(photos) -> float:
    """Hypersim's tone-map rule written out: the stops that bring the 90th percentile of the
    brightness 0.3 R + 0.59 G + 0.11 B of all pixels to 0.8 after a 1/2.2 gamma."""
    brightness = np.concatenate([(p[..., :3] @ np.array([0.3, 0.59, 0.11])).ravel() for p in photos])
    return float(np.log2(0.8 ** 2.2 / np.percentile(brightness, 90)))


def test_hdr_photos_without_an_exposure_are_warned_with_the_rules_stops(scene, caplog):
    darker = []
    for v in range(2):
        photo = imageio.read_image(scene.parent / "photos" / f"v{v}.exr") * 0.05      # 4.3 stops under
        set_image(scene, v, "photo", f"photos/v{v}_dark.exr", photo)
        darker.append(imageio.read_image(scene.parent / "photos" / f"v{v}_dark.exr"))
    stops = hypersim_stops(darker)
    assert stops > 3.0
    with caplog.at_level(logging.WARNING):
        read_scene(scene)
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.WARNING, f"{scene}: views[*].exposure: no view gives an exposure, so the prior sees these HDR photos "
                          f"as they are (0 stops), but Hypersim's rule, which RGB<->X was trained with, gives "
                          f"{stops:+.2f} stops: add \"exposure\": {stops:.2f} to every view (scripts/import_scene.py "
                          "and the dataset loaders do), or \"exposure\": 0 to every view to keep them as they are "
                          "(2 HDR photos)")]
    caplog.clear()
    doc = json.loads(scene.read_text())
    for entry in doc["views"]:
        entry["exposure"] = 0
    scene.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        read_scene(scene)
    assert caplog.records == []
