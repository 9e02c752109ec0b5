"""Volume constraints per sub-volume (Deul & Bender 2013, section 4.6; PBD projection of
section 4.2.2): the gradient kernel against central finite differences, one PBD iteration
against a NumPy oracle, convergence, pinned particles and kinematic centers, the volume and
center kernels against the host sub-volumes, determinism. Every device."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import warp as wp

from oracles import rig_lbs
from warpskin.errors import InputError
from warpskin.preprocess.sub_volumes import SubVolumeParams, SubVolumes
from warpskin.model import ModelParams, SkinModelBuilder
from warpskin.scenes.arm import make_arm
from warpskin.skinning import Skinner
from warpskin.volume import VolumeConstraints, volume_layout

ARM = {"rings": 16, "segments": 12}


@functools.lru_cache(maxsize=None)
def _builder(single: bool = False) -> SkinModelBuilder:
    """The coarse arm (3 sub-volumes), or with both planes dropped (one closed sub-volume); as
    given (not refined: the kernels are tested on its own 194 vertices)."""
    params = ModelParams(subvolumes=SubVolumeParams(planes={"elbow": None, "wrist": None})) if single else ModelParams()
    params.refine = False
    return SkinModelBuilder(make_arm(**ARM), params).build()


@functools.lru_cache(maxsize=None)
def _model(device: str, single: bool = False):
    model = _builder(single).finalize(device)
    _BUILDER_OF[id(model)] = _builder(single)
    return model


_BUILDER_OF: dict = {}  # model id -> its builder (the model holds device arrays only)


def _host(model) -> SkinModelBuilder:
    """The builder (host view: rig, sub-volumes) of a cached model."""
    return _BUILDER_OF[id(model)]


def _setup(device: str, single: bool = False):
    model = _model(device, single)
    vc = VolumeConstraints(model)
    state = model.state()
    weight_scale = wp.ones(model.particle_count, dtype=wp.float32, device=model.device)
    return model, vc, state, weight_scale


def _perturbed(model, seed: int, scale: float = 0.002) -> np.ndarray:
    """All 4V particle positions, the skin layer moved by Gaussian noise [m]."""
    x = model.particle_q0.numpy().copy()
    rng = np.random.default_rng(seed)
    v = model.vertex_count
    x[:v] += rng.normal(scale=scale, size=(v, 3)).astype(np.float32)
    return x


def _skin(x: np.ndarray, v: int) -> np.ndarray:
    return np.asarray(x[:v], dtype=np.float64)


def _rel_error(sv: SubVolumes, x: np.ndarray, centers: np.ndarray) -> np.ndarray:
    return sv.volumes(_skin(x, sv.vertex_count), centers) / sv.rest_volume - 1.0


def _gradients_numpy(sv: SubVolumes, points: np.ndarray, centers: np.ndarray, surface_only: bool = False) -> np.ndarray:
    """Brute-force ``grad_i V_s`` [S, V, 3] from the closed triangles (float64); with
    ``surface_only`` from the surface triangles alone (without the closing fans), taken about
    the vertex itself: a third of its triangles' area-weighted normals."""
    v = sv.vertex_count
    allp = np.concatenate([points, centers.reshape(-1, 3)]) - points.mean(axis=0)
    g = np.zeros((sv.count, allp.shape[0], 3))
    for s in range(sv.count):
        tri = sv.closed_triangles(s)
        if surface_only:
            tri = tri[(tri < v).all(axis=1)]
        for r in range(3):
            a, b, c = tri[:, r], tri[:, (r + 1) % 3], tri[:, (r + 2) % 3]
            o = allp[a] if surface_only else 0.0
            np.add.at(g[s], a, np.cross(allp[b] - o, allp[c] - o) / 6.0)
    return g[:, :v]


def _dense_pairs(vc: VolumeConstraints) -> np.ndarray:
    """The kernel's per-pair gradients scattered to [S, V, 3]."""
    g = np.zeros((vc.subvolume_count, vc.vertex_count, 3))
    g[vc.pair_subvolume.numpy(), vc.pair_vertex.numpy()] = vc.pair_gradient.numpy()
    return g


# --------------------------------------------------------------------------------------------
# layout
# --------------------------------------------------------------------------------------------


def test_layout_pairs_entries_and_loop_vertices():
    sv = _builder().subvolumes
    lay = volume_layout(sv)
    v, s = sv.vertex_count, sv.count
    tri_count, fan_count = sv.tri_indices.size, sv.fan_triangles.shape[0]
    # 3 entries per surface triangle, 2 per fan (the center gets none)
    assert lay.entry_count == 3 * tri_count + 2 * fan_count
    assert lay.pair_entry_offsets[-1] == lay.entry_count and (np.diff(lay.pair_entry_offsets) > 0).all()
    # pairs sorted by (sub-volume, vertex), unique, and contiguous per sub-volume
    key = lay.pair_subvolume.astype(np.int64) * v + lay.pair_vertex
    assert (np.diff(key) > 0).all()
    np.testing.assert_array_equal(lay.subvolume_pair_offsets, np.searchsorted(lay.pair_subvolume, np.arange(s + 1)))
    # a vertex on a cut loop belongs to the two sub-volumes of its plane, every other to one
    on_loop = np.zeros(v, dtype=bool)
    on_loop[np.concatenate(sv.loops)] = True
    npairs = np.diff(lay.vertex_pair_offsets)
    np.testing.assert_array_equal(npairs, np.where(on_loop, 2, 1))
    assert (lay.pair_vertex[lay.vertex_pairs] == np.repeat(np.arange(v), npairs)).all()
    for k, loop in enumerate(sv.loops):
        for i in loop[:3]:
            pairs = lay.vertex_pairs[lay.vertex_pair_offsets[i] : lay.vertex_pair_offsets[i + 1]]
            assert sorted(lay.pair_subvolume[pairs].tolist()) == sorted(sv.plane_sides[k].tolist())
    # origins: the first fan center of each sub-volume (all have fans on the arm)
    assert (lay.subvolume_origin >= v).all()
    assert all(a.dtype == np.int32 for a in (lay.closed_triangles, lay.entry_points, lay.vertex_pairs))
    # one closed volume without planes: no centers, the origin is a skin vertex
    one = volume_layout(_builder(single=True).subvolumes)
    assert one.subvolume_count == 1 and one.center_count == 0 and one.subvolume_origin[0] < v
    assert (np.diff(one.vertex_pair_offsets) == 1).all()


# --------------------------------------------------------------------------------------------
# gradient
# --------------------------------------------------------------------------------------------


def test_gradient_kernel_matches_central_finite_differences(device):
    model, vc, state, ws = _setup(device)
    sv = _host(model).subvolumes
    v = model.vertex_count
    x = _perturbed(model, seed=1, scale=0.004)
    state.x.assign(x)
    centers = sv.center_rest + np.random.default_rng(2).normal(scale=0.005, size=sv.center_rest.shape)
    vc.centers.assign(centers.astype(np.float32))
    centers = vc.centers.numpy().astype(np.float64)
    vc.gradients(state.x, model.particle_inv_mass, ws, vc.centers)
    got = _dense_pairs(vc)

    # central differences of the host float64 volumes at the same (float32) positions; V_s is
    # linear in each coordinate, so the difference quotient is exact up to rounding
    p = _skin(x, v)
    h = 1e-5
    fd = np.zeros((sv.count, v, 3))
    for i in range(v):
        for d in range(3):
            q = p.copy()
            q[i, d] += h
            up = sv.volumes(q, centers)
            q[i, d] -= 2 * h
            fd[:, i, d] = (up - sv.volumes(q, centers)) / (2 * h)
    scale = np.abs(fd).max()
    err = np.abs(got - fd).max() / scale
    assert err < 1e-8, err
    # per sub-volume, and the loop vertices shared by two sub-volumes
    for s in range(sv.count):
        assert np.abs(got[s] - fd[s]).max() < 1e-8 * np.abs(fd[s]).max()
    for k, lp in enumerate(sv.loops):
        a, b = sv.plane_sides[k]
        assert (np.linalg.norm(fd[a, lp], axis=1) > 0).all() and (np.linalg.norm(fd[b, lp], axis=1) > 0).all()
        np.testing.assert_allclose(got[[a, b]][:, lp], fd[[a, b]][:, lp], rtol=0, atol=1e-8 * scale)
    # vertices outside a sub-volume carry no gradient (no pair in the kernel; FD zero up to
    # the rounding of the host's mean-centred sums)
    outside = np.all(got == 0.0, axis=2)
    assert np.abs(fd[outside]).max() < 1e-10 * scale
    member = np.zeros((sv.count, v), dtype=bool)  # vertex i is on the closed surface of s
    for s_ in range(sv.count):
        ids = sv.closed_triangles(s_).ravel()
        member[s_, ids[ids < v]] = True
    assert np.array_equal(outside, ~member)
    # and the brute-force closed-triangle sum agrees
    np.testing.assert_allclose(got, _gradients_numpy(sv, p, centers), rtol=0, atol=1e-12 * scale)
    # the paper's projection moves along the gradient: weighted norms w_i |grad_i V_s|^2
    pair_vertex, pair_subvolume = vc.pair_vertex.numpy(), vc.pair_subvolume.numpy()
    assert np.array_equal(vc.pair_direction.numpy(), vc.pair_gradient.numpy())
    w = model.particle_inv_mass.numpy()[pair_vertex].astype(np.float64)
    g = fd[pair_subvolume, pair_vertex]
    np.testing.assert_allclose(vc.pair_weighted_norm.numpy(), w * np.einsum("ij,ij->i", g, g), rtol=1e-7)
    # along the normals: the surface triangles' part of the gradient (brute force), equal to the
    # gradient off the cut loops and different on them (the fans' part); w_i grad_i V_s . d_i
    along = VolumeConstraints(model, along_normals=True)
    along.centers.assign(vc.centers.numpy())
    along.gradients(state.x, model.particle_inv_mass, ws, along.centers)
    np.testing.assert_array_equal(along.pair_gradient.numpy(), vc.pair_gradient.numpy())
    direction = np.zeros_like(got)
    direction[pair_subvolume, pair_vertex] = along.pair_direction.numpy()
    surface = _gradients_numpy(sv, p, centers, surface_only=True)
    np.testing.assert_allclose(direction, surface, rtol=0, atol=1e-12 * scale)
    on_loop = np.zeros(v, dtype=bool)
    on_loop[np.concatenate(sv.loops)] = True
    np.testing.assert_allclose(direction[:, ~on_loop], got[:, ~on_loop], rtol=0, atol=1e-12 * scale)
    assert np.abs(direction[:, on_loop] - got[:, on_loop]).max() > 1e-3 * scale
    dd = surface[pair_subvolume, pair_vertex]
    want = w * np.einsum("ij,ij->i", g, dd)
    np.testing.assert_allclose(along.pair_weighted_norm.numpy(), want, rtol=1e-6, atol=1e-9 * np.abs(want).max())


# --------------------------------------------------------------------------------------------
# projection
# --------------------------------------------------------------------------------------------


def test_one_projection_removes_the_error_of_a_single_closed_volume(device):
    model, vc, state, ws = _setup(device, single=True)
    sv = _host(model).subvolumes
    assert sv.count == 1 and vc.center_count == 0
    v = model.vertex_count
    x = model.particle_q0.numpy().copy()
    c = x[:v].mean(axis=0)
    x[:v] = c + (x[:v] - c) * np.float32(0.95 ** (1.0 / 3.0))  # 5 % volume lost
    state.x.assign(x)
    centers = vc.centers  # [0]
    e0 = abs(_rel_error(sv, x, np.zeros((0, 3)))[0])
    assert e0 == pytest.approx(0.05, rel=1e-3)
    vc.project(state.x, model.particle_inv_mass, ws, centers, iterations=1)
    e1 = abs(_rel_error(sv, state.x.numpy(), np.zeros((0, 3)))[0])
    vc.project(state.x, model.particle_inv_mass, ws, centers, iterations=2)
    e3 = abs(_rel_error(sv, state.x.numpy(), np.zeros((0, 3)))[0])
    assert e1 < 1e-3, e1  # linearisation error: second order in the 5 %
    assert e3 < 1e-6, e3
    # only the skin layer moved
    np.testing.assert_array_equal(state.x.numpy()[v:], x[v:])


@pytest.mark.parametrize("along_normals", [False, True])
def test_one_iteration_matches_numpy_pbd_with_inverse_masses(device, along_normals):
    model, vc, state, ws = _setup(device)
    vc = VolumeConstraints(model, along_normals=along_normals)
    sv = _host(model).subvolumes
    v = model.vertex_count
    rng = np.random.default_rng(3)
    x0 = _perturbed(model, seed=4, scale=0.003)
    state.x.assign(x0)
    inv_mass = (model.particle_inv_mass.numpy() * rng.uniform(0.2, 5.0, model.particle_count)).astype(np.float32)
    scale = np.ones(model.particle_count, dtype=np.float32)
    scale[rng.choice(v, size=v // 10, replace=False)] = 0.0  # colliding particles
    ws.assign(scale)
    im = wp.array(inv_mass, dtype=wp.float32, device=model.device)
    stiffness = 0.8
    vc.project(state.x, im, ws, vc.centers, iterations=1, stiffness=stiffness)
    x1 = state.x.numpy()

    # NumPy oracle: dp_i = w_i sum_s lambda_s d_i, lambda_s = -k C_s / sum_j w_j grad_j V_s . d_j
    # with d the gradient (the paper), or along the normals its surface part
    p = _skin(x0, v)
    centers = vc.centers.numpy().astype(np.float64)  # the float32 rest centers
    g = _gradients_numpy(sv, p, centers)
    d = _gradients_numpy(sv, p, centers, surface_only=True) if along_normals else g
    w = inv_mass[:v].astype(np.float64) * scale[:v]
    vol = sv.volumes(p, centers)
    lam = -float(np.float32(stiffness)) * (vol - sv.rest_volume) / np.einsum("v,svd,svd->s", w, g, d)
    dp = w[:, None] * np.einsum("s,svd->vd", lam, d)
    np.testing.assert_allclose(vc.subvolume_volume.numpy(), vol, rtol=1e-12)
    np.testing.assert_allclose(vc.subvolume_lambda.numpy(), lam, rtol=1e-9)
    np.testing.assert_allclose(x1[:v], p + dp, rtol=0, atol=2e-7)
    assert np.abs(dp).max() > 1e-4  # the correction is far above the tolerance
    # pinned particles and the inner layers stay bit-identical
    np.testing.assert_array_equal(x1[:v][scale[:v] == 0], x0[:v][scale[:v] == 0])
    np.testing.assert_array_equal(x1[v:], x0[v:])
    # heavier particles move less: dp_i . g_i / (w_i |g_i|^2) is the same lambda for every
    # moving vertex of one sub-volume (vertices off the loops belong to one only)
    on_loop = np.zeros(v, dtype=bool)
    on_loop[np.concatenate(sv.loops)] = True
    d = (x1[:v] - x0[:v]).astype(np.float64)
    for s in range(sv.count):
        gs = g[s]
        sel = (~on_loop) & (w > 0) & (np.linalg.norm(gs, axis=1) > 0)
        sel &= np.linalg.norm(w[:, None] * gs, axis=1) * abs(lam[s]) > 1e-5  # well above float32 rounding
        assert sel.sum() >= 8
        ratio = np.einsum("vd,vd->v", d[sel], gs[sel]) / (w[sel] * np.einsum("vd,vd->v", gs[sel], gs[sel]))
        np.testing.assert_allclose(ratio, lam[s], rtol=2e-2)


def test_the_fused_cap_is_each_iteration_then_a_radial_clamp(device):
    """``project(..., cap=)`` against the uncapped iteration followed by a NumPy clamp of every
    skin vertex (pinned ones too) to its radius around its target, three times over."""
    model, vc, state, ws = _setup(device)
    v = model.vertex_count
    rng = np.random.default_rng(11)
    x0 = _perturbed(model, seed=12, scale=0.004)
    scale = np.ones(model.particle_count, dtype=np.float32)
    pinned = rng.choice(v, size=v // 10, replace=False)
    scale[pinned] = 0.0
    ws.assign(scale)
    targets = (x0[:v] + rng.normal(scale=0.003, size=(v, 3))).astype(np.float32)
    # generic radii: some vertices far inside their sphere, some far outside (none near it)
    gap = np.linalg.norm(x0[:v].astype(np.float64) - targets, axis=1)
    radius = (gap * rng.choice([0.3, 3.0], size=v)).astype(np.float32)
    t_dev = wp.array(targets, dtype=wp.vec3, device=model.device)
    r_dev = wp.array(radius, dtype=wp.float32, device=model.device)
    capped = wp.zeros(1, dtype=wp.int32, device=model.device)
    state.x.assign(x0)
    vc.project(state.x, model.particle_inv_mass, ws, vc.centers, iterations=3, cap=(t_dev, r_dev, capped))
    fused = state.x.numpy().copy()

    ref = x0.copy()
    clamps = near = 0
    for _ in range(3):
        state.x.assign(ref)
        vc.project(state.x, model.particle_inv_mass, ws, vc.centers, iterations=1)
        ref = state.x.numpy().copy()
        d = ref[:v].astype(np.float64) - targets
        dl = np.linalg.norm(d, axis=1)
        out = dl > radius
        ref[:v][out] = targets[out] + d[out] * (radius[out] / dl[out])[:, None]
        clamps += int(out.sum())
        # float32 may decide these either way: a vertex clamped before lies on its sphere
        near += int((np.abs(dl - radius) < 1e-5 * radius).sum())
    np.testing.assert_allclose(fused[:v], ref[:v], rtol=0, atol=2e-6)
    assert clamps - near >= v // 3  # clamps decided well away from the sphere
    assert clamps - near <= capped.numpy()[0] <= clamps + near
    # within the radius up to float32 rounding of the coordinates (about 0.6 m: 6e-8 m)
    assert (np.linalg.norm(fused[:v].astype(np.float64) - targets, axis=1) <= radius + 1e-6).all()
    assert set(np.nonzero(np.abs(fused[pinned] - x0[pinned]).max(axis=1) > 0)[0]) <= set(
        np.nonzero(gap[pinned] > radius[pinned])[0])  # a pinned vertex moves only by its clamp
    np.testing.assert_array_equal(fused[v:], x0[v:])  # the inner layers stay
    with pytest.raises(InputError, match="cap radius"):
        vc.project(state.x, model.particle_inv_mass, ws, vc.centers, iterations=1,
                   cap=(t_dev, wp.zeros(3, dtype=wp.float32, device=model.device), capped))


def test_iterations_converge_with_pinned_particles_and_kinematic_centers(device):
    model, vc, state, ws = _setup(device)
    sv = _host(model).subvolumes
    v = model.vertex_count
    x0 = _perturbed(model, seed=5, scale=0.003)
    # and squeeze the forearm piece by 4 % toward the bone axis (x)
    fore = np.unique(sv.triangles[sv.tri_indices[sv.tri_offsets[1] : sv.tri_offsets[2]]])
    fore = np.setdiff1d(fore, np.concatenate(sv.loops))
    x0[fore, 1:] *= np.float32(0.98)
    state.x.assign(x0)
    rng = np.random.default_rng(6)
    pinned = rng.choice(v, size=v // 5, replace=False)
    scale = np.ones(model.particle_count, dtype=np.float32)
    scale[pinned] = 0.0
    ws.assign(scale)
    c0 = vc.centers.numpy().copy()  # the rest centers
    e0 = _rel_error(sv, x0, sv.center_rest)
    assert np.abs(e0).min() > 1e-3
    vc.project(state.x, model.particle_inv_mass, ws, vc.centers, iterations=8)
    x1 = state.x.numpy()
    e8 = _rel_error(sv, x1, sv.center_rest)
    assert (np.abs(e8) < 1e-3 * np.abs(e0)).all(), (e0, e8)
    np.testing.assert_array_equal(vc.centers.numpy(), c0)  # kinematic: never written
    np.testing.assert_array_equal(x1[pinned], x0[pinned])
    np.testing.assert_array_equal(x1[v:], x0[v:])
    assert np.isfinite(x1).all()


def test_a_fully_pinned_subvolume_is_skipped(device):
    model, vc, state, ws = _setup(device)
    sv = _host(model).subvolumes
    x0 = _perturbed(model, seed=7)
    state.x.assign(x0)
    wrist = np.unique(sv.triangles[sv.tri_indices[sv.tri_offsets[2] : sv.tri_offsets[3]]])
    scale = np.ones(model.particle_count, dtype=np.float32)
    scale[wrist] = 0.0
    ws.assign(scale)
    vc.project(state.x, model.particle_inv_mass, ws, vc.centers, iterations=3)
    x1 = state.x.numpy()
    assert np.isfinite(x1).all()
    assert vc.subvolume_lambda.numpy()[2] == 0.0 and vc.subvolume_lambda.numpy()[1] != 0.0
    np.testing.assert_array_equal(x1[wrist], x0[wrist])
    e = _rel_error(sv, x1, sv.center_rest)
    assert e[2] == pytest.approx(_rel_error(sv, x0, sv.center_rest)[2], rel=1e-12)  # nothing of it moved
    assert abs(e[0]) < 1e-5 and abs(e[1]) < 1e-5


def test_projection_is_deterministic(device):
    model, vc, state, ws = _setup(device)
    x0 = _perturbed(model, seed=8, scale=0.003)
    other = VolumeConstraints(model)
    runs = []
    for obj in (vc, vc, other):
        state.x.assign(x0)
        obj.project(state.x, model.particle_inv_mass, ws, obj.centers, iterations=4)
        runs.append((state.x.numpy().tobytes(), obj.subvolume_lambda.numpy().tobytes()))
    assert runs[0] == runs[1] == runs[2]


# --------------------------------------------------------------------------------------------
# volumes and centers
# --------------------------------------------------------------------------------------------


def test_volumes_and_centers_match_the_host_at_rest_and_posed(device):
    model, vc, state, _ = _setup(device)
    sv = _host(model).subvolumes
    rig = _host(model).rig
    out = wp.zeros(sv.count, dtype=wp.float32, device=model.device)
    control = model.control()
    vc.center_positions(control.skin_matrices, vc.centers)  # bind pose: the rest centers
    np.testing.assert_allclose(vc.centers.numpy(), sv.center_rest, atol=1e-7)
    vc.volumes(state.x, vc.centers, out)
    np.testing.assert_allclose(out.numpy(), sv.rest_volume, rtol=1e-6)

    skinner = Skinner(rig, method="lbs", device=model.device)
    for t in (0.75, 1.5):  # flexing, then at 150 degrees
        skin = rig.skinning_matrices("flex", t)
        control.set_pose(skin)
        vc.center_positions(control.skin_matrices, vc.centers)
        ref_centers = sv.center_positions(skin)
        np.testing.assert_allclose(vc.centers.numpy(), ref_centers, atol=1e-6)
        pts = skinner.skin(skin)
        vc.volumes(pts, vc.centers, out)
        # against float64 LBS and centers: the float32 rounding of the skinned inputs moves the
        # small hand cap (2e-5 m^3 on this coarse arm) by up to ~3e-6, the others by < 1e-6
        ref = sv.volumes(rig_lbs(rig, skin), ref_centers)
        np.testing.assert_allclose(out.numpy()[:2], ref[:2], rtol=1e-6)
        np.testing.assert_allclose(out.numpy(), ref, rtol=5e-6)
        # against the same float32 inputs: float32 rounding of the result only
        same = sv.volumes(pts.numpy().astype(np.float64), vc.centers.numpy().astype(np.float64))
        np.testing.assert_allclose(out.numpy(), same, rtol=2e-7)


def test_volumes_far_from_the_origin(device):
    """A character 1 km from the origin: float32 positions, float64 sums about a local origin."""
    model, vc, _, _ = _setup(device)
    sv = _host(model).subvolumes
    shift = np.array([1000.0, -400.0, 250.0])
    pts = (_host(model).rig.vertices + shift).astype(np.float32)
    cen = (sv.center_rest + shift).astype(np.float32)
    x = wp.array(pts, dtype=wp.vec3, device=model.device)
    c = wp.array(cen, dtype=wp.vec3, device=model.device)
    out = wp.zeros(sv.count, dtype=wp.float32, device=model.device)
    vc.volumes(x, c, out)
    ref = sv.volumes(pts.astype(np.float64), cen.astype(np.float64))
    np.testing.assert_allclose(out.numpy(), ref, rtol=2e-7)
    # and the lambda kernel's float64 volume of the same points
    ws = wp.ones(model.vertex_count, dtype=wp.float32, device=model.device)
    vc.project(x, model.particle_inv_mass, ws, c, iterations=1)
    np.testing.assert_allclose(vc.subvolume_volume.numpy(), ref, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


def test_bad_input_says_what_to_fix():
    model = SkinModelBuilder(make_arm(**ARM), ModelParams(volume=False)).finalize("cpu")
    with pytest.raises(InputError, match="volume=True"):
        VolumeConstraints(model)
    model, vc, state, ws = _setup("cpu")
    with pytest.raises(InputError, match="centers must have 2 entries"):
        vc.project(state.x, model.particle_inv_mass, ws, wp.zeros(3, dtype=wp.vec3, device="cpu"), iterations=1)
    with pytest.raises(InputError, match="inv_mass must have dtype float32"):
        vc.project(state.x, wp.zeros(model.particle_count, dtype=wp.float64, device="cpu"), ws, vc.centers, 1)
    with pytest.raises(InputError, match="stiffness must be in"):
        vc.project(state.x, model.particle_inv_mass, ws, vc.centers, 1, stiffness=1.5)
    with pytest.raises(InputError, match="iterations"):
        vc.project(state.x, model.particle_inv_mass, ws, vc.centers, -1)
