"""Render-only simplification of visual meshes: fewer faces, close to the original, else unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from keygen.errors import InvalidParameterError
from keygen.sim.render_mesh import render_mesh


def _largest_deviation(a: trimesh.Trimesh, b: trimesh.Trimesh, n: int = 3000) -> float:
    """Both-way surface distance on samples other than the ones render_mesh checks with."""
    worst = 0.0
    for src, dst in ((a, b), (b, a)):
        points, _ = trimesh.sample.sample_surface(src, n, seed=7)
        worst = max(worst, float(trimesh.proximity.closest_point(dst, points)[1].max()))
    return worst


def _fine_sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=0.05)  # 20,480 faces


def test_a_fine_mesh_gets_fewer_faces_within_tolerance():
    sphere = _fine_sphere()
    vertices, faces = render_mesh(sphere.vertices, sphere.faces, max_faces=4000, tolerance=0.002)
    assert vertices.shape[1] == 3 and faces.shape[1] == 3
    assert len(faces) < len(sphere.faces) // 2
    assert faces.min() >= 0 and faces.max() < len(vertices)
    light = trimesh.Trimesh(vertices, faces, process=False)
    assert _largest_deviation(sphere, light) <= 0.002


def test_small_meshes_and_unreachable_tolerances_keep_the_original():
    box = trimesh.creation.box((0.1, 0.05, 0.02))
    v, f = render_mesh(box.vertices, box.faces, max_faces=100)
    np.testing.assert_array_equal(v, box.vertices)
    np.testing.assert_array_equal(f, box.faces)
    sphere = _fine_sphere()
    v, f = render_mesh(sphere.vertices, sphere.faces, max_faces=200, tolerance=1e-7)
    np.testing.assert_array_equal(f, sphere.faces)  # no simplification is that close: kept whole
    np.testing.assert_array_equal(v, sphere.vertices)


def test_results_are_cached_by_content():
    sphere = _fine_sphere()
    first = render_mesh(sphere.vertices, sphere.faces, max_faces=4000)
    again = render_mesh(sphere.vertices.copy(), sphere.faces.copy(), max_faces=4000)
    assert first[0] is again[0] and first[1] is again[1]


@pytest.mark.parametrize(
    "vertices, faces, max_faces, tolerance",
    [
        (np.zeros((4, 2)), np.zeros((2, 3), int), 10, 0.002),
        (np.zeros((4, 3)), np.zeros((2, 4), int), 10, 0.002),
        (np.zeros((4, 3)), np.zeros((2, 3), int), 2, 0.002),
        (np.zeros((4, 3)), np.zeros((2, 3), int), 10, 0.0),
    ],
)
def test_bad_input_is_refused(vertices, faces, max_faces, tolerance):
    with pytest.raises(InvalidParameterError):
        render_mesh(vertices, faces, max_faces, tolerance)


def test_a_mesh_the_simplifier_rejects_is_drawn_whole(monkeypatch):
    def broken(self, *args, **kwargs):
        raise ValueError("non-manifold input")

    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", broken)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.03)  # not cached by the other tests
    v, f = render_mesh(sphere.vertices, sphere.faces, max_faces=1000)
    np.testing.assert_array_equal(f, sphere.faces)
    np.testing.assert_array_equal(v, sphere.vertices)
