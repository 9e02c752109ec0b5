"""Shared fixtures: the devices to run on, the procedural arm and the third-party assets folder.
Independent reference implementations live in ``oracles.py``."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _assets_dir() -> Path | None:
    env = os.environ.get("WARPSKIN_ASSETS")
    candidates = [Path(env)] if env else []
    candidates.append(ROOT.parent / "shared" / "assets")
    for c in candidates:
        if (c / "MANIFEST.md").is_file():
            return c
    return None


ASSETS = _assets_dir()


def _devices() -> list[str]:
    import warp as wp

    wp.init()
    return ["cpu"] + [str(d) for d in wp.get_cuda_devices()]


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    """Every Warp device present: ``cpu`` always, ``cuda:N`` where a GPU exists."""
    return request.param


@pytest.fixture
def assets() -> Path:
    """The shared third-party assets folder (``../shared/assets`` or ``$WARPSKIN_ASSETS``)."""
    if ASSETS is None:
        pytest.skip("third-party assets not found: ../shared/assets is absent and WARPSKIN_ASSETS is unset")
    return ASSETS


@pytest.fixture(scope="module")
def arm():
    """The shipped procedural arm (2918 vertices), built once per test module."""
    from warpskin.scenes.arm import make_arm

    return make_arm()


@pytest.fixture(scope="module")
def coarse_arm():
    """The arm at the coarse resolution of :data:`oracles.COARSE`, once per test module."""
    from oracles import coarse_arm as make

    return make()
