"""Regions: omega-rings against a breadth-first reference; CSR consistent both ways."""

from __future__ import annotations


import numpy as np
import pytest

from oracles import neighbour_sets, omega_ring
from warpskin.preprocess.layers import build_layers
from warpskin.preprocess.masses import particle_masses
from warpskin.preprocess.regions import build_regions, omega_rings, particle_radii
from warpskin.rig import RigError
from warpskin.scenes.arm import make_arm


@pytest.fixture(scope="module")
def small_arm():
    return make_arm(rings=14, segments=12)


def _bfs_ring(tris, v, start, omega):
    return sorted(omega_ring(neighbour_sets(tris, v), start, omega))


@pytest.mark.parametrize("omega", [1, 2, 3])
def test_omega_rings_equal_breadth_first_search(small_arm, omega):
    off, mem = omega_rings(small_arm.triangles, small_arm.vertex_count, omega)
    rng = np.random.default_rng(omega)
    for i in rng.choice(small_arm.vertex_count, 40, replace=False):
        assert list(mem[off[i]:off[i + 1]]) == _bfs_ring(small_arm.triangles, small_arm.vertex_count, int(i), omega)


@pytest.mark.parametrize("omega", [1, 2])
def test_regions_csr_consistent_both_ways(small_arm, omega):
    layers = build_layers(small_arm)
    masses = particle_masses(layers, small_arm.triangles)
    reg = build_regions(layers, small_arm.triangles, masses, omega=omega)
    v = small_arm.vertex_count
    n = 4 * v
    ring_off, ring_mem = omega_rings(small_arm.triangles, v, omega)
    # expected members of every region, built naively
    for r in range(n):
        k, i = divmod(r, v)
        ring = [k * v + j for j in ring_mem[ring_off[i]:ring_off[i + 1]]]
        sib = ([r - v] if k > 0 else []) + ([r + v] if k < 3 else [])
        assert list(reg.region_members[reg.region_offsets[r]:reg.region_offsets[r + 1]]) == ring + sib
        assert reg.sibling_count[r] == len(sib)
    # transpose: (region, slot) pairs of each particle point back at that particle
    pairs = set()
    for p in range(n):
        for q in range(reg.particle_offsets[p], reg.particle_offsets[p + 1]):
            rr, slot = reg.particle_regions[q], reg.particle_slots[q]
            assert reg.region_offsets[rr] <= slot < reg.region_offsets[rr + 1]
            assert reg.region_members[slot] == p
            pairs.add((rr, slot))
    assert len(pairs) == reg.region_members.size  # every entry exactly once
    # rest data: mass-weighted centre, offsets sum to zero with masses
    x0 = layers.flat()
    region_of = reg.region_of_entry()
    m = masses[reg.region_members]
    assert np.allclose(np.bincount(region_of, m * reg.rest_offsets[:, 0], minlength=n), 0.0, atol=1e-15)
    r = 7 + v
    mem = reg.region_members[reg.region_offsets[r]:reg.region_offsets[r + 1]]
    com = (masses[mem, None] * x0[mem]).sum(0) / masses[mem].sum()
    assert np.allclose(reg.rest_com[r], com)


def test_particle_radii_positive_with_floor(small_arm):
    layers = build_layers(small_arm)
    r = particle_radii(layers, small_arm.triangles)
    assert r.shape == (4 * small_arm.vertex_count,) and (r > 0).all()


def test_bad_omega(small_arm):
    with pytest.raises(RigError, match="omega must be an integer >= 1"):
        omega_rings(small_arm.triangles, small_arm.vertex_count, 0)
