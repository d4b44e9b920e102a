"""Fragment buffers against analytic ray-plane and ray-box intersections."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import look_at_camera
from jaxdistill.scene import shapes as synthetic
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import Mesh


def analytic_plane(camera, size, subdivisions, height=0.0):
    """Per pixel: hit, t, uv and triangle id of the plane built by `synthetic.plane`, solved in closed form."""
    d = camera.pixel_directions()
    o = camera.c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (height - o[1]) / d[:, 1]
    p = o + t[:, None] * d
    h = size / 2
    u = (p[:, 0] + h) / size
    v = (h - p[:, 2]) / size
    hit = (t > 0) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    n = subdivisions
    i = np.clip(np.floor(u * n), 0, n - 1)
    j = np.clip(np.floor(v * n), 0, n - 1)
    fu, fv = u * n - i, v * n - j
    cell = (j * n + i).astype(np.int64)
    tri = np.where(fu >= fv, cell, n * n + cell)
    shape = (camera.height, camera.width)
    depth = t * (d @ camera.c2w[:3, 2])
    return (hit.reshape(shape), np.stack([u, v], 1).reshape(*shape, 2), np.where(hit, tri, -1).reshape(shape),
            depth.reshape(shape))


def test_plane_matches_analytic_projection(cache_dir):
    size, n = 2.0, 8
    mesh = synthetic.plane(size, n)
    camera = look_at_camera((0.3, 1.5, 2.2), (0.1, 0.0, -0.2), width=64, height=48, fx=50.0, cx=30.0, cy=26.0)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=cache_dir, progress=False)
    hit, uv, tri, depth = analytic_plane(camera, size, n)
    both = hit & frag.hit
    hit_agree = (hit == frag.hit).mean()
    tri_agree = (tri[both] == frag.triangle[both]).mean()
    print(f"plane: hit agreement {hit_agree:.5f}, triangle agreement {tri_agree:.5f} over {both.sum()} pixels")
    assert hit.sum() > 800 and hit_agree > 0.995 and tri_agree > 0.995
    np.testing.assert_allclose(frag.uv[both], uv[both], atol=2e-6)
    np.testing.assert_allclose(frag.depth[both], depth[both], rtol=1e-5)
    assert np.all(np.isinf(frag.depth[~frag.hit])) and np.all(frag.triangle[~frag.hit] == -1)


def test_uv_derivatives_match_finite_differences():
    size = 2.0
    mesh = synthetic.plane(size, 1)
    camera = look_at_camera((0.0, 1.0, 1.5), (0.0, 0.0, 0.0), width=40, height=30, fx=35.0)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)

    def uv_at(px, py):
        d = (camera.c2w[:3, :3] @ np.linalg.inv(camera.K) @ np.array([px, py, 1.0]))
        o = camera.c2w[:3, 3]
        p = o + (-o[1] / d[1]) * d
        return np.array([(p[0] + 1) / size, (1 - p[2]) / size])

    rows, cols = np.nonzero(frag.hit)
    for r, c in list(zip(rows, cols))[:: max(1, len(rows) // 50)]:
        x, y, eps = c + 0.5, r + 0.5, 1e-3
        ddx = (uv_at(x + eps, y) - uv_at(x - eps, y)) / (2 * eps)
        ddy = (uv_at(x, y + eps) - uv_at(x, y - eps)) / (2 * eps)
        np.testing.assert_allclose(frag.uv_grad[r, c, 0], ddx, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(frag.uv_grad[r, c, 1], ddy, rtol=1e-4, atol=1e-7)


def test_camera_inside_box_room_sees_walls_everywhere():
    size = np.array([4.0, 2.5, 3.0])
    mesh = synthetic.box_room(tuple(size), subdivisions=3)
    camera = look_at_camera((1.0, 1.2, 0.8), (3.5, 0.7, 2.6), width=48, height=36, fx=20.0)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
    assert frag.hit.all(), "a closed room seen from inside must cover every pixel"
    # Independent: nearest of the six planes along each ray.
    d = camera.pixel_directions()
    o = camera.c2w[:3, 3]
    with np.errstate(divide="ignore"):
        t_lo, t_hi = (0 - o) / d, (size - o) / d
    t_exit = np.where(d > 0, t_hi, t_lo)
    axis = np.argmin(t_exit, axis=1)
    positive = np.take_along_axis(d, axis[:, None], 1)[:, 0] > 0
    # object order of synthetic.box_patches: floor(y lo), ceiling(y hi), z0, z1, x0, x1
    expected = np.select([(axis == 1) & ~positive, (axis == 1) & positive, (axis == 2) & ~positive,
                          (axis == 2) & positive, (axis == 0) & ~positive], [0, 1, 2, 3, 4], 5)
    agree = (expected.reshape(frag.shape) == frag.object_id).mean()
    print(f"box room: object agreement {agree:.5f}")
    assert agree > 0.99
    np.testing.assert_allclose(frag.depth.ravel(), np.min(t_exit, 1) * (d @ camera.c2w[:3, 2]), rtol=1e-5)


def test_back_faces_and_misses():
    mesh = synthetic.plane(2.0, 1)
    below = look_at_camera((0.0, -1.0, 0.01), (0.0, 0.0, 0.0), fx=10.0, up=(0, 0, 1))
    away = look_at_camera((0.0, 1.0, 0.0), (0.0, 2.0, 0.5), fx=10.0)
    f_below, f_away = fr.compute_fragments(mesh, [below, away], cache_dir=False, progress=False)
    assert f_below.hit.mean() > 0.5
    assert not f_away.hit.any()
    assert np.all(f_away.uv == 0) and np.all(f_away.uv_grad == 0) and np.all(np.isinf(f_away.depth))


def test_depths_alone_are_the_fragments_triangle_and_depth_bit_for_bit(cache_dir):
    """`compute_depths` (the photo-light trace's triangles and depths) against `compute_fragments`' fields,
    cast fresh and read from the cache, with misses, against the analytic plane too."""
    mesh = synthetic.plane(2.0, 4)
    cameras = [look_at_camera((0.3, 1.5, 0.8), (0.0, 0.0, 0.0), width=48, height=32, fx=20.0),
               look_at_camera((0.0, 1.0, 0.0), (0.0, 2.0, 0.5), fx=10.0),                    # sees nothing
               look_at_camera((-0.5, 0.7, -0.2), (0.2, 0.0, 0.1), width=40, height=40, fx=35.0)]
    frags = fr.compute_fragments(mesh, cameras, cache_dir=False, progress=False)
    fresh = fr.compute_depths(mesh, cameras, cache_dir=cache_dir)                   # cast, and written to the cache
    cached = fr.compute_depths(mesh, cameras, cache_dir=cache_dir)                  # read back
    for frag, one, other in zip(frags, fresh, cached, strict=True):
        for tri, depth in (one, other):
            assert tri.dtype == np.int32 and depth.dtype == np.float32
            np.testing.assert_array_equal(tri, frag.triangle)
            np.testing.assert_array_equal(depth, frag.depth)
    hit, _, tri, depth = analytic_plane(cameras[0], 2.0, 4)
    assert hit.mean() > 0.3 and (fresh[1][0] == -1).all() and np.isinf(fresh[1][1]).all()
    np.testing.assert_allclose(fresh[0][1][hit], depth[hit], rtol=1e-6)


def test_degenerate_triangles_are_never_hit_and_stay_finite():
    base = synthetic.plane(2.0, 2)
    # Append zero-area triangles (repeated vertex, collinear vertices) lying inside the plane.
    verts = np.concatenate([base.vertices, [[0.1, 0.0, 0.1], [0.5, 0.0, 0.1], [0.9, 0.0, 0.1]]])
    k = len(base.vertices)
    degenerate = np.array([[k, k, k + 1], [k, k + 1, k + 2]])
    mesh = Mesh(vertices=verts, faces=np.concatenate([base.faces, degenerate]),
                uv=np.concatenate([base.uv, np.full((2, 3, 2), 0.5)]),
                face_object=np.zeros(len(base.faces) + 2, np.int32), object_names=("plane",))
    camera = look_at_camera((0.2, 1.0, 0.3), (0.3, 0.0, 0.1), width=64, height=64, fx=200.0)
    (frag,) = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False)
    assert frag.hit.all()
    assert not np.isin(frag.triangle, [len(base.faces), len(base.faces) + 1]).any()
    assert np.isfinite(frag.uv_grad).all() and np.isfinite(frag.uv).all()


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_scale_invariance_mm_and_km(scale):
    mesh = synthetic.plane(2.0, 4)
    camera = look_at_camera((0.3, 1.0, 0.9), (0.0, 0.0, 0.0), width=32, height=32, fx=30.0)
    scaled = Mesh(vertices=mesh.vertices * scale, faces=mesh.faces, uv=mesh.uv, face_object=mesh.face_object,
                  object_names=mesh.object_names)
    c2w = camera.c2w.copy()
    c2w[:3, 3] *= scale
    scaled_cam = type(camera)(K=camera.K, c2w=c2w, width=camera.width, height=camera.height)
    a, b = fr.compute_fragments(mesh, [camera], cache_dir=False, progress=False) + \
        fr.compute_fragments(scaled, [scaled_cam], cache_dir=False, progress=False)
    assert (a.triangle == b.triangle).mean() > 0.999
    np.testing.assert_allclose(a.uv, b.uv, atol=1e-5)
    np.testing.assert_allclose(a.depth * scale, b.depth, rtol=1e-5)


def test_cache_is_reused_and_keyed_on_mesh_and_camera(cache_dir, monkeypatch):
    mesh = synthetic.plane(2.0, 2)
    camera = look_at_camera((0.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    (first,) = fr.compute_fragments(mesh, [camera], cache_dir=cache_dir, progress=False)
    assert len(list((cache_dir / "fragments").glob("*.npz"))) == 1

    def no_ray_casting(*_, **__):
        raise AssertionError("ray cast although a cached result exists")

    monkeypatch.setattr(fr, "RayCaster", no_ray_casting)
    (again,) = fr.compute_fragments(mesh, [camera], cache_dir=cache_dir, progress=False)
    np.testing.assert_array_equal(first.triangle, again.triangle)
    np.testing.assert_array_equal(first.uv, again.uv)

    moved = Mesh(vertices=mesh.vertices + [0.0, 0.1, 0.0], faces=mesh.faces, uv=mesh.uv,
                 face_object=mesh.face_object, object_names=mesh.object_names)
    turned = look_at_camera((0.0, 1.0, 1.0), (0.1, 0.0, 0.0))
    with pytest.raises(AssertionError, match="ray cast"):
        fr.compute_fragments(moved, [camera], cache_dir=cache_dir, progress=False)
    with pytest.raises(AssertionError, match="ray cast"):
        fr.compute_fragments(mesh, [turned], cache_dir=cache_dir, progress=False)
    assert fr.mesh_key(moved) != fr.mesh_key(mesh)


def test_a_cache_that_would_not_fit_on_its_disk_is_refused_before_any_ray_cast(cache_dir, monkeypatch):
    """The ray casts not cached yet need H·W·20 bytes (+ 1 KiB) each: with less free space than that
    plus the 256 MiB headroom, InputError names the cache folder, both amounts and $JAXDISTILL_CACHE,
    and nothing is cast; views already cached need nothing."""
    import collections
    from jaxdistill.errors import InputError

    mesh = synthetic.plane(2.0, 2)
    cached = look_at_camera((0.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    fr.compute_fragments(mesh, [cached], cache_dir=cache_dir, progress=False)
    new = [look_at_camera((0.0, 1.0, 1.0), (0.1 * i, 0.0, 0.0), width=640, height=480) for i in range(1, 4)]
    needed = 3 * (640 * 480 * (4 + 2 * 4 + 8) + 1024)
    usage = collections.namedtuple("usage", "total used free")
    free = needed + fr.CACHE_HEADROOM - 1              # one byte short
    monkeypatch.setattr(fr.shutil, "disk_usage", lambda path: usage(10 * free, 9 * free, free))
    monkeypatch.setattr(fr, "RayCaster", lambda *_: pytest.fail("ray cast before the space check"))
    with pytest.raises(InputError, match=rf"{cache_dir / 'fragments'}.*disk space.*3 views need "
                                         rf"{needed / 2 ** 30:.2f} GB.*{free / 2 ** 30:.2f} GB free.*JAXDISTILL_CACHE"):
        fr.compute_fragments(mesh, [cached, *new], cache_dir=cache_dir, progress=False)
    (again,) = fr.compute_fragments(mesh, [cached], cache_dir=cache_dir, progress=False)   # cached: no space needed
    assert again.triangle.shape == (24, 32)
    monkeypatch.setattr(fr.shutil, "disk_usage", lambda path: usage(10 * free, 9 * free, free + 1))
    with pytest.raises(pytest.fail.Exception, match="ray cast before the space check"):   # just enough: casts
        fr.compute_fragments(mesh, new, cache_dir=cache_dir, progress=False)


def test_the_cache_estimate_is_the_size_of_the_files_written(cache_dir):
    mesh = synthetic.plane(2.0, 2)
    camera = look_at_camera((0.0, 1.0, 1.0), (0.0, 0.0, 0.0), width=64, height=48)
    fr.compute_fragments(mesh, [camera], cache_dir=cache_dir, progress=False)
    (path,) = (cache_dir / "fragments").glob("*.npz")
    size = path.stat().st_size
    assert 64 * 48 * fr.CACHE_BYTES_PER_PIXEL <= size <= 64 * 48 * fr.CACHE_BYTES_PER_PIXEL + fr.CACHE_BYTES_PER_VIEW
