"""The Warp LBS kernel on the real CesiumMan asset against usd-core's own skinning, and the
same asset read from glTF and from USD skinned to the same surface (every device)."""

from __future__ import annotations

import numpy as np

from warpskin.io import load_rig
from warpskin.skinning import Skinner

TIME_CODES = [1.0, 10.5, 24.0, 37.25, 48.0]


def _usd_reference(path, time_codes):
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Root):
            cache.Populate(UsdSkel.Root(prim), Usd.PrimDefaultPredicate)
            for binding in cache.ComputeSkelBindings(UsdSkel.Root(prim), Usd.PrimDefaultPredicate):
                skel_query = cache.GetSkelQuery(binding.GetSkeleton())
                for query in binding.GetSkinningTargets():
                    mesh = UsdGeom.Mesh(query.GetPrim())
                    for tc in time_codes:
                        xforms = skel_query.ComputeSkinningTransforms(tc)
                        pts = mesh.GetPointsAttr().Get(tc)
                        query.ComputeSkinnedPoints(xforms, pts, tc)
                        l2w = np.array(UsdGeom.Xformable(binding.GetSkeleton().GetPrim()).ComputeLocalToWorldTransform(tc)).T
                        p = np.array(pts, dtype=np.float64)
                        out[tc] = p @ l2w[:3, :3].T + l2w[:3, 3]
    return out


def test_warp_lbs_matches_usdskel_compute_skinned_points(device, assets):
    path = assets / "usd" / "CesiumMan" / "CesiumMan.usdz"
    rig = load_rig(path)
    ref = _usd_reference(path, TIME_CODES)
    skinner = Skinner(rig, method="lbs", device=device)
    clip = rig.clip()
    worst = 0.0
    for tc in TIME_CODES:
        got = skinner.skin_at(clip, tc / 24.0).numpy()[rig.weld_map]  # back to the file's points
        worst = max(worst, np.abs(got - ref[tc]).max() / rig.size())
    print(f"CesiumMan.usdz: Warp LBS vs UsdSkel ComputeSkinnedPoints, max error {worst:.2e} of the model size")
    assert worst < 1e-5


def test_glb_and_usdz_of_one_asset_skin_alike(device, assets):
    glb = load_rig(assets / "CesiumMan" / "CesiumMan.glb")
    usdz = load_rig(assets / "usd" / "CesiumMan" / "CesiumMan.usdz")
    assert glb.vertex_count == usdz.vertex_count == 2338
    a = Skinner(glb, method="lbs", device=device)
    b = Skinner(usdz, method="lbs", device=device)
    worst = 0.0
    for t in [0.0417, 0.5, 1.0, 1.25, 1.9]:
        pa = a.skin_at(glb.clip(), t).numpy()[glb.weld_map]
        pb = b.skin_at(usdz.clip(), t).numpy()[usdz.weld_map]
        worst = max(worst, np.abs(pa - pb).max() / glb.size())  # both files keep one vertex order
    print(f"CesiumMan glb vs usdz LBS: max difference {worst:.2e} of the model size")
    assert worst < 1e-5
