"""The renderers against closed forms: planes at known distances, silhouettes where K puts them,
tiles that do not bleed into their neighbours."""
from __future__ import annotations

import numpy as np
import pytest

from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.render.batched import BatchedDepthRenderer
from app.render.scene import SceneRenderer

CAMERA = PinholeCamera(K=np.array([[60.0, 0.0, 39.3], [0.0, 61.0, 29.6], [0.0, 0.0, 1.0]]), width=80, height=60)


def quad(half: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def pixel_rays(camera: PinholeCamera) -> np.ndarray:
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(float)
    return pix @ np.linalg.inv(camera.K).T


def test_fronto_parallel_plane_renders_at_its_exact_distance(ctx):
    vertices, faces = quad(5.0)
    T_camera_plane = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 0.5]))
    scene = SceneRenderer(ctx, CAMERA)
    scene.add_mesh("plane", vertices, faces, label=7)
    depth, labels = scene.render({"plane": T_camera_plane})
    scene.release()
    np.testing.assert_allclose(depth, 0.5, rtol=1e-6)
    assert np.all(labels == 7)


def test_tilted_plane_depth_is_the_ray_plane_intersection(ctx, rng):
    vertices, faces = quad(5.0)
    R = quat.to_matrix(quat.exp_map(np.array([0.4, -0.3, 0.1])))
    T_camera_plane = se3.make_pose(R, np.array([0.02, -0.01, 0.6]))
    renderer = BatchedDepthRenderer(ctx, vertices, faces, CAMERA, capacity=1)
    renderer.render(T_camera_plane[None])
    depth = renderer.read_depth(1)[0]
    renderer.release()
    n_camera = R[:, 2]
    d = n_camera @ T_camera_plane[:3, 3]
    rays = pixel_rays(CAMERA)
    expected = d / (rays @ n_camera)   # rays have z = 1, so the ray parameter is the depth
    np.testing.assert_allclose(depth, expected, rtol=2e-6)


def test_silhouette_lands_where_K_projects_it(ctx):
    # A square whose projected corners fall on pixel boundaries (x.5): pixel centres are
    # unambiguously inside or outside, so the mask must match exactly.
    z = 0.4
    u0, u1, v0, v1 = 20.5, 50.5, 10.5, 40.5
    corners_uv = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    p = np.column_stack([(corners_uv[:, 0] - CAMERA.cx) * z / CAMERA.fx, (corners_uv[:, 1] - CAMERA.cy) * z / CAMERA.fy, np.full(4, z)])
    renderer = BatchedDepthRenderer(ctx, p, np.array([[0, 1, 2], [0, 2, 3]]), CAMERA, capacity=1)
    renderer.render(np.eye(4)[None])
    mask = renderer.read_depth(1)[0] > 0
    renderer.release()
    expected = np.zeros_like(mask)
    expected[11:41, 21:51] = True
    np.testing.assert_array_equal(mask, expected)
    uv, _ = CAMERA.project(p)
    np.testing.assert_allclose(uv, corners_uv, atol=1e-9)


def random_poses(rng, n, z=0.5, spread=0.05):
    q = quat.random_uniform(rng, n)
    t = np.column_stack([rng.normal(0, spread, n), rng.normal(0, spread, n), z + rng.normal(0, spread, n)])
    return se3.from_quat_trans(q, t)


@pytest.fixture
def crest():
    from app.mesh import load_mesh
    from tests.conftest import REPO

    return load_mesh(REPO / "meshes" / "iliac_crest_tracking.ply")


def test_batched_tiles_equal_single_renders(ctx, rng, crest):
    poses = random_poses(rng, 7)
    batch = BatchedDepthRenderer(ctx, crest.vertices, crest.faces, CAMERA, capacity=7)
    batch.render(poses)
    tiles = batch.read_depth(7)
    single = BatchedDepthRenderer(ctx, crest.vertices, crest.faces, CAMERA, capacity=1)
    for i, T in enumerate(poses):
        single.render(T[None])
        alone = single.read_depth(1)[0]
        # the tile offset changes float rounding in the rasteriser: same coverage, depth to float32 precision
        assert np.mean((tiles[i] > 0) != (alone > 0)) < 0.002
        both = (tiles[i] > 0) & (alone > 0)
        np.testing.assert_allclose(tiles[i][both], alone[both], atol=2e-5)  # 20 um
    batch.release()
    single.release()
    assert all((tile > 0).any() for tile in tiles)


def test_pose_straddling_a_tile_border_leaves_its_neighbours_unchanged(ctx, rng, crest):
    poses = random_poses(rng, 6)
    # particle 1 sits half out of its tile to the right, near the camera: it would cover tile 2
    poses[1] = se3.make_pose(np.eye(3), np.array([0.10, 0.0, 0.25]))
    renderer = BatchedDepthRenderer(ctx, crest.vertices, crest.faces, CAMERA, capacity=6)
    renderer.render(poses)
    with_straddler = renderer.read_depth(6)
    far_away = poses.copy()
    far_away[1] = se3.make_pose(np.eye(3), np.array([0.0, 0.0, -1.0]))   # behind the camera: draws nothing
    renderer.render(far_away)
    without = renderer.read_depth(6)
    renderer.release()
    assert (with_straddler[1] > 0).any() and (with_straddler[1][:, -1] > 0).any(), "the straddler must reach its tile's edge"
    for i in (0, 2, 3, 4, 5):
        np.testing.assert_array_equal(with_straddler[i], without[i])
