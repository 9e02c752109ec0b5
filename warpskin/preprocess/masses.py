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

from ..mesh import mixed_voronoi_areas
from ..rig import RigError
from .layers import LAYER_NAMES, Layers

__all__ = ["mixed_voronoi_areas", "layer_heights", "particle_masses"]


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
