"""The session's projector output: the template only for a fresh ok estimate, the warning otherwise."""
from __future__ import annotations

import numpy as np
import pytest

from app import plugins_registry as registry
from app.errors import ConfigError
from app.geometry import se3
from app.interfaces import Estimate
from app.mesh import load_mesh
from app.projector.model import default_projector
from tests.conftest import REPO


def _poses():
    """A camera looking at the default crest from 0.42 m (the default projector aims there)."""
    projector = default_projector()
    T_base_camera = np.eye(4)
    T_camera_bone = se3.make_pose(np.diag([1.0, -1.0, -1.0]), np.array([0.0, 0.0, 0.42]))
    return projector, T_base_camera, T_base_camera @ T_camera_bone


def test_projector_output_blanks_the_template_unless_ok_and_fresh(tmp_path, ctx):
    mesh = load_mesh(REPO / "meshes" / "iliac_crest.ply")
    _, T_base_camera, T_base_bone = _poses()
    out = registry.create("output", "projector", {"png_dir": str(tmp_path), "rerun": "off"}, "outputs")
    out.open({"mesh": mesh})
    cases = [("ok", 0.03), ("lost", 0.03), ("uncertain", 0.03), ("ok", None), ("ok", 5.0)]
    for k, (status, latency) in enumerate(cases):
        out.on_estimate(Estimate(stamp=float(k), frame_id=k, T_base_bone=T_base_bone, status=status,
                                 T_base_camera=T_base_camera, latency_s=latency))
    summary = out.close()
    assert summary == {"rendered": 5, "template_shown": 1}
    from PIL import Image

    images = [np.asarray(Image.open(p)) for p in sorted(tmp_path.glob("*.png"))]
    assert len(images) == 5
    green = [int(((im[..., 1] > 200) & (im[..., 0] < 50)).sum()) for im in images]
    red = [int(((im[..., 0] > 200) & (im[..., 1] < 50)).sum()) for im in images]
    assert green[0] > 100 and red[0] == 0                 # the outline, no warning
    assert all(g == 0 for g in green[1:]) and all(r > 100 for r in red[1:])


def test_projector_output_needs_the_mesh_and_a_sane_rate():
    with pytest.raises(ConfigError, match="every"):
        registry.create("output", "projector", {"every": 0}, "outputs")
    out = registry.create("output", "projector", {"rerun": "off"}, "outputs")
    with pytest.raises(ConfigError, match="bone.mesh"):
        out.open({"mesh": None})
