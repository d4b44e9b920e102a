"""Tiny datasets in every format the loaders read, written from ONE set of known OpenCV cameras.

Each writer converts the ground-truth cameras into its format's own convention with the
format's documented formulas (written here, independently of jaxdistill.scene.cameras), so a loader
that gets a convention wrong puts the known points on the wrong pixels. The room is a 4 x 2.5 x 3
box (six wall objects); photos are small random images.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from jaxdistill.io import images as imageio
from jaxdistill.scene.shapes import box_room

WIDTH, HEIGHT, FOCAL = 32, 24, 28.0
ROOM = (4.0, 2.5, 3.0)


@pytest.fixture(autouse=True)
def cache(tmp_path_factory, monkeypatch):
    """Imports' caches in the test session's folder (autouse in a module that imports it)."""
    monkeypatch.setenv("JAXDISTILL_CACHE", str(tmp_path_factory.getbasetemp() / "dataset_cache"))


@pytest.fixture(scope="module")
def cams():
    return ground_truth_cameras(3)


def room_mesh():
    return box_room(size=ROOM, subdivisions=2)


def ground_truth_cameras(n: int = 3) -> list[dict]:
    """n OpenCV cameras inside the room: {"K": (3, 3), "c2w": (4, 4)} (x right, y down, z forward)."""
    out = []
    centre = np.array([2.0, 1.25, 1.5])
    for i in range(n):
        angle = 0.4 + 2 * math.pi * i / n
        fwd = np.array([math.cos(angle), -0.15, math.sin(angle)])
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 1.0, 0.0])        # image x: right of the view, world y is up
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = right, down, fwd
        c2w[:3, 3] = centre - 0.4 * fwd + np.array([0.1 * i, 0.05 * i, 0.0])
        K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
        out.append({"K": K, "c2w": c2w})
    return out


def known_points(cams, per_camera: int = 4, seed: int = 0) -> np.ndarray:
    """(N, 3) world points in front of every camera's image (seeded)."""
    rng = np.random.default_rng(seed)
    points = []
    for cam in cams:
        for _ in range(per_camera):
            z = rng.uniform(0.8, 1.5)
            x = rng.uniform(-0.3, 0.3) * z
            y = rng.uniform(-0.25, 0.25) * z
            points.append(cam["c2w"][:3, :3] @ [x, y, z] + cam["c2w"][:3, 3])
    return np.array(points)


def reference_pixels(cam: dict, points: np.ndarray) -> np.ndarray:
    """(N, 2) pixel (col, row) of points through the OpenCV pinhole u = fx X/Z + cx (centres at +0.5)."""
    rel = points - cam["c2w"][:3, 3]
    local = rel @ cam["c2w"][:3, :3]                 # = R^T (X - c) per row
    K = cam["K"]
    return np.stack([K[0, 0] * local[:, 0] / local[:, 2] + K[0, 2], K[1, 1] * local[:, 1] / local[:, 2] + K[1, 2]], 1)


def _photo(rng, hdr: bool) -> np.ndarray:
    base = rng.uniform(0.05, 0.9, (HEIGHT, WIDTH, 3)).astype(np.float32)
    return base * 3.0 if hdr else base


def write_mesh(path: Path, uvs: bool = True) -> Path:
    """The room as OBJ/PLY/GLB, one node per wall; without UVs when uvs=False."""
    mesh = room_mesh()
    path.parent.mkdir(parents=True, exist_ok=True)
    if uvs:
        from jaxdistill.scene.model import save_mesh

        save_mesh(mesh, path)
    else:
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    return path


# ----------------------------------------------------------------------------- formats

def write_fipt(root: Path, cams, *, ldr: bool = False, missing_photo: int | None = None, seed: int = 0) -> Path:
    """FIPT layout. Pose: camera x left, y up, z forward -> negate OpenCV's x and y columns."""
    rng = np.random.default_rng(seed)
    split = root / "train"
    frames = []
    for i, cam in enumerate(cams):
        m = cam["c2w"].copy()
        m[:3, 0] *= -1
        m[:3, 1] *= -1
        frames.append({"file_path": f"./train/{i:03d}", "transform_matrix": m.tolist()})
        stem = f"{i:03d}_0001"
        if i != missing_photo:
            imageio.write_image(split / "Image" / f"{stem}{'.png' if ldr else '.exr'}", _photo(rng, not ldr))
        imageio.write_image(split / "DiffCol" / f"{stem}.exr", rng.uniform(0, 1, (HEIGHT, WIDTH, 3)))
        imageio.write_image(split / "Roughness" / f"{stem}.exr", np.repeat(rng.uniform(0, 1, (HEIGHT, WIDTH, 1)), 3, -1))
        emit = np.zeros((HEIGHT, WIDTH, 3), np.float32)
        emit[:4, :5] = 10.0                                           # an emitter in the top-left corner
        imageio.write_image(split / "Emit" / f"{stem}.exr", emit)
    angle = 2 * math.atan(WIDTH / 2 / FOCAL)
    (split / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    write_mesh(root / "scene.obj")
    return root


def fipt_ray(transform_matrix, camera_angle_x, col: float, row: float) -> tuple[np.ndarray, np.ndarray]:
    """FIPT's ray for continuous pixel coordinates (col, row): R [-(col - W/2)/f, -(row - H/2)/f, 1]."""
    m = np.asarray(transform_matrix)
    f = 0.5 * WIDTH / math.tan(0.5 * camera_angle_x)
    d = m[:3, :3] @ np.array([-(col - WIDTH / 2) / f, -(row - HEIGHT / 2) / f, 1.0])
    return m[:3, 3], d / np.linalg.norm(d)


def _opengl_matrix(cam) -> np.ndarray:
    """OpenGL c2w (x right, y up, looking along -z): negate OpenCV's y and z columns."""
    m = cam["c2w"].copy()
    m[:3, 1] *= -1
    m[:3, 2] *= -1
    return m


def write_nerfstudio(root: Path, cams, *, distortion=None, model: str | None = None, seed: int = 1) -> Path:
    """transforms.json + images/frame_XXXXX.png; OPENCV k1, k2, p1, p2 when `distortion` is given
    (the photos are then NOT distorted: only the pose check and the undistortion step run)."""
    rng = np.random.default_rng(seed)
    K = cams[0]["K"]
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": WIDTH, "h": HEIGHT,
            "camera_model": model or ("OPENCV" if distortion else "PINHOLE"), "frames": []}
    if distortion:
        meta.update(distortion)
    for i, cam in enumerate(cams):
        name = f"images/frame_{i + 1:05d}.png"
        imageio.write_image(root / name, _photo(rng, False))
        meta["frames"].append({"file_path": name, "transform_matrix": _opengl_matrix(cam).tolist()})
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def scannetpp_transform_matrix(c2w_cv) -> np.ndarray:
    """ScanNet++'s nerfstudio `transform_matrix` of a COLMAP (OpenCV) pose in the mesh's world, as
    their common/utils/nerfstudio.py::convert_frames writes it: c2w = inverse(world_to_camera),
    negate camera columns y and z, swap world rows 0 and 1, negate world row 2."""
    world_to_camera = np.linalg.inv(np.asarray(c2w_cv, np.float64))
    c2w = np.linalg.inv(world_to_camera)
    c2w[0:3, 1:3] *= -1
    c2w = c2w[np.array([1, 0, 2, 3]), :]
    c2w[2, :] *= -1
    return c2w


def write_scannetpp(root: Path, cams, *, seed: int = 2, bad_frame: int | None = None, masks: bool = True,
                    test_frame: int | None = None, undistorted: bool = True) -> Path:
    """data/<id> layout; poses by ScanNet++'s own formula (`scannetpp_transform_matrix`), with a slightly
    non-orthogonal rotation (as theirs); `test_frame` goes to "test_frames"; undistorted=False
    writes only the fisheye dslr/nerfstudio/transforms.json (what the release ships before
    their undistortion script runs)."""
    rng = np.random.default_rng(seed)
    K = cams[0]["K"]
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": WIDTH, "h": HEIGHT,
            "camera_model": "PINHOLE", "frames": [], "test_frames": []}
    dslr = root / "dslr"
    for i, cam in enumerate(cams):
        name = f"DSC{i:05d}.JPG"
        imageio.write_image(dslr / "undistorted_images" / name, _photo(rng, False))
        if masks:
            mask = np.ones((HEIGHT, WIDTH, 1), np.float32)
            mask[-3:, -3:] = 0.0
            imageio.write_image(dslr / "undistorted_anon_masks" / f"DSC{i:05d}.png", mask, encode_srgb=False)
        m = scannetpp_transform_matrix(cam["c2w"])
        noise = 2e-4 * rng.normal(size=(3, 3))
        m[:3, :3] = m[:3, :3] @ (np.eye(3) + noise + noise.T)       # not orthonormal; its polar part is R
        frame = {"file_path": name, "transform_matrix": m.tolist(), "is_bad": i == bad_frame}
        meta["test_frames" if i == test_frame else "frames"].append(frame)
    (dslr / "nerfstudio").mkdir(parents=True, exist_ok=True)
    if undistorted:
        (dslr / "nerfstudio" / "transforms_undistorted.json").write_text(json.dumps(meta))
    else:
        fisheye = {**meta, "camera_model": "OPENCV_FISHEYE", "k1": 0.01, "k2": -0.002, "k3": 0.0, "k4": 0.0}
        (dslr / "nerfstudio" / "transforms.json").write_text(json.dumps(fisheye))
    write_mesh(root / "scans" / "mesh_aligned_0.05.ply", uvs=False)
    return root


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix, Shepperd's trace method."""
    tr = np.trace(R)
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        return np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    i = int(np.argmax(np.diag(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2 * math.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
    q = np.zeros(4)
    q[0] = (R[k, j] - R[j, k]) / s
    q[1 + i] = 0.25 * s
    q[1 + j] = (R[j, i] + R[i, j]) / s
    q[1 + k] = (R[k, i] + R[i, k]) / s
    return q


def write_colmap(root: Path, cams, *, model: str = "PINHOLE", k: float = 0.0, seed: int = 3) -> Path:
    """cameras.txt + images.txt (+ images/): x_cam = R X + t with R = c2w^T, t = -R c."""
    rng = np.random.default_rng(seed)
    K = cams[0]["K"]
    params = {"PINHOLE": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
              "SIMPLE_RADIAL": [K[0, 0], K[0, 2], K[1, 2], k]}[model]
    root.mkdir(parents=True, exist_ok=True)
    (root / "cameras.txt").write_text("# Camera list\n" f"1 {model} {WIDTH} {HEIGHT} " + " ".join(f"{float(x)!r}" for x in params) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for i, cam in enumerate(cams):
        R = cam["c2w"][:3, :3].T
        t = -R @ cam["c2w"][:3, 3]
        q = rotation_to_quaternion(R)
        name = f"img_{i}.png"
        imageio.write_image(root / "images" / name, _photo(rng, False))
        lines.append(f"{i + 1} " + " ".join(f"{float(x)!r}" for x in [*q, *t]) + f" 1 {name}")
        lines.append("")                                            # no 2D points
    (root / "images.txt").write_text("\n".join(lines) + "\n")
    return root
