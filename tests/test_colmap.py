"""Tests for jaxdistill.datasets.colmap: a tiny COLMAP text model written from known cameras."""

import math

import numpy as np
import pytest

from jaxdistill.datasets.colmap import read_cameras_txt, read_colmap_model, read_images_txt
from jaxdistill.datasets.undistort import distort_normalized
from jaxdistill.errors import InputError
from dataset_fixtures import rotation_to_quaternion

# Known cameras: id -> (model, width, height, params).
PINHOLE = (1, "PINHOLE", 64, 48, [50.0, 52.5, 31.7, 24.2])
RADIAL = (2, "SIMPLE_RADIAL", 80, 60, [70.0, 40.5, 29.5, -0.08])
POINT = np.array([0.3, -0.2, 0.4])  # a world point all the images see


def _rodrigues(axis, angle):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _look_at_c2w_rotation(eye, target):
    """Columns: camera x (right), y (down), z (forward) in world coordinates; world up is +z."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(fwd, right), fwd], axis=1)


# Known images: (image_id, camera, eye, c2w rotation, name, points line).
IMAGES = [
    (7, PINHOLE, np.array([2.0, -1.5, 1.2]), None, "b.jpg", "10.5 20.25 -1 30.0 12.0 5"),
    (3, RADIAL, np.array([-1.8, -0.4, 0.9]), None, "a.jpg", ""),  # no 2D points: EMPTY line
    # a camera rolled upside down (trace < 0: the non-trivial branch of the quaternion formula)
    (12, RADIAL, np.array([0.4, 2.5, -0.3]), "roll", "sub dir/c 1.png", "1 2 3"),
]


def _pose(eye, rot):
    R_c2w = _look_at_c2w_rotation(eye, POINT + [0.05, 0.02, -0.03])
    if rot == "roll":
        R_c2w = R_c2w @ _rodrigues([0.1, 0.05, 1.0], 2.9)  # roll ~166 deg about the optical axis
    R = R_c2w.T  # world-to-camera
    return R, -R @ eye


def _hand_colmap_projection(R, t, camera, X):
    """COLMAP's projection written out: x_cam = R X + t, divide by z, distort, apply K."""
    _, model, _, _, p = camera
    xc = R @ X + t
    u, v = xc[0] / xc[2], xc[1] / xc[2]
    if model == "PINHOLE":
        fx, fy, cx, cy = p
        return np.array([fx * u + cx, fy * v + cy])
    f, cx, cy, k = p
    r2 = u * u + v * v
    return np.array([f * u * (1 + k * r2) + cx, f * v * (1 + k * r2) + cy])


def _known_intrinsics(camera):
    """(fx, fy, cx, cy) of a known camera."""
    _, model, _, _, p = camera
    return tuple(p) if model == "PINHOLE" else (p[0], p[0], p[1], p[2])


def _camera_line(camera):
    cid, model, w, h, params = camera
    return f"{cid} {model} {w} {h} " + " ".join(repr(p) for p in params)


def _image_lines(image, scale=1.0):
    iid, camera, eye, rot, name, points = image
    R, t = _pose(eye, rot)
    q = scale * rotation_to_quaternion(R)
    return [f"{iid} " + " ".join(repr(float(v)) for v in [*q, *t]) + f" {camera[0]} {name}", points]


def _write(folder, cameras=None, images=None, newline="\n"):
    folder.mkdir(parents=True, exist_ok=True)
    if cameras is None:
        cameras = ["# Camera list with one line of data per camera:",
                   "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                   "# Number of cameras: 2", _camera_line(PINHOLE), _camera_line(RADIAL)]
    if images is None:
        images = ["# Image list with two lines of data per image:",
                  "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                  "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                  "# Number of images: 3, mean observations per image: 1.5"]
        for image, scale in zip(IMAGES, (1.0, -1.0, 2.5)):  # q, -q and 2.5 q: the same rotation
            images += _image_lines(image, scale)
    (folder / "cameras.txt").write_text(newline.join(cameras) + newline, encoding="utf-8")
    (folder / "images.txt").write_text(newline.join(images) + newline, encoding="utf-8")
    return folder


# ----------------------------------------------------------------------------- reading


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_model_reprojects_like_colmap(tmp_path, newline):
    images = read_colmap_model(_write(tmp_path / "model", newline=newline))
    assert [im.name for im in images] == ["a.jpg", "b.jpg", "sub dir/c 1.png"]  # sorted by name
    by_id = {im.image_id: im for im in images}
    assert sorted(by_id) == [3, 7, 12]
    for iid, camera, eye, rot, name, _ in IMAGES:
        im = by_id[iid]
        assert im.name == name and im.camera_id == camera[0]
        assert (im.camera.width, im.camera.height) == (camera[2], camera[3])
        np.testing.assert_allclose(im.camera.center, eye, atol=1e-12)
        R, t = _pose(eye, rot)
        pixel, depth = im.camera.project(POINT[None])
        assert depth[0] > 0
        # the pinhole part: our camera projects like COLMAP without distortion
        xc = R @ POINT + t
        fx, fy, cx, cy = _known_intrinsics(camera)
        np.testing.assert_allclose(pixel[0], [fx * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy], atol=1e-9)
        # with the distortion: the same pixel as COLMAP's full projection
        c, f = np.array([cx, cy]), np.array([fx, fy])
        distorted = distort_normalized(((pixel - c) / f), im.distortion) * f + c
        np.testing.assert_allclose(distorted[0], _hand_colmap_projection(R, t, camera, POINT), atol=1e-9)
        assert 0 < distorted[0, 0] < camera[2] and 0 < distorted[0, 1] < camera[3]


def test_intrinsics_and_distortion(tmp_path):
    images = {im.image_id: im for im in read_colmap_model(_write(tmp_path))}
    np.testing.assert_array_equal(images[7].camera.K, [[50.0, 0, 31.7], [0, 52.5, 24.2], [0, 0, 1]])
    assert images[7].distortion.is_identity()
    np.testing.assert_array_equal(images[3].camera.K, [[70.0, 0, 40.5], [0, 70.0, 29.5], [0, 0, 1]])
    d = images[3].distortion
    assert (d.model, d.k1, d.k2, d.p1, d.p2) == ("radial", -0.08, 0.0, 0.0, 0.0)


def test_other_supported_models(tmp_path):
    cams = ["1 SIMPLE_PINHOLE 40 30 35 20 15", "2 RADIAL 40 30 35 20 15 0.01 -0.002",
            "3 OPENCV 40 30 35 36 20 15 0.01 -0.002 0.0003 -0.0004"]
    imgs = [line for i in (1, 2, 3) for line in (f"{i} 1 0 0 0 0 0 0 {i} im{i}.png", "")]
    images = read_colmap_model(_write(tmp_path, cams, imgs))
    got = {im.camera_id: (im.camera.K[0, 0], im.camera.K[1, 1], im.distortion) for im in images}
    assert got[1][:2] == (35, 35) and got[1][2].is_identity()
    assert got[2][:2] == (35, 35) and (got[2][2].model, got[2][2].k1, got[2][2].k2) == ("radial", 0.01, -0.002)
    d = got[3][2]
    assert got[3][:2] == (35, 36) and (d.model, d.k1, d.k2, d.p1, d.p2) == ("opencv", 0.01, -0.002, 0.0003, -0.0004)
    np.testing.assert_array_equal(images[0].camera.c2w, np.eye(4))


def test_low_level_readers(tmp_path):
    folder = _write(tmp_path)
    cams = read_cameras_txt(folder / "cameras.txt")
    assert sorted(cams) == [1, 2]
    model, w, h, params = cams[2]
    assert (model, w, h) == ("SIMPLE_RADIAL", 80, 60) and params.tolist() == [70.0, 40.5, 29.5, -0.08]
    recs = read_images_txt(folder / "images.txt")
    assert [(r[0], r[3], r[4]) for r in recs] == [(7, 1, "b.jpg"), (3, 2, "a.jpg"), (12, 2, "sub dir/c 1.png")]
    for rec in recs:
        assert np.linalg.norm(rec[1]) == pytest.approx(1.0)
    assert recs[1][1] == pytest.approx(-rotation_to_quaternion(_pose(IMAGES[1][2], None)[0]))


def test_points_line_only_empty_at_end_of_file(tmp_path):
    lines = _image_lines(IMAGES[0]) + _image_lines(IMAGES[1])[:1]  # last image without its points line
    images = read_colmap_model(_write(tmp_path, images=lines))
    assert [im.image_id for im in images] == [3, 7]


# ----------------------------------------------------------------------------- errors


def _error(folder) -> str:
    with pytest.raises(InputError) as info:
        read_colmap_model(folder)
    return str(info.value)


def test_unsupported_model(tmp_path):
    cams = [_camera_line(PINHOLE), "2 OPENCV_FISHEYE 80 60 70 70 40 30 0.1 0.01 0.0 0.0"]
    msg = _error(_write(tmp_path, cams))
    assert "cameras.txt: camera 2 model (line 2): camera model OPENCV_FISHEYE is not supported" in msg
    assert "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV" in msg and "colmap image_undistorter" in msg
    # an unsupported camera no image uses is harmless
    only_pinhole = _image_lines(IMAGES[0])
    assert len(read_colmap_model(_write(tmp_path / "b", cams, only_pinhole))) == 1


def test_unknown_camera_id(tmp_path):
    msg = _error(_write(tmp_path, cameras=[_camera_line(PINHOLE)]))
    assert "images.txt: line 7 (image 3 CAMERA_ID): camera 2 is not in cameras.txt (camera ids there: 1)" in msg
    assert "line 9 (image 12 CAMERA_ID)" in msg  # every problem is listed


def test_missing_files(tmp_path):
    (tmp_path / "m").mkdir()
    msg = _error(tmp_path / "m")
    assert "cameras.txt: (file): not found" in msg
    (tmp_path / "m" / "cameras.bin").write_bytes(b"\0")
    assert "colmap model_converter" in _error(tmp_path / "m")
    (tmp_path / "m" / "cameras.txt").write_text(_camera_line(PINHOLE) + "\n")
    assert "images.txt: (file): not found" in _error(tmp_path / "m")
    assert "(folder): COLMAP model folder not found" in _error(tmp_path / "nowhere")


@pytest.mark.parametrize("line, expected", [
    ("2 SIMPLE_RADIAL 80 60 70 40.5 29.5", "camera 2 params (line 2): model SIMPLE_RADIAL takes 4 parameters (f, cx, cy, k), got 3"),
    ("2 OPENCV_FISHEYE 80 60 70 40.5 29.5", "camera 2 params (line 2): model OPENCV_FISHEYE takes 8 parameters, got 3"),
    ("2 SIMPLE_RADIAL 80 60 70 40.5 abc -0.08", "camera 2 params (line 2): parameter 3 must be a number, got 'abc'"),
    ("2 SIMPLE_RADIAL 80 60 70 40.5 nan -0.08", "camera 2 params (line 2): parameter 3 must be finite, got 'nan'"),
    ("2 SIMPLE_RADIAL 80.5 60 70 40.5 29.5 -0.08", "line 2 (camera 2): WIDTH must be an integer, got '80.5'"),
    ("2 SIMPLE_RADIAL 80 0 70 40.5 29.5 -0.08", "line 2 (camera 2): HEIGHT must be > 0, got 0"),
    ("x SIMPLE_RADIAL 80 60 70 40.5 29.5 -0.08", "line 2: CAMERA_ID must be an integer, got 'x'"),
    ("2 SIMPLE_RADIAL 80", "line 2: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got 3 value(s)"),
    ("1 SIMPLE_RADIAL 80 60 70 40.5 29.5 -0.08", "line 2 (camera 1): duplicate CAMERA_ID 1 (first on line 1)"),
    ("2 2 80 60 70 40.5 29.5 -0.08", "camera 2 model (line 2): numeric model id 2"),
    ("2 SIMPLE_RADIAL 80 60 -70 40.5 29.5 -0.08", "camera 2 params (line 2): focal length must be > 0, got f = -70"),
])
def test_bad_cameras_txt(tmp_path, line, expected):
    msg = _error(_write(tmp_path, cameras=[_camera_line(PINHOLE), line]))
    assert "cameras.txt: " + expected in msg


def _images_with(pose_line, points=""):
    return _image_lines(IMAGES[0]) + [pose_line, points]


@pytest.mark.parametrize("pose_line, points, expected", [
    ("5 1 0 0 0 0 0 0 1", "", "line 3: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 values), got 9"),
    ("5 1 0 zero 0 0 0 0 1 x.png", "", "line 3: QY must be a number, got 'zero'"),
    ("5 1 0 0 0 0 inf 0 1 x.png", "", "line 3: TY must be finite"),
    ("5.5 1 0 0 0 0 0 0 1.0 x.png", "", "line 3: IMAGE_ID must be an integer, got '5.5'; CAMERA_ID must be an integer, got '1.0'"),
    ("7 1 0 0 0 0 0 0 1 x.png", "", "line 3: duplicate IMAGE_ID 7 (first on line 1)"),
    ("5 1 0 0 0 0 0 0 1 b.jpg", "", "line 3: duplicate image NAME 'b.jpg' (first on line 1)"),
    ("5 0 0 0 0 0 0 0 1 x.png", "", "line 3: quaternion QW QX QY QZ is zero"),
    ("5 1 0 0 0 0 0 0 1 x.png", "1 2", "line 4: expected the 2D points line"),
])
def test_bad_images_txt(tmp_path, pose_line, points, expected):
    msg = _error(_write(tmp_path, images=_images_with(pose_line, points)))
    assert "images.txt: " + expected in msg


def test_points_lines_removed(tmp_path):
    pose_lines = [_image_lines(im)[0] for im in IMAGES]  # someone deleted the 2D points lines
    msg = _error(_write(tmp_path, images=pose_lines))
    assert "images.txt: line 2: expected the 2D points line" in msg and "were the points lines removed?" in msg


def test_no_images(tmp_path):
    msg = _error(_write(tmp_path, images=["# Number of images: 0", ""]))
    assert "images.txt: (file): contains no images" in msg
