"""Irradiance traced from the photos (`render.light_trace`, `--anchor=traced`) against analytic
answers: cosine-weighted moments, a closed box whose walls all shine alike (the irradiance is
their radiance, exactly), the form factor of a square light, occlusion, and the anchor's gain
in a white furnace."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxdistill.engine.config import DistillConfig
from jaxdistill.errors import InputError
from jaxdistill.export import anchor, photo_light
from jaxdistill.io.images import write_image
from jaxdistill.render import light_trace
from jaxdistill.render.fragments import RayCaster
from jaxdistill.scene.cameras import look_at
from jaxdistill.scene.mesh import Mesh
from jaxdistill.scene.model import Scene, View
from jaxdistill.scene.shapes import box_room, mesh_from_patches, quad_patch
from tolerance import assert_close


def test_cosine_directions_have_the_cosine_densitys_moments():
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(64, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[0] = (0, 0, -1)                                  # the frame's one sign switch
    d = light_trace.cosine_directions(normals, 1024, rng)
    assert_close(np.linalg.norm(d, axis=-1), np.ones(d.shape[:2]), rtol=1e-12)
    cos = np.einsum("nkc,nc->nk", d, normals)
    assert cos.min() >= 0
    # density cos θ / π: E[cos θ] = 2/3, E[cos² θ] = 1/2; stratified, so close at 1024 samples
    assert_close(cos.mean(axis=1), np.full(64, 2 / 3), rtol=0.01)
    assert_close((cos ** 2).mean(axis=1), np.full(64, 0.5), rtol=0.02)
    # and no preferred azimuth: the tangential part averages to zero
    tangential = d - cos[..., None] * normals[:, None]
    assert np.abs(tangential.mean(axis=1)).max() < 0.03


def test_inside_a_box_whose_walls_all_shine_alike_the_irradiance_is_their_radiance():
    mesh = box_room(size=(4.0, 3.0, 5.0), subdivisions=2)
    caster = RayCaster(mesh)
    rng = np.random.default_rng(1)
    points = rng.uniform((0.5, 0.5, 0.5), (3.5, 2.5, 4.5), (40, 3))
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    wall = np.array([0.2, 0.5, 0.9])
    irradiance, known, escaped = light_trace.traced_irradiance(
        caster.intersect, points, normals, lambda y, tri: (np.broadcast_to(wall, y.shape), np.ones(len(y), bool)),
        rays=64, rng=rng, offset=1e-6)
    assert_close(irradiance, np.broadcast_to(wall, irradiance.shape), rtol=1e-12)
    assert (known == 1).all() and (escaped == 0).all()
    # unknown radiance where the lookup says so: those rays take the known rays' mean
    irradiance, known, _ = light_trace.traced_irradiance(
        caster.intersect, points, normals, lambda y, tri: (np.broadcast_to(wall, y.shape), y[:, 1] > 1.5),
        rays=64, rng=rng, offset=1e-6)
    some = known > 0                      # a point facing the floor may have no ray above y = 1.5
    assert_close(irradiance[some], np.broadcast_to(wall, irradiance[some].shape), rtol=1e-12)
    assert (irradiance[~some] == 0).all() and some.sum() > 20 and known.mean() < 1
    # an open box: the rays through the missing ceiling escape; they add the background, or nothing
    top = box_room(size=(4.0, 3.0, 5.0), subdivisions=2)
    floor_only = Mesh(top.vertices, top.faces[top.face_object != top.object_names.index("room_ceiling")],
                      top.uv[top.face_object != top.object_names.index("room_ceiling")],
                      top.face_object[top.face_object != top.object_names.index("room_ceiling")], top.object_names)
    up = np.tile([0.0, 1.0, 0.0], (40, 1))
    look = lambda y, tri: (np.broadcast_to(wall, y.shape), np.ones(len(y), bool))
    sky = np.array([2.0, 2.0, 2.0])
    dark, known, escaped = light_trace.traced_irradiance(RayCaster(floor_only).intersect, points, up, look, rays=64,
                                                         rng=np.random.default_rng(7), offset=1e-6)
    lit, known_lit, _ = light_trace.traced_irradiance(RayCaster(floor_only).intersect, points, up, look, rays=64,
                                                      rng=np.random.default_rng(7), offset=1e-6, background=sky)
    assert escaped.min() > 0.1 and (known_lit == 1).all()
    assert_close(dark, wall * (1 - escaped)[:, None], rtol=1e-12)
    assert_close(lit, wall * (1 - escaped)[:, None] + sky * escaped[:, None], rtol=1e-12)


def square_light(half: float, height: float) -> Mesh:
    """A square [-half, half]² at y = height, facing down (two triangles), as one object."""
    return mesh_from_patches([("light", np.array([-half, height, -half]), np.array([2 * half, 0, 0]),
                               np.array([0, 0, 2 * half]), 1)])


def test_a_square_lights_irradiance_is_its_radiance_times_the_form_factor():
    half, height = 0.5, 1.0
    mesh = square_light(half, height)
    caster = RayCaster(mesh)
    radiance = np.array([3.0, 2.0, 1.0])
    corners = mesh.triangles()
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(normal, axis=1)
    emitters = light_trace.Emitters(np.arange(2), corners, normal / (2 * area[:, None]), area,
                                    np.tile(radiance, (2, 1)), np.array([0.5, 1.0]))
    point, up = np.zeros((1, 3)), np.array([[0.0, 1.0, 0.0]])
    e = light_trace.emitted_irradiance(caster.intersect, point, up, emitters, samples=200_000,
                                       rng=np.random.default_rng(2), offset=0.0)
    # point on the axis of a square of half side a at distance h: four corner rectangles a × a,
    # each F = (1/2π)·2·X/√(1+X²)·atan(X/√(1+X²)), X = a/h; E/π = L·F
    x = half / height
    form = 4 * (1 / (2 * np.pi)) * 2 * x / np.sqrt(1 + x * x) * np.arctan(x / np.sqrt(1 + x * x))
    assert_close(e[0], radiance * form, rtol=0.01)
    # a point that faces away gets nothing; one behind an occluder gets nothing
    assert (light_trace.emitted_irradiance(caster.intersect, point, -up, emitters, samples=64,
                                           rng=np.random.default_rng(3), offset=0.0) == 0).all()
    blocker = mesh_from_patches([("light", np.array([-half, height, -half]), np.array([2 * half, 0, 0]),
                                  np.array([0, 0, 2 * half]), 1),
                                 ("roof", np.array([-2.0, 0.5, -2.0]), np.array([4.0, 0, 0]), np.array([0, 0, 4.0]), 1)])
    blocked = dataclasses.replace(emitters, faces=np.flatnonzero(blocker.face_object == 0))
    assert (light_trace.emitted_irradiance(RayCaster(blocker).intersect, point, up, blocked, samples=64,
                                           rng=np.random.default_rng(4), offset=0.0) == 0).all()


def test_the_photos_radiance_is_read_only_where_a_view_sees_the_point():
    camera = look_at((0, 0, 5), (0, 0, 0), (0, 1, 0), np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]), 16, 16)
    depth = np.full((16, 16), 5.0, np.float32)                     # a wall at z = 0, facing the camera
    image = np.zeros((16, 16, 3), np.float32)
    image[..., 0] = np.arange(16)[None, :]                         # the column index in red
    on_wall = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    behind = np.array([[0.0, 0.0, -1.0]])                         # hidden by the wall
    outside = np.array([[10.0, 0.0, 0.0]])                        # outside the picture
    behind_camera = np.array([[0.0, 0.0, 7.0]])                  # projects into the picture from behind
    mean, views = light_trace.visible_radiance(np.concatenate([on_wall, behind, outside, behind_camera]), [camera],
                                               [depth], [image])
    assert views.tolist() == [1, 1, 0, 0, 0]
    pix, _ = camera.project(on_wall)
    assert mean[:2, 0].tolist() == np.floor(pix[:, 0]).tolist() and (mean[2:] == 0).all()
    # a view that sees nothing adds nothing, to the faces' statistics either
    mean, pixels, peak = light_trace.face_radiance(3, [np.full((4, 4), -1), np.zeros((4, 4), int)],
                                                   [np.ones((4, 4, 3)), np.full((4, 4, 3), 2.0)])
    assert pixels.tolist() == [16, 0, 0] and mean[0].tolist() == [2.0] * 3 and peak[0].tolist() == [2.0] * 3


def test_emitters_are_the_faces_far_brighter_than_the_rest_and_their_unseen_faces_too():
    mesh = box_room(size=(2.0, 2.0, 2.0), subdivisions=1)          # 6 objects of 2 faces each
    mean = np.full((12, 3), 0.1)
    pixels = np.full(12, 100)
    ceiling = np.flatnonzero(mesh.face_object == mesh.object_names.index("room_ceiling"))
    mean[ceiling[0]] = 50.0
    pixels[ceiling[1]] = 0                                           # the light's other half: no photo sees it
    found = light_trace.find_emitters(mesh.vertices, mesh.faces, mesh.face_object, mean, pixels)
    assert sorted(found.faces.tolist()) == sorted(ceiling.tolist())
    assert_close(found.radiance, np.full((2, 3), 50.0), rtol=1e-12)
    assert_close(found.cdf[-1], 1.0, rtol=1e-12)
    assert light_trace.find_emitters(mesh.vertices, mesh.faces, mesh.face_object, np.full((12, 3), 0.1), pixels) is None


def test_a_faces_peak_is_its_brightest_pixel_and_a_small_lights_radiance():
    tri = np.array([[0, 0, 1], [1, -1, 1]])
    image = np.zeros((2, 3, 3), np.float32)
    image[0, :, 0] = [1.0, 2.0, 9.0]              # face 0: red 1, 2; face 1: red 9, green 4, red 3
    image[1, 0, 1], image[1, 2, 0] = 4.0, 3.0
    mean, pixels, peak = light_trace.face_radiance(3, [tri, tri], [image, 2 * image])
    assert pixels.tolist() == [4, 6, 0]
    assert_close(mean, np.array([[(1 + 2 + 2 + 4) / 4, 0, 0], [(9 + 3 + 18 + 6) / 6, (4 + 8) / 6, 0], [0, 0, 0]]),
                 rtol=1e-12)
    assert_close(peak, np.array([[4.0, 0, 0], [0, 8.0, 0], [0, 0, 0]]), rtol=1e-12)   # by luminance green 8 beats red 18
    # an emitter found by its mean takes its brightest pixel, and so do its unseen faces
    mesh = box_room(size=(2.0, 2.0, 2.0), subdivisions=1)
    mean, pixels, peak = np.full((12, 3), 0.1), np.full(12, 100), np.full((12, 3), 0.2)
    ceiling = np.flatnonzero(mesh.face_object == mesh.object_names.index("room_ceiling"))
    mean[ceiling[0]], peak[ceiling[0]], pixels[ceiling[1]] = 30.0, 80.0, 0
    found = light_trace.find_emitters(mesh.vertices, mesh.faces, mesh.face_object, mean, pixels, peak)
    assert_close(found.radiance, np.full((2, 3), 80.0), rtol=1e-12)


def test_the_gain_is_a_weighted_median_over_objects_of_their_ratio_of_sums():
    from jaxdistill.export.photo_light import TracedPoints, gain_from_points, weighted_median

    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.array([1, 1, 5])) == 2.0
    assert weighted_median(np.array([3.0, 1.0, 2.0]), np.array([5, 1, 1])) == 3.0
    assert weighted_median(np.array([1.0, 2.0]), np.array([1, 1])) == 1.0                 # the lower on a tie
    rng = np.random.default_rng(0)
    # objects 0, 1, 2 with 60, 30, 20 points whose photos are 2×, 3× and 5× albedo · irradiance;
    # per point the radiance is noisy, per object its sum is what counts; 10 emitter points and
    # 5 points with too little known light are left out
    obj = np.repeat([0, 1, 2, 3, 4], [60, 30, 20, 10, 5])
    albedo = rng.uniform(0.2, 0.8, (125, 3))
    irradiance = rng.uniform(0.5, 2.0, (125, 3))
    factor = np.array([2.0, 3.0, 5.0, 100.0, 100.0])[obj]
    noise = rng.normal(0, 0.3, (125, 3))
    noise -= np.stack([np.bincount(obj, noise[:, c] * albedo[:, c] * irradiance[:, c]) /
                       np.bincount(obj, albedo[:, c] * irradiance[:, c]) for c in range(3)], 1)[obj]   # zero-sum
    radiance = factor[:, None] * albedo * irradiance * (1 + noise)
    t = TracedPoints(np.zeros((125, 3)), np.zeros((125, 3)), radiance, np.ones(125, int), albedo, irradiance,
                     known=np.where(obj == 4, 0.5, 1.0), escaped=np.zeros(125), emitter=obj == 3, object=obj,
                     background=None, record={})
    gain, record = gain_from_points(t)
    assert_close(gain, np.full(3, 2.0), rtol=1e-9)       # object 0 holds more than half the weight
    assert record["counted"] == 110 and record["objects"] == 3
    t = dataclasses.replace(t, object=np.repeat([0, 1, 2, 3, 4], [30, 60, 20, 10, 5]))
    assert_close(gain_from_points(t)[0], np.full(3, 3.0), rtol=0.2)          # now object 1's points
    few = dataclasses.replace(t, known=np.where(np.arange(125) < 40, 1.0, 0.0))
    assert gain_from_points(few)[0] is None                                   # 40 counted: fewer than 50


def test_bad_trace_settings_are_refused():
    caster = RayCaster(box_room(size=(2.0, 2.0, 2.0), subdivisions=1))
    look = lambda y, tri: (np.ones_like(y), np.ones(len(y), bool))
    with pytest.raises(ValueError, match="rays must be at least 1"):
        light_trace.traced_irradiance(caster.intersect, np.ones((1, 3)), np.array([[0, 1.0, 0]]), look, rays=0,
                                      rng=np.random.default_rng(0), offset=1e-6)
    corners = np.zeros((1, 3, 3))
    emitters = light_trace.Emitters(np.array([0]), corners, np.array([[0, 1.0, 0]]), np.ones(1), np.ones((1, 3)),
                                    np.ones(1))
    with pytest.raises(ValueError, match="emitter_samples < 1"):
        light_trace.traced_irradiance(caster.intersect, np.ones((1, 3)), np.array([[0, 1.0, 0]]), look, rays=4,
                                      rng=np.random.default_rng(0), offset=1e-6, emitters=emitters)


def furnace_scene(folder, *, suffix: str = ".exr") -> Scene:
    """A closed box whose photos show one radiance everywhere (a white furnace: every surface
    reflects all it receives), seen by six views from inside, one per side."""
    mesh = box_room(size=(4.0, 3.0, 5.0), subdivisions=2)
    K = np.array([[24.0, 0, 16], [0, 24.0, 12], [0, 0, 1]])
    views = []
    for k, target in enumerate([(0, 1.5, 2.5), (4, 1.5, 2.5), (2, 1.5, 0), (2, 1.5, 5), (2, 0, 2.5), (2, 3, 2.5)]):
        camera = look_at((2.0, 1.5, 2.5), target, (0, 0, 1) if k >= 4 else (0, 1, 0), K, 32, 24)
        photo = folder / f"view_{k}{suffix}"
        write_image(photo, np.full((24, 32, 3), 0.3 if suffix == ".exr" else 0.5, np.float32))
        views.append(View(name=f"view_{k}", camera=camera, photo=photo))
    return Scene(name="furnace", mesh=mesh, views=tuple(views), root=folder)


def test_in_a_white_furnace_the_traced_albedo_is_one_so_the_gain_is_one_over_the_renders(tmp_path):
    scene = furnace_scene(tmp_path)
    renders = [{"albedo": np.full((24, 32, 3), 0.5)} for _ in scene.views]
    hits = [np.ones((24, 32), bool) for _ in scene.views]
    gain, record = photo_light.traced_albedo_gain(scene, renders, hits, points=32, rays=16)
    # every ray hits a wall of radiance 0.3 (seen by a view, else its face's or object's mean):
    # irradiance 0.3, albedo 0.3 / 0.3 = 1 against the renders' 0.5
    assert_close(gain, np.full(3, 2.0), rtol=1e-6)
    assert record["counted"] == record["points"] > photo_light.TRACE_MIN_POINTS and record["emitter_faces"] == 0
    split = anchor.traced_gains(gain, ("albedo", "normal", "irradiance"))      # the product kept
    assert sorted(split) == ["albedo", "irradiance"]
    assert_close(split["albedo"] * split["irradiance"], np.ones(3), rtol=1e-12)


def test_the_traced_anchor_refuses_ldr_photos_before_compute(tmp_path):
    scene = furnace_scene(tmp_path, suffix=".png")
    config = DistillConfig(scene="unused", out_dir="unused", anchor="traced")
    with pytest.raises(InputError, match=r"view_0\.png.*photo.*--anchor=traced needs linear HDR photos"):
        anchor.check_anchor(config, scene)
    anchor.check_anchor(dataclasses.replace(config, anchor="estimates"), scene)     # others read no radiance
    anchor.check_anchor(config, furnace_scene(tmp_path / "hdr"))


def unit_cube() -> Mesh:
    v = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    uv = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), (len(faces), 1, 1))
    return Mesh(v, faces, uv, np.zeros(len(faces), np.int32), ("cube",))


def test_a_floor_point_sees_the_photographed_ceilings_form_factor():
    """A unit cube seen whole by six views from inside; the photos show radiance 1 on the ceiling
    and 0 elsewhere. At the floor's centre E/π is the ceiling's form factor, four corner
    rectangles of 0.5 × 0.5 at height 1: 0.2394, found through the photos both by the
    hemisphere's rays and by sampling the ceiling as an emitter (it is far brighter than the rest)."""
    from jaxdistill.export.photo_light import PhotoRadiance

    mesh, size = unit_cube(), 48
    centre = np.array([0.5, 0.5, 0.5])
    f = size / 2 / np.tan(np.radians(50))                # 100° field of view: each camera sees its whole wall
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    axes = [np.eye(3)[i] * s for i in range(3) for s in (1, -1)]
    cams = [look_at(centre - 0.3 * d, centre + d, np.array([0.0, 0.0, 1.0]) if abs(d[1]) else np.array([0.0, 1.0, 0.0]),
                    K, size, size) for d in axes]
    caster = RayCaster(mesh)
    ceiling = np.all(np.isclose(mesh.triangles()[:, :, 1], 1.0), axis=1)
    triangles, depths, photos = [], [], []
    for cam in cams:
        o, d = cam.pixel_rays()
        tri, _, dist = caster.intersect(o, d)
        triangles.append(tri.reshape(size, size))
        depths.append(np.where(tri >= 0, dist * (d @ cam.c2w[:3, 2]), np.inf).reshape(size, size))
        photos.append(np.where(ceiling[np.maximum(tri, 0)] & (tri >= 0), 1.0, 0.0)[:, None].repeat(3, 1)
                      .reshape(size, size, 3))
    mean, pixels, peak = light_trace.face_radiance(len(mesh.faces), triangles, photos)
    light = PhotoRadiance(cams, depths, photos, mean, pixels, mean[:1] * 0, np.zeros(1), None, None)
    look = lambda y, tri: light.lookup(y, tri, mesh.face_object)
    p, n = np.array([[0.5, 0.0, 0.5]]), np.array([[0.0, 1.0, 0.0]])
    x = 0.5                                                        # each quarter: a 0.5 × 0.5 corner rectangle
    quarter = (x / np.sqrt(1 + x * x) * np.arctan(x / np.sqrt(1 + x * x))) * 2 / (2 * np.pi)
    expected = 4 * quarter                                         # 0.2394
    e, known, escaped = light_trace.traced_irradiance(caster.intersect, p, n, look, rays=8192,
                                                      rng=np.random.default_rng(1), offset=1e-6)
    assert known[0] == 1 and escaped[0] == 0
    # Monte Carlo with 8192 stratified rays, sd below sqrt(F (1 - F) / 8192) = 0.0047 (2 % of F)
    assert_close(e[0], np.full(3, expected), rtol=0.03)
    emitters = light_trace.find_emitters(mesh.vertices, mesh.faces, mesh.face_object, mean, pixels, peak)
    assert sorted(emitters.faces.tolist()) == np.flatnonzero(ceiling).tolist()
    e, _, _ = light_trace.traced_irradiance(caster.intersect, p, n, look, rays=64, rng=np.random.default_rng(2),
                                            offset=1e-6, emitters=emitters, emitter_samples=8192)
    assert_close(e[0], np.full(3, expected), rtol=0.03)
