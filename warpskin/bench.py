"""Benchmarks (``warpskin bench``): milliseconds per frame on one device, JSON out.

Timings are the best of ``repeat`` runs of ``frames`` frames each; every measured region ends
with ``wp.synchronize_device`` so asynchronous CUDA launches are counted in full. Tests never
assert timings; this is the performance record.
"""

from __future__ import annotations

import math
import os
import platform
import time
from dataclasses import replace

import numpy as np
import warp as wp

from .batch_model import batch_model
from .character import Character
from .device import resolve_device
from .errors import WarpskinError
from .guard import SurfaceGuard
from .metrics import self_intersections
from .model import SkinModelBuilder
from .popping.dynamics import PoppingDynamics
from .popping.pose_space import PoseSpaceDeformer
from .preprocess.cage import build_cage, character_soup
from .rig import Clip
from .run.physics import PhysicsStepper, initial_state
from .run.plan import FramePlan
from .skinning import Skinner
from .transforms import linear_blend_skin
from .scene import resolve_scene
from .solver import SkinSolver, largest_step

__all__ = ["run_skinning_bench", "run_build_bench", "run_solver_bench", "run_popping_bench", "run_batch_bench"]


def _best_ms(fn, frames: int, repeat: int, device) -> float:
    best = float("inf")
    for _ in range(repeat):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for f in range(frames):
            fn(f)
        wp.synchronize_device(device)
        best = min(best, (time.perf_counter() - t0) * 1e3 / frames)
    return best


def memory_bandwidth_gbs(device, mib: int = 64, repeat: int = 5) -> float:
    """The device's memory bandwidth [GB/s] as a copy of ``mib`` MiB between two of its arrays
    sees it (bytes read plus bytes written over the best of ``repeat`` copies): the ceiling a
    kernel that streams its arrays can reach."""
    n = mib * (1 << 20) // 4
    src = wp.zeros(n, dtype=wp.float32, device=device)
    dst = wp.empty(n, dtype=wp.float32, device=device)
    wp.copy(dst, src)  # first touch of the pages outside the timing
    ms = _best_ms(lambda f: wp.copy(dst, src), 1, repeat, device)
    return 2.0 * n * 4 / (ms * 1e-3) / 1e9


def _array_bytes(arr) -> int:
    """The bytes of a Warp array's elements (0 for anything else)."""
    if not isinstance(arr, wp.array):
        return 0
    return int(arr.size) * int(wp.types.type_size_in_bytes(arr.dtype))


class _CallCount:
    """Counts, while entered, the calls of Warp's ``launch`` and ``copy`` (the launches: kernel
    and memory) and of ``array.numpy`` on arrays of ``device`` (the reads to the host; on a GPU
    the host's own arrays, such as the guard's pair queries, are not counted, on the CPU every
    read is), and ``bytes``: per launch, the sizes of the distinct arrays it takes (inputs and
    outputs), per copy what it reads and writes; the traffic of launches that stream each of
    their arrays once (more than a launch moves where it reads part of an array, such as
    contact buffers sized by their capacity; less where it gathers an element more than once).
    A measuring tool only: it wraps those three module attributes and restores them on exit."""

    def __init__(self, device=None) -> None:
        self.device = device
        self.launches = self.readbacks = self.bytes = 0

    def __enter__(self):
        self.launches = self.readbacks = self.bytes = 0
        self._saved = (wp.launch, wp.copy, wp.array.numpy)
        launch, copy, numpy = self._saved

        def counted_launch(kernel, dim=None, inputs=(), outputs=(), *args, **kwargs):
            self.launches += 1
            seen = {id(a): a for a in (*(inputs or ()), *(outputs or ())) if isinstance(a, wp.array)}
            self.bytes += sum(_array_bytes(a) for a in seen.values())
            return launch(kernel, dim, inputs, outputs, *args, **kwargs)

        def counted_copy(dest, src, dest_offset=0, src_offset=0, count=0, *args, **kwargs):
            self.launches += 1
            size = _array_bytes(src)
            if count and isinstance(src, wp.array) and src.size:
                size = size // int(src.size) * int(count)
            self.bytes += 2 * size
            return copy(dest, src, dest_offset, src_offset, count, *args, **kwargs)

        def counted_numpy(arr, *args, **kwargs):
            if self.device is None or arr.device == self.device:
                self.readbacks += 1
            return numpy(arr, *args, **kwargs)

        wp.launch, wp.copy, wp.array.numpy = counted_launch, counted_copy, counted_numpy
        return self

    def __exit__(self, *exc):
        wp.launch, wp.copy, wp.array.numpy = self._saved
        return False


def _simulate_timing(scene, device, first: int, count: int) -> dict:
    """A ``simulate`` run of ``count`` frames from ``first`` (its pre-roll first; the file
    written to a temporary folder, removed): ``simulate_frame_ms`` (a frame after the first as
    a whole: steps, read-back, guard and checks, writing), ``simulate_steps_ms`` (its steps and
    read-back), ``host_share`` (the share of the frame around the steps), and per frame after
    the first: ``launches_per_frame`` (kernel launches and copies, not an array's ``zero_``
    memsets; a captured graph's replay is one) and ``readbacks_per_frame`` (reads of the
    device's arrays to the host: on the CPU every read of a Warp array, the guard's pair
    queries included)."""
    import tempfile

    from .run import simulate
    from .run.runner import FrameRunner

    counts: list[tuple[int, int]] = []
    run_frames = FrameRunner.run

    def counted(self, **kwargs):  # each frame after the first: its steps, read-back, guard, checks
        advance, frame = self.stepper.advance, self.stepper.frame
        tally = _CallCount(device)

        def advance_counted(i):
            if i < 1:
                return advance(i)
            tally.__enter__()
            try:
                return advance(i)
            except BaseException:
                tally.__exit__(None, None, None)
                raise

        def frame_counted(i):
            if i < 1:
                return frame(i)
            try:
                return frame(i)
            finally:
                tally.__exit__(None, None, None)
                counts.append((tally.launches, tally.readbacks))

        self.stepper.advance, self.stepper.frame = advance_counted, frame_counted
        try:
            return run_frames(self, **kwargs)
        finally:
            del self.stepper.advance, self.stepper.frame

    with tempfile.TemporaryDirectory(prefix="warpskin-bench-") as tmp:
        FrameRunner.run = counted
        try:
            run = simulate(scene, os.path.join(tmp, "bench.usdc"), frames=(first, first + count - 1), progress=False,
                           device=str(device))
        finally:
            FrameRunner.run = run_frames
    s = run.summary
    launches, reads = [c[0] for c in counts] or [0], [c[1] for c in counts] or [0]
    return {"simulate_frames": s["frames"], "simulate_particles": s["particles"], "simulate_frame_ms": s["mean_frame_ms"],
            "simulate_steps_ms": s["mean_step_ms"] * s["substeps_per_frame"], "host_share": s["host_share"],
            "launches_per_frame": float(np.mean(launches)), "readbacks_per_frame": float(np.mean(reads))}


def run_skinning_bench(targets: list[str], *, device: str | None = None, frames: int = 60, repeat: int = 3) -> dict:
    """Time LBS and DQS per frame for each scene.

    Reports, per scene: vertices, joints; ``pose_ms`` (host clip sampling and forward
    kinematics per frame); ``lbs_ms`` and ``dqs_ms`` (upload of joint data plus the kernel);
    ``lbs_kernel_ms`` and ``dqs_kernel_ms`` (kernel launch alone, joint data resident);
    and ``dqs_over_lbs`` (ratio of the kernel times, measured in the same run).
    """

    if frames < 1 or repeat < 1:
        raise ValueError("frames and repeat must be >= 1")
    dev = resolve_device(device)
    out = {
        "device": str(dev),
        "device_name": dev.name if hasattr(dev, "name") else str(dev),
        "warp": wp.config.version,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "frames": frames,
        "repeat": repeat,
        "scenes": {},
    }
    for target in targets:
        scene = resolve_scene(target)
        rig = scene.rig()
        clip = rig.clip(scene.clip)
        first, last = scene.frame_range()
        span = max(last - first + 1, 1)
        times = [scene.frame_time(first + (f % span)) for f in range(frames)]
        mats = np.stack([rig.skinning_matrices(clip, t) for t in times])
        lbs = Skinner(rig, method="lbs", device=str(dev))
        dqs = Skinner(rig, method="dqs", device=str(dev))
        lbs.skin(mats[0])  # compile / load kernels outside the timed region
        dqs.skin(mats[0])
        row = {
            "vertices": rig.vertex_count,
            "joints": rig.joint_count,
            "pose_ms": _best_ms(lambda f: rig.skinning_matrices(clip, times[f]), frames, repeat, dev),
            "lbs_ms": _best_ms(lambda f: lbs.skin(mats[f]), frames, repeat, dev),
            "dqs_ms": _best_ms(lambda f: dqs.skin(mats[f]), frames, repeat, dev),
            "lbs_kernel_ms": _best_ms(lambda f: lbs.launch(), frames, repeat, dev),
            "dqs_kernel_ms": _best_ms(lambda f: dqs.launch(), frames, repeat, dev),
        }
        row["dqs_over_lbs"] = row["dqs_kernel_ms"] / row["lbs_kernel_ms"] if row["lbs_kernel_ms"] > 0 else None
        out["scenes"][scene.name] = row
    return out


def run_build_bench(targets: list[str]) -> dict:
    """Host build time of the multi-layer model per stage [s], for scenes or rig files.

    ``arm35k`` is the procedural arm at 35k vertices (190 rings of 184). A scene whose rig
    cannot be found (``cesium_man`` without the assets folder) is reported with its error.
    """
    from .scenes.arm import make_arm

    out = {"machine": platform.machine(), "cpu_count": os.cpu_count(), "scenes": {}}
    for target in targets:
        try:
            if target == "arm35k":
                rig, params = make_arm(rings=190, segments=184), None
            else:
                scene = resolve_scene(target)
                rig, params = scene.rig(), scene.model_params()
            t0 = time.perf_counter()
            builder = SkinModelBuilder(rig, params).build()
            total = time.perf_counter() - t0
            row = builder.summary()
            row["total_s"] = total
            row["cage"] = _cage_build(rig)
            out["scenes"][target] = row
        except Exception as exc:  # report and go on with the other scenes
            out["scenes"][target] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def _cage_build(rig) -> dict:
    """An automatic cage around the rig's meshes (what ``simulate --cage`` builds first): its
    vertices and seconds per stage, with the render points it was built around; the cage's
    capture (``capture_s``), the written points' deformation per frame against the render
    skin's LBS kernel, and the surface guard of the written meshes per frame (``guard_ms`` on a
    frame it lets through, ``guard_acting_ms`` on one where it takes a crumpled patch back)."""
    soup = character_soup(rig)
    tetra = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    build_cage(tetra, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]), edge=0.2)  # compile outside the timing
    cage = build_cage(soup.points, soup.triangles)
    row = {"render_points": int(len(soup.points)), "vertices": int(len(cage.vertices)), "build_s": cage.build_s,
           **{f"{k}_s": v for k, v in cage.timings_s.items()}}
    # per frame: the written points through the cage (the displacement and deformation
    # launches of warpskin.character) against the LBS kernel of the render skin, both on the
    # CPU device and on device-resident inputs
    dev = wp.get_device("cpu")
    t0 = time.perf_counter()
    character = Character(rig, cage="always", device=dev)
    character.bind(device=dev)
    row["capture_s"] = time.perf_counter() - t0
    deformer = character._deformer
    rest = Clip("rest")
    rng = np.random.default_rng(0)
    x_host = character.cage_surface.vertices + rng.normal(scale=1e-3 * character.edge(), size=character.cage_surface.vertices.shape)
    x = wp.array(x_host.astype(np.float32), dtype=wp.vec3, device=dev)
    deformer.evaluate(x, rest, 0.0)
    targets = wp.array(deformer.sim_lbs.numpy(), dtype=wp.vec3,
                       device=dev)  # the surface's LBS: what a simulation's tether writes every step
    deformer.launch(x, targets)
    lbs = Skinner(rig, method="lbs", device=str(dev))
    lbs.skin(rig.skinning_matrices(rest, 0.0))
    # sub-millisecond launches: the best of many short blocks, taken in turn so that a busy
    # spell of the machine meets each of them alike. In a simulation the cage's LBS is the
    # solver tether's targets of the frame's last step: deformation_ms; computed here as well:
    # deformation_with_cage_lbs_ms
    timed = {"deformation_ms": lambda f: deformer.launch(x, targets),
             "deformation_with_cage_lbs_ms": lambda f: deformer.launch(x),
             "render_lbs_kernel_ms": lambda f: lbs.launch()}
    row.update({key: float("inf") for key in timed})
    for _ in range(15):
        for key, fn in timed.items():
            row[key] = min(row[key], _best_ms(fn, 100, 1, dev))
    row["render_lbs_vertices"] = int(rig.vertex_count)
    row["deformation_over_lbs"] = row["deformation_ms"] / row["render_lbs_kernel_ms"]
    # the surface guard of every written mesh, per frame on the host: on a frame it lets
    # through (a small smooth displacement: its checks and the two exact pair counts), and on
    # a frame where it acts (a patch of the first mesh crumpled)
    physical = deformer.launch(x, targets).numpy().astype(np.float64)
    lbs_host = character.lbs(rest, 0.0)
    crumpled = physical.copy()
    first = character.parts[0]
    near = np.linalg.norm(lbs_host[first.start:first.start + first.count] - lbs_host[first.start], axis=1)
    patch = first.start + np.argsort(near)[: max(8, first.count // 50)]
    crumpled[patch] += rng.normal(scale=0.5 * character.edge(), size=(len(patch), 3))
    for key, frame in (("guard_ms", physical), ("guard_acting_ms", crumpled)):
        best = float("inf")
        for _ in range(3):
            guards = {p.name: SurfaceGuard(character.meshes[p.name]) for p in character.parts if p.physics}
            t0 = time.perf_counter()
            for p in character.parts:
                if p.name in guards:
                    sl = slice(p.start, p.start + p.count)
                    guards[p.name].apply(frame[sl], lbs_host[sl])
            best = min(best, (time.perf_counter() - t0) * 1e3)
        row[key] = best
    return row


def run_solver_bench(targets: list[str], *, device: str | None = None, steps: int = 10, repeat: int = 3,
                     frames_timed: int = 6) -> dict:
    """Milliseconds per solver step, split as the paper's Table 1, per scene.

    Per scene, on the surface ``simulate`` simulates (the skin where it is one closed manifold,
    else the character's own pieces or a cage: :class:`~warpskin.character.Character`), in a
    state the simulation reaches: the clip's frames from its start to 40 % of it are stepped as
    ``simulate`` steps them (the scene's pre-roll first; a state started from LBS's pose mid-clip
    would keep the crossings LBS has there), then one step from there; each component's timing starts
    from that step's result (a copy back before each run, its few microseconds included), so
    that repeating it does not drive the state anywhere a simulation would not go;
    ``warmup_frames``, ``contacts`` (the candidates the detection finds there, point-triangle and
    edge-edge) and ``intersecting_pairs`` (the file's own triangles there; LBS's at that time:
    ``intersecting_pairs_lbs``) say which state:
    ``particles``, ``iterations``; ``dt_s`` (the step timed: the scene's ``dt``,
    shortened to ``gravity_step_limit_s`` where that is shorter, as ``simulate`` does);
    ``elasticity_ms`` (the elasticity loop: region fit
    and goal blend with coupling and joint constraints, direct gather); ``collision_ms`` (skin
    self-collision: detection plus the contact passes of every iteration; ``collision_detect_ms``
    the detection alone, ``contacts`` the candidates found, point-triangle and edge-edge) and
    ``elasticity_fast_summation_ms`` (the same with prefix scans along the paths);
    ``volume_ms`` (the volume loop); ``total_ms`` (a whole step, plain launches) and
    ``total_graph_ms`` (a whole step as ``warpskin simulate`` runs it: the frame runner's
    physics stepper replaying each frame's captured graph, with the per-frame read-back and
    overflow check, per substep); ``lbs_ms`` (the LBS kernel on the skin vertices, the
    kinematic baseline) and ``total_over_lbs``; ``launches_per_step`` (kernel launches and
    copies of one step in plain launches, not the memsets of ``zero_``); ``step_bytes`` and
    ``elasticity_bytes`` (the arrays one step's and one elasticity loop's launches take, each
    once per launch: :class:`_CallCount`), ``step_gbs`` and ``elasticity_gbs`` (those bytes over
    ``total_ms`` and ``elasticity_ms``) and their ``..._bandwidth_share`` of the device's
    ``memory_gbs`` (:func:`memory_bandwidth_gbs`, once per bench, at the top level). Then ``simulate``
    runs ``frames_timed`` frames from the timed pose (:func:`_simulate_timing`): ``simulate_frame_ms``, ``simulate_steps_ms``,
    ``host_share`` (the share of a frame spent around its steps: guard, checks, writing),
    ``launches_per_frame`` and ``readbacks_per_frame``.
    """
    if frames_timed < 2:
        raise ValueError(f"frames_timed must be >= 2 (the first frame is not stepped), got {frames_timed}")
    dev = resolve_device(device)
    out = {"device": str(dev), "device_name": getattr(dev, "name", str(dev)), "warp": wp.config.version,
           "cpu_count": os.cpu_count(), "steps": steps, "repeat": repeat,
           "memory_gbs": memory_bandwidth_gbs(dev), "scenes": {}}
    for target in targets:
        try:
            scene = resolve_scene(target)
            rig = scene.rig()
            params = scene.solver_params()
            # what simulate simulates: the skin where it is closed, else the character's own
            # pieces or a cage (an open character's skin has no closed surface to time)
            character = Character(rig, device=dev)
        except Exception as exc:  # e.g. cesium_man without the assets folder
            out["scenes"][target] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        clip = rig.clip(scene.clip)
        rig = character.sim_rig
        builder = SkinModelBuilder(rig, scene.model_params())
        builder.params.collision = scene.collision_params()
        model = builder.finalize(dev)
        dt, limit = largest_step(model, params)  # the step simulate takes
        # a state the simulation reaches: the frames before t_mid stepped as simulate steps
        # them (the frame runner's stepper, captured graphs, contact buffers grown), then the
        # timing loops on it; then the stepper goes on for total_graph_ms
        t_mid = clip.start + 0.4 * clip.duration  # the arm: 2 s, flexed, forearm pressing
        warmup = int(math.floor((t_mid - clip.start) * scene.frame_rate + 1e-9)) + 1  # clip start .. t_mid
        frames = warmup + steps * repeat
        times = [t_mid + (k - warmup + 1) / scene.frame_rate for k in range(frames)]
        plan = FramePlan.at_times(list(range(frames)), times, scene.frame_rate, max_dt=dt)
        st = PhysicsStepper(builder.rig, SkinSolver(model, params), plan, clip, label=f"bench {builder.rig.name}",
                            preroll=scene.preroll)
        for k in range(warmup):
            st.advance(k)
        solver = SkinSolver(model, params)
        col = solver.collision
        contacts = model.contacts(st.contacts.capacity, st.contacts.pair_capacity) if st.contacts is not None else None
        a, b, c = model.state(), model.state(), model.control()
        a.assign(st.state_a)
        c.set_pose(rig.skinning_matrices(clip, t_mid + dt))
        solver.step(a, b, c, contacts, dt)  # compile / load outside the timed regions
        if contacts is not None and contacts.overflowed():
            contacts.grow()
            solver.step(a, b, c, contacts, dt)
        reached = wp.clone(b.x)  # a step's result from the reached state: every timing starts there

        def restart():
            wp.copy(b.x, reached)
        def elasticity(fast: bool):
            restart()
            solver.params = replace(solver.params, fast_summation=fast)
            q_src, q_dst = a.q, solver.q_scratch
            for it in range(params.iterations):
                solver.region_fit(b.x, q_src, q_dst)
                solver.blend_and_constrain(b.x, q_dst, it)
                q_src, q_dst = q_dst, q_src

        def collisions():
            restart()
            col.detect(a.x, b.x, contacts)
            for _ in range(params.iterations):
                col.project(b.x, model.particle_inv_mass, contacts)

        fast0 = params.fast_summation
        row = {"particles": model.particle_count, "vertices": model.vertex_count, "iterations": params.iterations,
               "volume_iterations": params.volume_iterations, "dt_s": dt, "warmup_frames": warmup,
               "gravity_step_limit_s": limit if math.isfinite(limit) else None}
        row["elasticity_ms"] = _best_ms(lambda f: elasticity(False), steps, repeat, dev)
        if col is not None:
            collisions()
            row["collision_ms"] = _best_ms(lambda f: collisions(), steps, repeat, dev)
            restart()
            row["collision_detect_ms"] = _best_ms(lambda f: col.detect(a.x, b.x, contacts), steps, repeat, dev)
            row["contacts"] = [int(c) for c in contacts.counts.numpy()[:2]]
            skin_lbs = linear_blend_skin(rig.vertices, rig.joint_indices, rig.joint_weights,
                                         rig.skinning_matrices(clip, t_mid + dt))
            row["intersecting_pairs"], row["intersecting_pairs_lbs"] = (
                int(len(self_intersections(x[: rig.output_count], rig.output_triangles)))
                for x in (reached.numpy(), skin_lbs))
        else:
            row["collision_ms"] = 0.0
        elasticity(True)  # compile the scan kernels
        row["elasticity_fast_summation_ms"] = _best_ms(lambda f: elasticity(True), steps, repeat, dev)
        solver.params = replace(solver.params, fast_summation=fast0)
        if solver.volume is not None:
            restart()
            row["volume_ms"] = _best_ms(
                lambda f: solver.volume.project(b.x, solver.volume_inv_mass, solver.volume_weight_scale,
                                                solver.volume_centres, params.volume_iterations, params.volume_stiffness),
                steps, repeat, dev)
        else:
            row["volume_ms"] = 0.0
        states = [a, b]
        row["total_ms"] = _best_ms(lambda f: solver.step(states[f % 2], states[(f + 1) % 2], c, contacts, dt), steps,
                                   repeat, dev)
        # the user's code path: the frame runner's stepper, frame after frame from the reached state
        nxt = iter(range(warmup, frames))
        row["total_graph_ms"] = _best_ms(lambda f: st.advance(next(nxt)), steps, repeat, dev) / plan.substeps
        row["graph_capture"] = bool(st.graphs)
        lbs = Skinner(rig, method="lbs", device=str(dev))
        lbs.skin(rig.skinning_matrices(clip, t_mid))
        row["lbs_ms"] = _best_ms(lambda f: lbs.launch(), steps, repeat, dev)
        best_total = row["total_graph_ms"] or row["total_ms"]
        row["total_over_lbs"] = best_total / row["lbs_ms"] if row["lbs_ms"] > 0 else None
        with _CallCount() as tally:  # one step in plain launches
            solver.step(a, b, c, contacts, dt)
        row["launches_per_step"] = tally.launches
        row["step_bytes"] = tally.bytes
        with _CallCount() as tally:
            elasticity(False)
        row["elasticity_bytes"] = tally.bytes
        bandwidth = out["memory_gbs"]
        for key, bytes_, ms in (("elasticity", row["elasticity_bytes"], row["elasticity_ms"]),
                                ("step", row["step_bytes"], row["total_ms"])):
            gbs = bytes_ / (ms * 1e-3) / 1e9 if ms > 0 else None
            row[f"{key}_gbs"] = gbs
            row[f"{key}_bandwidth_share"] = gbs / bandwidth if gbs is not None and bandwidth > 0 else None
        # a whole simulate frame there: how much of it is the steps, how much the host's work
        first = int(round(t_mid * scene.frame_rate))  # the timed pose's frame (time code)
        row.update(_simulate_timing(scene, dev, first, frames_timed))
        out["scenes"][scene.name] = row
    return out


def run_popping_bench(device=None, steps: int = 200, repeat: int = 3, *, rings: int = 80, segments: int = 54) -> dict:
    """Milliseconds per frame of the popping pipeline on the arm at 4322 vertices (the paper's
    character has 4380 and runs at 60 FPS on a 3.6 GHz CPU), against plain LBS in the same run.

    Returns:
        ``vertices``; ``pose_space_ms`` (set_pose: host RBF weights, uploads and the pose space
        kernel) and ``pose_space_kernel_ms`` (the kernel alone); ``step_ms`` (one popping step:
        host activation latch plus the kernel); ``frame_ms`` (pose space + one step, the
        paper's per-frame work) and ``fps``; ``lbs_ms`` (the LBS Skinner: upload plus kernel)
        and ``lbs_kernel_ms``; ``frame_over_lbs`` and ``step_over_lbs_kernel`` ratios.
    """
    from .scenes.popping_arm import elbow_pose, make_popping_arm, popping_arm_examples

    if steps < 1 or repeat < 1:
        raise ValueError("steps and repeat must be >= 1")
    dev = resolve_device(device)
    rig = make_popping_arm(rings=rings, segments=segments)
    examples = popping_arm_examples(rig, rings=rings, segments=segments)
    # a slowly moving elbow, so every frame's pose (and RBF weights) differ
    mats = [elbow_pose(rig, 60.0 + 60.0 * k / max(steps - 1, 1)) for k in range(steps)]
    deformer = PoseSpaceDeformer(rig, examples, device=dev)
    dynamics = PoppingDynamics(deformer, alpha_min=0.1, beta=30.0)
    lbs = Skinner(rig, method="lbs", device=str(dev))
    h = 1.0 / 240.0
    act = np.ones(deformer.group_count)
    deformer.set_pose(mats[0])  # compile / load outside the timed regions
    dynamics.step(h, act)
    lbs.skin(mats[0])
    row = {
        "device": str(dev),
        "device_name": getattr(dev, "name", str(dev)),
        "warp": wp.config.version,
        "vertices": rig.vertex_count,
        "groups": deformer.group_count,
        "normal_examples": examples.normal_count,
        "steps": steps,
        "repeat": repeat,
    }
    row["pose_space_ms"] = _best_ms(lambda f: deformer.set_pose(mats[f]), steps, repeat, dev)
    row["pose_space_kernel_ms"] = _best_ms(lambda f: deformer.launch(), steps, repeat, dev)
    row["step_ms"] = _best_ms(lambda f: dynamics.step(h, act), steps, repeat, dev)

    def frame(f):
        deformer.set_pose(mats[f])
        dynamics.step(h, act)

    row["frame_ms"] = _best_ms(frame, steps, repeat, dev)
    row["fps"] = 1e3 / row["frame_ms"] if row["frame_ms"] > 0 else None
    row["lbs_ms"] = _best_ms(lambda f: lbs.skin(mats[f]), steps, repeat, dev)
    row["lbs_kernel_ms"] = _best_ms(lambda f: lbs.launch(), steps, repeat, dev)
    row["frame_over_lbs"] = row["frame_ms"] / row["lbs_ms"] if row["lbs_ms"] > 0 else None
    row["step_over_lbs_kernel"] = row["step_ms"] / row["lbs_kernel_ms"] if row["lbs_kernel_ms"] > 0 else None
    return row


def run_batch_bench(targets: list[str], count: int, *, device: str | None = None, steps: int = 10,
                    repeat: int = 3) -> dict:
    """Character-steps per second of ``count`` instances of each scene in one batched model
    (:func:`~warpskin.batch_model.batch_model`: one launch per kernel steps them all) against
    the same instances as ``count`` separate models stepped one after another, on one device.

    Per scene: ``characters``, ``particles`` (the batch's); ``dt_s`` (the step timed: the scene's
    ``dt``, shortened to ``gravity_step_limit_s`` where that is shorter, as ``simulate`` does);
    ``batch_step_ms`` (one step of the
    batch, collisions included, each instance at its own moment of the clip);
    ``separate_step_ms`` (the same instances as separate models, one step each, one after
    another: ``count`` separate runs) and ``single_step_ms`` (its mean per instance); ``batch_character_steps_per_s`` and
    ``separate_character_steps_per_s``; ``speedup`` (separate over batch, measured in the same
    run). A scene that cannot be loaded or batched (its assets absent, a rest-shape drive)
    reports its ``error``.
    """
    if not (isinstance(count, int) and count >= 1):
        raise ValueError(f"--batch needs a positive number of characters, got {count!r}")
    if steps < 1 or repeat < 1:
        raise ValueError("steps and repeat must be >= 1")
    dev = resolve_device(device)
    out = {"device": str(dev), "device_name": getattr(dev, "name", str(dev)), "warp": wp.config.version,
           "cpu_count": os.cpu_count(), "characters": count, "steps": steps, "repeat": repeat, "scenes": {}}
    for target in targets:
        try:
            scene = resolve_scene(target)
            rig = scene.rig()
            params = scene.solver_params()
            builder = SkinModelBuilder(rig, scene.model_params())
            builder.params.collision = scene.collision_params()
            batch = batch_model([builder] * count, dev)
        except (WarpskinError, OSError) as exc:  # a scene without its assets, a model the batch refuses
            out["scenes"][target] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        dt, limit = largest_step(batch, params)  # gravity's limit applies to a batch as well
        clip = rig.clip(scene.clip)
        times = [clip.start + (0.3 + 0.4 * k / max(count, 1)) * clip.duration for k in range(count)]
        poses = [rig.skinning_matrices(clip, t) for t in times]

        def stepper(model, mats: list[np.ndarray]):
            solver = SkinSolver(model, params)
            a, b, c = model.state(), model.state(), model.control()
            contacts = model.contacts()
            initial_state(model, a, np.concatenate(mats))
            c.set_pose(np.concatenate(mats))
            states = [a, b]
            for k in range(4):  # compile, and grow the contact buffers, outside the timed region
                solver.step(states[k % 2], states[(k + 1) % 2], c, contacts, dt)
                if contacts is not None and contacts.overflowed():
                    contacts.grow()
            return lambda f: solver.step(states[f % 2], states[(f + 1) % 2], c, contacts, dt)

        batch_ms = _best_ms(stepper(batch, poses), steps, repeat, dev)
        alone = builder.finalize(dev)
        singles = [_best_ms(stepper(alone, [m]), steps, repeat, dev) for m in poses]  # each at its own moment
        separate_ms = float(sum(singles))
        out["scenes"][scene.name] = {
            "characters": count, "particles": batch.particle_count, "dt_s": dt,
            "gravity_step_limit_s": limit if math.isfinite(limit) else None, "batch_step_ms": batch_ms,
            "single_step_ms": separate_ms / count, "separate_step_ms": separate_ms,
            "batch_character_steps_per_s": 1e3 * count / batch_ms if batch_ms > 0 else None,
            "separate_character_steps_per_s": 1e3 * count / separate_ms if separate_ms > 0 else None,
            "speedup": separate_ms / batch_ms if batch_ms > 0 else None,
        }
    return out
