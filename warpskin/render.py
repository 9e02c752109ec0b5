"""``warpskin render``: pictures of a bake in Blender, the physical result beside LBS.

A bake written with ``--lbs`` holds every physically deformed mesh ``X`` and its LBS as the
guide ``X_lbs`` (the welded skin of older bakes: ``skin`` and ``lbs``). :func:`render_bake`
measures every such pair frame by frame (:mod:`warpskin.quality`: strained edges, flipped
triangles, offset), picks the worst frame (largest strained share beyond LBS's, then largest
offset) and a few others spread over the bake, and renders each in Blender with the physical
meshes on the left and LBS on the right, captioned with the frame's measures; a close-up of
the worst mesh at the worst frame follows. Blender runs as its Python module ``bpy`` in its
own interpreter (the README's ``.venv-bpy``), which executes
:mod:`warpskin.blender_render`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .mesh import triangulate_faces
from .units import extent
from .quality import STRAIN_LIMIT, WrittenMesh, mesh_measures

#: The colourings of :func:`render_bake`.
COLORS = ("plain", "offset", "motion")

__all__ = ["COLORS", "BakePair", "bake_pairs", "bake_quality", "find_blender_python", "render_bake"]


@dataclass
class BakePair:
    """A physically deformed mesh of a bake and its LBS guide (prim paths)."""

    name: str
    physical: str
    lbs: str


def bake_pairs(stage) -> list[BakePair]:
    """Every mesh of ``stage`` that has an LBS guide beside it: ``X`` with ``X_lbs``, or the
    older ``skin`` with ``lbs``."""
    from pxr import UsdGeom

    meshes = {p.GetPath().pathString: p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    out = []
    for path, prim in meshes.items():
        if path.endswith("_lbs") or prim.GetName() in ("lbs", "cage"):
            continue
        parent = prim.GetParent().GetPath().pathString
        guide = f"{path}_lbs" if f"{path}_lbs" in meshes else (f"{parent}/lbs" if prim.GetName() == "skin" else None)
        if guide in meshes:
            out.append(BakePair(prim.GetName(), path, guide))
    return out


def bake_quality(path, pairs: list[BakePair] | None = None) -> tuple[list[float], dict]:
    """The measures of every pair over every time sample of the bake: ``(time codes, {name:
    {measure: [per frame]}})`` (:func:`~warpskin.quality.mesh_measures` without pairs)."""
    from pxr import Usd, UsdGeom


    stage = Usd.Stage.Open(str(path))
    pairs = bake_pairs(stage) if pairs is None else pairs
    times: list[float] = []
    series: dict = {}
    for pair in pairs:
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(pair.physical))
        guide = UsdGeom.Mesh(stage.GetPrimAtPath(pair.lbs))
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
        idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
        tris = triangulate_faces(counts, idx)[0]
        attr = mesh.GetPointsAttr()
        rest = np.asarray(attr.Get(Usd.TimeCode.Default()) or attr.Get(Usd.TimeCode.EarliestTime()), dtype=np.float64)
        wm = WrittenMesh(pair.name, tris, rest)
        samples = attr.GetTimeSamples()
        times = list(samples) if len(samples) > len(times) else times
        s = series.setdefault(pair.name, {})
        for t in samples:
            m = mesh_measures(wm, np.asarray(attr.Get(t)), np.asarray(guide.GetPointsAttr().Get(t)), pairs=False)
            for k in ("strained", "strained_lbs", "flipped", "offset"):
                s.setdefault(k, []).append(m[k])
    return times, series


def find_blender_python(python: str | None = None) -> str:
    """The interpreter that has ``bpy``: ``python`` (only it, when given), else
    ``$WARPSKIN_BPY_PYTHON``, else ``.venv-bpy/bin/python`` in the current folder or beside the
    warpskin checkout.

    Raises:
        InputError: none of them imports ``bpy`` (one line naming what was tried).
    """
    tried = []
    here = Path(__file__).resolve().parents[1]
    given = [python] if python else [os.environ.get("WARPSKIN_BPY_PYTHON"), ".venv-bpy/bin/python",
                                     str(here / ".venv-bpy/bin/python")]
    for cand in given:
        if not cand or cand in tried:
            continue
        tried.append(cand)
        exe = shutil.which(cand) or (cand if Path(cand).is_file() else None)
        if exe is None:
            continue
        ok = subprocess.run([exe, "-c", "import bpy"], capture_output=True, timeout=120)
        if ok.returncode == 0:
            return exe
    raise InputError(f"render: no Python with Blender's bpy module found (tried {', '.join(tried)}); install it with "
                     "'python3.11 -m venv .venv-bpy && .venv-bpy/bin/pip install bpy==5.0.1' or pass --python")


def _where_worst(stage, pair: BakePair, tc: float) -> list[int]:
    """The vertices of the physical mesh to frame in a close-up at time code ``tc``: those on
    edges strained past 1.5x where LBS's are not, else those farthest from LBS (at least half
    the largest offset)."""
    from pxr import Usd, UsdGeom


    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(pair.physical))
    guide = UsdGeom.Mesh(stage.GetPrimAtPath(pair.lbs))
    attr = mesh.GetPointsAttr()
    rest = np.asarray(attr.Get(Usd.TimeCode.Default()) or attr.Get(Usd.TimeCode.EarliestTime()), dtype=np.float64)
    tris = triangulate_faces(mesh.GetFaceVertexCountsAttr().Get(), mesh.GetFaceVertexIndicesAttr().Get())[0]
    wm = WrittenMesh(pair.name, tris, rest)
    x = np.asarray(attr.Get(tc), dtype=np.float64)
    lb = np.asarray(guide.GetPointsAttr().Get(tc), dtype=np.float64)
    bad = (wm.strain(x) > STRAIN_LIMIT) & (wm.strain(lb) <= STRAIN_LIMIT)
    if bad.any():
        welded = np.unique(wm.edges[bad].ravel())
        return np.nonzero(np.isin(wm.weld, welded))[0].tolist()
    d = np.linalg.norm(x - lb, axis=1)
    return np.nonzero(d >= 0.5 * d.max())[0].tolist() if d.max() > 0 else list(range(len(x)))


def _height(stage, pairs: list[BakePair]) -> float:
    """The character's height in the bake's unit: the largest extent of its physical meshes'
    rest points together (as the run's chatter measure takes it)."""
    from pxr import Usd, UsdGeom

    rest = []
    for pair in pairs:
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(pair.physical)).GetPointsAttr()
        x = attr.Get(Usd.TimeCode.Default()) or attr.Get(Usd.TimeCode.EarliestTime())
        if x is not None and len(x):
            rest.append(np.asarray(x, dtype=np.float64))
    return extent(np.concatenate(rest)) if rest else 0.0


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def render_bake(bake, out_dir, *, frames: list[float] | None = None, extra: int = 2, close_up: bool = True,
                resolution: tuple[int, int] = (800, 900), python: str | None = None, progress: bool = True,
                yaw: float = 20.0, color: str = "plain") -> list[Path]:
    """Render ``bake`` (a USD file written with ``--lbs``) into PNGs in ``out_dir``: the worst
    frame and ``extra`` others (or exactly ``frames``, time codes), the physical meshes beside
    their LBS, captioned; with ``close_up``, also the worst frame framed on its worst mesh. The
    camera looks at the character's front turned by ``yaw`` degrees about the vertical (180:
    from behind). ``color``: ``plain`` (one colour per side), ``offset`` (the physical meshes
    coloured by each point's distance from its LBS) or ``motion`` (by the change of that offset
    since the previous time sample: what moves against the animation; 0 at the first), white at
    0 to red from the frame's 98th percentile over the physical meshes on, that scale in the
    caption as a share of the character's height. Returns the PNG paths.

    Raises:
        InputError: the bake does not exist, has no mesh with an LBS guide, a frame is not one
            of its time samples, or no Blender Python was found.
    """
    from pxr import Usd

    if color not in COLORS:
        raise InputError(f"render: color must be one of {', '.join(COLORS)}, got {color!r}")
    bake = Path(bake)
    if not bake.is_file():
        raise InputError(f"render: {bake}: no such file")
    stage = Usd.Stage.Open(str(bake))
    if stage is None:
        raise InputError(f"render: {bake}: not a USD file")
    pairs = bake_pairs(stage)
    if not pairs:
        raise InputError(f"render: {bake}: no mesh with an LBS guide beside it (bake it with --lbs)")
    exe = find_blender_python(python)
    times, series = bake_quality(bake, pairs)
    if not times:
        raise InputError(f"render: {bake}: no time samples")
    n = len(times)
    height = _height(stage, pairs)
    excess = np.max([np.asarray(s["strained"]) - np.asarray(s["strained_lbs"]) for s in series.values()], axis=0)
    offset = np.max([np.asarray(s["offset"]) for s in series.values()], axis=0)
    worst = int(np.lexsort((offset, excess))[-1])
    if frames is not None:
        chosen = []
        for f in frames:
            hits = [i for i, t in enumerate(times) if abs(t - float(f)) < 1e-6]
            if not hits:
                raise InputError(f"render: frame {f:g} is not a time sample of {bake} ({times[0]:g}..{times[-1]:g})")
            chosen.append(hits[0])
    else:
        chosen = [worst] + [int(round(k)) for k in np.linspace(0, n - 1, extra + 2)[1:-1]] if extra > 0 else [worst]
        chosen = list(dict.fromkeys(chosen))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = bake.stem
    views = []
    for i in chosen:
        views.append({"frame": times[i], "out": str(out_dir / f"{stem}_{times[i]:g}.png"),
                      "captions": _captions(stem, times[i], i, series, i == worst, height), "focus": None,
                      "previous": times[i - 1] if i > 0 else None})
    if close_up:
        name = max(series, key=lambda k: (series[k]["strained"][worst] - series[k]["strained_lbs"][worst],
                                          series[k]["offset"][worst]))
        pair = next(p for p in pairs if p.name == name)
        views.append({"frame": times[worst], "out": str(out_dir / f"{stem}_{times[worst]:g}_{name}.png"),
                      "captions": _captions(stem, times[worst], worst, {name: series[name]}, True, height, close=name),
                      "focus": [pair.physical], "focus_points": _where_worst(stage, pair, times[worst]),
                      "previous": times[worst - 1] if worst > 0 else None})
    job = {"bake": str(bake.resolve()), "views": views, "physical": [p.physical for p in pairs],
           "lbs": [p.lbs for p in pairs], "resolution": list(resolution), "yaw": float(yaw), "color": color,
           "height": height}
    script = Path(__file__).with_name("blender_render.py")
    with tempfile.TemporaryDirectory(prefix="warpskin-render-") as tmp:
        job_path = Path(tmp) / "job.json"
        job_path.write_text(json.dumps(job))
        run = subprocess.run([exe, str(script), str(job_path)], capture_output=True, text=True)
    if run.returncode != 0:
        tail = (run.stderr or run.stdout).strip().splitlines()[-1:] or ["no output"]
        raise InputError(f"render: Blender failed on {bake} (exit {run.returncode}): {tail[0]}")
    paths = [Path(v["out"]) for v in views]
    if progress:
        for p in paths:
            print(f"wrote {p}", file=sys.stderr)
    return paths


def _captions(stem: str, t: float, i: int, series: dict, worst: bool, height: float,
              close: str | None = None) -> list[list[str]]:
    """Two caption blocks (physical, LBS) for frame index ``i``: the worst mesh's figures; the
    largest offset from LBS as a share of ``height`` (the character's, in the bake's unit), which
    reads the same whatever unit the file is in."""
    name = max(series, key=lambda k: series[k]["strained"][i] - series[k]["strained_lbs"][i])
    s = series[name]
    where = f"{close} close-up, " if close else ""
    tag = " (worst frame)" if worst else ""
    flipped = max(series[k]["flipped"][i] for k in series)
    offset = max(series[k]["offset"][i] for k in series)
    return [
        [f"warpskin  {stem}  {where}frame {t:g}{tag}",
         f"strained edges {_pct(s['strained'][i])} ({name}), flipped {_pct(flipped)}, offset "
         f"{_pct(offset / height if height > 0 else 0.0)} of the height"],
        ["LBS", f"strained edges {_pct(s['strained_lbs'][i])} ({name})"],
    ]
