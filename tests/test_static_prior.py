"""The static-bone prior of the refinement's track (app/filter/static_prior.py).

Closed forms on a made-up information matrix (fast), and the scene it was built for (slow): a CT
crest under a hand rising to 80 % (static_occluded), where without the prior the refined track slid
along the crest and was lost on 46-62 % of the frames of crest_left_03 (BENCHMARKS.md §6c).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.filter.static_prior import StaticPrior, StaticPriorConfig, increment, log_increment
from app.geometry import se3
from app.tracking import levels

CENTER = np.array([0.01, -0.02, 0.03])
CLEAR_STD = 0.0006   # m, the predicted template error of a clear view (crest_left_03: 0.56 mm)


def _info(weak_axis_scale: float = 1.0) -> np.ndarray:
    """H of a view: rotations 1e6 / rad², translations 1e9 / m², x-translation scaled (a crest's long axis)."""
    H = np.diag([1e6, 1e6, 1e6, 1e9, 1e9, 1e9])
    H[3, 3] *= weak_axis_scale
    return H


def _moved(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    return T @ se3.inverse(increment(delta, CENTER))


def test_log_increment_inverts_increment_on_random_poses():
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = se3.from_rotvec_trans(rng.normal(0, 1, 3), rng.normal(0, 0.3, 3))
        delta = np.concatenate([rng.normal(0, 0.2, 3), rng.normal(0, 0.02, 3)])
        np.testing.assert_allclose(log_increment(T, _moved(T, delta), CENTER), delta, atol=1e-9)


def test_a_pull_along_an_unconstrained_direction_does_not_move_the_held_pose():
    prior = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    T0 = se3.from_rotvec_trans(np.array([0.1, 0.2, -0.3]), np.array([0.3, -0.1, 0.05]))
    for _ in range(200):   # clear frames at the same pose build the prior's information
        prior.update(T0, _info(), image_std=CLEAR_STD)
    pulled = _moved(T0, np.array([0, 0, 0, 0.008, 0, 0]))   # 8 mm along the axis the hand left unconstrained
    for _ in range(300):
        T = prior.update(pulled, _info(weak_axis_scale=1e-4), image_std=30 * CLEAR_STD)
        assert not prior.released
    assert se3.translation_distance(T, T0) < 1e-4, "the held pose slid with the image's pull"


def test_a_constrained_contradiction_releases_the_prior_at_once():
    prior = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    T0 = np.eye(4)
    for _ in range(100):
        prior.update(T0, _info(), image_std=CLEAR_STD)
    moved = _moved(T0, np.array([0, 0, 0, 0, 0.002, 0]))   # the bone moved 2 mm, the image sees it clearly
    # Δχ² = 0.002² 1e9 / 6 = 667 > 25
    T = prior.update(moved, _info(), image_std=1.2 * CLEAR_STD)
    assert prior.released
    np.testing.assert_allclose(T, moved, atol=1e-12)


def test_a_weak_frame_neither_releases_nor_moves_the_held_pose():
    prior = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    T0 = np.eye(4)
    for _ in range(100):
        prior.update(T0, _info(), image_std=CLEAR_STD)
    far = _moved(T0, np.array([0, 0, 0, 0, 0.002, 0]))
    T = prior.update(far, _info(), image_std=2.0 * CLEAR_STD)   # twice the clearest view's error: a hand
    assert not prior.released and prior.held
    np.testing.assert_allclose(T, T0)
    T = prior.update(far, _info(), image_std=1.4 * CLEAR_STD)   # clear again (<= 1.5x): released
    assert prior.released
    np.testing.assert_allclose(T, far, atol=1e-12)


def test_small_changes_are_fused_in_information_form():
    """One prior frame and one image frame of equal information: the fused pose lies half-way (closed form)."""
    prior = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    T0 = np.eye(4)
    prior.update(T0, _info(), image_std=CLEAR_STD)
    T = prior.update(_moved(T0, np.array([0, 0, 0, 0, 0, 1e-4])), _info(), image_std=CLEAR_STD)
    assert not prior.released
    np.testing.assert_allclose(log_increment(T0, T, CENTER), [0, 0, 0, 0, 0, 5e-5], atol=1e-9)


def _moving_bone(prior: StaticPrior, T0: np.ndarray, step: float, frames: int) -> list[float]:
    """A bone moving ``step`` m per frame along y, each frame's fit exactly at the bone (clear view):
    returns the anchor's lag behind the bone (m) per frame."""
    lags = []
    for k in range(1, frames + 1):
        bone = _moved(T0, np.array([0, 0, 0, 0, step * k, 0]))
        T = prior.update(bone, _info(), image_std=CLEAR_STD)
        lags.append(se3.translation_distance(T, bone))
    return lags


def test_a_bone_moving_in_small_steps_is_followed_not_fused():
    """0.1 mm a frame (9 mm/s at 90 Hz): each frame's Δχ² against the anchor (1.7 at the first step) is
    far under the release's 25, so without the motion test the anchor is fused behind the bone and lags
    until Δχ² > 25 (√(25 · 6 / 1e9) = 0.39 mm, closed form). The motion test compares the fit with the
    fit k clear frames ago in both fits' information, (H/6)/2: k · 0.1 mm > √(25 · 12 / 1e9) = 0.55 mm
    from the 6th moving frame on, and from then every frame is released onto the image's fit
    (crest_left_02 bone_moves seed 2: 3.49 mm after rest before, BENCHMARKS.md §6c)."""
    T0 = np.eye(4)
    lags = {}
    for frames in (0, 9):
        # the release's threshold as it was when the motion test was built (25; 4 now follows this bone by
        # its contradiction test alone, from a lag of 0.155 mm): the motion test must follow it even so
        prior = StaticPrior(StaticPriorConfig(release_chi2=25.0, motion_frames=frames), CENTER, inflation=6.0)
        for _ in range(100):
            prior.update(T0, _info(), image_std=CLEAR_STD)
        lags[frames] = _moving_bone(prior, T0, 1e-4, 40)
    assert max(lags[0][10:]) > 2e-4, "without the motion test the fused anchor lags the moving bone"
    assert max(lags[9][:5]) > 0 and max(lags[9][5:]) < 1e-9, "from the 6th moving frame the anchor is the image's fit"


def _starting_bone(release_chi2: float) -> tuple[list[float], list[float], list[bool]]:
    """A bone accelerating from rest along a constrained axis (each frame 0.01 mm farther than the last,
    up to 0.2 mm a frame: 0.9-18 mm/s at 90 Hz), every frame's fit exactly at the bone: the anchor's
    lag behind it, the prior's Δχ² and whether it released, per frame."""
    T0 = np.eye(4)
    prior = StaticPrior(StaticPriorConfig(release_chi2=release_chi2), CENTER, inflation=6.0)
    for _ in range(100):
        prior.update(T0, _info(), image_std=CLEAR_STD)
    lags, chi2, released, position = [], [], [], 0.0
    for k in range(1, 21):
        position += 1e-5 * k
        bone = _moved(T0, np.array([0, 0, 0, 0, position, 0]))
        T = prior.update(bone, _info(), image_std=CLEAR_STD)
        lags.append(se3.translation_distance(T, bone))
        chi2.append(prior.chi2)
        released.append(prior.released)
    return lags, chi2, released


def test_a_slowly_starting_bone_is_followed_and_a_held_lag_is_never_ok():
    """At the default release (25) the anchor is fused behind a bone starting to move slowly
    (crest_left_05 bone_moves: up to 1 mm while ok before the held-pose rule, BENCHMARKS.md §6f);
    every frame lagging more than 0.2 mm has Δχ² > 4 (closed form: δ² · 1e9 / 6 > 4 from δ =
    0.155 mm), which the status's held test (3.62 at status.alpha) does not let be ok. A release at 4
    (tried, not kept: §6f) follows the image's fit once it lies Δχ² > 4 away: the anchor never lags
    by more than a frame's step."""
    assert StaticPriorConfig().release_chi2 == 25.0
    lags, chi2, released = _starting_bone(StaticPriorConfig().release_chi2)
    lagging = [c for lag, c, r in zip(lags, chi2, released) if not r and lag > 2e-4]
    assert len(lagging) >= 3 and min(lagging) > 4.0
    lags, chi2, released = _starting_bone(4.0)
    assert any(released)
    assert all(lag < 2e-4 for lag in lags), lags                         # the largest step is 0.2 mm
    assert all(c <= 4.0 for c, r in zip(chi2, released) if not r)       # never held against the image


def test_at_rest_the_held_pose_chi2_stays_under_the_status_threshold():
    """Fits of a static bone scattered with the image's own covariance H⁻¹ (χ²₆ / 6 against the
    anchor): at most a few frames in 2,000 are over the status's held bound (χ²₆ at status.alpha / 6, 3.62;
    P ~ 0.135 %)."""
    rng = np.random.default_rng(5)
    std = 1.0 / np.sqrt(np.diag(_info()))
    rest = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    chi2 = []
    for _ in range(2000):
        rest.update(_moved(np.eye(4), rng.normal(0.0, std)), _info(), image_std=CLEAR_STD)
        chi2.append(rest.chi2)
    bound = levels.held_level(levels.ALPHA, 6.0)
    assert np.mean(np.array(chi2[100:]) > bound) < 0.005


def test_static_fits_scattered_by_the_images_own_noise_never_release():
    """Fits of a static bone scattered with the image's own covariance H⁻¹ (the inflation's 6 covers
    correlated pixels and model error on top): both tests' Δχ² are about χ²(6) / 6 (mean 1), P(> 25)
    ~ 1e-24: 1,000 frames never release and the anchor stays within the noise."""
    rng = np.random.default_rng(12)
    std = 1.0 / np.sqrt(np.diag(_info()))
    prior = StaticPrior(StaticPriorConfig(), CENTER, inflation=6.0)
    T0 = se3.from_rotvec_trans(np.array([0.1, 0.2, -0.3]), np.array([0.3, -0.1, 0.05]))
    released = 0
    for _ in range(1000):
        prior.update(_moved(T0, rng.normal(0.0, std)), _info(), image_std=CLEAR_STD)
        released += prior.released
    assert released == 1, "only the first frame starts the prior"
    assert se3.translation_distance(prior.T_base_bone, T0) < 2e-5


def test_the_motion_window_spans_clear_frames_only():
    """A weak frame (a hand) empties the window: the first clear frame after it cannot compare with a
    fit from before the hand (that contradiction is the anchor's own Δχ² test)."""
    # the release's old threshold, 25, so that the anchor's own test lets this 0.3 mm through (4 would release)
    prior = StaticPrior(StaticPriorConfig(release_chi2=25.0), CENTER, inflation=6.0)
    T0 = np.eye(4)
    for _ in range(20):
        prior.update(T0, _info(), image_std=CLEAR_STD)
    slid = _moved(T0, np.array([0, 0, 0, 0, 3e-4, 0]))   # Δχ² against the anchor 15 < 25; (0.3 mm)² 1e9/12 = 7.5
    prior.update(slid, _info(), image_std=3 * CLEAR_STD)
    assert prior.held and not np.isfinite(prior.motion_chi2)
    prior.update(slid, _info(), image_std=CLEAR_STD)
    assert not prior.released and not np.isfinite(prior.motion_chi2)


PELVIS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pelvis"


@pytest.mark.slow
@pytest.mark.skipif(not (PELVIS / "crest_left_03.ply").is_file(), reason=f"no CT crest meshes at {PELVIS}")
def test_ct_crest_is_held_under_an_80_percent_hand(tmp_path):
    """crest_left_03, static_occluded, seed 0, 5 s (the hand at 80 % from 4 s): before the prior the
    track slid along the crest (lost, ADD > 10 mm, from ~2.6 s: BENCHMARKS.md §6c); now held."""
    from app.config import load_config
    from app.metrics import DANGEROUS_ADD_MM, LOST_ADD_MM
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate

    simulate(tmp_path / "trial", mesh_path=PELVIS / "crest_left_03.ply", scenario_name="static_occluded",
             seconds=5.0, seed=0)
    result = replay(tmp_path / "trial", None, load_config(None), rrd=False, projector=False)
    add, statuses = np.asarray(result.errors["add_mm"]), np.asarray(result.statuses)
    print(f"\nADD median {np.median(add):.2f} mm, max {add.max():.2f}, ok {np.mean(statuses == 'ok'):.0%}")
    assert not np.any((statuses == "ok") & (add > DANGEROUS_ADD_MM))
    assert add.max() < LOST_ADD_MM / 2
    assert np.median(add) < 1.0


def test_a_stride_1_view_does_not_make_the_same_view_at_stride_2_weak(far_frame):
    """The prior's clear test compares views on one grid (refine_track.RefinedTrack._on_grid). The same image,
    refined first at stride 1 (a small silhouette: four times the points, about half the predicted
    error) and then at stride 2, is one view: the second frame must not be held as weak. Compared
    raw, crest_left_02 bone_moves (seed 0) was held 6.4 mm off after rest (BENCHMARKS.md §6c)."""
    from app.filter.refine import Refiner, RefineParams
    from app.filter.refine_track import RefineConfig, RefinedTrack
    from app.sim.simulator import D415_640x480

    vertices, faces, T_camera_bone, measured = far_frame
    fine = Refiner(vertices, faces, D415_640x480, RefineParams())
    coarse = Refiner(vertices, faces, D415_640x480, RefineParams(fine_below=0))
    assert fine.choose_stride(T_camera_bone)[0] == 1 and coarse.choose_stride(T_camera_bone)[0] == 2
    track = RefinedTrack(fine, RefineConfig(), vertices, inflation=6.0)
    T_base_camera = np.eye(4)
    track.seed(T_camera_bone)
    first = track.update(measured, T_base_camera, T_camera_bone)
    assert track.prior.active and np.isfinite(first.template_std)
    track.refiner = coarse          # the next frame's silhouette just above fine_below: stride 2
    second = track.update(measured, T_base_camera, T_camera_bone)
    assert second.template_std > 1.6 * first.template_std     # raw: the stride-2 H predicts ~2x the error
    assert not track.prior.held, track.last_info
    assert track.last_info["grid_std_mm"] < 1.5 * 1e3 * 2 * first.template_std


def _poor_then_clear(forget_ratio: float, poor_frames: int = 200) -> tuple[StaticPrior, np.ndarray, np.ndarray]:
    """``poor_frames`` frames of a view 4x poorer (H / 16, σ 4x) all fitting a pose 0.2 mm off along y
    (a view's bias: it does not average out), then one clear frame (H, σ) fitting the truth. Returns
    the prior, the truth and the biased pose."""
    prior = StaticPrior(StaticPriorConfig(forget_ratio=forget_ratio), CENTER, inflation=6.0)
    truth = np.eye(4)
    biased = _moved(truth, np.array([0, 0, 0, 0, 0.0002, 0]))
    for _ in range(poor_frames):
        prior.update(biased, _info() / 16.0, image_std=4 * CLEAR_STD)
    prior.update(truth, _info(), image_std=CLEAR_STD)
    return prior, truth, biased


def test_a_clearer_view_discounts_the_information_built_on_a_poorer_one():
    """Closed form (static_prior.py, "clear frame, the view improves"): Λ = 200 H/16 (/ inflation) is
    discounted by (σ/σ_b)² = 1/16 to 200/256 H, so the clear frame's fit moves the anchor
    1 / (1 + 200/256) of the way to it; without the discount 1 / (1 + 200/16) = 0.074 of the way. The
    Δχ² (0.2 mm, 1e9 / 6: 6.7) stays under 25: it is fused, not released."""
    for ratio, share in ((2.0, 1.0 / (1.0 + 200.0 / 256.0)), (0.0, 1.0 / (1.0 + 200.0 / 16.0))):
        prior, truth, biased = _poor_then_clear(ratio)
        assert not prior.released and prior.discounted == (ratio > 0)
        moved = log_increment(biased, prior.T_base_bone, CENTER)
        np.testing.assert_allclose(moved, [0, 0, 0, 0, -0.0002 * share, 0], atol=1e-10)


def test_the_discount_needs_the_view_to_improve_by_the_ratio():
    """A clear view fluctuating within the clear test (σ 0.8-1.2x the first) never discounts Λ: the
    information is the plain sum (a static bone under a steady view averages every frame); a view
    improving step by step discounts at each halving of σ_b only (4σ -> 2σ -> σ)."""
    prior = StaticPrior(StaticPriorConfig(forget_ratio=2.0), CENTER, inflation=6.0)
    rng = np.random.default_rng(5)
    for _ in range(100):
        prior.update(np.eye(4), _info(), image_std=CLEAR_STD * rng.uniform(0.8, 1.2))
        assert not prior.discounted
    np.testing.assert_allclose(prior.information, 100 * _info() / 6.0, rtol=1e-12)
    prior = StaticPrior(StaticPriorConfig(forget_ratio=2.0), CENTER, inflation=6.0)
    stds = np.linspace(4.0, 1.0, 31) * CLEAR_STD
    fired = []
    for std in stds:
        prior.update(np.eye(4), _info() * (CLEAR_STD / std) ** 2, image_std=std)
        fired.append(prior.discounted)
    first_half = int(np.argmax(stds <= 2.0 * CLEAR_STD * (1 + 1e-9)))   # the first σ <= 4σ / 2
    assert sum(fired) == 2 and fired.index(True) == first_half, fired
    assert fired[-1]   # σ = CLEAR_STD: half the basis 2σ set by the first discount


def test_a_stride_1_fit_enters_the_prior_with_a_quarter_of_its_information(far_frame):
    """RefinedTrack._on_grid: the prior counts a stride-1 fit's H on the configured stride-2 grid,
    H · (1/2)² (correlated full-resolution pixels; the calibration of BENCHMARKS.md §6: inflation
    12.7 at stride 1 against 2.9 at stride 2 for 90 % coverage); a stride-2 fit as it is."""
    from app.filter.refine import Refiner, RefineParams
    from app.filter.refine_track import RefineConfig, RefinedTrack
    from app.sim.simulator import D415_640x480

    vertices, faces, T_camera_bone, measured = far_frame
    fine = Refiner(vertices, faces, D415_640x480, RefineParams())
    result = fine.refine(measured, T_camera_bone)
    assert result.stride == 1
    track = RefinedTrack(fine, RefineConfig(), vertices, inflation=6.0)
    grid_H, grid_std = track._on_grid(result, 0.001)
    np.testing.assert_allclose(grid_H, result.H / 4.0, rtol=1e-12)
    assert grid_std == pytest.approx(0.002, rel=1e-12)           # σ_grid = σ stride_grid / stride
    coarse = Refiner(vertices, faces, D415_640x480, RefineParams(fine_below=0))
    result2 = coarse.refine(measured, T_camera_bone)
    assert result2.stride == 2
    grid_H2, grid_std2 = RefinedTrack(coarse, RefineConfig(), vertices, 6.0)._on_grid(result2, 0.001)
    np.testing.assert_allclose(grid_H2, result2.H)
    assert grid_std2 == 0.001


@pytest.mark.slow
@pytest.mark.skipif(not (PELVIS / "crest_left_02.ply").is_file(), reason=f"no CT crest meshes at {PELVIS}")
def test_ct_crest_moved_at_5_cm_s_is_back_within_1_mm_after_rest(tmp_path):
    """crest_left_02, bone_moves, seed 2 (4.5 s, at rest from ~3.5 s): before the motion test the prior
    fused the lagging fits of the move and held the bone 3.49 mm off after rest (BENCHMARKS.md §6c);
    issue 12's target is 1 mm from 0.3 s after rest."""
    from app.bench.scoring import after_rest
    from app.config import load_config
    from app.metrics import DANGEROUS_ADD_MM
    from app.pipeline.replay import replay
    from app.sim.simulator import simulate
    from app.trial.reader import open_trial

    simulate(tmp_path / "trial", mesh_path=PELVIS / "crest_left_02.ply", scenario_name="bone_moves",
             seconds=4.5, seed=2)
    result = replay(tmp_path / "trial", None, load_config(None), rrd=False, projector=False)
    add, statuses = np.asarray(result.errors["add_mm"]), np.asarray(result.statuses)
    rest = after_rest(open_trial(tmp_path / "trial").groundtruth, result.stamps, add)
    print(f"\nADD median {np.median(add):.2f} mm, p95 {np.percentile(add, 95):.2f}, after rest max {rest['max_add_mm']:.2f}")
    assert not np.any((statuses == "ok") & (add > DANGEROUS_ADD_MM))
    assert rest["max_add_mm"] < 1.0
