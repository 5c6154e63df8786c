"""The one-point initialiser (app/filter/smc_init.py): its geometry against closed forms, its
tempering rule, its prior, and a simulated trial started from nothing but a point on the bone."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from app.filter import weights as lw_ops
from app.filter import resampling as rs
from app.filter.smc_init import SMCInitConfig, SurfacePrior, measured_normal, next_phi, rotate_about, rotation_between
from app.geometry import quaternion as quat
from app.geometry import se3
from app.geometry.camera import PinholeCamera


def _unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_rotation_between_takes_a_onto_b_including_opposite_vectors(rng):
    a = _unit(rng, 50)
    b = _unit(rng, 1)[0]
    a[0] = -b                                     # the 180 degree case
    a[1] = b                                      # the identity case
    q = rotation_between(a, b)
    np.testing.assert_allclose(quat.rotate(q, a), np.repeat(b[None], 50, axis=0), atol=1e-9)
    # shortest: the angle of the rotation is the angle between the vectors
    np.testing.assert_allclose(quat.angle_between(q, np.repeat(np.array([[1.0, 0, 0, 0]]), 50, axis=0)),
                               np.arccos(np.clip(a @ b, -1, 1)), atol=1e-6)


def test_rotation_about_the_pointed_point_keeps_it_on_the_same_bone_point(rng):
    n = 20
    p, q = rng.normal(size=(n, 3)), quat.random_uniform(rng, n)
    point = rng.normal(size=3)
    dq = quat.random_uniform(rng, n)
    p2, q2 = rotate_about(point, p, q, dq)
    before = quat.rotate(quat.conjugate(q), point[None] - p)     # the point in each bone frame
    after = quat.rotate(quat.conjugate(q2), point[None] - p2)
    np.testing.assert_allclose(after, before, atol=1e-9)
    np.testing.assert_allclose(quat.angle_between(quat.multiply(q2, quat.conjugate(q)), dq), 0.0, atol=1e-6)


def test_measured_normal_of_a_tilted_plane_is_its_normal_facing_the_camera():
    camera = PinholeCamera(np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]]), 160, 120)
    normal_camera = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])   # faces the camera
    point_camera = np.array([0.01, -0.02, 0.5])
    rays = camera.pixel_rays().reshape(-1, 3)
    z = (normal_camera @ point_camera) / (rays @ normal_camera)          # ray-plane intersection
    depth = z.reshape(120, 80 * 2).astype(np.float32)
    T_base_camera = se3.from_rotvec_trans(np.array([0.4, -0.3, 1.0]), np.array([0.2, 0.1, 0.6]))
    point_base = T_base_camera[:3, :3] @ point_camera + T_base_camera[:3, 3]
    n = measured_normal(depth, camera, T_base_camera, point_base, radius=0.01)
    np.testing.assert_allclose(n, T_base_camera[:3, :3] @ normal_camera, atol=1e-4)
    hidden = np.zeros_like(depth)                                        # nothing measured there
    assert measured_normal(hidden, camera, T_base_camera, point_base, radius=0.01) is None


def test_next_phi_keeps_the_target_ess_and_goes_to_one_when_it_can(rng):
    ll = rng.normal(0.0, 200.0, 500)
    phi = next_phi(0.1, ll, 0.5)
    assert 0.1 < phi < 1.0
    ess = lw_ops.ess(lw_ops.normalise_log_weights((phi - 0.1) * ll)) / len(ll)
    assert ess == pytest.approx(0.5, abs=0.01)
    assert next_phi(0.3, np.full(100, -7.0), 0.5) == 1.0                # a flat likelihood: straight to 1


def test_ess_fraction_is_the_weights_modules_ess_over_n_with_zero_weights(rng):
    from app.filter.smc_init.tempering import ess_fraction

    for scale in (0.1, 30.0, 3000.0):
        log_w = rng.normal(0.0, scale, 400)
        log_w[:7] = -np.inf
        assert ess_fraction(log_w) == pytest.approx(lw_ops.ess(lw_ops.normalise_log_weights(log_w)) / 400, rel=1e-12)
    assert ess_fraction(np.full(5, -np.inf)) == 0.0


def test_systematic_resampling_draws_any_count_following_the_weights(rng):
    """The initialiser keeps n of its wider first draw: systematic resampling with n != N draws."""
    w = np.array([0.5, 0.25, 0.125, 0.125])
    idx = rs.systematic(np.log(w), rng.random(), 800)
    np.testing.assert_array_equal(np.bincount(idx, minlength=4), (800 * w).astype(int))


def test_surface_prior_peaks_at_the_true_pose_and_its_draws_obey_it(rng):
    mesh = trimesh.creation.box((0.08, 0.03, 0.02))
    T_base_bone = se3.from_rotvec_trans(np.array([0.2, 0.5, -0.3]), np.array([0.5, 0.1, 0.05]))
    top_bone = np.array([0.01, 0.005, 0.01])                             # on the box's top face
    point_base = T_base_bone[:3, :3] @ top_bone + T_base_bone[:3, 3]
    prior = SurfacePrior(mesh.vertices, mesh.faces, point_base, 0.002, 4000, rng)
    q0, t0 = se3.to_quat_trans(T_base_bone)
    assert prior.log_density(t0[None], q0[None])[0] > -0.5
    assert prior.log_density(t0[None] + [[0.0, 0.0, 0.01]], q0[None])[0] < -5       # 1 cm off: 5 sigma
    normal_base = T_base_bone[:3, :3] @ np.array([0.0, 0.0, 1.0])
    prior.set_normal(normal_base, 0.1)
    assert prior.log_density(t0[None], q0[None])[0] > -0.5
    p, q = prior.sample(400, rng)
    d, idx = prior.nearest(p, q)
    assert np.median(d) < 0.004
    angles = np.arccos(np.clip(quat.rotate(q, prior.normals_bone[idx]) @ normal_base, -1, 1))
    assert np.median(angles) < 0.3


@pytest.fixture(scope="module")
def point_start(tmp_path_factory):
    from app.config import load_config
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    base = tmp_path_factory.mktemp("smc")
    simulate(base / "trial", scenario_name="static_clear", seconds=1.5, seed=11)
    # the initialiser's budget counts likelihood evaluations; its wall-time safety net is pinned out
    # of reach so that a loaded machine runs exactly the same restarts as a free one
    config = replace(load_config(None), init_method="point", init_budget_s=3600.0)
    return base, replay(base / "trial", base / "out", config, rrd=False, projector=False)


def test_a_point_on_the_bone_can_start_tracking_but_never_reports_ok(point_start):
    """No initial pose: on this seeded trial the sampler finds the crest from the simulated pointed
    point on the first frame and the filter tracks it from there; because the sampler can also
    settle on the crest turned end for end (smc_init.py), such a session is never ok."""
    import json

    base, result = point_start
    init = json.loads((base / "out" / "summary.json").read_text())["init"]
    assert init["add_mm"] < 5.0 and init["rotation_deg"] < 5.0
    assert init["tempering_steps"] >= 1 and init["seconds"] > 0
    assert 0 < init["evaluations"] <= SMCInitConfig.max_evaluations
    add = result.errors["add_mm"]
    assert np.median(add[30:]) < 2.5
    assert "ok" not in result.statuses and "uncertain" in result.statuses


def test_point_start_without_a_point_names_the_key(tmp_path):
    from app.config import load_config
    from app.errors import TrialFormatError
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate
    from app.trial.meta import dump_meta, load_meta

    simulate(tmp_path / "trial", scenario_name="static_clear", seconds=0.2, seed=1)
    meta = load_meta(tmp_path / "trial" / "trial.yaml")
    dump_meta(replace(meta, point_prior=None), tmp_path / "trial" / "trial.yaml")
    with pytest.raises(TrialFormatError, match="point_prior"):
        replay(tmp_path / "trial", tmp_path / "out", replace(load_config(None), init_method="point"), rrd=False)


def test_mesh_symmetries_are_the_half_turns_that_map_the_mesh_onto_itself():
    """A box is its own image under the half turn about each of its axes; a cone only under the
    half turn about its own axis (its principal axes: the axis and two perpendicular ones)."""
    from app.filter.smc_init import mesh_symmetries

    box = trimesh.creation.box((0.08, 0.03, 0.02))
    found = mesh_symmetries(box.vertices, box.faces)
    assert len(found) == 3
    for S in found:
        q, t = se3.to_quat_trans(S)
        assert np.degrees(quat.angle_between(q[None], np.array([[1.0, 0, 0, 0]])))[0] == pytest.approx(180, abs=2)
        assert np.linalg.norm(t) < 0.002                      # about the centre
    cone = trimesh.creation.cone(radius=0.015, height=0.08, sections=64)
    cone.apply_translation(-cone.center_mass)
    found = mesh_symmetries(cone.vertices, cone.faces)
    assert len(found) == 1
    axis = quat.log_map(se3.to_quat_trans(found[0])[0][None])[0]
    assert abs(axis[2]) / np.linalg.norm(axis) > 0.99          # the cone's own axis (z)


def test_symmetry_check_turns_a_cloud_stuck_on_the_turned_bone_back_to_the_likelier_pose(rng):
    """A cloud settled on the box turned by one of its half-turn symmetries, under a likelihood that
    peaks only at the true pose: the check must find and take the true pose (and leave a cloud that
    is already right where it is)."""
    from app.filter.estimate import estimate
    from app.filter.smc_init import Budget, Level, OnePointInitialiser, SMCInitConfig, SMCResult, Tempering, mesh_symmetries

    box = trimesh.creation.box((0.08, 0.03, 0.02))
    T_true = se3.from_rotvec_trans(np.array([0.1, -0.2, 0.3]), np.array([0.4, 0.05, 0.02]))
    q_true, t_true = se3.to_quat_trans(T_true)
    top_base = T_true[:3, :3] @ np.array([0.01, 0.0, 0.01]) + T_true[:3, 3]
    prior = SurfacePrior(box.vertices, box.faces, top_base, 0.005, 4000, rng)

    def log_lik(p, q):   # a narrow peak at the true pose: -(|Δt| / 2 mm)² - (angle / 2 deg)²
        angle = quat.angle_between(q, np.repeat(q_true[None], len(q), axis=0))
        return -(np.linalg.norm(p - t_true, axis=1) / 0.002) ** 2 - (angle / np.radians(2.0)) ** 2

    config = SMCInitConfig(particles=100)
    initialiser = OnePointInitialiser(None, None, box.vertices, box.faces, config, rng)
    tempering, level = Tempering(prior, config, Budget(), rng), Level("closed form", log_lik)
    S = mesh_symmetries(box.vertices, box.faces)[0]

    def cloud_at(T):
        q0, t0 = se3.to_quat_trans(T)
        p = t0 + rng.normal(0.0, 0.0005, (100, 3))
        q = np.repeat(q0[None], 100, axis=0)
        ll = log_lik(p, q)
        return SMCResult(p, q, ll, estimate(p, q, np.full(100, -np.log(100))))

    turned = initialiser._symmetry_check(cloud_at(T_true @ S), tempering, level)
    assert turned.symmetry_turned
    assert np.linalg.norm(turned.estimate.T_base_bone[:3, 3] - t_true) < 0.003
    assert np.degrees(se3.rotation_angle(turned.estimate.T_base_bone, T_true)) < 3.0
    kept = initialiser._symmetry_check(cloud_at(T_true), tempering, level)
    assert not kept.symmetry_turned


class CountingBackend:
    """A closed-form likelihood: -|t_camera_bone - t_true|^2 / (2 (2 mm)^2), counting the poses scored."""

    def __init__(self, T_camera_bone_true: np.ndarray):
        self.t_true = T_camera_bone_true[:3, 3]
        self.scored = 0

    def log_likelihood(self, T_camera_bone, depth):
        self.scored += len(T_camera_bone)
        return -np.sum((T_camera_bone[:, :3, 3] - self.t_true) ** 2, axis=1) / (2 * 0.002 ** 2)


@pytest.mark.parametrize("max_evaluations", [12_000, 40_000])
def test_the_initialiser_budget_counts_evaluations_not_seconds(max_evaluations):
    """The budget is a count of scored poses: a run stops at it, overshooting by at most the step that
    crosses it and the final sweeps at φ = 1 (2 x mh_moves x particles = 1,600 poses; the symmetry
    check, which scores more, is off here), and the same seed
    gives the same cloud however long each evaluation takes (nothing reads the clock but the 600 s
    safety net, which these runs of a few hundred ms never approach)."""
    from app.filter.smc_init import OnePointInitialiser

    box = trimesh.creation.box((0.06, 0.02, 0.01))
    T_base_camera = np.eye(4)
    T_base_bone = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 0.3]))
    point = T_base_bone[:3, 3] + np.array([0.0, 0.0, 0.005])          # the top face's centre
    config = replace(SMCInitConfig(), restarts=3, max_evaluations=max_evaluations, prior_draws=2000,
                     sigma_n=0.0, symmetry_check=False, surface_samples=500)
    camera = PinholeCamera(np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]), 64, 48)
    results = []
    for _ in range(2):
        backend = CountingBackend(se3.inverse(T_base_camera) @ T_base_bone)
        init = OnePointInitialiser(backend, camera, box.vertices, box.faces, config, np.random.default_rng(5))
        result = init.run(np.zeros((48, 64), np.float32), T_base_camera, point)
        assert result.evaluations == backend.scored
        assert backend.scored <= max_evaluations + 2 * config.mh_moves * config.particles
        results.append(result)
    np.testing.assert_array_equal(results[0].p, results[1].p)
    if max_evaluations == 12_000:
        # 12,000 / 3 runs = 4,000 each: 2,000 prior draws, then 3 steps of 800: every run uses its share
        assert results[0].evaluations >= max_evaluations


class ScaledBackend(CountingBackend):
    """CountingBackend whose log-likelihood is ``scale`` times the closed form, with ``resized`` like the
    CPU backend (a coarser level: the scale of its pixel count), and NaN for poses past ``nan_beyond`` m."""

    name = "cpu"

    def __init__(self, T_camera_bone_true, camera, nan_beyond=np.inf, vertices=None, faces=None, sharpness=1.0):
        super().__init__(T_camera_bone_true)
        self.camera, self.nan_beyond, self.vertices, self.faces, self.cull = camera, nan_beyond, vertices, faces, True
        self.sharpness, self.children = sharpness, []

    def log_likelihood(self, T_camera_bone, depth):
        assert depth.shape == (self.camera.height, self.camera.width)
        scale = self.sharpness * self.camera.width * self.camera.height / 64 / 48
        ll = super().log_likelihood(T_camera_bone, depth) * scale
        far = np.linalg.norm(T_camera_bone[:, :3, 3] - self.t_true, axis=1) > self.nan_beyond
        return np.where(far, np.nan, ll)

    def resized(self, camera, vertices=None, faces=None, cull_back_faces=None):
        child = ScaledBackend(self.t_true_pose, camera, self.nan_beyond, vertices, faces, self.sharpness)
        self.children.append(child)
        return child

    @property
    def t_true_pose(self):
        return se3.make_pose(np.eye(3), self.t_true)


def test_levels_coarse_to_fine_with_decimated_meshes_and_pixel_scales():
    from app.filter.smc_init import make_levels

    box = trimesh.creation.icosphere(subdivisions=3, radius=0.02)          # 1,280 triangles, outward
    camera = PinholeCamera(np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]]), 160, 120)
    backend = ScaledBackend(np.eye(4), camera, vertices=box.vertices, faces=box.faces)
    levels = make_levels(backend, camera, np.zeros((120, 160), np.float32), np.eye(4), ((4, 250), (2, 500), (64, 10)))
    assert [v.name for v in levels] == ["40x30", "80x60", "160x120"]    # 160/64 px is under the minimum: skipped
    assert [v.scale for v in levels] == [1200.0, 4800.0, 19200.0]
    assert [len(c.faces) <= t for c, t in zip(backend.children, (250, 500))] == [True, True]
    assert all(len(c.faces) > 100 for c in backend.children)
    plain = make_levels(CountingBackend(np.eye(4)), camera, np.zeros((120, 160), np.float32), np.eye(4), ((2, 500),))
    assert [v.name for v in plain] == ["160x120"]                         # no ``resized``: the filter's level only


def test_a_level_switch_between_proportional_likelihoods_keeps_the_cloud_and_divides_phi(rng):
    """p_b = p_a^4 (4x the pixels): π_a at φ is π_b at φ / 4 exactly, so the weights are uniform and
    systematic resampling keeps every pose once."""
    from app.filter.smc_init import Budget, Level, Tempering

    def ll_a(p, q):
        return -np.sum(p ** 2, axis=1) / 2e-4

    a, b = Level("a", ll_a, 1200.0), Level("b", lambda p, q: 4.0 * ll_a(p, q), 4800.0)
    prior = SurfacePrior(trimesh.creation.box((0.02, 0.02, 0.02)).vertices, trimesh.creation.box((0.02, 0.02, 0.02)).faces,
                         np.zeros(3), 0.005, 200, rng)
    budget = Budget()
    tempering = Tempering(prior, SMCInitConfig(), budget, rng)
    cloud = tempering.score(a, rng.normal(0, 0.01, (50, 3)), quat.random_uniform(rng, 50))
    moved, phi = tempering.switch(cloud, 0.6, a, b)
    assert phi == pytest.approx(0.15)
    np.testing.assert_array_equal(np.sort(moved.p, axis=0), np.sort(cloud.p, axis=0))
    np.testing.assert_allclose(moved.ll, 4.0 * ll_a(moved.p, moved.q))
    assert budget.evaluations == 100
    assert tempering.switch(cloud, 1.0, b, a)[1] == 1.0                    # never past φ = 1


def test_non_finite_log_likelihoods_are_minus_infinity_counted_and_never_chosen():
    """Policy of the particle filter: NaN / +inf scores are -inf (zero likelihood) and counted. Poses
    more than 2 cm off score NaN here; the sampler must still find the pose and report the count."""
    from app.filter.smc_init import Budget, Level, OnePointInitialiser, evaluate

    budget = Budget()
    ll = evaluate(Level("x", lambda p, q: np.array([1.0, np.nan, np.inf, -np.inf])), np.zeros((4, 3)),
                  np.zeros((4, 4)), budget)
    np.testing.assert_array_equal(ll, [1.0, -np.inf, -np.inf, -np.inf])
    assert budget.nonfinite == 2 and budget.evaluations == 4

    box = trimesh.creation.box((0.06, 0.02, 0.01))
    T_base_bone = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 0.3]))
    point = T_base_bone[:3, 3] + np.array([0.0, 0.0, 0.005])
    camera = PinholeCamera(np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]), 64, 48)
    config = replace(SMCInitConfig(), restarts=1, prior_draws=2000, sigma_n=0.0, symmetry_check=False,
                     surface_samples=500, max_evaluations=20_000, coarse_levels=((2, 1000),))
    backend = ScaledBackend(T_base_bone, camera, nan_beyond=0.02, vertices=box.vertices, faces=box.faces)
    result = OnePointInitialiser(backend, camera, box.vertices, box.faces, config,
                                 np.random.default_rng(3)).run(np.zeros((48, 64), np.float32), np.eye(4), point)
    assert result.levels == ["32x24", "64x48"] and result.nonfinite > 0
    assert np.all(np.isfinite(result.log_likelihood)) and np.all(np.isfinite(result.p))
    assert np.linalg.norm(result.estimate.T_base_bone[:3, 3] - T_base_bone[:3, 3]) < 0.005
    assert result.evaluations == backend.scored + sum(c.scored for c in backend.children)


def test_coarse_levels_of_the_cpu_backend_scale_with_their_pixel_count():
    """The level switch assumes log p_b ≈ (s_b / s_a) log p_a between resolutions (levels.py): on the
    crest's rendered depth, over poses spread like the early tempering's (3 cm, 0.5 rad), each level's
    log-likelihood is 4x the coarser one's (a least-squares slope within 3.3-4.7) and follows it."""
    from app.config import load_config
    from app.filter.smc_init import make_levels
    from app.mesh import load_mesh, outward_wound, prepare_mesh
    from app.render.cpu_likelihood import CPULikelihoodBackend
    from app.sim.simulator import D415_640x480, DEFAULT_MESH

    config = load_config(None)
    mesh = prepare_mesh(load_mesh(DEFAULT_MESH), max_triangles=1000, center=False)
    camera = D415_640x480.resized(160, 120)
    backend = CPULikelihoodBackend(mesh.vertices, mesh.faces, camera, params=config.likelihood,
                                   cull_back_faces=outward_wound(mesh))
    T_camera_bone = se3.make_pose(quat.to_matrix(quat.exp_map(np.array([3.0, 0.1, 0.0]))), np.array([0.0, 0.0, 0.42]))
    rendered = backend.render_depth(T_camera_bone[None])[0]
    depth = np.where(rendered > 0, rendered, 0.6).astype(np.float32)
    levels = make_levels(backend, camera, depth, np.eye(4), ((4, 250), (2, 500)))
    assert [v.name for v in levels] == ["40x30", "80x60", "160x120"]
    rng = np.random.default_rng(0)
    q0, t0 = se3.to_quat_trans(T_camera_bone)
    p = t0 + rng.normal(0.0, 0.03, (200, 3))
    q = quat.normalize(quat.multiply(quat.exp_map(rng.normal(0.0, 0.5, (200, 3))), np.repeat(q0[None], 200, axis=0)))
    ll = [level.score(p, q) for level in levels]
    for coarse, fine in zip(ll[:-1], ll[1:]):
        a, b = coarse - coarse.mean(), fine - fine.mean()
        assert 3.3 < (a @ b) / (a @ a) < 4.7
        assert np.corrcoef(a, b)[0, 1] > 0.9


def test_the_end_at_the_filters_level_keeps_its_share_of_a_small_budget():
    """With coarse levels, the runs share max_evaluations less FINISH_SHARE of it, and the end at the
    filter's level gets that share from when it starts: a budget the run exhausts (a sharp likelihood,
    12,000 first draws of 20,000) must not reach the end spent (where φ would jump straight to 1)."""
    from app.filter.smc_init import OnePointInitialiser
    from app.filter.smc_init.initialiser import FINISH_SHARE

    box = trimesh.creation.box((0.06, 0.02, 0.01))
    T_base_bone = se3.make_pose(np.eye(3), np.array([0.0, 0.0, 0.3]))
    point = T_base_bone[:3, 3] + np.array([0.0, 0.0, 0.005])
    camera = PinholeCamera(np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]]), 64, 48)
    config = replace(SMCInitConfig(), restarts=1, prior_draws=12_000, sigma_n=0.0, symmetry_check=False,
                     surface_samples=500, max_evaluations=20_000, coarse_levels=((2, 1000),))
    backend = ScaledBackend(T_base_bone, camera, vertices=box.vertices, faces=box.faces, sharpness=3000.0)
    result = OnePointInitialiser(backend, camera, box.vertices, box.faces, config,
                                 np.random.default_rng(4)).run(np.zeros((48, 64), np.float32), np.eye(4), point)
    coarse_scored = sum(c.scored for c in backend.children)
    overshoot = 2 * config.mh_moves * config.particles
    assert coarse_scored <= (1 - FINISH_SHARE) * config.max_evaluations + overshoot
    assert backend.scored >= FINISH_SHARE * config.max_evaluations        # the end got its share
    assert result.evaluations == coarse_scored + backend.scored <= config.max_evaluations + 2 * overshoot
    # the coarse run ends at φ = 1, the end starts at φ = 1 x 768 / 3072 px = 0.25 and tempers by the
    # ESS rule (spent, it would jump from 0.25 straight to 1)
    start = result.phis.index(0.25)
    assert len(result.phis) - start >= 3 and 0.25 < result.phis[start + 1] < 1.0
    assert np.linalg.norm(result.estimate.T_base_bone[:3, 3] - T_base_bone[:3, 3]) < 0.005
