"""Every Python snippet of the README runs as written (in a scratch folder)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_the_readme_has_python_snippets():
    assert len(BLOCKS) >= 4


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_snippet_runs(index, tmp_path, monkeypatch, request):
    code = BLOCKS[index]
    monkeypatch.chdir(tmp_path)
    if "CesiumMan.glb" in code:  # the README's example file: the shared asset, linked in
        assets = request.getfixturevalue("assets")
        (tmp_path / "CesiumMan.glb").symlink_to(assets / "CesiumMan" / "CesiumMan.glb")
    exec(compile(code, f"README.md python block {index + 1}", "exec"), {"__name__": "__readme__"})
