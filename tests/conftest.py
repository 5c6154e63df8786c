"""Shared fixtures: one EGL context for the run (llvmpipe without a GPU), paths to test data.

Parallel runs (``make test``: pytest-xdist, ``-n auto --dist loadfile``): each worker is its own
process with its own EGL context (``gl_ctx``) and its own ``tmp_path_factory`` base, and a test
file runs whole on one worker, so module-scoped fixtures (simulated trials, replays) are made once.
Numba's ``cache=True`` kernels (app/render/cpu_raster.py) may be compiled by two workers at once
into the same ``__pycache__``: numba writes each index and data file to a unique temporary name
and renames it into place (``numba.core.caching._CacheFile._open_for_write``), so a worker reads a
whole file or none, and the two write the same contents. Tests use no fixed port (the RTDE server
takes a free loopback address) and write only under their tmp paths.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PELVIS_DIR = REPO.parent / "shared" / "data" / "pelvis"


@pytest.fixture(scope="session")
def gl_ctx():
    """The main thread's :func:`~app.render.context.shared_context`, the one the product code renders on.

    Not a second context: creating one makes it current, and moderngl does not switch back, so the
    product's renderers and the tests' would each run on whichever context was made current last.
    """
    from app.render.context import shared_context

    ctx = shared_context()
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


@pytest.fixture(scope="module")
def far_frame(gl_ctx):
    """The synthetic crest in its tissue at 0.8 m (~1,000 cells at stride 2: a small silhouette, refined
    at stride 1 by default), with the simulator's sensor noise (app/sim/sensor.py: σ = 0.0015 z² +
    0.0003 m, 1.26 mm there): (vertices, faces, T_camera_bone, measured depth). Shared by
    tests/test_refine.py and tests/test_static_prior.py."""
    from app.sim.sensor import SensorModel
    from tests.scenes import crest_in_tissue

    vertices, faces, T_camera_bone, z, _ = crest_in_tissue(gl_ctx, 0.8)
    noise = SensorModel().sigma(z) * np.random.default_rng(3).standard_normal(z.shape)
    return vertices, faces, T_camera_bone, np.where(z > 0, z + noise, 0.0)


# The test files that take longest (module totals from `--durations` of a parallel run on the 2-core
# machine, longest first). They run first so that a parallel run (`make test`: xdist --dist loadfile
# --no-loadscope-reorder) does not end on one of them while the other worker idles; the rest keep
# their order. Only the order changes: no test is selected or skipped by this list.
SLOW_FILES_FIRST = (
    "test_cli_outputs.py", "test_recovery.py", "test_misuse_matrix.py", "test_tracking_accuracy.py",
    "test_projector_calibration.py", "test_smc_init.py", "test_bench.py", "test_track_cli.py",
    "test_projector_live.py", "test_sim_images.py", "test_recovery_session.py", "test_projector_render.py",
    "test_frame_core.py", "test_plugins_realsense_images.py", "test_simulator.py",
)


def pytest_collection_modifyitems(config, items):
    """Slow files first (a stable sort: each file's tests keep their order)."""
    rank = {name: i for i, name in enumerate(SLOW_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
