"""glTF skins and animations: joints, the skeleton with folded non-joint nodes, clips."""

from __future__ import annotations

import warnings

import numpy as np

from ...animation import PATHS, Clip, Track, key_rate
from ...rig import RigError, RigWarning, Skeleton
from ...transforms import compose_trs, decompose_trs, quat_multiply
from .document import _Document



class _SkinInfo:
    """The skin's joints mapped onto a :class:`Skeleton`, plus what the tracks need."""

    def __init__(self, doc: _Document, skin_index: int, node_parent: np.ndarray) -> None:
        skin = doc.skins[skin_index]
        joints = list(skin.joints or [])
        if not joints:
            raise doc.error(f"skin {skin_index} has no joints")
        for k in joints:
            doc.item("nodes", k, f"skin {skin_index} joint list")
        if len(set(joints)) != len(joints):
            dup = sorted({k for k in joints if joints.count(k) > 1})
            raise doc.error(f"skin {skin_index} lists nodes {dup} more than once")
        self.joints = joints
        self.joint_of_node = {node: j for j, node in enumerate(joints)}
        n_j = len(joints)
        self.names = _joint_names(doc, joints)
        parents = np.full(n_j, -1, dtype=np.int64)
        root_transform = np.tile(np.eye(4), (n_j, 1, 1))
        trs_t, trs_r, trs_s = np.zeros((n_j, 3)), np.zeros((n_j, 4)), np.zeros((n_j, 3))
        # joint -> static transform of the non-joint nodes between it and its parent joint
        self.pre: dict[int, tuple[np.ndarray, np.ndarray, float, bool]] = {}
        self.ancestors: set[int] = set()  # non-joint ancestors of any joint
        self.root_chain_nodes: set[int] = set()  # those above a root joint (their animation is kept)
        root_chains: dict[int, list[tuple[int, np.ndarray]]] = {}
        for j, node in enumerate(joints):
            chain = []
            p = int(node_parent[node])
            while p >= 0 and p not in self.joint_of_node:
                chain.append(p)
                p = int(node_parent[p])
            self.ancestors.update(chain)
            chain_m = np.eye(4)
            for c in reversed(chain):  # top-down product
                chain_m = chain_m @ doc.local_matrix(c)
            t, r, s = doc.local_trs(node)
            if p < 0:
                root_transform[j] = chain_m
                if chain:
                    root_chains[j] = [(int(c), doc.local_matrix(c)) for c in reversed(chain)]
                    self.root_chain_nodes.update(int(c) for c in chain)
            else:
                parents[j] = self.joint_of_node[p]
                if not np.allclose(chain_m, np.eye(4), atol=1e-12):
                    t, r, s, pre = self._fold(doc, chain_m, chain, t, r, s)
                    self.pre[j] = pre
            trs_t[j], trs_r[j], trs_s[j] = t, r, s
        self.skeleton = Skeleton(self.names, parents, trs_t, trs_r, trs_s, root_transform, root_chains)

    @staticmethod
    def _fold(
        doc: _Document, chain_m: np.ndarray, chain: list[int], t: np.ndarray, r: np.ndarray, s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, float, bool]]:
        """Fold a static non-joint transform ``C`` between two joints into the child's local TRS.

        For a similarity ``C = T_c R_c (s_c I)``: ``C @ T R S = T' R' S'`` with
        ``T' = C @ t``, ``R' = R_c R``, ``S' = s_c S``; the same affine maps apply to every key.
        """
        ct, cr, cs = decompose_trs(chain_m)
        similarity = bool(
            np.allclose(cs, cs.mean(), rtol=1e-6) and np.allclose(compose_trs(ct, cr, cs), chain_m, atol=1e-9)
        )
        c3 = chain_m[:3, :3]
        if similarity:
            sc = float(cs.mean())
            return c3 @ t + chain_m[:3, 3], quat_multiply(cr, r), sc * s, (chain_m, cr, sc, True)
        t2, r2, s2 = decompose_trs(chain_m @ compose_trs(t, r, s))
        return t2, r2, s2, (chain_m, cr, float(np.cbrt(abs(np.linalg.det(c3)))), False)

    def bake(self, j: int, path: str, values: np.ndarray, cubic: bool) -> np.ndarray:
        """Map a track's values through the folded non-joint transform of joint ``j``."""
        if j not in self.pre:
            return values
        chain_m, cr, sc, _ = self.pre[j]
        if path == "translation":
            out = values @ chain_m[:3, :3].T
            if cubic:
                out[:, 1] += chain_m[:3, 3]  # tangents are directions: no offset
            else:
                out += chain_m[:3, 3]
            return out
        if path == "rotation":
            return quat_multiply(cr, values)  # linear in the key: valid for tangents too
        return values * sc


def _joint_names(doc: _Document, joints: list[int]) -> list[str]:
    names: list[str] = []
    taken: set[str] = set()
    for node in joints:
        base = doc.nodes[node].name or f"node_{node}"
        name = base if base not in taken else f"{base}_{node}"
        k = 1
        while name in taken:
            name, k = f"{base}_{node}_{k}", k + 1
        taken.add(name)
        names.append(name)
    return names


def _read_clips(doc: _Document, info: _SkinInfo) -> dict[str, Clip]:
    clips: dict[str, Clip] = {}
    names: set[str] = set()
    for a, anim in enumerate(doc.animations):
        base = anim.name or f"animation_{a}"
        name, k = base, 1
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.add(name)
        tracks: dict[tuple[int, str], Track] = {}
        above: dict[tuple[int, str], Track] = {}  # animated nodes above the root joints
        ignored: set[int] = set()
        approximated: set[int] = set()
        samplers = list(anim.samplers or [])
        for c, ch in enumerate(anim.channels or []):
            target = ch.target
            node = target.node if target is not None else None
            path = target.path if target is not None else None
            if node is None or path not in PATHS:
                continue  # morph weights, KHR_animation_pointer, ...
            doc.item("nodes", node, f"animation {name!r} channel {c}")
            if node not in info.joint_of_node and node not in info.root_chain_nodes:
                if node in info.ancestors:
                    ignored.add(int(node))
                continue
            j = info.joint_of_node.get(node)
            what = (f"animation {name!r} channel {c} ({info.names[j]!r} {path})" if j is not None
                    else f"animation {name!r} channel {c} ({doc.node_label(node)} {path}, above the skeleton)")
            if not isinstance(ch.sampler, int) or not 0 <= ch.sampler < len(samplers):
                raise doc.error(f"{what} uses sampler {ch.sampler!r}, but the animation has {len(samplers)}")
            sampler = samplers[ch.sampler]
            interp = sampler.interpolation or "LINEAR"
            times = doc.accessor(sampler.input, f"{what} input")
            if times.shape[1] != 1:
                raise doc.error(f"{what}: the input (time) accessor is not SCALAR")
            values = doc.accessor(sampler.output, f"{what} output")
            cubic = interp == "CUBICSPLINE"
            width = PATHS[path]
            k_count = times.shape[0]
            expected = 3 * k_count if cubic else k_count
            if values.shape[1] != width or values.shape[0] != expected:
                raise doc.error(
                    f"{what}: accessor count mismatch: {k_count} key times need {expected} "
                    f"{'VEC' + str(width)} output values, got {values.shape[0]} of {values.shape[1]} components"
                )
            if j is not None and j in info.pre:
                if not info.pre[j][3]:
                    approximated.add(j)
                values = info.bake(j, path, values.reshape((k_count, 3, width) if cubic else (k_count, width)), cubic)
            try:
                track = Track(path, times.ravel(), values, interp)
            except RigError as e:
                raise doc.error(f"{what}: {e}") from e
            if j is None:
                above[(int(node), path)] = track
            else:
                tracks[(j, path)] = track
        if ignored:
            warnings.warn(
                f"{doc.where}: animation {name!r} animates non-joint nodes between joints of the skeleton "
                f"({', '.join(doc.node_label(n) for n in sorted(ignored))}); that animation is ignored "
                "(their rest transform is used)",
                RigWarning,
                stacklevel=3,
            )
        if approximated:
            warnings.warn(
                f"{doc.where}: animation {name!r}: joints {[info.names[j] for j in sorted(approximated)]} sit "
                "below non-joint nodes with non-uniform scale or shear; their animation is approximated",
                RigWarning,
                stacklevel=3,
            )
        if tracks or above:
            times = np.concatenate([tr.times for tr in list(tracks.values()) + list(above.values())])
            clips[name] = Clip(name, tracks, rate=key_rate(times), ancestor_tracks=above)
    return clips


# --------------------------------------------------------------------------------------------
# Loader
# --------------------------------------------------------------------------------------------
