"""The README's Python snippets run as written (in a scratch folder; the CesiumMan one reads the
shared asset through a link named as in the snippet)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_the_readme_has_snippets():
    assert len(BLOCKS) >= 4


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_snippet_runs(index, tmp_path, monkeypatch, request):
    code = BLOCKS[index]
    monkeypatch.chdir(tmp_path)
    if "CesiumMan.glb" in code:
        assets = request.getfixturevalue("assets")  # skips with the reason where the folder is absent
        (tmp_path / "CesiumMan.glb").symlink_to(assets / "CesiumMan" / "CesiumMan.glb")
    exec(compile(code, f"README.md python block {index + 1}", "exec"), {"__name__": "__readme__"})


def test_the_readme_scene_file_is_a_valid_scene(tmp_path):
    # the TOML example of "Scenes" parses, and every section it shows is read with its values
    from warpskin.scene import load_scene

    text = re.findall(r"```toml\n(.*?)```", README.read_text().split("\n## Scenes\n", 1)[1], flags=re.S)[0]
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

    block = next(b for b in re.findall(r"```toml\n(.*?)```", README.read_text(), flags=re.S) if "[popping.examples]" in b)
    path = _shaped_box(tmp_path, {"elbow_fix": (_MID, _FULL, {}), "biceps_clenched": (_TOP, _FULL, {}),
                                  "biceps_bent": (_TOP, _FULL[::-1], {})}, with_anim=True)
    scene_path = tmp_path / "pop.toml"
    scene_path.write_text(f'[scene]\nname = "pop"\n[rig]\nfile = "{path.name}"\n{block}')
    examples = examples_from_file(load_scene(scene_path))
    assert examples.group_names == ["biceps"] and examples.normal_count == 2
    assert examples.clenched_matrices[0].shape[0] == 2
