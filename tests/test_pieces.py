"""A character's own pieces as the simulation surface (warpskin.preprocess.pieces): boundary
loops and their caps against closed forms (a prism's volume), the pieces a character is made of
classified as what they are (a body simulated, a garment worn over it, a sheet, a small rigid
piece), decimation that keeps the holes' loops, and the collision groups: seams apart, the rest
colliding. Meshes are made here, in generic positions (no exact ties)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from oracles import point_mesh_distance
from warpskin.preprocess.pieces import PieceParams, boundary_loops, cap_loop, piece_surface
from warpskin.rig import mesh_edge_report
from warpskin.units import metres_per_unit


def _tube(p0, p1, radius: float, segments: int = 16, rings: int = 12, jitter: float = 0.0, seed: int = 0):
    """An open tube (no ends) from ``p0`` to ``p1``, triangles counter-clockwise from outside."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    a = (p1 - p0) / np.linalg.norm(p1 - p0)
    e1 = np.cross(a, [0.3, 0.5, 0.81])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    s = np.linspace(0.0, 1.0, rings)
    th = np.arange(segments) / segments * 2 * np.pi
    pts = p0 + s[:, None, None] * (p1 - p0) + radius * (np.cos(th)[None, :, None] * e1 + np.sin(th)[None, :, None] * e2)
    pts = pts.reshape(-1, 3)
    if jitter:
        pts = pts + np.random.default_rng(seed).normal(scale=jitter, size=pts.shape)
    k = np.arange(rings - 1)[:, None]
    j = np.arange(segments)[None, :]
    v00, v01 = (k * segments + j).ravel(), (k * segments + (j + 1) % segments).ravel()
    v10, v11 = ((k + 1) * segments + j).ravel(), ((k + 1) * segments + (j + 1) % segments).ravel()
    tris = np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)])
    c = pts[tris].mean(axis=1) - p0
    n = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])
    if np.einsum("ij,ij->i", n, c - np.outer(c @ a, a)).sum() < 0:
        tris = tris[:, ::-1]
    return pts, tris


def _closed_volume(points, tris) -> float:
    p = points[tris]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("rings", [False, True])
def test_capped_prism_is_closed_and_holds_its_exact_volume(rings):
    # a straight prism of a regular 16-gon, its two ends capped: closed, manifold, wound outward,
    # and (the caps planar) its volume is exactly the polygon's area times the length
    radius, length, n = 0.05, 0.4, 16
    pts, tris = _tube([0.01, 0.02, 0.03], [0.01 + 0.4 * 0.6, 0.02 + 0.4 * 0.8, 0.03], radius, segments=n)
    loops, simple = boundary_loops(tris)
    assert simple and len(loops) == 2
    edges = {tuple(e) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    for loop in loops:  # each loop in the order the tube's own triangles run its edges
        assert all((int(a), int(b)) in edges for a, b in zip(loop, np.roll(loop, -1)))
    allp, allt = pts, tris
    for loop in loops:
        new, t, _ = cap_loop(allp, loop, rings=rings)
        allp = np.concatenate([allp, new])
        allt = np.concatenate([allt, t])
    rep = mesh_edge_report(allt, len(allp))
    assert rep["closed"] and rep["manifold"]
    exact = 0.5 * n * radius ** 2 * np.sin(2 * np.pi / n) * length
    assert abs(_closed_volume(allp, allt) - exact) < 1e-9 * exact
    assert (len(allp) > len(pts)) == rings


def test_a_loop_that_cannot_be_capped_is_refused():
    # a saddle: the loop leaves its best plane by far more than its radius allows
    th = np.arange(24) / 24 * 2 * np.pi + 0.013
    pts = np.stack([np.cos(th), np.sin(th), 1.2 * np.cos(2 * th)], 1)
    assert cap_loop(pts, np.arange(24)) is None


def _character():
    """A body tube (open at both ends), a sleeve worn over its upper part, a flat sheet in front
    of it, a small rigid bead near it and a second tube meeting the body end to end: points,
    triangles, dense weights (3 joints), mesh of each point (all one mesh)."""
    parts = []
    body = _tube([0, 0, 0], [0, 1.0, 0], 0.08, segments=20, rings=30, jitter=1e-4, seed=1)
    sleeve = _tube([0, 0.55, 0], [0, 0.95, 0], 0.10, segments=24, rings=14, jitter=1e-4, seed=2)
    foot = _tube([0, -0.5, 0], [0, -0.004, 0], 0.06, segments=20, rings=16, jitter=1e-4, seed=3)
    u, v = np.meshgrid(np.linspace(-0.06, 0.06, 7), np.linspace(0.2, 0.4, 9), indexing="ij")
    sheet = np.stack([u, v, np.full_like(u, 0.13) + 0.01 * u * u], -1).reshape(-1, 3)
    idx = np.arange(63).reshape(7, 9)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    sheet_t = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    bead = trimesh.creation.icosphere(subdivisions=2, radius=0.01)
    bead_p = np.asarray(bead.vertices) + [0.11, 0.3, 0.0]
    for pts, tris, joint in ((body[0], body[1], 0), (sleeve[0], sleeve[1], 0), (foot[0], foot[1], 1),
                             (sheet, sheet_t, 0), (bead_p, np.asarray(bead.faces), 2)):
        parts.append((pts, tris, joint))
    points, triangles, dense, base = [], [], [], 0
    for pts, tris, joint in parts:
        w = np.zeros((len(pts), 3))
        if joint == 2:
            w[:, 2] = 1.0
        else:  # a blend along y between joints 0 and 1, so only the bead is rigid
            t = np.clip((pts[:, 1] + 0.5) / 1.5, 0.0, 1.0)
            w[:, 1], w[:, 0] = 1.0 - t, t
        points.append(pts)
        triangles.append(tris + base)
        dense.append(w)
        base += len(pts)
    return np.concatenate(points), np.concatenate(triangles), np.concatenate(dense)


def test_pieces_are_told_apart_and_the_surface_is_closed(device):
    points, tris, dense = _character()
    ps = piece_surface(points, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"],
                       joint_names=["spine", "leg", "bead"], params=PieceParams(max_vertices=None), device=device)
    assert ps is not None
    rep = mesh_edge_report(ps.triangles, ps.vertex_count)
    assert rep["closed"] and rep["manifold"]
    # every piece's closed surface winds outward: positive volume
    for k in np.nonzero(ps.simulated)[0]:
        t = ps.triangles[ps.vertex_piece[ps.triangles[:, 0]] == k]
        assert _closed_volume(ps.vertices, t) > 0
    piece_of = {name: k for k, name in enumerate(ps.groups.names)}
    kinds = {}
    for name, k in piece_of.items():
        kinds[name] = ("garment" if ps.garment[k] else "simulated" if ps.simulated[k] else
                       "rigid" if ps.rigid[k] else "sheet" if not ps.closable[k] else "attached")
    assert sorted(kinds.values()) == ["garment", "rigid", "sheet", "simulated", "simulated"]
    # the written points of a simulated piece are its vertices, exactly; caps are extra vertices
    on = ps.vertex_of_point >= 0
    assert np.array_equal(ps.vertices[ps.vertex_of_point[on]], points[on])
    assert ps.cap.sum() == 0  # strips across the loops by default: no point of their own
    # the two tubes meet end to end (4 mm apart): a seam zone near the joint, colliding elsewhere
    body, foot = (next(k for k in range(len(ps.groups.names)) if ps.simulated[k] and
                       ((ps.vertices[ps.vertex_piece == k][:, 1].min() > -0.1) == want)) for want in (True, False))
    g, ex = ps.groups.group, ps.groups.excluded
    near = (ps.vertex_piece == body) & (ps.vertices[:, 1] < 0.02)
    far = (ps.vertex_piece == body) & (ps.vertices[:, 1] > 0.3)
    foot_far = (ps.vertex_piece == foot) & (ps.vertices[:, 1] < -0.3)
    assert ex[np.ix_(np.unique(g[near]), np.unique(g[ps.vertex_piece == foot]))].all()
    assert not ex[np.ix_(np.unique(g[far]), np.unique(g[foot_far]))].any()


@pytest.mark.parametrize("scale", [0.5, 2.0, 1e-3, 1e-2, 1e2])
def test_decimation_does_not_depend_on_the_file_unit(device, scale):
    # the same character in another unit is reduced to the same surface, scaled (the quadric
    # collapse's error thresholds are absolute: it runs at about human size). Within a decade
    # (a power of two), every float of the reduction's input is exactly the same; across decades
    # (a file in millimetres or centimetres, or a 0.01 scale on its root) the file's points times
    # the power of ten are, as --unit-scale brings them to metres
    points, tris, dense = _character()
    prm = PieceParams(max_vertices=400, min_piece_points=60)
    small = points * scale
    metres = small / scale if scale in (0.5, 2.0) else small * metres_per_unit(np.ptp(small, axis=0).max())
    if scale not in (0.5, 2.0):
        assert not np.array_equal(metres, points)  # the round trip is not exact: a fair test
    ref = piece_surface(metres, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"], params=prm, device=device)
    other = piece_surface(small, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"], params=prm,
                          device=device)
    assert ref.decimated.any()
    assert other.vertex_count == ref.vertex_count
    assert np.array_equal(other.triangles, ref.triangles)
    ratio = np.ptp(metres, axis=0).max() / np.ptp(small, axis=0).max()
    np.testing.assert_allclose(other.vertices * ratio, ref.vertices, rtol=0.0, atol=1e-9 * np.ptp(points))


def test_decimation_keeps_the_loops_and_the_shape(device):
    points, tris, dense = _character()
    full = piece_surface(points, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"],
                         params=PieceParams(max_vertices=None), device=device)
    small = piece_surface(points, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"],
                          params=PieceParams(max_vertices=400, min_piece_points=60), device=device)
    assert small.decimated.any()
    assert small.vertex_count < full.vertex_count
    rep = mesh_edge_report(small.triangles, small.vertex_count)
    assert rep["closed"] and rep["manifold"]
    # the loops (the holes' rims) are kept point for point
    for k in np.nonzero(small.decimated)[0]:
        t_full = full.written_triangles[full.vertex_piece[full.written_triangles[:, 0]] == k]
        t_small = small.written_triangles[small.vertex_piece[small.written_triangles[:, 0]] == k]
        rims_full = np.sort(np.concatenate([full.vertices[lp] for lp in boundary_loops(t_full)[0]]), axis=0)
        rims_small = np.sort(np.concatenate([small.vertices[lp] for lp in boundary_loops(t_small)[0]]), axis=0)
        assert np.allclose(rims_full, rims_small, atol=1e-12)
        # every reduced vertex lies on (within a small share of the radius of) the piece as it was
        dist = point_mesh_distance(small.vertices[(small.vertex_piece == k) & ~small.cap], full.vertices, t_full)
        assert dist.max() < 0.05 * 0.08


def _patch(radius: float, centre, keep):
    """A patch of a sphere (the faces of an icosphere whose centroids pass ``keep``), its
    unused vertices dropped: an open sheet lying on a sphere, as a hair cap lies on a skull."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    f = f[keep(v[f].mean(axis=1))]
    used, f = np.unique(f, return_inverse=True)
    return v[used] + centre, f.reshape(-1, 3)


@pytest.mark.parametrize("bony", [0.25, 1.0])
def test_the_tissue_beneath_a_rigid_piece_is_thinned_on_its_joint_only(device, bony):
    # a head (a sphere, strongest joint "head", not rigid), a neck tube below it (strongest
    # joint "neck"), a hair cap (a patch of a sphere over the crown, rigid on "head": a sheet,
    # worn, not simulated) and a patch on the side of the head rigid on "neck": each head
    # vertex's factor is bony + (1 - bony) smoothstep(d / s - 1) with d its distance to the cap
    # (nearest point, brute force) and s the cap's half-diagonal, at most a worn piece's largest
    # gap; the side patch, on another
    # joint, lowers no head vertex but the neck's near it, and the spine's keep 1
    centre = np.array([0.0, 1.0, 0.0])
    head = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    head_p = np.asarray(head.vertices) * [1.0, 1.02, 0.97] + centre
    neck_p, neck_t = _tube([0, 0.55, 0], [0, 0.93, 0], 0.05, segments=20, rings=20, jitter=1e-4, seed=4)
    cap_p, cap_t = _patch(0.104, centre, lambda c: c[:, 1] > 0.094)
    side_p, side_t = _patch(0.103, centre, lambda c: c[:, 0] < -0.088)
    parts = [(head_p, np.asarray(head.faces), [0.0, 0.1, 0.9]), (neck_p, neck_t, None),
             (cap_p, cap_t, [0.0, 0.0, 1.0]), (side_p, side_t, [0.0, 1.0, 0.0])]
    points, tris, dense, base = [], [], [], 0
    for pts, t, w in parts:
        if w is None:  # spine to neck along the tube
            s = np.clip((pts[:, 1] - 0.55) / 0.38, 0.0, 1.0)
            w = np.stack([0.8 - 0.5 * s, 0.2 + 0.5 * s, np.zeros(len(pts))], axis=1)
        points.append(pts)
        tris.append(t + base)
        dense.append(np.broadcast_to(np.asarray(w, dtype=np.float64), (len(pts), 3)))
        base += len(pts)
    points, tris, dense = np.concatenate(points), np.concatenate(tris), np.concatenate(dense)
    ps = piece_surface(points, tris, dense, np.zeros(len(points), dtype=np.int64), ["guy"],
                       joint_names=["spine", "neck", "head"], params=PieceParams(max_vertices=None, bony_depth=bony),
                       device=device)
    assert ps is not None
    cap_piece, side_piece = (int(ps.piece_of_point[len(head_p) + len(neck_p) + k]) for k in (0, len(cap_p)))
    assert ps.rigid[cap_piece] and not ps.simulated[cap_piece] and ps.rigid[side_piece] and not ps.simulated[side_piece]
    f = ps.groups.depth_factor
    assert f.shape == (ps.vertex_count,)
    on_head = np.isin(ps.origin, np.arange(len(head_p))) & ~ps.cap
    on_neck = np.isin(ps.origin, len(head_p) + np.arange(len(neck_p)))
    assert on_head.sum() == len(head_p) and on_neck.any()
    d = np.linalg.norm(ps.vertices[on_head][:, None] - cap_p[None], axis=2).min(axis=1)
    reach = PieceParams().garment_gap * np.ptp(points, axis=0).max()  # a worn piece's largest gap
    s = 0.5 * np.linalg.norm(np.ptp(cap_p, axis=0))
    assert s > reach  # the cap's half-diagonal is cut to the reach
    s = reach
    u = np.clip(d / s - 1.0, 0.0, 1.0)
    np.testing.assert_allclose(f[on_head], bony + (1.0 - bony) * u * u * (3.0 - 2.0 * u), rtol=0, atol=1e-12)
    # the neck's points whose strongest joint is the neck, beside the side patch: by it alone;
    # those whose strongest joint is the spine: 1
    on_neck_joint = on_neck & (np.argmax(ps.dense_weights, axis=1) == 1)
    d = np.linalg.norm(ps.vertices[on_neck_joint][:, None] - side_p[None], axis=2).min(axis=1)
    u = np.clip(d / min(0.5 * np.linalg.norm(np.ptp(side_p, axis=0)), reach) - 1.0, 0.0, 1.0)
    np.testing.assert_allclose(f[on_neck_joint], bony + (1.0 - bony) * u * u * (3.0 - 2.0 * u), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(f[on_neck & ~on_neck_joint], 1.0)
    assert (on_neck & ~on_neck_joint).sum() > 100
    if bony < 1.0:
        assert (f[on_head] == bony).sum() > 50 and (f[on_head] == 1.0).sum() > 50  # thinned beneath, not beyond
        assert ((f[on_head] > bony) & (f[on_head] < 1.0)).sum() > 50  # blended between
