"""The ``warpskin`` command line.

    warpskin scenes                          list the shipped scenes
    warpskin info RIG|SCENE                  meshes, joints, clips, closedness, weight problems
    warpskin skin RIG|SCENE -o OUT.usdc      LBS or DQS skinning to time-sampled USD
    warpskin bench [SCENE ...] [--json F]    per-frame timings (LBS, DQS) on a device
    warpskin render BAKE.usdc -o DIR          Blender pictures: physical beside LBS, worst frame
    warpskin warmup                          compile (and cache) every Warp kernel

Errors print one line and exit with status 2 (bad input) or 1 (anything else); ``--debug``
prints the traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from .batch import add_parser as add_batch, cmd_batch
from .errors import InputError, SceneError, SimulationError, Stopped
from .io import list_meshes
from .parser import build_parser as command_parser
from .render import render_bake
from .scene import DEFAULT_FPS, Scene, clip_frame_span, find_assets_dir, is_rig_file, list_scenes, load_scene
from .units import describe, extent, file_unit

__all__ = ["main"]


def _scene_of(args):
    if is_rig_file(args.target):
        scene = Scene.from_rig_file(
            args.target, clip=getattr(args, "clip", None), fps=getattr(args, "fps", None),
            mesh=getattr(args, "mesh", None), unit_scale=getattr(args, "unit_scale", None),
        )
        if getattr(args, "weights", None):
            scene.rig_spec["weights"] = args.weights
        return _with_projection(scene, args)
    scene = load_scene(args.target)
    if getattr(args, "weights", None):
        scene.rig_spec["weights"] = args.weights
    if getattr(args, "clip", None):
        scene.clip = args.clip
    if getattr(args, "mesh", None):
        scene.rig_spec["mesh"] = args.mesh
    if getattr(args, "unit_scale", None):
        scene.rig_spec["unit_scale"] = args.unit_scale
    return _with_projection(scene, args)


def _with_projection(scene, args):
    """``--projection F,M,B``: the layers' projection parameters (scene: [layers] fat, muscle, bone)."""
    p = getattr(args, "projection", None)
    if p is not None:
        layers = scene.extra.setdefault("layers", {})
        layers["fat"], layers["muscle"], layers["bone"] = p
    return scene


# ------------------------------------------------------------------------------------ commands
def cmd_scenes(args) -> int:
    for s in list_scenes():
        print(f"{s['name']:<14} {s['rig']:<34} {s['description']}")
    return 0


def _muscle_summary(scene, character):
    """The muscle groups ``pop`` (``--pop-on surface``, the default) finds from the skeleton
    of what is simulated (the skin, or the cage), swelling the written meshes, as the pop
    summary lists them, or the one line why none are found; and the lines naming those left
    out (too coarse to show)."""
    from .model import SkinModelBuilder
    from .popping.examples import has_examples
    from .run.pop import LEFT_OUT, surface_muscles

    if has_examples(scene):
        return "the scene's popping examples", []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            builder = SkinModelBuilder(character.sim_rig, scene.model_params())
            found = surface_muscles(character, builder)[0]
    except InputError as exc:
        return f"no muscle groups ({exc})", []
    left = [str(w.message) for w in caught if str(w.message).startswith(LEFT_OUT)]
    return [{"name": m.name, "joints": m.joints, "vertices": m.vertices, "depth_mm": 1e3 * m.depth_m,
             "peak_swell_mm": 1e3 * m.peak_m} for m in found], left


def cmd_info(args) -> int:
    out: dict = {}
    if is_rig_file(args.target):
        out["meshes"] = list_meshes(args.target)
    scene = _scene_of(args)
    try:
        rig = scene.rig()
    except InputError as exc:
        if args.json:
            out["error"] = str(exc)
            print(json.dumps(out, indent=2))
        raise
    from .preprocess.cage import character_soup, rigid_pieces, surface_report

    summary = rig.summary()
    out.update(summary)
    out.update(surface_report(rig.triangles, rig.vertex_count))
    out["other_meshes"] = [a.name for a in rig.attachments]
    out["simulation"] = "direct" if (summary["closed"] and summary["manifold"]) else "cage"
    pieces = rigid_pieces(character_soup(rig))
    out["rigid_pieces"] = int(pieces.max()) + 1 if pieces.size else 0
    out["joint_names"] = rig.skeleton.joint_names
    out["length_unit_m"] = file_unit(scene.solver_params().units, rig.vertices)
    out["parents"] = rig.skeleton.parents.tolist()
    # the automatic physics weights of every mesh (through the cage simulate would build)
    from .character import Character

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        character = Character(rig, cage=args.cage, weights=scene.physics_weights() or None)
        character.bind()
    out["physics_weight"] = character.weight_summary()
    out["simulation"] = "cage" if character.caged else "direct"  # as --cage chose
    out["muscles"], left_out = _muscle_summary(scene, character)
    if left_out:
        out["muscles_left_out"] = left_out
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{summary['name']}  ({summary['source']})")
    if "meshes" in out:
        print("meshes:")
        for m in out["meshes"]:
            mark = "*" if m.get("name") == rig.mesh_name else " "
            skinned = "skinned" if m.get("skinned", m.get("skin") is not None) else "not skinned"
            print(f"  {mark} {m.get('name')}: {m.get('vertices')} vertices, {m.get('triangles')} triangles, {skinned}")
    print(
        f"mesh {summary['mesh']!r}: {summary['vertices']} vertices welded ({summary['file_vertices']} in the file), "
        f"{summary['triangles']} triangles, up axis {summary['up_axis']}, metres per unit {summary['meters_per_unit']:g}"
    )
    lo, hi = summary["bbox_min"], summary["bbox_max"]
    print("bounds [m]: " + " .. ".join("(" + ", ".join(f"{c:.4g}" for c in v) + ")" for v in (lo, hi)))
    print(_unit_line(scene, rig))
    closed = "closed" if summary["closed"] else f"OPEN ({summary['boundary_edges']} boundary edges)"
    manifold = "manifold" if summary["manifold"] else f"NOT manifold ({summary['nonmanifold_edges']} non-manifold edges)"
    print(f"surface: {closed}, {manifold}; {out['pieces']} piece(s), {out['boundary_loops']} boundary loop(s); "
          f"degenerate triangles: {summary['degenerate_triangles']}")
    if out["other_meshes"]:
        print(f"other meshes following the skeleton ({len(out['other_meshes'])}): {', '.join(out['other_meshes'])}")
    why = "as --cage asks" if summary["closed"] and summary["manifold"] else "the skin is not one closed manifold"
    how = ("its skin directly (closed, manifold)" if out["simulation"] == "direct"
           else f"a closed cage around it, every mesh captured by it ({why})")
    print(f"simulate would use: {how}")
    if out["rigid_pieces"]:
        print(f"rigid pieces (meshes or parts that LBS moves rigidly, one joint each): {out['rigid_pieces']}; through a "
              "cage they move by one rigid motion with the cage around them (--rigid-pieces joint: with their joints)")
    _print_weights(out["physics_weight"])
    muscles = out["muscles"]
    if isinstance(muscles, list):
        print(f"pop would use ({len(muscles)} muscle groups from the skeleton; --groups NAME=JOINT_PATTERN names others):")
        for m in muscles:
            print(f"  {m['name']}: {m['vertices']} written points, tissue "
                  f"{m['depth_mm']:.0f} mm deep, swelling up to {m['peak_swell_mm']:.1f} mm")
    else:
        print(f"pop would use: {muscles}")
    for line in out.get("muscles_left_out", []):
        print(f"  ({line})")
    print(f"joints ({summary['joints']}), max {summary['max_influences']} influences per vertex:")
    names = rig.skeleton.joint_names
    for j, (n, p) in enumerate(zip(names, rig.skeleton.parents)):
        print(f"  {j:3d} {n}  <- {names[p] if p >= 0 else '(root)'}")
    print("clips:" if summary["clips"] else "clips: none (rest pose only; a scene file keys its joints in "
          "[animation.keys], see the docs' scenes page)")
    for n, c in summary["clips"].items():
        rate = scene.fps or rig.clip(n).rate or DEFAULT_FPS
        first, last = clip_frame_span(rig.clip(n), rate)
        print(f"  {n}: frames {first}:{last} at {rate:g} fps ({c['start']:.4g} .. {c['end']:.4g} s), "
              f"{c['tracks']} tracks")
    for w in summary["warnings"]:
        print(f"warning: {w}")
    return 0


def _of_diagonal(length: float, summary: dict, digits: int = 2) -> str:
    """``" (0.19 % of the diagonal)"``: ``length`` [m] as a share of the written meshes' rest
    diagonal (empty where the summary has none)."""
    diag = summary.get("written_diagonal_m") or summary.get("body_diagonal_m") or 0.0
    return f" ({100 * length / diag:.{digits}f} % of the diagonal)" if diag > 0 else ""


def _joint_text(row: dict, summary: dict) -> str:
    """``", at its joints 0.012 m (0.19 % of the diagonal)"``: how far a written mesh moved from
    its LBS where it meets other pieces (empty where it meets none)."""
    j = row.get("max_joint_offset")
    if not j:
        return ""
    return f", at its joints {j:.3g} m{_of_diagonal(j, summary)}"


def _unit_line(scene, rig) -> str:
    """One line: the character's size and the length unit physics takes it in."""
    unit = file_unit(scene.solver_params().units, rig.vertices)
    size = extent(rig.vertices)
    how = ("[solver] units = \"file\"" if scene.solver_params().units == "file"
           else "the power of ten nearest human size; [solver] units = \"file\" takes metres")
    return (f"size: {size:.4g} units across (largest side); physics takes 1 unit as {describe(unit)} ({how}): "
            f"{size * unit:.3g} m")


def _print_weights(weights: dict) -> None:
    """The physics weight map, a line per written mesh."""
    for name, w in weights.items():
        if name == "notes":
            continue
        print(f"physics weight of {name}: mean {w['mean']:.2f}, {100 * w['lbs_share']:.0f} % of its points LBS, "
              f"{100 * w['physical_share']:.0f} % fully physical")


def cmd_skin(args) -> int:
    from .run import SkinningOptions, skin_to_usd

    scene = _scene_of(args)
    out = Path(args.output)
    options = SkinningOptions(
        method=args.method, device=args.device, frames=args.frames, fps=args.fps, start_frame=args.start_frame,
        with_rest=args.with_rest, with_lbs=args.with_lbs, topology=args.topology, progress=not args.quiet,
        comment="warpskin " + " ".join(sys.argv[1:]),
    )
    run = skin_to_usd(scene, out, options)
    if args.json:
        return _print_json({"path": str(run.path), **run.summary})
    print(f"wrote {run.path} ({run.frames} frames, {args.method})")
    return 0


def _print_json(summary: dict) -> int:
    """A command's summary as one JSON document on stdout (``--json``)."""

    def plain(value):
        if isinstance(value, (np.floating, np.integer)):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
        return str(value)

    print(json.dumps(summary, indent=2, default=plain))
    return 0


def cmd_layers(args) -> int:
    from .io.model_usd import write_model_usd
    from .io.usd_export import check_output_path
    from .model import SkinModelBuilder

    from .character import Character

    scene = _scene_of(args)
    check_output_path(args.output, inputs=scene.input_paths())  # before any work
    # the model that simulate would build: of the skin, or of the automatic cage of an open one
    character = Character(scene.rig(), weights=scene.physics_weights() or None)
    builder = SkinModelBuilder(character.sim_rig, scene.model_params())
    builder.build()
    character.bind(builder)
    path = write_model_usd(builder, args.output, comment="warpskin " + " ".join(sys.argv[1:]), character=character)
    summary = builder.summary()
    summary["physics_weight"] = character.weight_summary()
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(
            f"{summary['particles']} particles on 4 layers ({summary['vertices']} per layer), "
            f"total mass {summary['total_mass_kg']:.3g} kg; regions: omega {summary['omega']}, "
            f"{summary['mean_region_size']:.1f} particles on average; fast summation: {summary['paths']} paths, "
            f"{summary['mean_runs_per_region']:.2f} runs per region; {summary['subvolumes']} sub-volumes; "
            f"{summary['joint_constraints']} joint constraints"
        )
        for note in summary["depth_notes"]:
            print(note)
        _print_weights(summary["physics_weight"])
        print("build time: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in summary["timings_s"].items()))
    print(f"wrote {path}")
    return 0


def cmd_simulate(args) -> int:
    from dataclasses import replace

    from .run import SimulationOptions, simulate

    scene = _scene_of(args)
    if args.fps:
        scene.fps = float(args.fps)
    # the scene's settings, then the command line's overrides of them, in one place
    changes = {key: getattr(args, key) for key in ("iterations", "volume_iterations", "dt", "damping")
               if getattr(args, key) is not None}
    if args.fast_summation:
        changes["fast_summation"] = True
    if args.no_gravity:
        changes["gravity"] = (0.0, 0.0, 0.0)
    params = replace(scene.solver_params(), **changes)
    collision = scene.collision_params()
    if args.no_collisions:
        collision = replace(collision, enabled=False)
    guard = scene.guard_params()
    if args.no_guard:
        guard = replace(guard, enabled=False)
    options = SimulationOptions(
        device=args.device, frames=args.frames, solver_params=params, collision=collision, with_lbs=args.lbs,
        with_layers=args.layers, report_dir=args.report, progress=not args.quiet,
        comment="warpskin " + " ".join(sys.argv[1:]), preroll=args.preroll, allow_unstable=args.allow_unstable,
        start_frame=args.start_frame, topology=args.topology, cage=args.cage, rigid_pieces=args.rigid_pieces,
        physics_weights=dict(args.physics_weight or []), guard=guard,
    )
    result = simulate(scene, Path(args.output), options)
    s = result.summary
    if args.json:
        return _print_json({"path": str(result.path), **s})
    delivered = s.get("delivered", {})
    worst = max(delivered.values(), key=lambda d: d["volume"]) if delivered else None
    line = (
        f"wrote {result.path} ({s['frames']} frames, {s['particles']} particles, {s['substeps_per_frame']} substeps "
        f"of {s['dt_s'] * 1e3:.2f} ms, {s['mean_step_ms']:.1f} ms per step on {s['device']}, "
        f"{s['mean_frame_ms']:.0f} ms per frame of which {100 * s['host_share']:.0f} % around the steps)"
    )
    if worst is not None:
        line += (f"; largest volume change of what is written after the first frame: warpskin "
                 f"{100 * worst['volume']:.2f} %, LBS {100 * worst['volume_lbs']:.2f} %")
    print(line)
    # what was written: each mesh's worst frame against its own LBS, and what the physics delivered
    for name, r in s["written"].items():
        d = delivered.get(name, {})
        pairs = (f", pairs beyond the rest pose's {r['max_pairs_new']} (LBS {r['max_pairs_new_lbs']})"
                 if "max_pairs_new" in r else "")
        held = f", held back {100 * d['held']:.1f} % (worst frame {100 * d['held_max']:.1f} %)" if d else ""
        held += f", copies of a point apart {1e3 * r['max_split']:.2f} mm" if r.get("max_split") else ""
        motion = (f", secondary motion {100 * d['secondary_motion']:.1f} % of the animation's, largest jump "
                  f"{100 * d['chatter']:.2f} % of the height, volume {100 * d['volume']:.2f} % (LBS "
                  f"{100 * d['volume_lbs']:.2f} %)" if d else "")
        rigid = (f", rigid pieces within {1e3 * d['rigid_rms_m']:.2f} mm RMS" if d.get("rigid_pieces") else "")
        print(f"  {name}: physics weight {s['physics_weight'].get(name, {}).get('mean', 0.0):.2f}{held}{motion}"
              f"{pairs}, edges strained past 1.5x {100 * r['max_strained']:.2f} % (LBS {100 * r['max_strained_lbs']:.2f} %), "
              f"flipped {100 * r['max_flipped']:.2f} %, offset {r['max_offset']:.3g} m{_of_diagonal(r['max_offset'], s, 1)}"
              f"{_joint_text(r, s)}{rigid}")
    across = s.get("written_across") or {}
    if across:
        where = (f", the most at frame {across['max_pairs_across_excess_frame']:g} between "
                 f"{' and '.join(across['max_pairs_across_excess_meshes'])}" if across["max_pairs_across_excess_meshes"]
                 else "")
        print(f"pairs between written meshes beyond the rest pose's (worst frame): warpskin "
              f"{across['max_pairs_across_new']}, LBS {across['max_pairs_across_new_lbs']}; more than LBS in "
              f"{across['frames_pairs_across_over']} of {across['frames']} frames{where}")
    surface = s.get("surface", {})
    kind = {"skin": "the skin itself", "pieces": f"its own pieces ({len(surface.get('simulated', []))} simulated, "
            f"{len(surface.get('attached', []))} carried or worn)", "cage": "an automatic cage"}.get(surface.get("kind"), "")
    if surface.get("kind") == "cage" and s.get("cage", {}) and s["cage"].get("source") != "automatic":
        kind = f"the cage {s['cage']['source']}"
    print(f"simulated surface, {kind}: volume after the first frame {100 * s['max_volume_deviation']:.2f} % "
          f"(LBS {100 * s['max_volume_deviation_lbs']:.2f} %)")
    if "max_intersecting_pairs" in s:
        print(f"intersecting pairs of the simulated surface (exact check, worst frame): warpskin {s['max_intersecting_pairs']}, "
              f"LBS {s['max_intersecting_pairs_lbs']}")
        if s["intersecting_pairs_first_frame"]:
            hint = "" if s["preroll_steps"] else "; --preroll 0.5 reaches it from the bind pose instead"
            print(f"note: the first frame already self-intersects ({s['intersecting_pairs_first_frame']} pairs); "
                  f"contacts keep surfaces apart but cannot undo intersections they start with{hint}")
    if args.report:
        print(f"report: {Path(args.report) / 'report.json'}")
    return 0


def cmd_bench(args) -> int:
    from .bench import run_build_bench, run_skinning_bench, run_solver_bench

    if args.build:
        result = run_build_bench(args.scenes or ["arm", "cesium_man", "arm35k"])
    elif args.batch is not None:
        from .bench import run_batch_bench

        if args.batch < 1:
            raise InputError(f"--batch needs a positive number of characters, got {args.batch}")
        result = run_batch_bench(args.scenes or ["arm"], args.batch, device=args.device, steps=args.steps,
                                 repeat=args.repeat)
    else:
        scenes = args.scenes or ["arm", "cesium_man"]
        from .bench import run_popping_bench

        result = {
            "solver": run_solver_bench(scenes, device=args.device, steps=args.steps, repeat=args.repeat),
            "skinning": run_skinning_bench([s for s in scenes if not _missing_asset(s)], device=args.device,
                                           frames=args.frames, repeat=args.repeat),
            "popping": run_popping_bench(args.device, steps=max(args.steps, 50), repeat=args.repeat),
        }
    return _emit_json(result, args.json)


def _emit_json(result: dict, path: str | None) -> int:
    """Print a benchmark's JSON and, with ``--json FILE``, write it there too."""
    text = json.dumps(result, indent=2)
    if path and path != "-":
        Path(path).write_text(text + "\n")
        print(f"wrote {path}")
    print(text)
    return 0


def _missing_asset(target: str) -> bool:
    if is_rig_file(target):
        return False
    try:
        return "asset" in load_scene(target).rig_spec and find_assets_dir() is None
    except Exception:
        return False


def cmd_pop(args) -> int:
    from .bench import run_popping_bench
    from .run import PoppingOptions, run_popping

    if args.bench:
        return _emit_json(run_popping_bench(args.device, steps=args.steps, repeat=args.repeat), args.json)
    if args.target is None or args.output is None:
        raise SceneError("pop needs a SCENE and -o OUT.usdc (or --bench)")
    scene = _scene_of(args)
    options = PoppingOptions(
        device=args.device, frames=args.frames, fps=args.fps, start_frame=args.start_frame, topology=args.topology,
        alpha_min=args.alpha_min, beta=args.beta, dt=args.dt, progress=not args.quiet,
        comment="warpskin " + " ".join(sys.argv[1:]), mode=args.mode, beats=_beat_spec(args),
        muscles=_group_entries(args), swell=args.swell, cage=args.cage, report_dir=args.report,
        normal_guide=not args.no_normal_guide, vibrate=not args.no_vibrate, pop_on=args.pop_on,
    )
    result = run_popping(scene, Path(args.output), options)
    s = result.summary
    if args.json:
        return _print_json({"path": str(result.path), "frames": result.frames, **s})
    if s.get("mode") == "layered" and s.get("pop_on") == "surface":
        print(
            f"wrote {result.path} ({result.frames} frames, on the written meshes: muscles driven by groups {', '.join(s['groups'])} "
            f"over the physical skin of {s['particles']} particles, {s['mean_step_ms']:.1f} ms per step on "
            f"{s['device']}); each mesh it moves also written without it as <mesh>_normal"
        )
    elif s.get("mode") == "layered":
        print(
            f"wrote {result.path} ({result.frames} frames, layered: the muscle layer of {s['particles']} particles driven "
            f"by groups {', '.join(s['groups'])}, {s['mean_step_ms']:.1f} ms per step on {s['device']}); largest volume "
            f"deviation after the first frame {100 * s['max_volume_deviation']:.2f} %"
        )
    if s.get("mode") == "layered":
        for m in s.get("muscles", []):
            print(f"  {m['name']}: bones {', '.join(m['joints'])}, {m['vertices']} skin vertices, tissue "
                  f"{m['depth_mm']:.0f} mm deep, swelling up to {m['peak_swell_mm']:.1f} mm")
        _print_beats(s)
        return 0
    print(
        f"wrote {result.path} ({result.frames} frames, {s['substeps']} steps of {s['dt_s'] * 1e3:.2f} ms per frame, "
        f"{s['vertices']} vertices, groups {', '.join(s['groups'])}, {s['ms_per_frame']:.2f} ms per frame on {s['device']}); "
        f"peak overshoot {s['peak_overshoot_m'] * 1e3:.2f} mm (alpha_min {s['alpha_min']:g})"
    )
    _print_beats(s)
    return 0


def _print_beats(s: dict) -> None:
    """With ``--report``: each group's pops as read back from the written file, one line."""
    if not s.get("beats"):
        return
    print(f"pops read back from the file (the skin over each belly outside its reference; report: {s['popping_report']}):")

    def span(values, fmt):
        lo, hi = min(values), max(values)
        return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else f"{fmt.format(lo)}-{fmt.format(hi)}"

    for g, rows in s["beats"].items():
        if not rows:
            print(f"  {g}: no pop within the frames written")
            continue
        share = (f" ({span([100 * r['share_of_depth'] for r in rows], '{:.0f}')} % of its depth)"
                 if "share_of_depth" in rows[0] else "")
        print(f"  {g}: {len(rows)} pops, peak {span([r['peak_mm'] for r in rows], '{:.1f}')} mm{share}, reached "
              f"{span([r['rise_lag_frames'] for r in rows], '{:.3g}')} frames after the beat (90 %), largest "
              f"{span([r['peak_lag_frames'] for r in rows], '{:.3g}')} after, "
              f"{span([r['end_mm'] for r in rows], '{:.1f}')} mm left before the next")


def _group_entries(args) -> list[str] | None:
    """``--groups`` split at its commas (``NAME`` or ``NAME=JOINT_PATTERN`` each)."""
    return [g.strip() for g in args.groups.split(",")] if args.groups else None


def _beat_spec(args):
    """The pops on the beat the ``pop`` command's flags ask for (``None``: the scene's own
    activation)."""
    from .popping.activation import BeatSpec, read_beats

    entries = _group_entries(args)
    groups = [e.partition("=")[0].strip() for e in entries] if entries is not None else None
    if groups is not None and (not all(groups) or len(set(groups)) != len(groups)):
        raise SceneError(f"--groups must name distinct muscle groups separated by commas, got {args.groups!r}")
    tempo_only = [flag for flag, given in (("--offset", args.offset != 0.0), ("--every", args.every != 1)) if given]
    if args.bpm is None and args.beats is None:
        extra = [flag for flag, given in (("--hold", args.hold is not None), ("--groups", groups is not None),
                                          ("--in-turn", args.in_turn)) if given] + tempo_only
        if extra:
            raise SceneError(f"{', '.join(extra)} need --bpm or --beats")
        return None
    if args.bpm is not None and args.beats is not None:
        raise SceneError("give one of --bpm or --beats, not both")
    if args.beats is not None and tempo_only:
        raise SceneError(f"{', '.join(tempo_only)} apply to --bpm, not to --beats")
    return BeatSpec(bpm=args.bpm, offset=args.offset, every=args.every,
                    beats=read_beats(args.beats) if args.beats is not None else None, hold=args.hold, groups=groups,
                    in_turn=args.in_turn)


def cmd_render(args) -> int:
    render_bake(args.bake, args.output, frames=args.frames, extra=args.extra, close_up=not args.no_close_up,
                resolution=args.resolution, python=args.python, progress=not args.quiet, yaw=args.yaw,
                color=args.color)
    return 0


def cmd_warmup(args) -> int:
    import importlib
    import pkgutil
    import time

    import warp as wp

    from . import kernels
    from .device import resolve_device

    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    for info in pkgutil.iter_modules(kernels.__path__):  # every kernel module, none forgotten
        wp.load_module(importlib.import_module(f"{kernels.__name__}.{info.name}"), device=dev)
    print(f"kernels ready on {dev} in {time.perf_counter() - t0:.1f} s (cache: {wp.config.kernel_cache_dir})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The parser of every command (:func:`warpskin.parser.build_parser`), each command's
    function set as its ``func``, ``warpskin batch`` included."""
    handlers = {"scenes": cmd_scenes, "info": cmd_info, "skin": cmd_skin, "simulate": cmd_simulate,
                "layers": cmd_layers, "bench": cmd_bench, "pop": cmd_pop, "render": cmd_render,
                "warmup": cmd_warmup}

    def batch(sub) -> None:
        add_batch(sub)
        sub.choices["batch"].set_defaults(func=cmd_batch)

    return command_parser(handlers, batch)


def _init_warp_quietly() -> None:
    """Initialise Warp with its native "no CUDA driver" notice (printed by the C library on
    every start of a machine without a GPU) kept off the terminal; a command that asks for a
    CUDA device initialises it normally and sees the notice."""
    import os

    import warp as wp

    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no real stderr (captured): nothing to hide
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
        wp.init()
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def _on_signal(signum, frame):
    raise Stopped(signum)


def _install_signal_handlers() -> dict:
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return {}
    saved = {}
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is not None and signal.getsignal(sig) is not signal.SIG_IGN:  # nohup keeps SIGHUP ignored
            saved[sig] = signal.signal(sig, _on_signal)
    return saved


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    if not getattr(args, "command", None):
        parser.print_help()
        return 2
    if args.debug:  # Warp's banner and module-load lines too (warpskin.device quiets them)
        import warp as wp

        from . import device  # noqa: F401 (its import sets the level this one overrides)

        wp.config.log_level = wp.LOG_INFO
    else:
        import warp as wp

        wp.config.log_level = wp.LOG_ERROR  # no banner
        if not str(getattr(args, "device", None) or "").startswith("cuda"):
            _init_warp_quietly()
    def one_line(message, category, filename, lineno, file=None, line=None):  # no file paths or source lines
        print(f"warpskin: warning: {message}", file=sys.stderr if file is None else file)

    shown = warnings.showwarning
    if not args.debug:
        warnings.showwarning = one_line
    saved_handlers = _install_signal_handlers()
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        from .io.usd_export import remove_temporary_files

        remove_temporary_files()
        print("warpskin: interrupted; nothing was written", file=sys.stderr)
        return 130
    except Stopped as exc:
        import signal

        from .io.usd_export import remove_temporary_files

        remove_temporary_files()  # also a writer the signal caught before anything could abort it
        if exc.kept is not None:
            print(f"warpskin: stopped by {signal.Signals(exc.signum).name}; the {exc.kept[0]} frames finished before "
                  f"it were written to {exc.kept[1]}", file=sys.stderr)
            return 128 + exc.signum

        print(f"warpskin: stopped by {signal.Signals(exc.signum).name}; nothing was written", file=sys.stderr)
        return 128 + exc.signum
    except SimulationError as exc:  # the run failed or left its valid range; earlier frames kept
        if args.debug:
            raise
        print(f"warpskin: simulation failed: {exc}", file=sys.stderr)
        return SimulationError.exit_code
    except (InputError, argparse.ArgumentTypeError) as exc:  # bad input or usage
        if args.debug:
            raise
        print(f"warpskin: error: {exc}", file=sys.stderr)
        return InputError.exit_code
    except Exception as exc:  # a bug: one clear line; --debug for the traceback
        if args.debug:
            raise
        print(f"warpskin: internal error: {type(exc).__name__}: {exc} (this is a bug; run with --debug for the "
              "traceback)", file=sys.stderr)
        return 1
    finally:
        warnings.showwarning = shown
        import signal

        for sig, handler in saved_handlers.items():
            signal.signal(sig, handler)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
