"""Training data of our RGB<->X-family prior: the irradiance integrator against analytic
irradiance, the procedural rooms' geometry, and the data job (scripts/make_rgbx_data.py's
`room_render.main`) end to end (tiny)."""

from __future__ import annotations

import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from jaxdistill.datasets.mitsuba import bridge as mb  # noqa: E402
from jaxdistill.models.training import procedural_rooms, room_render, shards  # noqa: E402
from jaxdistill.scene import cameras  # noqa: E402


def plane_scene(albedo, sky, sun, sun_direction):
    mb.load_mitsuba()
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(50),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": sky}},
        "sun": {"type": "directional", "direction": sun_direction, "irradiance": {"type": "rgb", "value": sun}},
    })


def test_intrinsic_integrator_gives_analytic_irradiance_and_photo_equals_albedo_times_it():
    """A Lambertian plane under a constant sky and a tilted sun: E / pi = sky + sun cos / pi
    (the plane sees exactly half the sky sphere), and the photo is albedo * E / pi."""
    sky, sun, albedo = np.array([0.3, 0.4, 0.5]), np.array([3.0, 2.5, 2.0]), np.array([0.6, 0.5, 0.2])
    direction = np.array([0.0, -0.8, 0.6])                       # cos to the plane's normal = 0.8
    scene = plane_scene(albedo.tolist(), sky.tolist(), sun.tolist(), direction.tolist())
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    cam = cameras.look_at([0, 3, 3], [0, 0, 0], [0, 1, 0], K, 16, 12)
    image = mb.render(scene, cam, spp=32, seed=1, integrator=mb.intrinsic_integrator())
    irradiance = image[..., mb.IRRADIANCE_CHANNELS].reshape(-1, 3).mean(0)
    expected = sky + sun * 0.8 / math.pi
    np.testing.assert_allclose(irradiance, expected, rtol=0.03)
    np.testing.assert_allclose(image[..., :3].reshape(-1, 3).mean(0), albedo * expected, rtol=0.03)


def interior_point_faces_inward(rects, centre):
    """For each rect, whether its normal points towards `centre`."""
    out = []
    for r in rects:
        n = np.cross(r.edge_u, r.edge_v)
        mid = r.origin + 0.5 * (r.edge_u + r.edge_v)
        out.append(np.dot(n, centre - mid) > 0)
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 3, 11])
def test_rooms_are_deterministic_closed_inward_boxes_with_light(seed):
    room = procedural_rooms.random_room(seed)
    again = procedural_rooms.random_room(seed)
    assert [o[0] for o in room.objects] == [o[0] for o in again.objects]
    assert np.array_equal(room.size, again.size)
    centre = room.size / 2
    for name, rects, _ in room.objects:
        if name in ("floor", "ceiling") or name.startswith("wall_"):
            assert interior_point_faces_inward(rects, centre).all(), name
    lights = [m for _, _, m in room.objects if m.emission] + ([room.sun_irradiance] if room.sun_irradiance else [])
    assert lights or room.sky_radiance is not None
    vertices = np.concatenate([np.concatenate([r.origin[None], (r.origin + r.edge_u + r.edge_v)[None]]) for _, rects, _ in room.objects for r in rects])
    window_reveal = 0.15 + 1e-9                                   # window reveals reach out through the wall
    assert (vertices >= -window_reveal).all() and (vertices <= room.size + window_reveal).all()


def test_furniture_footprints_do_not_overlap():
    rng = np.random.default_rng(5)
    for _ in range(20):
        size = np.array([rng.uniform(3, 6.5), 2.6, rng.uniform(3, 6.5)])
        placed = procedural_rooms.place_furniture(rng, size, 8)
        for i, a in enumerate(placed):
            assert 0 <= a[1] and a[1] + a[3] <= size[0] and 0 <= a[2] and a[2] + a[4] <= size[2]
            for b in placed[:i]:
                overlap_x = a[1] < b[1] + b[3] and b[1] < a[1] + a[3]
                overlap_z = a[2] < b[2] + b[4] and b[2] < a[2] + a[4]
                assert not (overlap_x and overlap_z)


def test_make_rgbx_data_writes_resumable_deterministic_shards(tmp_path, capsys):
    args = ["--out", str(tmp_path), "--rooms=1", "--views=2", "--width=32", "--height=24", "--spp=2", "--variant=scalar_rgb"]
    assert room_render.main(args) == 0
    shard = tmp_path / "room_0000000.npz"
    arrays, meta = shards.read_shard(shard)
    assert meta["seed"] == 0 and len(meta["cameras"]) == 2
    channels = {"photo": 3, "albedo": 3, "normal": 3, "roughness": 1, "metallic": 1, "irradiance": 3, "valid": 1}
    for name, c in channels.items():
        assert arrays[name].shape == (2, 24, 32, c) and arrays[name].dtype == np.uint8, name
    valid = arrays["valid"][..., 0] > 0
    assert valid.mean() > 0.5
    normal = arrays["normal"][valid].astype(np.float64) / 255 * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=0.02)   # 8-bit quantisation
    # surfaces face the camera: in RGB<->X camera space (x right, y up, z towards the camera)
    # the direction to the camera of pixel (u, v) is (-x, y, 1) with (x, y, 1) = K^-1 (u, v, 1)
    # (OpenCV); open objects (a lamp shade seen from below) may show a few back faces
    facing = []
    for view, cam in enumerate(meta["cameras"]):
        u, v = np.meshgrid(np.arange(32) + 0.5, np.arange(24) + 0.5)
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(np.array(cam["K"])).T
        to_camera = rays * [-1, 1, 1]
        n = arrays["normal"][view].astype(np.float64) / 255 * 2 - 1
        facing.append((np.sum(n * to_camera, -1) > 0)[valid[view]])
    assert np.mean(np.concatenate(facing)) > 0.97

    first = shard.read_bytes()
    capsys.readouterr()
    assert room_render.main(args) == 0                          # resumes: nothing to do
    assert "1 already written" in capsys.readouterr().out
    assert shard.read_bytes() == first
    shard.unlink()
    assert room_render.main(args) == 0                          # regenerated identically
    again, _ = shards.read_shard(shard)
    for name in ("albedo", "normal", "roughness", "metallic", "valid"):
        assert np.array_equal(arrays[name], again[name]), name


def test_firefly_filter_removes_isolated_outliers_only():
    image = np.full((9, 9, 3), 0.2, np.float32)
    image[4, 4] = 5.0                                             # an isolated outlier
    image[:, 7:] = 3.0                                            # a bright 2-pixel-wide stripe
    out = room_render.remove_fireflies(image)
    np.testing.assert_allclose(out[4, 4], 0.2)
    np.testing.assert_array_equal(out[:, 7:], image[:, 7:])
    np.testing.assert_array_equal(np.delete(out.reshape(-1, 3), 4 * 9 + 4, 0), np.delete(image.reshape(-1, 3), 4 * 9 + 4, 0))
