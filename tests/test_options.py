"""The Python API's options objects (:class:`~warpskin.run.SimulationOptions`,
:class:`~warpskin.run.PoppingOptions`, :class:`~warpskin.run.SkinningOptions`): one frozen object
per driver, keyword overrides applied in one place, unknown names refused with one line."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from warpskin.errors import InputError
from warpskin.options import with_overrides
from warpskin.run import PoppingOptions, SimulationOptions, SkinningOptions, simulate, skin_to_usd


@pytest.mark.parametrize("kind", [SimulationOptions, PoppingOptions, SkinningOptions])
def test_options_are_frozen_and_overrides_replace_only_what_is_named(kind):
    base = kind()
    with pytest.raises(dataclasses.FrozenInstanceError):
        base.progress = False
    out = with_overrides(kind, base, {"progress": False, "comment": "x"}, "cmd")
    assert (out.progress, out.comment) == (False, "x")
    assert base.progress is True  # the given object is not changed
    rest = [f.name for f in dataclasses.fields(kind) if f.name not in ("progress", "comment")]
    assert all(getattr(out, n) == getattr(base, n) for n in rest)
    assert with_overrides(kind, None, {}, "cmd") == kind()
    assert with_overrides(kind, base, {}, "cmd") is base


def test_unknown_option_and_wrong_options_object_are_one_line_input_errors(tmp_path):
    with pytest.raises(InputError, match=r"^simulate: unknown option 'frame' \(options: .*frames.*\)$"):
        simulate("arm", tmp_path / "a.usdc", frame=(0, 1))
    with pytest.raises(InputError, match=r"^skin: options must be a SkinningOptions, got SimulationOptions$"):
        skin_to_usd("arm", tmp_path / "a.usdc", SimulationOptions())
    assert not list(tmp_path.iterdir())  # refused before any work


def test_an_options_object_and_keyword_overrides_bake_the_same(tmp_path):
    from pxr import Usd, UsdGeom

    a = skin_to_usd("arm", tmp_path / "a.usdc", SkinningOptions(frames=(0, 2), method="dqs", progress=False))
    b = skin_to_usd("arm", tmp_path / "b.usdc", SkinningOptions(method="lbs"), frames=(0, 2), method="dqs",
                    progress=False)
    assert a.summary["method"] == b.summary["method"] == "dqs" and a.frames == b.frames == 3
    stages = [Usd.Stage.Open(str(r.path)) for r in (a, b)]
    meshes = [p.GetPath() for p in stages[0].Traverse() if p.IsA(UsdGeom.Mesh)]
    assert meshes
    for path in meshes:
        pa, pb = (UsdGeom.Mesh(s.GetPrimAtPath(path)).GetPointsAttr() for s in stages)
        assert pa.GetTimeSamples() == pb.GetTimeSamples() == [0.0, 1.0, 2.0]
        for t in pa.GetTimeSamples():
            np.testing.assert_array_equal(np.array(pa.Get(t)), np.array(pb.Get(t)))
