"""The version lives in one place (``warpskin.__version__``): the installed package's metadata,
``warpskin --version``, every written USD file and the changelog's latest release agree."""

from __future__ import annotations

import importlib.metadata
import re
from pathlib import Path

import numpy as np
from pxr import Usd

import warpskin
from warpskin.cli import main
from warpskin.io.usd_export import UsdSkinWriter

ROOT = Path(__file__).resolve().parent.parent


def test_the_version_is_declared_once_and_read_everywhere(tmp_path, capsys):
    assert importlib.metadata.version("warpskin") == warpskin.__version__
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    assert capsys.readouterr().out.strip() == f"warpskin {warpskin.__version__}"
    path = tmp_path / "v.usda"
    with UsdSkinWriter(path, fps=24, root="v") as out:
        out.add_mesh("skin", np.array([[0, 1, 2]]), rest_points=np.eye(3))
        out.write_frame(0, {"skin": np.eye(3)})
    stage = Usd.Stage.Open(str(path))
    assert stage.GetRootLayer().customLayerData["warpskin:version"] == warpskin.__version__
    assert "version =" not in (ROOT / "pyproject.toml").read_text().split("[project]", 1)[1].split("[", 1)[0]


def test_the_changelog_keeps_its_form():
    text = (ROOT / "CHANGELOG.md").read_text()
    heads = re.findall(r"^## \[([^\]]+)\](?: - (\d{4}-\d{2}-\d{2}))?$", text, flags=re.M)
    assert heads[0] == ("Unreleased", "")
    released = [v for v, d in heads[1:] if d]
    assert released and released[0] == warpskin.__version__  # the latest release is this version
    assert all(re.fullmatch(r"\d+\.\d+\.\d+", v) for v in released)
    for section in re.findall(r"^### (.+)$", text, flags=re.M):
        assert section in {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}
