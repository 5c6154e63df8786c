"""numba kernels of the consistency test's noise estimate (app/tracking/fit_test.py), for the refinement.

Import as ``from app.tracking import fit_kernels``. :func:`residual_noise` computes in one call what
app/filter/refine.py's numpy path computes with fit_test's functions for ``RefineResult.noise`` and
``.correlation`` (refine.py step 7): the residuals as depth noise along the ray, u_i = r_i / |cos θ_i|
(fit_test module docstring, 1), laid out on the refinement's grid, less their local mean over the
window (:func:`detrended`), σ̂_d = 1.4826 median of the back half, the lag-one correlations ρ₁ along
the rows and the columns, the fixed point that gives back what the local mean took
(R_d = R − 2 M∗R + M∗M∗R for a Gaussian correlation, :func:`detrended_correlation`), and
f = S_u S_v with S = Σ_k ρ₁^(k²) (Cressie 1993, §1.3; fit_test module docstring, 2).

The box means follow scipy.ndimage.uniform_filter's running sum (mode "constant", the sum divided by
the size at each step), so they equal scipy's bit for bit; sums over cells are plain loops (numpy
sums pairwise), so the results equal fit_test's to rounding (tests/test_fit_kernels.py compares both
on random fields and on refined frames).
"""
from __future__ import annotations

import math

import numpy as np

from app.render.cpu_raster import _njit
from app.tracking.fit_test import (BACK_SIGMAS, FIXED_POINT_TOL, FRONT_SIGMAS, MAX_RHO, MIN_BEHIND, MIN_PAIRS,
                                   MIN_WINDOW_CELLS)

MIN_COS = 0.3             # fit_test.depth_residuals' default: grazing rays give no depth residual


@_njit()
def _box_line(src, dst, size):
    """dst = the mean of src over a centred window of ``size`` (zeros outside): scipy's uniform_filter1d
    with mode "constant", in its running-sum form (1-D views, same length)."""
    n = src.shape[0]
    s1 = size // 2
    s2 = size - s1 - 1
    tmp = 0.0
    for k in range(size):
        i = k - s1
        if 0 <= i < n:
            tmp += src[i]
    dst[0] = tmp / size
    for k in range(1, n):
        a, b = k + s2, k - 1 - s1
        va = src[a] if a < n else 0.0
        vb = src[b] if b >= 0 else 0.0
        tmp += va - vb
        dst[k] = tmp / size


@_njit()
def box_mean(img, size):
    """scipy.ndimage.uniform_filter(img, size, mode="constant") of a 2-D float64 array: along the rows'
    axis (0) first, then along axis 1, as scipy does."""
    h, w = img.shape
    tmp = np.empty((h, w))
    out = np.empty((h, w))
    col_in = np.empty(h)
    col_out = np.empty(h)
    for c in range(w):
        for r in range(h):
            col_in[r] = img[r, c]
        _box_line(col_in, col_out, size)
        for r in range(h):
            tmp[r, c] = col_out[r]
    for r in range(h):
        _box_line(tmp[r], out[r], size)
    return out


@_njit()
def detrended(grid, window):
    """fit_test.detrended(grid, isfinite(grid), window): the field less its local mean over the finite
    cells of each ``window`` x ``window`` window; NaN outside them and where fewer than
    MIN_WINDOW_CELLS cells hold the mean."""
    h, w = grid.shape
    values = np.zeros((h, w))
    weight = np.zeros((h, w))
    for r in range(h):
        for c in range(w):
            if np.isfinite(grid[r, c]):
                values[r, c] = grid[r, c]
                weight[r, c] = 1.0
    total = box_mean(values, window)
    count = box_mean(weight, window)
    out = np.full((h, w), np.nan)
    for r in range(h):
        for c in range(w):
            if weight[r, c] > 0.0 and count[r, c] * window * window >= MIN_WINDOW_CELLS:
                out[r, c] = grid[r, c] - total[r, c] / count[r, c]
    return out


@_njit()
def surface_noise(field):
    """fit_test.surface_noise: 1.4826 median(|d| : d < 0), NaN with fewer than MIN_BEHIND."""
    flat = field.ravel()
    back = np.empty(flat.shape[0])
    m = 0
    for i in range(flat.shape[0]):
        d = flat[i]
        if np.isfinite(d) and d < 0.0:
            back[m] = -d
            m += 1
    if m < MIN_BEHIND:
        return np.nan
    s = np.sort(back[:m])
    if m % 2 == 1:
        return 1.4826 * s[m // 2]
    return 1.4826 * ((s[m // 2 - 1] + s[m // 2]) / 2.0)


@_njit()
def lag_one_correlation(grid, axis):
    """fit_test.lag_one_correlation: (ρ₁, pairs) of the field with itself one cell along ``axis``."""
    h, w = grid.shape
    sxy, sxx, syy = 0.0, 0.0, 0.0
    pairs = 0
    if axis == 0:
        for r in range(h - 1):
            for c in range(w):
                x, y = grid[r, c], grid[r + 1, c]
                if np.isfinite(x) and np.isfinite(y):
                    sxy += x * y
                    sxx += x * x
                    syy += y * y
                    pairs += 1
    else:
        for c in range(w - 1):
            for r in range(h):
                x, y = grid[r, c], grid[r, c + 1]
                if np.isfinite(x) and np.isfinite(y):
                    sxy += x * y
                    sxx += x * x
                    syy += y * y
                    pairs += 1
    if pairs < MIN_PAIRS:
        return 0.0, pairs
    denom = math.sqrt(sxx * syy)
    return (sxy / denom if denom > 0 else 0.0), pairs


@_njit()
def _clip_rho(rho):
    return min(max(rho, 0.0), MAX_RHO)


@_njit()
def gaussian_sum(rho):
    """fit_test.gaussian_sum: S = Σ_{k ∈ ℤ} ρ^(k²), 1 at ρ = 0."""
    rho = _clip_rho(rho)
    if rho <= 0.0:
        return 1.0
    total = 0.0
    for k in range(1, 64):
        total += rho ** float(k * k)
    return 1.0 + 2.0 * total


@_njit()
def _axis_terms(rho, window):
    """(r, M∗r, M∗M∗r) of one axis: the Gaussian correlation ρ^(k²) on k = −2 window .. 2 window and
    its box means (fit_test.detrended_correlation)."""
    half = 2 * window
    n = 2 * half + 1
    seq = np.empty(n)
    r = _clip_rho(rho)
    for i in range(n):
        k = float(i - half)
        if r > 0:
            seq[i] = r ** (k * k)
        else:
            seq[i] = 1.0 if i == half else 0.0
    once = np.empty(n)
    twice = np.empty(n)
    _box_line(seq, once, window)
    _box_line(once, twice, window)
    return seq, once, twice


@_njit()
def detrended_correlation(rho_u, rho_v, window):
    """fit_test.detrended_correlation((ρ_u, ρ_v), window): (variance share, ρ_d along the rows (u),
    along the columns (v)) of the detrended field, R_d = R − 2 M∗R + M∗M∗R."""
    rv, mrv, mmrv = _axis_terms(rho_v, window)
    ru, mru, mmru = _axis_terms(rho_u, window)
    c = 2 * window
    var = rv[c] * ru[c] - 2.0 * mrv[c] * mru[c] + mmrv[c] * mmru[c]
    along_u = rv[c] * ru[c + 1] - 2.0 * mrv[c] * mru[c + 1] + mmrv[c] * mmru[c + 1]
    along_v = rv[c + 1] * ru[c] - 2.0 * mrv[c + 1] * mru[c] + mmrv[c + 1] * mmru[c]
    return var, along_u / var, along_v / var


@_njit()
def noise_and_factor(field, window, rounds=12):
    """fit_test.noise_and_factor: (σ̂_n, f) of the rough residual field, the local mean's share given back
    by the damped fixed point on the lag-one correlations."""
    noise_d = surface_noise(field)
    finite = 0
    for v in field.ravel():
        if np.isfinite(v):
            finite += 1
    if finite < MIN_PAIRS:
        return noise_d, 1.0
    target_u = max(lag_one_correlation(field, 1)[0], 0.0)
    target_v = max(lag_one_correlation(field, 0)[0], 0.0)
    rho_u, rho_v = target_u, target_v
    for _ in range(rounds):
        _, got_u, got_v = detrended_correlation(rho_u, rho_v, window)
        step_u, step_v = target_u - got_u, target_v - got_v
        rho_u = min(max(rho_u + step_u, 0.0), MAX_RHO)
        rho_v = min(max(rho_v + step_v, 0.0), MAX_RHO)
        if max(abs(step_u), abs(step_v)) < FIXED_POINT_TOL:
            break
    share = detrended_correlation(rho_u, rho_v, window)[0]
    return noise_d / math.sqrt(max(share, 0.25)), gaussian_sum(rho_u) * gaussian_sum(rho_v)


@_njit()
def noise_field(cols, rows, u, sigma_model, window):
    """fit_test.noise_field from the cells' columns and rows (M,) int64: the residuals within
    FRONT_SIGMAS σ in front and BACK_SIGMAS σ behind, on the grid spanned by all the cells, detrended."""
    m = u.shape[0]
    if m == 0:
        return np.full((0, 0), np.nan)
    c0, r0, c1, r1 = cols[0], rows[0], cols[0], rows[0]
    for i in range(m):
        c0, c1 = min(c0, cols[i]), max(c1, cols[i])
        r0, r1 = min(r0, rows[i]), max(r1, rows[i])
    grid = np.full((r1 - r0 + 1, c1 - c0 + 1), np.nan)
    for i in range(m):
        core = np.isfinite(u[i]) and u[i] < FRONT_SIGMAS * sigma_model[i] and u[i] > -BACK_SIGMAS * sigma_model[i]
        grid[rows[i] - r0, cols[i] - c0] = u[i] if core else np.nan
    return detrended(grid, window)


@_njit()
def residual_noise(y, p, n, r, camera_bone, stride, fx, fy, cx, cy, sigma_model, window):
    """(σ̂_n, f) of one fit (refine.py ``Refiner._residual_noise``, step 7): y (M, 3) the camera-frame
    measurements, p (M, 3) them in the bone frame, n (M, 3) the associated normals (NaN: none), r (M,)
    the signed point-to-plane residuals, ``camera_bone`` (3,) the camera's centre in the bone frame,
    ``sigma_model`` (M,) σ(z), ``window`` the detrending window in cells."""
    m = y.shape[0]
    u = np.empty(m)
    cols = np.empty(m, np.int64)
    rows = np.empty(m, np.int64)
    s = max(stride, 1)
    for i in range(m):
        rx, ry, rz = p[i, 0] - camera_bone[0], p[i, 1] - camera_bone[1], p[i, 2] - camera_bone[2]
        cos = abs((n[i, 0] * rx + n[i, 1] * ry + n[i, 2] * rz) / math.sqrt(rx * rx + ry * ry + rz * rz))
        u[i] = r[i] / cos if cos >= MIN_COS else np.nan
        col = np.floor(np.rint(y[i, 0] / y[i, 2] * fx + cx) / s)     # fit_test's cells: rint(...) // stride
        row = np.floor(np.rint(y[i, 1] / y[i, 2] * fy + cy) / s)
        cols[i] = np.int64(col) if np.isfinite(col) else 0
        rows[i] = np.int64(row) if np.isfinite(row) else 0
    return noise_and_factor(noise_field(cols, rows, u, sigma_model, window), window)
