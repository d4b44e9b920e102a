"""Mitsuba 0.5/0.6 XML upgraded to Mitsuba 3 on import; the mask BSDF's cut-outs are masked."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from conftest import look_at_camera
from jaxdistill.io import images as imageio
from jaxdistill.errors import InputError
from jaxdistill.datasets.mitsuba.upgrade import needs_upgrade, upgrade
from jaxdistill.datasets.mitsuba.upgrade_rules import camel_to_snake
from jaxdistill.render import fragments as fr
from mitsuba05_fixture import (FLOOR_ALPHA, FLOOR_RGB, LEAF_CENTRE, LEAF_RGB, LIGHT_RADIANCE, PHONG_EXPONENT,
                               WALL_SRGB_HEX, write_scene05)

mi = pytest.importorskip("mitsuba")
pytest.importorskip("xatlas")
from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba.ground_truth import GroundTruthEvaluator
from jaxdistill.datasets.mitsuba.prepare import prepare_scene
from jaxdistill.datasets.mitsuba.shapes import reconstruction_mesh
from jaxdistill.datasets.mitsuba.source import load_source


def srgb_decode(code: int) -> float:
    """IEC 61966-2-1 sRGB decoding of an 8-bit code (the reference for <srgb>)."""
    c = code / 255.0
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


@pytest.fixture(scope="module")
def scene05(tmp_path_factory) -> Path:
    return write_scene05(tmp_path_factory.mktemp("scene05"))


@pytest.fixture(scope="module")
def upgraded(scene05):
    return upgrade(ET.parse(scene05).getroot(), source=str(scene05), base_dir=scene05.parent)


def params_of(xml_text: str) -> dict:
    """{key: value} of every traversed parameter of a scene loaded from a string (scalar_rgb)."""
    mb.load_mitsuba()
    params = mi.traverse(mi.load_string(xml_text, optimize=False))
    out = {}
    for key in params.keys():
        value = params[key]
        if isinstance(value, mi.ScalarTransform4f) or isinstance(value, mi.ScalarTransform3f):
            value = value.matrix
        try:
            out[key] = np.array(value, np.float64)
        except (TypeError, ValueError):
            out[key] = value
    return out


def test_camel_to_snake_follows_mitsuba3():
    cases = {"toWorld": "to_world", "intIOR": "int_ior", "extIOR": "ext_ior", "sampleCount": "sample_count",
             "diffuseReflectance": "diffuse_reflectance", "fovAxis": "fov_axis", "alphaU": "alpha_u",
             "maxDepth": "max_depth", "uoffset": "uoffset", "to_world": "to_world", "HDR": "HDR"}
    assert {k: camel_to_snake(k) for k in cases} == cases


def test_versions():
    assert needs_upgrade(ET.fromstring('<scene version="0.5.0"/>'))
    assert needs_upgrade(ET.fromstring('<scene version="0.6"/>'))
    assert not needs_upgrade(ET.fromstring('<scene version="3.0.0"/>'))
    assert not needs_upgrade(ET.fromstring('<scene version="2.1.0"/>'))


def test_mitsuba3_refuses_the_original_and_loads_the_upgrade(scene05, upgraded):
    mb.load_mitsuba()
    with pytest.raises(RuntimeError, match="lookAt"):
        mi.load_file(str(scene05), optimize=False)
    scene = mi.load_string(upgraded.to_string(), optimize=False)
    assert {s.id() for s in scene.shapes()} == {"floor", "wall", "leaf", "ball", "light"}
    assert upgraded.root.get("version") == "3.0.0" and upgraded.source_version == "0.5.0"


def test_parameter_values_survive(upgraded):
    p = params_of(upgraded.to_string())
    wall = [srgb_decode(int(WALL_SRGB_HEX[i:i + 2], 16)) for i in (1, 3, 5)]
    np.testing.assert_allclose(p["Wall.brdf_0.reflectance.value"], wall, rtol=1e-6)
    np.testing.assert_allclose(p["Floor.diffuse_reflectance.value"], FLOOR_RGB, rtol=1e-6)
    np.testing.assert_allclose(p["Floor.alpha"], FLOOR_ALPHA, rtol=1e-6)
    np.testing.assert_allclose(p["Floor.eta"], 1.5, rtol=1e-6)                    # intIOR / extIOR
    np.testing.assert_allclose(p["Old.diffuse_reflectance.value"], [0x40 / 255, 0x20 / 255, 0x10 / 255], rtol=1e-6)
    np.testing.assert_allclose(p["Old.alpha"], math.sqrt(2.0 / (PHONG_EXPONENT + 2.0)), rtol=1e-6)
    np.testing.assert_allclose(p["Leaves.nested_bsdf.brdf_0.reflectance.value"], LEAF_RGB, rtol=1e-6)
    np.testing.assert_allclose(p["light.emitter.radiance.value"], [LIGHT_RADIANCE] * 3, rtol=1e-6)
    sensor = next(k[:-len(".x_fov")] for k in p if k.endswith(".x_fov"))
    np.testing.assert_allclose(p[sensor + ".x_fov"], 45.0, rtol=1e-6)              # fovAxis x
    np.testing.assert_array_equal(p[sensor + ".film.size"], [64, 48])
    # lookAt origin (0, 1, 3) towards (0, 1, 1): Mitsuba's camera z is the viewing direction
    np.testing.assert_allclose(np.array(p[sensor + ".to_world"])[:3, 2:], [[0, 0], [0, 1], [-1, 3]], atol=1e-6)


def test_same_scene_as_mitsuba3s_own_renaming(tmp_path, scene05):
    """Where Mitsuba 3's parser upgrades a 0.5 file itself (camelCase names, diffuse's
    diffuseReflectance, uoffset/uscale -> to_uv), our upgrade must give the same scene."""
    xml = f"""<scene version="0.5.0">
      <integrator type="path"><integer name="maxDepth" value="3"/><integer name="rrDepth" value="2"/></integrator>
      <shape type="obj" id="mesh"><string name="filename" value="{scene05.parent / 'floor.obj'}"/>
        <boolean name="faceNormals" value="true"/>
        <transform name="toWorld"><rotate y="1" angle="30"/><translate x="1" y="2" z="3"/></transform>
        <bsdf type="roughplastic"><float name="intIOR" value="1.7"/><float name="alpha" value="0.3"/>
          <rgb name="diffuseReflectance" value="0.1, 0.2, 0.3"/></bsdf></shape>
      <shape type="sphere" id="ball"><float name="radius" value="0.5"/>
        <bsdf type="diffuse"><texture type="bitmap" name="diffuseReflectance">
          <string name="filename" value="{scene05.parent / 'leaf_alpha.png'}"/><string name="wrapMode" value="mirror"/>
          <float name="uoffset" value="0.25"/><float name="uscale" value="2"/><float name="vscale" value="3"/>
        </texture></bsdf></shape>
    </scene>"""
    ours = upgrade(ET.fromstring(xml)).to_string()
    native, mine = params_of(xml), params_of(ours)
    assert sorted(native) == sorted(mine)
    for key in native:
        if isinstance(native[key], np.ndarray) and native[key].dtype != object:
            np.testing.assert_allclose(mine[key], native[key], rtol=1e-6, atol=1e-7, err_msg=key)


def test_change_report_lists_each_change(upgraded):
    changes = [str(c) for c in upgraded.changes]
    text = "\n".join(changes)
    for expected in ("<scene>: version 0.5.0 -> 3.0.0",
                     "renamed 'toWorld' -> 'to_world' (4 times)",
                     "renamed 'intIOR' -> 'int_ior'", "renamed 'fovAxis' -> 'fov_axis'",
                     "renamed 'filterType' -> 'filter_type'", "renamed 'sampleCount' -> 'sample_count'",
                     '<bsdf type="twosided" id="Wall"> <srgb name="diffuse_reflectance">: <srgb> -> linear <rgb',
                     '<bsdf type="twosided" id="Wall"> <bsdf type="diffuse">: diffuse_reflectance -> reflectance',
                     "<sensor type=\"perspective\"> <lookat>: <lookAt> -> <lookat>",
                     "plugin 'ldrfilm' -> 'hdrfilm'", "removed parameter 'banner'", "removed parameter 'gamma'",
                     "<integrator type=\"path\">: removed parameter 'strict_normals'",
                     "WARNING: <sensor type=\"perspective\"> <sampler type=\"sobol\">: plugin 'sobol' -> "
                     "'independent'",
                     "WARNING: <bsdf type=\"phong\" id=\"Old\">: plugin 'phong' -> 'roughplastic'",
                     "<texture type=\"bitmap\" name=\"opacity\">: gamma 1 -> raw",
                     "constant <spectrum value=\"5.0\"> -> <rgb value=\"5.0, 5.0, 5.0\">",
                     "2 relative file names made absolute"):
        assert expected in text, expected
    assert len(changes) == len(set(changes))
    assert upgraded.to_string().count("\n   ") >= len(changes)       # listed in the XML's top comment


def test_refused_plugins_are_listed_together():
    xml = """<scene version="0.6.0">
      <bsdf type="hk" id="Skin"/>
      <shape type="sphere"><bsdf type="diffuse"><texture type="vertexcolors" name="reflectance"/></bsdf></shape>
      <shape type="sphere"><bsdf type="phong"><texture type="bitmap" name="exponent">
        <string name="filename" value="e.png"/></texture></bsdf></shape>
      <bsdf type="mixturebsdf" id="Mix"><string name="weights" value="0.2, 0.3, 0.5"/>
        <bsdf type="diffuse"/><bsdf type="diffuse"/><bsdf type="diffuse"/></bsdf>
    </scene>"""
    with pytest.raises(InputError) as err:
        upgrade(ET.fromstring(xml), source="old.xml")
    problems = err.value.problems
    assert [p[1] for p in problems] == ['<bsdf type="hk" id="Skin">',
                                        '<shape type="sphere"> <texture type="vertexcolors" name="reflectance">',
                                        '<shape type="sphere"> <bsdf type="phong">',
                                        '<bsdf type="mixturebsdf" id="Mix">']
    assert all(p[0] == "old.xml" for p in problems)
    assert "no Mitsuba 3 equivalent" in problems[0][2] and "replace it" in problems[0][2]


def test_nearest_plugin_mappings():
    xml = """<scene version="0.5.0">
      <bsdf type="ward" id="W"><float name="alphaU" value="0.04"/><float name="alphaV" value="0.25"/></bsdf>
      <bsdf type="mixturebsdf" id="M"><string name="weights" value="0.2, 0.6"/>
        <bsdf type="diffuse"/><bsdf type="conductor"><string name="extEta" value="air"/></bsdf></bsdf>
      <bsdf type="coating" id="C"><float name="thickness" value="1"/><bsdf type="roughdiffuse"/></bsdf>
      <bsdf type="roughconductor" id="R"><string name="distribution" value="as"/></bsdf>
      <integrator type="bdpt"><integer name="maxDepth" value="7"/><boolean name="lightImage" value="true"/></integrator>
    </scene>"""
    result = upgrade(ET.fromstring(xml))
    p = params_of(result.to_string())
    np.testing.assert_allclose(p["W.alpha"], math.sqrt(0.04 * 0.25), rtol=1e-6)
    np.testing.assert_allclose(p["M.weight.value"], 0.6 / 0.8, rtol=1e-6)
    assert result.root.find("bsdf[@id='C']").get("type") == "diffuse"
    assert result.root.find("integrator").get("type") == "path"
    text = "\n".join(map(str, result.changes))
    assert "WARNING: <bsdf type=\"coating\" id=\"C\">: 'coating' (no Mitsuba 3 equivalent) -> the coated BSDF" in text
    assert "WARNING: <bsdf type=\"roughconductor\" id=\"R\">: distribution 'as' -> 'beckmann'" in text
    assert "removed parameter 'ext_eta'" in text and "plugin 'bdpt' -> 'path'" in text


def test_import_upgrades_and_masks_cutouts(scene05, tmp_path):
    source = load_source(scene05, upgraded_dir=tmp_path)
    written = tmp_path / "scene.mitsuba3.xml"
    assert written.is_file() and 'version="3.0.0"' in written.read_text()
    assert any("phong" in c for c in source.upgrade_changes)
    leaf = next(o for o in source.objects if o.name == "leaf")
    assert leaf.material.plugin == "mask(diffuse)" and not leaf.masked

    mesh, _ = reconstruction_mesh(source.objects)
    evaluator = GroundTruthEvaluator(source.objects, mesh)
    eye = np.array([0.0, 1.0, 3.0])
    cam = look_at_camera(eye, LEAF_CENTRE, width=40, height=30, fx=40.0)
    gt = evaluator.evaluate(cam, fr.compute_fragments(mesh, [cam], cache_dir=False, progress=False)[0])

    # Independent reference: the pixel rays meet the leaf plane z = 1 at x, y; opacity is 0 for
    # u = (x + 0.5) < 0.5 (the bitmap's left texel), 1 otherwise. Pixels near the edges are skipped.
    o, d = cam.pixel_rays()
    t = (LEAF_CENTRE[2] - o[:, 2]) / d[:, 2]
    x, y = (o[:, 0] + t * d[:, 0]).reshape(30, 40), (o[:, 1] + t * d[:, 1]).reshape(30, 40)
    inside = (np.abs(x) < 0.47) & (np.abs(y - 1.0) < 0.47) & (np.abs(x) > 0.03)
    cut, kept = inside & (x < 0), inside & (x > 0)
    assert cut.sum() > 50 and kept.sum() > 50
    assert not gt.mask[cut].any() and gt.hit[cut].all()
    assert gt.mask[kept].all()
    np.testing.assert_allclose(gt.albedo[kept], np.broadcast_to(LEAF_RGB, (kept.sum(), 3)), rtol=1e-6)
    np.testing.assert_array_equal(gt.albedo[cut], 0.0)
    np.testing.assert_allclose(gt.roughness[kept], 1.0)        # the nested diffuse BSDF
    wall_only = (np.abs(x) > 0.55) & (np.abs(x) < 1.9) & (np.abs(y - 1.0) < 0.9)
    assert gt.mask[wall_only].all()                             # the wall behind is not affected


def test_mitsuba3_files_are_not_upgraded(tmp_path):
    xml = tmp_path / "scene.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse"/></shape></scene>')
    source = load_source(xml, upgraded_dir=tmp_path / "out")
    assert source.upgrade_changes == () and not (tmp_path / "out").exists()


def test_refused_scene_stops_prepare_scene_before_compute(tmp_path):
    xml = tmp_path / "old.xml"
    xml.write_text('<scene version="0.5.0"><shape type="sphere"><bsdf type="irawan" id="Cloth"/></shape></scene>')
    with pytest.raises(InputError) as err:
        prepare_scene(xml, tmp_path / "out", num_views=1, width=8, height=8, spp=1, progress=False)
    message = str(err.value)
    assert f"{xml}: <shape type=\"sphere\"> <bsdf type=\"irawan\" id=\"Cloth\">: plugin 'irawan' has no Mitsuba 3 " \
           "equivalent; replace it by a Mitsuba 3 BSDF" in message
    assert not (tmp_path / "out").exists()


def test_channel_selection_is_refused():
    xml = """<scene version="0.5.0"><bsdf type="mask" id="Leaf"><texture type="bitmap" name="opacity">
      <string name="filename" value="leaf.png"/><string name="channel" value="a"/></texture>
      <bsdf type="diffuse"/></bsdf>
    </scene>"""
    with pytest.raises(InputError) as err:
        upgrade(ET.fromstring(xml))
    where, what = err.value.problems[0][1:]
    assert where == '<bsdf type="mask" id="Leaf"> <texture type="bitmap" name="opacity">'
    assert what.startswith("channel 'a': Mitsuba 3 bitmaps have no channel selection")


def test_load_error_after_the_upgrade_names_the_upgraded_file(tmp_path):
    xml = tmp_path / "old.xml"
    xml.write_text('<scene version="0.5.0"><shape type="sphere"><bsdf type="diffuse">'
                   '<float name="fooBar" value="1"/></bsdf></shape></scene>')
    with pytest.raises(InputError) as err:
        load_source(xml, upgraded_dir=tmp_path / "out")
    message = str(err.value)
    assert "Mitsuba 3 cannot load it after the upgrade from Mitsuba 0.x" in message and '"foo_bar"' in message
    assert str(tmp_path / "out" / "old.mitsuba3.xml") in message


def test_a_05_room_imports_as_its_mitsuba3_original(tmp_path):
    """The test room of test_prepare_scene written in 0.5 style (camelCase, <lookAt>) imports to
    the same ground truth, masks and photos as the Mitsuba 3 original."""
    from test_prepare_scene import write_room
    original = write_room(tmp_path / "v3")
    text = original.read_text().replace('version="3.0.0"', 'version="0.5.0"').replace("<lookat ", "<lookAt ")
    for new, old in (("to_world", "toWorld"), ("diffuse_reflectance", "diffuseReflectance"), ("max_depth", "maxDepth"),
                     ("filter_type", "filterType")):
        text = text.replace(f'name="{new}"', f'name="{old}"')
    old05 = original.parent / "scene05.xml"
    old05.write_text(text)
    args = dict(num_views=2, width=24, height=18, spp=2, seed=3, progress=False)
    prepare_scene(original, tmp_path / "a", **args)
    prepare_scene(old05, tmp_path / "b", **args)
    assert (tmp_path / "b" / "scene05.mitsuba3.xml").is_file()
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*")
                   if p.suffix in (".exr", ".png") and "photos" not in p.parts)
    assert len(files) >= 2 * 5                      # albedo, normal, roughness, metallic, mask per view
    for rel in files + [Path("photos") / f"view_{i:03d}.exr" for i in range(2)]:
        a, b = imageio.read_image(tmp_path / "a" / rel), imageio.read_image(tmp_path / "b" / rel)
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6 * max(1.0, float(np.abs(a).max())), err_msg=str(rel))


def test_non_numeric_values_are_refused_not_a_traceback():
    xml = """<scene version="0.5.0">
      <emitter type="sunsky" id="Sky"><float name="scale" value="$skyScale"/></emitter>
      <texture type="bitmap" id="T"><string name="filename" value="t.png"/>
        <float name="uscale" value="$tiles"/></texture>
      <emitter type="area" id="A"><blackbody name="radiance" temperature="warm"/></emitter>
    </scene>"""
    with pytest.raises(InputError) as err:
        upgrade(ET.fromstring(xml), source="x.xml")
    assert sorted(p[1] for p in err.value.problems) == [
        '<emitter type="area" id="A"> <blackbody name="radiance">', '<emitter type="sunsky" id="Sky">',
        '<texture type="bitmap" id="T">']
