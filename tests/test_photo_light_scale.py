"""scripts/photo_light_scale.py's irradiance from the photos' own light, against analytic geometry:
inside a closed unit cube whose ceiling alone shows radiance 1, the irradiance (E/π) at the
floor's centre is the ceiling's form factor from there (the point-to-parallel-rectangle formula,
four quarter squares), by both estimators; with every wall at one radiance it is that radiance."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxdistill.render.fragments import RayCaster, compute_fragments
from jaxdistill.scene.cameras import look_at
from jaxdistill.scene.mesh import Mesh

REPO = Path(__file__).resolve().parents[1]
SIZE = 48


def load_script():
    spec = importlib.util.spec_from_file_location("photo_light_scale", REPO / "scripts" / "photo_light_scale.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["photo_light_scale"] = module
    spec.loader.exec_module(module)
    return module


def unit_cube() -> Mesh:
    v = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    uv = np.tile(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]), (len(faces), 1, 1))
    return Mesh(v, faces, uv, np.zeros(len(faces), np.int32), ("cube",))


def quarter_form_factor(x: float, y: float) -> float:
    """Form factor from a point to a parallel rectangle of sides x, y (in units of its height)
    with one corner straight above the point."""
    a, b = math.sqrt(1 + x * x), math.sqrt(1 + y * y)
    return (x / a * math.atan(y / a) + y / b * math.atan(x / b)) / (2 * math.pi)


@pytest.fixture(scope="module")
def cube_views():
    mesh = unit_cube()
    centre = np.array([0.5, 0.5, 0.5])
    f = SIZE / 2 / math.tan(math.radians(50))          # 100° field of view: each camera sees its whole wall
    K = np.array([[f, 0, SIZE / 2], [0, f, SIZE / 2], [0, 0, 1.0]])
    axes = [np.eye(3)[i] * s for i in range(3) for s in (1, -1)]
    cams = [look_at(centre - 0.3 * d, centre + d, np.array([0.0, 0.0, 1.0]) if abs(d[1]) else np.array([0.0, 1.0, 0.0]),
                    K, SIZE, SIZE) for d in axes]
    frags = compute_fragments(mesh, cams, cache_dir=False, progress=False)
    return mesh, cams, frags


def test_floor_centre_sees_the_ceiling_form_factor(cube_views):
    script = load_script()
    mesh, cams, frags = cube_views
    tri_v = mesh.vertices[mesh.faces]
    ceiling = np.all(np.isclose(tri_v[:, :, 1], 1.0), axis=1)
    photos = [np.where(ceiling[np.maximum(f.triangle, 0)][..., None] & f.hit[..., None], 1.0, 0.0) * np.ones(3)
              for f in frags]
    seen = [f.hit for f in frags]
    p, n = np.array([[0.5, 0.0, 0.5]]), np.array([[0.0, 1.0, 0.0]])
    expected = 4 * quarter_form_factor(0.5, 0.5)        # 0.2394
    caster = RayCaster(mesh)
    depths = [f.depth for f in frags]
    e_rays, frac_rays = script.photo_irradiance(mesh, caster, p, n, cams, depths, photos, seen, rays=8192, seed=1)
    q, nq, aq, _ = script.area_samples(mesh, 20000, np.random.default_rng(0))
    radiance, seen_q = script.observed_radiance(q, cams, depths, photos, seen)
    e_area, frac_area = script.photo_irradiance_area(caster, p, n, (q, nq, aq), radiance, seen_q.astype(float))
    assert frac_rays[0] > 0.99 and frac_area[0] > 0.97           # a closed box the six views see whole
    # rays: Monte Carlo with 8192 rays, sd sqrt(F (1 - F) / 8192) = 0.0047 (2 % of F): 4 sd
    np.testing.assert_allclose(e_rays[0], expected, rtol=0.08)
    np.testing.assert_allclose(e_area[0], expected, rtol=0.05)


def test_uniform_radiance_is_the_irradiance(cube_views):
    script = load_script()
    mesh, cams, frags = cube_views
    photos = [np.where(f.hit[..., None], 0.37, 0.0) * np.ones(3) for f in frags]
    seen = [f.hit for f in frags]
    p = np.array([[0.3, 0.0, 0.6], [0.0, 0.5, 0.5], [0.8, 1.0, 0.2]])
    n = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    e, frac = script.photo_irradiance(mesh, RayCaster(mesh), p, n, cams, [f.depth for f in frags], photos, seen,
                                      rays=256, seed=0)
    np.testing.assert_allclose(e, 0.37, rtol=1e-5)
    assert np.all(frac > 0.98)
