"""Constraints on the written triangles of a refined skin (its chords).

A coarse skin (a game mesh of a few hundred vertices) is simulated on a refined copy
(:func:`warpskin.preprocess.refine.refine_long_edges`) and written with the file's own
triangles, chords of the simulated surface. Shape matching keeps the refined surface's local
shape, but nothing keeps a chord triangle from turning over, or a chord edge from stretching,
where the refined surface between its corners bends (a low-poly paw folding at its wrist). Two
unilateral position-based constraints act on the chords, once per elasticity iteration and
``CHORD_PASSES`` times after the tether and the fail-safe, before the volume loop
(``warpskin.solver``):

* **Orientation**: ``C = n . m - a |n_L| >= 0`` per written triangle, ``n = (x1 - x0) x (x2 - x0)``
  (twice its area along its normal), ``n_L`` the same of its LBS and ``m = n_L / |n_L|``: the
  triangle keeps at least the share ``a`` of LBS's area facing the way LBS faces it, so it never
  turns over against LBS (where LBS itself folds a triangle, a collapsed crease, it stays as LBS
  has it). Gradients: ``dC/dx1 = (x2 - x0) x m``, ``dC/dx2 = m x (x1 - x0)``,
  ``dC/dx0 = -(dC/dx1 + dC/dx2)`` (they sum to zero: the projection keeps the triangle's
  mass-weighted centre).
* **Strain**: every written edge keeps a length within ``[min(l0 / s, l_L), max(s l0, l_L)]``
  (``l0`` at rest, ``l_L`` under LBS, ``s`` the strain limit): a stretch limit as in cloth (Provot
  1995), relative to LBS's own where LBS strains the edge more.

The step's LBS of the skin (``n_L``, ``l_L``) is :func:`~warpskin.kernels.skinning.lbs_kernel`'s,
launched once per step. Both are projected Gauss-Seidel style (atomic adds into the positions; on the CPU the threads run
in order, so the result is deterministic), corrections by inverse mass (the skin's particles).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def chord_orientation_kernel(
    triangles: wp.array2d(dtype=wp.int32),
    lbs: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    share: float,
    # in-out
    x: wp.array(dtype=wp.vec3),
):
    """The orientation constraint of one written triangle (module docstring)."""
    t = wp.tid()
    i0 = triangles[t, 0]
    i1 = triangles[t, 1]
    i2 = triangles[t, 2]
    n_lbs = wp.cross(lbs[i1] - lbs[i0], lbs[i2] - lbs[i0])
    length = wp.length(n_lbs)
    if length <= 0.0:
        return
    m = n_lbs / length
    floor = share * length
    e1 = x[i1] - x[i0]
    e2 = x[i2] - x[i0]
    c = wp.dot(wp.cross(e1, e2), m)
    if c >= floor:
        return
    g1 = wp.cross(e2, m)
    g2 = wp.cross(m, e1)
    g0 = -(g1 + g2)
    w0 = inv_mass[i0]
    w1 = inv_mass[i1]
    w2 = inv_mass[i2]
    den = w0 * wp.dot(g0, g0) + w1 * wp.dot(g1, g1) + w2 * wp.dot(g2, g2)
    if den <= 0.0:
        return
    lam = (floor - c) / den
    wp.atomic_add(x, i0, lam * w0 * g0)
    wp.atomic_add(x, i1, lam * w1 * g1)
    wp.atomic_add(x, i2, lam * w2 * g2)


@wp.kernel
def chord_strain_kernel(
    edges: wp.array2d(dtype=wp.int32),
    rest_length: wp.array(dtype=wp.float32),
    lbs: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    strain: float,
    # in-out
    x: wp.array(dtype=wp.vec3),
):
    """The strain constraint of one written edge (module docstring)."""
    e = wp.tid()
    i = edges[e, 0]
    j = edges[e, 1]
    d = x[i] - x[j]
    length = wp.length(d)
    if length <= 0.0:
        return
    l0 = rest_length[e]
    l_lbs = wp.length(lbs[i] - lbs[j])
    target = wp.clamp(length, wp.min(l0 / strain, l_lbs), wp.max(strain * l0, l_lbs))
    if target == length:
        return
    wi = inv_mass[i]
    wj = inv_mass[j]
    w = wi + wj
    if w <= 0.0:
        return
    c = (length - target) / (w * length)
    wp.atomic_add(x, i, -c * wi * d)
    wp.atomic_add(x, j, c * wj * d)
