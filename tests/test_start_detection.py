"""Start without a pose (issue 33): the detector (app/tracking/detector.py), ``init.method: auto``'s
choice of start, a point-only trial replayed with the defaults, and the detected start's confirmation.

The CT-crest frames are simulated (app/sim, ``static_clear``) on the first crest of
../shared/data/pelvis; a test skips when that folder is absent. Work is counted, never timed.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from app import metrics
from app.filter.recovery import RecoveryConfig, RecoveryPolicy
from app.filter.status import TrackingStatus
from app.pipeline.tracker import start_method

POINT_OFF_M = 0.003


def _cpu_config():
    from app.config import load_config

    return replace(load_config(None), backend="cpu")


@pytest.fixture(scope="module")
def crest_trial(tmp_path_factory):
    """A short static_clear trial of the first CT crest (0.3 s), or a skip without the shared meshes."""
    from app.sim.simulator import simulate
    from tests.conftest import PELVIS_DIR, pelvis_meshes

    meshes = pelvis_meshes()
    if not meshes:
        pytest.skip(f"real pelvis meshes not found in {PELVIS_DIR}")
    base = tmp_path_factory.mktemp("start")
    simulate(base / "trial", mesh_path=meshes[0], scenario_name="static_clear", seconds=0.3, seed=3)
    return base / "trial"


@pytest.fixture(scope="module")
def crest_frame(crest_trial):
    """(tracker, depth small, depth full, T_base_camera, truth, the simulated crest-top point) of frame 0."""
    from app.depth_image import downsample_nearest
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    reader = open_trial(crest_trial)
    config = _cpu_config()
    tracker = DepthTracker(config, reader.load_mesh(), reader.meta.camera)
    tracker.trial_reader = reader
    T_base_camera, _ = reader.camera_poses()
    depth = reader.read_depth(0)
    yield (tracker, downsample_nearest(depth, *config.resolution), depth, T_base_camera[0],
           np.asarray(reader.groundtruth[0]), np.asarray(reader.meta.point_prior))
    tracker.release()


def test_the_search_detector_finds_a_ct_crest_within_1_mm_from_a_point_3_mm_off(crest_frame):
    """A point 3 mm off the crest's top, no pose: the wide search around it, verified by the
    refinement, finds the truth within 1 mm, within the start's budget of work (init.detector_*).
    The simulator's seed 3 tilts this crest's top 21 deg from up: found only with the tilted starts
    (StartSearch.tilt_rad), for three points."""
    from app.sim.point_start import offset_point
    from app.tracking.detector import SearchDetector

    tracker, small, depth, T_base_camera, T_true, top = crest_frame
    assert np.degrees(np.arccos(T_true[2, 2])) > 20.0          # the view this test is about: a tilted crest
    start = tracker.config.detector
    for seed in (4, 6, 7):
        point = offset_point(top, POINT_OFF_M, np.random.default_rng(seed))
        assert abs(np.linalg.norm(point - top) - POINT_OFF_M) < 1e-9
        detector = SearchDetector(tracker.wide_search, np.random.default_rng(seed + 1), start)
        found = detector.detect(small, depth, T_base_camera, point)
        assert found is not None
        assert 1e3 * metrics.add(found.T_base_bone, T_true, tracker.mesh_vertices) < 1.0
        assert found.score >= tracker.wide_search.config.min_sharp and found.fitness >= 0.6
        assert 0 < found.evaluations <= start.evaluations
        assert 0 < found.refinements <= 5 * start.refine_top


def test_tilt_rotations_tilt_the_bones_top_by_the_angle_towards_evenly_spaced_directions():
    """R_k = exp(θ [cos b_k, sin b_k, 0]^): R_k z makes the angle θ with z, its horizontal part points
    along b_k + 90 deg (a turn about an axis in the xy plane), and 0 directions or θ = 0 gives none."""
    from app.tracking.detector import BONE_TOP, tilt_rotations

    theta = np.radians(15.0)
    rotations = tilt_rotations(theta, 6)
    assert len(rotations) == 6 and tilt_rotations(0.0, 6) == () and tilt_rotations(theta, 0) == ()
    for k, R in enumerate(rotations):
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        top = R @ BONE_TOP
        assert np.degrees(np.arccos(top[2])) == pytest.approx(15.0, abs=1e-9)
        b = 2.0 * np.pi * k / 6
        np.testing.assert_allclose(top[:2] / np.linalg.norm(top[:2]), [np.sin(b), -np.cos(b)], atol=1e-12)


def test_the_anchored_hypotheses_put_each_ridge_point_on_each_anchor_at_each_yaw_and_scatter_as_drawn():
    """WideSearch._anchored (one batch): hypothesis (anchor a, yaw ψ, ridge point r) is q = exp(ψ up) ⊗ q_ok,
    p = a − R(q) r (the ridge point r lands on a), in that order, each first of its ``per_hypothesis``;
    its draws, turned about the centroid (the bone frame's origin here), scatter p by ANCHOR_SIGMA_M."""
    from app.filter.wide_search import ANCHOR_SIGMA_M, UP_BASE, SearchConfig, WideSearch, ridge_points
    from app.geometry import quaternion as quat

    rng = np.random.default_rng(0)
    vertices = rng.normal(0.0, 0.03, (300, 3))
    vertices -= vertices.mean(axis=0)          # the centroid at the origin: a turn about it leaves p0 in place
    search = WideSearch(None, None, None, vertices, SearchConfig())
    T = np.eye(4)
    T[:3, :3] = quat.to_matrix(quat.exp_map(np.array([0.2, -0.1, 0.5])))
    anchors = rng.normal(0.0, 0.1, (3, 3))
    p, q = search._anchored(anchors, T, 1, np.random.default_rng(1))
    ridge = ridge_points(vertices, T[:3, :3])
    k = 0
    for a in anchors:
        for step in range(search.config.yaw_steps):
            R = quat.to_matrix(quat.exp_map(2.0 * np.pi * step / search.config.yaw_steps * UP_BASE)) @ T[:3, :3]
            for r in ridge:
                np.testing.assert_allclose(quat.to_matrix(q[k]), R, atol=1e-12)
                np.testing.assert_allclose(p[k] + R @ r, a, atol=1e-12)
                k += 1
    assert k == len(p) == len(q)
    p_draws, _ = search._anchored(anchors, T, 50, np.random.default_rng(2))
    hypotheses = p_draws.reshape(-1, 50, 3)
    np.testing.assert_allclose(hypotheses[:, 0], p, atol=1e-15)
    scatter = hypotheses[:, 1:] - hypotheses[:, :1]
    # turned about the centroid, which is the bone frame's origin here: p' - p0 = ε ~ N(0, ANCHOR_SIGMA_M² I)
    assert np.mean(scatter) == pytest.approx(0.0, abs=0.05 * ANCHOR_SIGMA_M)
    assert np.std(scatter) == pytest.approx(ANCHOR_SIGMA_M, rel=0.03)


def test_the_search_detector_declines_a_point_over_an_empty_table(crest_frame):
    """Nothing but a flat table in the image: nothing confirmed, no pose (the start keeps waiting)."""
    from app.depth_image import downsample_nearest
    from app.tracking.detector import SearchDetector

    tracker, _, depth, T_base_camera, _, top = crest_frame
    table = np.full_like(depth, 0.45)
    detector = SearchDetector(tracker.wide_search, np.random.default_rng(5))
    assert detector.detect(downsample_nearest(table, *tracker.config.resolution), table, T_base_camera, top) is None
    assert detector.last_work[0] > 0


def test_a_detectors_prior_of_another_shape_is_refused_with_the_shapes_accepted():
    from app.tracking.detector import prior_kind

    assert prior_kind(None) == "none" and prior_kind(np.zeros(3)) == "point" and prior_kind(np.eye(4)) == "pose"
    with pytest.raises(ValueError, match="3 finite numbers"):
        prior_kind(np.zeros(2))


def test_init_method_auto_takes_the_pose_then_the_point_then_the_whole_image():
    pose, point = np.eye(4), np.zeros(3)
    assert start_method("auto", pose, point) == "pose"
    assert start_method("auto", None, point) == "detect"
    assert start_method("auto", None, None) == "detect"
    assert start_method("point", pose, point) == "point" and start_method("pose", None, point) == "pose"


def test_auto_is_the_default_and_starts_a_depth_tracker_by_what_it_is_given(crest_frame):
    """The tracker's own start under the default: a pose spreads the particles (no detection pending);
    a point makes the detector pending from that point; nothing makes it pending over the whole image."""
    from app.config import load_config
    from app.pipeline.tracker import DepthTracker, start_tracker

    assert load_config(None).init_method == "auto"
    tracker, _, _, _, T_true, top = crest_frame
    reader = tracker.trial_reader
    fresh = DepthTracker(tracker.config, reader.load_mesh(), reader.meta.camera)
    try:
        start_tracker(fresh, T_true, top)
        assert fresh.start_report is None
        start_tracker(fresh, None, top)
        assert fresh.start_report["method"] == "detect_point" and fresh._start_detection.pending
        np.testing.assert_allclose(fresh._start_detection.point, top)
        start_tracker(fresh, None, None)
        assert fresh.start_report["method"] == "detect_whole_image"
    finally:
        fresh.release()
    no_search = replace(tracker.config, recovery=replace(tracker.config.recovery, search=False))
    fresh = DepthTracker(no_search, reader.load_mesh(), reader.meta.camera)
    try:                                    # the recovery without its search: the start builds one alike
        assert fresh.wide_search is None
        start_tracker(fresh, None, top)
        assert fresh._start_detection.detector.search.config.evaluations == no_search.recovery.search_evaluations
    finally:
        fresh.release()


def test_a_point_only_trial_replays_with_the_defaults_found_at_once_and_not_ok_before_confirmed(crest_trial, tmp_path):
    """No initial_pose, a point 3 mm off: replay with the default configuration (it refused before)
    starts by the detector on the first frame, tracks within 1 mm, and is not ok on these few frames:
    a detected start is ok only after the recovery's confirm_frames (90) weighed frames found ok."""
    import shutil

    from app.pipeline.replay import replay
    from app.sim.point_start import make_point_only

    trial = tmp_path / "point_only"
    shutil.copytree(crest_trial, trial)
    make_point_only(trial, POINT_OFF_M, np.random.default_rng(6))
    result = replay(trial, None, _cpu_config(), rrd=False, projector=False, max_frames=6)
    start = result.summary["start"]
    assert start["found"] and start["attempts"] == 1 and start["found_stamp"] == pytest.approx(result.stamps[0])
    assert np.max(result.errors["add_mm"]) < 1.0
    assert "ok" not in result.statuses and "lost" not in result.statuses
    from app.pipeline.report import summary_rows

    assert "detector from the point: found on the frame stamped" in dict(summary_rows(result.summary))["start"]


def test_replay_with_init_method_pose_and_no_pose_names_the_key_and_the_fix(crest_trial, tmp_path):
    import shutil

    from app.errors import TrialFormatError
    from app.pipeline.replay import replay
    from app.sim.point_start import make_point_only

    trial = tmp_path / "point_only"
    shutil.copytree(crest_trial, trial)
    make_point_only(trial, POINT_OFF_M, np.random.default_rng(6))
    with pytest.raises(TrialFormatError, match="init.method 'pose' needs 'initial_pose'.*'auto'"):
        replay(trial, None, replace(_cpu_config(), init_method="pose"), rrd=False, projector=False)


def test_a_detected_start_is_ok_only_after_confirm_frames_found_ok_at_it():
    """RecoveryPolicy.set_found_start: agreeing with the start pose is no evidence (it is the
    hypothesis); the rules must find confirm_frames weighed frames in a row ok. A frame not ok
    restarts the count. A coarse start (set_start) is ok at once, as before."""
    T = np.eye(4)
    config = RecoveryConfig(confirm_frames=5)
    policy = RecoveryPolicy(config, np.zeros(3), np.zeros(3), refine_enabled=True)
    policy.set_found_start(T)
    out = [policy.update(TrackingStatus.OK, True, True, 0.9, T, 0.01 * k, sharp=0.8) for k in range(3)]
    out.append(policy.update(TrackingStatus.UNCERTAIN, True, True, 0.9, T, 0.03, sharp=0.8))
    out += [policy.update(TrackingStatus.OK, True, True, 0.9, T, 0.04 + 0.01 * k, sharp=0.8) for k in range(6)]
    assert out[:4] == [TrackingStatus.UNCERTAIN] * 4
    assert out[4:8] == [TrackingStatus.UNCERTAIN] * 4 and out[8] == TrackingStatus.OK and out[9] == TrackingStatus.OK
    assert policy.capped == ""
    coarse = RecoveryPolicy(config, np.zeros(3), np.zeros(3), refine_enabled=True)
    coarse.set_start(T)
    assert coarse.update(TrackingStatus.OK, True, True, 0.9, T, 0.0, sharp=0.8) == TrackingStatus.OK


def test_the_smc_detector_reports_a_pose_only_when_the_refinement_confirms_it(crest_frame):
    """The one-point SMC behind the same interface, its pose verified as a wide-search candidate (two
    chains: 5 refinements). On a CT crest its weighted mean lies far off (the known failure,
    app/filter/smc_init/); such a pose is declined, never returned as found; a returned one is right."""
    from app.filter.smc_init import smc_config_for
    from app.tracking.detector import SMCDetector

    tracker, small, depth, T_base_camera, T_true, top = crest_frame
    smc = smc_config_for(tracker.config, max_evaluations=3000, prior_draws=1000, restarts=1)
    detector = SMCDetector(tracker.backend, tracker.camera, tracker.mesh_vertices, tracker.mesh_faces, smc,
                           tracker.wide_search, np.random.default_rng(0))
    found = detector.detect(small, depth, T_base_camera, top)
    evaluations, refinements = detector.last_work
    assert evaluations == detector.last_result.evaluations > 0 and refinements == 5
    smc_add = 1e3 * metrics.add(detector.last_result.estimate.T_base_bone, T_true, tracker.mesh_vertices)
    if found is None:
        assert smc_add > 2.0
    else:
        assert 1e3 * metrics.add(found.T_base_bone, T_true, tracker.mesh_vertices) < 1.0


class _Declining:
    """A detector that finds nothing on its first ``misses`` calls, then a fixed pose (10 evaluations,
    2 refinements a call): the start's retry rule is under test, not a detector."""

    strategy = "fake"

    def __init__(self, misses: int):
        self.misses, self.calls, self.last_work = misses, 0, (0, 0)

    def detect(self, depth_small, depth_m, T_base_camera, prior):
        from app.tracking.detector import Detection

        self.calls += 1
        self.last_work = (10, 2)
        if self.calls <= self.misses:
            return None
        return Detection(np.eye(4), 0.8, 0.9, 10, 2, "fake")


def test_a_start_that_finds_nothing_is_retried_after_search_retry_s_and_counts_every_attempt():
    from app.tracking.start import StartByDetection

    period = 1.0 / 90.0
    start = StartByDetection(_Declining(misses=2), np.zeros(3), retry_s=30 * period)
    found_at = None
    for k in range(200):
        if start.attempt(None, None, np.eye(4), k * period) is not None:
            found_at = k * period
            break
    assert start.detector.calls == 3 and not start.pending
    assert found_at == pytest.approx(2 * 30 * period, abs=period)       # recovery.search_retry_s, as given
    report = start.report()
    assert report["attempts"] == 3 and report["evaluations"] == 30 and report["refinements"] == 6
    assert report["found"] and report["found_stamp"] == pytest.approx(found_at) and report["method"] == "detect_point"
    assert start.attempt(None, None, np.eye(4), 10.0) is None and start.detector.calls == 3   # found: no more attempts


def test_a_point_start_that_finds_nothing_reports_lost_initialising_frames_and_does_not_fail(crest_trial, tmp_path):
    """A point 30 cm beside the bone (out of the image): the detector confirms nothing on the first
    frame; the frames until its retry are lost and 'initialising' (no particles yet), the replay goes on."""
    import shutil

    from app.pipeline.replay import replay
    from app.sim.point_start import make_point_only
    from app.trial.meta import dump_meta, load_meta

    trial = tmp_path / "far_point"
    shutil.copytree(crest_trial, trial)
    make_point_only(trial, 0.0, np.random.default_rng(7))
    meta = load_meta(trial / "trial.yaml")
    meta.point_prior = meta.point_prior + np.array([0.3, 0.0, 0.0])
    dump_meta(meta, trial / "trial.yaml")
    result = replay(trial, None, _cpu_config(), rrd=False, projector=False, max_frames=4)
    start = result.summary["start"]
    assert not start["found"] and start["attempts"] == 1 and start["evaluations"] > 0
    assert set(result.statuses) == {"lost"}


def test_a_live_start_detects_on_the_worker_while_the_frames_go_on(crest_trial):
    """recovery.search_worker thread (a live session's): the detector runs on the search worker; the
    frames meanwhile are lost, 'initialising', never ok; the first frame after the worker finished
    takes its pose (within 1 mm of the truth), and the start's report counts that one attempt. No wall
    time: the test waits for the worker, never for a clock."""
    from app.pipeline.tracker import DepthTracker
    from app.trial.reader import open_trial

    reader = open_trial(crest_trial)
    config = _cpu_config()
    config = replace(config, recovery=replace(config.recovery, search_worker="thread"))
    mesh = reader.load_mesh()
    tracker = DepthTracker(config, mesh, reader.meta.camera)
    tracker.start_by_detection(np.asarray(reader.meta.point_prior))
    worker = tracker._start_detection.worker
    assert worker is tracker.recovery_runner.worker and worker is not None
    assert tracker._start_detection.retry_s == config.recovery.search_retry_s     # the retry from the config
    T_base_camera, valid = reader.camera_poses()
    frames = list(reader.iter_frames())
    first = tracker.process(frames[0].depth_m, frames[0].stamp, T_base_camera[0])     # hands the detection over
    assert worker.in_flight and first.state == "initialising" and first.status == "lost"
    worker._future.result()                                                            # the worker finishes
    taken = tracker.process(frames[1].depth_m, frames[1].stamp, T_base_camera[1])
    points = np.asarray(mesh.vertices)
    from app import metrics

    assert not tracker._start_detection.pending and taken.state == "confirming" and taken.status != "ok"
    assert 1e3 * metrics.add(taken.T_base_bone, reader.groundtruth[1], points) < 1.0
    report = tracker.start_report
    assert report["found"] and report["attempts"] == 1 and report["found_stamp"] == pytest.approx(frames[1].stamp)
    tracker.release()


class _Landscape:
    """A likelihood over the bone's position alone (rotations ignored): a narrow peak of 400 at the
    truth (the origin; 100 at 6 mm) and a broad ridge of wrong poses 75 mm away (200-330, never above 340)."""

    def score(self, p, q):
        d = np.linalg.norm(p, axis=1)
        truth = 400.0 - 300.0 * (d / 0.006) ** 2
        wrong = 330.0 - 2000.0 * np.abs(p[:, 1] - 0.075) - 0.2 * np.abs(1e3 * p[:, 0]) + 10.0 * np.cos(40.0 * p[:, 0])
        return np.maximum(truth, np.minimum(wrong, 340.0))


def _landscape_search(screened: int):
    from app.filter.wide_search import SearchConfig
    from app.tracking.detector import PriorSearch

    vertices = np.random.default_rng(0).normal(0.0, 0.03, (200, 3))
    vertices -= vertices.mean(axis=0)            # the centroid at the origin: draws turn about it, p stays
    search = PriorSearch(None, None, None, vertices, SearchConfig(evaluations=8000, clusters=12, refine_top=8))
    search.screened = screened
    # 40 hypotheses along the wrong ridge (15 mm apart) and one 6 mm from the truth, ranked last
    p = np.vstack([np.column_stack([np.linspace(-0.3, 0.3, 40), np.full(40, 0.075), np.zeros(40)]), [[0.006, 0, 0]]])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(p), 1))
    ll = _Landscape().score(p, q)
    assert np.argsort(-ll)[-1] == 40                      # the truth's neighbour scores below every wrong one
    return search, p, q, ll


@pytest.mark.parametrize("screened", [0, 60])
def test_the_start_s_screening_round_lifts_a_hypothesis_near_the_truth_above_a_wrong_family(screened):
    """PriorSearch._search_locally (successive halving): every one of the ``screened`` best distinct
    hypotheses gets one round of draws, and the clusters are the best of the screened. A hypothesis 6 mm
    from a narrow peak, ranked below 40 of a broad wrong ridge, is lifted into the clusters and its local
    search reaches the peak; without the round (screened 0: the recovery's local search) the ten
    clusters are all on the ridge. The budget is the configured evaluations, every round as many draws."""
    search, p, q, ll = _landscape_search(screened)
    evaluations0 = 3360
    found, evaluations = search._search_locally(_Landscape(), p, q, ll, np.array(["image"] * len(p)), evaluations0,
                                                np.random.default_rng(7))
    clusters = found["image"]
    assert len(clusters) == 10 and found["track"] == []
    assert evaluations <= search.config.evaluations
    nearest = min(np.linalg.norm(c[1]) for c in clusters)
    best = max(clusters, key=lambda c: c[0])
    if screened:
        per_round = (8000 - evaluations0) // (41 + 10 * 2)      # 41 hypotheses screened, 10 clusters x 2 rounds
        assert evaluations == evaluations0 + per_round * (41 + 20)
        assert nearest < 0.001 and best[0] > 390.0 and np.linalg.norm(best[1]) < 0.001
    else:
        assert nearest > 0.05 and best[0] <= 340.0


def test_the_start_s_verification_chains_are_chosen_by_name_and_a_bad_name_is_refused(tmp_path):
    """init.detector_chains: 'wide' verifies a start's candidates with the wide search's first chain alone
    (2 refinements each), 'both' with the recovery's two (5); another name names the key and the choices."""
    from app.config import load_config
    from app.errors import ConfigError
    from app.filter.wide_search import VERIFY_CHAINS, SearchConfig, WideSearch
    from app.tracking.detector import SearchDetector, StartSearch

    search = WideSearch(None, None, None, np.zeros((4, 3)), SearchConfig())
    wide = SearchDetector(search, np.random.default_rng(0), StartSearch(chains="wide")).prior_search
    both = SearchDetector(search, np.random.default_rng(0), StartSearch(chains="both")).prior_search
    assert wide.verify_chains == VERIFY_CHAINS[:1] and both.verify_chains == VERIFY_CHAINS
    assert search.verify_chains == VERIFY_CHAINS                       # the recovery's own search keeps both
    assert load_config(None).detector.chains == "wide"
    path = tmp_path / "bad.yaml"
    path.write_text("init:\n  detector_chains: narrow\n")
    with pytest.raises(ConfigError, match=r"init\.detector_chains.*wide"):
        load_config(path)
