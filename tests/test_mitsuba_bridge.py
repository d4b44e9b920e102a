"""Our cameras and meshes rendered by Mitsuba 3 agree with our rays and our sampler."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import look_at_camera
from jaxdistill.scene import shapes as synthetic
from jaxdistill.render import fragments as fr
from jaxdistill.render.sampler import sample_pages

mi = pytest.importorskip("mitsuba")
from jaxdistill.datasets.mitsuba import bridge as mb


def off_centre_camera():
    return look_at_camera((1.0, 1.4, 2.8), (3.5, 1.1, 0.5), width=40, height=30, fx=34.0, cx=17.3, cy=16.9)


def test_sensor_rays_match_camera_rays():
    mb.load_mitsuba()
    cam = off_centre_camera()
    sensor = mi.load_dict(mb.sensor_dict(cam))
    pixels = np.array([[0.5, 0.5], [39.5, 0.5], [20.0, 15.0], [3.25, 28.75]])
    origins, directions = cam.pixel_rays(pixels)
    for p, o, d in zip(pixels, origins, directions):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.ScalarPoint2f(p[0] / cam.width, p[1] / cam.height),
                                   mi.ScalarPoint2f(0.5, 0.5))
        d = d / np.linalg.norm(d)
        np.testing.assert_allclose(np.array(ray.d), d, atol=1e-5)
        offset = np.array(ray.o) - o          # Mitsuba starts rays at the near clip plane
        np.testing.assert_allclose(np.cross(offset, d), 0.0, atol=1e-5)
        assert 0 < offset @ d < 2e-3


def test_non_square_pixels_are_refused():
    cam = look_at_camera((1, 1, 4), (1, 1, 0), fx=30.0, fy=31.0)
    with pytest.raises(ValueError, match="square pixels"):
        mb.sensor_dict(cam)


def test_aov_albedo_and_object_ids_match_our_sampler():
    mb.load_mitsuba()
    mesh = synthetic.box_room(size=(4.0, 2.5, 3.0), subdivisions=2, furniture=True)
    rng = np.random.default_rng(0)
    pages = [rng.uniform(0.05, 0.95, (16, 16, 3)).astype(np.float32) for _ in mesh.object_names]
    shapes = {}
    for i, name in enumerate(mesh.object_names):
        sel = mesh.face_object == i
        bsdf = {"type": "diffuse", "reflectance": mb.bitmap(pages[i])}
        shapes[name] = mb.mesh_shape(name, mesh.vertices, mesh.faces[sel], mesh.uv[sel], bsdf=bsdf)
    scene = mi.load_dict({"type": "scene", **shapes})
    cam = off_centre_camera()
    aov = mb.render(scene, cam, centre_samples=True,
                    integrator=mb.aov_integrator("albedo:albedo", "obj:shape_index"))
    frag = fr.compute_fragments(mesh, [cam], cache_dir=False, progress=False)[0]
    ours = sample_pages(pages, [frag], range(len(pages)))[0]
    hit = frag.object_id >= 0
    assert hit.all()
    np.testing.assert_allclose(aov[..., :3], ours, atol=2e-3)
    names = [s.id() for s in scene.shapes()]      # shape_index is 1-based; 0 is a miss
    mitsuba_object = np.array([mesh.object_names.index(names[int(k) - 1]) for k in aov[..., 3].ravel()])
    assert (mitsuba_object.reshape(hit.shape) == frag.object_id).mean() > 0.99


def test_path_traced_renders_are_reproducible():
    mi = mb.load_mitsuba()
    mesh = synthetic.box_room(size=(4.0, 2.5, 3.0), subdivisions=2, furniture=True)
    shapes = {name: mb.mesh_shape(name, mesh.vertices, mesh.faces[mesh.face_object == i], mesh.uv[mesh.face_object == i],
                                  bsdf={"type": "diffuse"})
              for i, name in enumerate(mesh.object_names) if name != "room_ceiling"}      # the sky comes in
    scene = mi.load_dict({"type": "scene", **shapes, "sky": {"type": "constant"}})
    cam = look_at_camera((1.0, 1.4, 2.8), (3.5, 1.1, 0.5), width=160, height=120, fx=130.0, cx=77.0, cy=62.0)
    a, b = (mb.render(scene, cam, spp=4, seed=7, integrator={"type": "path", "max_depth": 3}) for _ in range(2))
    c = mb.render(scene, cam, spp=4, seed=8, integrator={"type": "path", "max_depth": 3})
    assert a.std() > 0.05
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
