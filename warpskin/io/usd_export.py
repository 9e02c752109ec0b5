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

import os
import tempfile
from pathlib import Path

import numpy as np
from ..errors import OutputError

__all__ = ["UsdSkinWriter", "ExportError", "USD_EXTENSIONS"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc")


class ExportError(OutputError):
    """Writing the USD file failed; nothing was left under the target name."""


def _pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt
    except ImportError as exc:  # pragma: no cover - usd-core is a dependency
        raise ExportError("USD export needs usd-core: pip install usd-core") from exc
    return Gf, Sdf, Usd, UsdGeom, Vt


def _prim_name(name: str) -> str:
    out = "".join(c if (c.isalnum() or c == "_") else "_" for c in name)
    if not out or out[0].isdigit():
        out = "_" + out
    return out


class UsdSkinWriter:
    """Writes time-sampled skin surfaces to a USD stage.

    Args:
        path: Target file: ``.usdc`` (binary, default and fast), ``.usda`` (text) or ``.usd``
            (binary).
        fps: Frames per second; also the stage's time codes per second, so a frame number is
            its time code.
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: Stage ``metersPerUnit`` (warpskin writes metres: 1).
        root: Name of the root ``Xform`` prim.
        comment: Stage comment (e.g. the command line that made it).
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
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=f".tmp{ext}", dir=parent)
        os.close(fd)
        os.unlink(tmp)  # USD creates the layer itself; the name is reserved by its randomness
        self._tmp = Path(tmp)
        self._vt, self._gf, self._usdgeom, self._sdf = Vt, Gf, UsdGeom, Sdf
        self._stage = Usd.Stage.CreateNew(str(self._tmp))
        if self._stage is None:  # pragma: no cover
            raise ExportError(f"{self.path}: USD could not create a stage")
        self.fps = float(fps)
        st = self._stage
        st.SetTimeCodesPerSecond(self.fps)
        st.SetFramesPerSecond(self.fps)
        UsdGeom.SetStageUpAxis(st, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(st, float(meters_per_unit))
        self._root = UsdGeom.Xform.Define(st, Sdf.Path("/" + _prim_name(root)))
        st.SetDefaultPrim(self._root.GetPrim())
        if comment:
            st.GetRootLayer().comment = comment
        self._meshes: dict[str, tuple] = {}
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

        Returns:
            The prim path.
        """
        self._check_open()
        UsdGeom, Vt = self._usdgeom, self._vt
        key = "/".join(_prim_name(part) for part in name.split("/"))
        if key in self._meshes:
            raise ExportError(f"mesh {name!r} was already added")
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.size == 0:
            raise ExportError(f"mesh {name!r}: triangles must have shape [T, 3], got {tri.shape}")
        vertex_count = int(tri.max()) + 1
        if rest_points is not None:
            rest = np.asarray(rest_points, dtype=np.float32)
            if rest.shape[0] < vertex_count or rest.ndim != 2 or rest.shape[1] != 3:
                raise ExportError(
                    f"mesh {name!r}: rest points of shape {rest.shape} do not cover the {vertex_count} vertices the triangles use"
                )
            vertex_count = rest.shape[0]
        path = self._root.GetPath().AppendPath(key)
        mesh = UsdGeom.Mesh.Define(self._stage, path)
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
        self._meshes[key] = (mesh, pts_attr, ext_attr, vertex_count, animated)
        return str(path)

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
        key = "/".join(_prim_name(part) for part in name.split("/"))
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
        self._meshes[key] = (prim, None, None, pts.shape[0], False)
        return str(prim.GetPath())

    def add_group(self, name: str) -> UsdSkinWriter:
        """Not a new writer: returns self after defining an ``Xform`` scope ``name``; prims
        added with a ``"name/child"`` path land in it."""
        self._check_open()
        from pxr import UsdGeom

        UsdGeom.Xform.Define(self._stage, self._root.GetPath().AppendChild(_prim_name(name)))
        return self

    # ------------------------------------------------------------------ frames
    def write_frame(self, frame: float, points: dict[str, np.ndarray]) -> None:
        """Time-sample the points of some or all animated meshes at ``frame`` (a time code).

        Args:
            frame: Frame number; time [s] = frame / fps.
            points: Mesh name -> ``[V, 3]`` positions [m] (NumPy or anything with ``.numpy()``).

        Raises:
            ExportError: an unknown mesh name, a wrong vertex count, or NaN/inf positions
            (naming the mesh, the frame and the first bad vertex).
        """
        self._check_open()
        Vt = self._vt
        tc = float(frame)
        for name, pts in points.items():
            key = "/".join(_prim_name(part) for part in name.split("/"))
            if key not in self._meshes:
                raise ExportError(f"frame {frame}: no mesh {name!r} was added (meshes: {sorted(self._meshes)})")
            mesh, pts_attr, ext_attr, count, animated = self._meshes[key]
            if not animated:
                raise ExportError(f"mesh {name!r} was added as static")
            arr = pts.numpy() if hasattr(pts, "numpy") else pts
            arr = np.asarray(arr, dtype=np.float32)
            if arr.shape != (count, 3):
                raise ExportError(f"frame {frame}: mesh {name!r} expects {count} points [V, 3], got shape {arr.shape}")
            finite = np.isfinite(arr).all(axis=1)
            if not finite.all():
                bad = int(np.nonzero(~finite)[0][0])
                raise ExportError(f"frame {frame}: mesh {name!r} has a NaN or inf position at vertex {bad}")
            pts_attr.Set(Vt.Vec3fArray.FromNumpy(arr), tc)
            ext_attr.Set(self._extent(arr), tc)
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
            os.replace(self._tmp, self.path)
        except Exception as exc:
            self.abort()
            if isinstance(exc, ExportError):
                raise
            raise ExportError(f"{self.path}: writing failed: {exc}") from exc
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Drop everything written so far; the target path is left untouched."""
        self._stage = None
        self._closed = True
        try:
            self._tmp.unlink()
        except FileNotFoundError:
            pass

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

