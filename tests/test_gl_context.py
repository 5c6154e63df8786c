"""One GL context per thread: a context created after the thread's shared one must not capture the
renderers built on the shared one (the GL_INVALID_OPERATION the projector output left behind)."""
from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO

# Runs in a fresh interpreter: it creates a second context in its main thread, which this test
# process must not do (tests/conftest.py's gl_ctx is the shared context).
SCRIPT = r"""
import numpy as np
from app.geometry import se3
from app.mesh import load_mesh
from app.projector.model import default_projector
from app.projector.plan import make_crest_plan
from app.projector.view import ProjectorView
from app.render import context

mesh = load_mesh("meshes/iliac_crest.ply")
V, F = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
plan = make_crest_plan("box", V, F)
projector = default_projector(320, 200)
T = se3.make_pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 0.42]))

def cycle():
    view = ProjectorView.create(projector, V, F, plan)      # on context.shared_context()
    image = view.render(T, "ok")
    view.release()                                          # binds the shared context's idle framebuffer
    return image

shared = context.shared_context()
first = cycle()
other = context.create_context()                            # as tests/conftest.py's gl_ctx once did
second = cycle()
print("after another context:", shared.error, other.error, int(np.abs(second.astype(int) - first).max()))
other.release()
context.describe_default_context()                          # a throwaway context, created and released
third = cycle()
print("after a throwaway context:", shared.error, int(np.abs(third.astype(int) - first).max()))
assert (first > 0).any()
"""


def test_shared_context_stays_current_when_another_context_is_created():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.strip().splitlines()[-2:]
    assert lines == ["after another context: GL_NO_ERROR GL_NO_ERROR 0",
                     "after a throwaway context: GL_NO_ERROR 0"], proc.stdout
