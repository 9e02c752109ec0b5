"""USD export of animated skins: one ``UsdGeom.Mesh`` per surface, topology written once,
``points`` and ``extent`` time-sampled per frame.

The stage is written to a temporary file beside the target and renamed over it only when
:meth:`UsdSkinWriter.close` succeeds, so an error mid-way never leaves a truncated file under
the requested name.

Example:
    >>> with UsdSkinWriter("arm.usdc", fps=30) as out:
    ...     out.add_mesh("skin", rig.triangles, rest_points=rig.vertices)
    ...     for frame in range(10):
    ...         out.write_frame(frame, {"skin": points_of(frame)})
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np
from .. import __version__
from ..errors import OutputError
from .render import group_normals

__all__ = ["UsdSkinWriter", "ExportError", "USD_EXTENSIONS", "check_output_path", "OutputLock", "valid_prim_name"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc")


class ExportError(OutputError):
    """Writing the USD file failed; nothing was left under the target name."""


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ExportError("USD export needs usd-core: pip install usd-core") from exc
    return Gf, Sdf, Usd, UsdGeom, Vt


def _file_name(name: str) -> str:
    out = "".join(c if (c.isalnum() or c in "-_.") else "_" for c in Path(name).name).lstrip(".")
    return out or "texture.png"


def _valid_faces(tri: np.ndarray) -> np.ndarray:
    """``[T]`` bool: triangles with three distinct vertices that no earlier triangle repeats (as
    a vertex set)."""
    t = np.asarray(tri, dtype=np.int64)
    distinct = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    _, first = np.unique(np.sort(t, axis=1), axis=0, return_index=True)
    unique = np.zeros(t.shape[0], dtype=bool)
    unique[first] = True
    return distinct & unique


def valid_prim_name(name: str) -> str:
    """A valid USD prim name made of ``name``: every character but a letter, a digit or ``_``
    replaced by ``_``, and ``_`` put before a name that is empty or starts with a digit."""
    out = "".join(c if (c.isalnum() or c == "_") else "_" for c in name)
    if not out or out[0].isdigit():
        out = "_" + out
    return out


def check_output_path(path: str | os.PathLike, *, inputs=()) -> Path:
    """Check, before any work, that a USD file can be written at ``path``: a USD extension, an
    existing folder we may write to, not a folder itself, a name short enough for the
    temporary name beside it, not being written by another run (:class:`OutputLock`), and not one
    of ``inputs`` (a bake never overwrites its source).
    Returns the path; raises :class:`ExportError` naming the problem."""
    p = Path(path)
    if p.is_dir():
        raise ExportError(f"{p}: is a folder; give a file name such as {p / 'bake.usdc'}")
    ext = p.suffix.lower()
    if ext not in USD_EXTENSIONS:
        raise ExportError(f"{p}: output must end in one of {USD_EXTENSIONS} (got {ext or 'no extension'})")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ExportError(f"{p}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ExportError(f"{p}: folder {parent} is not writable")
    limit = os.pathconf(parent, "PC_NAME_MAX") if hasattr(os, "pathconf") else 255
    longest = max(len(p.name.encode()), len(f".{p.stem}.xxxxxxxx.tmp{ext}".encode()), len(f"{p.stem}_textures".encode()),
                  len(f".{p.name}.lock".encode()))
    if longest > limit:
        raise ExportError(f"{p}: the file name is {len(p.name.encode())} bytes; with warpskin's temporary name it "
                          f"needs {longest}, over this file system's {limit}")
    try:  # what access() cannot tell (a read-only or virtual file system, a root-owned folder): try it
        fd, probe = tempfile.mkstemp(prefix=".warpskin-", suffix=".probe", dir=parent)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise ExportError(f"{p}: cannot write in folder {parent} ({exc.strerror or exc})") from None
    OutputLock(p).acquire().release()  # another run writing this file: refused now, not after the work
    for src in inputs:
        try:
            same = Path(src).exists() and p.exists() and os.path.samefile(src, p)
        except OSError:
            same = False
        if same or Path(src).resolve() == p.resolve():
            raise ExportError(f"{p}: is the input file; write the bake under another name")
    return p


#: Temporary files of writers not yet closed or aborted: a signal that lands between a writer's
#: creation and the code that would abort it still finds them (:func:`remove_temporary_files`).
_LIVE_TEMPORARIES: set[Path] = set()


def _block_stop_signals():
    import signal

    sigs = {getattr(signal, n) for n in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, n)}
    if not hasattr(signal, "pthread_sigmask") or not sigs:
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, sigs)


def _unblock(previous) -> None:
    if previous is not None:
        import signal

        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def remove_temporary_files() -> None:
    """Delete the temporary file of every writer still open (on SIGTERM/SIGHUP, at exit)."""
    for tmp in list(_LIVE_TEMPORARIES):
        try:
            tmp.unlink()
        except OSError:
            pass
        _LIVE_TEMPORARIES.discard(tmp)


class OutputLock:
    """An exclusive lock on an output path while a writer fills it: the hidden file
    ``.<name>.lock`` beside it, locked with ``flock`` (Linux, macOS; elsewhere no lock) and removed
    when the writer closes or aborts. A second run asked to write the same file while the first
    does is refused (:class:`ExportError`, exit 2) instead of both printing "wrote" and the last
    silently winning. A lock file left by a killed run (SIGKILL) is not held and is taken over.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.lock_path = self.path.with_name(f".{self.path.name}.lock")
        self._fd: int | None = None

    def acquire(self) -> OutputLock:
        """Take the lock (at once, or raise :class:`ExportError` naming the path)."""
        try:
            import fcntl
        except ImportError:  # no flock here: no lock
            return self
        for _ in range(8):  # a lock file removed between our open and our lock: open it again
            try:
                fd = os.open(self.lock_path, os.O_CREAT | os.O_RDWR, 0o644)
            except OSError as exc:
                raise ExportError(f"{self.path}: cannot write in folder {self.lock_path.parent} "
                                  f"({exc.strerror or exc})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise ExportError(f"{self.path}: another run is writing this file (its lock {self.lock_path.name} "
                                  f"is held); wait for it to finish or write another file") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                _LIVE_TEMPORARIES.add(self.lock_path)
                return self
            os.close(fd)
        raise ExportError(f"{self.path}: its lock {self.lock_path.name} keeps changing; another run is writing it")

    def release(self) -> None:
        """Remove the lock file and let the lock go (no-op when not held)."""
        if self._fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            self.lock_path.unlink()
        _LIVE_TEMPORARIES.discard(self.lock_path)
        os.close(self._fd)
        self._fd = None


def _remove_stale_temporaries(path: Path) -> list[Path]:
    """The temporary files of earlier writers of ``path`` that were killed before they could
    remove them (``.<stem>.*.tmp<ext>`` beside it), removed; call with its :class:`OutputLock`
    held (no live writer of ``path`` then owns one). Returns what was removed."""
    prefix, suffix = f".{path.stem}.", f".tmp{path.suffix.lower()}"
    gone = []
    with contextlib.suppress(OSError):
        for p in path.parent.iterdir():
            if p.name.startswith(prefix) and p.name.endswith(suffix) and p.is_file():
                with contextlib.suppress(OSError):
                    p.unlink()
                    gone.append(p)
    return gone


class UsdSkinWriter:
    """Writes time-sampled skin surfaces to a USD stage.

    Args:
        path: Target file: ``.usdc`` (binary, default and fast), ``.usda`` (text) or ``.usd``
            (binary).
        fps: Frames per second; also the stage's time codes per second, so a frame number is
            its time code.
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: Stage ``metersPerUnit`` (warpskin writes metres: 1).
        root: Name of the root ``Xform`` prim: the character's name, so that bakes of several
            characters can be referenced into one stage side by side. It is the stage's
            ``defaultPrim`` and of ``kind`` component.
        comment: Stage comment (e.g. the command line that made it).

    Materials (:meth:`add_material`) go under ``<root>/Looks``; their texture images are
    written beside the USD file, in ``<stem>_textures/``, when the writer closes.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        fps: float = 30.0,
        up_axis: str = "Y",
        meters_per_unit: float = 1.0,
        root: str = "warpskin",
        comment: str = "",
    ) -> None:
        Gf, Sdf, Usd, UsdGeom, Vt = _pxr()
        self.path = Path(path)
        ext = self.path.suffix.lower()
        if ext not in USD_EXTENSIONS:
            raise ExportError(f"{self.path}: output must end in one of {USD_EXTENSIONS} (got {ext or 'no extension'})")
        if not (np.isfinite(fps) and fps > 0):
            raise ExportError(f"fps must be a positive number, got {fps}")
        if up_axis not in ("Y", "Z"):
            raise ExportError(f"up axis must be 'Y' or 'Z', got {up_axis!r}")
        parent = self.path.parent if str(self.path.parent) else Path(".")
        if not parent.is_dir():
            raise ExportError(f"{self.path}: folder {parent} does not exist")
        blocked = _block_stop_signals()  # a stop signal waits until the temporary name is registered
        try:
            self._lock = OutputLock(self.path).acquire()
            _remove_stale_temporaries(self.path)  # a killed run's, now that no live writer has one
            try:
                fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=f".tmp{ext}", dir=parent)
            except OSError as exc:
                self._lock.release()
                raise ExportError(f"{self.path}: cannot write in folder {parent} ({exc.strerror or exc})") from None
            self._tmp = Path(tmp)
            _LIVE_TEMPORARIES.add(self._tmp)
            os.close(fd)
            os.unlink(tmp)  # USD creates the layer itself; the name is reserved by its randomness
        finally:
            _unblock(blocked)
        self._vt, self._gf, self._usdgeom, self._sdf = Vt, Gf, UsdGeom, Sdf
        try:
            self._stage = Usd.Stage.CreateNew(str(self._tmp))
        except Exception as exc:  # pxr's Tf.ErrorException: a folder that refuses the file
            self._stage = None
            _LIVE_TEMPORARIES.discard(self._tmp)
            self._lock.release()
            raise ExportError(f"{self.path}: USD could not create the file in {parent}: {exc}") from None
        if self._stage is None:  # pragma: no cover
            _LIVE_TEMPORARIES.discard(self._tmp)
            self._lock.release()
            raise ExportError(f"{self.path}: USD could not create a stage")
        self.fps = float(fps)
        st = self._stage
        st.SetTimeCodesPerSecond(self.fps)
        st.SetFramesPerSecond(self.fps)
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, float(meters_per_unit))
        self._root = UsdGeom.Xform.Define(st, Sdf.Path("/" + valid_prim_name(root)))
        st.SetDefaultPrim(self._root.GetPrim())
        from pxr import Kind, Usd as _Usd

        _Usd.ModelAPI(self._root.GetPrim()).SetKind(Kind.Tokens.component)
        self._textures: dict[str, bytes] = {}
        self._material_paths: dict[tuple, str] = {}
        self._animated_primvars: dict[str, dict] = {}
        if comment:
            st.GetRootLayer().comment = comment
        st.GetRootLayer().customLayerData = {"warpskin:version": __version__}  # what wrote it
        self._meshes: dict[str, tuple] = {}
        self._children: dict[str, str] = {}  # mesh key -> its prim's name under the root
        #: Faces left out per mesh (degenerate or repeated in the source), for the run's notes.
        self.dropped_faces: dict[str, int] = {}
        self._first: float | None = None
        self._last: float | None = None
        self._closed = False
        self.frames_written = 0

    # ------------------------------------------------------------------ set-up
    def add_mesh(
        self,
        name: str,
        triangles: np.ndarray,
        *,
        rest_points: np.ndarray | None = None,
        color: tuple[float, float, float] | None = None,
        animated: bool = True,
        purpose: str | None = None,
        vertex_primvars: dict[str, np.ndarray] | None = None,
        remap: np.ndarray | None = None,
        uvs: np.ndarray | None = None,
        normal_groups: np.ndarray | None = None,
        materials: list[tuple[str, np.ndarray]] | None = None,
        animated_primvars: tuple[str, ...] = (),
        prim_name: str | None = None,
    ) -> str:
        """Declare a surface. Its topology is written once.

        Args:
            name: Prim name under the root (sanitised to a USD identifier).
            triangles: ``[T, 3]`` vertex indices, counter-clockwise seen from outside.
            rest_points: ``[V, 3]`` positions [m] written as the default (untimed) value.
            color: Display colour, RGB in [0, 1].
            animated: False for a static prim (its points are the rest points only).
            purpose: Optional ``UsdGeom`` purpose (``"guide"`` hides it in renders).
            vertex_primvars: Static per-vertex float primvars ``{name: [V]}`` (vertex
                interpolation), for a DCC to colour the mesh by (e.g. the layer depth factor).
            remap: ``[V]`` index of every written vertex into the points :meth:`write_frame`
                is given (a file's seam-split vertices from the welded surface warpskin
                simulates); rest points are given already remapped.
            uvs: ``[T, 3, 2]`` texture coordinates per triangle corner (``primvars:st``,
                faceVarying).
            normal_groups: ``[V]`` smoothing group per vertex: normals (vertex interpolation)
                are then computed from every frame's points
                (:func:`~warpskin.io.render.group_normals`) and time-sampled with them.
            materials: ``[(material path, triangle indices)]`` from :meth:`add_material`: one
                covering every triangle is bound to the mesh, several as face GeomSubsets.
            animated_primvars: Names of per-vertex float primvars time-sampled with the points
                (``write_frame(..., primvars=...)``), e.g. the distance from LBS.
            prim_name: The prim's own name when it differs from ``name`` (the character's skin,
                written under its file's mesh name while callers keep calling it ``skin``); the
                prim then records ``name`` as its ``warpskin:role`` custom data.

        Returns:
            The prim path.
        """
        self._check_open()
        UsdGeom, Vt = self._usdgeom, self._vt
        key = "/".join(valid_prim_name(part) for part in name.split("/"))
        if key in self._meshes:
            raise ExportError(f"mesh {name!r} was already added")
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.size == 0:
            raise ExportError(f"mesh {name!r}: triangles must have shape [T, 3], got {tri.shape}")
        vertex_count = int(tri.max()) + 1
        # faces that repeat a vertex (a file's degenerate triangles) or repeat another face are
        # not written: DCCs reject them as invalid face data (Blender "corrects" the mesh)
        keep = _valid_faces(tri)
        if not keep.all():
            self.dropped_faces[name] = int((~keep).sum())
            tri = tri[keep]
            if uvs is not None:
                uvs = np.asarray(uvs).reshape(-1, 3, 2)[keep]
            if materials:
                new_index = np.cumsum(keep) - 1
                materials = [(m, new_index[np.asarray(f, dtype=np.int64)[keep[np.asarray(f, dtype=np.int64)]]])
                             for m, f in materials]
                materials = [(m, f) for m, f in materials if f.size]
        if rest_points is not None:
            rest = np.asarray(rest_points, dtype=np.float32)
            if rest.shape[0] < vertex_count or rest.ndim != 2 or rest.shape[1] != 3:
                raise ExportError(
                    f"mesh {name!r}: rest points of shape {rest.shape} do not cover the {vertex_count} vertices the triangles use"
                )
            vertex_count = rest.shape[0]
        if remap is not None:
            remap = np.asarray(remap, dtype=np.int64)
            if remap.ndim != 1 or remap.shape[0] != vertex_count:
                raise ExportError(f"mesh {name!r}: remap must give one source index per vertex ({vertex_count})")
        child = key if prim_name is None else valid_prim_name(prim_name)
        if child != key and (child in self._meshes or child in self._children.values()):
            raise ExportError(f"mesh {name!r}: prim name {child!r} is taken")
        self._children[key] = child
        path = self._root.GetPath().AppendPath(child)
        mesh = UsdGeom.Mesh.Define(self._stage, path)
        if child != key:
            mesh.GetPrim().SetCustomDataByKey("warpskin:role", key)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(tri.shape[0], 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tri.astype(np.int32).ravel()))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        pts_attr = mesh.CreatePointsAttr()
        ext_attr = mesh.CreateExtentAttr()
        if rest_points is not None:
            pts_attr.Set(Vt.Vec3fArray.FromNumpy(rest))
            ext_attr.Set(self._extent(rest))
        if color is not None:
            mesh.CreateDisplayColorAttr([self._gf.Vec3f(*map(float, color))])
        if purpose is not None:
            mesh.CreatePurposeAttr(purpose)
        for pv_name, values in (vertex_primvars or {}).items():
            vals = np.asarray(values, dtype=np.float32).ravel()
            if vals.shape[0] != vertex_count or not np.all(np.isfinite(vals)):
                raise ExportError(f"mesh {name!r}: primvar {pv_name!r} needs {vertex_count} finite values, got {vals.shape[0]}")
            pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(pv_name, self._sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex)
            pv.Set(Vt.FloatArray.FromNumpy(vals))
        if uvs is not None:
            st = np.asarray(uvs, dtype=np.float32).reshape(-1, 2)
            if st.shape[0] != 3 * tri.shape[0] or not np.isfinite(st).all():
                raise ExportError(f"mesh {name!r}: uvs must be finite, one per triangle corner ({3 * tri.shape[0]})")
            pv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", self._sdf.ValueTypeNames.TexCoord2fArray,
                                                         UsdGeom.Tokens.faceVarying)
            pv.Set(Vt.Vec2fArray.FromNumpy(st))
        normals = None
        if normal_groups is not None:
            groups = np.asarray(normal_groups, dtype=np.int64)
            if groups.shape != (vertex_count,):
                raise ExportError(f"mesh {name!r}: normal groups must be one per vertex ({vertex_count})")
            normals = (mesh.CreateNormalsAttr(), groups, tri.astype(np.int64))
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            if rest_points is not None:
                normals[0].Set(Vt.Vec3fArray.FromNumpy(self._normals(rest, normals)))
        for mat_path, faces in materials or []:
            material = self._usdshade().Material(self._stage.GetPrimAtPath(mat_path))
            faces = np.asarray(faces, dtype=np.int64)
            if faces.size == tri.shape[0]:
                binding = self._usdshade().MaterialBindingAPI.Apply(mesh.GetPrim())
                binding.Bind(material)
            else:
                subset = UsdGeom.Subset.CreateGeomSubset(mesh, valid_prim_name(material.GetPrim().GetName()),
                                                         UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces.astype(np.int32)),
                                                         "materialBind")
                self._usdshade().MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
        if materials and len(materials) > 1:  # one material per triangle: the subsets partition the faces
            covered = sum(np.asarray(f).size for _, f in materials)
            UsdGeom.Subset.SetFamilyType(mesh, "materialBind",
                                         UsdGeom.Tokens.partition if covered == tri.shape[0] else UsdGeom.Tokens.nonOverlapping)
        extra = {}
        for pv_name in animated_primvars:
            extra[pv_name] = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(pv_name, self._sdf.ValueTypeNames.FloatArray,
                                                                     UsdGeom.Tokens.vertex)
        self._meshes[key] = (mesh, pts_attr, ext_attr, vertex_count, animated, remap, normals)
        self._animated_primvars[key] = extra
        return str(path)

    @staticmethod
    def _usdshade():
        from pxr import UsdShade

        return UsdShade

    def _normals(self, points: np.ndarray, normals) -> np.ndarray:
        _, groups, tri = normals
        return group_normals(points, tri, groups).astype(np.float32)

    def add_material(self, material) -> str:
        """A ``UsdPreviewSurface`` material for a :class:`~warpskin.io.render.Material` under
        ``<root>/Looks``: its base colour, and its texture (read through ``primvars:st``)
        where it has one. Returns the material's path."""
        self._check_open()
        UsdShade, Sdf = self._usdshade(), self._sdf
        looks = self._root.GetPath().AppendChild("Looks")
        if not self._stage.GetPrimAtPath(looks):
            self._stage.DefinePrim(looks, "Scope")
        import hashlib

        identity = (material.name, tuple(float(c) for c in material.base_color),
                    hashlib.sha1(material.texture).hexdigest() if material.texture else "")
        if identity in self._material_paths:  # the same material again (several meshes share it)
            return self._material_paths[identity]
        base = valid_prim_name(material.name)
        path, k = looks.AppendChild(base), 1
        while self._stage.GetPrimAtPath(path):  # another material of that (sanitised) name
            path, k = looks.AppendChild(f"{base}_{k}"), k + 1
        self._material_paths[identity] = str(path)
        mat = UsdShade.Material.Define(self._stage, path)
        surface = UsdShade.Shader.Define(self._stage, path.AppendChild("PreviewSurface"))
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
        color = surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
        rgba = tuple(float(c) for c in material.base_color)
        color.Set(self._gf.Vec3f(*rgba[:3]))
        if rgba[3] < 1.0:
            surface.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(rgba[3])
        mat.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        if material.texture:
            name = _file_name(material.texture_name or f"{valid_prim_name(material.name)}.png")
            while name in self._textures and self._textures[name] != material.texture:
                name = "_" + name
            self._textures[name] = material.texture
            reader = UsdShade.Shader.Define(self._stage, path.AppendChild("stReader"))
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
            tex = UsdShade.Shader.Define(self._stage, path.AppendChild("BaseColorTexture"))
            tex.CreateIdAttr("UsdUVTexture")
            tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{self._texture_dir.name}/{name}"))
            tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
            tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
            tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(self._gf.Vec4f(*rgba[:3], 1.0))
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
            color.ConnectToSource(tex.ConnectableAPI(), "rgb")
        return str(path)

    @property
    def _texture_dir(self) -> Path:
        return self.path.with_name(f"{self.path.stem}_textures")

    def add_variant_set(self, name: str, variants: dict[str, dict[str, dict]], default: str) -> None:
        """A variant set on the root prim: ``{variant: {child prim name: {"visibility": ...,
        "purpose": ...}}}``, so that a reviewer flips between, e.g., the physical skin and LBS in
        any DCC."""
        self._check_open()
        from pxr import UsdGeom

        root = self._root.GetPrim()
        # a local opinion is stronger than any variant's: every attribute a variant sets moves
        # into the variants, each of which authors it (its own value, or the local one it had)
        keys = {(child, attr) for prims in variants.values() for child, ops in prims.items() for attr in ops}
        local = {}
        for child, attr in keys:
            target = root.GetChild(self._children.get(valid_prim_name(child), valid_prim_name(child)))
            held = target.GetAttribute(attr)
            local[(child, attr)] = held.Get() if held and held.HasAuthoredValue() else None
            if held:
                target.RemoveProperty(attr)
        vset = root.GetVariantSets().AddVariantSet(name)
        for variant, prims in variants.items():
            vset.AddVariant(variant)
            vset.SetVariantSelection(variant)
            with vset.GetVariantEditContext():
                for child, attr in sorted(keys):
                    value = prims.get(child, {}).get(attr, local[(child, attr)])
                    if value is None:
                        continue
                    img = UsdGeom.Imageable(root.GetChild(self._children.get(valid_prim_name(child), valid_prim_name(child))))
                    (img.CreateVisibilityAttr() if attr == "visibility" else img.CreatePurposeAttr()).Set(value)
        vset.SetVariantSelection(default)

    def add_points(
        self,
        name: str,
        points: np.ndarray,
        *,
        width: float = 0.002,
        color: tuple[float, float, float] | None = None,
    ) -> str:
        """A static ``UsdGeom.Points`` prim (e.g. constrained particles for inspection).

        Args:
            name: Prim name under the root.
            points: ``[N, 3]`` positions [m].
            width: Display diameter of every point [m].
            color: Display colour, RGB in [0, 1].
        """
        self._check_open()
        UsdGeom, Vt = self._usdgeom, self._vt
        key = "/".join(valid_prim_name(part) for part in name.split("/"))
        if key in self._meshes:
            raise ExportError(f"prim {name!r} was already added")
        pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if not np.isfinite(pts).all():
            raise ExportError(f"points {name!r} hold NaN or inf")
        prim = UsdGeom.Points.Define(self._stage, self._root.GetPath().AppendPath(key))
        prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        prim.CreateWidthsAttr(Vt.FloatArray.FromNumpy(np.full(pts.shape[0], width, dtype=np.float32)))
        if pts.shape[0]:
            prim.CreateExtentAttr(self._extent(pts))
        if color is not None:
            prim.CreateDisplayColorAttr([self._gf.Vec3f(*map(float, color))])
        self._meshes[key] = (prim, None, None, pts.shape[0], False, None, None)
        return str(prim.GetPath())

    def add_group(self, name: str) -> UsdSkinWriter:
        """Not a new writer: returns self after defining an ``Xform`` scope ``name``; prims
        added with a ``"name/child"`` path land in it."""
        self._check_open()
        from pxr import UsdGeom

        UsdGeom.Xform.Define(self._stage, self._root.GetPath().AppendChild(valid_prim_name(name)))
        return self

    # ------------------------------------------------------------------ frames
    def write_frame(self, frame: float, points: dict[str, np.ndarray], primvars: dict[str, dict] | None = None) -> None:
        """Time-sample the points of some or all animated meshes at ``frame`` (a time code).

        Args:
            frame: Frame number; time [s] = frame / fps.
            points: Mesh name -> ``[V, 3]`` positions [m] (NumPy or anything with ``.numpy()``).
            primvars: Mesh name -> ``{primvar: [V] values}`` for the mesh's animated primvars
                (given per source vertex, like the points, where the mesh remaps).

        Raises:
            ExportError: an unknown mesh name, a wrong vertex count, or NaN/inf positions
            (naming the mesh, the frame and the first bad vertex).
        """
        self._check_open()
        Vt = self._vt
        tc = float(frame)
        for name, pts in points.items():
            key = "/".join(valid_prim_name(part) for part in name.split("/"))
            if key not in self._meshes:
                raise ExportError(f"frame {frame}: no mesh {name!r} was added (meshes: {sorted(self._meshes)})")
            mesh, pts_attr, ext_attr, count, animated, remap, normals = self._meshes[key]
            if not animated:
                raise ExportError(f"mesh {name!r} was added as static")
            arr = pts.numpy() if hasattr(pts, "numpy") else pts
            arr = np.asarray(arr, dtype=np.float32)
            if remap is not None:
                if arr.ndim != 2 or arr.shape[0] <= int(remap.max()):
                    raise ExportError(f"frame {frame}: mesh {name!r} needs at least {int(remap.max()) + 1} points to "
                                      f"remap, got shape {arr.shape}")
                arr = arr[remap]
            if arr.shape != (count, 3):
                raise ExportError(f"frame {frame}: mesh {name!r} expects {count} points [V, 3], got shape {arr.shape}")
            finite = np.isfinite(arr).all(axis=1)
            if not finite.all():
                bad = int(np.nonzero(~finite)[0][0])
                raise ExportError(f"frame {frame}: mesh {name!r} has a NaN or inf position at vertex {bad}")
            pts_attr.Set(Vt.Vec3fArray.FromNumpy(arr), tc)
            ext_attr.Set(self._extent(arr), tc)
            if normals is not None:
                normals[0].Set(Vt.Vec3fArray.FromNumpy(self._normals(arr, normals)), tc)
        for name, values in (primvars or {}).items():
            key = "/".join(valid_prim_name(part) for part in name.split("/"))
            declared = self._animated_primvars.get(key, {})
            remap = self._meshes[key][5] if key in self._meshes else None
            for pv_name, vals in values.items():
                if pv_name not in declared:
                    raise ExportError(f"frame {frame}: mesh {name!r} has no animated primvar {pv_name!r}")
                v = np.asarray(vals, dtype=np.float32).ravel()
                v = v[remap] if remap is not None else v
                if v.shape[0] != self._meshes[key][3] or not np.isfinite(v).all():
                    raise ExportError(f"frame {frame}: primvar {pv_name!r} of mesh {name!r} needs "
                                      f"{self._meshes[key][3]} finite values")
                declared[pv_name].Set(Vt.FloatArray.FromNumpy(v), tc)
        self._first = tc if self._first is None else min(self._first, tc)
        self._last = tc if self._last is None else max(self._last, tc)
        self.frames_written += 1

    def _extent(self, arr: np.ndarray):
        lo, hi = arr.min(axis=0), arr.max(axis=0)
        return self._vt.Vec3fArray.FromNumpy(np.stack([lo, hi]).astype(np.float32))

    # ------------------------------------------------------------------ finish
    def close(self) -> Path:
        """Save the stage and move it to the target path. Returns the path."""
        if self._closed:
            return self.path
        try:
            if self._first is not None:
                self._stage.SetStartTimeCode(self._first)
                self._stage.SetEndTimeCode(self._last)
            self._stage.GetRootLayer().Save()
            self._stage = None
            self._write_textures()
            os.replace(self._tmp, self.path)
            _LIVE_TEMPORARIES.discard(self._tmp)
            self._lock.release()
        except Exception as exc:
            self.abort()
            if isinstance(exc, ExportError):
                raise
            raise ExportError(f"{self.path}: writing failed: {exc}") from exc
        self._closed = True
        return self.path

    def _write_textures(self) -> None:
        """The material images, each written to a temporary name and renamed into place."""
        if not self._textures:
            return
        folder = self._texture_dir
        folder.mkdir(exist_ok=True)
        for name, data in self._textures.items():
            fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
            try:
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                os.replace(tmp, folder / name)
            except BaseException:
                Path(tmp).unlink(missing_ok=True)
                raise

    def abort(self) -> None:
        """Drop everything written so far; the target path is left untouched."""
        self._stage = None
        self._closed = True
        try:
            self._tmp.unlink()
        except FileNotFoundError:
            pass
        _LIVE_TEMPORARIES.discard(self._tmp)
        self._lock.release()

    def _check_open(self) -> None:
        if self._closed:
            raise ExportError(f"{self.path}: the writer is closed")

    def __enter__(self) -> UsdSkinWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def __del__(self) -> None:  # an abandoned writer leaves no temp file behind
        if not getattr(self, "_closed", True):
            self.abort()

