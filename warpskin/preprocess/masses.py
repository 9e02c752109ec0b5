"""Particle masses: mixed Voronoi area times layer height times density.

Deul & Bender 2013, section 3: "the area A represented by a particle in its corresponding layer
is determined by using Voronoi regions and a special treatment for obtuse triangles [MDSB03].
Then, the half distance to each coupled layer is summed up to get the height h. Finally, we
approximate the volume by V = A h and compute the mass by m = V rho."

Mixed area (Meyer, Desbrun, Schroeder, Barr 2003, Fig. 4): for each triangle and corner P,
* non-obtuse triangle: the Voronoi part ``(|PR|^2 cot Q + |PQ|^2 cot R) / 8``;
* obtuse triangle: ``area / 2`` for the obtuse corner, ``area / 4`` for the two others.
The corner areas of a triangle sum to its area, so the vertex areas of a mesh sum to its area.
"""

from __future__ import annotations

import numpy as np

from ..rig import RigError
from .layers import LAYER_NAMES, Layers

__all__ = ["mixed_voronoi_areas", "layer_heights", "particle_masses"]


def mixed_voronoi_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Mixed Voronoi area of every vertex [m^2], ``[V]``."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    p = v[t]  # [T, 3 corners, 3]
    # edge opposite each corner c: from corner c+1 to c+2
    e = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], axis=1)
    len2 = np.einsum("tci,tci->tc", e, e)
    cross = np.cross(e[:, 1], e[:, 2])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    # cosine of the angle at corner c: between -e[c+2] and e[c+1]
    dots = np.stack(
        [
            -np.einsum("ti,ti->t", e[:, 2], e[:, 1]),
            -np.einsum("ti,ti->t", e[:, 0], e[:, 2]),
            -np.einsum("ti,ti->t", e[:, 1], e[:, 0]),
        ],
        axis=1,
    )
    safe = np.where(area > 0, 2.0 * area, 1.0)
    cot = dots / safe[:, None]  # cot(angle) = cos / sin = dot / |cross|
    # Voronoi corner area of corner c: (|e_{c+1}|^2 cot(c+1) + |e_{c+2}|^2 cot(c+2)) / 8, where e_k
    # is the edge opposite corner k (the edges incident to c are e_{c+1} and e_{c+2}).
    voronoi = np.empty_like(len2)
    for c in range(3):
        c1, c2 = (c + 1) % 3, (c + 2) % 3
        voronoi[:, c] = (len2[:, c1] * cot[:, c1] + len2[:, c2] * cot[:, c2]) / 8.0
    obtuse_corner = dots < 0.0
    obtuse = obtuse_corner.any(axis=1)
    corner = np.where(
        obtuse[:, None],
        np.where(obtuse_corner, area[:, None] / 2.0, area[:, None] / 4.0),
        voronoi,
    )
    out = np.zeros(v.shape[0])
    np.add.at(out, t.ravel(), corner.ravel())
    return out


def layer_heights(layers: Layers) -> np.ndarray:
    """Height of every particle [m], ``[4, V]``: half the distance to each coupled (adjacent)
    layer's sibling, summed."""
    x = layers.positions
    gap = np.linalg.norm(x[1:] - x[:-1], axis=2)  # [3, V]: skin-fat, fat-muscle, muscle-bone
    h = np.zeros(x.shape[:2])
    h[:-1] += 0.5 * gap
    h[1:] += 0.5 * gap
    return h


def particle_masses(layers: Layers, triangles: np.ndarray, *, density: float = 1000.0, where: str = "model") -> np.ndarray:
    """Masses [kg] of all particles, layer-major ``[4 V]``.

    Raises:
        RigError: non-positive density, or particles with zero mass (named), e.g. a vertex on
            its bone's center line or an isolated vertex.
    """
    if not (np.isfinite(density) and density > 0):
        raise RigError(f"{where}: density must be a positive number [kg/m^3], got {density}")
    h = layer_heights(layers)
    m = np.stack([mixed_voronoi_areas(layers.positions[k], triangles) for k in range(4)]) * h * density
    bad = np.nonzero(~(m > 0))
    if bad[0].size:
        k, i = int(bad[0][0]), int(bad[1][0])
        raise RigError(
            f"{where}: {bad[0].size} particles have zero mass, e.g. vertex {i} on the {LAYER_NAMES[k]} layer "
            "(zero area or zero layer height: the vertex lies on its bone's center line or belongs to no triangle)"
        )
    return m.reshape(-1)
