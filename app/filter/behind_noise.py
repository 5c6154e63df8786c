"""How much of a right pose's seen surface the depth noise alone puts behind the model (the status's behind rule).

Import as ``from app.filter.behind_noise import behind_bound, behind_moments, image_noise, noise_bound``. Used by
app/filter/refine.py (step 7) for ``RefineResult.behind_allowed``; the rule itself is stated in
app/filter/status.py's docstring and measured in BENCHMARKS.md §6d.
"""
from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from app.geometry.camera import PinholeCamera


def image_noise(depth: np.ndarray, y_cam: np.ndarray, camera: PinholeCamera) -> float:
    """The depth noise σ̂_n (m) of the measured pixels ``y_cam`` (M, 3), from the image itself: the
    second difference along the row, z(u−1) − 2 z(u) + z(u+1), has variance 6 σ_n² on a smooth surface
    (its slope cancels); robust scale 1.4826 MAD / √6 over the pixels whose two neighbours are valid.
    NaN with fewer than 30 such pixels. Spatially correlated noise makes it an underestimate (the
    behind rule then only gets stricter)."""
    u = np.rint(y_cam[:, 0] / y_cam[:, 2] * camera.fx + camera.cx).astype(int)
    v = np.rint(y_cam[:, 1] / y_cam[:, 2] * camera.fy + camera.cy).astype(int)
    inside = (u >= 1) & (u < depth.shape[1] - 1) & (v >= 0) & (v < depth.shape[0])
    u, v = u[inside], v[inside]
    left, mid, right = (np.asarray(depth[v, u + k], float) for k in (-1, 0, 1))
    valid = (left > 0) & (right > 0) & (mid > 0) & np.isfinite(left) & np.isfinite(right) & np.isfinite(mid)
    if valid.sum() < 30:
        return float("nan")
    dd = (left - 2 * mid + right)[valid]
    return float(1.4826 * np.median(np.abs(dd - np.median(dd))) / np.sqrt(6.0))


def behind_bound(p: np.ndarray, n: np.ndarray, threshold: np.ndarray, noise: float, camera_bone: np.ndarray,
                 z: float) -> float:
    """The largest share of measurements more than ``threshold`` (M,) behind a right pose that the
    noise explains: each point's depth noise σ_n along its ray moves it by σ_n |n_i·r̂_i| along the
    normal, so it lies behind with probability e_i = Φ(−threshold_i / (σ_n |n_i·r̂_i|)); the count is
    Poisson-binomial with mean Σ e_i and variance Σ e_i (1 − e_i); the bound is the mean plus ``z``
    standard deviations, over M. ``camera_bone``: the camera's centre in the bone frame. NaN when
    the noise is unknown."""
    mean, var = behind_moments(p, n, threshold, noise, camera_bone)
    return noise_bound(mean, var, len(p), z)


def noise_bound(mean: float, var: float, measurements: int, z: float) -> float:
    """The bound's share, (Σ e_i + z sqrt(Σ e_i (1 − e_i))) / M, from the count's mean and variance
    (:func:`behind_moments`; of one frame, or of several frames added: app/filter/behind_pool.py);
    NaN when they are unknown or there is no measurement."""
    if not (np.isfinite(mean) and np.isfinite(var)) or measurements <= 0:
        return float("nan")
    return float((mean + z * np.sqrt(var)) / measurements)


def behind_moments(p: np.ndarray, n: np.ndarray, threshold: np.ndarray, noise: float,
                   camera_bone: np.ndarray) -> tuple[float, float]:
    """(Σ e_i, Σ e_i (1 − e_i)): the mean and variance of the count of measurements the noise alone
    puts more than ``threshold`` behind a right pose (:func:`behind_bound`); NaN when the noise is
    unknown. Counts of independent frames add, so several frames of one track are tested together
    (app/filter/behind_pool.py)."""
    if not np.isfinite(noise) or len(p) == 0:
        return float("nan"), float("nan")
    ray = p - camera_bone
    with np.errstate(invalid="ignore"):
        cos = np.abs(np.einsum("ij,ij->i", n, ray)) / np.linalg.norm(ray, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):   # σ_n = 0 (a noise-free image): nothing lies behind
        e = np.where(np.isfinite(cos), ndtr(-threshold / (noise * np.maximum(cos, 1e-6))), 0.0)
    return float(e.sum()), float(np.sum(e * (1.0 - e)))
