"""The status's consistency test (app/tracking/fit_test.py) against closed forms."""
import numpy as np
import pytest
from scipy import ndimage

from app.tracking import fit_test


def _field(rng, shape, s):
    """Unit-variance noise, Gaussian-smoothed with std ``s`` cells (0: independent)."""
    noise = rng.normal(size=shape)
    if s > 0:
        noise = ndimage.gaussian_filter(noise, s)
    return noise / noise.std()


def _cells(shape):
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    return np.column_stack([cols.ravel(), rows.ravel()])


def test_surface_noise_is_the_scale_of_the_back_half_whatever_lies_in_front(rng):
    sigma = 0.0007
    u = rng.normal(0.0, sigma, 20_000)
    tissue = rng.uniform(0.002, 0.006, 8_000)          # residuals in front only (tissue): must not matter
    assert fit_test.surface_noise(np.concatenate([u, tissue])) == pytest.approx(sigma, rel=0.03)
    assert np.isnan(fit_test.surface_noise(np.abs(u[:100])))   # nothing behind: unknown


def test_depth_residuals_divide_by_the_ray_angle_and_drop_grazing_ones():
    u = fit_test.depth_residuals(np.array([0.001, -0.001, 0.001]), np.array([0.5, -1.0, 0.1]))
    assert u[0] == pytest.approx(0.002) and u[1] == pytest.approx(-0.001) and np.isnan(u[2])


@pytest.mark.parametrize("rho", [0.0, 0.3, 0.8])
def test_gaussian_sum_matches_the_series(rho):
    k = np.arange(-200, 201)
    assert fit_test.gaussian_sum(rho) == pytest.approx(np.sum(rho ** (k * k).astype(float)) if rho else 1.0)


def test_the_noise_field_keeps_the_noise_and_drops_a_pose_errors_smooth_residual(rng):
    """A rigid pose error leaves a nearly planar residual field: 2 mm across the view here, three times
    the noise. The detrended field's scale is still the noise's (less its local mean's share), and
    tissue 3 mm in front on a third of the cells does not enter."""
    shape, sigma = (80, 100), 0.0006
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    ramp = 0.002 * (cols / shape[1] - 0.5) + 0.001 * (rows / shape[0] - 0.5)
    u = ramp + sigma * _field(rng, shape, 0)
    u[:, :33] += 0.003
    field = fit_test.noise_field(_cells(shape), u.ravel(), np.full(u.size, 0.0012), fit_test.window_cells(2))
    assert fit_test.surface_noise(field) == pytest.approx(sigma, rel=0.1)


def test_independent_noise_has_factor_one(rng):
    shape = (60, 80)
    u = 0.0005 * _field(rng, shape, 0)
    field = fit_test.noise_field(_cells(shape), u.ravel(), np.full(u.size, 0.001), 15)
    assert 1.0 <= fit_test.correlation_factor(field) < 1.15


def test_smoothed_noise_has_the_factor_of_its_variance_of_the_mean(rng):
    """For a Gaussian-smoothed field (std s cells) the correlation is Gaussian, ρ(d) = exp(-d²/(4 s²)), and
    n / n_eff = Σ_d ρ(d) = (Σ_k ρ₁^(k²))² with ρ₁ = exp(-1/(4 s²)); checked by the variance of block means."""
    s, shape = 1.5, (120, 160)
    field = [_field(rng, shape, s) - 0.0 for _ in range(5)]
    factors = [fit_test.correlation_factor(f) for f in field]
    expected = fit_test.gaussian_sum(np.exp(-1.0 / (4 * s * s))) ** 2
    assert np.median(factors) == pytest.approx(expected, rel=0.15)
    block = [_field(rng, shape, s).reshape(6, 20, 8, 20).mean(axis=(1, 3)).ravel() for _ in range(40)]
    assert 400 * np.var(np.concatenate(block)) == pytest.approx(expected, rel=0.3)


def test_behind_count_of_correlated_noise_stays_within_the_inflated_bound(rng):
    """The count of correlated residuals beyond 1 σ behind exceeds mean + 3 sd of the independent bound
    often; with the variance multiplied by the measured f, seldom (α ≈ 0.13 %, one-sided)."""
    from scipy.special import ndtr
    s, n_frames, shape = 1.5, 200, (40, 60)
    plain = inflated = 0
    for _ in range(n_frames):
        u = 0.0006 * _field(rng, shape, s).ravel()
        count = np.sum(u < -0.0006)
        e = ndtr(-1.0)
        mean, var = u.size * e, u.size * e * (1 - e)
        f = fit_test.correlation_factor(u.reshape(shape) - u.mean())
        plain += count > mean + 3 * np.sqrt(var)
        inflated += count > mean + 3 * np.sqrt(f * var)
    assert plain > 0.1 * n_frames
    assert inflated <= 0.02 * n_frames


@pytest.mark.parametrize("s, window", [(0.0, 9), (1.3, 9), (2.6, 15)])
def test_the_local_means_share_is_given_back(rng, s, window):
    """Detrended over the window (9 cells at stride 2, 15 at stride 1: WINDOW_PX), correlated noise loses
    part of its variance and of its correlation to the local mean; noise_and_factor returns the field's
    own σ and f. s: a 9 px matching window's correlation at stride 2 and 1 (a box of 9 px has the
    Gaussian's std 9 / sqrt(12) px)."""
    shape, sigma = (120, 160), 0.0006
    u = sigma * _field(rng, shape, s)
    field = fit_test.noise_field(_cells(shape), u.ravel(), np.full(u.size, 0.0012), window)
    noise, f = fit_test.noise_and_factor(field, window)
    expected_f = fit_test.gaussian_sum(np.exp(-1.0 / (4 * s * s))) ** 2 if s else 1.0
    assert noise == pytest.approx(sigma, rel=0.12)
    assert f == pytest.approx(expected_f, rel=0.2)
    assert fit_test.surface_noise(field) < noise or s == 0.0      # uncorrected, correlated noise looks smaller


def test_the_detrending_window_comes_from_the_configuration():
    from app.config import load_config
    from app.pipeline.tracker import refine_params
    assert fit_test.window_cells(2) == 9 and fit_test.window_cells(1) == 15          # 15 px: 7.5 -> 8 -> odd 9 cells
    assert fit_test.window_cells(2, 31) == 17 and fit_test.window_cells(1, 4) == 5
    assert refine_params(load_config(None)).noise_window_px == fit_test.WINDOW_PX


def test_the_separable_form_equals_the_two_dimensional_filter():
    """detrended_correlation forms R − 2 M∗R + M∗M∗R from 1-D sequences; the same on a 2-D grid."""
    for rho, window in [((0.0, 0.0), 7), ((0.3, 0.8), 7), ((0.95, 0.6), 15)]:
        k = np.arange(-2 * window, 2 * window + 1, dtype=float)
        seq = [r ** (k * k) if r > 0 else (k == 0).astype(float) for r in (rho[1], rho[0])]
        R = np.outer(*seq)
        MR = ndimage.uniform_filter(R, window, mode="constant")
        Rd = R - 2 * MR + ndimage.uniform_filter(MR, window, mode="constant")
        c = 2 * window
        var, (rho_u, rho_v) = fit_test.detrended_correlation(rho, window)
        assert var == pytest.approx(Rd[c, c], abs=1e-12)
        assert rho_u == pytest.approx(Rd[c, c + 1] / Rd[c, c], abs=1e-12)
        assert rho_v == pytest.approx(Rd[c + 1, c] / Rd[c, c], abs=1e-12)
