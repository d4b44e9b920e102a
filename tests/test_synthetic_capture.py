"""The capture-sized synthetic room: deterministic from its seed, readable as a scene, and its
cameras walk round the room as a hand-held capture does (analytic checks on the camera poses)."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdistill.io import images as imageio
from jaxdistill.datasets.synthetic_capture import ROOM_SIZE, capture_room_mesh, write_capture_room
from jaxdistill.scene.model import read_scene
from jaxdistill.scene.shapes import walkthrough_cameras

REPO = Path(__file__).resolve().parents[1]


def digests(folder: Path) -> dict[str, str]:
    """Per file: a digest of its bytes, or for EXR of its pixels (the header holds a write time)."""
    def content(p: Path) -> bytes:
        return np.ascontiguousarray(imageio.read_image(p)).tobytes() if p.suffix == ".exr" else p.read_bytes()
    return {str(p.relative_to(folder)): hashlib.sha256(content(p)).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_the_face_count_follows_the_subdivisions():
    n = 5
    walls, furniture = 6 * 2 * n * n, 3 * 6 * 2 * max(1, n // 8) ** 2
    assert capture_room_mesh(n).num_faces == walls + furniture


def test_same_seed_same_files_other_seed_other_photos(tmp_path):
    kwargs = dict(faces_per_side=3, views=4, width=24, height=16, progress=False)
    a = write_capture_room(tmp_path / "a", seed=3, **kwargs)
    write_capture_room(tmp_path / "b", seed=3, **kwargs)
    write_capture_room(tmp_path / "c", seed=4, **kwargs)
    da, db, dc = (digests(tmp_path / k) for k in "abc")
    assert da == db
    assert da["photos/view_000.png"] != dc["photos/view_000.png"]
    scene = read_scene(tmp_path / "a" / "scene.json")
    assert a == {"faces": scene.mesh.num_faces, "objects": len(scene.mesh.object_names), "views": 4,
                 "width": 24, "height": 16}
    assert [v.name for v in scene.views] == [f"view_{i:03d}" for i in range(4)]


def test_the_walk_goes_once_round_the_room_at_eye_height():
    n = 24
    cams = walkthrough_cameras(n, ROOM_SIZE, width=64, height=48, seed=0)
    eyes = np.array([c.c2w[:3, 3] for c in cams])
    lo, hi = np.zeros(3), np.array(ROOM_SIZE)
    assert np.all(eyes > lo + 0.5) and np.all(eyes < hi - 0.5)
    assert np.allclose(eyes[:, 1], 1.6, atol=0.2)
    # evenly spaced: every step is close to the mean step, and the walk closes on itself
    steps = np.linalg.norm(np.diff(np.vstack([eyes, eyes[:1]]), axis=0), axis=1)
    assert steps.max() < 1.8 * np.median(steps)
    # the angle swept round the room's centre is one full turn
    centre = np.array([ROOM_SIZE[0] / 2, ROOM_SIZE[2] / 2])
    angles = np.unwrap(np.arctan2(eyes[:, 2] - centre[1], eyes[:, 0] - centre[0]))
    assert abs(angles[-1] - angles[0]) == pytest.approx(2 * np.pi * (n - 1) / n, rel=0.05)
    # each camera looks roughly level (a person's head), and its image size is what was asked
    forward = np.array([c.c2w[:3, 2] for c in cams])          # OpenCV: +z looks forward
    assert np.all(np.abs(forward[:, 1]) < 0.5)
    assert {(c.width, c.height) for c in cams} == {(64, 48)}


def test_bad_sizes_are_named():
    with pytest.raises(ValueError, match="num_views"):
        walkthrough_cameras(0)
    with pytest.raises(ValueError, match="faces_per_side"):
        capture_room_mesh(0)
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "make_capture_scene.py"), "--out=x", "--views=0"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "--views must be >= 1" in proc.stderr
