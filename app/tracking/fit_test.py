"""The status's consistency test: is the refined fit's residual what this image's noise explains?

Import as ``from app.tracking import fit_test``. DESIGN.md "The status as a test": light does not
pass through bone, so of the refined fit's signed point-to-plane residuals r_i (n_iᵀ(p_i − x_i),
normals outward, app/filter/refine.py step 7) the ones *in front* of the model may be tissue, blood
or an instrument, while the ones *behind* it can only be noise. The test counts the measurements more
than ``behind_sigmas`` σ_i behind the model and asks whether the noise explains that count at level
α (``status.alpha``, one-sided: 0.135 % = 3 standard deviations; app/tracking/levels.py).

Two quantities make it transfer between sensors (issue 32: the second difference along the rows of a
stereo camera's image, whose noise is correlated over the matching window, underestimated its noise
by half, and its 0.2 % fixed margin then blocked right poses on 99.8 % of the frames):

1. **The noise's scale from the fitted surface** (:func:`noise_field`, :func:`surface_noise`). Each
   residual, divided by |cos θ_i| = |n_i · r̂_i| (the ray's angle to the surface), is the depth noise
   along the ray, u_i = r_i / |cos θ_i|. Their local mean over ``refine.noise_window_px`` is taken
   off: a wrong pose leaves a smooth residual field, the sensor a rough one. The front half of what
   remains is contaminated (tissue), the back half is not: under a right pose it is half-normal,
   whose median is Φ⁻¹(0.75) σ_n = 0.6745 σ_n, so σ̂_d = 1.4826 median(|d_i| : d_i < 0). The local
   mean took a share of the noise with it; :func:`noise_and_factor` gives it back (exactly for a
   Gaussian correlation, :func:`detrended_correlation`). σ̂_n holds the model's own error
   (segmentation, discretisation) too: what this image and this mesh leave, not a datasheet's figure.
2. **An effective number of independent measurements** (:func:`correlation_factor`). n pixels whose
   noise is correlated carry the evidence of n / f independent ones, with f = Σ_d ρ(d) over the
   lags d of the residual field (the variance of a sum of a stationary field, e.g. Cressie 1993,
   §1.3). The count behind is Poisson-binomial with mean Σ e_i, e_i = Φ(−behind_sigmas σ_i /
   (σ̂_n |cos θ_i|)); its variance Σ e_i (1 − e_i) is multiplied by f. ρ is measured at one cell along
   the rows and the columns of the refinement's grid, ρ₁, and extended as a Gaussian correlation
   ρ(k) = ρ₁^(k²) (a smoothing window's shape), f = S_u S_v with S = Σ_k ρ₁^(k²) (k ∈ ℤ). Lag one
   only, so that a wrong pose's smooth residual pattern (which correlates every lag alike) inflates
   f as little as it can. Independent noise gives f ≈ 1 (the test of before); the indicator of
   "behind" is less correlated than the residual itself, so f errs on the side of fewer false
   alarms.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

MIN_BEHIND = 30           # behind residuals needed to estimate the noise's scale (else NaN: the caller falls back)
MIN_PAIRS = 30            # neighbouring pairs needed to estimate the correlation (else f = 1)
MAX_RHO = 0.98            # the lag-one correlation is capped here (f <= ~155): a perfectly smooth field is a model error, not noise
FRONT_SIGMAS = 2.0        # residuals up to this many σ(z) in front of the model enter the noise field (tissue further out does not)
BACK_SIGMAS = 4.0         # ... and up to this many behind (the background seen past the silhouette does not)
WINDOW_PX = 15            # px, the default of refine.noise_window_px (the detrending window, 10 mm at 0.42 m): wider let a fit slid 1.5 mm onto a tissue patch raise the scale it is judged by (tests/test_refine.py)
MIN_WINDOW_CELLS = 9      # a cell's local mean needs this many core cells in its window
FIXED_POINT_TOL = 1e-10   # the correction's fixed point stops once a round moves ρ by less


def depth_residuals(r: np.ndarray, cos: np.ndarray, min_cos: float = 0.3) -> np.ndarray:
    """u_i = r_i / |cos θ_i| (m): the point-to-plane residual as depth noise along the ray; NaN where
    the surface is seen at a grazing angle (|cos θ| < ``min_cos``) or the residual is unknown."""
    cos = np.abs(np.asarray(cos, float))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(cos >= min_cos, np.asarray(r, float) / cos, np.nan)


def residual_grid(cells: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``u`` (M,) laid out on the refinement's grid by ``cells`` (M, 2) integer (column, row); NaN where
    there is no measurement."""
    cells = np.asarray(cells, np.int64).reshape(-1, 2)
    c = cells - cells.min(axis=0) if len(cells) else cells
    grid = np.full((c[:, 1].max() + 1, c[:, 0].max() + 1) if len(c) else (0, 0), np.nan)
    grid[c[:, 1], c[:, 0]] = u
    return grid


def detrended(grid: np.ndarray, core: np.ndarray, window: int) -> np.ndarray:
    """The residual field less its local mean over ``window`` x ``window`` cells (normalised
    convolution over the ``core`` cells only; NaN outside the core). A pose error leaves a smooth
    residual field (a rigid motion's is nearly linear over a few centimetres of bone), the sensor's
    noise a rough one: the local mean takes the first away and keeps the second (its own share of
    the local mean, f / window², is a few per cent)."""
    values = np.where(core, grid, 0.0)
    weight = core.astype(float)
    total = ndimage.uniform_filter(values, window, mode="constant")
    count = ndimage.uniform_filter(weight, window, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        local = total / count
    return np.where(core & (count * window * window >= MIN_WINDOW_CELLS), grid - local, np.nan)


def noise_field(cells: np.ndarray, u: np.ndarray, sigma_model: np.ndarray, window: int) -> np.ndarray:
    """The rough part of the depth residuals on the grid (:func:`detrended`), over the core cells:
    those within ``FRONT_SIGMAS`` σ in front of and ``BACK_SIGMAS`` σ behind the model (σ the sensor
    model's σ(z), ``sigma_model`` (M,)): tissue further in front and background seen past the
    silhouette do not enter."""
    u = np.asarray(u, float)
    sigma_model = np.asarray(sigma_model, float)
    with np.errstate(invalid="ignore"):
        core = np.isfinite(u) & (u < FRONT_SIGMAS * sigma_model) & (u > -BACK_SIGMAS * sigma_model)
    grid = residual_grid(cells, np.where(core, u, np.nan))
    return detrended(grid, np.isfinite(grid), window)


def surface_noise(field: np.ndarray) -> float:
    """σ̂_n (m) = 1.4826 median(|d_i| : d_i < 0) of the rough residual field's back half (module
    docstring, 1); NaN with fewer than MIN_BEHIND of them."""
    d = np.asarray(field, float).ravel()
    back = -d[np.isfinite(d) & (d < 0)]
    if len(back) < MIN_BEHIND:
        return float("nan")
    return float(1.4826 * np.median(back))


def lag_one_correlation(grid: np.ndarray, axis: int) -> tuple[float, int]:
    """(ρ₁, pairs): the correlation of ``grid`` (2-D, NaN = no measurement, mean already removed)
    with itself shifted by one cell along ``axis``, over the pairs where both are known."""
    a = np.moveaxis(grid, axis, 0)
    x, y = a[:-1], a[1:]
    both = np.isfinite(x) & np.isfinite(y)
    pairs = int(both.sum())
    if pairs < MIN_PAIRS:
        return 0.0, pairs
    x, y = x[both], y[both]
    denom = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return (float(np.sum(x * y) / denom) if denom > 0 else 0.0), pairs


def gaussian_sum(rho: float) -> float:
    """S = Σ_{k ∈ ℤ} ρ^(k²) for 0 <= ρ < 1 (1 at ρ = 0): the sum of a Gaussian correlation sampled at
    whole cells whose value at one cell is ρ."""
    rho = float(np.clip(rho, 0.0, MAX_RHO))
    if rho <= 0.0:
        return 1.0
    k = np.arange(1, 64)
    return float(1.0 + 2.0 * np.sum(rho ** (k * k)))


def correlation_factor(field: np.ndarray) -> float:
    """f = n / n_eff >= 1 of a residual field as it is (module docstring, 2); 1 when unknown. The
    refinement uses :func:`noise_and_factor`, which also gives back what a local mean took."""
    field = np.asarray(field, float)
    if field.ndim != 2 or np.count_nonzero(np.isfinite(field)) < MIN_PAIRS:
        return 1.0
    rho_u, _ = lag_one_correlation(field, axis=1)
    rho_v, _ = lag_one_correlation(field, axis=0)
    return gaussian_sum(rho_u) * gaussian_sum(rho_v)


def detrended_correlation(rho: tuple[float, float], window: int) -> tuple[float, tuple[float, float]]:
    """(variance share, (ρ_d along the rows, along the columns)) of d = u − mean_W(u) for a unit-variance
    field of Gaussian correlation R(a, b) = ρ_v^(a²) ρ_u^(b²): R_d = R − 2 M∗R + M∗M∗R with M the
    ``window`` x ``window`` box average (symmetric). R and M are separable, so each term is an outer
    product of 1-D sequences (r, m∗r, m∗m∗r per axis) and only the three lags needed are formed."""
    half = 2 * window
    k = np.arange(-half, half + 1, dtype=float)
    axes = []
    for r in (float(np.clip(rho[1], 0.0, MAX_RHO)), float(np.clip(rho[0], 0.0, MAX_RHO))):   # rows (v), columns (u)
        seq = r ** (k * k) if r > 0 else (k == 0).astype(float)
        once = ndimage.uniform_filter1d(seq, window, mode="constant")
        axes.append((seq, once, ndimage.uniform_filter1d(once, window, mode="constant")))
    (rv, mrv, mmrv), (ru, mru, mmru) = axes

    def rd(a: int, b: int) -> float:
        return float(rv[a] * ru[b] - 2.0 * mrv[a] * mru[b] + mmrv[a] * mmru[b])
    c = half
    var = rd(c, c)
    return var, (rd(c, c + 1) / var, rd(c + 1, c) / var)


def noise_and_factor(field: np.ndarray, window: int, rounds: int = 12) -> tuple[float, float]:
    """(σ̂_n, f) of the rough residual field (:func:`noise_field` with ``window``), corrected for what the
    local mean took with it: the lag-one correlations ρ whose detrended values
    (:func:`detrended_correlation`) are the measured ρ_d (a damped fixed point), then f = S_u S_v
    (:func:`gaussian_sum`) and σ̂_n = σ̂_d / sqrt(the detrended variance share)."""
    noise_d = surface_noise(field)
    field = np.asarray(field, float)
    if field.ndim != 2 or np.count_nonzero(np.isfinite(field)) < MIN_PAIRS:
        return noise_d, 1.0
    target = np.array([max(lag_one_correlation(field, axis)[0], 0.0) for axis in (1, 0)])
    rho = target.copy()
    for _ in range(rounds):
        _, got = detrended_correlation(tuple(rho), window)
        step = target - np.array(got)
        rho = np.clip(rho + step, 0.0, MAX_RHO)
        if np.max(np.abs(step)) < FIXED_POINT_TOL:
            break
    share, _ = detrended_correlation(tuple(rho), window)
    return noise_d / np.sqrt(max(share, 0.25)), gaussian_sum(rho[0]) * gaussian_sum(rho[1])


def window_cells(stride: int, window_px: int = WINDOW_PX) -> int:
    """The detrending window in cells of a grid of step ``stride`` px: ``window_px`` (refine.noise_window_px), odd."""
    cells = max(3, int(round(window_px / max(stride, 1))))
    return cells + 1 - cells % 2
