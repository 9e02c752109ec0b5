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


def test_the_checkout_imports_its_kernels_from_any_python_m(tmp_path):
    # `python -m sphinx` (or any `python -m`) in the checkout imports its warpskin/, which has
    # no kernels/ of its own; it must find the top-level one (not an installed copy)
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parent.parent
    code = ("import sys; sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()]; "
            f"sys.path.insert(0, {str(repo)!r}); import warpskin.kernels.rotation as r, warpskin.scenes as s, warpskin; "
            "print(warpskin.__file__); print(r.__file__); print(s.__file__)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    pkg, kern, scenes = run.stdout.split()
    assert Path(pkg) == repo / "warpskin" / "__init__.py"
    assert Path(kern) == repo / "kernels" / "rotation.py" and Path(scenes) == repo / "scenes" / "__init__.py"
