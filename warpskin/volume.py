"""Volume conservation: one position-based volume constraint per sub-volume.

Deul & Bender 2013, section 4.6, adopting Diziol, Bender & Bayer 2011: every closed sub-volume
``s`` of the skin (:mod:`warpskin.preprocess.sub_volumes`, its surface triangles closed by fans to
kinematic bone centers) carries one constraint

    C_s(x) = V_s(x) - V_s^rest,

solved in its own loop after the elasticity loop, ``N_volume`` iterations, with the PBD
projection of section 4.2.2,

    dp_i = -w_i C_s / (sum_j w_j |grad_j C_s|^2) grad_i C_s,

where ``w_i`` is the inverse mass times a weight scale (0 for colliding particles, so that they
stay where the collision response put them). Fan centers are kinematic (infinite mass): they
take part in ``V_s`` but never move.

The projection is fully parallel, deterministic and free of atomics: the host
(:func:`volume_layout`) lists the unique (vertex, sub-volume) pairs that carry a gradient, each
with its gradient "entries"; one iteration is three kernel launches (pair gradients, per
sub-volume volume and multiplier, per-vertex correction), see :mod:`warpskin.kernels.volume`.

Example:
    >>> from warpskin.scenes.arm import make_arm
    >>> from warpskin.model import SkinModelBuilder
    >>> model = SkinModelBuilder(make_arm(rings=16, segments=12)).finalize("cpu")
    >>> vc = VolumeConstraints(model)
    >>> state, control = model.state(), model.control()
    >>> _ = vc.center_positions(control.skin_matrices, vc.centers)
    >>> weight_scale = wp.ones(model.particle_count, dtype=wp.float32, device=model.device)
    >>> vc.project(state.x, model.particle_inv_mass, weight_scale, vc.centers, iterations=2)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import InputError
from .preprocess.sub_volumes import SubVolumes
from .device import resolve_device
from .kernels import volume as _k

__all__ = ["VolumeLayout", "volume_layout", "VolumeData", "upload_volume_layout", "VolumeConstraints"]

#: Threads per sub-volume in the block reductions (volume, denominator) on CUDA devices; Warp
#: runs tiled kernels with one thread per block on the CPU.
BLOCK_DIM = 256


@dataclass
class VolumeLayout:
    """Index arrays of the atomic-free volume projection (host, all ``int32``).

    ``V`` skin vertices, ``C`` fan centers, ``S`` sub-volumes, ``P`` (vertex, sub-volume) pairs,
    ``E`` gradient entries. Point indices are encoded as in :meth:`SubVolumes.closed_triangles`:
    ``k < V`` is skin vertex ``k``, ``k >= V`` is fan center ``k - V``.

    Attributes:
        vertex_count: ``V``.
        center_count: ``C``.
        closed_offsets: CSR offsets of the closed triangles per sub-volume, ``[S + 1]``.
        closed_triangles: Surface triangles then fans of each sub-volume, encoded points,
            ``[T + F, 3]``, outward wound.
        subvolume_origin: A point of each sub-volume (its first fan center, else the first
            vertex of its first triangle), encoded, ``[S]``: the local origin of its sums.
        pair_vertex: Skin vertex of each pair, ``[P]``; pairs are sorted by (sub-volume,
            vertex).
        pair_subvolume: Sub-volume of each pair, ``[P]``.
        subvolume_pair_offsets: CSR offsets of the (contiguous) pairs of each sub-volume,
            ``[S + 1]``.
        pair_entry_offsets: CSR offsets of each pair's gradient entries, ``[P + 1]``.
        entry_points: The other two points ``(b, c)``, encoded, of a closed triangle
            ``(i, b, c)`` (rotated so the pair's vertex ``i`` comes first) contributing
            ``(p_b x p_c) / 6`` to ``grad_i V_s``, ``[E, 2]``.
        vertex_pair_offsets: CSR offsets of each vertex's pairs, ``[V + 1]``.
        vertex_pairs: Pairs of each vertex (one, or two on a cut loop), ``[P]``.
    """

    vertex_count: int
    center_count: int
    closed_offsets: np.ndarray
    closed_triangles: np.ndarray
    subvolume_origin: np.ndarray
    pair_vertex: np.ndarray
    pair_subvolume: np.ndarray
    subvolume_pair_offsets: np.ndarray
    pair_entry_offsets: np.ndarray
    entry_points: np.ndarray
    vertex_pair_offsets: np.ndarray
    vertex_pairs: np.ndarray

    @property
    def subvolume_count(self) -> int:
        """Number of sub-volumes ``S``."""
        return self.closed_offsets.size - 1

    @property
    def pair_count(self) -> int:
        """Number of (vertex, sub-volume) pairs ``P``."""
        return self.pair_vertex.size

    @property
    def entry_count(self) -> int:
        """Number of gradient entries ``E``."""
        return self.entry_points.shape[0]


def _offsets(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def _int32(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.int64)
    if a.size and a.max() > np.iinfo(np.int32).max:
        raise InputError(f"volume layout: {what} exceeds 32-bit indices; the mesh is too large")
    return np.ascontiguousarray(a, dtype=np.int32)


def volume_layout(subvolumes: SubVolumes) -> VolumeLayout:
    """Pairs, gradient entries and CSR lists of the volume projection (host, vectorised).

    Every closed triangle ``(a, b, c)`` of sub-volume ``s`` contributes ``(p_b x p_c) / 6`` to
    ``grad_a V_s`` and cyclically to ``b`` and ``c``; a fan center gets no entry (it is
    kinematic) but appears as an "other" point of the entries of the fan's two vertices.

    Args:
        subvolumes: The sub-volumes of the skin surface.

    Returns:
        The layout; pairs sorted by (sub-volume, vertex), entries of a pair in triangle order,
        so everything built from it is deterministic.
    """
    sv = subvolumes
    v = int(sv.vertex_count)
    c = int(sv.center_rest.shape[0])
    s_count = sv.count
    tri_off = np.asarray(sv.tri_offsets, dtype=np.int64)
    fan_off = np.asarray(sv.fan_offsets, dtype=np.int64)
    surf = np.asarray(sv.triangles, dtype=np.int64)[np.asarray(sv.tri_indices, dtype=np.int64)].reshape(-1, 3)
    fan = np.asarray(sv.fan_triangles, dtype=np.int64).reshape(-1, 3).copy()
    fan[:, 2] += v
    surf_owner = np.repeat(np.arange(s_count), np.diff(tri_off))
    fan_owner = np.repeat(np.arange(s_count), np.diff(fan_off))

    # closed triangles per sub-volume: its surface triangles, then its fans
    tri_all = np.concatenate([surf, fan])
    owner_all = np.concatenate([surf_owner, fan_owner])
    order = np.argsort(owner_all, kind="stable")
    closed = tri_all[order]
    closed_owner = owner_all[order]
    closed_offsets = _offsets(np.bincount(closed_owner, minlength=s_count))

    # local origin: the first fan center where there is one, else a surface vertex
    nfan = np.diff(fan_off)
    has_fan = nfan > 0
    origin = np.empty(s_count, dtype=np.int64)
    origin[has_fan] = fan[fan_off[:-1][has_fan], 2]
    no_fan = ~has_fan
    origin[no_fan] = surf[tri_off[:-1][no_fan], 0]

    # gradient entries: every rotation (i, b, c) of every closed triangle whose first point is
    # a skin vertex; ordered by (closed triangle, rotation) before the stable sort by pair
    rot = np.stack([closed, closed[:, [1, 2, 0]], closed[:, [2, 0, 1]]], axis=1).reshape(-1, 3)
    rot_owner = np.repeat(closed_owner, 3)
    keep = rot[:, 0] < v
    rot = rot[keep]
    rot_owner = rot_owner[keep]
    key = rot_owner * v + rot[:, 0]
    pair_key, entry_pair = np.unique(key, return_inverse=True)
    entry_order = np.argsort(entry_pair, kind="stable")
    entry_points = rot[entry_order][:, 1:]
    pair_count = pair_key.size
    pair_entry_offsets = _offsets(np.bincount(entry_pair, minlength=pair_count))
    pair_subvolume = pair_key // max(v, 1)
    pair_vertex = pair_key - pair_subvolume * v
    subvolume_pair_offsets = _offsets(np.bincount(pair_subvolume, minlength=s_count))

    # per-vertex CSR over its pairs
    vertex_pairs = np.argsort(pair_vertex, kind="stable")
    vertex_pair_offsets = _offsets(np.bincount(pair_vertex, minlength=v))

    return VolumeLayout(
        vertex_count=v,
        center_count=c,
        closed_offsets=_int32(closed_offsets, "closed triangle count"),
        closed_triangles=_int32(closed, "point index"),
        subvolume_origin=_int32(origin, "point index"),
        pair_vertex=_int32(pair_vertex, "vertex index"),
        pair_subvolume=_int32(pair_subvolume, "sub-volume index"),
        subvolume_pair_offsets=_int32(subvolume_pair_offsets, "pair count"),
        pair_entry_offsets=_int32(pair_entry_offsets, "entry count"),
        entry_points=_int32(entry_points.reshape(-1, 2), "point index"),
        vertex_pair_offsets=_int32(vertex_pair_offsets, "pair count"),
        vertex_pairs=_int32(vertex_pairs, "pair index"),
    )


_VOLUME_ARRAYS = (
    "closed_offsets", "closed_triangles", "subvolume_origin", "pair_vertex", "pair_subvolume", "subvolume_pair_offsets",
    "pair_entry_offsets", "entry_points", "vertex_pair_offsets", "vertex_pairs", "center_rest", "center_joint",
    "rest_volume",
)


class VolumeData:
    """The volume part of a :class:`~warpskin.model.SkinModel`: the :class:`VolumeLayout` as
    device arrays (same names), the fan centres' rest positions ``center_rest`` ``[C]`` and
    joints ``center_joint``, ``rest_volume`` ``[S]`` (float64), and the counts (the host layout
    stays with the model builder, ``builder.volume_layout``)."""


def upload_volume_layout(layout: VolumeLayout, subvolumes: SubVolumes, device) -> VolumeData:
    """One upload of a volume layout and the sub-volumes' kinematic centres."""
    d = VolumeData()
    d.vertex_count = layout.vertex_count
    d.center_count = layout.center_count
    d.subvolume_count = layout.subvolume_count
    d.pair_count = layout.pair_count
    with wp.ScopedDevice(device):
        i32 = lambda a: wp.array(a, dtype=wp.int32)
        d.closed_offsets = i32(layout.closed_offsets)
        d.closed_triangles = wp.array(layout.closed_triangles.reshape(-1, 3), dtype=wp.int32)
        d.subvolume_origin = i32(layout.subvolume_origin)
        d.pair_vertex = i32(layout.pair_vertex)
        d.pair_subvolume = i32(layout.pair_subvolume)
        d.subvolume_pair_offsets = i32(layout.subvolume_pair_offsets)
        d.pair_entry_offsets = i32(layout.pair_entry_offsets)
        d.entry_points = wp.array(layout.entry_points.reshape(-1, 2), dtype=wp.int32)
        d.vertex_pair_offsets = i32(layout.vertex_pair_offsets)
        d.vertex_pairs = i32(layout.vertex_pairs)
        d.center_rest = wp.array(np.asarray(subvolumes.center_rest, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3)
        d.center_joint = i32(np.asarray(subvolumes.center_joint, dtype=np.int32))
        d.rest_volume = wp.array(np.asarray(subvolumes.rest_volume, dtype=np.float64), dtype=wp.float64)
    return d


class VolumeConstraints:
    """Per-sub-volume volume constraints on one Warp device, every array preallocated.

    Args:
        source: A :class:`~warpskin.model.SkinModel` (its uploaded volume layout, on its
            device), or a :class:`~warpskin.preprocess.sub_volumes.SubVolumes` (laid out and
            uploaded here).
        device: Warp device when ``source`` is a ``SubVolumes``; ignored for a model.
        block_dim: Threads per sub-volume in the block reductions on CUDA devices.
        along_normals: Move the skin along the surface part of the gradient (``d_i``, see
            :mod:`warpskin.kernels.volume`) instead of the whole gradient (the paper's
            projection, the default).

    Attributes:
        centers: Fan centers [m], ``[C]`` vec3, a buffer for :meth:`center_positions`.
        rest_volume: ``V_s^rest`` [m^3], ``[S]`` float64.
        subvolume_volume: ``V_s`` [m^3] before the last correction of :meth:`project`, ``[S]``
            float64.
        subvolume_lambda: ``lambda_s`` of the last iteration, ``[S]`` float64.
        pair_gradient: ``grad_i V_s`` [m^2] per pair, ``[P]`` vec3d (last iteration, or
            :meth:`gradients`).
        pair_direction: ``d_i``, along which the correction moves the vertex [m^2], ``[P]``
            vec3d: ``grad_i V_s``, or with ``along_normals`` its surface part (without the
            closing fans' triangles; equal to it off the cut loops).
        pair_weighted_norm: ``w_i grad_i V_s . d_i`` per pair, ``[P]`` float64.

    References:
        Deul, Bender: Physically-based character skinning, VRIPHYS 2013, sections 4.2.2, 4.6.
        Diziol, Bender, Bayer: Robust real-time deformation of incompressible surface meshes,
        SCA 2011.

    Limitations:
        Sub-volumes are coupled only through shared loop vertices and solved Jacobi-style
        (every sub-volume uses the multipliers of the same iteration), so corrections at a loop
        vertex add up; with stiffness 1 this converges quickly in practice but is not a
        simultaneous solve. Fan centers never move, so the volume error of a sub-volume whose
        particles are all pinned stays.
    """

    def __init__(self, source, *, device=None, block_dim: int = BLOCK_DIM, along_normals: bool = False) -> None:
        self.along_normals = bool(along_normals)
        if isinstance(source, SubVolumes):
            self.device = resolve_device(device)
            data = upload_volume_layout(volume_layout(source), source, self.device)
        else:
            if not hasattr(source, "particle_q0") or not hasattr(source, "volume"):
                raise InputError(
                    f"VolumeConstraints needs a SkinModel or SubVolumes, got {type(source).__name__}"
                )
            data = source.volume
            if data is None:
                raise InputError(
                    "the model has no sub-volumes (built with ModelParams(volume=False)); build it with "
                    "volume=True to use volume constraints"
                )
            self.device = source.device
        if int(block_dim) < 1:
            raise InputError(f"block_dim must be a positive thread count, got {block_dim}")
        self.block_dim = int(block_dim)
        self.vertex_count = data.vertex_count
        self.center_count = data.center_count
        self.subvolume_count = data.subvolume_count
        self.pair_count = data.pair_count
        # the static layout (shared with the model), then this object's own buffers
        for name in _VOLUME_ARRAYS:
            setattr(self, name, getattr(data, name))
        with wp.ScopedDevice(self.device):
            self.centers = wp.clone(self.center_rest)
            self.subvolume_volume = wp.zeros(self.subvolume_count, dtype=wp.float64)
            self.subvolume_lambda = wp.zeros(self.subvolume_count, dtype=wp.float64)
            self.pair_gradient = wp.zeros(self.pair_count, dtype=wp.vec3d)
            self.pair_direction = wp.zeros(self.pair_count, dtype=wp.vec3d)
            self.pair_weighted_norm = wp.zeros(self.pair_count, dtype=wp.float64)
            # what the correction launch binds where there is no cap
            self._no_targets = wp.zeros(0, dtype=wp.vec3)
            self._no_radius = wp.zeros(0, dtype=wp.float32)
            self._no_count = wp.zeros(1, dtype=wp.int32)
        # recorded launches per (arrays, stiffness): a simulation alternates two states
        self._cmd_cache: dict = {}

    # ---------------------------------------------------------------------------------------
    # checks (host attributes only: no device synchronisation)
    # ---------------------------------------------------------------------------------------

    def _check(self, name: str, a, dtype, min_len: int, exact: bool = False) -> None:
        if not isinstance(a, wp.array):
            raise InputError(f"VolumeConstraints: {name} must be a wp.array, got {type(a).__name__}")
        if a.dtype != dtype:
            raise InputError(f"VolumeConstraints: {name} must have dtype {dtype.__name__}, got {a.dtype.__name__}")
        n = a.shape[0]
        if (exact and n != min_len) or n < min_len:
            want = f"{min_len}" if exact else f"at least {min_len}"
            raise InputError(f"VolumeConstraints: {name} must have {want} entries, got {n}")
        if a.device != self.device:
            raise InputError(f"VolumeConstraints: {name} lives on {a.device}, the constraints on {self.device}")

    def _check_points(self, x, centers) -> None:
        self._check("x (particle positions)", x, wp.vec3, self.vertex_count)
        self._check("centers", centers, wp.vec3, self.center_count, exact=True)

    # ---------------------------------------------------------------------------------------
    # public
    # ---------------------------------------------------------------------------------------

    def center_positions(self, skin_matrices: wp.array, centers_out: wp.array | None = None) -> wp.array:
        """Kinematic fan centers ``c_k = M_{j_k} @ c_k^rest`` [m] for skinning matrices
        ``M_j = G_j @ inverse_bind_j`` ``[J]`` (mat44). Writes ``centers_out`` ``[C]`` (vec3;
        default :attr:`centers`) and returns it."""
        out = self.centers if centers_out is None else centers_out
        self._check("centers_out", out, wp.vec3, self.center_count, exact=True)
        self._check("skin_matrices", skin_matrices, wp.mat44, 1 if self.center_count else 0)
        wp.launch(
            _k.subvolume_center_kernel,
            dim=self.center_count,
            inputs=[self.center_rest, self.center_joint, skin_matrices],
            outputs=[out],
            device=self.device,
        )
        return out

    def volumes(self, x: wp.array, centers: wp.array, out: wp.array) -> wp.array:
        """Signed volume of every sub-volume [m^3] into ``out`` ``[S]`` (float32), from skin
        positions ``x`` (the first ``V`` entries of a vec3 array) and fan centers ``[C]``."""
        self._check_points(x, centers)
        self._check("out", out, wp.float32, self.subvolume_count, exact=True)
        wp.launch_tiled(
            _k.subvolume_volume_kernel,
            dim=[self.subvolume_count],
            inputs=[x, centers, self.vertex_count, self.closed_offsets, self.closed_triangles, self.subvolume_origin],
            outputs=[out],
            block_dim=self.block_dim,
            device=self.device,
        )
        return out

    def gradients(self, x: wp.array, inv_mass: wp.array, weight_scale: wp.array, centers: wp.array) -> None:
        """Compute :attr:`pair_gradient` (``grad_i V_s`` [m^2]), :attr:`pair_direction` and
        :attr:`pair_weighted_norm` (``w_i grad_i V_s . d_i``) at ``x`` without moving anything
        (one launch)."""
        self._check_all(x, inv_mass, weight_scale, centers)
        self._commands(x, inv_mass, weight_scale, centers, 1.0)[0].launch()

    def project(
        self,
        x: wp.array,
        inv_mass: wp.array,
        weight_scale: wp.array,
        centers: wp.array,
        iterations: int,
        stiffness: float = 1.0,
        cap: tuple | None = None,
    ) -> None:
        """Project the volume constraints ``iterations`` times, in place.

        Each iteration is three launches: pair gradients, then per sub-volume
        ``lambda_s = -k (V_s - V_s^rest) / sum_i w_i |grad_i V_s|^2`` (skipped where the
        denominator vanishes: every weight 0), then per skin vertex
        ``x_i += w_i sum_s lambda_s grad_i V_s``. No allocation and no host synchronisation, so
        the call can be captured in a CUDA graph (:class:`wp.ScopedCapture`).

        Args:
            x: Particle positions [m], vec3, at least ``V`` (the layer-major ``[4V]`` array of
                the model is fine; only the skin layer, particles ``0 .. V-1``, moves).
            inv_mass: Inverse particle masses [1/kg], float32, at least ``V``.
            weight_scale: Per-particle factor on the inverse mass, float32, at least ``V``: 1
                by default, 0 for colliding particles (they stay put).
            centers: Fan centers [m], vec3, ``[C]`` (:meth:`center_positions`); read only.
            iterations: ``N_volume``.
            stiffness: ``k`` in [0, 1]; 1 removes the linearised error in one iteration.
            cap: ``(targets, radius, capped)``: after each iteration every skin vertex ``i``
                is put back within ``radius[i]`` [m] (float32, at least ``V``) of
                ``targets[i]`` [m] (vec3, at least ``V``) where it is farther, each such clamp
                counted in ``capped[0]`` (int32) (the solver's tether; fused into the
                correction launch).
        """
        if int(iterations) != iterations or iterations < 0:
            raise InputError(f"VolumeConstraints.project: iterations must be an integer >= 0, got {iterations}")
        if not (0.0 <= float(stiffness) <= 1.0):
            raise InputError(f"VolumeConstraints.project: stiffness must be in [0, 1], got {stiffness}")
        self._check_all(x, inv_mass, weight_scale, centers)
        if cap is not None:
            if not isinstance(cap, tuple) or len(cap) != 3:
                raise InputError("VolumeConstraints.project: cap must be a tuple (targets, radius, capped)")
            self._check("cap targets", cap[0], wp.vec3, self.vertex_count)
            self._check("cap radius", cap[1], wp.float32, self.vertex_count)
            self._check("cap count", cap[2], wp.int32, 1)
        if iterations == 0 or self.subvolume_count == 0:
            return
        cmds = self._commands(x, inv_mass, weight_scale, centers, float(stiffness), cap)
        for _ in range(int(iterations)):
            for cmd in cmds:
                cmd.launch()

    def _check_all(self, x, inv_mass, weight_scale, centers) -> None:
        self._check_points(x, centers)
        self._check("inv_mass", inv_mass, wp.float32, self.vertex_count)
        self._check("weight_scale", weight_scale, wp.float32, self.vertex_count)

    def _commands(self, x, inv_mass, weight_scale, centers, stiffness: float, cap: tuple | None = None) -> tuple:
        """The three recorded launches of one iteration, bound to these arrays (cached per
        arrays and stiffness: a simulation alternates between two states' positions)."""
        if cap is None:
            cap = (self._no_targets, self._no_radius, self._no_count)
            use_cap = 0
        else:
            use_cap = 1
        arrays = (x, inv_mass, weight_scale, centers, *cap)
        key = (*map(id, arrays), stiffness)  # the cache holds the arrays, so their ids stay theirs
        hit = self._cmd_cache.get(key)
        if hit is not None:
            return hit[1]
        if len(self._cmd_cache) >= 8:
            self._cmd_cache.clear()
        d = self.device
        grad = wp.launch(
            _k.volume_gradient_kernel,
            dim=self.pair_count,
            inputs=[
                x,
                centers,
                inv_mass,
                weight_scale,
                self.vertex_count,
                self.pair_vertex,
                self.pair_subvolume,
                self.pair_entry_offsets,
                self.entry_points,
                self.subvolume_origin,
                int(self.along_normals),
            ],
            outputs=[self.pair_gradient, self.pair_direction, self.pair_weighted_norm],
            device=d,
            record_cmd=True,
        )
        lam = wp.launch_tiled(
            _k.volume_lambda_kernel,
            dim=[self.subvolume_count],
            inputs=[
                x,
                centers,
                self.vertex_count,
                self.closed_offsets,
                self.closed_triangles,
                self.subvolume_origin,
                self.subvolume_pair_offsets,
                self.pair_weighted_norm,
                self.rest_volume,
                stiffness,
            ],
            outputs=[self.subvolume_volume, self.subvolume_lambda],
            block_dim=self.block_dim,
            device=d,
            record_cmd=True,
        )
        corr = wp.launch(
            _k.volume_correction_kernel,
            dim=self.vertex_count,
            inputs=[
                inv_mass,
                weight_scale,
                self.vertex_pair_offsets,
                self.vertex_pairs,
                self.pair_subvolume,
                self.pair_direction,
                self.subvolume_lambda,
                use_cap,
                cap[0],
                cap[1],
            ],
            outputs=[x, cap[2]],
            device=d,
            record_cmd=True,
        )
        self._cmd_cache[key] = (arrays, (grad, lam, corr))
        return grad, lam, corr
