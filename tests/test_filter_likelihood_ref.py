"""The numpy reference observation model: hand-worked pixels, invalid and uncovered pixels, the
options, and (B) eq. 4.33's closed form against a numerical convolution."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from app.filter import likelihood_ref as lr

P = lr.LikelihoodParams()


def one_pixel(z, z_star, params=P):
    return float(lr.log_likelihood(np.array([[z]], np.float32), np.array([[[z_star]]], np.float32), params)[0])


def normal_pdf(z, mu, s):
    return math.exp(-0.5 * ((z - mu) / s) ** 2) / (s * math.sqrt(2 * math.pi))


def hand_sigma(z_star):
    return 0.0011 * z_star**2 + 0.001


def test_hit_in_front_and_behind_match_hand_computed_values():
    zs = float(np.float32(0.5))
    for z in (0.5003, 0.4, 0.6):
        z = float(np.float32(z))
        s = hand_sigma(zs)
        p_e = math.log(2) * math.exp(-math.log(2) * z) / (1 - math.exp(-math.log(2) * zs)) if z < zs else 0.0
        expected = math.log(0.05 / 2.0 + 0.15 * p_e + 0.8 * normal_pdf(z, zs, s))
        assert one_pixel(z, zs) == pytest.approx(expected, rel=1e-12)


def test_invalid_and_out_of_range_measurements_are_outliers():
    expected = math.log(0.05 / 2.0)
    for z in (0.0, np.nan, np.inf, -np.inf, 2.5, -0.3):
        assert one_pixel(z, 0.5) == pytest.approx(expected)


def test_uncovered_pixels_contribute_zero():
    depth = np.array([[0.5, 0.0], [np.nan, 3.0]], np.float32)
    rendered = np.zeros((3, 2, 2), np.float32)
    np.testing.assert_array_equal(lr.log_likelihood(depth, rendered, P), 0.0)
    rendered[1, 0, 0] = 0.5
    values = lr.log_likelihood(depth, rendered, P)
    assert values[0] == 0.0 and values[2] == 0.0
    assert values[1] == pytest.approx(one_pixel(0.5, 0.5))


def test_sum_over_pixels_and_particles(rng):
    depth = rng.uniform(0.3, 0.7, (6, 8)).astype(np.float32)
    rendered = np.where(rng.random((4, 6, 8)) < 0.6, rng.uniform(0.3, 0.7, (4, 6, 8)), 0).astype(np.float32)
    values = lr.log_likelihood(depth, rendered, P)
    for j in range(4):
        expected = sum(one_pixel(depth[v, u], rendered[j, v, u]) for v in range(6) for u in range(8))
        assert values[j] == pytest.approx(expected, rel=1e-10)


def test_the_true_depth_scores_higher_than_a_shifted_one(rng):
    depth = rng.uniform(0.4, 0.5, (10, 10)).astype(np.float32)
    rendered = np.stack([depth, depth + 0.01, depth - 0.01]).astype(np.float32)
    values = lr.log_likelihood(depth, rendered, P)
    assert values[0] > values[1] and values[0] > values[2]
    # in front of the bone is explained by occlusion, behind it is not: shifting the model back
    # (measurements in front) costs less than shifting it forward
    assert values[1] > values[2]


def test_log_floor_bounds_every_pixel():
    params = replace(P, w_u=0.0, w_e=0.0)
    assert one_pixel(1.9, 0.3, params) == pytest.approx(math.log(lr.LOG_FLOOR))


@pytest.mark.parametrize("z_star,sigma", [(0.5, 0.02), (0.4, 0.004), (1.2, 0.05)])
def test_smooth_exponential_equals_the_numerical_convolution(z_star, sigma):
    lam = math.log(2)
    params = replace(P, occlusion="smooth_exponential")
    x = np.linspace(0.0, z_star, 400_001)
    trunc = lam * np.exp(-lam * x) / (1 - math.exp(-lam * z_star))
    for z in (0.01, 0.2, z_star - 2 * sigma, z_star, z_star + sigma, z_star + 4 * sigma):
        kernel = np.exp(-0.5 * ((z - x) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))
        numeric = np.trapezoid(trunc * kernel, x)
        closed = float(lr.occlusion_density(np.array(z), np.array(z_star), np.array(sigma), params))
        assert closed == pytest.approx(numeric, rel=1e-6, abs=1e-12)


def test_smooth_exponential_tends_to_the_truncated_one_away_from_the_surface():
    smooth = replace(P, occlusion="smooth_exponential")
    for z in (0.2, 0.35):
        assert one_pixel(z, 0.5, smooth) == pytest.approx(one_pixel(z, 0.5), rel=1e-6)


def test_erfc_matches_the_standard_library():
    xs = np.concatenate([np.linspace(-6, 6, 1201), [-30.0, -10.0, 10.0, 26.0, 0.0, 1.4999, 1.5, 2.9999, 3.0]])
    ours = lr.erfc(xs)
    ref = np.array([math.erfc(v) for v in xs])
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-300)


def test_classification_picks_the_larger_term_and_charges_background_pixels():
    params = replace(P, classification=True, l0_weight=2.0)
    zs = float(np.float32(0.5))
    hit = float(np.float32(0.5002))
    assert one_pixel(hit, zs, params) == pytest.approx(math.log(0.8 * normal_pdf(hit, zs, hand_sigma(zs))))
    front = float(np.float32(0.3))
    p_e = math.log(2) * math.exp(-math.log(2) * front) / (1 - math.exp(-math.log(2) * zs))
    assert one_pixel(front, zs, params) == pytest.approx(math.log(0.025 + 0.15 * p_e) - 2.0)
    assert one_pixel(0.0, zs, params) == pytest.approx(math.log(0.025) - 2.0)


def test_pixel_count_regularisation_averages_over_covered_pixels(rng):
    depth = rng.uniform(0.4, 0.5, (5, 5)).astype(np.float32)
    rendered = np.zeros((2, 5, 5), np.float32)
    rendered[0, :2] = depth[:2]
    rendered[1, :4] = depth[:4]
    plain = lr.log_likelihood(depth, rendered, P)
    reg = lr.log_likelihood(depth, rendered, replace(P, pixel_count_reg=30.0))
    np.testing.assert_allclose(reg, 30.0 * plain / np.array([10, 20]))
    assert lr.log_likelihood(depth, np.zeros((1, 5, 5), np.float32), replace(P, pixel_count_reg=30.0))[0] == 0.0


def test_inlier_mask_uses_three_sigma_on_valid_covered_pixels():
    z_star = np.full((1, 1, 4), 0.5, np.float32)
    s = hand_sigma(0.5)
    depth = np.array([[0.5 + 2 * s, 0.5 + 4 * s, 0.0, np.nan]], np.float32)
    np.testing.assert_array_equal(lr.inlier_mask(depth, z_star, P)[0, 0], [True, False, False, False])


def test_an_unknown_occlusion_model_is_rejected():
    with pytest.raises(ValueError, match="exponential, smooth_exponential"):
        one_pixel(0.4, 0.5, replace(P, occlusion="gaussian"))


def test_mismatched_shapes_are_rejected():
    with pytest.raises(ValueError, match="rendered depth must be"):
        lr.log_likelihood(np.zeros((4, 5), np.float32), np.zeros((2, 5, 4), np.float32), P)


def test_background_ratio_makes_occluders_and_invalid_pixels_neutral_and_see_through_negative():
    """Closed forms of the ratio mode: hit log(w_n p_n z_max + ...) > 0, an occluder 10 cm in front 0,
    an invalid pixel 0, a measurement 5 cm behind z* (the pose is not there) log(w_u) < 0."""
    import math

    params = replace(lr.LikelihoodParams(), background_ratio=True)
    z_star = np.float64(0.4)
    sigma = params.k * z_star**2 + params.sigma_base
    z = np.array([0.4, 0.3, 0.0, 0.45])
    l = lr.pixel_log_likelihood(z, np.full(4, z_star), params)
    p_e_hit = params.lam / (1 - math.exp(-params.lam * z_star)) * 0.0   # z = z* is not in front
    hit = math.log((params.w_u / params.z_max + p_e_hit + params.w_n / (sigma * math.sqrt(2 * math.pi))) * params.z_max)
    assert l[0] == pytest.approx(hit) and l[0] > 5
    assert l[1] == 0.0 and l[2] == 0.0
    assert l[3] == pytest.approx(math.log(params.w_u))
    assert lr.pixel_log_likelihood(np.array([0.39]), np.array([0.4]), params)[0] < 0   # 1 cm in front: a misfit, not an occluder
