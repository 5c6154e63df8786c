"""Test scenes shared by several test files (tests/conftest.py's fixtures, tests/test_refine.py,
tests/test_refine_kernels.py)."""
from __future__ import annotations

import numpy as np


def synthetic_crest() -> tuple[np.ndarray, np.ndarray]:
    """The default synthetic crest's (vertices centred on their mean, faces)."""
    import trimesh

    from app.sim.simulator import DEFAULT_MESH

    mesh = trimesh.load(DEFAULT_MESH)
    return np.asarray(mesh.vertices) - np.asarray(mesh.vertices).mean(axis=0), np.asarray(mesh.faces)


def crest_in_tissue(ctx, distance_m: float):
    """The synthetic crest (centred) in its soft tissue (10 mm protrusion), crest towards the lens at
    ``distance_m``, rendered exactly at 640x480: (vertices, faces, T_camera_bone, depth z (m, 0 where
    empty), labels (1 bone, 2 tissue)). The callers add their own noise."""
    import trimesh

    from app.geometry import se3
    from app.render.scene import SceneRenderer
    from app.sim import world
    from app.sim.simulator import D415_640x480

    vertices, faces = synthetic_crest()
    tissue = world.soft_tissue_mesh(trimesh.Trimesh(vertices, faces), np.random.default_rng(0))
    scene = SceneRenderer(ctx, D415_640x480)
    scene.add_mesh("bone", vertices, faces, label=1)
    scene.add_mesh("tissue", np.asarray(tissue.vertices), np.asarray(tissue.faces), label=2)
    T_camera_bone = se3.from_rotvec_trans(np.array([np.pi, 0.1, 0.1]), np.array([0.0, 0.0, distance_m]))
    depth, labels = scene.render({"bone": T_camera_bone, "tissue": T_camera_bone})
    scene.release()
    return vertices, faces, T_camera_bone, depth.astype(float), labels
