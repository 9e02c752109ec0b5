"""Small host-side (NumPy) transform helpers shared by the importers, the rig and the skinning
wrappers.

Conventions used everywhere in warpskin:

* 4x4 matrices act on column vectors: ``p_world = M @ [p, 1]``. (glTF stores matrices
  column-major, so a flat glTF matrix is ``np.reshape(m, (4, 4)).T``; USD's ``Gf.Matrix4d`` uses
  row vectors, so ``np.array(gf_matrix).T``.)
* Quaternions are ``(x, y, z, w)``, the order of glTF and of ``wp.quat``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "quat_normalize",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
    "quat_axis_angle",
    "quat_slerp",
    "compose_trs",
    "decompose_trs",
    "blend_skinning_matrices",
    "linear_blend_skin",
    "rigid_fit",
    "local_from_bind",
]


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Normalise quaternions ``(..., 4)``; a zero quaternion becomes the identity."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.where(n > 0.0, q / np.where(n > 0.0, n, 1.0), np.array([0.0, 0.0, 0.0, 1.0]))
    return out


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` in ``(x, y, z, w)`` order."""
    q = quat_normalize(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    m = np.empty(q.shape[:-1] + (3, 3))
    m[..., 0, 0] = 1 - 2 * (y * y + z * z)
    m[..., 0, 1] = 2 * (x * y - z * w)
    m[..., 0, 2] = 2 * (x * z + y * w)
    m[..., 1, 0] = 2 * (x * y + z * w)
    m[..., 1, 1] = 1 - 2 * (x * x + z * z)
    m[..., 1, 2] = 2 * (y * z - x * w)
    m[..., 2, 0] = 2 * (x * z - y * w)
    m[..., 2, 1] = 2 * (y * z + x * w)
    m[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return m


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (``w >= 0``) of rotation matrices ``(..., 3, 3)`` (Shepperd's method)."""
    m = np.asarray(m, dtype=np.float64)
    flat = m.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, r in enumerate(flat):  # joints are few; this is never called per vertex
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        if tr > 0.0:
            s = np.sqrt(tr + 1.0) * 2.0
            out[i] = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
        elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
            s = np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2.0
            out[i] = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
        elif r[1, 1] > r[2, 2]:
            s = np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2.0
            out[i] = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
        else:
            s = np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2.0
            out[i] = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    out = quat_normalize(out)
    out[out[:, 3] < 0.0] *= -1.0
    return out.reshape(m.shape[:-2] + (4,))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions ``(..., 4)`` in (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_axis_angle(axis, degrees: float) -> np.ndarray:
    """The unit quaternion ``(4,)`` in (x, y, z, w) order of a turn by ``degrees`` about ``axis``
    (any non-zero length)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    h = math.radians(degrees) / 2.0
    return np.array([*(a * math.sin(h)), math.cos(h)])


def quat_slerp(q0: np.ndarray, q1: np.ndarray, u: float | np.ndarray) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc (the glTF 2.0 rule), ``(..., 4)``."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    u = np.asarray(u, dtype=np.float64)[..., None] if np.ndim(u) else float(u)
    d = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(d < 0.0, -q1, q1)
    d = np.abs(d)
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    sin_t = np.sin(theta)
    near = sin_t < 1e-8
    safe = np.where(near, 1.0, sin_t)
    a = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / safe)
    b = np.where(near, u, np.sin(u * theta) / safe)
    return quat_normalize(a * q0 + b * q1)


def compose_trs(t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """4x4 matrices ``T * R * S`` (the glTF node order) from translations ``(..., 3)``,
    quaternions ``(..., 4)`` and scales ``(..., 3)``."""
    t = np.asarray(t, dtype=np.float64)
    rot = quat_to_matrix(r)
    m = np.zeros(t.shape[:-1] + (4, 4))
    m[..., :3, :3] = rot * np.asarray(s, dtype=np.float64)[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def decompose_trs(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split affine 4x4 matrices ``(..., 4, 4)`` into translation, rotation quaternion and scale.

    Shear, if any, is dropped (the rotation is the polar factor). A negative determinant is
    carried by a negative x scale.
    """
    m = np.asarray(m, dtype=np.float64)
    t = m[..., :3, 3].copy()
    a = m[..., :3, :3]
    s = np.linalg.norm(a, axis=-2)
    det = np.linalg.det(a)
    s[..., 0] = np.where(det < 0.0, -s[..., 0], s[..., 0])
    safe = np.where(np.abs(s) > 1e-30, s, 1.0)
    rot = a / safe[..., None, :]
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    return t, matrix_to_quat(rot), s


def blend_skinning_matrices(joint_indices: np.ndarray, joint_weights: np.ndarray, skin_matrices: np.ndarray) -> np.ndarray:
    """Per-vertex blended skinning matrices ``sum_k w_k M_{j_k}``, ``[V, 4, 4]`` (host reference).

    Influences whose joint index is out of range count with weight 0 (padding).
    """
    mats = np.asarray(skin_matrices, dtype=np.float64)
    ji = np.asarray(joint_indices)
    valid = (ji >= 0) & (ji < mats.shape[0])
    jw = np.where(valid, np.asarray(joint_weights, dtype=np.float64), 0.0)
    return np.einsum("vk,vkij->vij", jw, mats[np.clip(ji, 0, mats.shape[0] - 1)])


def linear_blend_skin(points: np.ndarray, joint_indices: np.ndarray, joint_weights: np.ndarray,
                      skin_matrices: np.ndarray) -> np.ndarray:
    """Linear blend skinning on the host: ``p_i' = (sum_k w_ik M_{j_ik}) [p_i, 1]``, ``[V, 3]``.

    The NumPy counterpart of the Warp LBS kernel, for one-off poses (initial states, examples,
    per-frame measurements); the Warp kernel is the one to use per frame on many vertices.
    """
    blend = blend_skinning_matrices(joint_indices, joint_weights, skin_matrices)
    return np.einsum("vij,vj->vi", blend[:, :3, :3], np.asarray(points, dtype=np.float64)) + blend[:, :3, 3]


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation ``R`` ``[3, 3]`` and translation ``t`` ``[3]`` minimising ``sum |R a_i + t -
    b_i|^2`` over the rows of ``a`` and ``b`` (``[n, 3]``, matched): Kabsch, without scaling,
    ``det R = +1`` (a reflection is never the answer)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, sign]) @ u.T
    return r, cb - r @ ca


def local_from_bind(bind: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Local transforms ``[J, 4, 4]`` from skeleton-space ones ``bind`` ``[J, 4, 4]`` (``parents``
    ``[J]``, -1 for a root): ``inv(bind[parent]) @ bind[j]``, a root's its own."""
    local = bind.copy()
    child = np.nonzero(parents >= 0)[0]
    if child.size:
        local[child] = np.linalg.inv(bind[parents[child]]) @ bind[child]
    return local
