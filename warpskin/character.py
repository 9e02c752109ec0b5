"""The character's path from the rig a user brings to the meshes that are written.

One place decides and holds, for a run:

* the **simulation surface**: the rig's own closed skin (welded); where the skin is not one
  closed manifold, the character's own pieces made closed (holes capped, pieces that overlap at
  rest kept from colliding; :mod:`warpskin.preprocess.pieces`), with the pieces that cannot be
  closed (sheets) and small rigid ones (eyes) captured by them; where no piece can be closed
  (or on request), an automatic closed cage around every mesh of the character with the skin
  weights transferred (:mod:`warpskin.preprocess.cage`), or the user's own cage;
* the **written meshes**: the skin in the file's topology and every other mesh of the
  character, each at rest in stage space, with the file's vertex numbers for messages;
* the **physics weight** of every written point (0 = LBS, 1 = the physical result) and the
  **capture** of every written point by the simulation surface (:mod:`warpskin.capture`);
* every frame, the written points: each mesh's own LBS plus the physical deformation carried
  from the simulation surface, blended by the physics weight (:mod:`warpskin.kernels.deform`,
  one launch for every written point, after one for the simulation surface's LBS where the
  solver's tether targets are not at hand).

Example:
    >>> character = Character(rig, cage="auto")
    >>> builder = SkinModelBuilder(character.sim_rig, params)
    >>> model = builder.finalize(device)
    >>> character.bind(builder, device=model.device)
    >>> pts = character.points(state.x, sim_skin_host, clip, t)      # {mesh name: [N, 3]}
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .capture import (
    Capture, CaptureParams, smoothstep, capture_points, identity_capture, shape_diameter,
    welded_pieces, Wrap, wrap_carriers,
)
from .deformer import WrittenDeformer, joint_points
from .errors import RigWarning, SceneError
from .guard import CrossGuard, GarmentSway, GuardParams, JumpLimit, PieceVolume, SurfaceGuard, Untangle, WornRepair
from .guard.params import as_written
from .guard.sway import piece_room
from .guard.swing import LoosePiece, PieceSwing, loose_pieces
from .io.cage_file import CAGE_EXTENSIONS, read_cage_mesh
from .io.usd_export import valid_prim_name
from .mesh import summed_face_normals, vertex_normals
from .preprocess.cage import strongest_influences, build_cage, cage_from_mesh, cage_rig, character_parts
from .preprocess.pieces import PieceParams, piece_surface
from .quality import CrossPairs, WrittenMesh
from .rig import Clip, Rig
from .transforms import linear_blend_skin

__all__ = ["Character", "WrittenPart", "CAGE_MODES", "RIGID_MODES", "check_choices", "is_caged"]

CAGE_MODES = ("auto", "always", "none")
RIGID_MODES = ("cage", "joint")


def check_choices(cage, rigid_pieces: str) -> Path | None:
    """Check a run's ``cage`` and ``rigid_pieces`` choices (one line naming the bad one); returns
    the user's cage file, or ``None`` for an automatic choice."""
    if rigid_pieces not in RIGID_MODES:
        raise SceneError(f"rigid_pieces must be 'cage' or 'joint', got {rigid_pieces!r}")
    if isinstance(cage, Path) or cage not in CAGE_MODES:
        if not isinstance(cage, (str, Path)) or Path(cage).suffix.lower() not in CAGE_EXTENSIONS:
            raise SceneError(f"cage must be 'auto', 'always', 'none' or a mesh file ({', '.join(CAGE_EXTENSIONS)}), "
                             f"got {cage!r}")
        return Path(cage)
    return None


def is_caged(rig, cage) -> bool:
    """Whether ``rig``'s skin is not simulated directly for the choice ``cage`` (``"auto"`` and
    ``"none"``: where its skin is not one closed manifold: its own pieces, else a cage;
    ``"always"``; a cage mesh file)."""
    if check_choices(cage, "cage") is not None or cage == "always":
        return True
    report = rig.report or rig.validate(raise_on_error=False)
    return not (report.closed and report.manifold)


#: Through its own pieces, at least this share of the written points must lie on simulated
#: pieces, else (a character of sheets) ``"auto"`` takes a cage.
MIN_SIMULATED_SHARE = 0.5


@dataclass
class WrittenPart:
    """One written mesh of the character.

    Attributes:
        name: Its prim name (``skin`` for the rig's skinned mesh).
        start, count: Its points in the character's written points (the soup order).
        triangles: ``[T, 3]`` into its own points.
        rest: ``[count, 3]`` rest positions in stage space [m].
        file_ids: ``[count]`` the file's number of each point.
        physics: Whether it is written with physics (else it follows its joints by LBS).
    """

    name: str
    start: int
    count: int
    triangles: np.ndarray
    rest: np.ndarray
    file_ids: np.ndarray
    physics: bool = True
    attachment: object = None


@dataclass
class Character:
    """A rig's simulation surface, written meshes, physics weights and capture.

    Args:
        rig: The rig as loaded (:class:`~warpskin.rig.Rig`): what is written.
        cage: ``"auto"`` (where the skin is not one closed manifold: its own pieces made closed,
            where at least :data:`MIN_SIMULATED_SHARE` of its points lie on pieces that can be;
            else a cage), ``"always"`` (a cage), ``"none"`` (never a cage: the skin, or its
            own pieces), or a cage mesh file.
        rigid_pieces: Through a cage, the pieces that LBS moves rigidly move by one rigid motion
            with the cage around them (``"cage"``) or follow their joints exactly
            (``"joint"``).
        capture: :class:`~warpskin.capture.CaptureParams`.
        weights: Physics-weight overrides by joint-name pattern (shell-style, case-insensitive;
            the first that matches a joint wins): a point's weight becomes the blend, by its
            LBS weights, of its joints' values (the automatic weight for joints no pattern
            names), so the override is as smooth as the skinning. A map painted in the file
            (glTF attribute ``_PHYSICS_WEIGHT``, USD primvar ``physicsWeight``) replaces the
            automatic weight where it is given; the patterns apply after it.
        device: Warp device of the cage's construction and the deformation.
        guard: :class:`~warpskin.guard.GuardParams` of the surface guard of every mesh written
            with physics (default: on).
    """

    rig: object
    cage: str | Path = "auto"
    rigid_pieces: str = "cage"
    capture: CaptureParams | None = None
    weights: dict | None = None
    device: object = None
    guard: GuardParams | None = None
    sim_rig: object = field(init=False)
    caged: bool = field(init=False)
    build_s: float = field(init=False, default=0.0)

    def __post_init__(self) -> None:
        from .preprocess.cage import character_soup, rigid_pieces

        cage_file = self.cage_file = check_choices(self.cage, self.rigid_pieces)
        rig = self.rig
        t0 = time.perf_counter()
        self.soup = character_soup(rig)
        #: What is simulated: ``"skin"`` (the rig's closed skin), ``"pieces"`` (its own pieces,
        #: capped) or ``"cage"``.
        self.surface = "skin"
        #: The :class:`~warpskin.preprocess.pieces.PieceSurface` where ``surface`` is ``"pieces"``.
        self.pieces = None
        self.cage_surface = self.matched = None
        if is_caged(rig, self.cage):
            if cage_file is None and self.cage in ("auto", "none"):
                self.pieces = self._piece_surface()
            if self.pieces is not None:
                self.surface = "pieces"
            elif self.cage == "none":
                rig.require_closed()  # says what is open
            else:
                self.surface = "cage"
        self.caged = self.surface == "cage"
        self.rigid = rigid_pieces(self.soup) if self.caged else np.full(len(self.soup.points), -1)
        self.parts = self._parts()
        if self.caged:
            self._build_cage(cage_file)
        elif self.surface == "pieces":
            self.sim_rig = self._pieces_rig()
        else:
            self.sim_rig = rig
        self.build_s = time.perf_counter() - t0
        self.capture_result: Capture | None = None
        self._deformer = None
        #: After :meth:`bind`: ``{part name: WrittenMesh}`` of the meshes written with physics,
        #: and their surface guards.
        self.meshes: dict[str, WrittenMesh] = {}
        self.guards: dict[str, SurfaceGuard] = {}
        self.cross: CrossGuard | None = None

    # ------------------------------------------------------------------ construction
    @property
    def captured(self) -> bool:
        """Whether the written meshes are captured by a simulated surface of their own (a cage,
        or the character's pieces made closed), rather than being the simulated skin itself."""
        return self.surface != "skin"

    @property
    def pieces_params(self):
        """The :class:`~warpskin.preprocess.pieces.PieceParams` of the character's own pieces."""
        return PieceParams()

    def _piece_surface(self):
        """The character's own pieces made closed (:func:`~warpskin.preprocess.pieces.piece_surface`),
        or ``None`` where too few of its points lie on pieces that can be (see ``cage``)."""
        soup = self.soup
        names = [self.display_name(name) for name, _, _ in soup.pieces]
        ps = piece_surface(soup.points, soup.triangles, soup.dense_weights, self._mesh_of_soup(), names,
                           joint_names=self.rig.skeleton.joint_names, params=self.pieces_params, device=self.device)
        if ps is None:
            return None
        share = float(np.mean(ps.simulated[ps.piece_of_point]))
        if share < MIN_SIMULATED_SHARE and self.cage != "none":
            return None
        return ps

    def _mesh_of_soup(self) -> np.ndarray:
        out = np.zeros(len(self.soup.points), dtype=np.int64)
        for k, (_, start, count) in enumerate(self.soup.pieces):
            out[start:start + count] = k
        return out

    def _pieces_rig(self):
        """The pieces' closed surface as a rig to simulate, bound at the rest pose in stage space
        (as a cage is: :func:`~warpskin.preprocess.cage.cage_rig`), with its collision groups."""
        rig, ps = self.rig, self.pieces
        ji, jw = strongest_influences(ps.dense_weights, 4)
        rest_world = rig.joint_world_transforms(Clip("rest"), 0.0)
        sim = Rig(name=rig.name, vertices=ps.vertices.copy(), triangles=ps.triangles, skeleton=rig.skeleton,
                  joint_indices=ji, joint_weights=jw, inverse_bind=np.linalg.inv(rest_world), clips=rig.clips,
                  source=f"{rig.source} (its own pieces, holes capped)", mesh_name=rig.mesh_name, up_axis=rig.up_axis,
                  meters_per_unit=rig.meters_per_unit, vertex_kind="piece", surface_groups=ps.groups)
        # each simulated vertex's mesh and file vertex number, -1 for a cap's, for messages
        file_ids = np.concatenate([p.file_ids for p in self.parts])
        mesh_of = self.mesh_of_point
        ok = ps.origin >= 0
        labels = np.full(len(ps.origin), -1, dtype=np.int64)
        labels[ok] = file_ids[ps.origin[ok]]
        sim.surface_labels = (labels, mesh_of[np.maximum(ps.origin, 0)], [self.display_name(p.name) for p in self.parts],
                              ps.vertex_piece, ps.groups.names)
        sim.validate(raise_on_error=True)
        return sim

    def _build_cage(self, cage_file) -> None:
        rig, soup = self.rig, self.soup
        if cage_file is not None:  # the user's own
            cage = cage_from_mesh(read_cage_mesh(cage_file), rig, device=self.device, soup=soup)
        else:
            cage = build_cage(soup.points, soup.triangles, device=self.device, parts=character_parts(rig, soup))
        self.cage_surface = cage
        self.sim_rig, _, self.matched = cage_rig(rig, cage, device=self.device)

    def _parts(self) -> list[WrittenPart]:
        rig = self.rig
        out = []
        for name, start, count in self.soup.pieces:
            if name == "skin":
                tris, ids, att = rig.output_triangles, rig.file_vertex_ids(np.arange(count)), None
            else:
                att = next(a for a in rig.attachments if a.name == name)
                tris, ids = np.asarray(att.triangles), np.arange(count)
            physics = self.captured or name == "skin"
            out.append(WrittenPart(name, start, count, np.asarray(tris, dtype=np.int64),
                                   self.soup.points[start:start + count], np.asarray(ids), physics, att))
        return out

    # ------------------------------------------------------------------ queries
    @property
    def point_count(self) -> int:
        return len(self.soup.points)

    @property
    def mesh_of_point(self) -> np.ndarray:
        """``[N]`` the written mesh (its index in :attr:`parts`) of every written point."""
        out = np.zeros(self.point_count, dtype=np.int64)
        for k, part in enumerate(self.parts):
            out[part.start:part.start + part.count] = k
        return out

    @property
    def rigid_piece_count(self) -> int:
        return int(self.rigid.max()) + 1 if self.rigid.size else 0

    def edge(self) -> float:
        """The simulation surface's resolution [m]: the cage's grid spacing, or the skin's mean
        edge length."""
        if self.caged:
            return float(self.cage_surface.edge)
        t = self.sim_rig.triangles
        v = self.sim_rig.vertices
        e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
        return float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())

    # ------------------------------------------------------------------ binding
    def bind(self, builder=None, *, device=None) -> Capture:
        """Capture every written point by the simulation surface and set the physics weights
        (after the model is built: ``builder`` gives the layers). Uploads the deformation's
        arrays to ``device``. Returns the :class:`~warpskin.capture.Capture`."""
        t0 = time.perf_counter()
        soup = self.soup
        n = self.point_count
        mesh_of = self.mesh_of_point
        if self.caged:
            sim = self.sim_rig
            cage_dense = sim._dense_weights(sim.joint_indices, sim.joint_weights)
            rigid = self.rigid if self.rigid_pieces == "cage" else None
            exclude = (self.rigid >= 0) if self.rigid_pieces == "joint" else None
            v = len(self.cage_surface.vertices)
            unresolved = builder.layers.unresolved[:v] if builder is not None else None
            cap = capture_points(soup.points, soup.triangles, soup.dense_weights, mesh_of, self.cage_surface.vertices,
                                 self.cage_surface.triangles, cage_dense, self.edge(), rigid=rigid, exclude=exclude,
                                 cage_exclude=unresolved, params=self.capture, device=device or self.device)
        elif self.surface == "pieces":
            cap = self._capture_pieces(builder, device or self.device)
        else:
            # a skin simulated directly is written as simulated (its own collisions keep it
            # clean), except where no layer depth fits: LBS there
            phi = np.zeros(n)
            c = self.parts[0].count
            phi[:c] = 1.0
            if builder is not None:
                phi[:c][builder.layers.unresolved[:c]] = 0.0
            cap = identity_capture(n, phi)

        cap.physics_weight = cap.uniform_in_groups(self._overridden(cap.physics_weight))
        if not np.any(cap.physics_weight > 0):
            import warnings


            warnings.warn(f"{self.rig.source or self.rig.name}: no written point is resolved by the simulation (a sheet "
                          "that encloses no volume, or parts thinner than about two cage cells): what is written is "
                          "its LBS", RigWarning, stacklevel=2)
        self.capture_result = cap
        joints = joint_points(self.soup.points, self.soup.triangles, cap.group)
        self._deformer = WrittenDeformer(self, cap, joints, device=device or self.device,
                                   joint_gap=(self.guard or GuardParams()).joint_gap) if self.captured else None
        self.meshes = {p.name: WrittenMesh(self.display_name(p.name), p.triangles, p.rest, p.file_ids,
                                           joint_points=np.nonzero(joints[p.start:p.start + p.count])[0])
                       for p in self.parts if p.physics}
        params = self.guard or GuardParams()
        intended = None  # a popped character: where its muscles stretch the written skin on purpose
        if builder is not None and builder.rest_drive is not None:
            belly = builder.rest_drive_support()
            if self.captured:  # the points that the surface's bellies carry (most of their capture)
                intended = (cap.weights * belly[cap.indices]).sum(axis=1) > 0.5
            else:
                intended = np.zeros(n, dtype=bool)
                c = self.parts[0].count
                intended[:c] = belly[:c]
        # a skin simulated directly (or a character's own pieces) hands the guard its physical
        # result whole, its physics weight as the ceiling: it is written as simulated while its
        # physics keeps the surface
        height = float(np.ptp(self.soup.points, axis=0).max())
        #: Per mesh written with physics, its :class:`~warpskin.guard.JumpLimit` (after its guard).
        self.limits = {p.name: JumpLimit(height, params, cap.group[p.start:p.start + p.count])
                       for p in self.parts if p.physics}
        #: Per mesh with garment points, its :class:`~warpskin.guard.WornRepair` (before its
        #: guard) and the rows of ``cap.wrap`` that are its points. Only garments (pieces worn
        #: over others, :class:`~warpskin.preprocess.pieces.PieceParams`) are repaired: other
        #: worn sheets lie on or in their neighbours, where taking them nearer crosses more.
        self.repairs = {}
        #: Per mesh with garment points, its :class:`~warpskin.guard.GarmentSway` (before its
        #: worn repair): loose garments swing after the body and settle after it stops.
        self.sways = {}
        if cap.wrap is not None and self.pieces is not None:
            worn = np.asarray(cap.wrap.points, dtype=np.int64)
            gamma, clearance = cap.wrap.gamma, np.asarray(cap.wrap.clearance)
            garment = self.pieces.garment[self.pieces.piece_of_point[worn]]
            # a point keeps its rest clearance over the surface it is worn on (floor 1: a point
            # at or under that surface at rest is not moved)
            floor = np.where((gamma > 0.0) & (clearance > 0.0), clearance / np.maximum(gamma, 1e-30), 1.0)
            for p in self.parts:
                rows = np.nonzero((worn >= p.start) & (worn < p.start + p.count) & garment)[0]
                if p.physics and rows.size:
                    self.repairs[p.name] = (WornRepair(self.meshes[p.name], worn[rows] - p.start, floor[rows], params),
                                            rows)
                    if params.enabled and params.sway > 0.0:
                        room = np.minimum(gamma[rows], piece_room(self.soup.points, self.pieces.piece_of_point, worn[rows]))
                        sway = GarmentSway(worn[rows] - p.start, room, cap.physics_weight[worn[rows]],
                                           params.sway_frequency, params.sway_damping, params.sway,
                                           self.meshes[p.name], self.pieces.piece_of_point[p.start:p.start + p.count])
                        if sway.enabled:
                            self.sways[p.name] = sway
        #: Per mesh with loose pieces (a hair bun on the skull), its
        #: :class:`~warpskin.guard.PieceSwing` (after its garments' sway).
        self.swings = self._piece_swings(cap, params) if self.pieces is not None else {}
        #: Per mesh written by capture from its own pieces, its
        #: :class:`~warpskin.guard.PieceVolume` (before its worn repair and guard): the written
        #: pieces keep the volume their simulation keeps.
        self.volumes = {}
        if self._deformer is not None and self.pieces is not None and intended is None:
            # every closed piece with physics in it, but those moved as a whole (they keep their
            # LBS shape, moved rigidly); not on a popped character, whose muscles swell it on
            # purpose
            weight = np.where(cap.group < 0, cap.physics_weight, 0.0)
            for p in self.parts:
                if p.physics:
                    repair = PieceVolume(self.meshes[p.name], weight[p.start:p.start + p.count])
                    if repair.active.any():
                        self.volumes[p.name] = repair
        # a skin simulated on a refined copy is written with chords of the simulated surface
        chords = self.surface == "skin" and builder is not None and builder.rig.refined_skin
        self.guards = {p.name: SurfaceGuard(self.meshes[p.name], params, cap.group[p.start:p.start + p.count],
                                            ceiling=None if self.caged else cap.physics_weight[p.start:p.start + p.count],
                                            direct=not self.caged, chords=chords and p.name == "skin",
                                            intended=None if intended is None else intended[p.start:p.start + p.count])
                       for p in self.parts if p.physics}
        #: Per mesh written with physics, its :class:`~warpskin.guard.Untangle` (after its guard;
        #: none with the guard or its pair checks off, or ``[guard] untangle`` 0).
        diag = float(np.linalg.norm(np.ptp(self.soup.points, axis=0)))
        self.untangles = {}
        if params.enabled and params.pairs and params.untangle > 0:
            for p in self.parts:
                if p.name in self.guards:
                    self.untangles[p.name] = Untangle(self.guards[p.name], cap.group[p.start:p.start + p.count],
                                                      rounds=params.untangle, max_step=params.untangle_step * diag,
                                                      max_offset=params.untangle_offset * diag)
        # pieces written as separate meshes keep apart as their LBS keeps them (after each
        # mesh's own guard)
        cross = CrossPairs([self.meshes.get(p.name) or WrittenMesh(self.display_name(p.name), p.triangles, p.rest,
                                                                   p.file_ids) for p in self.parts])
        #: :class:`~warpskin.guard.CrossGuard` over every written mesh (``None``: one mesh).
        self.cross = None
        if cross.active:
            level, dense = self.rig.skeleton.depth, self.soup.dense_weights
            depth = [level[int(np.argmax(dense[p.start:p.start + p.count].sum(axis=0)))] for p in self.parts]
            self.cross = CrossGuard(cross, {self.meshes[name].name: g for name, g in self.guards.items()}, params,
                                    depth=np.asarray(depth),
                                    joint_limit=(np.inf if self._deformer is None else self._deformer.joint_limit))
        self.build_s += time.perf_counter() - t0
        return cap

    def _capture_pieces(self, builder, device) -> Capture:
        """The capture of a character simulated on its own pieces: a point of a simulated piece
        is its simulated vertex (physics weight 1, 0 where no layer depth fits); a point of a
        simulated piece that was reduced is captured by that piece's simulated vertices alone
        (:func:`~warpskin.capture.capture_points`, caps and unresolved vertices left out); a
        garment's by the simulated surface beneath it (within 1.5 x its gap), so that it follows
        the body's deformation; the other points (sheets, small rigid pieces) by the simulated
        surface near them, each rigid piece as a whole. A captured point's physics weight is the capture's confidence (its
        skinning similarity, :class:`~warpskin.capture.CaptureParams` ``confidence``); on a
        reduced piece it ramps down over the parts thinner than its simulated copy resolves."""
        ps, soup = self.pieces, self.soup
        prm = self.capture or CaptureParams()
        n = self.point_count
        vop = ps.vertex_of_point
        unresolved = np.zeros(ps.vertex_count, dtype=bool)
        if builder is not None:
            unresolved = np.asarray(builder.layers.unresolved[:ps.vertex_count], dtype=bool)
        on = vop >= 0
        phi = np.zeros(n)
        phi[on] = np.where(unresolved[vop[on]], 0.0, 1.0)
        rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = [(np.nonzero(on)[0], vop[on, None],
                                                                  np.ones((int(on.sum()), 1)))]
        group = np.full(n, -1, dtype=np.int64)
        confidence = np.ones(n)
        notes = {"simulated_points": int(on.sum())}
        piece = ps.piece_of_point
        # the captured sets: each reduced piece by itself, then the attached points by any piece
        # (a reduced piece deforms with its surface: none of its parts moves as a whole)
        import dataclasses

        whole = dataclasses.replace(prm, small=0.0)
        # near a seam (within the seam zone's reach of another simulated piece: a tube's end in
        # a ball, a wrist at a hand) a point is captured by both pieces, so that the two keep
        # the relative motion LBS gives them there and cross no more than at rest
        from scipy.spatial import cKDTree

        seam = np.zeros(n, dtype=bool)
        sim_pts = np.nonzero(ps.simulated[piece])[0]
        for k in np.nonzero(ps.decimated)[0]:
            mine, others = sim_pts[piece[sim_pts] == k], sim_pts[piece[sim_pts] != k]
            if mine.size and others.size:
                d, _ = cKDTree(soup.points[others]).query(soup.points[mine], distance_upper_bound=1.5 * ps.edge)
                seam[mine[np.isfinite(d)]] = True
        sets = [(np.nonzero(~on & (piece == k) & ~seam)[0], (ps.vertex_piece != k), whole)
                for k in np.nonzero(ps.decimated)[0]]
        sets.append((np.nonzero(~on & seam)[0], np.zeros(ps.vertex_count, dtype=bool), whole))
        # a worn piece (a garment, a sheet such as a hair cap, knuckles on a palm: an attached
        # piece that lies on the simulated surface, within a garment's gap of it) rides on the
        # surface beneath it; a small rigid one (an eye), or one that stands off the surface (a
        # mitten beyond a wrist), is carried by the surface near it
        anywhere = np.zeros(ps.vertex_count, dtype=bool)
        reach = self.pieces_params.garment_gap * float(np.ptp(soup.points, axis=0).max())
        candidates = np.nonzero(~on & ~ps.simulated[piece] & ~ps.rigid[piece] & ~ps.carried[piece])[0]
        worn = np.zeros(n, dtype=bool)
        wrap = None
        if candidates.size:
            # on the written surface of the simulated pieces (what shows beneath a garment)
            body = soup.triangles[ps.simulated[piece[soup.triangles[:, 0]]]]
            corners, bary, coef, share, dist = wrap_carriers(
                soup.points[candidates], soup.dense_weights[candidates], soup.points, soup.dense_weights, body,
                reach=reach, device=device)
            for k in np.unique(piece[candidates]):
                sel = piece[candidates] == k
                if ps.garment[k] or float(np.percentile(dist[sel], 90)) <= reach:
                    worn[candidates[sel]] = True
            keep = worn[candidates]
            if keep.any():
                points = candidates[keep]
                corners, bary, coef, share, dist = corners[keep], bary[keep], coef[keep], share[keep], dist[keep]
                # the clearance a worn point keeps from the written simulated pieces (none where it
                # is inside one at rest: a hair cap through a bun)
                clearance = _clearance(soup.points[points], soup.points, body, None, 0.1, 0.05 * ps.edge, device)
                wrap = Wrap(points, corners, bary, coef, share, clearance, body)
                phi[points] = 1.0 - smoothstep(dist, reach, 2.0 * reach)  # beyond a garment's gap: less and less
                notes["wrapped_points"] = int(points.size)
        sets.append((np.nonzero(~on & ~ps.simulated[piece] & ~worn)[0], anywhere, prm))
        next_group = 0
        for points, other, sub_prm in sets:
            if points.size == 0:
                continue
            remap = np.full(n, -1, dtype=np.int64)
            remap[points] = np.arange(points.size)
            t = soup.triangles
            t = remap[t[(remap[t] >= 0).all(axis=1)]]
            rigid = np.where(ps.rigid[piece[points]], piece[points], -1)
            sub = capture_points(soup.points[points], t, soup.dense_weights[points], self.mesh_of_point[points],
                                 ps.vertices, ps.triangles, ps.dense_weights, ps.edge, rigid=rigid,
                                 cage_exclude=ps.cap | unresolved | other, params=sub_prm, device=device)
            rows.append((points, sub.indices, sub.weights))
            phi[points] = smoothstep(sub.confidence, *prm.confidence)
            # a carried assembly (a fist) moves with the surface that holds it, whatever that
            # surface's joints (the forearm's end): its weight is 1 where it is captured at all
            carried = ps.carried[piece[points]] & (sub.confidence > 0.0)
            phi[points[carried]] = 1.0
            phi[points[sub.weights.sum(axis=1) <= 0]] = 0.0
            confidence[points] = sub.confidence
            g = sub.group
            group[points] = np.where(g >= 0, g + next_group, -1)
            next_group = int(group.max()) + 1 if (group >= 0).any() else 0
            for key, v in sub.notes.items():
                notes[key] = notes.get(key, 0) + v
        # a simulated piece rigid in the file (a hair bun on the head joint) moves as a whole: its
        # points share one row, the mean displacement of up to 16 of its simulated vertices
        # spread over it (the piece swings, it does not deform)
        for k in np.nonzero(ps.simulated & ps.rigid)[0]:
            members = np.nonzero(piece == k)[0]
            verts = np.nonzero((ps.vertex_piece == k) & ~ps.cap & ~unresolved)[0]
            if members.size == 0 or verts.size == 0:
                continue
            chosen = [int(verts[0])]
            d = np.linalg.norm(ps.vertices[verts] - ps.vertices[chosen[0]], axis=1)
            while len(chosen) < min(16, verts.size):  # farthest-point sampling
                j = int(np.argmax(d))
                chosen.append(int(verts[j]))
                d = np.minimum(d, np.linalg.norm(ps.vertices[verts] - ps.vertices[verts[j]], axis=1))
            row = np.array(chosen, dtype=np.int64)
            rows.append((members, np.broadcast_to(row, (members.size, row.size)),
                         np.full((members.size, row.size), 1.0 / row.size)))
            group[members] = next_group
            next_group += 1
        notes["captured_points"] = int(n - on.sum())
        # parts of a reduced piece thinner than its simulated copy resolves (a wrist, fingers):
        # their physics weight ramps down with the thickness (the shape diameter, CaptureParams
        # thin and thick, in the surface's edges). A piece simulated as it is keeps its weights,
        # as a skin simulated directly does: its collisions keep its thin parts out of the rest
        # (a hand that LBS drives into the hip)
        sim_points = np.nonzero(ps.simulated[piece] & ps.decimated[piece])[0]
        if sim_points.size:
            first, cls, ctri, _ = welded_pieces(soup.points, soup.triangles, self.mesh_of_point)
            q = soup.points[first]
            thick = shape_diameter(q, vertex_normals(q, ctri), q, ctri, device=device)[cls]
            ramp = smoothstep(np.where(np.isfinite(thick), thick, np.inf), prm.thin * ps.edge, prm.thick * ps.edge)
            phi[sim_points] *= ramp[sim_points]
            notes["thin_points"] = int((ramp[sim_points] < 1.0).sum())
        k = max(r[1].shape[1] for r in rows)
        idx = np.zeros((n, k), dtype=np.int64)
        w = np.zeros((n, k))
        for points, i, ww in rows:  # later rows replace earlier ones (a rigid piece's shared row)
            idx[points] = 0
            w[points] = 0.0
            idx[points, :i.shape[1]] = i
            w[points, :ww.shape[1]] = ww
        cap = Capture(indices=idx, weights=w, physics_weight=phi, thickness=np.full(n, np.inf), confidence=confidence,
                      group=group, notes=notes, wrap=wrap)
        cap.physics_weight = cap.uniform_in_groups(cap.physics_weight)
        return cap

    def written(self, x, sim_skin: np.ndarray, clip, t: float, lbs: np.ndarray | None = None,
                surface_lbs=None) -> dict[str, np.ndarray]:
        """What is written at clip time ``t`` [s]: ``{mesh name: [N, 3]}`` (host), every mesh
        written with physics passed through its surface guard (:mod:`warpskin.guard`) against
        its own LBS, the others at their LBS. Arguments as :meth:`points`; call once per frame,
        in frame order (the guard's weight carries over from frame to frame)."""
        if self.capture_result is None:
            raise SceneError("Character.written before bind()")
        lbs = self.lbs(clip, t) if lbs is None else lbs
        if self._deformer is not None:
            physical = self.points(x, sim_skin, clip, t, lbs=lbs, surface_lbs=surface_lbs)
        else:  # the simulated skin whole: its physics weight is the guard's ceiling
            physical = lbs.copy()
            n = self.rig.output_count
            physical[:n] = np.asarray(sim_skin[:n], dtype=np.float64)
        physical, lbs_by = self.split(physical), self.split(lbs)
        #: The last frame's skinned normals of the meshes skinned by the rig, ``{mesh name:
        #: [T, 3]}`` (:meth:`skinned_normals`).
        self.last_skinned = skinned = self.skinned_normals(clip, t)
        if self.sways:  # garments swing (their carriers are not worn), before their volume is kept
            carriers = self._carriers(physical)
            for name, sway in self.sways.items():
                physical[name] = sway.apply(physical[name], lbs_by[name], t, carriers[self.repairs[name][1]])
        for name, swing in self.swings.items():  # loose pieces swing about where they hang
            physical[name] = swing.apply(physical[name], lbs_by[name], t)
        for name, repair in self.volumes.items():  # before the worn points' carriers are taken
            physical[name] = repair.apply(physical[name])
        carriers = self._carriers(physical) if self.repairs else None
        #: The last frame's physical result before the guard, ``{mesh name: [N, 3]}``.
        self.last_physical = physical
        out = dict(physical)
        guarded = {}
        for name, guard in self.guards.items():
            pts = physical[name]
            if name in self.repairs:
                repair, rows = self.repairs[name]
                repaired = repair.apply(pts, carriers[rows])
                if repaired is not pts:  # the volume the repair took, back
                    repaired = self._volume_back(name, repaired, pts)
                pts = repaired
            guarded[name] = guard.apply(pts, lbs_by[name], skinned.get(name))
            if name in self.untangles:  # the crossings that LBS drives too, repaired pair by pair
                untangle = self.untangles[name]
                untangled = untangle.apply(guarded[name], lbs_by[name], counted=True)
                if untangled is not guarded[name]:
                    guard.pair_keys = guard.pair_counts = None  # counted again on what is written
                    guarded[name] = as_written(self._volume_back(name, untangled, guarded[name]))  # its dents
                elif guard.pair_keys is None and untangle.pair_keys is not None:  # its count, for the measures
                    guard.pair_keys = untangle.pair_keys
                    guard.pair_counts = (int(untangle.pair_keys[0].size), int(untangle.pair_keys[1].size))
        if self.cross is not None:
            shown = {p.name: self.display_name(p.name) for p in self.parts}
            across = self.cross.apply({shown[n]: guarded.get(n, out[n]) for n in shown},
                                      {shown[n]: lbs_by[n] for n in shown})
            for name in guarded:
                if across[shown[name]] is not guarded[name]:  # carried or taken back: counted again
                    self.guards[name].pair_keys = self.guards[name].pair_counts = None
            guarded = {name: across[shown[name]] for name in guarded}
        for name, guard in self.guards.items():
            limited = self.limits[name].apply(guarded[name], lbs_by[name])
            out[name] = guard.keep(limited, guarded[name], lbs_by[name])
            if out[name] is not guarded[name]:
                guard.pair_keys = guard.pair_counts = None  # counted again on what is written
            if out[name] is not limited:  # the limit goes on from what is written
                self.limits[name].written(out[name], lbs_by[name])
        return out

    def _volume_back(self, name: str, repaired: np.ndarray, given: np.ndarray) -> np.ndarray:
        """``repaired`` (``[N, 3]`` [m], mesh ``name``'s points after a repair of ``given``) with
        the volume the repair took put back from the points it did not move (it rewrites the
        others to within rounding: moved is more than a thousandth of the median rest edge), by
        the mesh's :class:`~warpskin.guard.PieceVolume`; ``repaired`` itself where it has none."""
        if name not in self.volumes:
            return repaired
        tol = 1e-3 * float(np.median(self.meshes[name].rest_length))
        moved = np.linalg.norm(repaired - given, axis=1) > tol
        return self.volumes[name].apply(repaired, hold=moved)

    def _piece_swings(self, cap: Capture, params: GuardParams) -> dict:
        """``{mesh name: PieceSwing}`` for the meshes with loose pieces
        (:func:`~warpskin.guard.swing.loose_pieces`: pieces LBS moves rigidly, not carried in an
        assembly, hung from a closed simulated piece); empty with the guard off or ``[guard]
        swing`` 0."""
        if not (params.enabled and params.swing > 0.0):
            return {}
        ps, soup = self.pieces, self.soup
        closed = {}
        tri_piece = ps.vertex_piece[ps.triangles[:, 0]]
        for k in np.nonzero(ps.simulated & ps.closable)[0]:
            tris = ps.triangles[tri_piece == k]
            used, local = np.unique(tris, return_inverse=True)
            closed[int(k)] = (ps.vertices[used], local.reshape(-1, 3))
        joint = np.argmax(soup.dense_weights, axis=1)
        loose = loose_pieces(soup.points, ps.piece_of_point, joint, ps.rigid & ~ps.small & ~ps.carried, closed, ps.edge)
        out = {}
        for p in self.parts:
            mine = [LoosePiece(lp.piece, lp.points - p.start, lp.visible, lp.pivot, lp.carrier, lp.touching,
                               lp.centre) for lp in loose
                    if p.physics and p.start <= lp.points[0] < p.start + p.count]
            if not mine:
                continue
            swing = PieceSwing(mine, soup.points[p.start:p.start + p.count], ps.piece_of_point[p.start:p.start + p.count],
                               cap.physics_weight[p.start:p.start + p.count], params.swing_frequency,
                               params.swing_damping, params.swing)
            if swing.enabled:
                out[p.name] = swing
        return out

    def _carriers(self, points: dict) -> np.ndarray:
        """``[K, 3]`` the carrier point of every worn point (``cap.wrap``'s rows) on the written
        surface ``points`` (``{mesh name: [N, 3]}``) as it is: the blend of its carriers."""
        return self.capture_result.wrap.carrier_points(np.concatenate([points[p.name] for p in self.parts]))

    def painted(self) -> np.ndarray:
        """``[N]`` the file's painted physics weight of every written point (NaN: none)."""
        out = np.full(self.point_count, np.nan)
        rig = self.rig
        for p in self.parts:
            render = rig.render if p.attachment is None else p.attachment.render
            w = getattr(render, "physics_weight", None) if render is not None else None
            if w is None:
                continue
            w = np.asarray(w, dtype=np.float64)
            if p.attachment is None:  # per file vertex: onto the welded skin (its first copy's)
                first = np.full(p.count, np.nan)
                order = np.arange(len(rig.weld_map))[::-1]
                first[rig.weld_map[order]] = w[order]
                w = first
            out[p.start:p.start + p.count] = w
        return out

    def _overridden(self, phi: np.ndarray) -> np.ndarray:
        """The automatic weights ``phi`` with the painted map and the joint patterns applied."""
        import fnmatch

        phi = np.asarray(phi, dtype=np.float64).copy()
        painted = self.painted()
        given = ~np.isnan(painted)
        phi[given] = painted[given]
        if self.weights:
            names = self.rig.skeleton.joint_names
            value = np.full(len(names), np.nan)
            for pattern, v in self.weights.items():
                hit = [j for j, name in enumerate(names)
                       if np.isnan(value[j]) and fnmatch.fnmatchcase(name.lower(), str(pattern).lower())]
                value[hit] = float(v)
            if not (~np.isnan(value)).any():
                raise SceneError(f"[physics.weights]: no joint matches {sorted(self.weights)} (joints: "
                                 f"{', '.join(names[:8])}{', ...' if len(names) > 8 else ''})")
            dense = self.soup.dense_weights
            set_share = dense[:, ~np.isnan(value)].sum(axis=1)
            phi = (1.0 - set_share) * phi + dense[:, ~np.isnan(value)] @ value[~np.isnan(value)]
        return np.clip(phi, 0.0, 1.0)

    # ------------------------------------------------------------------ per frame
    def skinned_normals(self, clip, t: float) -> dict[str, np.ndarray]:
        """``{mesh name: [T, 3]}`` at clip time ``t`` [s], for the rig's skin where it is
        written with physics: :meth:`~warpskin.quality.WrittenMesh.skinned_normals` of its
        points' blended skinning maps (what LBS's own folds are judged by)."""
        p = next((p for p in self.parts if p.name == "skin"), None)
        if p is None or p.name not in self.meshes:
            return {}
        rig = self.rig  # the skin's points are the rig's first output_count vertices
        m = rig.skinning_matrices(clip, t)[:, :3, :3]
        idx, w = rig.joint_indices[:p.count], rig.joint_weights[:p.count]
        blended = np.einsum("nk,nkij->nij", w, m[idx])
        return {p.name: self.meshes[p.name].skinned_normals(blended)}

    def lbs(self, clip, t: float) -> np.ndarray:
        """Every written point under LBS at clip time ``t`` [s], ``[N, 3]`` (host, float64)."""
        rig = self.rig
        n = rig.output_count
        skin = linear_blend_skin(rig.vertices[:n], rig.joint_indices[:n], rig.joint_weights[:n],
                                 rig.skinning_matrices(clip, t))
        if not rig.attachments:
            return skin
        world = rig.joint_world_transforms(clip, t)
        by_name = {a.name: a for a in rig.attachments}
        rest = [by_name[p.name].points(world) for p in self.parts[1:]]
        return np.concatenate([skin, *rest])

    def points(self, x, sim_skin: np.ndarray, clip, t: float, lbs: np.ndarray | None = None,
               surface_lbs=None) -> np.ndarray:
        """Every written point at clip time ``t`` [s], ``[N, 3]`` (host): its LBS plus its
        physics weight times the physical deformation (``x``: the simulation's particle
        positions on the device, its first vertices the skin layer; ``sim_skin``: their host
        copy, for a skin simulated directly; ``lbs``: :meth:`lbs` if the caller has it;
        ``surface_lbs``: the simulated surface's LBS at ``t`` on the device, where the caller has
        it: the solver's tether targets of the frame's last step)."""
        cap = self.capture_result
        if cap is None:
            raise SceneError("Character.points before bind()")
        if self._deformer is not None:
            return self._deformer.evaluate(x, clip, t, surface_lbs).numpy().astype(np.float64)
        lbs = self.lbs(clip, t) if lbs is None else lbs
        n = self.rig.output_count
        out = lbs.copy()
        phi = cap.physics_weight[:n, None]
        sim = np.asarray(sim_skin[:n], dtype=np.float64)
        # where the weight is 1 the simulated point itself (exactly), else the blend
        out[:n] = np.where(phi >= 1.0, sim, lbs[:n] + phi * (sim - lbs[:n]))
        return out

    def sim_vertex_weight(self, vertex_count: int) -> np.ndarray:
        """``[V]`` how much each simulated vertex shows in what is written: the largest physics
        weight among the points it captures (direct: its own point's; a vertex added by
        refining: 1)."""
        cap = self.capture_result
        out = np.zeros(vertex_count)
        if not self.captured:
            n = self.rig.output_count
            out[:] = 1.0
            out[:n] = cap.physics_weight[:n]
            return out
        used = cap.weights > 0
        np.maximum.at(out, cap.indices[used], np.broadcast_to(cap.physics_weight[:, None], cap.weights.shape)[used])
        return out  # (a worn point rides on written points: those show through their own rows)

    def display_name(self, name: str) -> str:
        """The name a written mesh has in the output (the skin: its file's mesh name)."""
        if name == "skin":
            return valid_prim_name(self.rig.mesh_name) if self.rig.mesh_name else "skin"
        return valid_prim_name(name)

    def weight_summary(self) -> dict:
        """Per written mesh (by its :meth:`display_name`): the mean physics weight and the share
        of points at 0 (LBS) and at 1, with the capture's notes."""
        cap = self.capture_result
        if cap is None:
            return {}
        out = {}
        for p in self.parts:
            phi = cap.physics_weight[p.start:p.start + p.count]
            out[self.display_name(p.name)] = {"mean": float(phi.mean()) if phi.size else 0.0,
                                              "lbs_share": float(np.mean(phi <= 0.0)),
                           "physical_share": float(np.mean(phi >= 1.0))}
        if cap.notes:
            out["notes"] = dict(cap.notes)
        return out

    def split(self, points: np.ndarray) -> dict[str, np.ndarray]:
        """``{mesh name: its rows of points}``."""
        return {p.name: points[p.start:p.start + p.count] for p in self.parts}


def _clearance(points: np.ndarray, surface: np.ndarray, triangles: np.ndarray, dist, share: float, edge: float,
               device) -> np.ndarray:
    """``[M]`` the clearance [m] worn ``points`` keep from the written surface of the simulated
    pieces (``surface`` ``[N, 3]``, ``triangles``) at rest: ``share`` x their rest distance to it
    (at most ``edge``), 0 (none) where a point lies behind it at rest (inside a simulated piece:
    a hair cap through a bun). ``dist``: unused (the distance is measured here)."""
    import warp as wp

    from .kernels import deform as k

    with wp.ScopedDevice(device):
        flat = wp.array(np.asarray(triangles, dtype=np.int32).ravel(), dtype=wp.int32)
        mesh = wp.Mesh(points=wp.array(np.asarray(surface, dtype=np.float32), dtype=wp.vec3), indices=flat)
        normals = wp.array(summed_face_normals(np.asarray(surface, dtype=np.float64),
                                               np.asarray(triangles, dtype=np.int64)).astype(np.float32), dtype=wp.vec3)
        far = 2.0 * float(np.linalg.norm(np.ptp(np.concatenate([points, surface]), axis=0))) + 1.0
        d = wp.zeros(len(points), dtype=wp.float32)
        wp.launch(k.signed_distance_kernel, dim=len(points),
                  inputs=[mesh.id, normals, flat, wp.array(np.asarray(points, dtype=np.float32), dtype=wp.vec3), far],
                  outputs=[d])
        d = d.numpy().astype(np.float64)
    return np.where(d > 0.0, np.minimum(share * d, edge), 0.0)
