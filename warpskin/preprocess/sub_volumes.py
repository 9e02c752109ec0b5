"""Sub-volumes for volume conservation: the closed surface cut by planes normal to the bones.

Deul & Bender 2013, section 4.6 ("Volume Conservation"): a single volume constraint over the
whole mesh behaves like a balloon (pressing the foot inflates the ears), so the mesh is divided
into sub-volumes, one volume constraint each. "We first define cutting planes along the bones of
the animation skeleton where the sub-volumes shall end. The normal of the plane is defined to be
parallel to the corresponding bone segment. These planes intersect a triangle ring of the mesh
around the bone. We search a connected path of edges in this ring [...]. [...] we search all
triangles of the original mesh that lie between the connected paths of edges defining the
sub-volume by a flood fill algorithm. To close the sub-volumes triangle-fans are created with the
help of the edges in the connected paths. [...] The third point of the triangle is defined by the
center point of the bone that lies on the cutting plane". Planes sit at the bone endpoints; "in
regions where there are several bones we only create one sub-volume" (for the hand the planes
were moved to the middle of the proximal phalanges and of the carpal bone).

Method, per plane (all in rest space, vectorised over the mesh; the loop is over planes):

1. Signed distance ``s = (x - c) . n`` of every vertex to the plane through the bone center
   point ``c`` with unit normal ``n`` (along the bone, pointing away from the root). A triangle
   is *crossed* when its vertices have both signs (``s <= 0`` counts as the proximal side).
2. Crossed triangles form bands, one per intersection curve (connected components over shared
   edges). The proximal boundary of a band (edges between the band and triangles entirely on
   the proximal side) is a set of closed edge paths: a boundary of a triangle set on a closed,
   consistently wound surface, so every vertex has as many outgoing as incoming edges. It is
   split into its connected paths (a proximal island inside the band has its own path).
3. Of the paths, the loop is the one that winds around ``c`` (projected into the plane,
   winding number non-zero) and whose band touches the surface belonging to the bone
   (vertices whose dominant joint is within two bones of the joint carrying ``c``); the
   nearest one (mean distance to ``c``) if several. A plane through the hip therefore never
   cuts the hanging hands: their loops do not surround the hip.
4. After all planes: the loop edges are cut and a flood fill over triangle adjacency (scipy
   connected components) partitions the surface; each component is one sub-volume. Every loop
   must have exactly one sub-volume on each side, two different ones.
5. Each sub-volume is closed by a fan per bounding loop: for a loop edge ``a -> b`` as traversed
   by the sub-volume's own surface triangle, the fan triangle ``(b, a, center)``. The sub-volume
   on the other side traverses the edge as ``b -> a`` and gets ``(a, b, center)``: the fans of a
   loop cancel, so the signed volumes of all sub-volumes sum to the volume of the whole mesh in
   any pose, for any center position.

Fan centers are kinematic: they move rigidly with the joint whose bone carries them,
``c(t) = G_q(t) @ inverse_bind_q @ c_rest`` (:meth:`SubVolumes.center_positions`).

Default planes (:func:`default_plane_positions`). A plane is named by a joint ``j`` with a
parent ``p``; its position ``t`` runs along the bone chain through ``j``: ``t`` in ``[0, 1]``
is on the parent bone ``p -> j`` (``t = 1`` is the joint, normal along ``p -> j``), ``t`` in
``(1, 2]`` is on joint ``j``'s own bone (:func:`~warpskin.preprocess.bones.bone_segments`, normal
along it); values beyond extrapolate along the last segment. The default rule, with
``merge=True``:

* ordinary joint (neither ``j`` nor ``p`` branches): ``t = 1``, the plane at the joint, as in
  the paper (elbow, wrist, knee, ankle, toe, head);
* a branching joint ``j`` (two or more children: chest, pelvis, hand): its parent bone's plane
  moves to the middle, ``t = 0.5`` (the paper's carpal bone), so the joint lies inside one
  sub-volume with all the bones that meet there;
* a child ``j`` of a branching joint (with a single child itself): the short bone from the
  branch to ``j`` (clavicle, hip offset, neck base) points across the body, and a plane normal
  to it would slice the trunk. The plane goes onto ``j``'s own bone instead (``t = 1 + a``,
  normal along the limb), at the smallest ``a`` in :data:`BRANCH_CHILD_OFFSETS`
  (0.05 ... 0.5) whose loop runs only over surface dominated by the branch joint, ``j`` and
  ``j``'s children (it clears the armpit or the crotch); where none does, the plane is left
  out and the limb joins the branch's sub-volume;
* the root has no plane.

Planes named in :attr:`SubVolumeParams.planes` are placed first and must work (else
:class:`~warpskin.rig.RigError`); then the default planes from the root outward. A default
plane whose loop would share edges with or cross an earlier loop, or that finds no loop around
its bone, is left out; :attr:`SubVolumes.notes` says which and why.

With ``merge=False`` every non-root joint gets its plane at ``t = 1`` (the paper's literal
default); on rigs whose branch bones are short and point across the body those planes slice
the trunk (on CesiumMan the two shoulder planes are left out and the pieces are odd).

Results. The procedural arm (shoulder, elbow, wrist along +x): 3 sub-volumes, the upper arm
(root piece, named ``shoulder``), the forearm (``elbow``, between the elbow and wrist planes)
and the hand cap beyond the wrist plane (``wrist``). CesiumMan (19 joints; two branch: the
pelvis root into spine and legs, the chest into neck and arms; hands and toes are leaves): 19
sub-volumes, the pelvis (root piece); the belly, from a plane 5 % up the ``torso_joint_2`` bone
to the chest plane halfway up the same bone; the chest; the neck (plane 5 % up the neck bone);
the head; and per side the upper arm (plane 20 % down the upper arm, below the armpit),
forearm, hand, thigh (plane 5 % down the thigh, below the crotch), shin, foot and toes. Their
signed volumes sum to the mesh volume to ~1e-15 relative, at rest and posed.

Limitations. Loops follow mesh edges, so a loop lies within one edge length on the proximal
side of its plane, not in it (on coarse meshes such as CesiumMan's limbs, 8 edges around,
the cut is visibly jagged). Planes are found in the rest pose only. Choosing the loop by its
winding around the bone center assumes the center lies inside the cross-section; a plane whose
center lies outside the surface is rejected. The surface must be closed, manifold and
consistently wound (:meth:`~warpskin.rig.Rig.require_closed`); on a surface with handles a cut
may not separate and is rejected. The pieces are named and ordered by joint, not by anatomy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from ..mesh import triangle_areas
from ..rig import Rig, RigError, RigWarning
from ..settings import setting
from .bones import Bones, bone_segments, dominant_bone

__all__ = [
    "SubVolumeParams",
    "SubVolumes",
    "build_subvolumes",
    "default_plane_positions",
    "resolve_joint",
]

#: Offsets ``a`` tried (``t = 1 + a``) for the plane of a child of a branching joint.
BRANCH_CHILD_OFFSETS = (0.05, 0.1, 0.2, 0.3, 0.4, 0.5)


@dataclass
class SubVolumeParams:
    """Where the cutting planes go.

    Attributes:
        planes: Overrides of the default rule by joint name (full path or the last path
            component where unique): the plane's position ``t`` (see the module docstring;
            ``1.0`` is the joint itself, normal along the parent bone), or ``None`` to drop the
            plane. Joints not named keep their default.
        merge: Apply the branching rule (one sub-volume where several bones meet). ``False``
            puts a plane at every non-root joint (``t = 1``).
    """

    _section = "subvolumes"

    planes: dict[str, float | None] = setting({}, "table", "cutting planes by joint name: the plane's position t "
                                              "along the parent bone (1: at the joint), or false to drop it")
    merge: bool = True


@dataclass
class SubVolumes:
    """A partition of a closed surface into closed sub-volumes.

    ``S`` sub-volumes, ``C`` cutting planes (one fan center each), ``V`` surface vertices.

    Attributes:
        names: Sub-volume names, ``[S]``: the joint of the plane bounding it on the root side
            (the piece beyond the elbow plane is ``"elbow"``); for the root piece, the joint
            dominating most of its area; ``#2`` etc. where two would share a name. Ordered by
            that joint.
        triangles: The surface triangles (the rig's), ``[T, 3]``.
        tri_offsets: CSR offsets into ``tri_indices``, ``[S + 1]``.
        tri_indices: Surface triangles per sub-volume, ``[T]``: every triangle exactly once.
        fan_offsets: CSR offsets into ``fan_triangles``, ``[S + 1]``.
        fan_triangles: Closing triangles ``(v0, v1, center)``, ``[F, 3]``: two vertex indices
            and an index into the centers, wound so that the closed sub-volume faces outward.
        center_rest: Fan centers at rest [m], ``[C, 3]``: the bone point on each plane.
        center_joint: Joint whose skinning matrix moves each center, ``[C]``.
        loops: Per plane, the loop's vertex indices in order (one closed path; a loop that
            touches itself repeats the vertex; several closed paths are concatenated).
        rest_volume: Signed volume of each sub-volume at rest [m^3], ``[S]`` (see ``measured``).
        plane_joint: Joint naming each plane, ``[C]``.
        plane_t: Position parameter of each plane (module docstring), ``[C]``.
        plane_normal: Unit plane normal at rest, ``[C, 3]``, pointing away from the root.
        plane_sides: Sub-volumes on the proximal (``s <= 0``) and distal side, ``[C, 2]``.
        vertex_count: ``V``.
        notes: How the default rule placed its planes: branch-child planes moved along their
            bone, default planes left out (and why).
    """

    names: list[str]
    triangles: np.ndarray
    tri_offsets: np.ndarray
    tri_indices: np.ndarray
    fan_offsets: np.ndarray
    fan_triangles: np.ndarray
    center_rest: np.ndarray
    center_joint: np.ndarray
    loops: list[np.ndarray]
    rest_volume: np.ndarray
    plane_joint: np.ndarray
    plane_t: np.ndarray
    plane_normal: np.ndarray
    plane_sides: np.ndarray
    vertex_count: int
    notes: list[str] = field(default_factory=list)
    #: ``[S]`` bool: the sub-volumes whose relative volume error is meaningful (a rest volume
    #: above 1e-6 of the total); ``None``: all.
    measured: np.ndarray | None = None

    def __post_init__(self) -> None:
        s = len(self.names)
        self._tri_owner = np.repeat(np.arange(s), np.diff(self.tri_offsets))
        self._fan_owner = np.repeat(np.arange(s), np.diff(self.fan_offsets))

    #: A sub-volume's volume error is measured against its rest volume, or against this share
    #: of the whole rest volume where it is smaller (:attr:`error_scale`).
    SMALL_SHARE = 0.01

    @property
    def count(self) -> int:
        """Number of sub-volumes ``S``."""
        return len(self.names)

    @property
    def error_scale(self) -> np.ndarray:
        """``[S]`` [m^3]: what each sub-volume's volume error is a share of, its rest volume or
        :attr:`SMALL_SHARE` of the whole rest volume where that is larger. A sub-volume of a small
        part of the body (a foot's tip, a finger's end: a few thousandths of the body) is cut from
        its neighbours by planes through the joints, and a change of the surface small against
        the body (a few millimetres where the plane meets it) changes it by a large share of
        itself, in LBS as in the simulation; against a hundredth of the body, a change of that
        size is what it is: small. The checks of a run and its reports measure by this."""
        rest = np.abs(np.asarray(self.rest_volume, dtype=np.float64))
        return np.maximum(rest, self.SMALL_SHARE * float(rest.sum()))

    def volume_errors(self, volumes: np.ndarray) -> np.ndarray:
        """``[..., S]``: each sub-volume's error ``|V - V_rest|`` as a share of its
        :attr:`error_scale` (``volumes`` ``[..., S]`` [m^3]: one frame's or a series'); 0 for the
        sub-volumes that are not :attr:`measured` (they enclose next to nothing)."""
        err = np.abs(np.asarray(volumes, dtype=np.float64) - self.rest_volume) / self.error_scale
        return err if self.measured is None else np.where(self.measured, err, 0.0)

    def triangle_labels(self) -> np.ndarray:
        """Sub-volume of every surface triangle, ``[T]``."""
        lab = np.empty(self.triangles.shape[0], dtype=np.int64)
        lab[self.tri_indices] = self._tri_owner
        return lab

    def closed_triangles(self, s: int) -> np.ndarray:
        """Triangles of closed sub-volume ``s``, ``[n, 3]``, indexing the points followed by
        the centers (``V + center`` for a fan center): surface triangles, then fans."""
        tri = self.triangles[self.tri_indices[self.tri_offsets[s] : self.tri_offsets[s + 1]]]
        fan = self.fan_triangles[self.fan_offsets[s] : self.fan_offsets[s + 1]].copy()
        fan[:, 2] += self.vertex_count
        return np.concatenate([tri, fan])

    def volumes(self, points: np.ndarray, centers: np.ndarray) -> np.ndarray:
        """Signed volumes (divergence theorem) of every sub-volume [m^3], ``[S]``.

        Args:
            points: Surface vertex positions [m], ``[V, 3]``.
            centers: Fan center positions [m], ``[C, 3]`` (:meth:`center_positions`).
        """
        p = np.asarray(points, dtype=np.float64)
        c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        if p.shape != (self.vertex_count, 3):
            raise ValueError(f"points must have shape ({self.vertex_count}, 3), got {p.shape}")
        if c.shape[0] != self.center_rest.shape[0]:
            raise ValueError(f"centers must have shape ({self.center_rest.shape[0]}, 3), got {c.shape}")
        ref = p.mean(axis=0)  # translation invariant; a local origin keeps the sum well conditioned
        p = p - ref
        c = c - ref
        t = self.triangles[self.tri_indices]
        d_surf = np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]]))
        f = self.fan_triangles
        d_fan = np.einsum("ij,ij->i", p[f[:, 0]], np.cross(p[f[:, 1]], c[f[:, 2]]))
        s = self.count
        vol = np.bincount(self._tri_owner, weights=d_surf, minlength=s)
        vol += np.bincount(self._fan_owner, weights=d_fan, minlength=s)
        return vol / 6.0

    def center_positions(self, skin_matrices: np.ndarray) -> np.ndarray:
        """Fan centers moved rigidly with their joints [m], ``[C, 3]``.

        Args:
            skin_matrices: ``G_j @ inverse_bind_j`` per joint, ``[J, 4, 4]``
                (:meth:`~warpskin.rig.Rig.skinning_matrices`).
        """
        m = np.asarray(skin_matrices, dtype=np.float64)[self.center_joint]
        return np.einsum("cij,cj->ci", m[:, :3, :3], self.center_rest) + m[:, :3, 3]


# --------------------------------------------------------------------------------------------
# planes
# --------------------------------------------------------------------------------------------


def resolve_joint(rig: Rig, name: str) -> int:
    """Joint index of ``name``: the full joint name, or the last ``/`` component where unique.

    Raises:
        RigError: no (or more than one) joint matches; the message lists the joints.
    """
    names = rig.skeleton.joint_names
    if name in names:
        return names.index(name)
    hits = [k for k, n in enumerate(names) if n.rsplit("/", 1)[-1] == name]
    if len(hits) == 1:
        return hits[0]
    where = rig.source or rig.name
    short = [n.rsplit("/", 1)[-1] for n in names]
    if hits:
        raise RigError(f"{where}: sub-volume plane {name!r} matches several joints; use the full name")
    raise RigError(f"{where}: sub-volume planes name an unknown joint {name!r}; joints are {short}")


def _short(name: str) -> str:
    return name.rsplit("/", 1)[-1]


def _display(names: list[str], j: int) -> str:
    """The last path component of joint ``j``'s name where unique, else the full name."""
    short = _short(names[j])
    return short if sum(_short(n) == short for n in names) == 1 else names[j]


@dataclass
class _Plane:
    joint: int  # the joint naming the plane
    t: float
    center: np.ndarray  # [3]
    normal: np.ndarray  # [3]
    carrier: int  # joint whose bone carries the center (moves it)


def _plane_geometry(rig: Rig, bones: Bones, j: int, t: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Center [3], unit normal [3] and carrying joint of the plane of joint ``j`` at ``t``."""
    p = int(rig.skeleton.parents[j])
    where = rig.source or rig.name
    name = _display(rig.skeleton.joint_names, j)
    if p < 0:
        raise RigError(f"{where}: joint {name!r} is a root; it has no parent bone to put a sub-volume plane on")
    if not np.isfinite(t):
        raise RigError(f"{where}: sub-volume plane of joint {name!r}: position must be a finite number, got {t}")
    if t <= 1.0:
        a, b, u, carrier = bones.start[p], bones.start[j], t, p
    else:
        a, b, u, carrier = bones.start[j], bones.end[j], t - 1.0, j
    d = b - a
    length = float(np.linalg.norm(d))
    if length <= 1e-9 * max(rig.size(), 1e-30):
        raise RigError(
            f"{where}: sub-volume plane of joint {name!r} at t={t}: the bone "
            f"{_display(rig.skeleton.joint_names, carrier)!r} has no length, so the plane has no normal"
        )
    return a + u * d, d / length, carrier


def default_plane_positions(rig: Rig, *, merge: bool = True) -> dict[int, float]:
    """The default plane of every joint that gets one: ``{joint: t}`` (module docstring).

    Children of branching joints get ``t = 1.0`` here; with ``merge``, :func:`build_subvolumes`
    searches ``t = 1 + a`` along their own bone instead (:data:`BRANCH_CHILD_OFFSETS`).
    """
    parents = rig.skeleton.parents
    nkids = np.bincount(parents[parents >= 0], minlength=rig.joint_count)
    out: dict[int, float] = {}
    for j in range(rig.joint_count):
        p = int(parents[j])
        if p < 0:
            continue
        out[j] = 0.5 if (merge and nkids[j] >= 2) else 1.0
    return out


def _within(parents: np.ndarray, joint: int, hops: int) -> np.ndarray:
    """Joints within ``hops`` bones of ``joint`` in the hierarchy, ``[k]``."""
    n = parents.size
    rows = np.concatenate([np.arange(n)[parents >= 0], parents[parents >= 0]])
    cols = np.concatenate([parents[parents >= 0], np.arange(n)[parents >= 0]])
    adj = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    reach = np.zeros(n, dtype=bool)
    reach[joint] = True
    frontier = reach.copy()
    for _ in range(hops):
        frontier = (adj @ frontier.astype(float)) > 0
        reach |= frontier
    return np.nonzero(reach)[0]


# --------------------------------------------------------------------------------------------
# mesh topology and one cut
# --------------------------------------------------------------------------------------------


class _Topology:
    """Half-edges of a closed, consistently wound triangle mesh: half-edge ``h = 3 f + k`` runs
    from ``T[f, k]`` to ``T[f, (k + 1) % 3]``; ``twin[h]`` runs back in the neighbour."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = vertices
        self.tri = triangles
        v = vertices.shape[0]
        self.src = triangles.ravel()
        self.dst = triangles[:, [1, 2, 0]].ravel()
        self.face = np.repeat(np.arange(triangles.shape[0]), 3)
        key = self.src * v + self.dst
        order = np.argsort(key)
        want = self.dst * v + self.src
        pos = np.clip(np.searchsorted(key[order], want), 0, key.size - 1)
        twin = order[pos]
        if not np.array_equal(key[twin], want):  # require_closed() guarantees this
            raise RigError("sub-volumes: the mesh has edges without an opposite half-edge")
        self.twin = twin
        self.nface = self.face[twin]


@dataclass
class _Cut:
    half_edges: np.ndarray  # proximal-side half-edges (as traversed by the proximal triangle)
    winding: float
    radius: float
    loop_owners: np.ndarray  # dominant joints of the loop vertices


def _cut(topo: _Topology, owner: np.ndarray, plane: _Plane, local: np.ndarray, label: str) -> _Cut:
    """The loop of one plane (steps 1-3 of the module docstring)."""
    x = topo.vertices
    tri = topo.tri
    s = (x - plane.center) @ plane.normal
    pos = s > 0.0
    npos = pos[tri].sum(axis=1)
    crossed = (npos > 0) & (npos < 3)
    if not crossed.any():
        raise RigError(f"{label} cuts nothing: the whole surface lies on one side of it")
    fcount = tri.shape[0]
    ci = np.nonzero(crossed)[0]
    idx = np.full(fcount, -1, dtype=np.int64)
    idx[ci] = np.arange(ci.size)
    h = np.nonzero(crossed[topo.face] & crossed[topo.nface])[0]
    g = sp.csr_matrix((np.ones(h.size), (idx[topo.face[h]], idx[topo.nface[h]])), shape=(ci.size, ci.size))
    ncomp, lab = connected_components(g, directed=False)
    comp = np.full(fcount, -1, dtype=np.int64)
    comp[ci] = lab
    # which bands touch the bone's own surface
    local_tri = np.isin(owner[tri], local).any(axis=1)
    comp_local = np.bincount(lab, weights=local_tri[ci].astype(float), minlength=ncomp) > 0
    if not comp_local.any():
        raise RigError(f"{label} cuts nothing near its bone (it only crosses other parts of the body)")
    # proximal boundary of every band: half-edges of all-proximal triangles facing a band,
    # split into closed paths (connected over shared vertices); a band around a proximal
    # island (a dip below the plane inside the band) has one path per island
    hb = np.nonzero((npos[topo.face] == 0) & crossed[topo.nface])[0]
    if hb.size == 0:
        raise RigError(f"{label} only touches the surface; it cuts nothing near its bone")
    a, b = topo.src[hb], topo.dst[hb]
    verts, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
    m = hb.size
    g = sp.csr_matrix((np.ones(m), (inv[:m], inv[m:])), shape=(verts.size, verts.size))
    npath, vlab = connected_components(g, directed=False)
    path = vlab[inv[:m]]
    path_local = np.bincount(path, weights=comp_local[comp[topo.nface[hb]]].astype(float), minlength=npath) > 0
    # winding number of every path around the center, in the plane
    n = plane.normal
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.5:
        e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    rel = x - plane.center
    ang = np.arctan2(rel @ e2, rel @ e1)
    dang = ang[b] - ang[a]
    dang = (dang + np.pi) % (2.0 * np.pi) - np.pi
    wind = np.bincount(path, weights=dang, minlength=npath) / (2.0 * np.pi)
    radial = np.linalg.norm(rel - np.outer(s, n), axis=1)
    cnt = np.bincount(path, minlength=npath)
    radius = np.bincount(path, weights=radial[a], minlength=npath) / np.maximum(cnt, 1)
    ok = path_local & (np.abs(wind) > 0.5)
    if not ok.any():
        raise RigError(
            f"{label} crosses the surface near its bone, but none of its cuts surrounds the bone "
            "(the bone center lies outside every cross-section); move the plane along the bone"
        )
    best = int(np.argmin(np.where(ok, radius, np.inf)))
    he = hb[path == best]
    return _Cut(
        half_edges=he,
        winding=float(wind[best]),
        radius=float(radius[best]),
        loop_owners=np.unique(owner[topo.src[he]]),
    )


def _order_loop(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Vertices of the closed edge paths ``src[i] -> dst[i]``, in walking order, ``[E]``."""
    out_edges: dict[int, list[int]] = {}
    for i, a in enumerate(src.tolist()):
        out_edges.setdefault(a, []).append(i)
    used = np.zeros(src.size, dtype=bool)
    order: list[int] = []
    for start in range(src.size):  # per-plane loop over its (few hundred at most) loop edges
        if used[start]:
            continue
        e = start
        while not used[e]:
            used[e] = True
            order.append(int(src[e]))
            nxt = [k for k in out_edges[int(dst[e])] if not used[k]]
            if not nxt:
                break
            e = nxt[0]
    return np.asarray(order, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# build
# --------------------------------------------------------------------------------------------


def _partition(
    topo: _Topology, cuts: list[_Cut], labels: list[str], where: str
) -> tuple[int, np.ndarray, np.ndarray]:
    """Flood fill (step 4): cut the loop edges and label the triangles by connected component.

    Returns:
        ``(count, component [T], sides [P, 2])``: the proximal and distal component of every
        loop.

    Raises:
        RigError: two loops share edges or cross, or a loop does not separate the surface;
            the message names the plane (``labels``).
    """
    nhalf = topo.src.size
    edge_of = np.minimum(np.arange(nhalf), topo.twin)  # undirected edge id of each half-edge
    plane_of_edge = np.full(nhalf, -1, dtype=np.int64)
    for k, cut in enumerate(cuts):
        e = edge_of[cut.half_edges]
        clash = plane_of_edge[e]
        if (clash >= 0).any():
            o = int(clash[clash >= 0][0])
            raise RigError(f"{where}: {labels[k]} and {labels[o]} cut along the same mesh edges; move one of them")
        plane_of_edge[e] = k
    is_cut = plane_of_edge[edge_of] >= 0
    h = np.nonzero(~is_cut)[0]
    fcount = topo.tri.shape[0]
    g = sp.csr_matrix((np.ones(h.size), (topo.face[h], topo.nface[h])), shape=(fcount, fcount))
    ncomp, comp = connected_components(g, directed=False)
    sides = np.zeros((len(cuts), 2), dtype=np.int64)
    for k, cut in enumerate(cuts):
        prox = np.unique(comp[topo.face[cut.half_edges]])
        dist = np.unique(comp[topo.nface[cut.half_edges]])
        if prox.size != 1 or dist.size != 1:
            raise RigError(
                f"{where}: {labels[k]}: its loop borders {prox.size} pieces on one side and {dist.size} on the "
                "other: it crosses another plane's loop; move one of the planes"
            )
        if prox[0] == dist[0]:
            raise RigError(
                f"{where}: {labels[k]}: its cut is not a closed loop separating the surface (the same piece "
                "lies on both sides, e.g. the surface has a handle there)"
            )
        sides[k] = (prox[0], dist[0])
    return ncomp, comp, sides


def build_subvolumes(rig: Rig, params: SubVolumeParams | None = None, *, bones: Bones | None = None) -> SubVolumes:
    """Cut the rig's closed rest surface into sub-volumes (Deul & Bender 2013, section 4.6).

    Planes named in ``params.planes`` are placed first and must all work; then the default
    planes in hierarchy order (root side first). A default plane whose loop would share edges
    with or cross an earlier loop, or that finds no cut, is left out and listed in
    :attr:`SubVolumes.notes` (on CesiumMan: none).

    Args:
        rig: A rig with a closed, manifold, consistently wound surface.
        params: Plane placement; the default rule when ``None``.
        bones: Bone segments (:func:`~warpskin.preprocess.bones.bone_segments`), computed when
            ``None``; the joint positions and the own-bone segments come from them.

    Returns:
        The sub-volumes with their closing fans and rest volumes.

    Raises:
        RigError: the surface is open or non-manifold; a plane names an unknown joint or the
            root; a named plane cuts nothing near its bone, no cut surrounds the bone, its loop
            shares edges with or crosses another, or it does not separate the surface; a
            sub-volume is empty (no positive volume at rest). Messages name the joint.
    """
    params = params or SubVolumeParams()
    rig.require_closed()
    where = rig.source or rig.name
    names = rig.skeleton.joint_names
    parents = rig.skeleton.parents
    if bones is None:
        bones = bone_segments(rig)
    if bones.start.shape != (rig.joint_count, 3) or bones.end.shape != (rig.joint_count, 3):
        raise RigError(f"{where}: bone segments of shape {bones.start.shape} do not match {rig.joint_count} joints")
    owner = dominant_bone(rig)
    topo = _Topology(rig.vertices, rig.triangles)
    nkids = np.bincount(parents[parents >= 0], minlength=rig.joint_count)

    # ---- which planes: explicit ones first, then the defaults from the root outward
    defaults = default_plane_positions(rig, merge=params.merge)
    explicit: dict[int, float] = {}
    for key, t in params.planes.items():
        j = resolve_joint(rig, key)
        if parents[j] < 0:
            raise RigError(f"{where}: sub-volume plane {key!r} names the root joint; it has no parent bone")
        defaults.pop(j, None)
        if t is not None:
            explicit[j] = float(t)
    depth = np.zeros(rig.joint_count, dtype=np.int64)
    for j in range(rig.joint_count):  # joints are few; the skeleton has no cycles
        k = int(parents[j])
        while k >= 0:
            depth[j] += 1
            k = int(parents[k])
    requests: list[tuple[int, tuple[float, ...], bool]] = [(j, (t,), True) for j, t in explicit.items()]
    for j in sorted(defaults, key=lambda i: (depth[i], i)):
        t = defaults[j]
        if params.merge and nkids[parents[j]] >= 2 and nkids[j] == 1:
            ts = tuple(1.0 + a for a in BRANCH_CHILD_OFFSETS)  # slide along the own bone
        else:
            ts = (t,)
        requests.append((j, ts, False))

    def label(j: int, t: float) -> str:
        return f"sub-volume plane of joint {_display(names, j)!r} (t={t:g})"

    planes: list[_Plane] = []
    cuts: list[_Cut] = []
    labels: list[str] = []
    notes: list[str] = []
    for j, ts, required in requests:
        accept = np.concatenate([[parents[j], j], np.nonzero(parents == j)[0]])
        placed = False
        errors: list[str] = []
        for t in ts:
            try:
                c, n, q = _plane_geometry(rig, bones, j, t)
                pl = _Plane(j, t, c, n, q)
                cut = _cut(topo, owner, pl, _within(parents, q, 2), f"{where}: {label(j, t)}")
                if len(ts) > 1 and not np.isin(cut.loop_owners, accept).all():
                    others = [_short(names[o]) for o in cut.loop_owners if o not in accept]
                    raise RigError(f"{where}: {label(j, t)}: its loop runs over the surface of {others}")
                _partition(topo, cuts + [cut], labels + [label(j, t)], where)
            except RigError as err:
                if required:
                    raise
                errors.append(str(err))
                continue
            planes.append(pl)
            cuts.append(cut)
            labels.append(label(j, t))
            if len(ts) > 1:
                notes.append(f"plane of joint {_display(names, j)!r} placed at t={t:g} on its own bone")
            placed = True
            break
        if not placed:
            why = errors[-1].removeprefix(where + ": ")
            notes.append(f"default plane of joint {_display(names, j)!r} left out: {why}")

    ncomp, comp, sides = _partition(topo, cuts, labels, where)

    # ---- name and order the pieces: a piece distal to exactly one plane is named after that
    # plane's joint, any other (the root piece) after the joint dominating most of its area
    v = rig.vertices
    tri = rig.triangles
    area = triangle_areas(v, tri)
    jc = rig.joint_count
    share = np.bincount(
        (comp[:, None] * jc + owner[tri]).ravel(), weights=np.repeat(area / 3.0, 3), minlength=ncomp * jc
    ).reshape(ncomp, jc)
    major = np.argmax(share, axis=1)
    distal_of = np.bincount(sides[:, 1], minlength=ncomp) if len(cuts) else np.zeros(ncomp, dtype=np.int64)
    for k, pl in enumerate(planes):
        if distal_of[sides[k, 1]] == 1:
            major[sides[k, 1]] = pl.joint
    order = np.lexsort((-share.sum(axis=1), major))
    rank = np.empty(ncomp, dtype=np.int64)
    rank[order] = np.arange(ncomp)
    comp = rank[comp]
    sides = rank[sides]
    major = major[order]
    sub_names: list[str] = []
    for s in range(ncomp):
        base = _short(names[major[s]])
        k = int(np.count_nonzero(major[:s] == major[s]))
        sub_names.append(base if k == 0 else f"{base}#{k + 1}")

    # ---- fans (step 5) and loops; planes in joint order
    porder = sorted(range(len(planes)), key=lambda k: (planes[k].joint, planes[k].t))
    planes = [planes[k] for k in porder]
    cuts = [cuts[k] for k in porder]
    sides = sides[porder] if len(porder) else sides
    fan_rows: list[np.ndarray] = []
    fan_owner: list[np.ndarray] = []
    loops: list[np.ndarray] = []
    for k, cut in enumerate(cuts):
        he = cut.half_edges
        a, b = topo.src[he], topo.dst[he]
        cidx = np.full(he.size, k, dtype=np.int64)
        fan_rows.append(np.stack([b, a, cidx], axis=1))  # proximal side traverses a -> b
        fan_owner.append(np.full(he.size, sides[k, 0]))
        fan_rows.append(np.stack([a, b, cidx], axis=1))  # distal side traverses b -> a
        fan_owner.append(np.full(he.size, sides[k, 1]))
        loops.append(_order_loop(a, b))

    tri_order = np.argsort(comp, kind="stable")
    tri_offsets = np.concatenate([[0], np.cumsum(np.bincount(comp, minlength=ncomp))])
    if fan_rows:
        fan_all = np.concatenate(fan_rows)
        fown = np.concatenate(fan_owner)
    else:
        fan_all = np.zeros((0, 3), dtype=np.int64)
        fown = np.zeros(0, dtype=np.int64)
    forder = np.argsort(fown, kind="stable")
    fan_offsets = np.concatenate([[0], np.cumsum(np.bincount(fown, minlength=ncomp))])
    centers = np.array([pl.center for pl in planes], dtype=np.float64).reshape(-1, 3)
    result = SubVolumes(
        names=sub_names,
        triangles=tri.copy(),
        tri_offsets=tri_offsets.astype(np.int64),
        tri_indices=tri_order.astype(np.int64),
        fan_offsets=fan_offsets.astype(np.int64),
        fan_triangles=fan_all[forder].astype(np.int64),
        center_rest=centers,
        center_joint=np.array([pl.carrier for pl in planes], dtype=np.int64),
        loops=loops,
        rest_volume=np.zeros(ncomp),
        plane_joint=np.array([pl.joint for pl in planes], dtype=np.int64),
        plane_t=np.array([pl.t for pl in planes], dtype=np.float64),
        plane_normal=np.array([pl.normal for pl in planes], dtype=np.float64).reshape(-1, 3),
        plane_sides=sides,
        vertex_count=rig.vertex_count,
        notes=notes,
    )
    result.rest_volume = result.volumes(rig.vertices, centers)
    total = float(np.abs(result.rest_volume).sum())
    bad = np.nonzero(result.rest_volume <= 1e-6 * total)[0]
    if bad.size:
        # a sub-volume that encloses (next to) nothing: its constraint still holds its rest value,
        # but a relative volume error means nothing for it (the checks and reports skip it)
        import warnings


        s = int(bad[0])
        bounding = [_short(names[planes[k].joint]) for k in range(len(planes)) if s in sides[k]]
        note = (f"{where}: {bad.size} sub-volume(s) enclose almost no volume (e.g. {sub_names[s]!r}, "
                f"{result.rest_volume[s]:.3g} m^3, bounded by the planes of joints {bounding}); their volume is held "
                "but not reported")
        result.notes.append(note)
        warnings.warn(note, RigWarning, stacklevel=2)
    result.measured = result.rest_volume > 1e-6 * total
    return result
