"""Pinhole cameras in one canonical convention, and converters from the other conventions.

Canonical (OpenCV): camera x right, y down, z forward. `K` is (3, 3) float64 in pixels,
`[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`; `c2w` is a (4, 4) float64 rigid camera-to-world.
Pixel (col i, row j) has its centre at continuous image coordinates (i + 0.5, j + 0.5), so a
centred principal point is (W / 2, H / 2). Everything here is plain NumPy, float64.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

_RIGID_TOL = 1e-4  # max |R^T R - I| accepted for a rotation (which must also have det > 0)
_REORTH_TOL = 1e-2  # max |R^T R - I| that from_scannetpp still calls "slightly" non-orthogonal
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL camera (y up, -z fwd) <-> OpenCV; own inverse
_FLIP_XZ = np.diag([-1.0, 1.0, -1.0, 1.0])  # OpenGL camera -> PyTorch3D camera (thesis B.2)
_P3D_TO_CV = np.diag([-1.0, -1.0, 1.0, 1.0])  # PyTorch3D/Mitsuba camera (x left, y up) -> OpenCV
# ScanNet++'s nerfstudio world -> its mesh/COLMAP world: their writer swaps world rows x and y and
# negates z (common/utils/nerfstudio.py::convert_frames); a proper rotation and its own inverse
SCANNETPP_WORLD = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
_FOV_AXES = ("x", "y", "diagonal", "smaller", "larger")
_NERF_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h")


# ----------------------------------------------------------------------------- validation


def _numeric(x, shape: tuple[int, ...]) -> tuple[np.ndarray | None, list[str]]:
    """Returns (x as float64 array, []) or (None, [why]) if not finite numbers of `shape`."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        return None, [f"not a numeric array ({e})"]
    if a.shape != shape:
        return None, [f"expected shape {shape}, got {a.shape}"]
    if not np.all(np.isfinite(a)):
        return None, ["contains non-finite values (NaN or inf)"]
    return a, []


def _as_float(x, shape: tuple[int, ...], name: str) -> np.ndarray:
    """Returns `x` as a new finite float64 array of `shape`; ValueError naming `name` if not."""
    a, problems = _numeric(x, shape)
    _raise_if(problems, name)
    return np.array(a)


def _size(v, name: str) -> int:
    """Returns image size `v` as a positive int (integral floats accepted); ValueError if not."""
    number = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
    if not (number and math.isfinite(v) and v == int(v) and v > 0):
        raise ValueError(f"{name}: expected a positive integer, got {v!r}")
    return int(v)


def _raise_if(problems: list[str], name: str) -> None:
    """Raises one ValueError `name: problem; problem` if `problems` is non-empty."""
    if problems:
        raise ValueError(f"{name}: " + "; ".join(problems))


def _last_row_problems(m: np.ndarray) -> list[str]:
    """Returns [why] if the last row of a homogeneous (4, 4) transform is not [0, 0, 0, 1]."""
    ok = np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() <= 1e-9
    return [] if ok else [f"last row must be [0, 0, 0, 1], got {m[3].tolist()}"]


def rotation_problems(R) -> list[str]:
    """Returns what keeps `R` (3, 3) from being a proper rotation (empty list = OK)."""
    a, problems = _numeric(R, (3, 3))
    if a is None:
        return problems
    err = float(np.abs(a.T @ a - np.eye(3)).max())
    if err > _RIGID_TOL:
        problems.append(f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > "
                        f"{_RIGID_TOL:g}; scaled or sheared?)")
    det = float(np.linalg.det(a))  # orthonormal and det > 0 imply det = +1 within tolerance
    if det <= 0:
        problems.append(f"rotation has determinant {det:.6g} <= 0 (a mirror, not a rotation)")
    return problems


def pose_problems(c2w) -> list[str]:
    """Returns what keeps `c2w` (4, 4) from being a finite rigid transform (empty list = OK)."""
    a, problems = _numeric(c2w, (4, 4))
    return problems if a is None else _last_row_problems(a) + rotation_problems(a[:3, :3])


def intrinsics_problems(K) -> list[str]:
    """Returns what keeps `K` (3, 3) from being valid zero-skew pinhole intrinsics (empty = OK)."""
    a, problems = _numeric(K, (3, 3))
    if a is None:
        return problems
    problems = [f"focal length {n} must be > 0, got {a[i, i]:g}"
                for i, n in ((0, "fx"), (1, "fy")) if not a[i, i] > 0]
    if abs(a[0, 1]) > 1e-9 * max(abs(a[0, 0]), 1.0) or a[1, 0] != 0:
        problems.append(f"skew must be zero, got K[0,1]={a[0, 1]:g}, K[1,0]={a[1, 0]:g}")
    if a[2].tolist() != [0.0, 0.0, 1.0]:
        problems.append(f"last row must be [0, 0, 1], got {a[2].tolist()}")
    return problems


def validate_pose(c2w, where: str = "c2w") -> np.ndarray:
    """Returns `c2w` as a new (4, 4) float64 array; ValueError prefixed `where` if not rigid."""
    _raise_if(pose_problems(c2w), where)
    return np.array(c2w, dtype=np.float64)


def validate_intrinsics(K, where: str = "K") -> np.ndarray:
    """Returns `K` as a new (3, 3) float64 array; ValueError prefixed `where` if invalid."""
    _raise_if(intrinsics_problems(K), where)
    return np.array(K, dtype=np.float64)


def _rigid_inverse(m: np.ndarray) -> np.ndarray:
    """Returns the inverse (4, 4) of a rigid (4, 4) transform, exactly: [R^T, -R^T t]."""
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = m[:3, :3].T, -m[:3, :3].T @ m[:3, 3]
    return out


def nearest_rotation(m) -> np.ndarray:
    """Returns the proper rotation (3, 3) closest in Frobenius norm to `m` (3, 3), via SVD."""
    u, _, vt = np.linalg.svd(np.asarray(m, dtype=np.float64))
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def quaternion_to_rotation(q) -> np.ndarray:
    """(3, 3) rotation of a Hamilton quaternion (w, x, y, z), normalised first (COLMAP's order)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


# ----------------------------------------------------------------------------- camera


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: K (3, 3) pixels, c2w (4, 4) rigid, OpenCV axes, pixel centres at +0.5."""

    K: np.ndarray
    c2w: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        K, c2w = validate_intrinsics(self.K, "K"), validate_pose(self.c2w, "c2w")
        K.setflags(write=False)
        c2w.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "width", _size(self.width, "width"))
        object.__setattr__(self, "height", _size(self.height, "height"))

    @property
    def w2c(self) -> np.ndarray:
        """Returns the (4, 4) world-to-camera transform (exact rigid inverse of c2w)."""
        return _rigid_inverse(self.c2w)

    @property
    def center(self) -> np.ndarray:
        """Returns the camera centre (3,) in world coordinates."""
        return self.c2w[:3, 3].copy()

    def project(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Returns (pixels (N, 2) as (col, row) continuous coords, depth (N,) = camera z).

        `points` is (N, 3) world coordinates; depth <= 0 means behind the camera.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        w2c = self.w2c
        cam = p @ w2c[:3, :3].T + w2c[:3, 3]
        depth = cam[:, 2]
        return (cam @ self.K.T)[:, :2] / depth[:, None], depth

    def pixel_directions(self, pixels=None) -> np.ndarray:
        """Returns un-normalised world directions R K^-1 [x, y, 1] (N, 3) through `pixels` (N, 2).

        None means every pixel centre, row-major: row j * W + i passes through (i + .5, j + .5).
        """
        if pixels is None:
            i, j = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
            pixels = np.stack([i.ravel(), j.ravel()], axis=-1)
        uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        uv1 = np.concatenate([uv, np.ones((len(uv), 1))], axis=-1)
        return uv1 @ (self.c2w[:3, :3] @ np.linalg.inv(self.K)).T

    def pixel_rays(self, pixels=None) -> tuple[np.ndarray, np.ndarray]:
        """Returns (origins (N, 3), unit directions (N, 3)) through `pixels` (see pixel_directions)."""
        d = self.pixel_directions(pixels)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.c2w[:3, 3], d.shape).copy(), d


# ----------------------------------------------------------------------------- converters


def from_opencv(K, c2w=None, w2c=None, *, width, height) -> Camera:
    """Returns a Camera from OpenCV K (3, 3) and exactly one of c2w / w2c (4, 4)."""
    if (c2w is None) == (w2c is None):
        raise ValueError("from_opencv: give exactly one of c2w or w2c")
    K = validate_intrinsics(K, "K")
    if c2w is not None:
        return Camera(K, validate_pose(c2w, "c2w"), width, height)
    return Camera(K, _rigid_inverse(validate_pose(w2c, "w2c")), width, height)


def from_opencv_rt(R, t, K, width, height) -> Camera:
    """Returns a Camera from world-to-camera R (3, 3), t (3,) (x_cam = R x_world + t, COLMAP)."""
    _raise_if(rotation_problems(R), "R")
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = _as_float(R, (3, 3), "R"), _as_float(t, (3,), "t")
    return from_opencv(K, w2c=w2c, width=width, height=height)


def intrinsics_from_fov(fov_deg: float, width: int, height: int, axis: str = "x") -> np.ndarray:
    """Returns K (3, 3), square pixels, centred principal point, for a field of view in degrees.

    `axis` says which extent `fov_deg` spans, as Mitsuba's `fov_axis`: "x" (width), "y"
    (height), "diagonal", "smaller" / "larger" (the smaller / larger of width and height).
    """
    width, height = _size(width, "width"), _size(height, "height")
    if axis not in _FOV_AXES:
        raise ValueError(f"axis: expected one of {_FOV_AXES}, got {axis!r}")
    fov = float(_as_float(fov_deg, (), "fov_deg"))
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov_deg: must be in (0, 180) degrees, got {fov:g}")
    if axis in ("smaller", "larger"):
        axis = "x" if (width <= height) == (axis == "smaller") else "y"
    extent = {"x": width, "y": height, "diagonal": math.hypot(width, height)}[axis]
    f = 0.5 * extent / math.tan(math.radians(fov) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def _look_at_pose(eye, target, up, where: str) -> np.ndarray:
    """Returns OpenCV c2w (4, 4) at `eye` looking at `target`, image up along `up` (projected)."""
    fwd = target - eye
    if np.linalg.norm(fwd) < 1e-12:
        raise ValueError(f"{where}: eye and target coincide, no viewing direction")
    if np.linalg.norm(up) < 1e-12:
        raise ValueError(f"{where}: up vector is zero")
    fwd = fwd / np.linalg.norm(fwd)
    x = np.cross(fwd, up / np.linalg.norm(up))
    if np.linalg.norm(x) < 1e-6:
        raise ValueError(f"{where}: up {up.tolist()} is parallel to the viewing direction "
                         f"{fwd.tolist()}")
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, np.cross(fwd, x), fwd, eye
    return c2w


def look_at(eye, target, up, K, width, height) -> Camera:
    """Returns a Camera at eye (3,) looking at target (3,); image up is `up` (3,) projected."""
    eye, target, up = (_as_float(v, (3,), n) for v, n in ((eye, "eye"), (target, "target"),
                                                         (up, "up")))
    return Camera(validate_intrinsics(K, "K"), _look_at_pose(eye, target, up, "look_at"),
                  width, height)


def _from_gl(c2w_gl, K, width, height, name: str) -> Camera:
    """Returns a Camera from OpenGL camera-to-world `c2w_gl`, errors naming `name`."""
    return Camera(validate_intrinsics(K, "K"), validate_pose(c2w_gl, name) @ _GL_TO_CV,
                  width, height)


def from_opengl(c2w_gl, K, width, height) -> Camera:
    """Returns a Camera from OpenGL/Blender/NeRF c2w (4, 4): x right, y up, looks along -z."""
    return _from_gl(c2w_gl, K, width, height, "c2w_gl")


def to_opengl(camera: Camera) -> np.ndarray:
    """Returns the camera's OpenGL/glTF c2w (4, 4): x right, y up, looking along -z (from_opengl's inverse)."""
    return camera.c2w @ _GL_TO_CV


def from_nerf_frame(meta: dict, frame: dict, width=None, height=None) -> Camera:
    """Returns a Camera for one `frames[i]` of a NeRF/Blender/nerfstudio `transforms.json`.

    Intrinsics: `fl_x`, `fl_y`, `cx`, `cy` (pixels), else `camera_angle_x` (radians, centred
    principal point, fy = fx unless `camera_angle_y`); a frame's keys override `meta`'s. Size:
    `width`/`height`, else `w`/`h`. Pose: `frame["transform_matrix"]`, OpenGL c2w (4, 4).
    """
    where = f"frame {frame.get('file_path', '')!s}".rstrip()
    if "transform_matrix" not in frame:
        raise ValueError(f"{where}: missing key 'transform_matrix' (4x4 OpenGL camera-to-world)")
    p = {k: frame.get(k, meta.get(k)) for k in _NERF_KEYS if k in frame or k in meta}
    size = {}
    for arg, value, key in (("width", width, "w"), ("height", height, "h")):
        if value is None and key not in p:
            raise ValueError(f"{where}: no {arg} given and key '{key}' missing from transforms")
        if value is not None and key in p and "fl_x" in p and p[key] != _size(value, arg):
            raise ValueError(f"{where}: {arg}={value} differs from '{key}'={p[key]}, the size the "
                             "pixel intrinsics refer to; rescale fl_x/fl_y/cx/cy first")
        size[arg] = _size(value if value is not None else p[key], arg)
    W, H = size["width"], size["height"]
    if "fl_x" in p:
        missing = [k for k in ("fl_y", "cx", "cy") if k not in p]
        if missing:
            raise ValueError(f"{where}: 'fl_x' given but key(s) {missing} missing from transforms")
        fx, fy, cx, cy = (float(p[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
    elif "camera_angle_x" in p:
        fx = 0.5 * W / math.tan(float(p["camera_angle_x"]) / 2.0)
        fy = 0.5 * H / math.tan(float(p["camera_angle_y"]) / 2.0) if "camera_angle_y" in p else fx
        cx, cy = W / 2.0, H / 2.0
    else:
        raise ValueError(f"{where}: intrinsics missing: need key 'camera_angle_x' or keys "
                         "'fl_x', 'fl_y', 'cx', 'cy'")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    _raise_if(intrinsics_problems(K), f"{where}: intrinsics")
    return _from_gl(frame["transform_matrix"], K, W, H, f"{where}: transform_matrix")


def _algorithm1(m: np.ndarray, where: str) -> np.ndarray:
    """Returns OpenCV c2w from a c2w `m` whose camera axes are x left, y up, z forward.

    Thesis Algorithm 1: eye = translation, up = R (0, 1, 0), forward = R (0, 0, 1), then
    look-at. Only up and forward are used, so scale and a mirrored x axis are ignored.
    """
    eye, R = m[:3, 3], m[:3, :3]
    return _look_at_pose(eye, eye + R @ [0.0, 0.0, 1.0], R @ [0.0, 1.0, 0.0], where)


def from_mitsuba(to_world, fov_deg, width, height, fov_axis="x",
                 principal_point_offset_x=0.0, principal_point_offset_y=0.0) -> Camera:
    """Returns a Camera for a Mitsuba 3 `perspective` sensor (camera x left, y up, z forward).

    Pose by thesis Algorithm 1 on `to_world` (4, 4). Mitsuba shifts the film sample by the
    offsets (fractions of film width / height) before unprojecting, so the optical axis meets
    the image at cx = W (0.5 - offset_x), cy = H (0.5 - offset_y) (checked against
    `sensor.sample_ray` and a render). A to_world with det < 0 makes Mitsuba render a mirror
    image, which no rigid camera reproduces: this returns the unmirrored camera, whose image
    is that render flipped left-right when principal_point_offset_x is negated.
    """
    m = _as_float(to_world, (4, 4), "to_world")
    _raise_if(_last_row_problems(m), "to_world")
    W, H = _size(width, "width"), _size(height, "height")
    K = intrinsics_from_fov(fov_deg, W, H, fov_axis)
    ox = float(_as_float(principal_point_offset_x, (), "principal_point_offset_x"))
    oy = float(_as_float(principal_point_offset_y, (), "principal_point_offset_y"))
    K[0, 2], K[1, 2] = W * (0.5 - ox), H * (0.5 - oy)
    return Camera(K, _algorithm1(m, "to_world"), W, H)


def from_fipt(transform_matrix, camera_angle_x, width, height) -> Camera:
    """Returns a Camera for one frame of a FIPT/IRIS `transforms.json` (camera x left, y up, z forward).

    FIPT generates the ray of pixel (i, j) as R [-(i + .5 - W/2) / f, -(j + .5 - H/2) / f, 1]
    from the c2w (4, 4) `transform_matrix`, f = W / 2 / tan(camera_angle_x / 2) (radians), so
    square pixels, a centred principal point, and the pose by thesis Algorithm 1.
    """
    m = _as_float(transform_matrix, (4, 4), "transform_matrix")
    _raise_if(_last_row_problems(m), "transform_matrix")
    angle = float(_as_float(camera_angle_x, (), "camera_angle_x"))
    if not 0.0 < angle < math.pi:
        raise ValueError(f"camera_angle_x: must be in (0, pi) radians, got {angle:g}")
    W, H = _size(width, "width"), _size(height, "height")
    return Camera(intrinsics_from_fov(math.degrees(angle), W, H, "x"), _algorithm1(m, "transform_matrix"), W, H)


def intrinsics_to_pytorch3d_ndc(K, width, height) -> tuple[np.ndarray, np.ndarray]:
    """Returns (f_norm (2,), p_norm (2,)): PyTorch3D NDC intrinsics, thesis Algorithm 2."""
    K = validate_intrinsics(K, "K")
    f, p = np.array([K[0, 0], K[1, 1]]), np.array([K[0, 2], K[1, 2]])
    s_wh = np.array([_size(width, "width"), _size(height, "height")], dtype=np.float64)
    s = s_wh.min() / 2.0
    c0 = s_wh / 2.0
    return f / s, -(p - c0) / s


def from_pytorch3d(R, T, focal_ndc, principal_ndc, width, height) -> Camera:
    """Returns a Camera from PyTorch3D R (3, 3), T (3,) and NDC focal (2,) / principal (2,).

    PyTorch3D: X_cam = X_world @ R + T (row vectors), camera +X left, +Y up, +Z forward; NDC
    spans [-1, 1] on the shorter image side, so pixel = (W, H) / 2 - s * ndc, s = min(W, H) / 2.
    A scalar focal_ndc means fx = fy.
    """
    _raise_if(rotation_problems(R), "R")
    R, T = _as_float(R, (3, 3), "R"), _as_float(T, (3,), "T")
    f = _as_float(focal_ndc if np.ndim(focal_ndc) else [focal_ndc] * 2, (2,), "focal_ndc")
    p = _as_float(principal_ndc, (2,), "principal_ndc")
    if not np.all(f > 0):
        raise ValueError(f"focal_ndc: must be > 0, got {f.tolist()}")
    W, H = _size(width, "width"), _size(height, "height")
    s = min(W, H) / 2.0
    K = np.array([[f[0] * s, 0.0, W / 2.0 - p[0] * s], [0.0, f[1] * s, H / 2.0 - p[1] * s],
                  [0.0, 0.0, 1.0]])
    w2c_p3d = np.eye(4)
    w2c_p3d[:3, :3], w2c_p3d[:3, 3] = R.T, T  # column form of the row-vector convention
    return from_opencv(K, w2c=_P3D_TO_CV @ w2c_p3d, width=W, height=H)


def from_scannetpp(transform_matrix, fl_x, fl_y, cx, cy, width, height) -> Camera:
    """Returns a Camera, in the mesh's world, for a ScanNet++ DSLR nerfstudio pose ((4, 4)).

    ScanNet++ writes `transform_matrix` from the COLMAP pose (OpenCV c2w in the mesh's world) by
    negating the camera's y and z columns (OpenGL camera) and then permuting the WORLD: rows x
    and y swapped, row z negated. We undo both: re-orthogonalise the rotation (nearest rotation,
    det +1), bring the pose back into the mesh's world (`SCANNETPP_WORLD @ M`), invert the
    camera's X and Z axes as thesis B.2 does (a PyTorch3D camera: x left, y up, z forward), then
    Algorithm 1. Net effect: c2w_cv = SCANNETPP_WORLD @ reorth(M) @ diag(1, -1, -1, 1).
    Intrinsics are pixels (undistorted).
    """
    m = _as_float(transform_matrix, (4, 4), "transform_matrix")
    _raise_if(_last_row_problems(m), "transform_matrix")
    err = float(np.abs(m[:3, :3].T @ m[:3, :3] - np.eye(3)).max())
    if err > _REORTH_TOL or np.linalg.det(m[:3, :3]) <= 0:
        raise ValueError(f"transform_matrix: rotation too far from a proper rotation to "
                         f"re-orthogonalise (max |R^T R - I| = {err:.3g}, det = "
                         f"{np.linalg.det(m[:3, :3]):.3g})")
    m[:3, :3] = nearest_rotation(m[:3, :3])
    K = _as_float([[fl_x, 0.0, cx], [0.0, fl_y, cy], [0.0, 0.0, 1.0]], (3, 3), "fl_x/fl_y/cx/cy")
    _raise_if(intrinsics_problems(K), "fl_x/fl_y/cx/cy")
    return Camera(K, _algorithm1(SCANNETPP_WORLD @ m @ _FLIP_XZ, "transform_matrix"), width, height)


def rgbx_camera_rotation(c2w) -> np.ndarray:
    """(3, 3) M with n_camera = n_world @ M, RGB<->X's camera axes: x right, y up, z towards the camera."""
    return np.asarray(c2w, np.float64)[:3, :3] @ np.diag([1.0, -1.0, -1.0])


def rgbx_camera_normals(normals_world, camera: Camera) -> np.ndarray:
    """(..., 3) world-space normals in RGB<->X's camera space: x right, y up, z towards the camera."""
    return np.asarray(normals_world, np.float64) @ rgbx_camera_rotation(camera.c2w)


def camera_normals(normals_world: np.ndarray, triangle: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W, 3) float32 RGB<->X camera-space normals of the faces `triangle` (H, W) hits; 0 on misses."""
    hit = triangle >= 0
    n = rgbx_camera_normals(normals_world[np.where(hit, triangle, 0)], camera)
    return np.where(hit[..., None], n, 0.0).astype(np.float32)
