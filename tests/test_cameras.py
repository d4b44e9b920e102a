"""Tests for jaxdistill.scene.cameras: one physical camera described in every convention."""

import dataclasses
import math

import numpy as np
import pytest

from jaxdistill.scene import cameras as cams

# The physical camera: 384x288, non-square pixels, off-centre principal point, general rotation.
W, H = 384, 288
FX, FY, CX, CY = 301.5, 312.25, 201.3, 131.7
POS = np.array([1.7, 1.4, -2.3])  # somewhere inside a room


def _rotation(axis, angle):
    """Rodrigues rotation matrix, written out in the test."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


# World directions of the physical camera axes (right x down = forward, right-handed).
RIGHT, DOWN, FWD = _rotation([0.3, -0.8, 0.5], 2.1).T
LEFT, UP, BACK = -RIGHT, -DOWN, -FWD

# Known 3D points, given by their normalised image coordinates (a, b) and depth z.
ABZ = np.array([(0.0, 0.0, 2.0), (0.31, -0.22, 1.5), (-0.6, 0.45, 3.7), (0.55, 0.4, 0.8),
                (-0.2, -0.4, 5.0), (0.9, -0.7, 2.2)])  # the last one lies outside the image
POINTS = POS + ABZ[:, 2:] * (ABZ[:, :1] * RIGHT + ABZ[:, 1:2] * DOWN + FWD)


def _truth(fx, fy, cx, cy):
    """Ground-truth pixels of POINTS for intrinsics (fx, fy, cx, cy) of the physical camera."""
    return np.stack([fx * ABZ[:, 0] + cx, fy * ABZ[:, 1] + cy], axis=-1)


def _columns(*cols):
    """4x4 matrix whose first three columns are `cols[:3]` and translation `cols[3]`."""
    m = np.eye(4)
    for i, c in enumerate(cols):
        m[:3, i] = c
    return m


def _project_gl(c2w_gl, fx, fy, cx, cy, pts):
    """OpenGL-style projection: camera y up, looks along -z, image rows grow downwards."""
    p = (np.linalg.inv(c2w_gl) @ np.c_[pts, np.ones(len(pts))].T).T
    return np.stack([cx + fx * p[:, 0] / -p[:, 2], cy - fy * p[:, 1] / -p[:, 2]], axis=-1)


def _project_mitsuba(to_world, fov_x_deg, ox, oy, w, h, pts):
    """Mitsuba film coordinates (x left, y up camera; offsets shift the film sample) -> pixels."""
    p = (np.linalg.inv(to_world) @ np.c_[pts, np.ones(len(pts))].T).T
    tan_x = math.tan(math.radians(fov_x_deg) / 2)
    tan_y = tan_x * h / w
    u = 0.5 - ox - p[:, 0] / p[:, 2] / (2 * tan_x)
    v = 0.5 - oy - p[:, 1] / p[:, 2] / (2 * tan_y)
    return np.stack([u * w, v * h], axis=-1)


def _pytorch3d_ndc():
    """Focal length and principal point of the physical camera in PyTorch3D NDC (+x left, +y up)."""
    s = min(W, H) / 2
    return np.array([FX / s, FY / s]), np.array([(W / 2 - CX) / s, (H / 2 - CY) / s])


def _project_pytorch3d(R, T, f_ndc, p_ndc, pts):
    """PyTorch3D: row vectors X_cam = X R + T; NDC = f X/Z + p; screen = (W, H)/2 - s NDC."""
    xc = pts @ R + T
    ndc = f_ndc * xc[:, :2] / xc[:, 2:] + p_ndc
    s = min(W, H) / 2
    return np.stack([W / 2 - s * ndc[:, 0], H / 2 - s * ndc[:, 1]], axis=-1)


K_PHYS = np.array([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]])
C2W_GL = _columns(RIGHT, UP, BACK, POS)


def _opencv():
    cam = cams.from_opencv(K_PHYS, c2w=_columns(RIGHT, DOWN, FWD, POS), width=W, height=H)
    own = (K_PHYS @ (np.stack([RIGHT, DOWN, FWD]) @ (POINTS - POS).T)).T
    return cam, own[:, :2] / own[:, 2:], _truth(FX, FY, CX, CY)


def _opencv_rt():
    R = np.stack([RIGHT, DOWN, FWD])  # rows: world -> camera
    t = -R @ POS
    own = (K_PHYS @ (POINTS @ R.T + t).T).T
    return cams.from_opencv_rt(R, t, K_PHYS, W, H), own[:, :2] / own[:, 2:], _truth(FX, FY, CX, CY)


def _opengl():
    cam = cams.from_opengl(C2W_GL, K_PHYS, W, H)
    return cam, _project_gl(C2W_GL, FX, FY, CX, CY, POINTS), _truth(FX, FY, CX, CY)


def _nerf_pixels():
    meta = {"fl_x": FX, "fl_y": FY, "cx": CX, "cy": CY, "w": W, "h": H}
    cam = cams.from_nerf_frame(meta, {"transform_matrix": C2W_GL.tolist()})
    return cam, _project_gl(C2W_GL, FX, FY, CX, CY, POINTS), _truth(FX, FY, CX, CY)


def _nerf_angles():  # camera_angle_x/y imply a centred principal point
    meta = {"camera_angle_x": 2 * math.atan(W / 2 / FX),
            "camera_angle_y": 2 * math.atan(H / 2 / FY)}
    cam = cams.from_nerf_frame(meta, {"transform_matrix": C2W_GL}, width=W, height=H)
    return cam, _project_gl(C2W_GL, FX, FY, W / 2, H / 2, POINTS), _truth(FX, FY, W / 2, H / 2)


def _look_at():
    cam = cams.look_at(POS, POS + 2.5 * FWD, UP + 0.7 * FWD, K_PHYS, W, H)
    return cam, _opencv()[1], _truth(FX, FY, CX, CY)


def _pytorch3d():
    R = np.stack([LEFT, UP, FWD], axis=1)  # X_world @ R = (left, up, forward) components
    T = -POS @ R
    f_ndc, p_ndc = _pytorch3d_ndc()
    cam = cams.from_pytorch3d(R, T, f_ndc, p_ndc, W, H)
    return cam, _project_pytorch3d(R, T, f_ndc, p_ndc, POINTS), _truth(FX, FY, CX, CY)


def _mitsuba():  # Mitsuba has square pixels: the same camera with fy = fx
    to_world = _columns(LEFT, UP, FWD, POS)
    fov = math.degrees(2 * math.atan(W / 2 / FX))
    ox, oy = 0.5 - CX / W, 0.5 - CY / H
    cam = cams.from_mitsuba(to_world, fov, W, H, "x", ox, oy)
    return cam, _project_mitsuba(to_world, fov, ox, oy, W, H, POINTS), _truth(FX, FX, CX, CY)


def _scannetpp_matrix(c2w_cv):
    """ScanNet++'s transform_matrix of an OpenCV c2w (their convert_frames, written out here):
    negate camera columns y and z, swap world rows 0 and 1, negate world row 2."""
    m = np.array(c2w_cv, float)
    m[0:3, 1:3] *= -1
    m = m[[1, 0, 2, 3], :]
    m[2, :] *= -1
    return m


C2W_SPP = _scannetpp_matrix(_columns(RIGHT, DOWN, FWD, POS))


def _scannetpp():  # ScanNet++'s own world has x and y swapped and z negated: (y, x, -z) of ours
    cam = cams.from_scannetpp(C2W_SPP, FX, FY, CX, CY, W, H)
    in_their_world = POINTS[:, [1, 0, 2]] * [1.0, 1.0, -1.0]
    return cam, _project_gl(C2W_SPP, FX, FY, CX, CY, in_their_world), _truth(FX, FY, CX, CY)


CONVENTIONS = [_opencv, _opencv_rt, _opengl, _nerf_pixels, _nerf_angles, _look_at, _pytorch3d,
               _mitsuba, _scannetpp]


@pytest.mark.parametrize("describe", CONVENTIONS, ids=lambda f: f.__name__.strip("_"))
def test_every_convention_projects_like_the_physical_camera(describe):
    cam, own_formula, truth = describe()
    np.testing.assert_allclose(own_formula, truth, atol=1e-6)  # the description itself is right
    pixels, depth = cam.project(POINTS)
    np.testing.assert_allclose(pixels, truth, atol=1e-4)
    np.testing.assert_allclose(depth, ABZ[:, 2], atol=1e-9)
    assert cam.width == W and cam.height == H
    assert cams.pose_problems(cam.c2w) == [] and cams.intrinsics_problems(cam.K) == []


def test_pytorch3d_ndc_is_algorithm_2():
    f_norm, p_norm = cams.intrinsics_to_pytorch3d_ndc(K_PHYS, W, H)
    f_ndc, p_ndc = _pytorch3d_ndc()
    np.testing.assert_allclose(f_norm, f_ndc, rtol=1e-12)
    np.testing.assert_allclose(p_norm, p_ndc, rtol=1e-12)
    K = cams.from_pytorch3d(np.eye(3), np.zeros(3), 1.5, [0.0, 0.0], W, H).K  # scalar focal
    np.testing.assert_allclose(K, [[216, 0, W / 2], [0, 216, H / 2], [0, 0, 1]], rtol=1e-12)


def test_camera_basics_and_pixel_rays():
    cam = _opencv()[0]
    np.testing.assert_allclose(cam.w2c @ cam.c2w, np.eye(4), atol=1e-12)
    pixels, depth = cam.project(POINTS)
    origins, dirs = cam.pixel_rays(pixels)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0, atol=1e-12)
    dist = np.linalg.norm(POINTS - origins, axis=-1)
    np.testing.assert_allclose(origins + dist[:, None] * dirs, POINTS, atol=1e-9)
    np.testing.assert_allclose(dirs @ FWD * dist, depth, atol=1e-9)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cam.width = 3
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0


def test_pixel_rays_none_is_every_pixel_centre_row_major():
    cam = cams.from_opencv(np.array([[4.0, 0, 2.2], [0, 5.0, 1.4], [0, 0, 1]]),
                           c2w=_columns(RIGHT, DOWN, FWD, POS), width=5, height=3)
    origins, dirs = cam.pixel_rays()
    assert origins.shape == dirs.shape == (15, 3)
    pixels, _ = cam.project(origins + 2.0 * dirs)
    j, i = np.divmod(np.arange(15), 5)
    np.testing.assert_allclose(pixels, np.stack([i + 0.5, j + 0.5], axis=-1), atol=1e-12)


def test_intrinsics_from_fov_axes():
    t = math.tan(math.radians(50) / 2)
    for axis, extent in [("x", 384), ("y", 288), ("diagonal", 480), ("smaller", 288),
                         ("larger", 384)]:
        K = cams.intrinsics_from_fov(50, 384, 288, axis)
        np.testing.assert_allclose(K, [[extent / 2 / t, 0, 192], [0, extent / 2 / t, 144],
                                       [0, 0, 1]], rtol=1e-12)
    assert cams.intrinsics_from_fov(50, 288, 384, "smaller")[0, 0] == pytest.approx(144 / t)


def test_nerf_frame_overrides_and_default_fy():
    meta = {"camera_angle_x": 1.1, "w": 320, "h": 240}
    cam = cams.from_nerf_frame(meta, {"transform_matrix": C2W_GL})
    fx = 160 / math.tan(0.55)
    np.testing.assert_allclose(cam.K, [[fx, 0, 160], [0, fx, 120], [0, 0, 1]], rtol=1e-12)
    meta = {"fl_x": 100.0, "fl_y": 110.0, "cx": 50.0, "cy": 40.0, "w": 100, "h": 80}
    frame = {"transform_matrix": C2W_GL, "fl_x": 120.0, "cx": 52.5}
    cam = cams.from_nerf_frame(meta, frame)
    np.testing.assert_allclose(cam.K, [[120, 0, 52.5], [0, 110, 40], [0, 0, 1]])
    np.testing.assert_allclose(cam.c2w, C2W_GL @ np.diag([1.0, -1, -1, 1]), atol=1e-12)


def test_scannetpp_reorthogonalises_a_slightly_non_orthogonal_pose():
    stretch = np.array([[1.0, 0.4, -0.2], [0.4, 0.5, 0.3], [-0.2, 0.3, -0.7]])  # symmetric
    noisy = C2W_SPP.copy()
    noisy[:3, :3] = C2W_SPP[:3, :3] @ (np.eye(3) + 2e-3 * stretch)  # nearest rotation: unchanged
    assert any("orthonormal" in p for p in cams.pose_problems(noisy))
    cam = cams.from_scannetpp(noisy, FX, FY, CX, CY, W, H)
    assert cams.pose_problems(cam.c2w) == []
    np.testing.assert_allclose(cam.project(POINTS)[0], _truth(FX, FY, CX, CY), atol=1e-4)
    np.testing.assert_allclose(cam.c2w, _columns(RIGHT, DOWN, FWD, POS), atol=1e-9)
    with pytest.raises(ValueError, match="transform_matrix.*re-orthogonalise"):
        cams.from_scannetpp(C2W_SPP @ np.diag([1.5, 1, 1, 1]), FX, FY, CX, CY, W, H)


def test_mitsuba_algorithm1_ignores_scale_of_to_world():
    base = _mitsuba()[0]
    scaled = _columns(2 * LEFT, 0.5 * UP, 3 * FWD, POS)
    cam = cams.from_mitsuba(scaled, math.degrees(2 * math.atan(W / 2 / FX)), W, H, "x",
                            0.5 - CX / W, 0.5 - CY / H)
    np.testing.assert_allclose(cam.c2w, base.c2w, atol=1e-12)


@pytest.mark.parametrize("message, call", [
    ("K: focal length fx must be > 0", lambda: cams.from_opencv(
        np.diag([-300.0, 300, 1]), c2w=np.eye(4), width=W, height=H)),
    ("K: .*fy must be > 0", lambda: cams.Camera(np.diag([300.0, 0, 1]), np.eye(4), W, H)),
    ("c2w_gl: rotation is not orthonormal", lambda: cams.from_opengl(
        np.diag([2.0, 2, 2, 1]), K_PHYS, W, H)),
    ("c2w: .*determinant", lambda: cams.from_opencv(
        K_PHYS, c2w=np.diag([-1.0, 1, 1, 1]), width=W, height=H)),
    ("c2w: contains non-finite", lambda: cams.from_opencv(
        K_PHYS, c2w=np.full((4, 4), np.nan), width=W, height=H)),
    ("K: contains non-finite", lambda: cams.from_opengl(np.eye(4), np.full((3, 3), np.inf), W, H)),
    ("eye: contains non-finite", lambda: cams.look_at(
        [np.nan, 0, 0], [0, 0, 1], [0, 1, 0], K_PHYS, W, H)),
    ("up .* parallel to the viewing direction", lambda: cams.look_at(
        [0, 0, 0], [0, 2, 0], [0, -1, 0], K_PHYS, W, H)),
    ("eye and target coincide", lambda: cams.look_at([1, 2, 3], [1, 2, 3], UP, K_PHYS, W, H)),
    ("to_world: .*parallel", lambda: cams.from_mitsuba(
        _columns(LEFT, FWD, FWD, POS), 60, W, H)),
    ("fov_deg: must be in", lambda: cams.intrinsics_from_fov(180, W, H)),
    ("axis: expected one of", lambda: cams.intrinsics_from_fov(60, W, H, "z")),
    ("width: expected a positive integer", lambda: cams.Camera(K_PHYS, np.eye(4), 0, H)),
    ("missing key 'transform_matrix'", lambda: cams.from_nerf_frame(
        {"camera_angle_x": 1.0, "w": W, "h": H}, {"file_path": "a.png"})),
    ("frame a.png: intrinsics missing.*camera_angle_x", lambda: cams.from_nerf_frame(
        {"w": W, "h": H}, {"file_path": "a.png", "transform_matrix": C2W_GL})),
    (r"\['cy'\] missing", lambda: cams.from_nerf_frame(
        {"fl_x": 1.0, "fl_y": 1.0, "cx": 1.0, "w": W, "h": H}, {"transform_matrix": C2W_GL})),
    ("key 'h' missing", lambda: cams.from_nerf_frame(
        {"camera_angle_x": 1.0, "w": W}, {"transform_matrix": C2W_GL})),
    ("width=100 differs from 'w'", lambda: cams.from_nerf_frame(
        {"fl_x": 1.0, "fl_y": 1.0, "cx": 1.0, "cy": 1.0, "w": W, "h": H},
        {"transform_matrix": C2W_GL}, width=100)),
    ("transform_matrix: .*last row", lambda: cams.from_nerf_frame(
        {"camera_angle_x": 1.0, "w": W, "h": H}, {"transform_matrix": np.ones((4, 4))})),
    ("focal_ndc: must be > 0", lambda: cams.from_pytorch3d(np.eye(3), np.zeros(3), [1.0, -1.0],
                                                           [0, 0], W, H)),
    ("R: rotation is not orthonormal", lambda: cams.from_opencv_rt(
        2 * np.eye(3), np.zeros(3), K_PHYS, W, H)),
    ("exactly one of c2w or w2c", lambda: cams.from_opencv(K_PHYS, width=W, height=H)),
])
def test_errors_name_the_offending_argument(message, call):
    with pytest.raises(ValueError, match=message):
        call()


def test_problem_lists():
    assert cams.pose_problems(C2W_GL) == [] and cams.intrinsics_problems(K_PHYS) == []
    bad = np.array([[0.0, 0.5, 1], [0, -1, 1], [0, 0, 2]])
    problems = cams.intrinsics_problems(bad)
    assert len(problems) == 4 and "fx" in problems[0] and "fy" in problems[1]
    assert "skew" in problems[2] and "last row" in problems[3]
    assert "last row" in cams.pose_problems(np.ones((4, 4)))[0]
    assert cams.pose_problems(np.eye(3)) == ["expected shape (4, 4), got (3, 3)"]


# ----------------------------------------------------------------------------- Mitsuba itself

MI_CASES = [  # (width, height, fov_axis, principal_point_offset_x, principal_point_offset_y)
    (384, 288, "x", 0.5 - CX / W, 0.5 - CY / H),
    (384, 288, "y", 0.12, -0.07),
    (288, 384, "smaller", -0.2, 0.15),
    (288, 384, "larger", 0.0, 0.3),
    (300, 200, "diagonal", 0.05, 0.05),
]


def _mitsuba_sensor(mi, to_world, fov, w, h, axis, ox, oy):
    return mi.load_dict({
        "type": "perspective", "fov": fov, "fov_axis": axis, "principal_point_offset_x": ox,
        "principal_point_offset_y": oy, "to_world": mi.ScalarTransform4f(to_world),
        "film": {"type": "hdrfilm", "width": w, "height": h}})


def _mitsuba_rays(mi, sensor, pixels, w, h):
    origins, dirs = [], []
    for px, py in pixels:
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.ScalarPoint2f(px / w, py / h),
                                   mi.ScalarPoint2f(0.5, 0.5))
        origins.append(np.array(ray.o, float))
        dirs.append(np.array(ray.d, float))
    return np.array(origins), np.array(dirs)


def _pixel_grid(w, h):
    return [(i + 0.5, j + 0.5) for i in (0, w // 3, w - 1) for j in (0, h // 2, h - 1)]


@pytest.mark.parametrize("w, h, axis, ox, oy", MI_CASES)
def test_matches_mitsuba_sensor_rays(w, h, axis, ox, oy):
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    to_world = np.array(mi.ScalarTransform4f().look_at(
        origin=POS.tolist(), target=(POS + FWD).tolist(), up=(UP + 0.3 * FWD).tolist()).matrix)
    sensor = _mitsuba_sensor(mi, to_world, 63.0, w, h, axis, ox, oy)
    cam = cams.from_mitsuba(to_world, 63.0, w, h, axis, ox, oy)
    pixels = _pixel_grid(w, h)
    mi_o, mi_d = _mitsuba_rays(mi, sensor, pixels, w, h)
    o, d = cam.pixel_rays(np.array(pixels))
    np.testing.assert_allclose(mi_d, d, atol=1e-5)
    along = np.sum((mi_o - o) * d, axis=-1)  # Mitsuba starts rays on the near plane
    np.testing.assert_allclose(mi_o, o + along[:, None] * d, atol=1e-5)


def test_mitsuba_mirrored_to_world_renders_the_flipped_image():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    mirrored = _columns(RIGHT, UP, FWD, POS)  # det = -1: Mitsuba renders a mirror image
    ox, oy = 0.1, -0.05
    sensor = _mitsuba_sensor(mi, mirrored, 50.0, W, H, "x", ox, oy)
    cam = cams.from_mitsuba(mirrored, 50.0, W, H, "x", -ox, oy)
    pixels = np.array(_pixel_grid(W, H))
    _, mi_d = _mitsuba_rays(mi, sensor, pixels, W, H)
    _, d = cam.pixel_rays(np.c_[W - pixels[:, 0], pixels[:, 1]])
    np.testing.assert_allclose(mi_d, d, atol=1e-5)
