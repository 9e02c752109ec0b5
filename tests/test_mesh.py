"""The mesh helpers written once (:mod:`warpskin.mesh`) against trimesh and closed forms."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from warpskin.mesh import (
    face_normals, mixed_voronoi_areas, summed_face_normals, surface_area, triangle_areas, vertex_normals,
)


@pytest.fixture
def blob():
    """A closed, irregular surface: an icosphere with its vertices pushed in and out."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    rng = np.random.default_rng(7)
    v = sphere.vertices * (1.0 + 0.2 * rng.random((len(sphere.vertices), 1)))
    return v, np.asarray(sphere.faces, dtype=np.int64)


def test_face_normals_and_areas_match_trimesh(blob):
    v, f = blob
    ref = trimesh.Trimesh(v, f, process=False)
    n = face_normals(v, f)
    np.testing.assert_allclose(n / np.linalg.norm(n, axis=1, keepdims=True), ref.face_normals, atol=1e-12)
    np.testing.assert_allclose(triangle_areas(v, f), ref.area_faces, rtol=1e-12)
    assert surface_area(v, f) == pytest.approx(ref.area, rel=1e-12)
    assert face_normals(v.astype(np.float32), f).dtype == np.float32  # keeps the dtype it is given


def test_vertex_normals_are_the_normalised_area_weighted_sums(blob):
    v, f = blob
    summed = np.zeros_like(v)
    fn = trimesh.Trimesh(v, f, process=False).face_normals * trimesh.Trimesh(v, f, process=False).area_faces[:, None]
    for k in range(3):  # brute force: every triangle's area-weighted normal to its three corners
        np.add.at(summed, f[:, k], 2.0 * fn)
    np.testing.assert_allclose(summed_face_normals(v, f), summed, atol=1e-12)
    np.testing.assert_allclose(vertex_normals(v, f), summed / np.linalg.norm(summed, axis=1, keepdims=True),
                               atol=1e-12)
    lone = vertex_normals(np.vstack([v, [[5.0, 5.0, 5.0]]]), f)  # a point on no triangle: zero
    np.testing.assert_array_equal(lone[-1], 0.0)


def test_mixed_voronoi_areas_sum_to_the_area_and_split_a_right_and_an_obtuse_triangle():
    # an acute triangle: the circumcentre's Voronoi cells (closed form: 1/8 sum |e|^2 cot)
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.4, 0.9, 0.0]])
    t = np.array([[0, 1, 2]])
    areas = mixed_voronoi_areas(a, t)
    assert areas.sum() == pytest.approx(0.45, rel=1e-12)

    def cot(p, q, r):  # at p
        u, w = q - p, r - p
        return float(np.dot(u, w) / np.linalg.norm(np.cross(u, w)))

    e2 = lambda i, j: float(np.sum((a[i] - a[j]) ** 2))  # noqa: E731
    expect0 = (e2(0, 1) * cot(a[2], a[0], a[1]) + e2(0, 2) * cot(a[1], a[0], a[2])) / 8.0
    assert areas[0] == pytest.approx(expect0, rel=1e-12)
    # an obtuse triangle (at corner 2): half to the obtuse corner, a quarter to each other
    o = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.45, 0.1, 0.0]])
    np.testing.assert_allclose(mixed_voronoi_areas(o, t), [0.0125, 0.0125, 0.025], rtol=1e-12)


def test_mixed_voronoi_areas_of_a_closed_surface_sum_to_its_area(blob):
    v, f = blob
    areas = mixed_voronoi_areas(v, f)
    assert (areas > 0).all()
    assert areas.sum() == pytest.approx(trimesh.Trimesh(v, f, process=False).area, rel=1e-12)
