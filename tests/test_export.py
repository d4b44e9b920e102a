"""Exports: map files, tangent-space normals, glTF (orientation via a raw GLB parse), plots."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from jaxdistill.export import gltf, pages as page_files, plots, tangents
from jaxdistill.io import images as imageio
from jaxdistill.scene.cameras import Camera, look_at
from jaxdistill.scene.model import Mesh
from tolerance import assert_close


def srgb_encode(x):
    """IEC 61966-2-1 sRGB transfer function (independent reference)."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def random_pages(sizes, seed=0):
    rng = np.random.default_rng(seed)
    pages = {"albedo": [], "normal": [], "roughness": [], "metallic": [], "irradiance": []}
    for s in sizes:
        pages["albedo"].append(rng.uniform(0, 1, (s, s, 3)).astype(np.float32))
        n = rng.normal(size=(s, s, 3))
        pages["normal"].append((n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32))
        pages["roughness"].append(rng.uniform(0, 1, (s, s, 1)).astype(np.float32))
        pages["metallic"].append(rng.uniform(0, 1, (s, s, 1)).astype(np.float32))
        pages["irradiance"].append(rng.uniform(0, 3, (s, s, 3)).astype(np.float32))
    return pages


def quad_mesh(uv_of_xy=lambda x, y: (x, y), faces=((0, 1, 2), (0, 2, 3)), rotation=None):
    """Unit square in the z=0 plane (counter-clockwise seen from +z), UVs from (x, y)."""
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    vertices = np.concatenate([xy, np.zeros((4, 1))], axis=1)
    if rotation is not None:
        vertices = vertices @ rotation.T
    faces = np.array(faces, np.int64)
    uv = np.array([[uv_of_xy(*xy[i]) for i in face] for face in faces], np.float64)
    return Mesh(vertices=vertices, faces=faces, uv=uv, face_object=np.zeros(len(faces), np.int32),
                object_names=("quad",))


# ----------------------------------------------------------------------------- write_maps


def test_page_names():
    assert page_files.page_names(["floor", "bed"], [0, 1]) == ["floor", "bed"]
    assert page_files.page_names(["floor", "bed", "lamp"], [0, 0, 1]) == ["page_000", "lamp"]
    assert page_files.page_names(["a", "b"], [0, 0]) == ["page_000"]
    assert page_files.page_names(["my lamp/1", "x"], [0, 1]) == ["my_lamp_1", "x"]
    assert page_files.page_names(["a b", "a/b"], [0, 1]) == ["a_b", "a_b_001"]


def test_write_maps_single_page(tmp_path):
    pages = random_pages([8])
    written = page_files.write_maps(tmp_path, pages, ["floor", "bed"], [0, 0])
    names = sorted(p.relative_to(tmp_path).as_posix() for p in written)
    assert names == sorted(f"maps/{m}.{e}" for m in pages for e in ("exr", "png"))
    for m in pages:
        np.testing.assert_array_equal(imageio.read_image(tmp_path / f"maps/{m}.exr"), pages[m][0])
    tol = 0.5 / 255 + 1e-6
    png = lambda m: imageio.read_image(tmp_path / f"maps/{m}.png", linear=False)
    np.testing.assert_allclose(png("albedo"), srgb_encode(pages["albedo"][0]), atol=tol)
    np.testing.assert_allclose(png("irradiance"), srgb_encode(np.minimum(pages["irradiance"][0], 1)), atol=tol)
    assert (pages["irradiance"][0] > 1).any() and imageio.read_image(tmp_path / "maps/irradiance.exr").max() > 1
    np.testing.assert_allclose(png("normal"), (pages["normal"][0] + 1) / 2, atol=tol)
    np.testing.assert_allclose(png("roughness"), pages["roughness"][0], atol=tol)
    np.testing.assert_allclose(png("metallic"), pages["metallic"][0], atol=tol)


def png_zlib_level_class(path) -> int:
    """FLEVEL of the first IDAT chunk's zlib header (RFC 1950: 0 fastest, 1 fast, 2 default, 3 best;
    zlib writes 1 for levels 2-5 and 2 for 6)."""
    data = path.read_bytes()
    at = 8                                                       # after the PNG signature
    while True:
        length, kind = struct.unpack(">I4s", data[at:at + 8])
        if kind == b"IDAT":
            cmf, flg = data[at + 8], data[at + 9]
            assert cmf & 0x0F == 8 and (cmf << 8 | flg) % 31 == 0          # deflate, a valid header
            return flg >> 6
        at += 12 + length


def test_pngs_are_written_at_the_faster_zlib_level_and_stay_lossless(tmp_path):
    """PNG_COMPRESSION_LEVEL (4, against OpenImageIO's 6) reaches the file: the zlib header says
    a fast level; the 8-bit values read back exactly."""
    assert imageio.PNG_COMPRESSION_LEVEL == 4
    values = np.random.default_rng(0).integers(0, 256, (24, 32, 3)) / 255.0
    imageio.write_image(tmp_path / "a.png", values, encode_srgb=False)
    assert png_zlib_level_class(tmp_path / "a.png") == 1
    np.testing.assert_array_equal(np.round(imageio.read_image(tmp_path / "a.png", linear=False) * 255), values * 255)


def test_write_maps_several_pages(tmp_path):
    pages = random_pages([8, 4])
    written = page_files.write_maps(tmp_path, pages, ["wall", "lamp"], [0, 1])
    assert len(written) == 5 * 2 * 2
    for m in pages:
        for p, stem in enumerate(["wall", "lamp"]):
            np.testing.assert_array_equal(imageio.read_image(tmp_path / f"maps/{m}/{stem}.exr"), pages[m][p])
            assert imageio.image_size(tmp_path / f"maps/{m}/{stem}.png")[:2] == pages[m][p].shape[:2][::-1]


def test_write_maps_errors(tmp_path):
    pages = random_pages([8, 4])
    bad = dict(pages, roughness=[pages["roughness"][0], np.zeros((8, 8, 1), np.float32)])
    with pytest.raises(ValueError, match="'roughness' page 1 is 8x8"):
        page_files.write_maps(tmp_path, bad, ["wall", "lamp"], [0, 1])
    with pytest.raises(ValueError, match=r"'metallic' page 0.*\(S, S, 1\)"):
        page_files.write_maps(tmp_path, dict(pages, metallic=pages["albedo"]), ["wall", "lamp"], [0, 1])
    with pytest.raises(ValueError, match="unknown map 'depth'"):
        page_files.write_maps(tmp_path, {"depth": pages["roughness"]}, ["wall", "lamp"], [0, 1])
    with pytest.raises(ValueError, match="2 pages, but object_page uses 1"):
        page_files.write_maps(tmp_path, pages, ["wall", "lamp"], [0, 0])
    # a page that cannot be written (pages are written two at a time) stops the call with its error
    (tmp_path / "out" / "maps" / "normal").mkdir(parents=True)
    (tmp_path / "out" / "maps" / "normal" / "lamp.png").mkdir()        # a folder where the PNG goes
    with pytest.raises(OSError, match="lamp.png"):
        page_files.write_maps(tmp_path / "out", pages, ["wall", "lamp"], [0, 1])


# ----------------------------------------------------------------------------- tangent space

TILT = 0.4
S = 8


def uniform_normal(n, size=S):
    n = np.asarray(n, np.float64)
    return [np.broadcast_to(n / np.linalg.norm(n), (size, size, 3)).astype(np.float32)]


def decoded(page):
    return page.astype(np.float64) * 2 - 1


@pytest.mark.parametrize("uv_of_xy, world, expected", [
    # UVs along x, y: the frame is the world frame
    (lambda x, y: (x, y), (0, 0, 1), (0, 0, 1)),
    (lambda x, y: (x, y), (np.sin(TILT), 0, np.cos(TILT)), (np.sin(TILT), 0, np.cos(TILT))),
    (lambda x, y: (x, y), (0, np.sin(TILT), np.cos(TILT)), (0, np.sin(TILT), np.cos(TILT))),
    # UVs rotated by 90 degrees: +u along +y, +v along -x
    (lambda x, y: (y, 1 - x), (np.sin(TILT), 0, np.cos(TILT)), (0, -np.sin(TILT), np.cos(TILT))),
    (lambda x, y: (y, 1 - x), (0, np.sin(TILT), np.cos(TILT)), (np.sin(TILT), 0, np.cos(TILT))),
    # mirrored u: +u along -x, v still along +y (bitangent sign -1)
    (lambda x, y: (1 - x, y), (np.sin(TILT), 0, np.cos(TILT)), (-np.sin(TILT), 0, np.cos(TILT))),
    (lambda x, y: (1 - x, y), (0, np.sin(TILT), np.cos(TILT)), (0, np.sin(TILT), np.cos(TILT))),
    # mirrored v
    (lambda x, y: (x, 1 - y), (0, np.sin(TILT), np.cos(TILT)), (0, -np.sin(TILT), np.cos(TILT))),
    # a normal facing away from the surface
    (lambda x, y: (x, y), (0, 0, -1), (0, 0, -1)),
])
def test_tangent_space_quad(uv_of_xy, world, expected):
    (page,) = tangents.tangent_space_normals(uniform_normal(world), quad_mesh(uv_of_xy), [0])
    assert page.shape == (S, S, 3) and page.dtype == np.float32
    np.testing.assert_allclose(decoded(page), np.broadcast_to(expected, (S, S, 3)), atol=1e-6)


def test_tangent_space_is_rotation_invariant():
    angle = 0.7
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    world = np.array([np.sin(TILT), 0.2, np.cos(TILT)])
    mesh = quad_mesh(lambda x, y: (y, 1 - x), rotation=rot)
    (page,) = tangents.tangent_space_normals(uniform_normal(rot @ world), mesh, [0])
    (flat,) = tangents.tangent_space_normals(uniform_normal(world), quad_mesh(lambda x, y: (y, 1 - x)), [0])
    np.testing.assert_allclose(page, flat, atol=1e-6)
    w = world / np.linalg.norm(world)
    np.testing.assert_allclose(decoded(page)[3, 3], [w[1], -w[0], w[2]], atol=1e-6)


def test_tangent_space_uncovered_seams_and_unknown():
    # one triangle covering the UV half u >= v (the page's upper right half, as row 0 is v = 1)
    mesh = quad_mesh(faces=((0, 1, 2),))
    world = uniform_normal((np.sin(TILT), 0, np.cos(TILT)), size=16)[0].copy()
    world[15, 15] = 0.0  # unknown normal inside the triangle
    (page,) = tangents.tangent_space_normals([world], mesh, [0], dilate=2)
    tilted = (np.array([np.sin(TILT), 0, np.cos(TILT)]) + 1) / 2
    r, c = np.mgrid[:16, :16]
    u, v = (c + 0.5) / 16, 1 - (r + 0.5) / 16
    covered = u >= v
    known = covered & ~((r == 15) & (c == 15))
    np.testing.assert_allclose(page[known], np.broadcast_to(tilted, (int(known.sum()), 3)), atol=1e-6)
    np.testing.assert_allclose(page[15, 15], [0.5, 0.5, 1.0])
    texel_distance = (v - u) * 16  # distance from the diagonal in texels along a row or column
    far = texel_distance > 4.5  # beyond two dilation passes (a diagonal step moves 2 texels off the edge)
    np.testing.assert_allclose(page[far], np.broadcast_to([0.5, 0.5, 1.0], (int(far.sum()), 3)))
    # the first row of texels outside the triangle (a seam) takes the face's frame
    seam = (~covered) & (texel_distance <= 1.0)
    assert seam.any()
    np.testing.assert_allclose(page[seam], np.broadcast_to(tilted, (int(seam.sum()), 3)), atol=1e-6)
    # without dilation they stay flat
    (plain,) = tangents.tangent_space_normals([world], mesh, [0], dilate=0)
    np.testing.assert_allclose(plain[~covered], np.broadcast_to([0.5, 0.5, 1.0], (int((~covered).sum()), 3)))


def test_tangent_space_pages_and_errors():
    mesh = quad_mesh()
    two = Mesh(vertices=mesh.vertices, faces=mesh.faces, uv=mesh.uv, face_object=np.array([0, 1], np.int32),
               object_names=("a", "b"))
    tilt = (np.sin(TILT), 0, np.cos(TILT))
    p0, p1 = tangents.tangent_space_normals(uniform_normal(tilt, 8) + uniform_normal(tilt, 4), two, [0, 1])
    # each page only holds its object's face: face 0 covers u >= v, face 1 covers u <= v
    assert p0.shape == (8, 8, 3) and p1.shape == (4, 4, 3)
    np.testing.assert_allclose(p0[0, 0], [0.5, 0.5, 1.0])  # top left: u < v, face 1's half
    np.testing.assert_allclose(p1[0, 0], (np.array(tilt) + 1) / 2, atol=1e-6)
    with pytest.raises(ValueError, match="'normal' page 0"):
        tangents.tangent_space_normals([np.zeros((8, 4, 3))], mesh, [0])
    with pytest.raises(ValueError, match="object_page"):
        tangents.tangent_space_normals(uniform_normal(tilt), two, [0, 1])


# ----------------------------------------------------------------------------- glTF


def read_glb(path):
    """(json, bin) chunks of a GLB file, parsed by the glTF 2.0 spec (no trimesh)."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    n, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    doc = json.loads(data[20:20 + n])
    n2, kind2 = struct.unpack_from("<I4s", data, 20 + n)
    assert kind2 == b"BIN\x00"
    return doc, data[28 + n:28 + n + n2]


def accessor(doc, blob, index):
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[acc["componentType"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    assert view.get("byteStride", np.dtype(dtype).itemsize * width) == np.dtype(dtype).itemsize * width
    return np.frombuffer(blob, dtype, acc["count"] * width, start).reshape(acc["count"], width)


def gltf_scene():
    """Object 'wall' (a quad, 2 faces) on an 8x8 page, 'lamp' (1 face, tilted) on a 4x4 page."""
    quad = quad_mesh()
    lamp_v = np.array([[2.0, 0.0, 0.0], [3.0, 0.0, 1.0], [2.0, 1.0, 0.5]])
    mesh = Mesh(vertices=np.concatenate([quad.vertices, lamp_v]),
                faces=np.concatenate([quad.faces, [[4, 5, 6]]]),
                uv=np.concatenate([quad.uv, [[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]]]),
                face_object=np.array([0, 0, 1], np.int32), object_names=("wall", "lamp"))
    pages = random_pages([8, 4], seed=3)
    red_blue = np.zeros((8, 8, 3), np.float32)
    red_blue[:4, :, 0] = 1.0  # top half (rows 0..3, v > 0.5) red
    red_blue[4:, :, 2] = 1.0  # bottom half blue
    pages["albedo"][0] = red_blue
    return mesh, pages


def decode_png(doc, blob, texture_index):
    import PIL.Image
    import io

    image = doc["images"][doc["textures"][texture_index]["source"]]
    view = doc["bufferViews"][image["bufferView"]]
    start = view.get("byteOffset", 0)
    return np.asarray(PIL.Image.open(io.BytesIO(blob[start:start + view["byteLength"]])).convert("RGB"))


def test_gltf_orientation_raw(tmp_path):
    mesh, pages = gltf_scene()
    path = gltf.write_gltf(tmp_path / "room.glb", mesh, [0, 1], pages)
    doc, blob = read_glb(path)
    wall = next(m for m in doc["meshes"] if m["name"] == "wall")
    prim = wall["primitives"][0]
    texcoord = accessor(doc, blob, prim["attributes"]["TEXCOORD_0"]).astype(np.float64)
    position = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    index = doc["materials"][prim["material"]]["pbrMetallicRoughness"]["baseColorTexture"]["index"]
    image = decode_png(doc, blob, index)
    assert image.shape == (8, 8, 3)
    view = doc["bufferViews"][doc["images"][doc["textures"][index]["source"]]["bufferView"]]
    png = tmp_path / "embedded.png"
    png.write_bytes(blob[view.get("byteOffset", 0):view.get("byteOffset", 0) + view["byteLength"]])
    assert png_zlib_level_class(png) == 1                # PNG_COMPRESSION_LEVEL, as the maps' files
    # glTF: texcoord (s, t) samples the image at column s * W, row t * H from the top
    for (s, t), p in zip(texcoord, position):
        our_v = p[1]  # the wall's UVs are (x, y) in our convention (v up)
        np.testing.assert_allclose([s, t], [p[0], 1 - our_v], atol=1e-6)
        row = min(int(np.floor(t * 8 + (0.5 if t < 0.5 else -0.5))), 7)  # a texel inside, not on the edge
        pixel = image[row, min(int(s * 8), 7)]
        expected = [255, 0, 0] if our_v == 1 else [0, 0, 255]
        np.testing.assert_array_equal(pixel, expected)


def test_gltf_reload_with_trimesh(tmp_path):
    import trimesh

    mesh, pages = gltf_scene()
    path = gltf.write_gltf(tmp_path / "room.glb", mesh, [0, 1], pages)
    loaded = trimesh.load(path, force="scene", process=False)
    assert sorted(loaded.geometry) == ["lamp", "wall"]
    normals = tangents.tangent_space_normals(pages["normal"], mesh, [0, 1])
    for object_id, (name, page) in enumerate([("wall", 0), ("lamp", 1)]):
        geom = loaded.geometry[name]
        face_ids = np.nonzero(mesh.face_object == object_id)[0]
        assert len(geom.faces) == len(face_ids) and len(geom.vertices) == 3 * len(face_ids)
        np.testing.assert_allclose(geom.vertices[geom.faces], mesh.triangles()[face_ids], atol=1e-6)
        # trimesh undoes the glTF flip: the reloaded UVs are ours again (v up, image row 0 at v = 1)
        np.testing.assert_allclose(geom.visual.uv[geom.faces], mesh.uv[face_ids], atol=1e-6)
        mat = geom.visual.material
        assert mat.metallicFactor == 1.0 and mat.roughnessFactor == 1.0
        base = np.asarray(mat.baseColorTexture.convert("RGB"), np.float64) / 255
        np.testing.assert_allclose(base, srgb_encode(pages["albedo"][page]), atol=0.5 / 255 + 1e-6)
        mr = np.asarray(mat.metallicRoughnessTexture.convert("RGB"), np.float64) / 255
        np.testing.assert_allclose(mr[..., 1], pages["roughness"][page][..., 0], atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(mr[..., 2], pages["metallic"][page][..., 0], atol=0.5 / 255 + 1e-6)
        nt = np.asarray(mat.normalTexture.convert("RGB"), np.float64) / 255
        np.testing.assert_allclose(nt, normals[page], atol=0.5 / 255 + 1e-6)
    wall = loaded.geometry["wall"]
    top = wall.visual.uv[:, 1] == 1.0
    image = np.asarray(wall.visual.material.baseColorTexture.convert("RGB"))
    assert top.any() and (image[0] == [255, 0, 0]).all() and (image[-1] == [0, 0, 255]).all()


def test_gltf_albedo_only_and_atlas(tmp_path):
    import trimesh

    mesh, pages = gltf_scene()
    atlas = {"albedo": [pages["albedo"][0]]}
    path = gltf.write_gltf(tmp_path / "atlas.glb", mesh, [0, 0], atlas)
    doc, _ = read_glb(path)
    assert len(doc["materials"]) == 1 and len(doc["images"]) == 1
    material = doc["materials"][0]
    assert set(material["pbrMetallicRoughness"]) >= {"baseColorTexture"}
    assert "metallicRoughnessTexture" not in material["pbrMetallicRoughness"]
    assert material["pbrMetallicRoughness"]["metallicFactor"] == 0.0 and "normalTexture" not in material
    loaded = trimesh.load(path, force="scene", process=False)
    assert sorted(loaded.geometry) == ["lamp", "wall"]
    with pytest.raises(ValueError, match=".glb"):
        gltf.write_gltf(tmp_path / "atlas.obj", mesh, [0, 0], atlas)

def mirrored_scene():
    """gltf_scene plus object 'mirror': a triangle whose u runs against dP/dx x (mirrored UVs)."""
    mesh, pages = gltf_scene()
    v = np.array([[0.0, 0.0, 2.0], [1.0, 0.0, 2.0], [0.0, 1.0, 2.5]])
    mesh = Mesh(vertices=np.concatenate([mesh.vertices, v]), faces=np.concatenate([mesh.faces, [[7, 8, 9]]]),
                uv=np.concatenate([mesh.uv, [[[1.0, 0.0], [0.0, 0.0], [1.0, 1.0]]]]),
                face_object=np.array([0, 0, 1, 2], np.int32), object_names=("wall", "lamp", "mirror"))
    extra = random_pages([4], seed=5)
    return mesh, {m: pages[m] + extra[m] for m in pages}


def test_gltf_normals_and_tangents_decode_the_normal_pages(tmp_path):
    """NORMAL/TANGENT are unit, orthogonal, w = +-1, T along dP/du (solved independently by least
    squares) and w the UVs' handedness; a glTF renderer's decode of the normal texture with them,
    T x + cross(N, T) w y + N z, gives back the world normal pages (to 8-bit precision)."""
    mesh, pages = mirrored_scene()
    path = gltf.write_gltf(tmp_path / "room.glb", mesh, [0, 1, 2], pages)
    doc, blob = read_glb(path)
    signs = {}
    for object_id, name in enumerate(mesh.object_names):
        prim = next(m for m in doc["meshes"] if m["name"] == name)["primitives"][0]
        normal = accessor(doc, blob, prim["attributes"]["NORMAL"]).astype(np.float64)
        tangent = accessor(doc, blob, prim["attributes"]["TANGENT"]).astype(np.float64)
        assert_close(np.linalg.norm(normal, axis=1), np.ones(len(normal)))
        assert_close(np.linalg.norm(tangent[:, :3], axis=1), np.ones(len(normal)))
        assert np.abs(np.sum(normal * tangent[:, :3], axis=1)).max() < 1e-6
        assert set(np.unique(tangent[:, 3])) <= {-1.0, 1.0}
        texture = decode_png(doc, blob, doc["materials"][prim["material"]]["normalTexture"]["index"]) / 255.0
        size = texture.shape[0]
        for k, f in enumerate(np.nonzero(mesh.face_object == object_id)[0]):
            p, uv = mesh.triangles()[f], mesh.uv[f]
            duv = np.stack([uv[1] - uv[0], uv[2] - uv[0]])                  # (2 edges, (du, dv))
            dp = np.stack([p[1] - p[0], p[2] - p[0]])
            dpduv = np.linalg.lstsq(duv, dp, rcond=None)[0]                   # rows dP/du, dP/dv
            n = np.cross(dp[0], dp[1])
            n /= np.linalg.norm(n)
            t = dpduv[0] - n * (n @ dpduv[0])
            for c in range(3):
                assert_close(normal[3 * k + c], n)
                assert_close(tangent[3 * k + c, :3], t / np.linalg.norm(t))
                assert tangent[3 * k + c, 3] == np.sign(np.cross(n, t) @ dpduv[1])
            signs[name] = tangent[3 * k, 3]
            centre = uv.mean(axis=0)                                          # a texel inside the face
            row, col = int((1.0 - centre[1]) * size), int(centre[0] * size)
            ts = 2.0 * texture[row, col] - 1.0
            t_f, w = tangent[3 * k, :3], tangent[3 * k, 3]
            decoded_world = ts[0] * t_f + ts[1] * np.cross(normal[3 * k], t_f) * w + ts[2] * normal[3 * k]
            world = pages["normal"][object_id][row, col].astype(np.float64)
            np.testing.assert_allclose(decoded_world, world / np.linalg.norm(world), atol=3 * 2 / 255)
    assert signs["mirror"] == -1.0 and signs["wall"] == 1.0


def gltf_projection(doc, node) -> tuple:
    """(pixel function of world points, camera) from a glTF camera node, per the glTF spec:
    view = inverse(node matrix), infinite perspective matrix, NDC -> pixels of the extras' size."""
    cam = doc["cameras"][node["camera"]]
    persp = cam["perspective"]
    matrix = np.asarray(node["matrix"], np.float64).reshape(4, 4).T        # column-major
    tan = np.tan(persp["yfov"] / 2.0)
    a, zn = persp["aspectRatio"], persp["znear"]
    proj = np.array([[1 / (a * tan), 0, 0, 0], [0, 1 / tan, 0, 0], [0, 0, -1, -2 * zn], [0, 0, -1, 0]])
    w, h = cam["extras"]["width"], cam["extras"]["height"]
    shift = np.asarray(cam["extras"]["principal_point_offset_px"])

    def pixels(points):
        clip = (proj @ np.linalg.inv(matrix) @ np.c_[points, np.ones(len(points))].T).T
        ndc = clip[:, :2] / clip[:, 3:4]
        return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1) + shift
    return pixels, cam


@pytest.mark.parametrize("K", [[[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]],          # centred
                               [[224.5, 0, 169.4], [0, 251.0, 113.5], [0, 0, 1]]])       # off-centre, fx != fy
def test_gltf_cameras_project_like_K_and_c2w(tmp_path, K):
    mesh, pages = gltf_scene()
    cameras = [("view_a", look_at([3.0, -2.0, 1.5], [0.5, 0.5, 0.0], [0.0, 0.0, 1.0], K, 320, 240)),
               ("view_b", look_at([-1.0, 2.0, 2.0], [0.5, 0.5, 0.2], [0.0, 0.0, 1.0], K, 320, 240))]
    path = gltf.write_gltf(tmp_path / "room.glb", mesh, [0, 1], pages, cameras)
    doc, _ = read_glb(path)
    points = np.random.default_rng(0).uniform([0, 0, 0], [1, 1, 0.5], (20, 3))
    nodes = {n["name"]: n for n in doc["nodes"] if "camera" in n}
    assert sorted(nodes) == ["view_a", "view_b"]
    assert all(doc["nodes"].index(n) in doc["scenes"][doc["scene"]]["nodes"] for n in nodes.values())
    for name, camera in cameras:
        pixels, cam = gltf_projection(doc, nodes[name])
        assert cam["name"] == name and cam["type"] == "perspective"
        expected, depth = camera.project(points)
        assert (depth > 0).all()
        assert_close(pixels(points), expected, rtol=1e-9)
        centred = np.allclose(cam["extras"]["principal_point_offset_px"], 0.0)
        assert centred == (K[0][2] == 160 and K[1][2] == 120)
        if K[0][0] == K[1][1]:
            assert_close(cam["perspective"]["aspectRatio"], 320 / 240, rtol=1e-12)


# ----------------------------------------------------------------------------- plots


def test_write_loss_plot(tmp_path):
    steps = np.arange(200)
    loss = np.exp(-steps / 50) * (1 + 0.2 * np.sin(steps))
    psnr = {"albedo PSNR (dB)": (steps[::20], 10 + steps[::20] / 10)}
    path = plots.write_loss_plot(tmp_path / "plots/loss.png", steps, loss, extra=psnr, title="bedroom")
    image = imageio.read_image(path, linear=False)
    assert image.shape[0] >= 300 and image.shape[1] >= 500 and image.std() > 0.01
    negative = plots.write_loss_plot(tmp_path / "neg.png", steps, loss - 0.5)
    assert imageio.read_image(negative, linear=False).std() > 0.01
    with pytest.raises(ValueError, match="loss: 3 steps but 2 values"):
        plots.write_loss_plot(tmp_path / "bad.png", [0, 1, 2], [1.0, 2.0])


def test_write_contact_sheet(tmp_path):
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 1, (10, 12, 3))
    rows = [[a, rng.uniform(0, 1, (10, 16, 3)), None],
            [rng.uniform(0, 1, (14, 12, 3)), None, rng.uniform(0, 1, (6, 9, 3))]]
    path = plots.write_contact_sheet(tmp_path / "sheet.png", rows, ["photo", "albedo", "normal"],
                                     ["view_000", "view_001"], gap=4, title_px=20, label_px=40)
    sheet = imageio.read_image(path, linear=False)
    widths, heights = [12, 16, 9], [10, 14]
    assert sheet.shape == (20 + sum(heights) + 4 * 3, 40 + sum(widths) + 4 * 4, 3)
    # images are drawn 1:1 (no resampling), grey where missing
    x0, y0 = 40 + 4, 20 + 4
    np.testing.assert_allclose(sheet[y0:y0 + 10, x0:x0 + 12], a, atol=0.5 / 255 + 1e-6)
    x2 = x0 + 12 + 4 + 16 + 4
    np.testing.assert_allclose(sheet[y0:y0 + 10, x2:x2 + 9], 0.5, atol=1 / 255)
    # the title band holds text (non-white pixels)
    assert (sheet[:20] < 0.5).any() and (sheet[y0:, :40] < 0.5).any()
    plain = plots.write_contact_sheet(tmp_path / "plain.png", rows, ["a", "b", "c"], gap=2, title_px=16)
    assert imageio.read_image(plain, linear=False).shape == (16 + 24 + 2 * 3, 37 + 2 * 4, 3)
    with pytest.raises(ValueError, match="row 1: 2 images for 3 columns"):
        plots.write_contact_sheet(tmp_path / "bad.png", [rows[0], rows[1][:2]], ["a", "b", "c"])


@pytest.mark.parametrize("maps", [("albedo", "normal", "roughness", "metallic", "irradiance"), ("roughness",),
                                  ("metallic", "irradiance"), ("irradiance",)])
def test_material_images_built_one_map_at_a_time(maps):
    """write_outputs converts one map at a time (material_layers, then combine_material_layers),
    so the float pages of every map are never held together. Against the glTF packing written
    out in NumPy: baseColor = 8-bit sRGB albedo; metallicRoughness = (255, roughness, metallic),
    G 255 without roughness, B 0 without metallic; normal = 8-bit tangent_space_normals; no
    texture from irradiance."""
    mesh, pages = gltf_scene()
    pages = {m: pages[m] for m in maps}
    layers = {m: gltf.material_layers(m, pages[m], mesh, [0, 1]) for m in maps}
    assert layers.get("irradiance", None) is None
    images = gltf.combine_material_layers({m: v for m, v in layers.items() if v is not None}, 2)
    u8 = lambda x: np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)  # noqa: E731
    for p, page in enumerate(images):
        size = (8, 4)[p]
        expected = {}
        if "albedo" in maps:
            expected["baseColorTexture"] = u8(srgb_encode(pages["albedo"][p]))
        if "roughness" in maps or "metallic" in maps:
            rough = u8(pages["roughness"][p][..., 0]) if "roughness" in maps else np.full((size, size), 255, np.uint8)
            metal = u8(pages["metallic"][p][..., 0]) if "metallic" in maps else np.zeros((size, size), np.uint8)
            expected["metallicRoughnessTexture"] = np.stack([np.full((size, size), 255, np.uint8), rough, metal], -1)
        if "normal" in maps:
            expected["normalTexture"] = u8(tangents.tangent_space_normals(pages["normal"], mesh, [0, 1])[p])
        assert sorted(page) == sorted(expected)
        for key, want in expected.items():
            assert page[key].dtype == np.uint8
            np.testing.assert_allclose(page[key].astype(int), want.astype(int), atol=1, err_msg=key)


def test_evidence_passes_take_as_many_maps_a_pass_as_fit_the_budget():
    """The evidence's maps in order, in as few passes over the views as keep what each pass holds
    (12 bytes a texel and 20 a texel a channel) within the budget; a map alone over it gets a pass."""
    from jaxdistill.export.outputs import EVIDENCE_PASS_BYTES, evidence_passes

    maps = ("albedo", "normal", "roughness", "metallic", "irradiance")       # 3, 3, 1, 1, 3 channels
    assert EVIDENCE_PASS_BYTES == 1 << 29
    assert evidence_passes(maps, 4_097_280) == [("albedo",), ("normal", "roughness", "metallic"), ("irradiance",)]
    assert evidence_passes(maps, 60_000_000) == [(m,) for m in maps]       # a capture's texels: a map a pass
    assert evidence_passes(maps, 1_000_000) == [maps]                        # 0.22 GiB
    n = 1000
    assert evidence_passes(maps, n, budget=n * (12 + 20 * 7)) == [("albedo", "normal", "roughness"),
                                                                 ("metallic", "irradiance")]
    assert evidence_passes(maps, n, budget=n * (12 + 20 * 7) - 1) == [("albedo", "normal"),
                                                                     ("roughness", "metallic", "irradiance")]
    assert evidence_passes(("albedo",), n, budget=1) == [("albedo",)]


def test_every_maps_disagreement_pages_are_its_views_spread_by_a_numpy_reference(tmp_path, monkeypatch):
    """evidence/disagreement_<map> of all five maps, their statistics taken two maps, one map and two maps a pass,
    against a reference in float64 NumPy: each view's estimate (resized to the render size, normals
    into world space) spread onto the texels its taps read (Σ w·value / Σ w), then per texel the RMS
    deviation of the views' values from their mean over the channels, NaN where fewer than two views read it."""
    from tiny_scene import write_tiny_scene
    from jaxdistill.engine import config as config_lib
    from jaxdistill.engine.config import DistillConfig
    from jaxdistill.engine.problem import build_problem
    from jaxdistill.evaluate import scoring
    from jaxdistill.export import outputs
    from jaxdistill.io.view_images import resize
    from jaxdistill.render.sampler import expand
    from jaxdistill.scene.cameras import rgbx_camera_rotation

    maps = ("albedo", "normal", "roughness", "metallic", "irradiance")
    scene = write_tiny_scene(tmp_path / "scene", views=12)               # neighbouring views overlap
    config = config_lib.validate(DistillConfig(scene=str(scene), out_dir=str(tmp_path / "out"), maps=maps,
                                               prior="views", sampler="bilinear", render_size=16))
    problem = build_problem(config, cache_dir=tmp_path / "cache")
    ctx = scoring.evaluation_context(config, problem)
    baseline = scoring.per_view_baseline(config, problem, ctx.shapes).views
    space = problem.space
    assert space.pyramid_size == space.num_texels                     # bilinear: the taps index the texels
    passes = [("albedo", "normal"), ("roughness",), ("metallic", "irradiance")]
    monkeypatch.setattr(outputs, "evidence_passes", lambda names, num_texels: passes)
    written = outputs.write_evidence(tmp_path / "out", problem, ctx, baseline)
    stems = page_files.page_names(problem.scene.mesh.object_names, space.layout.object_page)
    n = space.num_texels
    index = np.asarray(problem.plan_index).reshape(problem.num_views, -1)
    weight = np.asarray(problem.plan_weight, np.float64).reshape(problem.num_views, -1)
    hit = np.asarray(problem.plan_hit).reshape(problem.num_views, -1)
    taps = np.asarray(problem.plan_index).shape[-1]
    checked = 0
    for m in maps:
        values, seen = [], []
        for v, camera in enumerate(ctx.cameras):
            image = resize(baseline[v][m], problem.height, problem.width).astype(np.float64)
            if m == "normal":
                image = image @ rgbx_camera_rotation(camera.c2w).T
            pixels = np.repeat(np.where(hit[v][:, None], image.reshape(-1, image.shape[-1]), 0.0), taps, axis=0)
            w = np.where(np.repeat(hit[v], taps), weight[v], 0.0)
            num, den = np.zeros((n, pixels.shape[1])), np.zeros(n)
            np.add.at(num, index[v], w[:, None] * pixels)
            np.add.at(den, index[v], w)
            values.append(num / np.maximum(den, 1e-300)[:, None])
            seen.append(den > 0)
        values, seen = np.stack(values), np.stack(seen)
        count = seen.sum(axis=0)
        mean = (values * seen[..., None]).sum(axis=0) / np.maximum(count, 1)[:, None]
        variance = (((values - mean) ** 2) * seen[..., None]).sum(axis=0) / np.maximum(count, 1)[:, None]
        spread = np.where(count >= 2, np.sqrt(variance.sum(axis=1)), np.nan)
        assert (count >= 2).sum() > 0.05 * n and np.nanmax(spread) > 1e-3
        for p, page in enumerate(expand(spread[:, None].astype(np.float32), space, np.nan, dilation=0)):
            got = imageio.read_image(tmp_path / "out" / "evidence" / f"disagreement_{m}" / f"{stems[p]}.exr")[..., 0]
            assert (tmp_path / "out" / "evidence" / f"disagreement_{m}" / f"{stems[p]}.exr") in written
            np.testing.assert_array_equal(np.isnan(got), np.isnan(page[..., 0]), err_msg=f"{m} page {p}")
            scale = max(float(np.nanmax(spread)), 1e-6)
            np.testing.assert_allclose(np.nan_to_num(got), np.nan_to_num(page[..., 0]), rtol=0, atol=2e-5 * scale,
                                       err_msg=f"{m} page {p}")
            checked += 1
    assert checked == 5 * len(stems)
