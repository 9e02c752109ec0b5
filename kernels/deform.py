"""The written meshes' deformation: every written point is its own linear blend skinning plus
the physical deformation captured from the simulated surface, blended by its physics weight.

    d_j  = x_j - sum_k w_jk C_{c_jk} [X_j, 1]                   simulated vertex j's displacement
                                                               from its own LBS (X_j: its rest;
                                                               the LBS is the solver tether's
                                                               target, or one launch here)
    p_i' = sum_k v_ik R_{r_ik} [P_i, 1] + phi_i sum_m a_im d_{s_im}

``C`` are the simulated surface's skinning matrices, ``R`` the written meshes' (each mesh its
own inverse binds, stacked ``mesh x joint``), ``P`` the written points in their bind space,
``(s_im, a_im)`` the capture (:mod:`warpskin.capture`: a few simulated vertices per written
point, weights summing to one) and ``phi_i`` in [0, 1] the physics weight. Where the simulation
is at its LBS (``d = 0``) or ``phi = 0`` the written point is exactly its LBS; a written piece
whose points share one capture row moves by one translation on top of its LBS.

Influences and captures are flat arrays with a fixed count per point (weight 0 pads), so every
argument is one-dimensional (Warp's contiguous CPU path). One thread per point, no atomics.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def lbs_flat(p: wp.vec3, row: int, influence_count: int, joint_indices: wp.array(dtype=wp.int32),
             joint_weights: wp.array(dtype=wp.float32), skin_matrices: wp.array(dtype=wp.mat44)) -> wp.vec3:
    """``sum_k w_k M_{j_k} [p, 1]`` over the ``influence_count`` influences of ``row`` (flat
    arrays, weight 0 pads)."""
    acc = wp.vec3(0.0)
    for k in range(influence_count):
        w = joint_weights[row * influence_count + k]
        if w != 0.0:
            acc += w * wp.transform_point(skin_matrices[joint_indices[row * influence_count + k]], p)
    return acc


@wp.kernel
def surface_lbs_kernel(
    rest: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    # output
    lbs: wp.array(dtype=wp.vec3),
):
    """``LBS(X_j)`` of every simulated surface vertex ``j`` (where the solver's tether targets
    are not at hand)."""
    j = wp.tid()
    lbs[j] = lbs_flat(rest[j], j, influence_count, joint_indices, joint_weights, skin_matrices)


@wp.kernel
def deform_from_targets_kernel(
    bind_points: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    capture_count: int,
    capture_indices: wp.array(dtype=wp.int32),
    capture_weights: wp.array(dtype=wp.float32),
    physics_weight: wp.array(dtype=wp.float32),
    x: wp.array(dtype=wp.vec3),
    surface_lbs: wp.array(dtype=wp.vec3),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """``p_i' = LBS(P_i) + phi_i sum_m a_im (x_{s_im} - surface_lbs_{s_im})`` (``joint_indices``
    already offset into the stacked per-mesh matrices; ``surface_lbs``: the simulated surface's
    LBS, the solver tether's targets of the step or :func:`surface_lbs_kernel`'s)."""
    i = wp.tid()
    acc = lbs_flat(bind_points[i], i, influence_count, joint_indices, joint_weights, skin_matrices)
    phi = physics_weight[i]
    if phi > 0.0:
        d = wp.vec3(0.0)
        for m in range(capture_count):
            a = capture_weights[i * capture_count + m]
            if a != 0.0:
                j = capture_indices[i * capture_count + m]
                d += a * (x[j] - surface_lbs[j])
        acc += phi * d
    out[i] = acc


@wp.kernel
def inward_rays_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    start: float,
    max_dist: float,
    tilt: float,
    # output
    hits: wp.array(dtype=wp.float32),
):
    """Distances along five rays into the surface from every point (the shape diameter there):
    one along the inward normal, four tilted by ``tilt`` radians about it, each to where it
    leaves the solid it starts in (surfaces entered and left on the way, of pieces that overlap
    this one, are counted through); each
    starts ``start`` inside the point (past its own faces) and reports ``max_dist`` where it
    leaves through nothing (an open piece)."""
    i = wp.tid()
    n = normals[i]
    helper = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        helper = wp.vec3(0.0, 1.0, 0.0)
    u = wp.normalize(wp.cross(n, helper))
    v = wp.cross(n, u)
    o = points[i] - start * n
    c = wp.cos(tilt)
    s = wp.sin(tilt)
    for r in range(5):
        d = -n
        if r == 1:
            d = -c * n + s * u
        elif r == 2:
            d = -c * n - s * u
        elif r == 3:
            d = -c * n + s * v
        elif r == 4:
            d = -c * n - s * v
        d = wp.normalize(d)
        # where the ray leaves the solid it starts in: it counts the surfaces it enters (front
        # faces) and leaves (back faces), so passing through another piece that overlaps this
        # one (a ball joint inside a tube's end) does not end the part
        travelled = float(0.0)
        result = max_dist
        depth = int(1)
        for _ in range(12):
            q = wp.mesh_query_ray(mesh, o + travelled * d, d, max_dist - travelled)
            if not q.result:
                break
            travelled += q.t
            if q.sign < 0.0:
                depth -= 1
            else:
                depth += 1
            if depth == 0:
                result = travelled + start
                break
            travelled += start
        hits[i * 5 + r] = result
