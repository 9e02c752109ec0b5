"""How a character's surfaces are written: in the file's own topology by default (its seam-split
vertices and triangles, with its UVs, recomputed normals and its materials), at rest in stage
space, under a root prim named after the character.

warpskin deforms the welded, closed surface; :class:`CharacterOutput` declares each mesh of it
to the :class:`~warpskin.io.usd_export.UsdSkinWriter` with the file's triangles and a remap from
the welded vertices, so the steppers keep producing welded points and the bake still lines up
with the source's UVs and faces.
"""

from __future__ import annotations

import numpy as np

from ..errors import SceneError
from ..io.render import smoothing_groups
from ..io.usd_export import valid_prim_name
from ..mesh import weld_by_position
from ..rig import Clip
from ..transforms import linear_blend_skin

__all__ = ["CharacterOutput", "TOPOLOGIES", "rest_pose_points", "attachment_kwargs"]

#: ``file``: the file's own vertices, faces and UVs (default); ``welded``: the closed surface
#: warpskin simulates (seam-split vertices merged).
TOPOLOGIES = ("file", "welded")


def rest_pose_points(rig) -> np.ndarray:
    """The skin in the skeleton's rest pose in stage space ``[V, 3]`` (every vertex of ``rig``):
    the default-time points of a bake, standing where its frames stand (CesiumMan's bind space
    is Z-up under a Y-up stage)."""
    mats = rig.skinning_matrices(Clip("rest"), 0.0)
    return linear_blend_skin(rig.vertices, rig.joint_indices, rig.joint_weights, mats)


def attachment_kwargs(attachment) -> dict:
    """How an attachment is declared (:meth:`CharacterOutput.declare`): smoothing groups over
    its own seams, and its render attributes."""

    render = attachment.render
    kw = {"normal_groups": smoothing_groups(weld_by_position(attachment.vertices)[1],
                                            render.normals if render is not None else None)}
    if render is not None:
        kw["render"] = render
    return kw


class CharacterOutput:
    """Declares a rig's surfaces to a writer in the chosen topology.

    Args:
        rig: The rig whose welded output surface the steppers deform (for a refined rig, its
            first :attr:`~warpskin.rig.Rig.output_count` vertices).
        topology: One of :data:`TOPOLOGIES`.
    """

    def __init__(self, rig, topology: str = "file", clip=None) -> None:
        if topology not in TOPOLOGIES:
            raise SceneError(f"topology must be one of {TOPOLOGIES}, got {topology!r}")
        self.rig, self.topology = rig, topology
        self.n = rig.output_count
        self.welded_triangles = rig.output_triangles
        self.rest = rest_pose_points(rig)[: self.n]
        render = rig.render
        self.groups = smoothing_groups(rig.weld_map, render.normals if render is not None else None)
        # the character's other meshes (rigid parts, other skinned meshes), written beside the
        # skin at the clip's poses
        self.clip = clip
        self.attachments = list(getattr(rig, "attachments", []) or []) if clip is not None else []

    @property
    def root_name(self) -> str:
        return self.rig.name or "character"

    @property
    def skin_prim(self) -> str:
        """The prim name of the character's skin: its file's mesh name (``Cesium_Man``,
        ``Hand_R``), ``skin`` where it has none; its LBS guide is ``<name>_lbs``."""
        name = valid_prim_name(self.rig.mesh_name) if self.rig.mesh_name else "skin"
        taken = {valid_prim_name(a.name) for a in getattr(self.rig, "attachments", []) or []}
        taken |= {"lbs", "rest", "cage", "Looks", "layer_fat", "layer_muscle", "layer_bone"}
        return name if name not in taken and f"{name}_lbs" not in taken else f"{name}_skin"

    def prim_of(self, name: str) -> str | None:
        """The prim name of mesh ``name`` where it is not ``name`` itself (``skin``, ``lbs``)."""
        return {"skin": self.skin_prim, "lbs": f"{self.skin_prim}_lbs"}.get(name)

    def is_character_mesh(self, triangles: np.ndarray) -> bool:
        t = np.asarray(triangles)
        return t.shape == self.welded_triangles.shape and np.array_equal(t, self.welded_triangles)

    def declare(self, writer, name: str, triangles: np.ndarray, rest: np.ndarray | None, kw: dict) -> str:
        """Add mesh ``name`` to ``writer``: a mesh of the character's welded output surface in
        the chosen topology, at rest in stage space; any other mesh as given (``kw["as_is"]``:
        the inner layers, the cage; ``kw["render"]``: another mesh of the character with its
        own render attributes, an embedded attachment)."""
        kw = dict(kw)
        as_is = kw.pop("as_is", False)
        render = kw.pop("render", None)
        if render is not None:
            self._render_kwargs(writer, render, kw)
        if as_is or render is not None or not self.is_character_mesh(triangles):
            return writer.add_mesh(name, triangles, rest_points=rest, **kw)
        kw["prim_name"] = kw.get("prim_name") or self.prim_of(name)
        if self.topology == "welded":
            return writer.add_mesh(name, triangles, rest_points=self.rest, **kw)
        rig = self.rig
        kw["remap"] = rig.weld_map
        kw["normal_groups"] = self.groups
        if rig.render is not None:
            self._render_kwargs(writer, rig.render, kw)
        return writer.add_mesh(name, rig.file_triangles, rest_points=self.rest[rig.weld_map], **kw)

    def declare_attachments(self, writer) -> None:
        """Add every attachment as a sibling mesh in its own topology, at rest in stage space."""
        rest_world = self.rig.joint_world_transforms(Clip("rest"), 0.0)
        for a in self.attachments:
            self.declare(writer, a.name, a.triangles, a.points(rest_world), attachment_kwargs(a))

    @staticmethod
    def _render_kwargs(writer, render, kw: dict) -> None:
        """UVs and materials of a mesh with its own render attributes, into ``kw`` (the writer
        writes a material shared by several meshes once)."""
        if render.uvs is not None:
            kw["uvs"] = render.uvs
        if render.materials and kw.get("purpose") != "guide":
            kw.pop("color", None)  # the material's colour, not the review colour
            paths = [writer.add_material(m) for m in render.materials]
            tm = render.triangle_material
            kw["materials"] = [(paths[k], np.nonzero(tm == k)[0]) for k in range(len(paths)) if np.any(tm == k)]

    def attachment_points(self, t: float) -> dict[str, np.ndarray]:
        """Every attachment's points at clip time ``t`` [s]."""
        if not self.attachments:
            return {}
        world = self.rig.joint_world_transforms(self.clip, t)
        return {a.name: a.points(world) for a in self.attachments}

