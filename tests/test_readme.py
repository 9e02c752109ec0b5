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
@pytest.mark.slow
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
    # every declared scene setting is in the scene-file reference, under its section, and every
    # option of every command on the command-line page
    from warpskin.scene import scene_sections

    scenes = (out / "scenes.html").read_text()
    for section, declared in scene_sections().items():
        table = scenes.split(f'<span class="pre">[{section}]</span></code>', 1)[1].split("</table>", 1)[0]
        for s in declared:
            assert f"<code class=\"docutils literal notranslate\"><span class=\"pre\">{s.scene_key}</span></code>" in table, s.name
    for action in _every_action(build_parser()):
        for option in action.option_strings:
            assert option in cli, option


def _every_action(parser):
    import argparse

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return [a for p in [parser, *sub.choices.values()] for a in p._actions]




# every ``warpskin`` command line of the README's and the docs' bash blocks: (page, line)
COMMAND_LINES = [(page, line.split("  #")[0].strip()) for page in PAGES
                 for block in re.findall(r"```bash\n(.*?)```", page.read_text(), flags=re.S)
                 for line in block.splitlines() if re.match(r"(\.venv/bin/)?warpskin ", line.strip())]


def test_the_docs_show_command_lines():
    assert len(COMMAND_LINES) >= 25


@pytest.mark.parametrize("page,line", COMMAND_LINES, ids=[f"{p.name}-{k}" for k, (p, _) in enumerate(COMMAND_LINES)])
def test_every_command_line_of_the_docs_parses(page, line, tmp_path, monkeypatch, capsys):
    # each command line shown parses with the real parser (its options exist, its values are in
    # their declared ranges); those that need no file (a shipped procedural scene, quick commands)
    # run, and exit 0
    import shlex

    from warpskin.cli import build_parser, main

    argv = shlex.split(line)[1:]
    monkeypatch.chdir(tmp_path)
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{page.name}: {line!r} does not parse: {capsys.readouterr().err.strip()} (exit {exc.code})")
    if argv[0] in ("scenes", "skin", "layers") and (len(argv) == 1 or argv[1] == "arm"):
        assert main(argv) == 0, capsys.readouterr().err
