"""Mixed Voronoi areas and masses against brute-force references."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from warpskin.preprocess.layers import LayerParams, build_layers
from warpskin.preprocess.masses import layer_heights, mixed_voronoi_areas, particle_masses
from warpskin.rig import RigError
from warpskin.scenes.arm import make_arm


def _brute_force_mixed_area(v, tris):
    """Meyer et al. 2003 mixed area, one triangle and corner at a time, angles by arccos."""
    out = np.zeros(len(v))
    for t in tris:
        p = v[t]
        area = 0.5 * np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
        ang = []
        for c in range(3):
            a, b = p[(c + 1) % 3] - p[c], p[(c + 2) % 3] - p[c]
            ang.append(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))
        for c in range(3):
            if max(ang) > np.pi / 2:
                out[t[c]] += area / 2 if ang[c] > np.pi / 2 else area / 4
            else:
                q, r = (c + 1) % 3, (c + 2) % 3
                pr2 = np.sum((p[r] - p[c]) ** 2)
                pq2 = np.sum((p[q] - p[c]) ** 2)
                out[t[c]] += (pr2 / np.tan(ang[q]) + pq2 / np.tan(ang[r])) / 8
    return out


@pytest.mark.parametrize("seed", range(4))
def test_mixed_area_matches_brute_force_with_obtuse_triangles(seed):
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=1)
    v = np.asarray(m.vertices) + rng.normal(scale=0.25, size=m.vertices.shape)  # many obtuse triangles
    f = np.asarray(m.faces)
    got = mixed_voronoi_areas(v, f)
    ref = _brute_force_mixed_area(v, f)
    tri = trimesh.Trimesh(v, f, process=False)
    angles = tri.face_angles
    assert (angles.max(axis=1) > np.pi / 2).sum() > 5  # the obtuse rule is exercised
    assert np.allclose(got, ref, rtol=1e-10, atol=1e-14)
    assert got.sum() == pytest.approx(tri.area, rel=1e-12)


def test_areas_sum_to_surface_area_on_each_arm_layer():
    rig = make_arm()
    layers = build_layers(rig)
    for k in range(4):
        area = trimesh.Trimesh(layers.positions[k], rig.triangles, process=False).area
        assert mixed_voronoi_areas(layers.positions[k], rig.triangles).sum() == pytest.approx(area, rel=1e-12)


def test_heights_and_masses():
    rig = make_arm()
    layers = build_layers(rig, LayerParams(0.15, 0.45, 0.8))
    h = layer_heights(layers)
    seg = np.linalg.norm(layers.foot - layers.positions[0], axis=1)
    # skin: half the skin-fat gap; fat: half of each neighbouring gap; bone: half the muscle-bone gap
    assert np.allclose(h[0], 0.5 * 0.15 * seg)
    assert np.allclose(h[1], 0.5 * 0.45 * seg)
    assert np.allclose(h[2], 0.5 * 0.65 * seg)
    assert np.allclose(h[3], 0.5 * 0.35 * seg)
    m = particle_masses(layers, rig.triangles, density=1000.0)
    assert m.shape == (4 * rig.vertex_count,) and (m > 0).all()
    # total mass ~ density x volume between the skin and the bone layer (a coarse, independent bound)
    vol = trimesh.Trimesh(layers.positions[0], rig.triangles, process=False).volume
    assert 0.3 * 1000 * vol < m.sum() < 1.5 * 1000 * vol
    with pytest.raises(RigError, match="density must be a positive"):
        particle_masses(layers, rig.triangles, density=-1)
