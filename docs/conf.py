"""Sphinx configuration of warpskin's documentation (MyST Markdown pages, the CLI reference from
the argparse parser, the Python API from the docstrings). Build: ``sphinx-build -W docs docs/_build``."""

from __future__ import annotations

import warpskin

project = "warpskin"
author = "the warpskin developers"
release = version = warpskin.__version__  # the one place the version lives
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.napoleon"]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "_generated"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = f"warpskin {release}"
autodoc_member_order = "bysource"
autodoc_typehints = "description"
napoleon_google_docstring = True
napoleon_numpy_docstring = False


def _cli_reference() -> str:
    """Every command's help as the parser prints it (``warpskin COMMAND --help``), in order."""
    import argparse

    from warpskin.cli import build_parser

    parser = build_parser()
    out = ["## warpskin", "", "```text", parser.format_help().rstrip(), "```", ""]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += [f"## warpskin {name}", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(out)


def _settings_reference() -> str:
    """Every scene section's declared settings (warpskin.settings), one table each."""
    from warpskin.scene import scene_sections
    from warpskin.settings import reference_markdown

    return "\n".join(reference_markdown(settings, section) for section, settings in scene_sections().items())


def setup(app):
    from pathlib import Path

    generated = Path(__file__).parent / "_generated"
    generated.mkdir(exist_ok=True)
    for name, text in (("cli.md", _cli_reference()), ("settings.md", _settings_reference())):
        target = generated / name
        if not target.exists() or target.read_text() != text:  # unchanged: no rebuild
            target.write_text(text)
