"""Shared fixtures: one EGL context for the run (llvmpipe without a GPU), paths to test data."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PELVIS_DIR = REPO.parent / "shared" / "data" / "pelvis"


@pytest.fixture(scope="session")
def gl_ctx():
    from app.render.context import create_context

    ctx = create_context()
    yield ctx
    ctx.release()


@pytest.fixture
def ctx(gl_ctx):
    """The session's context, with a GL error check after the test."""
    assert gl_ctx.error == "GL_NO_ERROR"
    yield gl_ctx
    assert gl_ctx.error == "GL_NO_ERROR"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def pelvis_meshes(pattern: str = "crest_*.ply") -> list[Path]:
    return sorted(PELVIS_DIR.glob(pattern)) if PELVIS_DIR.is_dir() else []


@pytest.fixture
def crest_mesh_path():
    paths = pelvis_meshes()
    if not paths:
        pytest.skip(f"real pelvis meshes not found in {PELVIS_DIR} (the shared data folder is absent)")
    return paths[0]
