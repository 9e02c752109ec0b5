"""Shape-matching regions of the multi-layer model.

Deul & Bender 2013, section 3: "On each layer of our model we create a particle for each vertex
... and define a region for this particle. This region contains the omega-ring of the particle
defined by the mesh of the layer ... Furthermore, to couple the layers we include sibling
particles from adjacent layers into the region." Region ``r`` belongs to particle ``r``; its
rotation is particle ``r``'s orientation (oriented particles, Mueller and Chentanez 2011).

Because every layer has the skin's topology, the omega-ring of vertex ``i`` is the same vertex
set on every layer: it is stored once (``ring_*``, size V) and shared with the fast-summation
path runs. The expanded per-particle regions (``region_*``, size 4V, global particle indices,
layer-major ``k * V + i``) serve the direct gather and the goal blend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..rig import RigError
from .layers import Layers
from .fast_summation import vertex_adjacency

__all__ = ["Regions", "omega_rings", "build_regions", "particle_radii"]


def omega_rings(triangles: np.ndarray, vertex_count: int, omega: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Omega-ring of every vertex (itself included) as CSR ``(offsets [V+1], members [M])``,
    members sorted by vertex index."""
    if int(omega) != omega or omega < 1:
        raise RigError(f"region size omega must be an integer >= 1, got {omega}")
    a = vertex_adjacency(triangles, vertex_count).astype(np.int32)
    reach = sp.identity(vertex_count, dtype=np.int32, format="csr")
    step = (a + reach).tocsr()
    for _ in range(int(omega)):
        reach = (reach @ step).tocsr()
        reach.data[:] = 1
    reach.sort_indices()
    return reach.indptr.astype(np.int64), reach.indices.astype(np.int64)


def particle_radii(layers: Layers, triangles: np.ndarray, *, floor_fraction: float = 0.25) -> np.ndarray:
    """Radius [m] of each oriented particle's (spherical) ellipsoid, ``[4 V]``: half the mean
    length of its incident edges on its layer, floored at ``floor_fraction`` of the layer's mean
    edge length so particles on collapsed (flat) parts of a layer keep a well-conditioned moment
    matrix."""
    t = np.asarray(triangles, dtype=np.int64)
    e = np.unique(np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1), axis=0)
    v = layers.vertex_count
    deg = np.bincount(e.ravel(), minlength=v).astype(np.float64)
    out = np.empty((4, v))
    for k in range(4):
        x = layers.positions[k]
        length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
        total = np.bincount(e[:, 0], length, minlength=v) + np.bincount(e[:, 1], length, minlength=v)
        r = 0.5 * total / np.maximum(deg, 1.0)
        out[k] = np.maximum(r, floor_fraction * 0.5 * length.mean())
    return out.reshape(-1)


@dataclass
class Regions:
    """Regions in CSR form, both ways, with shape-matching rest data.

    Attributes:
        omega: Ring size.
        ring_offsets, ring_members: Omega-ring per vertex (shared by all layers), ``[V+1]``, ``[Mr]``.
        region_offsets, region_members: Members of region ``r`` (global particle indices) are
            ``region_members[region_offsets[r]:region_offsets[r+1]]``: the ring on the region's
            layer, then the siblings on the adjacent layers. ``[4V+1]``, ``[M]``.
        sibling_count: Number of sibling members of each region (at the end of its list), ``[4V]``.
        particle_offsets, particle_regions, particle_slots: The transpose: regions containing
            particle ``p`` are ``particle_regions[particle_offsets[p]:particle_offsets[p+1]]`` and
            the matching entry of the region list is ``particle_slots[...]``. ``[4V+1]``, ``[M]``, ``[M]``.
        rest_com: Mass-weighted rest centre of each region [m], ``[4V, 3]``.
        rest_offsets: Rest position minus the region's rest centre per region entry [m], ``[M, 3]``.
        region_mass: Total mass of each region [kg], ``[4V]``.
    """

    omega: int
    ring_offsets: np.ndarray
    ring_members: np.ndarray
    region_offsets: np.ndarray
    region_members: np.ndarray
    sibling_count: np.ndarray
    particle_offsets: np.ndarray
    particle_regions: np.ndarray
    particle_slots: np.ndarray
    rest_com: np.ndarray
    rest_offsets: np.ndarray
    region_mass: np.ndarray

    @property
    def region_count(self) -> int:
        return int(self.region_offsets.size - 1)

    @property
    def mean_region_size(self) -> float:
        return float(self.region_members.size / max(self.region_count, 1))

    def region_of_entry(self) -> np.ndarray:
        """Region index of every entry of ``region_members``, ``[M]``."""
        return np.repeat(np.arange(self.region_count), np.diff(self.region_offsets))


def build_regions(layers: Layers, triangles: np.ndarray, masses: np.ndarray, *, omega: int = 1) -> Regions:
    """Regions of all ``4 V`` particles with their rest data.

    Args:
        layers: The layered rest geometry.
        triangles: Skin topology ``[T, 3]``.
        masses: Particle masses [kg], ``[4 V]``.
        omega: Ring size (1: the vertex and its neighbours).
    """
    v = layers.vertex_count
    n = 4 * v
    masses = np.asarray(masses, dtype=np.float64)
    if masses.shape != (n,):
        raise RigError(f"expected {n} particle masses, got shape {masses.shape}")
    ring_off, ring_mem = omega_rings(triangles, v, omega)
    ring_len = np.diff(ring_off)

    # per region: ring on its own layer + siblings on the adjacent layers
    layer = np.repeat(np.arange(4), v)
    vert = np.tile(np.arange(v), 4)
    sib = (layer > 0).astype(np.int64) + (layer < 3).astype(np.int64)
    sizes = ring_len[vert] + sib
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(sizes, out=offsets[1:])
    members = np.empty(offsets[-1], dtype=np.int64)
    # ring part: for region r = (k, i), entries offsets[r] + [0, ring_len[i])
    reg_of_ring_entry = np.repeat(np.arange(n), ring_len[vert])
    ring_pos = np.arange(reg_of_ring_entry.size) - np.repeat(np.cumsum(ring_len[vert]) - ring_len[vert], ring_len[vert])
    ring_src = ring_off[vert[reg_of_ring_entry]] + ring_pos
    members[offsets[reg_of_ring_entry] + ring_pos] = layer[reg_of_ring_entry] * v + ring_mem[ring_src]
    # siblings: the layer below (k-1) then the layer above (k+1)
    end_ring = offsets[:-1] + ring_len[vert]
    has_lo = layer > 0
    has_hi = layer < 3
    r = np.arange(n)
    members[end_ring[has_lo]] = (r - v)[has_lo]
    members[(end_ring + has_lo)[has_hi]] = (r + v)[has_hi]

    # transpose: particle -> (region, slot)
    entry = np.arange(members.size)
    region_of = np.repeat(r, sizes)
    t = sp.csr_matrix((entry + 1, (members, region_of)), shape=(n, n))
    t.sort_indices()
    p_off = t.indptr.astype(np.int64)
    p_reg = t.indices.astype(np.int64)
    p_slot = (t.data - 1).astype(np.int64)

    x0 = layers.flat()
    m = masses[members]
    region_mass = np.bincount(region_of, m, minlength=n)
    com = np.stack([np.bincount(region_of, m * x0[members, c], minlength=n) for c in range(3)], axis=1)
    com /= region_mass[:, None]
    rest_offsets = x0[members] - com[region_of]
    return Regions(
        omega=int(omega), ring_offsets=ring_off, ring_members=ring_mem,
        region_offsets=offsets, region_members=members, sibling_count=sib,
        particle_offsets=p_off, particle_regions=p_reg, particle_slots=p_slot,
        rest_com=com, rest_offsets=rest_offsets, region_mass=region_mass,
    )
