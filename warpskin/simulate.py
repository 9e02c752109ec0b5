"""Run the physically-based skin over a scene's frames and write it to USD (``warpskin
simulate``), with per-frame measurements and an optional report.

Poses for every substep are computed on the host once, before the loop, and uploaded as one
array; inside the loop a substep copies its pose on the device and calls ``solver.step``. Per
frame the skin positions come back to the host once, for the USD file and the measurements.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from .errors import SceneError
from .preprocess.layers import LAYER_NAMES
from .io.usd_export import UsdSkinWriter
from .metrics import self_intersections, signed_volume
from .model import SkinModelBuilder
from .progress import Progress
from .report import write_plots
from .scene import Scene
from .solver import SimulationError, SkinSolver, SolverParams
from .skinning import dual_quaternions
from .transforms import linear_blend_skin

__all__ = ["SimulationResult", "simulate", "initial_state"]


@dataclass
class SimulationResult:
    """What a run produced.

    Attributes:
        path: The USD file.
        frames: Frame numbers written.
        metrics: Per-frame series (``time``, ``volume``, ``volume_lbs``, ``subvolume``,
            ``subvolume_lbs``, ``kinetic_energy``, ``max_offset_from_lbs``, ``step_ms``).
        summary: Scalars: particle count, substeps, dt, volume deviations, timing.
    """

    path: Path
    frames: list[int]
    metrics: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def initial_state(model, state, skin_matrices: np.ndarray) -> None:
    """Put ``state`` at the pose ``skin_matrices`` ``[J, 4, 4]``: every particle skinned with
    its vertex's weights (LBS), at rest (zero velocities), oriented like its dominant bone."""
    b = model.builder
    rig = b.rig
    ji = np.tile(rig.joint_indices, (4, 1))
    jw = np.tile(rig.joint_weights, (4, 1))
    x = linear_blend_skin(b.layers.flat(), ji, jw, skin_matrices)
    q_joint, _, _ = dual_quaternions(skin_matrices)  # rotation part of every joint
    q = np.tile(q_joint[b.layers.bone], (4, 1))
    state.x.assign(x.astype(np.float32))
    state.q.assign(q.astype(np.float32))
    state.v.zero_()
    state.omega.zero_()


def simulate(
    scene: Scene,
    out_path,
    *,
    device=None,
    frames: tuple[int, int] | None = None,
    solver_params: SolverParams | None = None,
    with_lbs: bool = False,
    with_layers: bool = False,
    report_dir=None,
    progress: bool = True,
    comment: str = "",
    use_graph: bool = True,
    collision=None,
    check_intersections: bool | None = None,
    rest_shape: tuple | None = None,
    builder: SkinModelBuilder | None = None,
    preroll: float | None = None,
) -> SimulationResult:
    """Simulate a scene and write the skin (and on request LBS and the inner layers) to USD.

    ``use_graph`` records each frame's substeps once as a Warp graph (CPU and CUDA) and
    replays it, which removes the per-launch overhead; the results are bit-identical.
    ``rest_shape = (delta_offsets [G, M, 3], activation(t) -> [G])`` drives the rest shape by
    activations (layered popping; see :func:`warpskin.popping.muscle_rest_offset_deltas`);
    the activation of every substep is precomputed and uploaded once, like the poses.
    ``collision`` (:class:`~warpskin.collision.CollisionParams`) defaults to the scene's
    ``[collision]`` section (on unless disabled). If a frame finds more contact candidates than
    the buffers hold, the frame is run again with larger buffers. ``check_intersections`` counts
    intersecting skin triangle pairs per frame with the exact, solver-independent check
    (:func:`warpskin.metrics.self_intersections`); default: only when writing a report.
    ``preroll`` [s] (default: the scene's ``[animation] preroll``) simulates that long before
    the first frame, from the bind pose (the mesh as modelled) into the first frame's pose
    (local joint transforms interpolated, eased in and out); velocities are zeroed after it.
    A first pose whose LBS skin already passes through itself is then reached by collision
    instead of started from; nothing of the pre-roll is written.

    Raises:
        SimulationError: a particle became NaN; the message names the frame, particle, layer
            and vertex; the USD file keeps the frames before it (valid, closed).
    """
    params = solver_params or scene.solver_params()
    params.check(str(scene.source or scene.name))
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first, last = frames if frames is not None else scene.frame_range()
    if first < 0 or last < first:
        raise SceneError(f"bad frame range {first}:{last}")
    t_build = time.perf_counter()
    builder = builder or SkinModelBuilder(rig, scene.model_params())
    model = builder.finalize(device)
    build_s = time.perf_counter() - t_build
    collision = collision if collision is not None else scene.collision_params()
    solver = SkinSolver(model, params, collision=collision)
    col = solver.collision
    if check_intersections is None:
        check_intersections = report_dir is not None
    dev = model.device
    v = model.vertex_count
    frame_dt = 1.0 / scene.fps
    substeps = max(1, math.ceil(frame_dt / params.dt - 1e-9))
    dt = frame_dt / substeps
    frame_list = list(range(first, last + 1))
    # every substep's pose, once, on the host; then one upload
    j = rig.joint_count
    step_times = [scene.frame_time(f) + (s + 1) * dt for f in frame_list[:-1] for s in range(substeps)]
    poses = np.stack([rig.skinning_matrices(clip, t) for t in step_times]) if step_times else np.zeros((0, j, 4, 4))
    frame_poses = np.stack([rig.skinning_matrices(clip, scene.frame_time(f)) for f in frame_list])
    poses_dev = wp.array(poses.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=dev)
    staging = wp.zeros(substeps * j, dtype=wp.mat44, device=dev)  # this frame's substep poses
    act_dev = act_staging = None
    n_groups = 0
    if rest_shape is not None:
        deltas, activation_of = rest_shape
        activation_dev = solver.set_rest_shape_drive(deltas)
        n_groups = activation_dev.shape[0]
        acts = np.array([np.asarray(activation_of(t), dtype=np.float32).reshape(n_groups) for t in step_times]) \
            if step_times else np.zeros((0, n_groups), np.float32)
        act_dev = wp.array(acts.reshape(-1), dtype=wp.float32, device=dev)
        act_staging = wp.zeros(max(substeps * n_groups, 1), dtype=wp.float32, device=dev)
        wp.copy(activation_dev, wp.array(np.asarray(activation_of(scene.frame_time(frame_list[0])), np.float32).reshape(n_groups),
                                         dtype=wp.float32, device=dev))
    state_a, state_b, control = model.state(), model.state(), model.control()
    initial_state(model, state_a, frame_poses[0])
    preroll = scene.preroll if preroll is None else float(preroll)
    if not (math.isfinite(preroll) and preroll >= 0):
        raise SceneError(f"preroll must be a number of seconds >= 0, got {preroll!r}")
    preroll_steps = math.ceil(preroll / params.dt - 1e-9) if preroll > 0 else 0

    def run_frame(sa, sb):
        """All substeps of one frame from ``sa``; returns the state holding the result."""
        for s_ in range(substeps):
            wp.copy(control.skin_matrices, staging, dest_offset=0, src_offset=s_ * j, count=j)
            if act_staging is not None:
                wp.copy(solver.rest_activation, act_staging, dest_offset=0, src_offset=s_ * n_groups, count=n_groups)
            solver.step(sa, sb, control, dt)
            sa, sb = sb, sa
        return sa, sb

    # one captured graph per frame (Warp captures on CPU too); two, for the two state parities
    def capture_graphs():
        out = {}
        if use_graph and len(frame_list) > 2:
            try:
                for start in ((state_a, state_b), (state_b, state_a)) if substeps % 2 else ((state_a, state_b),):
                    with wp.ScopedCapture(device=dev) as cap:  # records; runs nothing yet
                        run_frame(*start)
                    out[id(start[0])] = cap.graph
            except Exception:  # capture unsupported here: plain launches
                out = {}
        return out

    def run_preroll():
        """From the bind pose into the first frame's pose (plain launches, once)."""
        initial_state(model, state_a, np.tile(np.eye(4), (j, 1, 1)))
        u = (np.arange(1, preroll_steps + 1) / preroll_steps)
        u = u * u * (3.0 - 2.0 * u)  # ease in and out
        pre = np.stack([rig.skinning_matrices_from_bind(clip, scene.frame_time(first), float(x)) for x in u])
        pre_dev = wp.array(pre.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=dev)
        sa, sb = state_a, state_b
        for s_ in range(preroll_steps):
            wp.copy(control.skin_matrices, pre_dev, dest_offset=0, src_offset=s_ * j, count=j)
            solver.step(sa, sb, control, preroll / preroll_steps)
            sa, sb = sb, sa
        if sa is not state_a:
            for name in ("x", "q"):
                wp.copy(getattr(state_a, name), getattr(sa, name))
        state_a.v.zero_()
        state_a.omega.zero_()

    if preroll_steps:
        bind_pairs = len(self_intersections(rig.vertices, rig.triangles))
        if bind_pairs:
            warnings.warn(f"{scene.name}: the bind pose itself has {bind_pairs} intersecting skin triangle pairs; the "
                          "pre-roll starts from them and cannot undo them", stacklevel=2)
        for attempt in range(9):
            run_preroll()
            if col is None or not col.overflowed():
                break
            if attempt == 8:
                raise SimulationError(f"pre-roll: more than {col.capacity} contact candidates even after growing the buffers "
                                      "8 times; lower [collision] detection_margin or thickness")
            col.grow()
        if not np.isfinite(state_a.x.numpy()).all():
            raise SimulationError("pre-roll: a particle became NaN or inf; lower dt or shorten the pre-roll's motion")

    graphs = capture_graphs()
    backup = model.state() if col is not None else None

    def copy_state(dst, src):
        for name in ("x", "v", "q", "omega"):
            wp.copy(getattr(dst, name), getattr(src, name))

    subs = builder.subvolumes
    b_layers = builder.layers
    tris = rig.triangles
    masses = builder.masses
    ji, jw = rig.joint_indices, rig.joint_weights
    metrics: dict = {k: [] for k in ("time", "volume", "volume_lbs", "subvolume", "subvolume_lbs", "kinetic_energy",
                                      "max_offset_from_lbs", "step_ms", "residuals", "contacts_point_triangle",
                                      "contacts_edge_edge", "constraints_active", "intersecting_pairs",
                                      "intersecting_pairs_lbs")}
    overflow_retries = 0
    metrics["volume_rest"] = signed_volume(rig.vertices, tris)
    metrics["subvolume_rest"] = subs.rest_volume.tolist() if subs is not None else []
    bar = Progress(len(frame_list), f"simulate {scene.name} ({dev}, {model.particle_count} particles)", enabled=progress)
    writer = UsdSkinWriter(out_path, fps=scene.fps, up_axis=rig.up_axis, comment=comment)
    written: list[int] = []
    failure: SimulationError | None = None
    try:
        writer.add_mesh("skin", tris, rest_points=rig.vertices, color=(0.85, 0.64, 0.52))
        if with_lbs:
            writer.add_mesh("lbs", tris, rest_points=rig.vertices, color=(0.4, 0.55, 0.85), purpose="guide")
        if with_layers:
            for k in range(1, 4):
                writer.add_mesh(f"layer_{LAYER_NAMES[k]}", tris, rest_points=b_layers.positions[k], purpose="guide")
        for fi, f in enumerate(frame_list):
            t0 = time.perf_counter()
            if fi > 0:
                wp.copy(staging, poses_dev, dest_offset=0, src_offset=(fi - 1) * substeps * j, count=substeps * j)
                if act_staging is not None:
                    wp.copy(act_staging, act_dev, dest_offset=0, src_offset=(fi - 1) * substeps * n_groups,
                            count=substeps * n_groups)
                if backup is not None:
                    copy_state(backup, state_a)
                    col.maybe_rebuild(skin)  # the previous frame's skin (host copy)
                frame_retries = 0
                while True:
                    graph = graphs.get(id(state_a))
                    if graph is not None:
                        wp.capture_launch(graph)
                        if substeps % 2:
                            state_a, state_b = state_b, state_a
                    else:
                        state_a, state_b = run_frame(state_a, state_b)
                    if col is None or not col.overflowed():
                        break
                    if not np.isfinite(state_a.x.numpy()).all():
                        col.clear_overflow()  # NaN boxes overlap everything: report the NaN below
                        break
                    if frame_retries >= 8:
                        raise SimulationError(
                            f"frame {f}: more than {col.capacity} contact candidates even after growing the buffers "
                            "8 times; lower [collision] detection_margin or thickness"
                        )
                    # more contact candidates than the buffers hold: grow them and redo the frame
                    if substeps % 2:
                        state_a, state_b = state_b, state_a
                    copy_state(state_a, backup)
                    col.grow()
                    overflow_retries += 1
                    frame_retries += 1
                    graphs = capture_graphs()
            x = state_a.x.numpy()
            step_ms = (time.perf_counter() - t0) * 1e3 / substeps if fi > 0 else 0.0
            finite = np.isfinite(x).all(axis=1)
            if not finite.all():
                bad = int(np.nonzero(~finite)[0][0])
                layer, vert = divmod(bad, v)
                failure = SimulationError(
                    f"frame {f}: particle {bad} ({LAYER_NAMES[layer]} layer, vertex {vert}) became NaN or inf; "
                    f"{len(written)} frames before it were written to {writer.path}. Lower dt or raise damping/iterations."
                )
                break
            skin = x[:v]
            lbs = linear_blend_skin(rig.vertices, ji, jw, frame_poses[fi])
            frame_points = {"skin": skin}
            if with_lbs:
                frame_points["lbs"] = lbs
            if with_layers:
                for k in range(1, 4):
                    frame_points[f"layer_{LAYER_NAMES[k]}"] = x[k * v:(k + 1) * v]
            writer.write_frame(f, frame_points)
            written.append(f)
            vel = state_a.v.numpy()
            metrics["time"].append(scene.frame_time(f))
            metrics["volume"].append(signed_volume(skin, tris))
            metrics["volume_lbs"].append(signed_volume(lbs, tris))
            if subs is not None:
                centres = subs.center_positions(frame_poses[fi])
                metrics["subvolume"].append(subs.volumes(skin.astype(np.float64), centres).tolist())
                metrics["subvolume_lbs"].append(subs.volumes(lbs, centres).tolist())
            metrics["kinetic_energy"].append(float(0.5 * np.sum(masses * np.einsum("ij,ij->i", vel, vel))))
            metrics["max_offset_from_lbs"].append(float(np.linalg.norm(skin - lbs, axis=1).max()))
            metrics["step_ms"].append(step_ms)
            metrics["residuals"].append(solver.residuals.numpy().tolist() if fi > 0 else [])
            if col is not None:
                counts = col.counts.numpy()
                metrics["contacts_point_triangle"].append(int(counts[0]) if fi > 0 else 0)
                metrics["contacts_edge_edge"].append(int(counts[1]) if fi > 0 else 0)
                metrics["constraints_active"].append(int(col.active.numpy()[0]) if fi > 0 else 0)
            if check_intersections:
                metrics["intersecting_pairs"].append(int(len(self_intersections(skin, tris))))
                metrics["intersecting_pairs_lbs"].append(int(len(self_intersections(lbs, tris))))
            bar.update(extra=f"{1e3 / step_ms:6.1f} steps/s" if step_ms > 0 else "")
    except BaseException:
        writer.abort()
        raise
    finally:
        bar.close()
    writer.close()  # on a NaN the frames before it stay, in a valid file

    # frame 0 is the LBS pose by construction (the simulation starts there): measure after it
    vol = np.array(metrics["volume"][1:])
    vol_lbs = np.array(metrics["volume_lbs"][1:])
    v0 = metrics["volume_rest"]
    summary = {
        "scene": scene.name,
        "device": str(dev),
        "particles": model.particle_count,
        "vertices": v,
        "frames": len(written),
        "substeps_per_frame": substeps,
        "dt_s": dt,
        "iterations": params.iterations,
        "volume_iterations": params.volume_iterations,
        "fast_summation": params.fast_summation,
        "graph_capture": bool(graphs),  # frames replayed from captured graphs (else plain launches)
        "build_s": build_s,
        "mean_step_ms": float(np.mean(metrics["step_ms"][1:])) if len(written) > 1 else 0.0,
        "max_volume_deviation": float(np.abs(vol / v0 - 1).max()) if vol.size else 0.0,
        "max_volume_deviation_lbs": float(np.abs(vol_lbs / v0 - 1).max()) if vol.size else 0.0,
        "collisions": col is not None,
        "collision_thickness_m": col.thickness if col is not None else None,
        "collision_capacity": col.capacity if col is not None else None,
        "overflow_retries": overflow_retries,
        "preroll_s": preroll,
        "preroll_steps": preroll_steps,
        "bvh_rebuilds": col.rebuilds if col is not None else 0,
    }
    if check_intersections and metrics["intersecting_pairs"]:
        summary["max_intersecting_pairs"] = max(metrics["intersecting_pairs"])
        summary["max_intersecting_pairs_lbs"] = max(metrics["intersecting_pairs_lbs"])
        summary["intersecting_pairs_first_frame"] = metrics["intersecting_pairs"][0]
    if subs is not None and metrics["subvolume"]:
        rest = np.array(metrics["subvolume_rest"])
        if len(metrics["subvolume"]) > 1:
            summary["max_subvolume_deviation"] = float(np.abs(np.array(metrics["subvolume"][1:]) / rest - 1).max())
            summary["max_subvolume_deviation_lbs"] = float(np.abs(np.array(metrics["subvolume_lbs"][1:]) / rest - 1).max())
        summary["subvolume_names"] = list(subs.names)
    result = SimulationResult(path=Path(writer.path), frames=written, metrics=metrics, summary=summary)
    if report_dir is not None:
        report = Path(report_dir)
        report.mkdir(parents=True, exist_ok=True)
        plots = write_plots(report, metrics, list(subs.names) if subs is not None else [])
        summary["plots"] = plots or "matplotlib not installed: pip install 'warpskin[report]' for PNG plots"
        (report / "report.json").write_text(json.dumps({"summary": summary, "metrics": metrics}, indent=1))
    if failure is not None:
        raise failure
    return result
