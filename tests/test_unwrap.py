"""UV detection, camera-driven xatlas unwrap, chunking of large objects, limits and cache."""

from __future__ import annotations

import time

import numpy as np
import pytest

from jaxdistill.render import atlas, uv_checks, unwrap as uw
from jaxdistill.scene.cameras import Camera
from jaxdistill.errors import InputError
from jaxdistill.scene.model import Mesh

pytest.importorskip("xatlas")
pytest.importorskip("embreex")


# ----------------------------------------------------------------------------- helpers


def grid(n: int, size: float = 1.0, noise: float = 0.0, offset=(0.0, 0.0, 0.0), seed: int = 0):
    """(vertices, faces) of an n x n grid of size^2 in z = 0 (2 n^2 faces, counter-clockwise seen
    from +z), z jittered by noise x the cell size, shifted by offset."""
    x, y = np.meshgrid(np.linspace(0, size, n + 1), np.linspace(0, size, n + 1))
    z = noise * size / n * np.random.default_rng(seed).standard_normal(x.shape)
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1) + offset
    i = (np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]).ravel()
    f = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    return v, f.astype(np.int64)


def make_mesh(parts, uvs=None) -> Mesh:
    """One object per (name, vertices, faces); uvs per object (F, 3, 2) or None for NaN."""
    vertices, faces, uv, face_object, offset = [], [], [], [], 0
    for k, (name, v, f) in enumerate(parts):
        vertices.append(v)
        faces.append(f + offset)
        u = None if uvs is None else uvs[k]
        uv.append(np.full((len(f), 3, 2), np.nan) if u is None else u)
        face_object.append(np.full(len(f), k, np.int32))
        offset += len(v)
    return Mesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces), uv=np.concatenate(uv),
                face_object=np.concatenate(face_object), object_names=tuple(p[0] for p in parts))


def planar_uv(v, f, size=1.0):
    """Per-corner UVs (x, y) / size: a valid, non-overlapping layout of a grid."""
    return v[f][..., :2] / size


def down_camera(height: float, focal: float, width: int = 64, height_px: int = 48, centre=(0.5, 0.5)) -> Camera:
    """Camera at (centre, height) looking straight down -z (OpenCV: x right, y down, z forward)."""
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = (centre[0], centre[1], height)
    K = np.array([[focal, 0, width / 2], [0, focal, height_px / 2], [0, 0, 1]])
    return Camera(K, c2w, width, height_px)


def areas3d(mesh: Mesh, idx) -> np.ndarray:
    t = mesh.triangles()[idx]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def check_layout(mesh: Mesh, idx, decision: uw.UVDecision, *, density_tol: float = 0.03):
    """UVs finite in [0, 1], no overlap at twice the page resolution, no folded chart, and the
    UV area matches 3D area x (texels_per_unit / page_size)^2."""
    uv = mesh.uv[idx]
    assert np.isfinite(uv).all() and uv.min() >= 0 and uv.max() <= 1
    assert uv_checks.uv_overlap_fraction(uv, resolution=2 * decision.page_size) == 0.0
    signed = uv_checks._uv_areas(uv)
    a3 = areas3d(mesh, idx)
    chart = uv_charts(mesh.faces[idx], uv)
    solid = a3 > 1e-12
    for c in np.unique(chart[solid]):                       # xatlas may mirror a chart, never fold one
        signs = np.sign(signed[solid & (chart == c)])
        assert (signs == signs[0]).all() and signs[0] != 0, c
    ratio = np.abs(signed).sum() * decision.page_size**2 / (a3.sum() * decision.texels_per_unit**2)
    assert abs(ratio - 1) < density_tol, ratio


def uv_charts(faces: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(F,) chart id: faces are connected where they share a corner (same vertex, same UV)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    key = np.concatenate([faces.reshape(-1, 1).astype(np.float64), uv.reshape(-1, 2)], axis=1)
    _, corner_id = np.unique(key, axis=0, return_inverse=True)
    face_of_corner = np.repeat(np.arange(len(faces)), 3)
    n = len(faces) + corner_id.max() + 1
    graph = coo_matrix((np.ones(len(corner_id)), (face_of_corner, len(faces) + corner_id.ravel())), shape=(n, n))
    return connected_components(graph, directed=False)[1][:len(faces)]


def reference_overlap(uv: np.ndarray, resolution: int) -> float:
    """Independent per-texel reference: barycentric inside-test of every texel centre in every triangle."""
    c = (np.stack(np.meshgrid(np.arange(resolution), np.arange(resolution)), -1).reshape(-1, 2) + 0.5) / resolution
    count = np.zeros(len(c), int)
    for tri in uv:
        m = np.array([tri[1] - tri[0], tri[2] - tri[0]]).T
        if abs(np.linalg.det(m)) < 1e-14:
            continue
        b = np.linalg.solve(m, (c - tri[0]).T).T
        count += (b[:, 0] > 1e-7) & (b[:, 1] > 1e-7) & (b.sum(1) < 1 - 1e-7)
    covered = (count > 0).sum()
    return (count > 1).sum() / covered if covered else 0.0


# ----------------------------------------------------------------------------- detection


def test_uv_problem_reasons():
    v, f = grid(6)
    tri, good = v[f], planar_uv(v, f)
    assert uv_checks.uv_problem(good, tri) is None
    assert "tiled" in uv_checks.uv_problem(good * 2, tri)
    assert "collapsed" in uv_checks.uv_problem(good * 0, tri)
    assert uv_checks.uv_problem(np.full_like(good, np.nan), tri) == "no texture coordinates"
    partly = good.copy()
    partly[3, 1] = np.nan
    assert "non-finite" in uv_checks.uv_problem(partly, tri)
    folded = good.copy()
    folded[..., 0] = np.minimum(folded[..., 0], 1 - folded[..., 0]) * 2     # both halves onto one
    assert "overlapping" in uv_checks.uv_problem(folded, tri)


def test_overlap_fraction_matches_reference():
    rng = np.random.default_rng(1)
    uv = rng.random((40, 3, 2)) * 0.6 + rng.random((40, 1, 2)) * 0.4
    for res in (16, 37):
        assert uv_checks.uv_overlap_fraction(uv, res) == pytest.approx(reference_overlap(uv, res), abs=1e-12)
    v, f = grid(10)
    assert uv_checks.uv_overlap_fraction(planar_uv(v, f), 64) == 0.0


def test_overlap_fraction_is_fast_on_a_million_faces():
    v, f = grid(708)                                        # 1.0M faces
    uv = planar_uv(v, f)
    t = time.perf_counter()
    assert uv_checks.uv_overlap_fraction(uv) == 0.0
    doubled = np.concatenate([uv[:200_000], uv[:200_000]])  # stacked copies
    assert uv_checks.uv_overlap_fraction(doubled) == 1.0
    stacked = np.tile(np.array([[[0, 0], [1, 0], [0, 1]]], float), (100_000, 1, 1))   # all the same big triangle
    assert uv_checks.uv_overlap_fraction(stacked) == 1.0
    assert time.perf_counter() - t < 15


# ----------------------------------------------------------------------------- policies


def two_objects():
    vg, fg = grid(8)
    vb, fb = grid(10, noise=0.2, offset=(2.0, 0.0, 0.0))
    return make_mesh([("good", vg, fg), ("bad", vb, fb)], uvs=[planar_uv(vg, fg), None]), len(fg)


def test_auto_keeps_good_uvs_and_unwraps_bad(tmp_path):
    mesh, n_good = two_objects()
    out, decisions = uw.ensure_uvs(mesh, cache_dir=False, progress=False)
    assert out.vertices is mesh.vertices and out.faces is mesh.faces and out.face_object is mesh.face_object
    assert out.object_names == mesh.object_names
    good, bad = decisions
    assert not good.reunwrapped and good.reason == "kept" and good.page_size is None
    np.testing.assert_array_equal(out.uv[:n_good], mesh.uv[:n_good])      # bitwise untouched
    assert bad.reunwrapped and bad.reason == "no texture coordinates" and not bad.cached
    check_layout(out, np.arange(n_good, mesh.num_faces), bad)
    table = uw.format_decisions(decisions)
    assert "good" in table and "kept" in table and "unwrapped" in table and "no texture coordinates" in table


def test_keep_policy_refuses_unusable_uvs():
    mesh, _ = two_objects()
    with pytest.raises(InputError) as err:
        uw.ensure_uvs(mesh, policy="keep", cache_dir=False, progress=False, mesh_file="room.glb")
    message = str(err.value)
    assert "room.glb" in message and "'bad'" in message and "no texture coordinates" in message
    assert "'good'" not in message


def test_unwrap_policy_unwraps_everything():
    mesh, n_good = two_objects()
    out, decisions = uw.ensure_uvs(mesh, policy="unwrap", cache_dir=False, progress=False)
    assert all(d.reunwrapped for d in decisions)
    assert decisions[0].reason == "unwrap requested"
    for o, d in enumerate(decisions):
        check_layout(out, np.flatnonzero(out.face_object == o), d)


def test_tiled_uvs_are_unwrapped():
    v, f = grid(6)
    mesh = make_mesh([("floor", v, f)], uvs=[planar_uv(v, f) * 3])
    out, (d,) = uw.ensure_uvs(mesh, cache_dir=False, progress=False)
    assert d.reunwrapped and "tiled" in d.reason
    check_layout(out, np.arange(mesh.num_faces), d)


# ----------------------------------------------------------------------------- density


def test_observed_density_of_a_plane_seen_head_on():
    v, f = grid(4, size=20.0, offset=(-10.0, -10.0, 0.0))
    vf, ff = grid(1, offset=(0.0, 0.0, 50.0))              # behind the camera: nobody sees it
    mesh = make_mesh([("plane", v, f), ("hidden", vf, ff)])
    cams = [down_camera(2.0, focal=500.0, width=640, height_px=480, centre=(0.0, 0.0))]
    density = uw.observed_texels_per_unit(mesh, cams)
    assert density[0] == pytest.approx(500.0 / 2.0, rel=1e-4)             # native focal, not the subsampled one
    assert np.isnan(density[1])
    cams.append(down_camera(4.0, focal=500.0, width=640, height_px=480, centre=(0.0, 0.0)))
    assert uw.observed_texels_per_unit(mesh, cams)[0] == pytest.approx(250.0, rel=1e-4)   # the closest wins


def test_page_size_follows_camera_distance_and_is_capped():
    v, f = grid(4, size=0.7)
    mesh = make_mesh([("plane", v, f)])
    far = down_camera(2.0, focal=512.0, centre=(0.35, 0.35))               # 256 texels/unit: 0.7 -> ~180 texels
    near = down_camera(1.0, focal=512.0, centre=(0.35, 0.35))              # twice as close
    out_far, (d_far,) = uw.ensure_uvs(mesh, [far], cache_dir=False, progress=False)
    out_near, (d_near,) = uw.ensure_uvs(mesh, [near], cache_dir=False, progress=False)
    assert d_far.texels_per_unit == 256.0 and d_near.texels_per_unit == 512.0
    assert (d_far.page_size, d_near.page_size) == (256, 512)
    check_layout(out_far, np.arange(mesh.num_faces), d_far)
    check_layout(out_near, np.arange(mesh.num_faces), d_near)
    out_cap, (d_cap,) = uw.ensure_uvs(mesh, [near], cache_dir=False, progress=False, max_page_size=128)
    assert d_cap.page_size == 128 and d_cap.texels_per_unit < 512 * 128 / 360 and "capped" in d_cap.reason
    check_layout(out_cap, np.arange(mesh.num_faces), d_cap, density_tol=0.05)


def test_unseen_object_gets_the_median_density():
    va, fa = grid(3, size=0.5)
    vb, fb = grid(3, size=0.5, offset=(0.0, 0.0, 50.0))
    mesh = make_mesh([("seen", va, fa), ("unseen", vb, fb)])
    _, decisions = uw.ensure_uvs(mesh, [down_camera(2.0, focal=256.0, centre=(0.25, 0.25))], cache_dir=False,
                                 progress=False)
    assert [d.texels_per_unit for d in decisions] == [128.0, 128.0]


def test_without_cameras_the_page_is_about_the_default_resolution():
    v, f = grid(6, noise=0.1)
    out, (d,) = uw.ensure_uvs(make_mesh([("thing", v, f)]), cache_dir=False, progress=False)
    assert d.page_size in (uw.DEFAULT_RESOLUTION // 2, uw.DEFAULT_RESOLUTION, 2 * uw.DEFAULT_RESOLUTION)
    check_layout(out, np.arange(len(f)), d)


# ----------------------------------------------------------------------------- large objects


def test_split_chunks_and_shelf_pack():
    rng = np.random.default_rng(3)
    centroids = rng.random((1000, 3)) * (5, 1, 1)
    chunks = atlas.split_chunks(centroids, 130)
    assert all(len(c) <= 130 for c in chunks)
    np.testing.assert_array_equal(np.sort(np.concatenate(chunks)), np.arange(1000))
    sizes = rng.integers(1, 40, (30, 2))
    offsets, w, h = atlas.shelf_pack(sizes, padding=2)
    assert (offsets >= 0).all() and (offsets + sizes <= (w, h)).all()
    lo, hi = offsets, offsets + sizes
    for i in range(len(sizes)):
        for j in range(i):
            apart = (lo[i] >= hi[j] + 2) | (lo[j] >= hi[i] + 2)
            assert apart.any(), (i, j)


def test_chunked_unwrap_is_valid(capsys, caplog):
    v, f = grid(45, noise=0.2)                               # 4050 faces
    mesh = make_mesh([("big", v, f)])
    with caplog.at_level("INFO", logger="jaxdistill.render.unwrap"):
        out, (d,) = uw.ensure_uvs(mesh, cache_dir=False, progress=True, chunk_faces=500)
    assert "16 chunk(s)" in caplog.text                    # 4050 -> 2025 -> 1012 -> 506 -> 253
    check_layout(out, np.arange(mesh.num_faces), d, density_tol=0.05)
    assert "uv unwrap big" in capsys.readouterr().err


def test_chunks_fall_back_to_the_shelf_packer(monkeypatch):
    def fail(parts, padding):
        raise RuntimeError("no repack")

    monkeypatch.setattr(atlas, "_repack", fail)
    v, f = grid(30, noise=0.2)                               # 1800 faces
    out, (d,) = uw.ensure_uvs(make_mesh([("big", v, f)]), cache_dir=False, progress=False, chunk_faces=500)
    check_layout(out, np.arange(len(f)), d, density_tol=0.05)


def test_large_objects_are_refused_with_a_decimation_hint():
    v, f = grid(20)                                          # 800 faces
    mesh = make_mesh([("statue", v, f)])
    with pytest.raises(InputError) as err:
        uw.ensure_uvs(mesh, cache_dir=False, progress=False, max_faces=500, mesh_file="statue.glb")
    message = str(err.value)
    assert "statue.glb" in message and "'statue'" in message and "800 faces" in message and "decimat" in message
    with pytest.raises(InputError) as err:
        uw.ensure_uvs(mesh, cache_dir=False, progress=False, time_limit_s=1e-6)
    assert "800 faces" in str(err.value) and "would take about" in str(err.value) and "decimat" in str(err.value)


def test_time_estimate_is_refined_after_the_first_chunk(monkeypatch):
    v, f = grid(20)
    monkeypatch.setattr(uw, "SECONDS_PER_FACE", 0.0)         # the up-front estimate lets it start
    with pytest.raises(InputError) as err:
        uw.ensure_uvs(make_mesh([("statue", v, f)]), cache_dir=False, progress=False, time_limit_s=1e-6,
                      chunk_faces=200)
    assert "measured on the first chunk" in str(err.value) and "decimat" in str(err.value)


# ----------------------------------------------------------------------------- cache


def test_cache_hits_misses_and_can_be_disabled(tmp_path, monkeypatch):
    v, f = grid(6, noise=0.1)
    mesh = make_mesh([("thing", v, f)])
    cam = [down_camera(3.0, focal=300.0)]
    out1, (d1,) = uw.ensure_uvs(mesh, cam, cache_dir=tmp_path, progress=False)
    assert not d1.cached and len(list((tmp_path / "unwrap").glob("*.npz"))) == 1
    out2, (d2,) = uw.ensure_uvs(mesh, cam, cache_dir=tmp_path, progress=False)
    assert d2.cached and d2.page_size == d1.page_size and d2.texels_per_unit == d1.texels_per_unit
    np.testing.assert_array_equal(out2.uv, out1.uv)
    nearby = [down_camera(3.1, focal=300.0)]                 # same power-of-two density: reused
    assert uw.ensure_uvs(mesh, nearby, cache_dir=tmp_path, progress=False)[1][0].cached
    (path,) = (tmp_path / "unwrap").glob("*.npz")
    path.write_bytes(b"not a zip")                           # a damaged entry is recomputed and rewritten
    out3, (d3,) = uw.ensure_uvs(mesh, cam, cache_dir=tmp_path, progress=False)
    assert not d3.cached and uw.ensure_uvs(mesh, cam, cache_dir=tmp_path, progress=False)[1][0].cached
    moved = make_mesh([("thing", v * 1.01, f)])
    assert not uw.ensure_uvs(moved, cam, cache_dir=tmp_path, progress=False)[1][0].cached
    assert len(list((tmp_path / "unwrap").glob("*"))) == 2
    empty = tmp_path / "default"
    monkeypatch.setenv("JAXDISTILL_CACHE", str(empty))
    uw.ensure_uvs(moved, cam, cache_dir=False, progress=False)
    assert not empty.exists()
