"""app.geometry.camera: projection against OpenCV, resize/crop intrinsics against closed forms
((B) eq. 4.23-4.25, pixel centres at integers), back-projection, and the OpenGL projection built
from K checked against cv2.projectPoints after the CV -> GL flip."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.geometry import se3
from app.geometry.camera import CV_TO_GL, PinholeCamera, opencv_to_opengl_view

K_D415 = np.array([[615.0, 0.0, 321.3], [0.0, 612.0, 238.7], [0.0, 0.0, 1.0]])


@pytest.fixture
def camera():
    return PinholeCamera(K_D415, 640, 480)


def points_in_view(camera: PinholeCamera, rng: np.random.Generator, n: int) -> np.ndarray:
    uv = rng.uniform([-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5], (n, 2))
    z = rng.uniform(0.2, 2.0, n)
    return np.column_stack([(uv[:, 0] - camera.cx) / camera.fx * z, (uv[:, 1] - camera.cy) / camera.fy * z, z])


def cv2_project(K: np.ndarray, p_camera: np.ndarray) -> np.ndarray:
    uv, _ = cv2.projectPoints(p_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, None)
    return uv.reshape(-1, 2)


def test_properties_and_dict_round_trip(camera):
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (615.0, 612.0, 321.3, 238.7)
    d = camera.to_dict()
    assert d == {"width": 640, "height": 480, "K": K_D415.tolist()}
    assert PinholeCamera.from_dict(d) == camera
    assert hash(PinholeCamera.from_dict(d)) == hash(camera)
    assert camera != camera.resized(320, 240)


def test_camera_is_immutable(camera):
    with pytest.raises(ValueError):
        camera.K[0, 0] = 1.0
    with pytest.raises(AttributeError):
        camera.width = 10


@pytest.mark.parametrize("bad, match", [
    ({"width": 640, "height": 480}, "K"),
    ({"width": 640, "height": 480, "K": [[1.0, 0, 0], [0, 1.0, 0]]}, "3x3"),
    ({"width": 640, "height": 480, "K": [[-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]]}, "positive"),
    ({"width": 0, "height": 480, "K": K_D415.tolist()}, "size"),
    ({"width": 640.5, "height": 480, "K": K_D415.tolist()}, "size"),
    ({"width": 640, "height": 480, "K": [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 2.0]]}, "last row"),
])
def test_from_dict_rejects_bad_cameras(bad, match):
    with pytest.raises(ValueError, match=match):
        PinholeCamera.from_dict(bad)


def test_project_matches_opencv(camera, rng):
    p = points_in_view(camera, rng, 100)
    uv, z = camera.project(p)
    np.testing.assert_allclose(uv, cv2_project(camera.K, p), atol=1e-9)
    np.testing.assert_array_equal(z, p[:, 2])


def test_backproject_inverts_project_and_skips_invalid_pixels(camera, rng):
    depth = rng.uniform(0.3, 1.5, (camera.height, camera.width))
    depth[10, 20] = 0.0
    depth[30, 40] = np.nan
    p, uv = camera.backproject(depth)
    assert p.shape == (camera.width * camera.height - 2, 3) and uv.shape == (len(p), 2)
    assert not np.any((uv[:, 0] == 20) & (uv[:, 1] == 10))
    np.testing.assert_array_equal(p[:, 2], depth[uv[:, 1], uv[:, 0]])
    uv_back, _ = camera.project(p)
    np.testing.assert_allclose(uv_back, uv, atol=1e-9)
    with pytest.raises(ValueError, match=r"\(480, 640\)"):
        camera.backproject(depth[:, :100])


def test_pixel_rays_pass_through_their_pixels(camera):
    rays = camera.pixel_rays()
    assert rays.shape == (480, 640, 3)
    np.testing.assert_array_equal(rays[..., 2], 1.0)
    uv, _ = camera.project(2.5 * rays[::37, ::41].reshape(-1, 3))
    v, u = np.mgrid[0:480:37, 0:640:41]
    np.testing.assert_allclose(uv, np.column_stack([u.ravel(), v.ravel()]), atol=1e-9)


def test_resize_640x480_to_80x60_maps_pixel_blocks_to_pixels(camera, rng):
    small = camera.resized(80, 60)
    # small pixel (u', v') covers original pixels 8u' .. 8u'+7: its centre is the original 8u' + 3.5
    for u_s, v_s in [(0, 0), (10, 7), (79, 59), (40, 30)]:
        u_o, v_o = 8 * u_s + 3.5, 8 * v_s + 3.5
        z = rng.uniform(0.3, 2.0)
        p = np.array([[(u_o - camera.cx) / camera.fx * z, (v_o - camera.cy) / camera.fy * z, z]])
        uv_small, _ = small.project(p)
        np.testing.assert_allclose(uv_small[0], [u_s, v_s], atol=1e-9)
    np.testing.assert_allclose(small.fx, camera.fx / 8)
    np.testing.assert_allclose(small.cx, (camera.cx + 0.5) / 8 - 0.5)
    assert (small.width, small.height) == (80, 60)


def test_resize_with_unequal_scales_matches_closed_form(camera, rng):
    cam2 = camera.resized(100, 75)  # s_x = 100/640, s_y = 75/480
    p = points_in_view(camera, rng, 20)
    uv, _ = camera.project(p)
    uv2, _ = cam2.project(p)
    s = np.array([100 / 640, 75 / 480])
    np.testing.assert_allclose(uv2, s * (uv + 0.5) - 0.5, atol=1e-9)
    # resizing back restores K
    np.testing.assert_allclose(cam2.resized(640, 480).K, camera.K, atol=1e-12)


def test_crop_shifts_the_principal_point(camera, rng):
    crop = camera.cropped(100, 50, 200, 150)
    assert (crop.width, crop.height) == (200, 150)
    p = points_in_view(camera, rng, 20)
    uv, _ = camera.project(p)
    uv_c, _ = crop.project(p)
    np.testing.assert_allclose(uv_c, uv - [100, 50], atol=1e-9)


@pytest.mark.parametrize("size", [(640, 480), (80, 60), (101, 77)])
def test_opengl_projection_matches_opencv_after_the_flip(size, rng):
    camera = PinholeCamera(K_D415, 640, 480).resized(*size)
    near, far = 0.05, 3.0
    P = camera.opengl_projection(near, far)
    assert P.dtype == np.float64 and P.shape == (4, 4)
    p_cv = points_in_view(camera, rng, 200)
    clip = (P @ CV_TO_GL @ np.column_stack([p_cv, np.ones(len(p_cv))]).T).T
    ndc = clip[:, :3] / clip[:, 3:]
    W, H = camera.width, camera.height
    # x_ndc = 2 (u + 0.5) / W - 1, y_ndc = 1 - 2 (v + 0.5) / H (v: row from the top)
    u = (ndc[:, 0] + 1) * W / 2 - 0.5
    v = (1 - ndc[:, 1]) * H / 2 - 0.5
    np.testing.assert_allclose(np.column_stack([u, v]), cv2_project(camera.K, p_cv), atol=1e-8)
    assert np.all(np.abs(ndc) <= 1 + 1e-12)
    np.testing.assert_allclose(clip[:, 3], p_cv[:, 2])  # w_clip is the OpenCV depth


def test_opengl_projection_maps_image_corners_and_clip_planes(camera):
    P = camera.opengl_projection(0.1, 2.0)
    W, H = camera.width, camera.height
    for (u, v), expected in [((-0.5, -0.5), (-1.0, 1.0)), ((W - 0.5, H - 0.5), (1.0, -1.0))]:
        for z in (0.1, 2.0):
            p = np.array([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z, 1.0])
            clip = P @ CV_TO_GL @ p
            np.testing.assert_allclose(clip[:2] / clip[3], expected, atol=1e-12)
            np.testing.assert_allclose(clip[2] / clip[3], -1.0 if z == 0.1 else 1.0, atol=1e-12)
    with pytest.raises(ValueError, match="near"):
        camera.opengl_projection(0.0, 1.0)


def test_opencv_to_opengl_view_flips_y_and_z(rng):
    T_camera_bone = se3.from_rotvec_trans(rng.normal(size=3), rng.normal(size=3))
    view = opencv_to_opengl_view(T_camera_bone)
    p_bone = rng.normal(size=(5, 3))
    p_cv = se3.transform_points(T_camera_bone, p_bone)
    np.testing.assert_allclose(se3.transform_points(view, p_bone), p_cv * [1, -1, -1], atol=1e-12)
    assert se3.is_rigid(view)
