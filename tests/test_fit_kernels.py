"""The noise estimate's numba kernels (app/tracking/fit_kernels.py) against fit_test's numpy functions
(app/tracking/fit_test.py) and scipy, on seeded random fields and on a refined frame."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from app.tracking import fit_kernels, fit_test

REL = 1e-12      # numpy sums pairwise, the kernels in order: equal to rounding


def _field(rng, shape, s, holes=0.2):
    """Noise smoothed over ``s`` cells (0: independent), NaN on a share ``holes`` of the cells."""
    noise = rng.normal(size=shape)
    if s > 0:
        noise = ndimage.gaussian_filter(noise, s)
    noise = 0.0006 * noise / noise.std()
    return np.where(rng.random(shape) < holes, np.nan, noise)


@pytest.mark.parametrize("size", [3, 7, 9, 15])
def test_box_mean_is_scipys_uniform_filter_bit_for_bit(rng, size):
    img = rng.normal(size=(37, 52))
    np.testing.assert_array_equal(fit_kernels.box_mean(img, size), ndimage.uniform_filter(img, size, mode="constant"))


@pytest.mark.parametrize("s, window", [(0, 7), (1.5, 9), (3, 15)])
def test_detrended_noise_and_factor_match_fit_test(rng, s, window):
    for _ in range(3):
        grid = _field(rng, (60, 75), s)
        ref = fit_test.detrended(grid, np.isfinite(grid), window)
        got = fit_kernels.detrended(grid, window)
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
        np.testing.assert_array_equal(got[np.isfinite(got)], ref[np.isfinite(ref)])
        assert fit_kernels.surface_noise(got) == fit_test.surface_noise(ref)
        for axis in (0, 1):
            rho, pairs = fit_kernels.lag_one_correlation(got, axis)
            rho_ref, pairs_ref = fit_test.lag_one_correlation(ref, axis)
            assert pairs == pairs_ref and rho == pytest.approx(rho_ref, rel=REL, abs=1e-15)
        noise, factor = fit_kernels.noise_and_factor(got, window)
        noise_ref, factor_ref = fit_test.noise_and_factor(ref, window)
        assert noise == pytest.approx(noise_ref, rel=REL) and factor == pytest.approx(factor_ref, rel=REL)


@pytest.mark.parametrize("rho_u, rho_v", [(0.0, 0.0), (0.3, 0.7), (0.98, 0.1), (0.99, 1.5)])
def test_detrended_correlation_and_gaussian_sum_match_fit_test(rho_u, rho_v):
    for window in (3, 9, 15):
        var, (du, dv) = fit_test.detrended_correlation((rho_u, rho_v), window)
        got = fit_kernels.detrended_correlation(rho_u, rho_v, window)
        assert got == pytest.approx((var, du, dv), rel=REL, abs=1e-15)
    assert fit_kernels.gaussian_sum(rho_u) == pytest.approx(fit_test.gaussian_sum(rho_u), rel=REL)


def test_few_cells_give_an_unknown_noise_and_factor_one(rng):
    grid = np.full((10, 10), np.nan)
    grid[2, 2:8] = -0.001
    assert np.isnan(fit_kernels.noise_and_factor(grid, 3)[0]) and fit_kernels.noise_and_factor(grid, 3)[1] == 1.0
    assert np.isnan(fit_test.noise_and_factor(grid, 3)[0])


def test_residual_noise_equals_the_numpy_path_of_a_refined_frame(rng):
    """Refine.py step 7 on a refined synthetic frame: the kernel's (σ̂_n, f) equal the numpy path's
    (fit_test's functions), with and without unassociated points (NaN normals) and at both strides."""
    from app.filter.refine import Refiner, RefineParams
    from app.geometry import se3
    from app.sim.simulator import D415_640x480
    from tests.scenes import synthetic_crest
    from tests.test_refine_kernels import _depth, _pose

    vertices, faces = synthetic_crest()
    refs = {b: Refiner(vertices, faces, D415_640x480, RefineParams(backend=b, samples=20_000)) for b in ("numpy", "numba")}
    T = _pose(rng)
    depth = _depth(refs["numpy"], T, rng)
    for stride in (1, 2):
        ref = refs["numpy"]
        y, _ = ref.measurements(depth, T, stride)
        p, x, n, d = ref._associate(y, T)
        n[::11] = np.nan                           # some not associated
        r = np.einsum("ij,ij->i", n, p - x)
        camera_bone = se3.inverse(T)[:3, 3]
        expected = ref._residual_noise(y, p, n, r, camera_bone, stride)
        got = refs["numba"]._residual_noise(y, p, n, r, camera_bone, stride)
        assert np.isfinite(expected[0]) and expected[1] >= 1.0
        assert got == pytest.approx(expected, rel=REL)
