"""The self-collision fail-safe (every device): a patch pushed through is put back and carried
with its bones, held and pinned without carry, looked for only where triangles moved, the same
from the detection's pair list as from the tree, pairs the animation drives through left to the
contacts, and off when asked (counts against the exact brute-force test)."""

from __future__ import annotations

import numpy as np
import warp as wp

from characters import pressed_arm
from oracles import coarse_arm
from warpskin.collision import CollisionParams, SelfCollision
from warpskin.metrics import self_intersections
from warpskin.model import ModelParams, SkinModelBuilder
from warpskin.run import initial_state


def _pushed_through(device, rounds=4):
    """The coarse arm at rest and the same skin one step later: everything translated by T
    (bones included), and a patch of forearm skin pushed through the far side of the forearm
    (2.6 tissue depths along minus its normal). Returns the rig, the collision, both states,
    T, the patch and its centre vertex."""
    rig = coarse_arm()
    builder = SkinModelBuilder(rig, ModelParams(volume=False))
    builder.params.collision = CollisionParams(fail_safe_rounds=rounds)
    model = builder.finalize(device)
    col = SelfCollision(model)
    v = rig.vertex_count
    a, b = model.state(), model.state()
    initial_state(model, a, rig.skinning_matrices("flex", 0.0))
    x0 = a.x.numpy().astype(np.float64)
    axis = np.argmax(np.ptp(x0[:v], axis=0))  # the arm's length
    lo, hi = x0[:v, axis].min(), x0[:v, axis].max()
    c = int(np.argmin(np.abs(x0[:v, axis] - (lo + 0.8 * (hi - lo))) + 1e-3 * np.arange(v) / v))  # mid-forearm
    depth = np.linalg.norm(x0[c] - x0[3 * v + c])
    normal = (x0[c] - x0[3 * v + c]) / depth
    patch = np.nonzero(np.linalg.norm(x0[:v] - x0[c], axis=1) < 0.5 * depth)[0]
    shift = np.array([0.011, -0.007, 0.005]) * rig.size()
    x1 = x0 + shift
    x1[patch] -= 2.6 * depth * normal
    b.x.assign(x1.astype(np.float32))
    # the step's pose: the rest pose translated by T (LBS: the clean skin moved along)
    mats = rig.skinning_matrices("flex", 0.0).copy()
    mats[:, :3, 3] += shift  # translation after the skinning matrix
    return rig, col, a, b, shift, patch, wp.array(mats.astype(np.float32), dtype=wp.mat44, device=device)


def test_fail_safe_puts_back_a_patch_pushed_through_and_carries_it_with_its_bones(device):
    # a clean skin, one step later translated by T with a patch pushed through the far side of
    # the forearm: after the fail-safe no pair intersects (exact float64 check,
    # solver-independent), every vertex of a new pair is where it started plus T (its bone
    # particle's motion), every vertex far from the patch is untouched, the inner layers too
    rig, col, a, b, shift, patch, mats = _pushed_through(device)
    v = rig.vertex_count
    tris = rig.triangles
    x0, x1 = a.x.numpy().astype(np.float64), b.x.numpy().astype(np.float64)
    assert len(self_intersections(x0[:v], tris)) == 0
    new = self_intersections(x1[:v], tris)
    assert len(new) > 10 and len(patch) >= 3
    col.fail_safe(a.x, b.x, mats)
    x = b.x.numpy().astype(np.float64)
    after = self_intersections(x[:v], tris)
    print(f"patch {len(patch)} vertices, new pairs {len(new)}, after the fail-safe {len(after)}, "
          f"pairs found {int(col.fail_safe_pairs.numpy()[0])}")
    assert len(after) == 0
    np.testing.assert_array_equal(x[v:], x1[v:])
    tol = 1e-6 * rig.size()
    carried = np.linalg.norm(x[:v] - (x0[:v] + shift), axis=1) < tol
    kept = np.linalg.norm(x[:v] - x1[:v], axis=1) < tol  # (a vertex carried to x1 differs by rounding)
    assert np.all(carried | kept)
    assert np.all(carried[np.unique(tris[new.ravel()])]) and np.all(carried[patch])
    # a local repair: only the pushed patch changes (the far side's vertices, put back too, are
    # carried to where the step had them)
    assert set(np.nonzero(~kept)[0].tolist()) == set(patch.tolist())
    assert int(col.fail_safe_pairs.numpy()[0]) >= len(new)


def test_fail_safe_without_carry_holds_the_pairs_and_pins_them_for_the_volume_loop(device):
    # the pass after the volume loop (carry=False): the same pushed-through patch goes back to
    # exactly where it was (no carrying by the bone particles, which moved by T here), no
    # pair is left (exact float64 check), every vertex that changed is bit for bit its
    # start, and pin_reverted gives exactly those vertices weight 0 for the volume iterations
    rig, col, a, b, shift, patch, mats = _pushed_through(device)
    v = rig.vertex_count
    tris = rig.triangles
    x0, x1 = a.x.numpy().copy(), b.x.numpy().copy()  # (a CPU array's numpy() is a view)
    new = self_intersections(x1[:v].astype(np.float64), tris)
    assert len(new) > 10
    col.fail_safe(a.x, b.x, mats, carry=False)
    x = b.x.numpy().copy()
    assert len(self_intersections(x[:v].astype(np.float64), tris)) == 0
    changed = np.nonzero(np.any(x[:v] != x1[:v], axis=1))[0]
    np.testing.assert_array_equal(x[changed], x0[changed])
    assert set(patch.tolist()) <= set(changed.tolist()) and set(np.unique(tris[new.ravel()]).tolist()) <= set(changed.tolist())
    np.testing.assert_array_equal(x[v:], x1[v:])
    scale = wp.ones(v, dtype=wp.float32, device=device)
    col.pin_reverted(scale)
    np.testing.assert_array_equal(np.nonzero(scale.numpy() == 0.0)[0], changed)
    assert np.all(scale.numpy()[np.setdiff1d(np.arange(v), changed)] == 1.0)


def test_fail_safe_min_move_looks_only_from_triangles_that_moved(device):
    # the pushed patch moved by T plus 2.6 tissue depths, the rest by T: with min_move just
    # above |T| only the patch's triangles look, and they find every pair (the same result as
    # looking from all); with min_move above the push, no triangle looks and nothing changes
    results = []
    for factor in (None, 1.05, 40.0):
        rig, col, a, b, shift, patch, mats = _pushed_through(device)
        x1 = b.x.numpy().copy()  # (a CPU array's numpy() is a view)
        depth = np.linalg.norm(x1[patch[0]] - shift - a.x.numpy()[patch[0]]) / 2.6
        assert np.linalg.norm(shift) * 40.0 > 2.7 * depth + np.linalg.norm(shift)
        mm = None if factor is None else factor * float(np.linalg.norm(shift))
        col.fail_safe(a.x, b.x, mats, carry=False, min_move=mm)
        results.append((b.x.numpy().copy(), int(col.fail_safe_pairs.numpy()[0]), x1))
    (x_all, n_all, _), (x_moved, n_moved, _), (x_none, n_none, x1) = results
    np.testing.assert_array_equal(x_moved, x_all)
    assert n_moved == n_all > 10
    np.testing.assert_array_equal(x_none, x1)
    assert n_none == 0


def test_fail_safe_from_the_pair_list_equals_the_query_from_every_triangle(device):
    # the coarse arm bending into contact under the solver; after some steps, the skin jittered
    # by 0.4 thicknesses (seeded) makes new pairs; the fail-safe from this step's detection
    # list (escaped triangles querying the tree) and from a tree query per triangle give the
    # same positions bit for bit and the same pair count, carried, held, and with min_move,
    # with the list's slots and the triangles taken one, five or 64 per thread; both halves have
    # work: some new pairs have two triangles that stayed in their boxes
    from warpskin.solver import SkinSolver, SolverParams

    rig = coarse_arm()
    builder = SkinModelBuilder(rig, ModelParams(volume=False))
    model = builder.finalize(device)
    solver = SkinSolver(model, SolverParams(iterations=4))
    col = solver.collision
    contacts = model.contacts()
    a, b, ctl = model.state(), model.state(), model.control()
    v, tris = rig.vertex_count, rig.triangles
    initial_state(model, a, rig.skinning_matrices("flex", 0.9))
    rng = np.random.default_rng(5)
    found = both_listed = 0
    for step in range(12):
        ctl.set_pose(rig.skinning_matrices("flex", 0.9 + 0.01 * (step + 1)))
        solver.step(a, b, ctl, contacts, 0.01)
        assert not contacts.overflowed()
        if step % 3 == 2:
            x_old = a.x.numpy().copy()  # (a CPU array's numpy() is a view)
            x = b.x.numpy().copy()
            x[:v] += rng.normal(scale=0.4 * col.thickness, size=(v, 3)).astype(np.float32)

            def fail_safe(c, **kw):
                xw = wp.array(x, dtype=wp.vec3, device=device)
                col.fail_safe_pairs.zero_()
                col.fail_safe(a.x, xw, ctl.skin_matrices, contacts=c, **kw)
                return xw.numpy().copy(), int(col.fail_safe_pairs.numpy()[0])

            variants = ({}, {"carry": False}, {"carry": False, "min_move": 0.5 * col.thickness})
            # the reference a thread per triangle (as on a GPU); the list's slots and the
            # triangles one, five and the default number per thread
            chunk0 = col.chunk
            col.chunk = 1
            ref = [fail_safe(None, **kw) for kw in variants]
            for r, kw in zip(ref, variants):
                for chunk in (1, 5, chunk0):
                    col.chunk = chunk
                    got = fail_safe(contacts, **kw)
                    np.testing.assert_array_equal(got[0], r[0])
                    assert got[1] == r[1]
                col.chunk = chunk0
                found += r[1]
            escaped = col.escaped.numpy().astype(bool)
            assert 0 < escaped.sum() < 0.5 * len(tris)
            print(f"escaped {escaped.sum()} of {len(tris)}")
            new = {tuple(q) for q in self_intersections(x[:v].astype(np.float64), tris).tolist()} - \
                {tuple(q) for q in self_intersections(x_old[:v].astype(np.float64), tris).tolist()}
            both_listed += sum(1 for t, u in new if not escaped[t] and not escaped[u])
            # a list that does not fit its buffer: every triangle queries the tree, same result
            short = model.contacts(pair_capacity=16)
            col.detect(a.x, b.x, short)
            for r, kw in zip(ref, variants):
                got = fail_safe(short, **kw)
                assert col.escaped.numpy().all()
                np.testing.assert_array_equal(got[0], r[0])
                assert got[1] == r[1]
        a, b = b, a
    print(f"pairs found {found}, new pairs of two listed triangles {both_listed}")
    assert found > 20 and both_listed > 0


def test_fail_safe_leaves_pairs_the_animation_drives_through_each_other(device):
    # the coarse arm's LBS from 1.2 s to 1.5 s presses the forearm through the upper arm: every
    # new pair intersects under LBS too (the step is LBS), so the fail-safe leaves them all to
    # the contacts and changes nothing
    rig, col, contacts, a, b = pressed_arm(device, 1 << 15)
    v = rig.vertex_count
    x0, x1 = a.x.numpy().copy(), b.x.numpy().copy()  # (a CPU array's numpy() is a view)
    new = {tuple(p) for p in self_intersections(x1[:v], rig.triangles).tolist()} - \
        {tuple(p) for p in self_intersections(x0[:v], rig.triangles).tolist()}
    assert len(new) > 10
    mats = wp.array(rig.skinning_matrices("flex", 1.5).astype(np.float32), dtype=wp.mat44, device=device)
    col.fail_safe(a.x, b.x, mats)
    np.testing.assert_array_equal(b.x.numpy(), x1)
    assert int(col.fail_safe_pairs.numpy()[0]) == 0


def test_fail_safe_off_keeps_the_step(device):
    rig, col, a, b, shift, patch, mats = _pushed_through(device, rounds=0)
    x1 = b.x.numpy().copy()  # (a CPU array's numpy() is a view)
    col.fail_safe(a.x, b.x, mats)
    np.testing.assert_array_equal(b.x.numpy(), x1)
    assert int(col.fail_safe_pairs.numpy()[0]) == 0
