"""Blender side of ``warpskin render``: runs inside a Python that has Blender's ``bpy`` module
(``.venv-bpy``), never imported by warpskin itself.

Usage (what :func:`warpskin.render.render_bake` runs)::

    python blender_render.py JOB.json

``JOB.json``::

    {"bake": "walk.usdc",
     "views": [{"frame": 12, "out": "walk_12.png", "captions": ["warpskin ...", "LBS ..."],
                "focus": ["/mannequin/shoe_l"] or null, "focus_points": [vertex, ...] or null}],
     "physical": ["/mannequin/body", ...], "lbs": ["/mannequin/lbs", ...],
     "resolution": [960, 720], "title": "...", "yaw": 20,
     "color": "plain" | "offset" | "motion", "height": 1.8}

(each view may also give ``"previous"``: the time code before its frame, or null.)

Every view renders the bake at one frame twice with the same orthographic camera, once with
the physical meshes and once with their LBS guides, with Blender's Workbench engine (no GPU
needed), and writes the two side by side into one PNG, each captioned. The camera frames the
physical meshes (or those named in ``focus``; with ``focus_points``, those vertices of the
first of them, with a margin) from the front, a little from the side; the bake
is imported with its guides (``import_guide=True``), as a reviewer would; ``yaw`` turns the
camera about the vertical (180: from behind).

With ``color`` ``offset`` or ``motion``, each view draws still copies of the meshes as evaluated
at its frame instead: the physical ones coloured per vertex by ``|P - L|`` (``offset``) or by
``|(P - L) - (P' - L')|`` (``motion``: ``'`` at the previous time code, 0 where there is none),
white at 0 to red from the 98th percentile of the values over the physical meshes on, the LBS
guides in their plain colour, and one more caption line gives the scale as a share of ``height``.
"""

import json
import math
import sys

import bpy
import numpy as np
from mathutils import Vector


def _objects_by_prim() -> dict:
    out = {}
    for obj in bpy.context.scene.objects:
        if obj.type != "MESH":
            continue
        path = None
        for mod in obj.modifiers:
            if mod.type == "MESH_SEQUENCE_CACHE":
                path = mod.object_path
        out[path or obj.name] = obj
    return out


def _world_points(obj, graph) -> np.ndarray:
    ev = obj.evaluated_get(graph)
    mesh = ev.to_mesh()
    pts = np.empty(len(mesh.vertices) * 3)
    mesh.vertices.foreach_get("co", pts)
    ev.to_mesh_clear()
    pts = pts.reshape(-1, 3)
    m = np.array(ev.matrix_world)
    return pts @ m[:3, :3].T + m[:3, 3]


def _ramp(value: np.ndarray, scale: float) -> np.ndarray:
    """``[N, 4]`` RGBA: white at 0 through orange to dark red at ``scale`` and beyond."""
    c = np.clip(value / scale, 0.0, 1.0) if scale > 0.0 else np.zeros_like(value)
    r = 1.0 - 0.45 * np.clip(2.0 * c - 1.0, 0.0, 1.0)
    g = 1.0 - np.clip(1.6 * c, 0.0, 1.0) * 0.85
    b = 1.0 - np.clip(2.0 * c, 0.0, 1.0)
    return np.stack([r, g, b, np.ones_like(c)], axis=1)


def _still_copy(scene, obj, graph, rgba: np.ndarray, per: str = "POINT"):
    """A still mesh object of ``obj`` as evaluated now, its vertices coloured ``rgba`` ``[N, 4]``
    (the colour attribute Workbench draws with ``color_type = "VERTEX"``; ``per="CORNER"``: one
    ``[1, 4]`` colour for every face corner)."""
    ev = obj.evaluated_get(graph)
    mesh = bpy.data.meshes.new_from_object(ev)
    attr = mesh.color_attributes.new("warpskin", "FLOAT_COLOR", per)
    rgba = np.asarray(rgba, dtype=np.float32)
    if per == "CORNER":
        rgba = np.tile(rgba.reshape(1, 4), (len(mesh.loops), 1))
    attr.data.foreach_set("color", rgba.ravel())
    mesh.color_attributes.active_color = attr
    mesh.color_attributes.render_color_index = mesh.color_attributes.active_color_index
    copy = bpy.data.objects.new(f"{obj.name}_still", mesh)
    copy.matrix_world = ev.matrix_world.copy()
    scene.collection.objects.link(copy)
    return copy


def _coloured(scene, view: dict, job: dict, physical: list, lbs: list) -> tuple[list, list, list]:
    """Still copies of the ``physical`` and ``lbs`` objects at the view's frame (the scene is
    there), coloured as ``job["color"]`` asks; and the caption lines of the scale."""
    graph = bpy.context.evaluated_depsgraph_get()
    now = [(_world_points(p, graph), _world_points(q, graph)) for p, q in zip(physical, lbs)]
    values = [np.linalg.norm(p - q, axis=1) for p, q in now]
    what = "offset from LBS"
    if job["color"] == "motion":
        what = "motion against LBS"  # since the previous time sample
        if view.get("previous") is None:
            values = [np.zeros(len(v)) for v in values]
        else:
            _goto(scene, view["previous"])
            graph = bpy.context.evaluated_depsgraph_get()
            before = [(_world_points(p, graph), _world_points(q, graph)) for p, q in zip(physical, lbs)]
            values = [np.linalg.norm((p - q) - (p0 - q0), axis=1) for (p, q), (p0, q0) in zip(now, before)]
            _goto(scene, view["frame"])
            graph = bpy.context.evaluated_depsgraph_get()
    every = np.concatenate(values) if values else np.zeros(0)
    scale = float(np.percentile(every, 98.0)) if every.size else 0.0  # one point's outlier leaves the rest drawn
    copies_p = [_still_copy(scene, o, graph, _ramp(v, scale)) for o, v in zip(physical, values)]
    copies_l = [_still_copy(scene, o, graph, np.tile([0.50, 0.62, 0.86, 1.0], (len(v), 1)))
                for o, v in zip(lbs, values)]
    share = 100.0 * scale / float(job.get("height") or 1.0)
    return copies_p, copies_l, [f"colour: {what}, red from {share:.2g} % of the height"]


def _camera(scene, lo: np.ndarray, hi: np.ndarray, aspect: float, yaw_deg: float = 20.0):
    cam_data = bpy.data.cameras.new("review")
    cam_data.type = "ORTHO"
    cam = bpy.data.objects.new("review", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    centre = 0.5 * (lo + hi)
    size = hi - lo
    yaw = math.radians(yaw_deg)
    # look along +y (the character faces -y after the importer's Y-up to Z-up turn), from the side
    direction = Vector((-math.sin(yaw), math.cos(yaw), 0.0))  # the camera's -z after its rotation
    distance = 4.0 * float(np.linalg.norm(size)) + 1.0
    cam.location = Vector(centre.tolist()) - direction * distance
    cam.rotation_euler = (math.radians(90.0), 0.0, yaw)
    width = abs(size[0] * math.cos(yaw)) + abs(size[1] * math.sin(yaw))
    # the orthographic scale spans the larger side of the picture
    cam_data.ortho_scale = 1.2 * max(width / min(1.0, aspect), size[2] / min(1.0, 1.0 / aspect)) + 1e-6
    cam_data.clip_end = 2.0 * distance + float(np.linalg.norm(size))
    return cam


def _goto(scene, t: float) -> None:
    """The scene at time code ``t`` (its fraction as a subframe)."""
    whole = math.floor(float(t))
    scene.frame_set(int(whole), subframe=float(t) - whole)


def _remove(objects: list) -> None:
    """Remove ``objects`` and the data blocks (mesh, curve, camera) they own."""
    for o in objects:
        data = o.data
        bpy.data.objects.remove(o)
        for kind, store in ((bpy.types.Mesh, bpy.data.meshes), (bpy.types.Curve, bpy.data.curves),
                            (bpy.types.Camera, bpy.data.cameras)):
            if isinstance(data, kind) and data.users == 0:
                store.remove(data)


def _caption(cam, text: str, aspect: float, row: int = 0):
    """A text object fixed in the camera's view, along its lower edge."""
    curve = bpy.data.curves.new(f"caption{row}", "FONT")
    curve.body = text
    obj = bpy.data.objects.new(f"caption{row}", curve)
    bpy.context.scene.collection.objects.link(obj)
    obj.parent = cam
    half_w = 0.5 * cam.data.ortho_scale * min(1.0, aspect)
    half_h = 0.5 * cam.data.ortho_scale * min(1.0, 1.0 / aspect)
    curve.size = 0.055 * half_w
    obj.location = (-0.95 * half_w, -half_h + (0.04 + 0.08 * row) * half_w, -1.0)
    obj.color = (0.05, 0.05, 0.05, 1.0)
    return obj


def main(job_path: str) -> None:
    job = json.loads(open(job_path).read())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=job["bake"], import_guide=True)
    scene = bpy.context.scene
    w, h = job.get("resolution", [960, 720])
    aspect = w / h
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    shading = scene.display.shading
    shading.light = "STUDIO"
    shading.color_type = "OBJECT"
    shading.show_cavity = True
    shading.show_shadows = False
    scene.world = scene.world or bpy.data.worlds.new("review")
    scene.world.color = (1.0, 1.0, 1.0)  # the film's background under Workbench
    scene.view_settings.view_transform = "Standard"
    objects = _objects_by_prim()
    physical = [objects[p] for p in job["physical"] if p in objects]
    lbs = [objects[p] for p in job["lbs"] if p in objects]
    missing = [p for p in job["physical"] + job["lbs"] if p not in objects]
    if missing:
        raise SystemExit(f"render: prims not imported by Blender: {missing[:4]}")
    for o in physical:
        o.color = (0.86, 0.66, 0.54, 1.0)
    for o in lbs:
        o.color = (0.50, 0.62, 0.86, 1.0)
    for view in job["views"]:
        _goto(scene, view["frame"])
        graph = bpy.context.evaluated_depsgraph_get()
        focus = [objects[p] for p in (view.get("focus") or []) if p in objects] or physical
        pts = np.concatenate([_world_points(o, graph) for o in focus])
        if view.get("focus_points"):  # the close-up: around these points of the first focus mesh
            pts = _world_points(focus[0], graph)[np.asarray(view["focus_points"], dtype=np.int64)]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if view.get("focus_points"):
            pad = 0.25 * float(np.linalg.norm(hi - lo)) + 1e-3 * float(np.linalg.norm(np.ptp(
                np.concatenate([_world_points(o, graph) for o in physical]), axis=0)))
            lo, hi = lo - pad, hi + pad
        cam = _camera(scene, lo, hi, aspect, float(job.get("yaw", 20.0)))
        panels = []
        sides, captions, copies = (physical, lbs), [list(c) for c in view["captions"]], []
        if job.get("color", "plain") != "plain":
            copies_p, copies_l, lines = _coloured(scene, view, job, physical, lbs)
            sides, copies = (copies_p, copies_l), copies_p + copies_l
            captions[0].extend(lines)
            shading.color_type = "VERTEX"
        for k, (shown, hidden) in enumerate(((sides[0], sides[1]), (sides[1], sides[0]))):
            for o in shown:
                o.hide_render = False
            for o in hidden:
                o.hide_render = True
            for o in scene.objects:  # everything else (the cage, the inner layers) stays out
                if o.type == "MESH" and o not in shown:
                    o.hide_render = True
            caps = [_caption(cam, line, aspect, row) for row, line in enumerate(reversed(captions[k]))]
            if copies:  # drawn by their vertex colours: the captions as still meshes in theirs
                graph = bpy.context.evaluated_depsgraph_get()
                still = [_still_copy(scene, c, graph, np.array([[0.05, 0.05, 0.05, 1.0]]), per="CORNER")
                         for c in caps]
                _remove(caps)
                caps = still
            path = f"{view['out']}.panel{k}.png"
            scene.render.filepath = path
            bpy.ops.render.render(write_still=True)
            _remove(caps)
            img = bpy.data.images.load(path)
            px = np.empty(w * h * 4, dtype=np.float32)
            img.pixels.foreach_get(px)
            panels.append(px.reshape(h, w, 4))
            bpy.data.images.remove(img)
            import os

            os.remove(path)
        _remove(copies)
        shading.color_type = "OBJECT"
        both = np.concatenate(panels, axis=1)
        out = bpy.data.images.new("review", width=2 * w, height=h, alpha=False)
        out.pixels.foreach_set(both.ravel())
        out.filepath_raw = view["out"]
        out.file_format = "PNG"
        out.save()
        bpy.data.images.remove(out)
        _remove([cam])
        print(f"wrote {view['out']}")


if __name__ == "__main__":
    main(sys.argv[-1])
