"""UsdSkel import: a skinned ``UsdGeom.Mesh``, its ``Skeleton`` and bound ``SkelAnimation``
as a :class:`~warpskin.rig.Rig`.

The conversion follows usd-core's own skinning queries (``UsdSkel.Cache``,
``UsdSkel.SkeletonQuery``, ``UsdSkel.SkinningQuery``) so the imported rig reproduces
``UsdSkel.SkinningQuery.ComputeSkinnedPoints``. In column-vector notation USD skins a point
``p`` of the mesh as::

    p_world(t) = L_skel @ sum_j w_j * S_j(t) @ inverse(B_j) @ G @ p

with ``L_skel`` the skeleton prim's local-to-world transform, ``S_j(t)`` the skeleton-space
transform of joint ``j`` (animation, else rest), ``B_j`` its ``bindTransforms`` entry and
``G`` the mesh's ``primvars:skel:geomBindTransform``. The rig stores ``G @ p`` as its rest
vertices (skeleton space), ``inverse(B_j)`` as its inverse bind matrices and ``L_skel`` as the
root transform of every root joint, which is the rig's convention
``p_world = sum_j w_j * G_j(t) @ inverse_bind[j] @ p_rest``.

``pxr`` (usd-core) is imported lazily, so the rest of warpskin works without it.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from ..errors import index_list
from ..mesh import polygon_triangle_count, triangulate_faces
from ..rig import Clip, Rig, RigError, RigWarning, Skeleton, Track
from ..transforms import local_from_bind
from .render import Material, RenderAttributes, read_asset_bytes

__all__ = ["load_usd", "list_usd_meshes", "USD_EXTENSIONS"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")


# --------------------------------------------------------------------------------------------
# pxr access
# --------------------------------------------------------------------------------------------


def _pxr() -> Any:
    """The ``pxr`` modules used here, as a namespace; :class:`RigError` if usd-core is missing."""
    try:
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdShade, UsdSkel, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise RigError(
            "reading USD files needs usd-core (the `pxr` module): pip install usd-core"
        ) from exc

    return SimpleNamespace(Gf=Gf, Sdf=Sdf, Tf=Tf, Usd=Usd, UsdGeom=UsdGeom, UsdShade=UsdShade, UsdSkel=UsdSkel, Vt=Vt)


def _warn(message: str) -> None:
    warnings.warn(message, RigWarning, stacklevel=3)


def _open_stage(path: str | Path) -> tuple[Any, Any, Path]:
    """Open ``path`` as a USD stage; :class:`RigError` for a missing or unreadable file."""
    pxr = _pxr()
    p = Path(path)
    if not p.exists():
        raise RigError(f"{p}: no such file")
    if not p.is_file():
        raise RigError(f"{p}: not a file")
    if p.suffix.lower() not in USD_EXTENSIONS:
        raise RigError(f"{p}: not a USD file (expected one of {USD_EXTENSIONS})")
    try:
        stage = pxr.Usd.Stage.Open(str(p), pxr.Usd.Stage.LoadAll)
    except Exception as exc:  # pxr raises Tf.ErrorException (a RuntimeError) with a long text
        detail = " ".join(str(exc).split())
        if len(detail) > 300:
            detail = detail[:300] + " ..."
        raise RigError(f"{p}: cannot be opened as a USD stage ({detail})") from None
    if stage is None or not stage.GetPseudoRoot():
        raise RigError(f"{p}: cannot be opened as a USD stage")
    return pxr, stage, p


# --------------------------------------------------------------------------------------------
# Discovery
# --------------------------------------------------------------------------------------------


@dataclass
class _Target:
    """One skinned mesh as UsdSkel resolves it."""

    prim: Any  # Usd.Prim of the UsdGeom.Mesh
    skinning: Any  # UsdSkel.SkinningQuery
    skeleton: Any  # UsdSkel.Skeleton
    skel_query: Any  # UsdSkel.SkeletonQuery


def _scan(pxr: Any, stage: Any) -> tuple[Any, list[_Target], list[Any]]:
    """Every skinned mesh (via SkelRoot bindings) and every other ``Mesh`` prim."""
    usd, usd_skel, usd_geom = pxr.Usd, pxr.UsdSkel, pxr.UsdGeom
    predicate = usd.TraverseInstanceProxies()
    cache = usd_skel.Cache()
    targets: dict[str, _Target] = {}
    meshes: list[Any] = []
    for prim in stage.Traverse(predicate):
        if prim.IsA(usd_geom.Mesh):
            meshes.append(prim)
        if not prim.IsA(usd_skel.Root):
            continue
        root = usd_skel.Root(prim)
        try:
            cache.Populate(root, predicate)
            bindings = cache.ComputeSkelBindings(root, predicate)
        except Exception as exc:  # malformed skeleton data surfaces as Tf errors
            _warn(f"{stage.GetRootLayer().identifier}: SkelRoot <{prim.GetPath()}> skipped: {exc}")
            continue
        for binding in bindings:
            skel = binding.GetSkeleton()
            skel_query = cache.GetSkelQuery(skel)
            for sq in binding.GetSkinningTargets():
                mprim = sq.GetPrim()
                key = str(mprim.GetPath())
                if mprim.IsA(usd_geom.Mesh) and key not in targets:
                    targets[key] = _Target(mprim, sq, skel, skel_query)
    others = [m for m in meshes if str(m.GetPath()) not in targets]
    return cache, list(targets.values()), others


def _looks_skinned(pxr: Any, prim: Any) -> str | None:
    """Why an unbound mesh with skinning data is not skinned (``None`` if it has none)."""
    api = pxr.UsdSkel.BindingAPI(prim)
    has_influences = api.GetJointIndicesAttr().HasAuthoredValue() or api.GetJointWeightsAttr().HasAuthoredValue()
    skel_rel = api.GetSkeletonRel()
    has_rel = bool(skel_rel) and skel_rel.HasAuthoredTargets()
    if not has_influences and not has_rel:
        return None
    if not has_influences:
        return "it binds a skeleton but has no primvars:skel:jointIndices / jointWeights"
    in_root = False
    p = prim.GetParent()
    while p and not p.IsPseudoRoot():
        if p.IsA(pxr.UsdSkel.Root):
            in_root = True
            break
        p = p.GetParent()
    if not in_root:
        return "it has skin weights but is not under a SkelRoot"
    if not has_rel:
        return "it has skin weights but no skel:skeleton binding (on itself or an ancestor)"
    return "its skel:skeleton binding does not resolve to a valid Skeleton prim"


def _face_counts(pxr: Any, prim: Any, time: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mesh = pxr.UsdGeom.Mesh(prim)
    counts = mesh.GetFaceVertexCountsAttr().Get(time)
    indices = mesh.GetFaceVertexIndicesAttr().Get(time)
    holes = mesh.GetHoleIndicesAttr().Get(time)
    counts = np.asarray(counts if counts is not None else [], dtype=np.int64).ravel()
    indices = np.asarray(indices if indices is not None else [], dtype=np.int64).ravel()
    holes = np.asarray(holes if holes is not None else [], dtype=np.int64).ravel()
    return counts, indices, holes


def _point_count(pxr: Any, prim: Any, time: Any) -> int:
    pts = pxr.UsdGeom.Mesh(prim).GetPointsAttr().Get(time)
    return 0 if pts is None else len(pts)


def _anim_path(target: _Target) -> str | None:
    aq = target.skel_query.GetAnimQuery() if target.skel_query else None
    return str(aq.GetPrim().GetPath()) if aq else None


def list_usd_meshes(path: str | Path) -> list[dict]:
    """The meshes of a USD file.

    Args:
        path: A ``.usd``/``.usda``/``.usdc``/``.usdz`` file.

    Returns:
        One dict per ``Mesh`` prim, skinned meshes first, with keys ``name`` (prim path),
        ``skinned`` (bound to a Skeleton through a SkelRoot), ``vertices`` (point count),
        ``triangles`` (after fan triangulation, holes skipped), ``joints`` (skeleton joint
        count, 0 if unskinned), ``skeleton`` and ``animation`` (prim paths or ``None``) and
        ``problem`` (why a mesh that carries skin weights is not skinned, else ``None``).
    """
    pxr, stage, _ = _open_stage(path)
    _, targets, others = _scan(pxr, stage)
    t0 = pxr.Usd.TimeCode.EarliestTime()
    out = []
    for tg in targets:
        counts, _, holes = _face_counts(pxr, tg.prim, t0)
        out.append(
            {
                "name": str(tg.prim.GetPath()),
                "skinned": True,
                "vertices": _point_count(pxr, tg.prim, t0),
                "triangles": polygon_triangle_count(counts, holes),
                "joints": len(tg.skel_query.GetJointOrder()) if tg.skel_query else 0,
                "skeleton": str(tg.skeleton.GetPrim().GetPath()),
                "animation": _anim_path(tg),
                "problem": None,
            }
        )
    for prim in others:
        counts, _, holes = _face_counts(pxr, prim, t0)
        out.append(
            {
                "name": str(prim.GetPath()),
                "skinned": False,
                "vertices": _point_count(pxr, prim, t0),
                "triangles": polygon_triangle_count(counts, holes),
                "joints": 0,
                "skeleton": None,
                "animation": None,
                "problem": _looks_skinned(pxr, prim),
            }
        )
    return out


# --------------------------------------------------------------------------------------------
# Conversion helpers
# --------------------------------------------------------------------------------------------


def _matrices(gf_matrices: Any) -> np.ndarray:
    """``Gf.Matrix4d`` array (row vectors) -> column-vector matrices ``[N, 4, 4]``."""
    m = np.asarray(gf_matrices, dtype=np.float64).reshape(-1, 4, 4)
    return np.ascontiguousarray(np.swapaxes(m, -1, -2))


_QUAT_LAYOUT_OK: bool | None = None


def _quats_xyzw(pxr: Any, arr: Any) -> np.ndarray:
    """A ``Vt.Quat{f,d,h}Array`` as ``[N, 4]`` quaternions ``(x, y, z, w)``."""
    global _QUAT_LAYOUT_OK
    if _QUAT_LAYOUT_OK is None:
        probe = np.asarray(pxr.Vt.QuatfArray([pxr.Gf.Quatf(0.5, pxr.Gf.Vec3f(1.0, 2.0, 3.0))]), dtype=np.float64)
        _QUAT_LAYOUT_OK = probe.shape == (1, 4) and np.allclose(probe[0], [1.0, 2.0, 3.0, 0.5])
    if _QUAT_LAYOUT_OK:
        return np.asarray(arr, dtype=np.float64).reshape(-1, 4)
    return np.array(  # pragma: no cover - older Vt without the (imaginary, real) buffer layout
        [(*q.GetImaginary(), q.GetReal()) for q in arr], dtype=np.float64
    ).reshape(-1, 4)


class _Where:
    """Formats error messages that name the file and the prim."""

    def __init__(self, path: Path, prim_path: str):
        self.path, self.prim = path, prim_path

    def error(self, message: str) -> RigError:
        return RigError(f"{self.path}: mesh <{self.prim}>: {message}")

    def warn(self, message: str) -> None:
        warnings.warn(f"{self.path}: mesh <{self.prim}>: {message}", RigWarning, stacklevel=4)


def _select(targets: list[_Target], others: list[Any], mesh: str | None, path: Path, pxr: Any) -> _Target:
    names = [str(t.prim.GetPath()) for t in targets]
    if mesh is None:
        if not targets:
            why = []
            for prim in others:
                reason = _looks_skinned(pxr, prim)
                if reason:
                    why.append(f"<{prim.GetPath()}>: {reason}")
            listing = ", ".join(f"<{m.GetPath()}>" for m in others) or "none"
            extra = ("; " + "; ".join(why)) if why else ""
            raise RigError(
                f"{path}: no skinned mesh (a Mesh with skin weights bound to a Skeleton under a "
                f"SkelRoot); meshes in the file: {listing}{extra}"
            )
        t0 = pxr.Usd.TimeCode.EarliestTime()
        sizes = [_point_count(pxr, t.prim, t0) for t in targets]
        return targets[int(np.argmax(sizes))]
    hits = [t for t, n in zip(targets, names) if n == mesh]
    if not hits:
        hits = [t for t in targets if t.prim.GetName() == mesh]
    if len(hits) == 1:
        return hits[0]
    if len(hits) > 1:
        raise RigError(
            f"{path}: mesh name {mesh!r} is ambiguous; use a prim path: "
            + ", ".join(str(t.prim.GetPath()) for t in hits)
        )
    for prim in others:
        if str(prim.GetPath()) == mesh or prim.GetName() == mesh:
            reason = _looks_skinned(pxr, prim) or "it has no skin weights"
            raise RigError(
                f"{path}: mesh <{prim.GetPath()}> is not skinned: {reason}; skinned meshes: "
                + (", ".join(names) or "none")
            )
    raise RigError(
        f"{path}: no skinned mesh named {mesh!r}; skinned meshes: " + (", ".join(names) or "none")
    )


# --------------------------------------------------------------------------------------------
# Mesh, influences, skeleton, animation
# --------------------------------------------------------------------------------------------


def _read_mesh(pxr: Any, tg: _Target, where: _Where, t0: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """File points ``[N, 3]`` (mesh space), CCW triangles ``[T, 3]``, the same triangles as
    face-vertex (corner) indices ``[T, 3]`` (for faceVarying primvars), and each triangle's face."""
    mesh = pxr.UsdGeom.Mesh(tg.prim)
    pts = mesh.GetPointsAttr().Get(t0)
    if pts is None or len(pts) == 0:
        raise where.error("has no points")
    points = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    n = points.shape[0]
    bad = np.nonzero(~np.all(np.isfinite(points), axis=1))[0]
    if bad.size:
        raise where.error(f"points {index_list(bad)} are NaN or inf")
    counts, indices, holes = _face_counts(pxr, tg.prim, t0)
    if counts.size == 0:
        raise where.error("has no faces (faceVertexCounts is empty)")
    if np.any(counts < 0) or int(counts.sum()) != indices.size:
        raise where.error(
            f"faceVertexCounts sum to {int(counts[counts > 0].sum())} but faceVertexIndices has "
            f"{indices.size} entries"
        )
    oob = np.nonzero((indices < 0) | (indices >= n))[0]
    if oob.size:
        raise where.error(
            f"faceVertexIndices entries {index_list(oob)} are outside [0, {n - 1}] "
            f"(values {index_list(np.unique(indices[oob]))})"
        )
    tri, skipped = triangulate_faces(counts, indices, holes)
    corners, _ = triangulate_faces(counts, np.arange(indices.size), holes)
    if skipped.size:
        where.warn(f"faces {index_list(skipped)} have fewer than 3 vertices; skipped")
    if tri.shape[0] == 0:
        raise where.error("has no polygon with 3 or more vertices")
    if mesh.GetOrientationAttr().Get(t0) == pxr.UsdGeom.Tokens.leftHanded:
        tri, corners = tri[:, [0, 2, 1]], corners[:, [0, 2, 1]]
    offsets = np.concatenate([[0], np.cumsum(counts)])
    face = np.searchsorted(offsets, corners[:, 0], side="right") - 1
    return points, tri, corners, face


def _flat_primvar(pxr: Any, pv: Any, t0: Any, n: int, tri: np.ndarray, corners: np.ndarray, face: np.ndarray,
                  width: int) -> np.ndarray | None:
    """A primvar's values per triangle corner ``[T, 3, width]`` whatever its interpolation, or
    ``None`` where its size does not match it."""
    values = pv.ComputeFlattened(t0)
    if values is None:
        return None
    v = np.asarray(values, dtype=np.float64).reshape(-1, width)
    interp = str(pv.GetInterpolation())
    if interp in ("vertex", "varying") and v.shape[0] == n:
        out = v[tri]
    elif interp == "faceVarying" and v.shape[0] > corners.max():
        out = v[corners]
    elif interp == "uniform" and v.shape[0] > face.max():
        out = np.repeat(v[face][:, None, :], 3, axis=1)
    elif interp == "constant" and v.shape[0] >= 1:
        out = np.broadcast_to(v[0], (tri.shape[0], 3, width)).copy()
    else:
        return None
    return out if np.isfinite(out).all() else None


def _read_render(pxr: Any, tg: _Target, where: _Where, t0: Any, n: int, tri: np.ndarray, corners: np.ndarray,
                 face: np.ndarray, geom_bind: np.ndarray) -> RenderAttributes:
    """UVs (``primvars:st``, or the first texture-coordinate primvar), rest normals (vertex
    interpolated ``primvars:normals`` or ``normals``, in bind space) and the bound
    UsdPreviewSurface material(s) of the mesh (per GeomSubset where faces bind their own)."""
    UsdGeom, UsdShade, Sdf = pxr.UsdGeom, pxr.UsdShade, pxr.Sdf
    mesh = UsdGeom.Mesh(tg.prim)
    api = UsdGeom.PrimvarsAPI(tg.prim)
    uvs = None
    candidates = [api.GetPrimvar("st")] + [pv for pv in api.GetPrimvars()
                                            if pv.GetTypeName().role == Sdf.ValueRoleNames.TextureCoordinate]
    for pv in candidates:
        if pv and pv.HasValue():
            uvs = _flat_primvar(pxr, pv, t0, n, tri, corners, face, 2)
            if uvs is not None:
                break
    normals = None
    npv = api.GetPrimvar("normals")
    if npv and npv.HasValue() and str(npv.GetInterpolation()) in ("vertex", "varying"):
        values = npv.ComputeFlattened(t0)
    elif mesh.GetNormalsAttr().HasValue() and str(mesh.GetNormalsInterpolation()) in ("vertex", "varying"):
        values = mesh.GetNormalsAttr().Get(t0)
    else:
        values = None
    if values is not None and len(values) == n:
        normals = np.asarray(values, dtype=np.float64).reshape(-1, 3) @ np.linalg.inv(geom_bind[:3, :3])
    # materials: the mesh's own binding, and GeomSubsets of faces that bind another
    materials: list[Material] = []
    tri_mat = np.full(tri.shape[0], -1, dtype=np.int64)
    known: dict[str, int] = {}

    def index_of(prim) -> int:
        bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
        if not bound:
            return -1
        key = str(bound.GetPath())
        if key not in known:
            known[key] = len(materials)
            materials.append(_usd_material(pxr, bound, where))
        return known[key]

    tri_mat[:] = index_of(tg.prim)
    for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh):
        if str(subset.GetElementTypeAttr().Get()) != "face":
            continue
        k = index_of(subset.GetPrim())
        faces = np.asarray(subset.GetIndicesAttr().Get(t0) or [], dtype=np.int64)
        if k >= 0 and faces.size:
            tri_mat[np.isin(face, faces)] = k
    paint = None
    ppv = api.GetPrimvar("physicsWeight")
    if ppv and ppv.HasValue():
        values = np.asarray(ppv.ComputeFlattened(t0), dtype=np.float64).ravel()
        if str(ppv.GetInterpolation()) not in ("vertex", "varying") or values.shape[0] != n:
            raise where.error(f"primvars:physicsWeight must be one float per point (vertex interpolation, {n}), got "
                              f"{values.shape[0]} values, {ppv.GetInterpolation()}")
        paint = values
    return RenderAttributes(uvs=uvs, normals=normals, materials=materials,
                            triangle_material=tri_mat if materials else None, physics_weight=paint)


def _usd_material(pxr: Any, material: Any, where: _Where) -> Material:
    """A UsdPreviewSurface's diffuse colour and, where it is connected to a UsdUVTexture, that
    texture's image bytes (from a plain file or inside a usdz)."""
    UsdShade = pxr.UsdShade
    name = material.GetPrim().GetName()
    shader = material.ComputeSurfaceSource()[0]
    if not shader:
        return Material(name=name)
    color = (0.18, 0.18, 0.18, 1.0)  # UsdPreviewSurface's default diffuseColor
    inp = shader.GetInput("diffuseColor")
    if inp:
        value = inp.Get()
        if value is not None:
            color = (*map(float, value), 1.0)
        source = inp.GetConnectedSource()
        if source:
            tex = UsdShade.Shader(source[0].GetPrim())
            file_input = tex.GetInput("file")
            asset = file_input.Get() if file_input else None
            resolved = asset.resolvedPath if asset is not None else ""
            data = read_asset_bytes(resolved) if resolved else None
            if data is not None:
                tex_name = Path(asset.path.split("[")[-1].rstrip("]")).name
                return Material(name=name, base_color=(1.0, 1.0, 1.0, 1.0), texture=data, texture_name=tex_name)
            where.warn(f"material <{material.GetPath()}>: its diffuse texture cannot be read; written without it")
    return Material(name=name, base_color=color)


def _read_influences(
    pxr: Any, tg: _Target, where: _Where, t0: Any, n: int, skel_joints: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """Joint indices (skeleton order) and weights per file point, ``[N, K]`` each."""
    sq = tg.skinning
    k = int(sq.GetNumInfluencesPerComponent())
    interp = str(sq.GetInterpolation())
    ji_pv, jw_pv = sq.GetJointIndicesPrimvar(), sq.GetJointWeightsPrimvar()
    raw_i = ji_pv.ComputeFlattened(t0) if ji_pv else None
    raw_w = jw_pv.ComputeFlattened(t0) if jw_pv else None
    if raw_i is None or raw_w is None:
        raise where.error("has no primvars:skel:jointIndices / primvars:skel:jointWeights")
    try:
        result = sq.ComputeJointInfluences(t0)
    except Exception:  # Tf errors on malformed primvars; diagnosed below
        result = None
    if k < 1:
        raise where.error(f"joint influence elementSize is {k}; it must be at least 1")
    if interp not in ("vertex", "constant"):
        raise where.error(f"joint influences have interpolation {interp!r}; UsdSkel supports 'vertex' and 'constant'")
    if len(raw_i) != len(raw_w):
        raise where.error(
            f"primvars:skel:jointIndices has {len(raw_i)} entries but primvars:skel:jointWeights has {len(raw_w)}"
        )
    expected = k if interp == "constant" else n * k
    if len(raw_i) != expected:
        raise where.error(
            f"joint influences hold {len(raw_i)} entries; {interp} interpolation with elementSize {k} "
            f"over {n} points needs {expected}"
        )
    if result:
        ji = np.asarray(result[0], dtype=np.int64)
        jw = np.asarray(result[1], dtype=np.float64)
    else:
        ji = np.asarray(raw_i, dtype=np.int64)
        jw = np.asarray(raw_w, dtype=np.float64)
    ji = ji.reshape(-1, k)
    jw = jw.reshape(-1, k)
    if interp == "constant":
        ji = np.repeat(ji[:1], n, axis=0)
        jw = np.repeat(jw[:1], n, axis=0)
    if ji.shape[0] != n:
        raise where.error(f"joint influences cover {ji.shape[0]} points but the mesh has {n}")

    # Validate against the mesh's own joint order, then map into the skeleton's.
    mesh_joints = sq.GetJointOrder()
    order = list(mesh_joints) if mesh_joints else list(skel_joints)
    bad_w = np.nonzero(~np.all(np.isfinite(jw), axis=1))[0]
    if bad_w.size:
        raise where.error(f"vertices {index_list(bad_w)} have NaN or inf joint weights")
    neg = np.nonzero((jw < 0.0).any(axis=1))[0]
    if neg.size:
        raise where.error(f"vertices {index_list(neg)} have negative joint weights")
    zero = np.nonzero(jw.sum(axis=1) <= 1e-12)[0]
    if zero.size:
        raise where.error(f"vertices {index_list(zero)} have no joint weight (all weights are zero)")
    used = jw != 0.0
    oob = used & ((ji < 0) | (ji >= len(order)))
    if oob.any():
        rows = np.nonzero(oob.any(axis=1))[0]
        src = "skel:joints" if mesh_joints else "the skeleton's joints"
        raise where.error(
            f"vertices {index_list(rows)} use joint indices {index_list(np.unique(ji[oob]))}, outside "
            f"[0, {len(order) - 1}] ({src} has {len(order)} entries)"
        )
    ji = np.where(used, ji, 0)
    if mesh_joints:
        index = {name: j for j, name in enumerate(skel_joints)}
        missing = [name for name in order if name not in index]
        if missing:
            raise where.error(
                f"skel:joints names {len(missing)} joint(s) that the skeleton "
                f"<{tg.skeleton.GetPrim().GetPath()}> ({len(skel_joints)} joints) lacks: {missing[:8]}"
            )
        mesh_to_skel = np.array([index[name] for name in order], dtype=np.int64)
        ji = mesh_to_skel[ji]
    return ji, jw


def _read_skeleton(pxr: Any, tg: _Target, where: _Where, t0: Any) -> tuple[Skeleton, np.ndarray, bool]:
    """The skeleton (metres not yet applied), inverse bind matrices ``[J, 4, 4]`` and whether
    ``restTransforms`` is authored."""
    sk_prim = tg.skeleton.GetPrim()
    sk_path = sk_prim.GetPath()
    query = tg.skel_query
    if not query:
        raise where.error(f"its skeleton <{sk_path}> is invalid (check its 'joints' topology)")
    joints = [str(j) for j in query.GetJointOrder()]
    if not joints:
        raise where.error(f"its skeleton <{sk_path}> has no joints")
    topo = query.GetTopology()
    ok, reason = (True, "")
    try:
        res = topo.Validate()
        ok, reason = (res, "") if isinstance(res, bool) else (bool(res[0]), str(res[1]))
    except Exception:  # pragma: no cover - Validate's Python signature differs across versions
        pass
    if not ok:
        raise where.error(f"skeleton <{sk_path}> has an invalid joint topology: {reason}")
    parents = np.asarray(topo.GetParentIndices(), dtype=np.int64)
    j = len(joints)
    skel = pxr.UsdSkel.Skeleton(sk_prim)
    bind_raw = skel.GetBindTransformsAttr().Get()
    if bind_raw is None or len(bind_raw) != j:
        size = 0 if bind_raw is None else len(bind_raw)
        raise where.error(f"skeleton <{sk_path}> has {size} bindTransforms for {j} joints")
    bind = _matrices(bind_raw)
    if not np.all(np.isfinite(bind)):
        raise where.error(f"skeleton <{sk_path}> bindTransforms hold NaN or inf")
    dets = np.linalg.det(bind[:, :3, :3])
    sing = np.nonzero(np.abs(dets) < 1e-12)[0]
    if sing.size:
        raise where.error(f"skeleton <{sk_path}> bindTransforms of joints {[joints[s] for s in sing[:8]]} are singular")
    rest_raw = skel.GetRestTransformsAttr().Get()
    has_rest = rest_raw is not None and len(rest_raw) == j
    if has_rest:
        rest_local = _matrices(rest_raw)
        if not np.all(np.isfinite(rest_local)):
            raise where.error(f"skeleton <{sk_path}> restTransforms hold NaN or inf")
    else:
        if rest_raw is not None and len(rest_raw) not in (0, j):
            where.warn(
                f"skeleton <{sk_path}> has {len(rest_raw)} restTransforms for {j} joints; "
                "using the rest pose implied by bindTransforms"
            )
        rest_local = local_from_bind(bind, parents)
    xformable = pxr.UsdGeom.Xformable(sk_prim)
    root = np.array(xformable.ComputeLocalToWorldTransform(t0), dtype=np.float64).T
    if _xform_might_vary(pxr, sk_prim):
        where.warn(
            f"the transform of skeleton <{sk_path}> or of an ancestor is animated; the rig uses its "
            "value at the earliest time sample"
        )
    try:
        skeleton = Skeleton.from_local_matrices(joints, parents, rest_local, np.tile(root, (j, 1, 1)))
    except RigError as exc:
        raise where.error(f"skeleton <{sk_path}>: {exc}") from None
    return skeleton, np.linalg.inv(bind), has_rest


def _xform_might_vary(pxr: Any, prim: Any) -> bool:
    p = prim
    while p and not p.IsPseudoRoot():
        if p.IsA(pxr.UsdGeom.Xformable) and pxr.UsdGeom.Xformable(p).TransformMightBeTimeVarying():
            return True
        p = p.GetParent()
    return False


def _attr_keys(
    pxr: Any, attr: Any, label: str, count: int, where: _Where, anim_path: str, comps: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Time codes ``[K]`` and values ``[K, count, comps]`` of one SkelAnimation array attribute;
    ``None`` when it has no value. A default-only value gives one key at time code NaN."""
    if not attr or not attr.HasAuthoredValue():
        return None
    times = list(attr.GetTimeSamples())
    samples = [attr.Get(t) for t in times] if times else [attr.Get()]
    if not times:
        times = [np.nan]
    out = np.empty((len(samples), count, comps))
    for i, (tc, v) in enumerate(zip(times, samples)):
        if v is None:
            raise where.error(f"animation <{anim_path}> {label} is blocked at time code {tc}")
        arr = _quats_xyzw(pxr, v) if comps == 4 else np.asarray(v, dtype=np.float64).reshape(-1, comps)
        if arr.shape[0] != count:
            at = "default value" if np.isnan(tc) else f"time code {tc:g}"
            raise where.error(
                f"animation <{anim_path}> {label} has {arr.shape[0]} entries at {at} but the "
                f"animation has {count} joints"
            )
        out[i] = arr
    if not np.all(np.isfinite(out)):
        raise where.error(f"animation <{anim_path}> {label} hold NaN or inf")
    return np.asarray(times, dtype=np.float64), out


def _read_animation(
    pxr: Any, stage: Any, tg: _Target, where: _Where, skel_joints: list[str], has_rest: bool
) -> dict[str, Clip]:
    """The bound SkelAnimation as one clip (empty dict when there is none)."""
    aq = tg.skel_query.GetAnimQuery()
    if not aq:
        return {}
    aprim = aq.GetPrim()
    apath = str(aprim.GetPath())
    if not aprim.IsA(pxr.UsdSkel.Animation):  # pragma: no cover - only SkelAnimation exists today
        where.warn(f"animation source <{apath}> is not a SkelAnimation; ignored")
        return {}
    anim = pxr.UsdSkel.Animation(aprim)
    anim_joints = anim.GetJointsAttr().Get()
    anim_joints = [str(n) for n in anim_joints] if anim_joints is not None else []
    if not anim_joints:
        where.warn(f"animation <{apath}> lists no joints; ignored")
        return {}
    mapper = pxr.UsdSkel.AnimMapper(pxr.Vt.TokenArray(anim_joints), pxr.Vt.TokenArray(skel_joints))
    if mapper.IsNull():
        where.warn(f"animation <{apath}> animates none of the skeleton's joints; ignored")
        return {}
    # anim_of[j]: index into the animation's arrays for skeleton joint j, or -1.
    anim_of = np.asarray(
        mapper.Remap(pxr.Vt.IntArray(list(range(len(anim_joints)))), defaultValue=-1), dtype=np.int64
    ).reshape(-1)
    if anim_of.size != len(skel_joints):  # pragma: no cover - defensive
        raise where.error(f"animation <{apath}> could not be mapped onto the skeleton's joints")
    if mapper.IsSparse() and not has_rest:
        where.warn(
            f"animation <{apath}> covers only some joints and the skeleton has no restTransforms; "
            "USD rejects that combination, warpskin uses the rest pose implied by bindTransforms"
        )
    a = len(anim_joints)
    keys = {
        "translation": _attr_keys(pxr, anim.GetTranslationsAttr(), "translations", a, where, apath, 3),
        "rotation": _attr_keys(pxr, anim.GetRotationsAttr(), "rotations", a, where, apath, 4),
        "scale": _attr_keys(pxr, anim.GetScalesAttr(), "scales", a, where, apath, 3),
    }
    missing = [name for name, v in keys.items() if v is None]
    if missing:
        where.warn(
            f"animation <{apath}> does not author {', '.join(missing)}; UsdSkel ignores such an "
            "animation, so the rig gets no clip"
        )
        return {}
    tcps = float(stage.GetTimeCodesPerSecond())
    if not np.isfinite(tcps) or tcps <= 0.0:
        raise where.error(f"stage timeCodesPerSecond is {tcps}")
    sampled = [v[0] for v in keys.values() if not np.isnan(v[0][0])]
    if sampled:
        const_tc = float(min(t.min() for t in sampled))
    elif stage.HasAuthoredTimeCodeRange():
        const_tc = float(stage.GetStartTimeCode())
    else:
        const_tc = 0.0
    held = stage.GetInterpolationType() == pxr.Usd.InterpolationTypeHeld
    interp = "STEP" if held else "LINEAR"
    tracks: dict[tuple[int, str], Track] = {}
    animated = np.nonzero(anim_of >= 0)[0]
    for path_name, (tcs, values) in keys.items():
        times = np.where(np.isnan(tcs), const_tc, tcs) / tcps
        for j in animated:
            tracks[(int(j), path_name)] = Track(path_name, times, values[:, anim_of[j], :], interp)
    name = aprim.GetName()
    return {name: Clip(name, tracks, rate=tcps)}


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------


def _dense_offsets(offsets: Any, indices: np.ndarray | None, n: int, label: str, where: _Where) -> np.ndarray:
    """A blend shape's (or inbetween's) offsets as one row per file point ``[n, 3]``: dense, or
    scattered by the shape's ``pointIndices`` (0 elsewhere). ``label`` names it in errors."""
    offsets = np.asarray(offsets if offsets is not None else [], dtype=np.float64).reshape(-1, 3)
    full = np.zeros((n, 3))
    if indices is None:
        if offsets.shape[0] != n:
            raise where.error(f"{label} has {offsets.shape[0]} offsets for {n} points and no pointIndices")
        full[:] = offsets
    else:
        if indices.shape[0] != offsets.shape[0]:
            raise where.error(f"{label}: {offsets.shape[0]} offsets for {indices.shape[0]} pointIndices")
        full[indices] = offsets
    if not np.all(np.isfinite(full)):
        raise where.error(f"{label} holds NaN or inf offsets")
    return full


def _blend_shapes(path: str | Path, mesh: str | None) -> tuple[Any, list[tuple[str, Any, np.ndarray | None]], int,
                                                               np.ndarray, _Where]:
    """The blend shapes bound to the chosen skinned mesh: ``(stage, [(name, BlendShape, point
    indices or None)], point count, geomBindTransform's linear part, where)``; the shapes are
    valid while the caller holds the stage."""
    pxr, stage, p = _open_stage(path)
    _, targets, others = _scan(pxr, stage)
    tg = _select(targets, others, mesh, p, pxr)
    where = _Where(p, str(tg.prim.GetPath()))
    t0 = pxr.Usd.TimeCode.EarliestTime()
    n = _point_count(pxr, tg.prim, t0)
    binding = pxr.UsdSkel.BindingAPI(tg.prim)
    names = list(binding.GetBlendShapesAttr().Get() or [])
    paths = list(binding.GetBlendShapeTargetsRel().GetForwardedTargets()) if binding.GetBlendShapeTargetsRel() else []
    if len(names) != len(paths):
        raise where.error(f"skel:blendShapes names {len(names)} shapes but skel:blendShapeTargets has {len(paths)}")
    geom_bind = np.array(tg.skinning.GetGeomBindTransform(t0), dtype=np.float64).T
    shapes = []
    for name, target in zip(names, paths):
        shape = pxr.UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        if not shape:
            raise where.error(f"blend shape {name!r}: {target} is not a BlendShape prim")
        indices = shape.GetPointIndicesAttr().Get()
        idx = None if indices is None or len(indices) == 0 else np.asarray(indices, dtype=np.int64)
        if idx is not None and (idx.min() < 0 or idx.max() >= n):
            raise where.error(f"blend shape {name!r} ({target}): pointIndices must lie in [0, {n - 1}]")
        shapes.append((str(name), shape, idx))
    return stage, shapes, n, geom_bind[:3, :3], where


def read_usd_blend_shapes(path: str | Path, *, mesh: str | None = None) -> dict[str, np.ndarray]:
    """The UsdSkel blend shapes bound to one skinned mesh, as offsets per file point.

    Args:
        path: A ``.usd``/``.usda``/``.usdc``/``.usdz`` file.
        mesh: The skinned mesh, as for :func:`load_usd` (default: the one with the most points).

    Returns:
        ``{name: offsets [N, 3]}`` in the order of the mesh's ``skel:blendShapes``, per file point
        (0 where a sparse shape's ``pointIndices`` leave a point out), in skeleton space
        (``geomBindTransform``'s linear part applied) and in the stage's units (multiply by the
        rig's ``meters_per_unit``). The shapes' inbetweens: :func:`read_usd_inbetweens`.

    Raises:
        RigError: names and targets that do not pair up, a target that is not a BlendShape,
            offsets that do not match the points or their indices; naming the file and prim.
    """
    stage, shapes, n, bind, where = _blend_shapes(path, mesh)  # noqa: F841 (holds the stage open)
    return {name: _dense_offsets(shape.GetOffsetsAttr().Get(), idx, n, f"blend shape {name!r} ({shape.GetPath()})",
                                 where) @ bind.T
            for name, shape, idx in shapes}


def read_usd_inbetweens(path: str | Path, *, mesh: str | None = None) -> dict[str, list[tuple[float, np.ndarray]]]:
    """The inbetween shapes of the UsdSkel blend shapes bound to one skinned mesh.

    A blend shape with inbetweens moves its points piecewise linearly in its weight ``w``:
    through 0 at ``w = 0``, each inbetween's offsets at its weight, and the shape's own offsets
    at ``w = 1`` (UsdSkel's blend shape rule, as ``UsdSkel.BlendShapeQuery`` computes it).

    Args:
        path, mesh: As :func:`read_usd_blend_shapes`.

    Returns:
        ``{shape name: [(weight, offsets [N, 3]), ...]}`` for the shapes that have inbetweens
        with weights strictly between 0 and 1 (sorted by weight; inbetweens outside [0, 1] only
        act on weights that an activation in [0, 1] never reaches and are left out), offsets
        per file point in the same space and units as :func:`read_usd_blend_shapes`'s.

    Raises:
        RigError: an inbetween at weight 0 or 1 or two at one weight, or offsets that do not
            match the shape's points; naming the file, prim and inbetween.
    """
    stage, shapes, n, bind, where = _blend_shapes(path, mesh)  # noqa: F841 (holds the stage open)
    out: dict[str, list[tuple[float, np.ndarray]]] = {}
    for name, shape, idx in shapes:
        levels = []
        for inb in shape.GetInbetweens():
            w = float(inb.GetWeight())
            label = f"inbetween {inb.GetAttr().GetBaseName()!r} of blend shape {name!r} ({shape.GetPath()})"
            if not math.isfinite(w) or w in (0.0, 1.0):
                raise where.error(f"{label} has weight {w}; an inbetween's weight must not be 0 or 1")
            if 0.0 < w < 1.0:
                levels.append((w, _dense_offsets(inb.GetOffsets(), idx, n, label, where) @ bind.T))
        levels.sort(key=lambda item: item[0])
        for (a, _), (b, _) in zip(levels, levels[1:]):
            if a == b:
                raise where.error(f"blend shape {name!r} ({shape.GetPath()}) has two inbetweens at weight {a}")
        if levels:
            out[name] = levels
    return out


def load_usd(path: str | Path, *, mesh: str | None = None, weld: bool = True) -> Rig:
    """Load a UsdSkel-skinned mesh with its skeleton and animation.

    Args:
        path: A ``.usd``/``.usda``/``.usdc``/``.usdz`` file.
        mesh: Which skinned mesh: its prim path or its name (last path element). Default: the
            skinned mesh with the most points.
        weld: Merge points that share a position (see :meth:`Rig.from_file_arrays`).

    Returns:
        The validated :class:`~warpskin.rig.Rig` in metres (lengths multiplied by the stage's
        ``metersPerUnit``). Rest vertices ``[V, 3]`` are in skeleton space
        (``geomBindTransform`` applied); every root joint's ``root_transform`` is the skeleton
        prim's local-to-world transform; ``inverse_bind`` ``[J, 4, 4]`` is the inverse of the
        skeleton's ``bindTransforms``. The bound ``SkelAnimation`` becomes one clip named after
        its prim, keyed at ``timeCode / timeCodesPerSecond`` [s], linearly interpolated
        (rotations slerped on the shorter arc, as USD does) or stepped when the stage uses
        held interpolation. Joints the animation does not cover keep their rest transform.

    Raises:
        RigError: The file is missing or not USD, there is no (such) skinned mesh, or the
            mesh, skin weights, skeleton or animation are malformed; the message names the
            file and prim.
    """
    pxr, stage, p = _open_stage(path)
    _, targets, others = _scan(pxr, stage)
    tg = _select(targets, others, mesh, p, pxr)
    prim_path = str(tg.prim.GetPath())
    where = _Where(p, prim_path)
    t0 = pxr.Usd.TimeCode.EarliestTime()

    points, triangles, corners, face = _read_mesh(pxr, tg, where, t0)
    skeleton, inverse_bind, has_rest = _read_skeleton(pxr, tg, where, t0)
    ji, jw = _read_influences(pxr, tg, where, t0, points.shape[0], skeleton.joint_names)

    sq = tg.skinning
    method = str(sq.GetSkinningMethod()) if hasattr(sq, "GetSkinningMethod") else "classicLinear"
    if method not in ("", "classicLinear"):
        where.warn(f"skel:skinningMethod is {method!r}; the rig is skinned with linear blend skinning")
    if sq.HasBlendShapes():
        where.warn("blend shapes are not applied to the skin (warpskin pop reads those named *clench*, *flex* or "
                   "*pump* as clenched examples, and those a scene's [popping.examples] maps)")
    geom_bind = np.array(sq.GetGeomBindTransform(t0), dtype=np.float64).T
    if not np.all(np.isfinite(geom_bind)) or abs(np.linalg.det(geom_bind[:3, :3])) < 1e-30:
        raise where.error("primvars:skel:geomBindTransform is singular or holds NaN/inf")
    rest = points @ geom_bind[:3, :3].T + geom_bind[:3, 3]
    if np.linalg.det(geom_bind[:3, :3]) < 0.0:  # a mirroring bind transform flips the winding
        triangles, corners = triangles[:, [0, 2, 1]], corners[:, [0, 2, 1]]
    render = _read_render(pxr, tg, where, t0, points.shape[0], triangles, corners, face, geom_bind)

    clips = _read_animation(pxr, stage, tg, where, skeleton.joint_names, has_rest)

    up = str(pxr.UsdGeom.GetStageUpAxis(stage))
    mpu = float(pxr.UsdGeom.GetStageMetersPerUnit(stage))
    if not np.isfinite(mpu) or mpu <= 0.0:
        raise RigError(f"{p}: stage metersPerUnit is {mpu}; it must be a positive number")
    try:
        rig = Rig.from_file_arrays(
            name=p.stem,
            points=rest,
            triangles=triangles,
            skeleton=skeleton,
            joint_indices=ji,
            joint_weights=jw,
            inverse_bind=inverse_bind,
            clips=clips,
            source=str(p),
            mesh_name=prim_path,
            weld=weld,
            up_axis=up,
            meters_per_unit=1.0,
            render=render,
        )
    except RigError as exc:
        msg = str(exc)
        prefix = f"{p}: "
        raise where.error(msg[len(prefix):] if msg.startswith(prefix) else msg) from None
    if mpu != 1.0:
        rig = rig.rescaled(mpu)
    return rig
