"""The README and the docs pages: every Python snippet runs as written (in a scratch folder; a
CesiumMan one reads the shared asset through a link named as in the snippet), the README is short
and starts with its two set-up commands, the scene examples are valid scenes, and the docs build
with Sphinx, warnings as errors."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
# every Python block of the README and the docs pages: (page, number on the page, code)
BLOCKS = [(page, k + 1, code) for page in PAGES
          for k, code in enumerate(re.findall(r"```python\n(.*?)```", page.read_text(), flags=re.S))]


def _docs_block(lang: str, where: str) -> str:
    """The first ``lang`` block of the docs pages that holds ``where``."""
    return next(b for page in PAGES for b in re.findall(rf"```{lang}\n(.*?)```", page.read_text(), flags=re.S)
                if where in b)


def test_the_readme_and_docs_have_snippets():
    assert sum(1 for page, _, _ in BLOCKS if page == README) >= 1
    assert len(BLOCKS) >= 5


def test_the_readme_is_short_and_starts_with_the_two_set_up_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    first = re.search(r"```bash\n(.*?)```", text, flags=re.S)
    assert text.index("```bash") < text.index("\n## ")  # before any section
    commands = first.group(1).strip().splitlines()
    assert len(commands) == 2
    assert "warpskin simulate" in commands[0] and commands[1].endswith("pytest -q")
    for link in re.findall(r"\]\(((?:docs/)?[\w./-]+\.(?:md|png))\)", text):  # every page it links exists
        assert (ROOT / link).exists(), link


@pytest.mark.parametrize("page,number,code", BLOCKS, ids=[f"{p.name}-{n}" for p, n, _ in BLOCKS])
def test_snippet_runs(page, number, code, tmp_path, monkeypatch, request):
    monkeypatch.chdir(tmp_path)
    if "CesiumMan.glb" in code:
        assets = request.getfixturevalue("assets")  # skips with the reason where the folder is absent
        (tmp_path / "CesiumMan.glb").symlink_to(assets / "CesiumMan" / "CesiumMan.glb")
    exec(compile(code, f"{page.name} python block {number}", "exec"), {"__name__": "__readme__"})


def test_the_readme_scene_file_is_a_valid_scene(tmp_path):
    # the TOML example of "Scenes" parses, and every section it shows is read with its values
    from warpskin.scene import load_scene

    text = re.findall(r"```toml\n(.*?)```", (ROOT / "docs" / "scenes.md").read_text(), flags=re.S)[0]
    p = tmp_path / "scene.toml"
    p.write_text(text)
    scene = load_scene(p)
    assert scene.physics_weights() == {"*hand*": 0.0}
    guard = scene.guard_params()
    assert (guard.enabled, guard.strain, guard.flip_degrees, guard.recover) == (True, 1.45, 80.0, 0.1)
    assert scene.solver_params().iterations == 20
    assert scene.collision_params().fail_safe_rounds == 4


def test_the_readme_example_table_maps_a_files_shapes(tmp_path):
    # the [popping.examples] block, under a USD box that has those shapes: two normal examples
    # (the bind mesh, the corrective at 0.5 s) and the biceps' two clenched examples
    from test_popping_morph import _FULL, _MID, _TOP, _shaped_box
    from warpskin.popping.examples import examples_from_file
    from warpskin.scene import load_scene

    block = _docs_block("toml", "[popping.examples]")
    path = _shaped_box(tmp_path, {"elbow_fix": (_MID, _FULL, {}), "biceps_clenched": (_TOP, _FULL, {}),
                                  "biceps_bent": (_TOP, _FULL[::-1], {})}, with_anim=True)
    scene_path = tmp_path / "pop.toml"
    scene_path.write_text(f'[scene]\nname = "pop"\n[rig]\nfile = "{path.name}"\n{block}')
    examples = examples_from_file(load_scene(scene_path))
    assert examples.group_names == ["biceps"] and examples.normal_count == 2
    assert examples.clenched_matrices[0].shape[0] == 2


def test_the_docs_build_with_warnings_as_errors(tmp_path):
    # the Sphinx site (MyST pages, the CLI reference made from the parser, the API from the
    # docstrings) builds clean, and its CLI page lists every command the parser has
    import argparse
    import subprocess
    import sys

    from warpskin.cli import build_parser

    out = tmp_path / "html"
    # (run from a scratch folder: ``python -m`` puts its working folder first on the path, and
    # the checkout's root is not an importable warpskin: the installed one is)
    done = subprocess.run([sys.executable, "-m", "sphinx", "-W", "-q", "-b", "html", str(ROOT / "docs"), str(out)],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    cli = (out / "cli.html").read_text()
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name in commands:
        assert f"warpskin {name}" in cli, name
    # every declared setting is in the scene-file reference, under its section
    from warpskin.scene import _declared_sections
    from warpskin.settings import settings_of

    scenes = (out / "scenes.html").read_text()
    for section, cls in _declared_sections().items():
        table = scenes.split(f"[{section}]", 1)[1]
        for s in settings_of(cls):
            assert f"<code class=\"docutils literal notranslate\"><span class=\"pre\">{s.name}</span></code>" in table, s.name


@pytest.mark.parametrize("section,bad_key,bad_value,message", [
    ("collision", "restitution", 1.7, r"t.toml: \[collision\] restitution must be in \[0, 1\], got 1.7"),
    ("guard", "strain", 1.7, r"t.toml: \[guard\] strain must be in \(1, 1.5\], got 1.7"),
])
def test_a_scene_section_takes_exactly_its_declared_settings(section, bad_key, bad_value, message, tmp_path):
    # the keys a declared section of a scene file may hold are its parameter class's declared
    # settings: each declared key is read with its value, an undeclared one is refused naming the
    # known ones, and a value out of its declared range is refused with the declared range
    from warpskin.errors import SceneError
    from warpskin.scene import _declared_sections, load_scene
    from warpskin.settings import settings_of

    cls = _declared_sections()[section]
    declared = settings_of(cls)
    values = {"bool": "false", "number": None, "integer": None}
    lines = []
    for s in declared:
        if s.kind == "bool":
            lines.append(f"{s.name} = {values['bool']}")
        else:  # a generic value inside the declared range
            lo = s.low if s.low is not None else 0.0
            hi = s.high if s.high is not None else lo + 10.0
            v = lo + 0.37 * (hi - lo) if s.kind == "number" else int(lo) + 3
            lines.append(f"{s.name} = {v!r}")
    base = '[scene]\nname = "t"\n[rig]\ngenerator = "arm"\n'
    path = tmp_path / "t.toml"
    read = (lambda sc: sc.collision_params()) if section == "collision" else (lambda sc: sc.guard_params())
    path.write_text(base + f"[{section}]\n" + "\n".join(lines) + "\n")
    got = read(load_scene(path))
    for s, line in zip(declared, lines):
        assert repr(getattr(got, s.name)).lower() == line.split(" = ")[1].lower(), line
    path.write_text(base + f"[{section}]\nnot_a_key = 0.01\n")
    with pytest.raises(SceneError, match=rf"unknown key\(s\) \['not_a_key'\] in \[{section}\]; known: "
                       + re.escape(str(sorted(s.name for s in declared)))):
        load_scene(path)
    path.write_text(base + f"[{section}]\n{bad_key} = {bad_value}\n")
    with pytest.raises(SceneError, match=message):
        read(load_scene(path))
