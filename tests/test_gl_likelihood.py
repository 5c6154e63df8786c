"""The GL likelihood (batched render + compute shader) equals the numpy reference on random poses
and images, for every option of the observation model, and a pose straddling a tile border leaves
its neighbours' values unchanged."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.filter.likelihood_ref import LikelihoodParams, log_likelihood
from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.mesh import load_mesh
from app.render.likelihood import GLLikelihoodBackend
from tests.conftest import REPO

CAMERA = PinholeCamera(K=np.array([[58.0, 0.0, 40.2], [0.0, 58.5, 29.1], [0.0, 0.0, 1.0]]), width=80, height=60)
OPTIONS = {
    "beam": {},
    "smooth_exponential": {"occlusion": "smooth_exponential"},
    "classification": {"classification": True, "l0_weight": 2.0},
    "pixel_count": {"pixel_count_reg": 50.0},
    "all": {"occlusion": "smooth_exponential", "classification": True, "pixel_count_reg": 50.0},
    "background_ratio": {"background_ratio": True, "pixel_weight": 0.3},
    "ratio_classification": {"background_ratio": True, "classification": True},
}


@pytest.fixture(scope="module")
def crest():
    return load_mesh(REPO / "meshes" / "iliac_crest_tracking.ply")


def poses_near(rng, T_camera_bone, n, sigma_t=0.01, sigma_r=0.1):
    q = quat.exp_map(rng.normal(0, sigma_r, (n, 3)))
    dT = se3.from_quat_trans(q, rng.normal(0, sigma_t, (n, 3)))
    return T_camera_bone @ dT


def measured_image(backend, T_true, rng):
    """The true pose's rendering with noise, occluders in front, invalid and far pixels."""
    z = backend.render_depth(T_true[None])[0].astype(np.float64)
    background = 0.55 + 0.02 * rng.random(z.shape)
    z = np.where(z > 0, z, background)
    z += rng.normal(0, 0.0015, z.shape)
    occluded = rng.random(z.shape) < 0.1
    z[occluded] *= rng.uniform(0.3, 0.9, occluded.sum())
    z[rng.random(z.shape) < 0.05] = 0.0          # invalid
    z[rng.random(z.shape) < 0.01] = 3.5          # beyond z_max: outliers
    z[0, :3] = np.nan                             # non-finite = invalid
    return z.astype(np.float32)


@pytest.mark.parametrize("option", list(OPTIONS))
def test_gl_likelihood_matches_the_numpy_reference(ctx, crest, rng, option):
    params = replace(LikelihoodParams(), **OPTIONS[option])
    n = 37
    backend = GLLikelihoodBackend(ctx, crest.vertices, crest.faces, CAMERA, capacity=n, params=params)
    T_true = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([2.9, 0.2, 0.1]))), np.array([0.0, 0.0, 0.45]))
    depth = measured_image(backend, T_true, rng)
    poses = poses_near(rng, T_true, n)
    poses[3] = se3.make_pose(np.eye(3), np.array([0.0, 0.0, -1.0]))      # behind the camera: covers nothing
    poses[4] = se3.make_pose(np.eye(3), np.array([0.3, 0.0, 0.4]))       # off screen
    gl = backend.log_likelihood(poses, depth)
    rendered = backend.render_depth(poses)
    reference = log_likelihood(depth, rendered, params)
    backend.release()
    assert gl.shape == (n,)
    assert gl[3] == 0.0 and reference[3] == 0.0
    np.testing.assert_allclose(gl, reference, rtol=1e-4, atol=1e-2)
    assert np.ptp(reference) > 10.0, "the poses must differ enough for the comparison to mean something"


def test_the_true_pose_scores_best(ctx, crest, rng):
    params = LikelihoodParams()
    backend = GLLikelihoodBackend(ctx, crest.vertices, crest.faces, CAMERA, capacity=50, params=params)
    T_true = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([2.9, 0.2, 0.1]))), np.array([0.0, 0.0, 0.45]))
    depth = measured_image(backend, T_true, rng)
    poses = poses_near(rng, T_true, 50, sigma_t=0.01, sigma_r=0.05)
    poses[0] = T_true
    values = backend.log_likelihood(poses, depth)
    backend.release()
    assert np.argmax(values) == 0


def test_a_pose_straddling_a_tile_border_leaves_its_neighbours_value_unchanged(ctx, crest, rng):
    params = LikelihoodParams()
    backend = GLLikelihoodBackend(ctx, crest.vertices, crest.faces, CAMERA, capacity=9, params=params)
    T_true = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([2.9, 0.2, 0.1]))), np.array([0.0, 0.0, 0.45]))
    depth = measured_image(backend, T_true, rng)
    poses = poses_near(rng, T_true, 9)
    poses[4] = se3.make_pose(np.eye(3), np.array([0.12, 0.05, 0.2]))    # near, off the tile's corner
    straddling = backend.log_likelihood(poses, depth)
    assert (backend.render_depth(poses)[4][:, -1] > 0).any(), "pose 4 must reach its tile's border"
    alone = poses.copy()
    alone[4] = se3.make_pose(np.eye(3), np.array([0.0, 0.0, -1.0]))
    without = backend.log_likelihood(alone, depth)
    backend.release()
    keep = np.arange(9) != 4
    np.testing.assert_array_equal(straddling[keep], without[keep])
