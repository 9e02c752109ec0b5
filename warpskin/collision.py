"""Self-collision of the skin layer: the launch wrappers of its kernels (detection,
:mod:`warpskin.kernels.contact_detection`; projection, friction and restitution,
:mod:`warpskin.kernels.contact_projection`; the fail-safe, :mod:`warpskin.kernels.fail_safe`;
what they share, :mod:`warpskin.kernels.collision`).

Only the skin layer collides with itself, as in the paper: the inner layers follow the skin by
shape matching (their regions contain the skin particles' siblings), so they are kept apart
indirectly; at a strongly bent joint the bone layers, pinned to LBS, still interpenetrate, which
nobody sees.

The topology (edges, their triangles, rigid vertices) is made on the host by the model builder
(:func:`collision_topology`) and uploaded with the model (:func:`upload_collision`); the
contact buffers are a :class:`~warpskin.model.Contacts` (``model.contacts()``).

Per step (Algorithm 1): :meth:`SelfCollision.detect` once on the predicted positions (BVH over
the skin triangles' swept boxes, refit every step; one query per triangle finds the
point-triangle and edge-edge candidates of the vertices and edges it owns, and lists the nearby
triangle pairs that the fail-safe's first round tests), :meth:`project` inside every elasticity
iteration, :meth:`volume_weights` before the volume loop (colliding particles get 5 % of their
weight: they move little, so the volume loop does not push them back into the contact) and
:meth:`friction_restitution` after the velocity update. Detection fills the pre-sized contact
buffers; if a step finds more candidates than fit, the contacts' overflow flag is raised and
the frame runner grows them and repeats the frame, so no contact is ever dropped silently.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import InputError
from .params import CollisionParams
from .kernels import collision as k
from .kernels import contact_detection as kd
from .kernels import contact_projection as kp
from .kernels import fail_safe as kf

__all__ = ["CollisionParams", "CollisionTopology", "collision_topology", "upload_collision", "SelfCollision", "skin_edges",
           "mean_edge", "triangle_ownership"]


def skin_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges ``[E, 2]`` and each triangle's three edge indices ``[T, 3]``."""
    t = np.asarray(triangles, dtype=np.int64)
    directed = np.stack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=1).reshape(-1, 2)
    und = np.sort(directed, axis=1)
    edges, inverse = np.unique(und, axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


def mean_edge(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """The mean length [m] of a mesh's unique edges (:func:`skin_edges`)."""
    edges, _ = skin_edges(triangles)
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1).mean())


@dataclass
class CollisionTopology:
    """Host topology of the skin self-collision (made by the model builder).

    Attributes:
        edges: Unique skin edges ``[E, 2]``.
        tri_edges: The three edge indices of every triangle ``[T, 3]``.
        edge_owner: First triangle of every edge ``[E]`` (an edge-edge pair is listed once,
            through it).
        dominant_joint: Joint of each vertex's largest weight ``[V]``.
        dominant_weight: That weight ``[V]``.
        mean_edge: Mean skin edge length [m].
        diagonal: Rest bounding-box diagonal [m].
        group: ``[V]`` each vertex's collision group (a piece of the surface, or a piece's cap;
            :class:`~warpskin.preprocess.pieces.SurfaceGroups`), ``None``: one group.
        group_pairs: ``[G, G]`` bool, the pairs of groups that never collide, ``None``: none.
        fail_safe_triangles: ``[W, 3]`` the triangles the fail-safe tests, where they are not
            the rig's written ones (a surface of pieces: its caps left out), else ``None``.
        group_owner: ``[G]`` the piece of every group, ``None``: one piece.
    """

    edges: np.ndarray
    tri_edges: np.ndarray
    edge_owner: np.ndarray
    dominant_joint: np.ndarray
    dominant_weight: np.ndarray
    mean_edge: float
    diagonal: float
    group: np.ndarray | None = None
    group_pairs: np.ndarray | None = None
    fail_safe_triangles: np.ndarray | None = None
    group_owner: np.ndarray | None = None


def collision_topology(rig) -> CollisionTopology:
    """The :class:`CollisionTopology` of a rig's closed skin surface (with the collision groups
    of a surface made of several pieces, ``rig.surface_groups``, where it has them)."""
    tris = rig.triangles
    edges, tri_edges = skin_edges(tris)
    owner = np.full(edges.shape[0], tris.shape[0], dtype=np.int64)  # first triangle of each edge
    np.minimum.at(owner, tri_edges.ravel(), np.repeat(np.arange(tris.shape[0]), 3))
    w = rig.joint_weights
    rows = np.arange(len(w))
    best = np.argmax(w, axis=1)
    groups = getattr(rig, "surface_groups", None)
    fail_safe = None
    if groups is not None:  # the fail-safe keeps what is written from crossing: the caps are not
        n_pieces = len(groups.names)
        g = np.asarray(groups.group)
        cap = (g >= n_pieces) & (g < 2 * n_pieces)
        out = np.asarray(rig.output_triangles)
        fail_safe = out[~cap[out].any(axis=1)]
    return CollisionTopology(
        edges=edges,
        tri_edges=tri_edges,
        edge_owner=owner,
        dominant_joint=rig.joint_indices[rows, best],
        dominant_weight=w[rows, best],
        mean_edge=mean_edge(rig.vertices, tris),
        diagonal=rig.size(),
        group=None if groups is None else np.asarray(groups.group, dtype=np.int64),
        group_pairs=None if groups is None else np.asarray(groups.excluded, dtype=bool),
        fail_safe_triangles=fail_safe,
        group_owner=None if groups is None or groups.owner is None else np.asarray(groups.owner, dtype=np.int64),
    )


def triangle_ownership(triangles: np.ndarray, tri_edges: np.ndarray, edge_owner: np.ndarray) -> np.ndarray:
    """What each triangle owns for the one-query-per-triangle detection: bit ``k`` (0-2) its
    corner ``k`` (a vertex is owned by the first triangle that has it), bit ``3 + k`` its edge
    ``k`` (corner ``k`` to ``k + 1``; ``edge_owner``). Every vertex and edge has one owner."""
    t = np.asarray(triangles, dtype=np.int64)
    n_tri = t.shape[0]
    vertex_owner = np.full(int(t.max()) + 1, n_tri, dtype=np.int64)
    np.minimum.at(vertex_owner, t.ravel(), np.repeat(np.arange(n_tri), 3))
    rows = np.arange(n_tri)[:, None]
    corner = vertex_owner[t] == rows
    edge = np.asarray(edge_owner)[np.asarray(tri_edges)] == rows
    bits = (corner * (1 << np.arange(3))).sum(axis=1) + (edge * (8 << np.arange(3))).sum(axis=1)
    return bits.astype(np.int32)


class CollisionData:
    """The collision part of a :class:`~warpskin.model.SkinModel`: device topology and the
    contact scalars of its :class:`CollisionParams`.

    Attributes:
        edge_indices ``[E, 2]``, tri_edges ``[T, 3]``, edge_owner ``[E]``, rigid_bone ``[V]``
        (the bone a vertex moves rigidly with, else -1), group ``[V]`` and group_pairs ``[G, G]``
        (the collision groups and the pairs that never collide), rest_lowers/rest_uppers ``[T]`` (rest
        triangle boxes); thickness [m], radius [m] (search radius), rest_gap [m], fold_cos,
        friction, restitution, passes, rebuild_spread, fail_safe_rounds;
        edge_count, triangle_count; diagonal [m]; characters: each character's contact
        scalars (:func:`contact_scalars`; one for a model, one each for a batched model's).
    """


def contact_scalars(topo: CollisionTopology, params: CollisionParams) -> dict:
    """One character's contact scalars: ``thickness`` (``params.thickness``, else 0.15 x its
    mean edge), the search ``radius`` and ``rest_gap`` [m], ``fold_cos``, ``friction``,
    ``restitution``, ``volume_weight``, ``rebuild_spread``: what :class:`SelfCollision` gives
    that character's vertices."""
    thickness = float(params.thickness) if params.thickness is not None else 0.15 * topo.mean_edge
    radius = thickness * float(params.detection_margin)
    return {"thickness": thickness, "radius": radius, "rest_gap": radius * float(params.rest_gap_margin),
            "fold_cos": float(params.fold_cos), "friction": float(params.friction),
            "restitution": float(params.restitution), "volume_weight": float(params.volume_weight),
            "rebuild_spread": float(params.rebuild_spread)}


def upload_collision(topo: CollisionTopology, rig, params: CollisionParams, device) -> CollisionData:
    """Upload a :class:`CollisionTopology` with the scalars of ``params`` (host work in NumPy
    first, then one upload per array)."""
    params.check()
    d = CollisionData()
    tris = rig.triangles
    one = contact_scalars(topo, params)
    d.thickness, d.radius, d.rest_gap = one["thickness"], one["radius"], one["rest_gap"]
    d.fold_cos, d.friction, d.restitution = one["fold_cos"], one["friction"], one["restitution"]
    d.passes = int(params.passes)
    d.volume_weight, d.rebuild_spread = one["volume_weight"], one["rebuild_spread"]
    d.fail_safe_rounds = int(params.fail_safe_rounds)
    d.diagonal = topo.diagonal
    # the scalars per character (one here; a batched model's, one each: warpskin.batch_model)
    d.characters = [one]
    d.edge_count = int(topo.edges.shape[0])
    d.triangle_count = int(tris.shape[0])
    rigid = np.where(topo.dominant_weight >= params.rigid_weight, topo.dominant_joint, -1)
    with wp.ScopedDevice(device):
        d.edge_indices = wp.array(topo.edges.astype(np.int32), dtype=wp.int32)
        d.tri_edges = wp.array(topo.tri_edges.astype(np.int32), dtype=wp.int32)
        d.edge_owner = wp.array(topo.edge_owner.astype(np.int32), dtype=wp.int32)
        d.tri_owns = wp.array(triangle_ownership(tris, topo.tri_edges, topo.edge_owner), dtype=wp.int32)
        d.rigid_bone = wp.array(rigid.astype(np.int32), dtype=wp.int32)
        group = np.zeros(len(rigid), dtype=np.int32) if topo.group is None else np.asarray(topo.group, dtype=np.int32)
        pairs = np.zeros((1, 1), dtype=np.int32) if topo.group_pairs is None else \
            np.asarray(topo.group_pairs, dtype=np.int32)
        d.group = wp.array(group, dtype=wp.int32)
        d.group_pairs = wp.array(pairs, dtype=wp.int32)
        # the fail-safe keeps to each piece's own crossings (two pieces' are the contacts' part)
        if topo.group_owner is None:
            d.fail_safe_pairs = wp.zeros((1, 1), dtype=wp.int32)
        else:
            o = np.asarray(topo.group_owner)
            d.fail_safe_pairs = wp.array((o[:, None] != o[None, :]).astype(np.int32), dtype=wp.int32)
        d.rest_lowers = wp.array(rig.vertices[tris].min(axis=1).astype(np.float32), dtype=wp.vec3)
        d.rest_uppers = wp.array(rig.vertices[tris].max(axis=1).astype(np.float32), dtype=wp.vec3)
        # the fail-safe tests the surface as written: the file's triangles of a refined skin
        # (chords of the simulated one: RobotExpressive's refined hand folds within them,
        # invisibly, and putting those folds back crossed the chords), else the skin's own
        out = np.asarray(rig.output_triangles if topo.fail_safe_triangles is None else topo.fail_safe_triangles)
        d.output_triangles = None if out.shape == tris.shape and np.array_equal(out, tris) else \
            wp.array(out.astype(np.int32), dtype=wp.int32)
        d.output_triangle_count = int(out.shape[0])
    return d


#: The pass after the volume loop looks for new intersections only from triangles with a vertex
#: that moved farther than this share of the contact thickness (see :meth:`SelfCollision.fail_safe`).
MIN_MOVE_SHARE = 1.0e-2

#: A triangle escapes the detection's pair list when its fail-safe box reaches farther than this
#: many search radii beyond its swept box; the list holds the pairs whose swept boxes are within
#: twice that of each other (at most 0.5: the tree returns the pairs within one radius).
ESCAPE_REACH = 0.25

#: Contact slots per thread of the contact kernels, and slots of the pair list or triangles per
#: thread of the fail-safe's kernels, on the CPU, whose threads run one after another (see
#: :func:`warpskin.kernels.collision.contact_range`); one on a GPU.
CPU_CONTACT_CHUNK = 64


def _trees(lowers: wp.array, uppers: wp.array, ranges: list[tuple[int, int]]) -> tuple:
    """One BVH per ``(first, count)`` range of the triangle boxes ``lowers``/``uppers`` (over
    views of them, so a refit after the boxes change sees the new ones), and the kernels' view
    of them: ``(bvhs, tree ids [K] uint64, each triangle's tree [T] int32, each tree's first
    triangle [K] int32)``."""
    bvhs = [wp.Bvh(lowers[t0:t0 + tn], uppers[t0:t0 + tn]) for t0, tn in ranges]
    tri_tree = np.zeros(lowers.shape[0], dtype=np.int32)
    for tree, (t0, tn) in enumerate(ranges):
        tri_tree[t0:t0 + tn] = tree
    return (bvhs, wp.array(np.array([b.id for b in bvhs], dtype=np.uint64), dtype=wp.uint64),
            wp.array(tri_tree, dtype=wp.int32), wp.array(np.array([t0 for t0, _ in ranges], dtype=np.int32), dtype=wp.int32))


class SelfCollision:
    """Skin self-collision of one model: the BVH and the scratch buffers (allocated here), the
    launches of detection, projection, volume weights and friction; the pairs go into a
    :class:`~warpskin.model.Contacts`."""

    def __init__(self, model) -> None:
        if model.collision is None:
            raise InputError("the model was built with [collision] enabled = false; it has no collision data")
        self.model = model
        self.data = c = model.collision
        self.device = model.device
        v = model.vertex_count
        # one tree per character of a batched model (over its own triangles: contacts stay
        # within a character, found in the order it finds them alone), else one
        ranges = list(getattr(model, "characters", None) or [])
        self._ranges = [(r.vertex_start, r.vertex_count, r.triangle_start, r.triangle_count) for r in ranges] \
            or [(0, v, 0, int(c.triangle_count))]
        # the written triangles of each (the fail-safe's; a refined skin's are the loaded mesh's)
        self._written = [(r.written_start, r.written_count) for r in ranges] or [(0, int(c.output_triangle_count))]
        self._diagonals = list(getattr(model, "character_diagonals", None) or [c.diagonal])
        with wp.ScopedDevice(self.device):
            self.lowers = wp.clone(c.rest_lowers)
            self.uppers = wp.clone(c.rest_uppers)
            self.bvhs, self.trees, self.tri_tree, self.tree_start = _trees(
                self.lowers, self.uppers, [(t0, tn) for _, _, t0, tn in self._ranges])
            vertex_tree = np.zeros(v, dtype=np.int32)
            for tree, (v0, vn, _, _) in enumerate(self._ranges):
                vertex_tree[v0:v0 + vn] = tree
            self.vertex_tree = wp.array(vertex_tree, dtype=wp.int32)
            # each character's scalars, and what the kernels derive from them (as one would)
            chars = self._chars = list(c.characters)
            if len(chars) != len(self._ranges):
                raise InputError(f"collision data for {len(chars)} characters on a model of {len(self._ranges)}")
            structs = []
            for ch in chars:
                reach = ESCAPE_REACH * ch["radius"]
                s = k.CollisionScalars()
                s.thickness, s.radius, s.rest_gap, s.fold_cos = ch["thickness"], ch["radius"], ch["rest_gap"], ch["fold_cos"]
                s.friction, s.restitution, s.volume_weight = ch["friction"], ch["restitution"], ch["volume_weight"]
                s.list_gap, s.escape_margin, s.fail_safe_pad = 2.0 * reach, ch["radius"] - reach, 1.0e-3 * ch["thickness"]
                structs.append(s)
            self.params = wp.array(structs, dtype=k.CollisionScalars)
            self._radius_pads = wp.array(np.array([ch["radius"] for ch in chars], dtype=np.float32), dtype=wp.float32)
            thickness_pads = wp.array(np.array([ch["thickness"] for ch in chars], dtype=np.float32), dtype=wp.float32)
            #: the fail-safe's ``min_move`` the solver uses: a hundredth of each character's thickness
            self.default_min_move = tuple(MIN_MOVE_SHARE * ch["thickness"] for ch in chars)
            self._min_move = wp.array(np.array(self.default_min_move, dtype=np.float32), dtype=wp.float32)
            # another min_move (a caller's own, outside a captured graph): an array of its own, so
            # that graphs captured with the solver's keep reading the solver's
            self._other_min_move = wp.zeros(len(chars), dtype=wp.float32)
            #: what never collides (rigid neighbourhoods, pieces apart at rest), one struct
            self.filter = k.CollisionFilter()
            self.filter.rigid_bone, self.filter.group, self.filter.group_pairs = c.rigid_bone, c.group, c.group_pairs
            self.filter.fail_safe_pairs = c.fail_safe_pairs
            self.vertex_normals = wp.zeros(v, dtype=wp.vec3)
            self.delta = wp.zeros(v, dtype=wp.vec3)
            self.delta_count = wp.zeros(v, dtype=wp.int32)
            self.revert = wp.zeros(v, dtype=wp.int32)
            self.moved = wp.zeros(v, dtype=wp.int32)
            self.carried = wp.zeros(v, dtype=wp.int32)
            # running count of the pairs the fail-safe found (read and reset by the caller)
            self.fail_safe_pairs = wp.zeros(1, dtype=wp.int32)
            # per fail-safe round, whether it put a vertex back (a round after one that did not is skipped)
            self.reverted = wp.zeros(max(c.fail_safe_rounds, 1), dtype=wp.int32)
        # the skin the tree was built for (host, read once: the rest skin the model uploaded)
        self._built_at = model.particle_q0.numpy()[:v].astype(np.float64)
        self.rebuilds = 0
        self.thickness, self.radius, self.rest_gap = c.thickness, c.radius, c.rest_gap
        # the fail-safe carries a skin vertex by its bone-layer particle (layer-major: + 3 V),
        # on the written triangles (a tree of their own where the skin was refined)
        self._carry = 3 * v if model.particle_count >= 4 * v else 0
        # the fail-safe's own tree (the detection's keeps its boxes for the escape test); on a
        # skin written as simulated, its first round takes the detection's pair list
        self._fs_tris = model.tri_indices if c.output_triangles is None else c.output_triangles
        self._listed = c.output_triangles is None
        self.chunk = CPU_CONTACT_CHUNK if wp.get_device(self.device).is_cpu else 1
        with wp.ScopedDevice(self.device):
            self._fs_lowers = wp.zeros(c.output_triangle_count, dtype=wp.vec3)
            self._fs_uppers = wp.zeros(c.output_triangle_count, dtype=wp.vec3)
            self.escaped = wp.zeros(c.output_triangle_count, dtype=wp.int32)
            wp.launch(kd.triangle_bounds_kernel, dim=c.output_triangle_count,
                      inputs=[model.particle_q0, model.particle_q0, self._fs_tris, thickness_pads, self.vertex_tree],
                      outputs=[self._fs_lowers, self._fs_uppers])
            # one tree per character over its written triangles
            self._fs_bvhs, self._fs_trees, self._fs_tri_tree, self._fs_tree_start = _trees(
                self._fs_lowers, self._fs_uppers, self._written)

    def maybe_rebuild(self, skin: np.ndarray) -> bool:
        """Host check between frames (never inside a captured graph): rebuild the BVH in place
        when the skin positions ``skin`` ``[V, 3]`` have deformed by more than
        ``rebuild_spread`` x the rest diagonal since the last build. Returns whether it did."""
        skin = np.asarray(skin, dtype=np.float64)
        rebuilt = False
        for tree, (v0, vn, _, _) in enumerate(self._ranges):  # each character by its own size
            d = skin[v0:v0 + vn] - self._built_at[v0:v0 + vn]
            spread = float(np.linalg.norm(d - d.mean(axis=0), axis=1).max())
            if spread <= self._chars[tree]["rebuild_spread"] * self._diagonals[tree]:
                continue
            self.bvhs[tree].rebuild()  # in place: graphs captured with these trees stay valid
            self._fs_bvhs[tree].rebuild()
            self._built_at[v0:v0 + vn] = skin[v0:v0 + vn]
            self.rebuilds += 1
            rebuilt = True
        return rebuilt

    # ------------------------------------------------------------------ per step
    def detect(self, x_old: wp.array, x_pred: wp.array, contacts) -> None:
        """Candidates on the predicted positions (swept from ``x_old``) into ``contacts``; skin
        layer only."""
        dev = self.device
        c = self.data
        m = self.model
        wp.launch(kd.reset_collision_kernel, dim=contacts.colliding.shape[0], outputs=[contacts.colliding], device=dev)
        wp.launch(kd.triangle_bounds_kernel, dim=c.triangle_count,
                  inputs=[x_old, x_pred, m.tri_indices, self._radius_pads, self.vertex_tree],
                  outputs=[self.lowers, self.uppers], device=dev)
        for tree in self.bvhs:
            tree.refit()
        self.vertex_normals.zero_()
        wp.launch(kd.vertex_normals_kernel, dim=c.triangle_count, inputs=[x_pred, m.tri_indices],
                  outputs=[self.vertex_normals], device=dev)
        # zero the two counters, keep the overflow flag (cleared by the caller after checking)
        wp.launch(kd.zero_counts_kernel, dim=1, outputs=[contacts.counts], device=dev)
        wp.launch(kd.detect_kernel, dim=c.triangle_count,
                  inputs=[self.trees, self.tri_tree, self.tree_start, x_old, x_pred, m.tri_indices, c.tri_owns, c.edge_indices, c.tri_edges,
                          c.edge_owner, self.lowers, self.uppers, self.filter, m.particle_q0,
                          self.vertex_normals, self.params, contacts.capacity],
                  outputs=[contacts.pt_count, contacts.pt_vertex, contacts.pt_triangle, contacts.ee_count, contacts.ee_a,
                           contacts.ee_b, contacts.ee_sign, contacts.overflow_flag, contacts.colliding,
                           int(self._listed and c.fail_safe_rounds > 0),
                           contacts.pair_capacity, contacts.tri_pairs,
                           contacts.pair_count], device=dev)

    def project(self, x: wp.array, inv_mass: wp.array, contacts) -> None:
        """``passes`` Jacobi passes over all point-triangle and edge-edge constraints;
        ``contacts.active`` counts the constraints still violated in the last pass (zeroed
        once, counted by that pass alone)."""
        contacts.active.zero_()
        for n in range(self.data.passes):
            self._project_pass(x, inv_mass, contacts, count_active=n == self.data.passes - 1)

    def _threads(self, items: int) -> int:
        """Threads of a chunked kernel over ``items`` slots or triangles: one per :attr:`chunk`."""
        return -(-items // self.chunk)

    def _project_pass(self, x: wp.array, inv_mass: wp.array, contacts, count_active: bool) -> None:
        dev = self.device
        c = self.data
        m = self.model
        dim = self._threads(contacts.capacity)  # per kind: both buffers hold ``capacity`` contacts
        wp.launch(kp.project_contacts_kernel, dim=2 * dim,
                  inputs=[x, inv_mass, m.tri_indices, contacts.pt_count, contacts.pt_vertex, contacts.pt_triangle,
                          c.edge_indices, contacts.ee_count, contacts.ee_a, contacts.ee_b, contacts.ee_sign,
                          self.params, self.vertex_tree, self.chunk, dim, int(count_active)],
                  outputs=[self.delta, self.delta_count, contacts.active], device=dev)
        wp.launch(kp.apply_deltas_kernel, dim=m.vertex_count, inputs=[self.delta, self.delta_count], outputs=[x], device=dev)

    def fail_safe(self, x_old: wp.array, x: wp.array, skin_matrices: wp.array, carry: bool = True,
                  min_move=None, contacts=None) -> None:
        """Put back the vertices of every pair of the written skin triangles that intersects at
        ``x``, did not at ``x_old`` and does not under LBS (``skin_matrices``, this step's
        pose): to ``x_old`` plus the step's motion of their bone-layer particles, and where
        that still intersects, to ``x_old``; in ``fail_safe_rounds`` rounds (see
        :func:`warpskin.kernels.fail_safe.new_intersections_kernel`). Adds the pairs found to
        :attr:`fail_safe_pairs`. Pairs that already intersected at ``x_old``, or under LBS,
        are left to the constraints. Without ``carry`` the vertices are held at ``x_old``
        (the pass after the volume loop, whose ``x_old`` is this step's positions before it:
        the bone layer has not moved since). With ``min_move`` [m] (one value, or one per
        character of a batched model; the solver's: :attr:`default_min_move`) the first round, too, looks
        only from the triangles with a vertex that moved farther than that from ``x_old``: a
        pair of two others was closer than twice it at ``x_old`` if it intersects now (the
        pass after the volume loop, which moves most of the skin by far less than the
        contact thickness: one query per moved triangle instead of one per triangle).

        With ``contacts`` (this step's, detected by :meth:`detect`) on a skin written as
        simulated, the first round tests the detection's list of nearby triangle pairs instead
        of querying the tree from every triangle: every triangle whose positions here stay
        within ``ESCAPE_REACH`` search radii of its swept box is in that list with every
        triangle it can touch, and only the others (the escaped ones) query the tree (all of
        them where the list did not fit its buffer). The same pairs are tested (a test checks
        it), for a fraction of the cost on the CPU."""
        c = self.data
        if c.fail_safe_rounds <= 0:
            return
        dev = self.device
        m = self.model
        tris, lowers, uppers, count = self._fs_tris, self._fs_lowers, self._fs_uppers, c.output_triangle_count
        listed = contacts is not None and self._listed
        self.carried.zero_()
        self.reverted.zero_()
        carry_offset = self._carry if carry else 0
        # boxes over the step's, the start's and the carried positions (padded by a thousandth of
        # the thickness against float rounding): one refit for all rounds
        tri_threads = self._threads(count)
        wp.launch(kf.fail_safe_bounds_kernel, dim=tri_threads,
                  inputs=[x_old, x, tris, carry_offset, self.params, self.vertex_tree, self.chunk],
                  outputs=[lowers, uppers], device=dev)
        for tree in self._fs_bvhs:
            tree.refit()
        if listed:
            wp.launch(kf.escaped_kernel, dim=tri_threads,
                      inputs=[x, tris, self.params, self.vertex_tree, self.lowers, self.uppers, contacts.pair_count,
                              contacts.pair_capacity, self.chunk], outputs=[self.escaped], device=dev)
        if min_move is not None:
            wp.launch(kf.moved_farther_kernel, dim=m.vertex_count,
                      inputs=[x_old, x, self._min_move_array(min_move), self.vertex_tree], outputs=[self.moved],
                      device=dev)
        lbs = [m.particle_q0, m.coupling_joint_indices, m.coupling_joint_weights, skin_matrices]
        for r in range(c.fail_safe_rounds):
            only_moved = int(r > 0 or min_move is not None)
            only_escaped = int(listed and r == 0)
            if only_escaped:
                wp.launch(kf.listed_new_intersections_kernel, dim=self._threads(contacts.pair_capacity),
                          inputs=[contacts.tri_pairs, contacts.pair_count, x_old, x, tris, lowers, uppers, 1.0e-4,
                                  self.moved, only_moved, self.escaped, *lbs, self.filter, self.chunk],
                          outputs=[self.revert, self.fail_safe_pairs], device=dev)
            # a round after one that put nothing back is skipped (its kernels return at once)
            wp.launch(kf.new_intersections_kernel, dim=tri_threads,
                      inputs=[self._fs_trees, self._fs_tri_tree, self._fs_tree_start, x_old, x, tris, self.params,
                              self.vertex_tree, 1.0e-4, self.moved, only_moved, self.escaped,
                              only_escaped, *lbs, self.filter, self.reverted, r - 1, self.chunk],
                      outputs=[self.revert, self.fail_safe_pairs], device=dev)
            wp.launch(kf.revert_kernel, dim=m.vertex_count, inputs=[x_old, carry_offset, r - 1, r],
                      outputs=[self.revert, self.carried, self.moved, x, self.reverted], device=dev)

    def _min_move_array(self, min_move) -> wp.array:
        """``[K]`` the fail-safe's ``min_move`` per character [m] (one value for all, or one
        each): the array made at construction for the solver's :attr:`default_min_move`, else
        another array filled with these values (not inside a captured graph)."""
        values = tuple(float(v) for v in np.broadcast_to(np.asarray(min_move, dtype=np.float64), (len(self._ranges),)))
        if values == self.default_min_move:
            return self._min_move
        self._other_min_move.assign(np.array(values, dtype=np.float32))
        return self._other_min_move

    def pin_reverted(self, weight_scale: wp.array) -> None:
        """Pin (``weight_scale`` 0) the vertices the last :meth:`fail_safe` put back."""
        wp.launch(kf.pin_reverted_kernel, dim=self.model.vertex_count, inputs=[self.carried], outputs=[weight_scale],
                  device=self.device)

    def volume_weights(self, contacts, weight_scale: wp.array) -> None:
        wp.launch(kp.volume_weights_kernel, dim=weight_scale.shape[0],
                  inputs=[contacts.colliding, self.params, self.vertex_tree, self.model.vertex_count],
                  outputs=[weight_scale],
                  device=self.device)

    def friction_restitution(self, x: wp.array, v: wp.array, inv_mass: wp.array, contacts) -> None:
        dev = self.device
        m = self.model
        wp.launch(kp.friction_restitution_kernel, dim=self._threads(contacts.capacity),
                  inputs=[x, v, inv_mass, m.tri_indices, contacts.pt_count, contacts.pt_vertex, contacts.pt_triangle,
                          self.params, self.vertex_tree, self.chunk],
                  outputs=[self.delta, self.delta_count], device=dev)
        wp.launch(kp.apply_deltas_kernel, dim=m.vertex_count, inputs=[self.delta, self.delta_count], outputs=[v], device=dev)
