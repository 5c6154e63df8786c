"""Numpy reference of the depth observation model: log p(z | x) per particle.

Import as ``from app.filter import likelihood_ref``. This is the specification: the GL compute
shader (``app/render/likelihood.comp.glsl``) implements the same formulas in float32 and is tested
against :func:`log_likelihood` (float64). Any change here must be made there too.

Inputs: the measured depth image z (H, W) float32 metres (0 or non-finite = invalid) and, per
particle j, the rendered linear depth z* (H, W) of the mesh at pose x_j (0 = the pose does not cover
the pixel). Per covered pixel i (z*_i > 0), with

    σ_i   = k z*_i² + σ_base                           (stereo noise grows quadratically)
    p_u   = 1 / z_max                                  (uniform outliers)
    p_n   = N(z_i; z*_i, σ_i²) = exp(-r²/2) / (σ_i √(2π)),  r = (z_i - z*_i) / σ_i
    p_e   = λ e^{-λ z_i} / (1 - e^{-λ z*_i})  if 0 < z_i < z*_i, else 0
            (occlusion='exponential': something in front of the bone; λ = ln 2 / m halves it
            every metre)
    p_e   = λ / (1 - e^{-λ z*}) · exp(-λ z + λ² σ² / 2)
            · [Φ((z* - z + λ σ²) / σ) - Φ((λ σ² - z) / σ)]
            (occlusion='smooth_exponential', (B) eq. 4.33: the truncated exponential on [0, z*]
            convolved with N(0, σ²); Φ(x) = ½ (1 + erf(x / √2)); used for every valid z)

a measurement is *valid* when it is finite and 0 < z_i <= z_max; z_i > z_max, 0, NaN and ±inf
are outliers that only p_u explains. With P_FLOOR = ``LOG_FLOOR`` = 1e-30 and
``safe_log(p) = log(max(p, LOG_FLOOR))`` (the floor keeps float32 logs finite on the GPU):

- beam model (classification=False, the default; DESIGN.md "Observation"):
  valid:   l_i = safe_log(w_u p_u + w_e p_e + w_n p_n)
  invalid: l_i = safe_log(w_u p_u)
- pixel-object classification (classification=True; our reading of (B) eq. 4.34-4.36 with the L0
  regularisation of (B) eq. 4.38-4.39):
  l_obj = safe_log(w_n p_n), l_bg = safe_log(w_u p_u + w_e p_e);
  object pixel if l_obj >= l_bg: l_i = l_obj; else background: l_i = l_bg - l0_weight.
  An invalid z is background: l_i = safe_log(w_u p_u) - l0_weight.
- uncovered pixels (z*_i <= 0) contribute 0 (log 1).
- background ratio (``background_ratio=True``; our addition, not in (A)/(B)): each covered pixel
  contributes the log-ratio of the bone hypothesis to the background hypothesis "this pixel sees
  something else at a depth uniform in [0, z_max]", p_0 = 1 / z_max:
  valid:   l_i ← l_i - log(1 / z_max);   invalid: l_i ← l_i - log(w_u p_u) (= 0 without
  classification: an invalid pixel says nothing about the pose).
  The uncovered pixels' 0 then means "explained by the background" as well, so the sum no longer
  rewards a pose for covering fewer pixels. A pixel measured more than ``occluder_margin``
  (20 mm) in front of z* sees an occluder (a hand, an instrument) and says nothing about the
  bone behind it: l_i = 0. Only measurements seen *through* the pose (z ≫ z*, log w_u ≈ -3)
  argue against it, hits (≈ +7) for it. This removes the drift of the cloud away from occluders
  and keeps it in place under a full occlusion (measured: BENCHMARKS.md).

Per particle: L = α Σ_i l_i, or with the pixel-count regularisation ((B) eq. 4.37, c_reg > 0)
L = c_reg · Σ_i l_i / max(N_px, 1), N_px the number of covered pixels; c_reg = 0 disables it.
α = ``pixel_weight`` (default 1) tempers the likelihood: neighbouring pixels of a downsampled
stereo image are correlated, so the product over pixels is overconfident; α < 1 counts each pixel
as a fraction of an independent measurement (it keeps the ESS and the spread honest).

Defaults (:class:`LikelihoodParams`): z_max = 2 m (beyond any working distance of a D415 over the
table; our choice), λ = ln 2 per metre (DESIGN.md), mixture weights w_u = 0.05, w_e = 0.15,
w_n = 0.8 (our choice: DESIGN.md gives none), k = 0.0011 /m and σ_base = 1 mm (D415-like stereo:
at z* = 0.5 m, σ = 0.28 mm + 1 mm).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LOG_FLOOR = 1e-30  # probability floor inside every log: log(max(p, LOG_FLOOR)) >= -69.08 (float32-safe)
OCCLUSION_MODELS = ("exponential", "smooth_exponential")
INLIER_SIGMAS = 3.0  # |z - z*| < 3 σ(z*) makes a pixel an inlier (for the tracking status)

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


@dataclass
class LikelihoodParams:
    """Parameters of the observation model (module docstring; units: metres).

    z_max : m, range of the uniform outlier density and the largest valid measurement
    lam : 1/m, rate λ of the occlusion exponential (ln 2: halves every metre)
    w_u, w_e, w_n : mixture weights of outliers, occlusion, noisy hit
    k : 1/m, quadratic noise coefficient, σ = k z*² + σ_base
    sigma_base : m, noise floor
    occlusion : 'exponential' (truncated exponential) or 'smooth_exponential' ((B) eq. 4.33)
    classification : pixel-object classification with L0 regularisation ((B) 4.34-4.39)
    l0_weight : the L0 penalty (nats) per background-classified pixel
    pixel_count_reg : c_reg of (B) eq. 4.37; 0 = off
    background_ratio : log-ratio to the uniform background hypothesis per covered pixel
    pixel_weight : α, the tempering factor of the sum over pixels (1 = the plain product)
    occluder_margin : m, with background_ratio a pixel this far in front of z* is neutral (0);
        the tracking status leaves such pixels out of its inlier rules as well
    """

    z_max: float = 2.0
    lam: float = math.log(2.0)
    w_u: float = 0.05
    w_e: float = 0.15
    w_n: float = 0.8
    k: float = 0.0011
    sigma_base: float = 0.001
    occlusion: str = "exponential"
    classification: bool = False
    l0_weight: float = 1.0
    pixel_count_reg: float = 0.0
    background_ratio: bool = False
    pixel_weight: float = 1.0
    occluder_margin: float = 0.02


def safe_log(p: np.ndarray) -> np.ndarray:
    """log(max(p, LOG_FLOOR))."""
    return np.log(np.maximum(p, LOG_FLOOR))


def noise_sigma(z_star: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """σ(z*) = k z*² + σ_base, metres."""
    return params.k * z_star * z_star + params.sigma_base


def erfc(x: np.ndarray) -> np.ndarray:
    """Complementary error function, vectorised numpy.

    Maclaurin series of erf for |x| < 1.5, continued fraction of erfc (100 levels, evaluated
    backwards) beyond; relative error ~1e-14 against ``math.erfc`` (tested).
    """
    x = np.asarray(x, dtype=float)
    ax = np.abs(x)
    small = ax < 1.5
    # erf(x) = 2/√π Σ_n (-1)^n x^(2n+1) / (n! (2n+1)); 40 terms: remainder < 1e-30 at |x| = 1.5
    xs = np.where(small, ax, 0.0)
    term = xs.copy()
    total = xs.copy()
    x2 = xs * xs
    for n in range(1, 40):
        term = term * (-x2) / n
        total = total + term / (2 * n + 1)
    erfc_small = 1.0 - 2.0 / math.sqrt(math.pi) * total
    # erfc(x) = e^{-x²}/√π · 1/(x + (1/2)/(x + 1/(x + (3/2)/(x + ...)))), x >= 1.5
    xl = np.where(small, 1.5, ax)
    cf = xl.copy()
    for k in range(100, 0, -1):
        cf = xl + (0.5 * k) / cf
    erfc_large = np.exp(-xl * xl) / (math.sqrt(math.pi) * cf)
    out = np.where(small, erfc_small, erfc_large)
    return np.where(x < 0, 2.0 - out, out)


def normal_cdf(x: np.ndarray) -> np.ndarray:
    """Φ(x) = ½ erfc(-x / √2) (accurate in both tails)."""
    return 0.5 * erfc(-np.asarray(x, dtype=float) / math.sqrt(2.0))


def occlusion_density(z: np.ndarray, z_star: np.ndarray, sigma: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """p_e(z | z*) of the chosen occlusion model (module docstring), for z*> 0; shapes broadcast."""
    norm = params.lam / (1.0 - np.exp(-params.lam * z_star))
    if params.occlusion == "smooth_exponential":
        s2 = params.lam * sigma * sigma
        window = normal_cdf((z_star - z + s2) / sigma) - normal_cdf((s2 - z) / sigma)
        return norm * np.exp(-params.lam * z + 0.5 * params.lam * s2) * window
    if params.occlusion == "exponential":
        return np.where((z > 0) & (z < z_star), norm * np.exp(-params.lam * z), 0.0)
    raise ValueError(f"unknown occlusion model {params.occlusion!r}; valid: {', '.join(OCCLUSION_MODELS)}")


def valid_measurement(z: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """Bool mask: finite and 0 < z <= z_max."""
    z = np.asarray(z)
    with np.errstate(invalid="ignore"):
        return np.isfinite(z) & (z > 0) & (z <= params.z_max)


def pixel_log_likelihood(z: np.ndarray, z_star: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """Per-pixel l_i (module docstring); 0 where z* <= 0. Shapes broadcast, float64 out."""
    z = np.asarray(z, dtype=float)
    z_star = np.asarray(z_star, dtype=float)
    z, z_star = np.broadcast_arrays(z, z_star)
    covered = z_star > 0
    valid = valid_measurement(z, params)
    zs = np.where(covered, z_star, 1.0)          # placeholders keep the maths finite where unused
    zz = np.where(valid, z, 1.0)
    sigma = noise_sigma(zs, params)
    r = (zz - zs) / sigma
    p_n = _INV_SQRT_2PI / sigma * np.exp(-0.5 * r * r)
    p_e = occlusion_density(zz, zs, sigma, params)
    p_u = params.w_u / params.z_max
    if params.classification:
        l_obj = safe_log(params.w_n * p_n)
        l_bg = safe_log(p_u + params.w_e * p_e)
        l_valid = np.where(l_obj >= l_bg, l_obj, l_bg - params.l0_weight)
        l_invalid = math.log(max(p_u, LOG_FLOOR)) - params.l0_weight
    else:
        l_valid = safe_log(p_u + params.w_e * p_e + params.w_n * p_n)
        l_invalid = math.log(max(p_u, LOG_FLOOR))
    if params.background_ratio:
        l_valid = np.where(zz < zs - params.occluder_margin, 0.0, l_valid + math.log(params.z_max))
        l_invalid = l_invalid - math.log(max(p_u, LOG_FLOOR))
    return np.where(covered, np.where(valid, l_valid, l_invalid), 0.0)


def log_likelihood(depth_meas: np.ndarray, depth_rendered: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """log p(z | x_j) for N rendered hypotheses.

    Parameters
    ----------
    depth_meas : (H, W) float32 metres, measured; 0 or non-finite = invalid
    depth_rendered : (N, H, W) float32 metres, linear depth of each pose; 0 = not covered
    params : LikelihoodParams

    Returns
    -------
    (N,) float64: Σ_i l_i, or c_reg Σ_i l_i / max(N_px, 1) when ``pixel_count_reg`` > 0
    """
    depth_rendered = np.asarray(depth_rendered)
    if depth_rendered.ndim != 3 or depth_rendered.shape[1:] != np.shape(depth_meas):
        raise ValueError(f"rendered depth must be (N, {np.shape(depth_meas)[0]}, {np.shape(depth_meas)[1]}), "
                         f"got {depth_rendered.shape}")
    l = pixel_log_likelihood(np.asarray(depth_meas)[None], depth_rendered, params)
    total = l.reshape(len(l), -1).sum(axis=1)
    if params.pixel_count_reg > 0:
        n_px = (depth_rendered > 0).reshape(len(l), -1).sum(axis=1)
        total = params.pixel_count_reg * total / np.maximum(n_px, 1)
    else:
        total = params.pixel_weight * total
    return total


def inlier_mask(depth_meas: np.ndarray, depth_rendered: np.ndarray, params: LikelihoodParams) -> np.ndarray:
    """(..., H, W) bool: covered, valid and |z - z*| < INLIER_SIGMAS σ(z*) (for the status)."""
    z = np.asarray(depth_meas, dtype=float)
    z_star = np.asarray(depth_rendered, dtype=float)
    valid = valid_measurement(z, params) & (z_star > 0)
    with np.errstate(invalid="ignore"):
        return valid & (np.abs(z - z_star) < INLIER_SIGMAS * noise_sigma(z_star, params))
