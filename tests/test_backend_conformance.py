"""Conformance of every likelihood backend (app/filter/observation.py) to the numpy reference.

The observation-model contract as well: each backend's ``evidence`` (covered pixels, inliers, hidden)
against the same counts on the ray cast, ``has_measurement``, and the CompositeObservation (the sum
of two models; one model alone scores as itself; pooled evidence) and the non-finite policy.

Each backend in BACKENDS must pass all of these; a third backend is added by adding its factory.
Inputs are random: poses near a true pose, plus poses behind the camera, off screen, crossing the
near plane and straddling the image (= GL tile) border; measured images with noise, occluders in
front, invalid pixels (0, NaN, +inf) and pixels beyond z_max; every likelihood option; 80x60 and
160x120; the default mesh and a CT crest of ../shared/data/pelvis (skipped without it).

The references are independent of the backend's own rendering: ``render_depth`` is compared with
the numpy ray caster of tests/raycast_ref.py, and ``log_likelihood`` with
:func:`app.filter.likelihood_ref.log_likelihood` given the *ray-cast* depth. Documented tolerance:
a pixel centre within rounding of a triangle edge can fall either way (GL rasterises in float32 with
its own tie rule, and where two surfaces meet either can win), so per pose at most max(2, 0.5 %)
of the covered pixels may differ in coverage, and as many more in depth by over 1e-4 m. The
likelihoods must agree to rtol 1e-4 + 0.02 nats on every pose whose rendering agrees with the ray
cast pixel for pixel (coverage; depth within the backend's precision, 1e-4 m for GL, whose llvmpipe
snaps vertices to 1/256 px, 1e-6 m for cpu; no measurement that close to the background ratio's
occluder threshold, a discontinuity; at least 80 % of the poses for cpu, 50 % for GL); on the others,
by at most the disagreeing pixels' worth of nats (70 nats, the log floor, per pixel, scaled like
the sum).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app.filter.likelihood_ref import LikelihoodParams, log_likelihood
from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera
from app.mesh import load_mesh, outward_wound, prepare_mesh
from app.sim.simulator import DEFAULT_MESH
from tests.conftest import pelvis_meshes
from tests.raycast_ref import raycast_depth

NEAR, FAR = 0.05, 4.0
CAMERA_80 = PinholeCamera(K=np.array([[58.0, 0.0, 40.2], [0.0, 58.5, 29.1], [0.0, 0.0, 1.0]]), width=80, height=60)
CAMERAS = {"80x60": CAMERA_80, "160x120": CAMERA_80.resized(160, 120)}
OPTIONS = {
    "beam": {},
    "smooth_exponential": {"occlusion": "smooth_exponential"},
    "classification": {"classification": True, "l0_weight": 2.0},
    "pixel_count": {"pixel_count_reg": 50.0},
    "all": {"occlusion": "smooth_exponential", "classification": True, "pixel_count_reg": 50.0},
    "background_ratio": {"background_ratio": True, "pixel_weight": 0.3},
    "ratio_classification": {"background_ratio": True, "classification": True, "occluder_margin": 0.01},
}
PER_PIXEL_BOUND = 70.0   # |l_i| <= -log(LOG_FLOOR) + log(z_max) + l0 for these parameters
T_TRUE = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([2.9, 0.2, 0.1]))), np.array([0.0, 0.0, 0.45]))


def make_gl(ctx, mesh, camera, capacity, params, cull):
    from app.render.likelihood import GLLikelihoodBackend

    return GLLikelihoodBackend(ctx, mesh.vertices, mesh.faces, camera, capacity, params,
                               near=NEAR, far=FAR, cull_back_faces=cull)


def make_cpu(ctx, mesh, camera, capacity, params, cull):
    from app.render.cpu_likelihood import CPULikelihoodBackend

    return CPULikelihoodBackend(mesh.vertices, mesh.faces, camera, capacity, params, near=NEAR, far=FAR,
                                cull_back_faces=cull)


BACKENDS = {"gl": make_gl, "cpu": make_cpu}
# m, how far a backend's rendered depth may stray from the exact ray cast on a pixel it covers like
# it: llvmpipe snaps vertices to 1/256 px (about 1e-5 m on oblique triangles), cpu is float64
DEPTH_PRECISION = {"gl": 1e-4, "cpu": 1e-6}
# the fraction of poses that must rasterise pixel for pixel like the ray cast (llvmpipe's snapping
# moves a silhouette pixel in up to half the poses at 160x120; cpu rounds like the ray cast)
MIN_EXACT = {"gl": 0.5, "cpu": 0.8}


@pytest.fixture(scope="module")
def meshes():
    """name -> (tracking mesh near the origin, cull back faces?) as the tracker prepares them."""
    out = {"default": prepare_mesh(load_mesh(DEFAULT_MESH), max_triangles=1000, center=False)}
    paths = pelvis_meshes()
    if paths:
        out["ct"] = prepare_mesh(load_mesh(paths[len(paths) // 2]), max_triangles=1000, center=True)
    return {name: (m, outward_wound(m)) for name, m in out.items()}


def get_mesh(meshes, name):
    if name not in meshes:
        pytest.skip("the CT crests of ../shared/data/pelvis are absent")
    return meshes[name]


def at_pixel(R, centre_bone, u, v, z):
    """The pose with rotation R that puts the mesh's centre on pixel (u, v) of CAMERA_80 at depth z."""
    ray = np.array([(u - CAMERA_80.cx) / CAMERA_80.fx, (v - CAMERA_80.cy) / CAMERA_80.fy, 1.0])
    return se3.make_pose(R, z * ray - R @ centre_bone)


def true_pose(mesh):
    """The measured image's pose: T_TRUE's rotation, the mesh's centre on the image centre at 0.45 m."""
    return at_pixel(T_TRUE[:3, :3], mesh.bounds.mean(axis=0), 40, 30, 0.45)


def random_poses(rng, n, mesh):
    """n poses near T_TRUE, with special cases in the first six (the image is scaled alike at 160x120)."""
    centre = mesh.bounds.mean(axis=0)
    R_true = T_TRUE[:3, :3]
    # σ_t 6 mm: few poses sit 2 cm behind the truth, where measurements meet the occluder threshold
    dT = se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.15, (n, 3))), rng.normal(0, 0.006, (n, 3)))
    poses = true_pose(mesh) @ dT
    poses[0] = se3.make_pose(np.eye(3), np.array([0.0, 0.0, -1.0]))                    # behind the camera
    poses[1] = at_pixel(np.eye(3), centre, 400, 30, 0.4)                               # off screen
    poses[2] = at_pixel(R_true, centre, 40, 30, 0.066)                                 # crosses the near plane
    poses[3] = at_pixel(R_true, centre, 79.5, 10, 0.3)                                 # straddles the right border
    poses[4] = at_pixel(quat.to_matrix(quat.exp_map(np.array([0.3, 2.8, 0.0]))), centre, 0.0, 59.5, 0.35)  # a corner
    poses[5] = poses[6] @ se3.make_pose(quat.to_matrix(quat.exp_map(np.array([1.4, 0.0, 0.0]))), np.zeros(3))  # grazing
    return poses


def measured_image(depth_true, rng, z_max):
    """The true pose's depth with noise, a table behind, occluders in front, invalid pixels (0, NaN,
    +inf) and pixels beyond z_max."""
    z = np.where(depth_true > 0, depth_true, 0.55 + 0.02 * rng.random(depth_true.shape))
    z = z + rng.normal(0, 0.0015, z.shape)
    occluded = rng.random(z.shape) < 0.1
    z[occluded] *= rng.uniform(0.3, 0.9, occluded.sum())
    z[rng.random(z.shape) < 0.05] = 0.0
    z[rng.random(z.shape) < 0.01] = z_max + 1.5
    z[0, :3] = np.nan
    z[-1, -3:] = np.inf
    return z.astype(np.float32)


def coverage_agreement(rendered, reference, depth_tol=1e-4):
    """Per pose: (pixels whose coverage differs, covered pixels, pixels both cover whose depths
    differ by more than ``depth_tol`` m)."""
    cov, ref = rendered > 0, reference > 0
    n = len(cov)
    differ = (cov ^ ref).reshape(n, -1).sum(1)
    covered = ref.reshape(n, -1).sum(1)
    depth_off = ((np.abs(rendered - reference) > depth_tol) & cov & ref).reshape(n, -1).sum(1)
    return differ, covered, depth_off


def at_a_threshold(depth, reference_depth, params, eps):
    """Per pose: covered pixels whose measurement lies within ``eps`` m (the backend's depth
    precision) of the background ratio's occluder threshold z = z* - margin, a discontinuity of the
    pixel term that the backend's rounding may put on either side."""
    if not params.background_ratio:
        return np.zeros(len(reference_depth), dtype=int)
    near_edge = np.abs(depth[None] - (reference_depth - params.occluder_margin)) < eps
    return (near_edge & (reference_depth > 0)).reshape(len(reference_depth), -1).sum(1)


@pytest.mark.parametrize("resolution", list(CAMERAS))
@pytest.mark.parametrize("mesh_name", ["default", "ct"])
@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_render_depth_matches_the_ray_cast(ctx, meshes, backend_name, mesh_name, resolution, rng):
    mesh, cull = get_mesh(meshes, mesh_name)
    camera = CAMERAS[resolution]
    poses = random_poses(rng, 24 if resolution == "80x60" else 14, mesh)
    backend = BACKENDS[backend_name](ctx, mesh, camera, len(poses), LikelihoodParams(), cull)
    try:
        rendered = backend.render_depth(poses)
    finally:
        backend.release()
    reference = raycast_depth(mesh.vertices, mesh.faces, camera, poses, NEAR, FAR, cull)
    assert rendered.shape == (len(poses), camera.height, camera.width) and rendered.dtype == np.float32
    differ, covered, depth_off = coverage_agreement(rendered, reference)
    assert covered[0] == covered[1] == 0 and differ[0] == differ[1] == 0
    assert (covered[2:] > 0).all(), "every other pose must be seen for the comparison to mean something"
    assert (reference[3][:, -1] > 0).any() and (reference[4][-1] > 0).any(), "poses 3, 4 must reach the border"
    assert (reference[2] > 0).sum() > 0.1 * reference[2].size, "pose 2 must fill much of the image, clipped by near"
    assert np.all(differ <= np.maximum(2, 0.005 * covered)), (differ, covered)
    assert np.all(depth_off <= np.maximum(2, 0.005 * covered)), (depth_off, covered)


def likelihood_case(ctx, meshes, backend_name, mesh_name, resolution, option, rng):
    mesh, cull = get_mesh(meshes, mesh_name)
    camera = CAMERAS[resolution]
    params = replace(LikelihoodParams(), **OPTIONS[option])
    poses = random_poses(rng, 40 if resolution == "80x60" else 14, mesh)   # the reference's erfc is slow
    truth = raycast_depth(mesh.vertices, mesh.faces, camera, true_pose(mesh)[None], NEAR, FAR, cull)[0]
    depth = measured_image(truth, rng, params.z_max)
    backend = BACKENDS[backend_name](ctx, mesh, camera, len(poses), params, cull)
    try:
        values = backend.log_likelihood(poses, depth)
        own = backend.render_depth(poses)       # only to tell which poses rasterised exactly like the ray cast
    finally:
        backend.release()
    reference_depth = raycast_depth(mesh.vertices, mesh.faces, camera, poses, NEAR, FAR, cull)
    reference = log_likelihood(depth, reference_depth.astype(np.float32), params)
    assert values.shape == (len(poses),) and values.dtype == np.float64
    assert values[0] == 0.0 and values[1] == 0.0, "a pose covering no pixel scores log 1 = 0"
    assert np.ptp(reference) > 10.0, "the poses must differ enough for the comparison to mean something"
    precision = DEPTH_PRECISION[backend_name]
    differ, covered, depth_off = coverage_agreement(own, reference_depth, precision)
    depth_off = depth_off + at_a_threshold(depth, reference_depth, params, precision)
    exact = (differ == 0) & (depth_off == 0)
    assert exact.mean() >= MIN_EXACT[backend_name], f"only {exact.sum()} of {len(exact)} poses rasterised exactly like the ray cast"
    tol = 1e-4 * np.abs(reference) + 0.02
    assert np.all(np.abs(values - reference)[exact] <= tol[exact]), np.abs(values - reference)[exact].max()
    scale = params.pixel_count_reg / np.maximum(covered - differ, 1) if params.pixel_count_reg > 0 else params.pixel_weight
    loose = tol + scale * PER_PIXEL_BOUND * (differ + depth_off) * (2 if params.pixel_count_reg > 0 else 1)
    assert np.all(np.abs(values - reference) <= loose)
    return values, reference


@pytest.mark.parametrize("option", list(OPTIONS))
@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_log_likelihood_matches_the_reference_for_every_option(ctx, meshes, backend_name, option, rng):
    likelihood_case(ctx, meshes, backend_name, "default", "80x60", option, rng)


@pytest.mark.parametrize("resolution, mesh_name, option", [("160x120", "default", "all"), ("80x60", "ct", "all"),
                                                            ("160x120", "ct", "background_ratio")])
@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_log_likelihood_matches_the_reference_at_160x120_and_on_a_ct_crest(ctx, meshes, backend_name, mesh_name,
                                                                            resolution, option, rng):
    likelihood_case(ctx, meshes, backend_name, mesh_name, resolution, option, rng)


@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_the_true_pose_scores_best(ctx, meshes, backend_name, rng):
    mesh, cull = meshes["default"]
    camera = CAMERAS["160x120"]
    params = LikelihoodParams(background_ratio=True, pixel_weight=0.2)
    truth = raycast_depth(mesh.vertices, mesh.faces, camera, true_pose(mesh)[None], NEAR, FAR, cull)[0]
    depth = measured_image(truth, rng, params.z_max)
    poses = true_pose(mesh) @ se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.05, (50, 3))), rng.normal(0, 0.01, (50, 3)))
    poses[0] = true_pose(mesh)
    backend = BACKENDS[backend_name](ctx, mesh, camera, len(poses), params, cull)
    try:
        assert np.argmax(backend.log_likelihood(poses, depth)) == 0
    finally:
        backend.release()


@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_a_pose_straddling_the_border_leaves_the_others_values_unchanged(ctx, meshes, backend_name, rng):
    """In GL, the image border is a tile border: a pose reaching it must not bleed into a neighbour."""
    mesh, cull = meshes["default"]
    backend = BACKENDS[backend_name](ctx, mesh, CAMERA_80, 9, LikelihoodParams(), cull)
    depth = measured_image(raycast_depth(mesh.vertices, mesh.faces, CAMERA_80, true_pose(mesh)[None], NEAR, FAR, cull)[0],
                           rng, 2.0)
    poses = true_pose(mesh) @ se3.from_quat_trans(quat.exp_map(rng.normal(0, 0.1, (9, 3))), rng.normal(0, 0.01, (9, 3)))
    poses[4] = at_pixel(np.eye(3), mesh.bounds.mean(axis=0), 79.5, 5.0, 0.25)    # across the right border
    try:
        straddling = backend.log_likelihood(poses, depth)
        assert (backend.render_depth(poses)[4][:, -1] > 0).any(), "pose 4 must reach the image border"
        alone = poses.copy()
        alone[4] = se3.make_pose(np.eye(3), np.array([0.0, 0.0, -1.0]))
        without = backend.log_likelihood(alone, depth)
    finally:
        backend.release()
    keep = np.arange(9) != 4
    np.testing.assert_array_equal(straddling[keep], without[keep])


@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_a_wrong_image_size_is_refused(ctx, meshes, backend_name):
    mesh, cull = meshes["default"]
    backend = BACKENDS[backend_name](ctx, mesh, CAMERA_80, 4, LikelihoodParams(), cull)
    try:
        with pytest.raises(ValueError, match="80x60"):
            backend.log_likelihood(np.repeat(true_pose(mesh)[None], 4, axis=0), np.zeros((120, 160), np.float32))
    finally:
        backend.release()


# -- the observation-model contract: evidence, measurement check, composite --------------------------

def reference_evidence(mesh, camera, cull, T_camera_bone, depth, params, min_covered):
    """The evidence of one pose computed on the numpy ray cast (the backend-independent reference)."""
    from app.filter.observation import depth_evidence

    def render(T):
        return raycast_depth(mesh.vertices, mesh.faces, camera, T, NEAR, FAR, cull).astype(np.float32)

    return depth_evidence(render, T_camera_bone, depth, params, min_covered)


@pytest.mark.parametrize("option", ["beam", "background_ratio"])
@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_evidence_matches_the_ray_cast_reference(ctx, meshes, backend_name, option, rng):
    """covered pixels and inliers of the true pose, offset poses and an off-screen pose agree with the
    ray cast's within the coverage tolerance of the module docstring; occluders in front are left out."""
    from app.filter.observation import Evidence, LikelihoodBackend, ObservationModel

    mesh, cull = meshes["default"]
    camera = CAMERAS["160x120"]
    params = replace(LikelihoodParams(), **OPTIONS[option])
    truth = raycast_depth(mesh.vertices, mesh.faces, camera, true_pose(mesh)[None], NEAR, FAR, cull)[0]
    depth = measured_image(truth, rng, params.z_max)
    poses = random_poses(rng, 8, mesh)
    poses[6] = true_pose(mesh)
    backend = BACKENDS[backend_name](ctx, mesh, camera, len(poses), params, cull)
    try:
        assert isinstance(backend, ObservationModel) and isinstance(backend, LikelihoodBackend)
        got = [backend.evidence(T, depth, 30) for T in poses]
    finally:
        backend.release()
    want = [reference_evidence(mesh, camera, cull, T, depth, params, 30) for T in poses]
    assert all(isinstance(e, Evidence) for e in got)
    assert got[0] == got[1] == Evidence(0, 0, True), "behind the camera / off screen: nothing covered, hidden"
    assert np.isnan(got[0].inlier_fraction)
    for g, w in zip(got[2:], want[2:]):
        slack = max(2, 0.005 * w.covered_pixels) * 2
        assert abs(g.covered_pixels - w.covered_pixels) <= slack and abs(g.inliers - w.inliers) <= slack, (g, w)
        assert g.bone_hidden == (g.covered_pixels < 30)
    assert want[6].covered_pixels > 300 and want[6].inlier_fraction > 0.6, "the true pose must be seen and explain it"
    assert got[6].inlier_fraction == pytest.approx(want[6].inlier_fraction, abs=0.01)


@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_evidence_says_hidden_when_an_occluder_covers_the_bone(ctx, meshes, backend_name):
    """A hand 5 cm in front of every pixel of the pose: nothing is covered, the bone is hidden; with
    the hand gone, the pose's pixels all count and all are inliers."""
    mesh, cull = meshes["default"]
    camera = CAMERAS["80x60"]
    T = true_pose(mesh)
    truth = raycast_depth(mesh.vertices, mesh.faces, camera, T[None], NEAR, FAR, cull)[0].astype(np.float32)
    background = np.float32(0.6)
    clear = np.where(truth > 0, truth, background).astype(np.float32)
    hand = np.where(truth > 0, truth - 0.05, background).astype(np.float32)
    backend = BACKENDS[backend_name](ctx, mesh, camera, 1, LikelihoodParams(), cull)
    try:
        seen, hidden = backend.evidence(T, clear, 30), backend.evidence(T, hand, 30)
    finally:
        backend.release()
    n = int((truth > 0).sum())
    assert n > 30
    assert abs(seen.covered_pixels - n) <= max(2, 0.005 * n) and seen.inliers == seen.covered_pixels
    assert not seen.bone_hidden and seen.inlier_fraction == 1.0
    assert hidden.covered_pixels == 0 and hidden.bone_hidden


@pytest.mark.parametrize("backend_name", list(BACKENDS))
def test_has_measurement_needs_one_valid_pixel(ctx, meshes, backend_name):
    mesh, cull = meshes["default"]
    params = LikelihoodParams()
    backend = BACKENDS[backend_name](ctx, mesh, CAMERA_80, 1, params, cull)
    try:
        empty = np.zeros((60, 80), np.float32)
        junk = empty.copy()
        junk[0, :3] = [np.nan, np.inf, params.z_max + 0.1]
        one = junk.copy()
        one[5, 5] = 0.5
        assert not backend.has_measurement(empty) and not backend.has_measurement(junk)
        assert backend.has_measurement(one)
    finally:
        backend.release()


class _Fixed:
    """A stand-in observation model with given scores and evidence (for the composite's arithmetic)."""

    def __init__(self, name, scores, evidence, measured=True):
        self.name, self.scores, self._evidence, self.measured = name, np.asarray(scores, float), evidence, measured
        self.timings = {"score": 0.001}
        self.released = False

    def log_likelihood(self, T_camera_bone, depth_meas):
        return self.scores[:len(T_camera_bone)]

    def has_measurement(self, depth_meas):
        return self.measured

    def evidence(self, T_camera_bone, depth_meas, min_covered_pixels):
        return self._evidence

    def describe(self):
        return f"fixed {self.name}"

    def release(self):
        self.released = True


def test_a_composite_of_two_backends_scores_their_sum_and_one_alone_scores_as_itself(ctx, meshes, rng):
    """CompositeObservation([a, b]) == a + b (two depth models with different options, on the CPU);
    CompositeObservation([a]) == a exactly, evidence included."""
    from app.filter.observation import CompositeObservation, ObservationModel

    mesh, cull = meshes["default"]
    camera = CAMERAS["80x60"]
    pa, pb = LikelihoodParams(), replace(LikelihoodParams(), **OPTIONS["background_ratio"])
    truth = raycast_depth(mesh.vertices, mesh.faces, camera, true_pose(mesh)[None], NEAR, FAR, cull)[0]
    depth = measured_image(truth, rng, pa.z_max)
    poses = random_poses(rng, 20, mesh)
    a, b = make_cpu(ctx, mesh, camera, 20, pa, cull), make_cpu(ctx, mesh, camera, 20, pb, cull)
    both, alone = CompositeObservation([a, b]), CompositeObservation([a])
    assert isinstance(both, ObservationModel)
    la, lb = a.log_likelihood(poses, depth), b.log_likelihood(poses, depth)
    assert np.ptp(la) > 10 and np.ptp(lb) > 1, "the scores must differ across poses for the sum to mean something"
    np.testing.assert_allclose(both.log_likelihood(poses, depth), la + lb, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(alone.log_likelihood(poses, depth), la)
    assert alone.evidence(poses[6], depth, 30) == a.evidence(poses[6], depth, 30)
    assert both.name == "cpu+cpu" and set(both.timings) == {"cpu_prepare", "cpu_raster_likelihood"}
    assert both.has_measurement(depth) and not both.has_measurement(np.zeros_like(depth))
    both.release()


def test_a_composite_pools_evidence_and_is_hidden_only_when_every_model_is():
    from app.filter.observation import CompositeObservation, Evidence

    seen, hidden = Evidence(100, 80, False), Evidence(10, 2, True)
    a, b = _Fixed("a", [1.0, -np.inf, 3.0], seen), _Fixed("b", [0.5, 2.0, np.nan], hidden, measured=False)
    composite = CompositeObservation([a, b])
    T = np.repeat(np.eye(4)[None], 3, axis=0)
    out = composite.log_likelihood(T, np.zeros((2, 2), np.float32))
    assert out[0] == 1.5 and out[1] == -np.inf and np.isnan(out[2]), "a plain sum: the filter applies the NaN policy"
    e = composite.evidence(T[0], None, 30)
    assert e == Evidence(110, 82, False) and e.inlier_fraction == pytest.approx(82 / 110)
    assert CompositeObservation([b, b]).evidence(T[0], None, 30).bone_hidden
    assert composite.has_measurement(None) and not CompositeObservation([b]).has_measurement(None)
    assert composite.describe() == "fixed a + fixed b"
    composite.release()
    assert a.released and b.released
    with pytest.raises(ValueError, match="at least one"):
        CompositeObservation([])


def test_the_non_finite_policy_sets_nan_and_plus_inf_to_minus_inf_and_counts_them():
    from app.filter.observation import finite_log_likelihood

    raw = np.array([1.0, np.nan, np.inf, -np.inf, -2.0])
    out, n_bad = finite_log_likelihood(raw)
    assert n_bad == 2 and np.isnan(raw[1]), "the caller's array is left alone"
    np.testing.assert_array_equal(out, [1.0, -np.inf, -np.inf, -np.inf, -2.0])
