"""Several characters in one :class:`~warpskin.model.SkinModel`: one launch per kernel steps
them all (the throughput path on a GPU), and on the CPU each character's particles come out
bit for bit as when it is simulated alone.

Each character is built alone (:class:`~warpskin.model.SkinModelBuilder`, its own rig and
parameters); :func:`batch_model` then lays their host arrays side by side
(:func:`~warpskin.model.model_host_arrays`) with every index offset, so that the solver's
kernels, unchanged, see one model of ``V`` skin vertices, ``V`` the characters' sum:

* vertices, triangles, joints, sub-volumes and fan centres are numbered character after
  character (:class:`CharacterRange` gives each one's range);
* particles stay layer-major over the whole batch, ``k * V + vertex`` (layer ``k`` of every
  character, then the next layer), so every kernel's layer arithmetic holds; the CSR over
  particles (regions, the regions of each particle, the joint constraints) is re-laid in that
  order, each row's entries in their own order;
* a character's paths, runs and sub-volumes only reach its own vertices, and every sum a
  kernel makes (a region's, a path's prefix, a sub-volume's) runs over the same terms in the
  same order as alone: on Warp's CPU backend, which runs a launch's threads one after another,
  the results are the same floats;
* per-character scalars go per vertex where the solver reads them (the body's diagonal for the
  tether) or must agree (the coupling stiffness); influences are padded with zero weights,
  which the skinning skips.

The batched model's scalars that one model has once (``diagonal``: the largest; ``output_count``:
every vertex; ``collision_params`` and ``collision.thickness``, ``radius``, ...: the first
character's) stand for the batch only where they agree; the solver reads each character's from
per-vertex arrays (``vertex_diagonal``, ``vertex_loaded``, ``collision.characters``).

Self-collision stays within a character: each has its own detection and fail-safe trees
(:class:`~warpskin.collision.SelfCollision`), queried in the order it queries them alone, its
own tree rebuilds and its own contact scalars (thickness, radius, margins, friction, ...). (In a
batch with a refined character, every character's fail-safe queries its tree from every
triangle rather than taking the detection's pair list: the same pairs, at more cost.) The
characters must agree on what the host loops over (collision on or off, its passes and
fail-safe rounds) and all have volume or none; a rest-shape drive (layered popping) is not
batched. :func:`batch_model` refuses each in one line naming the character. A refined skin
(a coarse mesh simulated on a refined copy) keeps its written mesh's volume constraint and its
fail-safe on the written triangles, each character its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from .collision import CollisionTopology, contact_scalars
from .device import resolve_device
from .errors import InputError
from .model import SkinModel, SkinModelBuilder, model_host_arrays
from .params import CollisionParams
from .preprocess.sub_volumes import SubVolumes
from .volume import VolumeLayout

__all__ = ["CharacterRange", "CharacterControl", "batch_host_arrays", "batch_model", "character_controls"]


@dataclass(frozen=True)
class CharacterRange:
    """Where one character of a batch lies in the batched model.

    Attributes:
        name: The character's rig name (or its place in the batch).
        vertex_start, vertex_count: Its skin vertices ``[vertex_start, vertex_start +
            vertex_count)``; its particle of layer ``k`` and vertex ``i`` is
            ``k * V + vertex_start + i`` (``V`` the batch's vertices).
        joint_start, joint_count: Its joints (its part of ``Control.skin_matrices``).
        triangle_start, triangle_count: Its simulated skin triangles.
        written_start, written_count: Its written triangles (the loaded mesh's, where its skin
            was refined; else its simulated ones), in the batch's written triangles.
    """

    name: str
    vertex_start: int
    vertex_count: int
    joint_start: int
    joint_count: int
    triangle_start: int
    triangle_count: int
    written_start: int = 0
    written_count: int = 0

    def skin(self, positions: np.ndarray) -> np.ndarray:
        """``[vertex_count, 3]`` its skin (the first layer) out of a batch's particle positions
        ``positions`` ``[4 V, 3]`` (``state.x.numpy()``): a view, in its own vertex order."""
        return np.asarray(positions)[self.vertex_start:self.vertex_start + self.vertex_count]

    def particles(self, total_vertices: int) -> np.ndarray:
        """``[4 * vertex_count]`` its particles in the batch, in its own (layer-major) order."""
        i = np.arange(self.vertex_count, dtype=np.int64)
        return np.concatenate([k * total_vertices + self.vertex_start + i for k in range(4)])


def _csr_by_particle(parts: list, offsets_key: str, value_keys: Sequence[str], total: int, value_maps) -> dict:
    """Re-lay a CSR over particles (``[4 V_c + 1]`` offsets per character) in the batch's
    layer-major order: rows of layer 0 of every character, then layer 1, ... Values under
    ``value_keys`` are mapped per character by ``value_maps[key](c, values)``. Returns the new
    offsets, values, and per character ``entry_map`` ``[E_c]`` (old entry -> new entry)."""
    rows, values = [], {k: [] for k in value_keys}
    entry_maps = [np.empty(int(p[offsets_key][-1]), dtype=np.int64) for p in parts]
    at = 0
    for k in range(4):
        for c, p in enumerate(parts):
            v = p["vertex_count"]
            off = p[offsets_key]
            lo, hi = int(off[k * v]), int(off[(k + 1) * v])
            rows.append(np.diff(off[k * v:(k + 1) * v + 1]))
            entry_maps[c][lo:hi] = at + np.arange(hi - lo)
            at += hi - lo
            for key in value_keys:
                values[key].append(value_maps[key](c, p[key][lo:hi]))
    offsets = np.zeros(4 * total + 1, dtype=np.int64)
    np.cumsum(np.concatenate(rows), out=offsets[1:])
    return {"offsets": offsets, "entry_maps": entry_maps,
            **{k: np.concatenate(values[k]) if values[k] else np.zeros(0) for k in value_keys}}


def batch_host_arrays(parts: Sequence[dict], names: Sequence[str] | None = None) -> dict:
    """One model's host arrays (:func:`~warpskin.model.model_host_arrays`' layout) from the
    host arrays of several characters, each index offset (module docstring); ``characters``
    holds their :class:`CharacterRange` s.

    Raises:
        InputError: no characters, different coupling stiffnesses, a rest-shape drive, or
            some characters with sub-volumes and some without.
    """
    parts = [dict(p) for p in parts]  # (the caller's dicts stay as they are)
    if not parts:
        raise InputError("a batch needs at least one character")
    names = list(names) if names is not None else [f"character {c}" for c in range(len(parts))]
    if len(names) != len(parts):
        raise InputError(f"{len(names)} names for {len(parts)} characters")
    stiff = {float(p["coupling_stiffness"]) for p in parts}
    if len(stiff) > 1:
        raise InputError(f"the characters of a batch need one coupling stiffness, got {sorted(stiff)}")
    for name, p in zip(names, parts):
        if p["rest_drive"] is not None:
            raise InputError(f"{name}: a rest-shape drive (layered popping) is not batched")
    with_volume = [p["subvolume_count"] > 0 for p in parts]
    if any(with_volume) and not all(with_volume):
        lacking = [n for n, w in zip(names, with_volume) if not w]
        raise InputError(f"the characters of a batch all need sub-volumes or none; {', '.join(lacking)} has none")
    vs = np.array([p["vertex_count"] for p in parts], dtype=np.int64)
    js = np.array([p["joint_count"] for p in parts], dtype=np.int64)
    ts = np.array([len(p["tri_indices"]) for p in parts], dtype=np.int64)
    v0, j0, t0 = (np.concatenate([[0], np.cumsum(a)[:-1]]) for a in (vs, js, ts))
    total = int(vs.sum())

    def particle_map(c: int, local: np.ndarray) -> np.ndarray:  # local particle -> batch particle
        local = np.asarray(local, dtype=np.int64)
        layer, i = np.divmod(local, vs[c])
        return layer * total + v0[c] + i

    def layer_major(key: str) -> np.ndarray:  # [4 V_c, ...] per character -> [4 V, ...]
        return np.concatenate([p[key][k * p["vertex_count"]:(k + 1) * p["vertex_count"]]
                               for k in range(4) for p in parts])

    out: dict = {"vertex_count": total, "joint_count": int(js.sum()),
                 "coupling_stiffness": stiff.pop(), "rest_drive": None}
    for name, p in zip(names, parts):  # a skin written as simulated: its own triangles
        if "written_triangles" not in p and p.get("written_surface") is not None:
            raise InputError(f"{name}: a refined skin needs its written triangles (written_triangles)")
        p.setdefault("written_triangles", p["tri_indices"])
    ws = np.array([len(p["written_triangles"]) for p in parts], dtype=np.int64)
    w0 = np.concatenate([[0], np.cumsum(ws)[:-1]])
    out["characters"] = [CharacterRange(n, int(v0[c]), int(vs[c]), int(j0[c]), int(js[c]), int(t0[c]), int(ts[c]),
                                        int(w0[c]), int(ws[c])) for c, n in enumerate(names)]
    out["written_triangles"] = np.concatenate([np.asarray(p["written_triangles"], dtype=np.int64) + v0[c]
                                               for c, p in enumerate(parts)])
    for key in ("particle_q0", "particle_mass", "volume_inv_mass", "particle_stiffness", "particle_moment",
                "region_sibling_count", "region_rest_com", "region_mass"):
        out[key] = layer_major(key)
    for key in ("coupling_rest", "vertex_tissue_depth", "vertex_diagonal", "position_is_path_start"):
        out[key] = np.concatenate([p[key] for p in parts])
    out["tri_indices"] = np.concatenate([np.asarray(p["tri_indices"], dtype=np.int64) + v0[c] for c, p in enumerate(parts)])
    out["joint_rest"] = np.concatenate([p["joint_rest"] for p in parts])
    out["extent"] = np.array([float(p.get("extent", 0.0)) for p in parts])
    # regions: a CSR over regions (region r is particle r) of member particles; entries follow
    regions = _csr_by_particle(parts, "region_offsets", ["region_members", "region_rest_offsets"], total,
                               {"region_members": particle_map, "region_rest_offsets": lambda c, x: x})
    out["region_offsets"], out["region_members"] = regions["offsets"], regions["region_members"]
    out["region_rest_offsets"] = regions["region_rest_offsets"].reshape(-1, 3)
    # the regions of each particle and each one's entry (slot) in its region
    mine = _csr_by_particle(parts, "particle_region_offsets", ["particle_regions", "particle_region_slots"], total,
                            {"particle_regions": particle_map,
                             "particle_region_slots": lambda c, x: regions["entry_maps"][c][np.asarray(x, dtype=np.int64)]})
    out["particle_region_offsets"] = mine["offsets"]
    out["particle_regions"], out["particle_region_slots"] = mine["particle_regions"], mine["particle_region_slots"]
    # joint constraints: a CSR over particles of joints
    jc = _csr_by_particle(parts, "joint_offsets", ["joint_ids", "joint_rest_distance"], total,
                          {"joint_ids": lambda c, x: np.asarray(x, dtype=np.int64) + j0[c],
                           "joint_rest_distance": lambda c, x: x})
    out["joint_offsets"], out["joint_ids"], out["joint_rest_distance"] = jc["offsets"], jc["joint_ids"], jc["joint_rest_distance"]
    # fast summation: positions are vertices' places along the paths, character after character
    out["path_order"] = np.concatenate([np.asarray(p["path_order"], dtype=np.int64) + v0[c] for c, p in enumerate(parts)])
    out["path_offsets"] = np.concatenate([[0]] + [np.asarray(p["path_offsets"][1:], dtype=np.int64) + v0[c]
                                                  for c, p in enumerate(parts)])
    runs = np.array([len(p["run_start"]) for p in parts], dtype=np.int64)
    r0 = np.concatenate([[0], np.cumsum(runs)[:-1]])
    out["run_offsets"] = np.concatenate([[0]] + [np.asarray(p["run_offsets"][1:], dtype=np.int64) + r0[c]
                                                 for c, p in enumerate(parts)])
    out["run_start"] = np.concatenate([np.asarray(p["run_start"], dtype=np.int64) + v0[c] for c, p in enumerate(parts)])
    out["run_end"] = np.concatenate([np.asarray(p["run_end"], dtype=np.int64) + v0[c] for c, p in enumerate(parts)])
    # influences: as many columns as the most any character has, the others padded with weight 0
    width = max(np.asarray(p["coupling_joint_weights"]).reshape(p["vertex_count"], -1).shape[1] for p in parts)
    idx, wts = [], []
    for c, p in enumerate(parts):
        ji = np.asarray(p["coupling_joint_indices"], dtype=np.int64).reshape(p["vertex_count"], -1)
        jw = np.asarray(p["coupling_joint_weights"]).reshape(p["vertex_count"], -1)
        pad = width - ji.shape[1]
        idx.append(np.pad(ji + j0[c], ((0, 0), (0, pad)), constant_values=j0[c]))
        wts.append(np.pad(jw, ((0, 0), (0, pad))))
    out["coupling_joint_indices"], out["coupling_joint_weights"] = np.concatenate(idx), np.concatenate(wts)
    out["output_count"] = total  # (one model's loaded vertices come first; a batch's are vertex_loaded)
    out["vertex_loaded"] = np.concatenate([p["vertex_loaded"] for p in parts])
    out["vertex_written_volume"] = np.concatenate([p["vertex_written_volume"] for p in parts])
    out["written_surface"] = _batch_written_surface(parts, v0, total)
    out["subvolume_count"] = int(sum(p["subvolume_count"] for p in parts))
    out["volume_layout"], out["volume_centres"] = _batch_volume(parts, v0, j0, total) if out["subvolume_count"] else (None, None)
    out["rest"] = [replace(p["rest"][0], joint_start=int(j0[c])) for c, p in enumerate(parts)]
    for key in ("mean_edges", "character_diagonals"):
        out[key] = [p[key][0] for p in parts]
    out["collision_params"], out["collision"] = _batch_collision(parts, names, out["characters"])
    return out


@dataclass
class _Centres:
    """The sub-volumes' kinematic centres :func:`~warpskin.volume.upload_volume_layout` reads."""

    center_rest: np.ndarray
    center_joint: np.ndarray
    rest_volume: np.ndarray


def _batch_volume(parts, v0, j0, total: int):
    """The volume layouts of ``parts`` side by side, encoded points re-encoded for the batch
    (``k < V``: skin vertex, else fan centre ``k - V``)."""
    lays = [p["volume_layout"] for p in parts]
    cs = np.array([lay.center_count for lay in lays], dtype=np.int64)
    c0 = np.concatenate([[0], np.cumsum(cs)[:-1]])
    s0 = np.concatenate([[0], np.cumsum([lay.subvolume_count for lay in lays])[:-1]])
    p0 = np.concatenate([[0], np.cumsum([lay.pair_count for lay in lays])[:-1]])
    e0 = np.concatenate([[0], np.cumsum([lay.entry_count for lay in lays])[:-1]])
    t0 = np.concatenate([[0], np.cumsum([len(lay.closed_triangles) for lay in lays])[:-1]])

    def point(c: int, k) -> np.ndarray:
        k = np.asarray(k, dtype=np.int64)
        v = lays[c].vertex_count
        return np.where(k < v, k + v0[c], total + c0[c] + (k - v))

    def cat(key, shift=None, first=False):
        arrays = [np.asarray(getattr(lay, key), dtype=np.int64) for lay in lays]
        if first:  # CSR offsets: drop each leading 0 but the first
            return np.concatenate([[0]] + [a[1:] + shift[c] for c, a in enumerate(arrays)])
        return np.concatenate([a + (shift[c] if shift is not None else 0) for c, a in enumerate(arrays)])

    layout = VolumeLayout(
        vertex_count=total, center_count=int(cs.sum()),
        closed_offsets=cat("closed_offsets", t0, first=True),
        closed_triangles=np.concatenate([point(c, lay.closed_triangles) for c, lay in enumerate(lays)]),
        subvolume_origin=np.concatenate([point(c, lay.subvolume_origin) for c, lay in enumerate(lays)]),
        pair_vertex=cat("pair_vertex", v0), pair_subvolume=cat("pair_subvolume", s0),
        subvolume_pair_offsets=cat("subvolume_pair_offsets", p0, first=True),
        pair_entry_offsets=cat("pair_entry_offsets", e0, first=True),
        entry_points=np.concatenate([point(c, lay.entry_points) for c, lay in enumerate(lays)]),
        vertex_pair_offsets=cat("vertex_pair_offsets", p0, first=True),
        vertex_pairs=cat("vertex_pairs", p0))
    for name in ("closed_offsets", "closed_triangles", "subvolume_origin", "pair_vertex", "pair_subvolume",
                 "subvolume_pair_offsets", "pair_entry_offsets", "entry_points", "vertex_pair_offsets", "vertex_pairs"):
        setattr(layout, name, getattr(layout, name).astype(np.int32))
    subs = [p["volume_centres"] for p in parts]
    centres = _Centres(
        center_rest=np.concatenate([np.asarray(s.center_rest, dtype=np.float64).reshape(-1, 3) for s in subs]),
        center_joint=np.concatenate([np.asarray(s.center_joint, dtype=np.int64) + j0[c] for c, s in enumerate(subs)]),
        rest_volume=np.concatenate([np.asarray(s.rest_volume, dtype=np.float64) for s in subs]))
    return layout, centres


def batch_model(builders: Sequence, device=None):
    """One :class:`~warpskin.model.SkinModel` of several characters, each built by its own
    :class:`~warpskin.model.SkinModelBuilder` (instances of one rig or different rigs); its
    ``characters`` are their :class:`CharacterRange` s, in order. Drive it with the
    characters' skinning matrices concatenated (``Control.set_pose``, ``[sum J_c, 4, 4]``).

    Raises:
        InputError: not a builder, a rest-shape drive, characters that disagree on
            self-collision on or off, its passes or fail-safe rounds, or on having volume
            (module docstring); each names the character.
    """

    builders = list(builders)
    names = []
    for c, b in enumerate(builders):
        if not isinstance(b, SkinModelBuilder):
            raise InputError(f"character {c}: expected a SkinModelBuilder (SkinModelBuilder(rig, params)), "
                             f"got {type(b).__name__}")
        b.build()
        names.append(f"character {c} ({b.rig.name})")
    parts = []
    for b in builders:
        part = model_host_arrays(b)
        part["written_triangles"] = np.asarray(b.rig.output_triangles)
        parts.append(part)
    return SkinModel(batch_host_arrays(parts, names), resolve_device(device))


def _batch_collision(parts, names, ranges):
    """``(params, host form)`` of the batch's self-collision (:func:`~warpskin.model.model_host_arrays`'
    ``collision_params`` and ``collision``; ``(off, None)`` where no character collides): the
    characters' topologies side by side (vertices, edges, triangles and bones offset), each
    character's own scalars (``characters``: its thickness, radius, margins, friction, ...; the
    kernels read each vertex's), and the host's loop counts, which must agree (``passes``,
    ``fail_safe_rounds``: the solver runs them for all)."""
    params = [p["collision_params"] for p in parts]
    if not any(c.enabled for c in params):
        return CollisionParams(enabled=False), None
    for name, c in zip(names, params):
        c.check(name)
    for key, what in (("enabled", "self-collision on or off"), ("passes", "[collision] passes"),
                      ("fail_safe_rounds", "[collision] fail_safe_rounds")):
        values = [getattr(c, key) for c in params]
        odd = [c for c, v in enumerate(values) if v != values[0]]
        if odd:
            raise InputError(f"the characters of a batch need one {what}: {names[0]} has {values[0]!r}, "
                             f"{names[odd[0]]} {values[odd[0]]!r}")
    cols = [p["collision"] for p in parts]
    topos = [c["topology"] for c in cols]
    e0 = np.concatenate([[0], np.cumsum([len(t.edges) for t in topos])[:-1]])
    topo = CollisionTopology(
        edges=np.concatenate([t.edges + r.vertex_start for t, r in zip(topos, ranges)]),
        tri_edges=np.concatenate([t.tri_edges + e0[c] for c, t in enumerate(topos)]),
        edge_owner=np.concatenate([t.edge_owner + r.triangle_start for t, r in zip(topos, ranges)]),
        dominant_joint=np.concatenate([t.dominant_joint + r.joint_start for t, r in zip(topos, ranges)]),
        dominant_weight=np.concatenate([t.dominant_weight for t in topos]),
        mean_edge=topos[0].mean_edge, diagonal=max(t.diagonal for t in topos))
    # the rigid bones by each character's own rigid_weight: one set of parameters uploads them all
    rigid = [np.where(t.dominant_weight >= c.rigid_weight, t.dominant_joint + r.joint_start, -1)
             for t, c, r in zip(topos, params, ranges)]
    return params[0], {
        "topology": topo, "params": params[0],
        "vertices": np.concatenate([c["vertices"] for c in cols]),
        "triangles": np.concatenate([np.asarray(c["triangles"], dtype=np.int64) + r.vertex_start
                                     for c, r in zip(cols, ranges)]),
        "output_triangles": np.concatenate([np.asarray(c["output_triangles"], dtype=np.int64) + r.vertex_start
                                            for c, r in zip(cols, ranges)]),
        "rigid_bone": np.concatenate(rigid).astype(np.int32),
        # each character's scalars as its own model gets them
        "characters": [contact_scalars(t, c) for t, c in zip(topos, params)]}


def _batch_written_surface(parts, v0, total: int):
    """The refined characters' written surfaces (each one closed "sub-volume" without fans,
    :func:`~warpskin.model.written_surface`) as one :class:`SubVolumes` over the batch's
    vertices, in character order; ``None`` where no character has one."""
    have = [(c, p["written_surface"]) for c, p in enumerate(parts) if p.get("written_surface") is not None]
    if not have:
        return None
    tris = [np.asarray(w.triangles, dtype=np.int64) + v0[c] for c, w in have]
    counts = np.array([len(t) for t in tris], dtype=np.int64)
    return SubVolumes(
        names=[f"written mesh {c}" for c, _ in have], triangles=np.concatenate(tris),
        tri_offsets=np.concatenate([[0], np.cumsum(counts)]), tri_indices=np.arange(int(counts.sum())),
        fan_offsets=np.zeros(len(have) + 1, dtype=np.int64), fan_triangles=np.zeros((0, 3), dtype=np.int64),
        center_rest=np.zeros((0, 3)), center_joint=np.zeros(0, dtype=np.int64), loops=[],
        rest_volume=np.concatenate([np.asarray(w.rest_volume, dtype=np.float64) for _, w in have]),
        plane_joint=np.zeros(0, dtype=np.int64), plane_t=np.zeros(0), plane_normal=np.zeros((0, 3)),
        plane_sides=np.zeros((0, 2), dtype=np.int64), vertex_count=total)


class CharacterControl:
    """One character's part of a batched model's :class:`~warpskin.model.Control`: its own
    skinning matrices, a view of the batch's (no copy, no allocation per frame).

    Args:
        control: The batch's ``model.control()``.
        character: Its :class:`CharacterRange`.
    """

    def __init__(self, control, character: CharacterRange) -> None:
        self.character = character
        r = character
        self.skin_matrices = control.skin_matrices[r.joint_start:r.joint_start + r.joint_count]
        self._host = np.zeros((r.joint_count, 4, 4), dtype=np.float32)

    def set_pose(self, skin_matrices: np.ndarray) -> None:
        """Upload its skinning matrices ``[J_c, 4, 4]`` (``rig.skinning_matrices(clip, t)`` of
        its own rig) into its part of the batch's control."""
        m = np.asarray(skin_matrices)
        if m.shape != self._host.shape:
            raise InputError(f"{self.character.name}: expected skinning matrices of shape {self._host.shape}, "
                             f"got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InputError(f"{self.character.name}: skinning matrices hold NaN or inf")
        self._host[:] = m
        self.skin_matrices.assign(self._host)


def character_controls(model, control) -> list[CharacterControl]:
    """Each character's own control (:class:`CharacterControl`) over the batch's ``control``
    (``model.control()``), in the order of ``model.characters``."""
    if not model.characters:
        raise InputError("not a batched model: it has no characters (batch_model makes one)")
    return [CharacterControl(control, r) for r in model.characters]
