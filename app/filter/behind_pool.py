"""The behind rule over the last frames of one track (the status's behind rule, pooled).

Import as ``from app.filter.behind_pool import BehindPool`` (used by app/filter/refine_track.py).

One frame's test (app/filter/refine.py step 7, status.py) compares the share b of the fit's M
measurements lying more than 1 σ inside the model with the share the image's noise explains, the
Poisson-binomial mean plus z = 3 standard deviations: e + z sqrt(v) / M with e = Σ e_i / M, v = Σ
e_i (1 − e_i). A pose that is off by a millimetre or two leaves only a few measurements more behind
it than the noise does, about one frame's standard deviation, and one frame cannot tell that from
chance. The noise of successive frames is independent (the simulated D415; a real sensor's fixed
pattern makes the pooled bound only stricter than it should be, not looser) while a wrong pose's
excess repeats, so the counts of the last ``frames`` frames are added (their means and variances
add) and tested together:

    excess = (Σ_k b_k M_k − Σ_k e_k M_k − z sqrt(Σ_k v_k)) / Σ_k M_k

The bound's share shrinks as 1 / sqrt(frames) and a repeated excess of one standard deviation per
frame shows after a few frames. The rule reports the larger of this and the current frame's own
excess (a fit that slides in one frame is caught at once). Measured in BENCHMARKS.md §6i.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from app.filter.behind_noise import noise_bound


class BehindPool:
    """The pooled behind excess over the last ``frames`` kept fits of one track (module docstring).

    frames : how many fits are pooled (1: the frame's own test); z : standard deviations of the bound.
    """

    def __init__(self, frames: int, z: float):
        if frames < 1:
            raise ValueError(f"BehindPool frames {frames}: at least 1")
        self.z = float(z)
        self._counts: deque = deque(maxlen=int(frames))

    def reset(self) -> None:
        """Forget the pooled frames (a new track)."""
        self._counts.clear()

    def add(self, behind: float, mean: float, var: float, measurements: int) -> float:
        """Add one fit (its share ``behind`` of ``measurements`` behind the model, and the noise's mean and
        variance of that count, app/filter/behind_noise.py ``behind_moments``) and return the pooled
        excess share; NaN when the noise is unknown (the frame is not pooled: the caller keeps the
        frame's own test)."""
        if not np.isfinite(noise_bound(mean, var, measurements, self.z)) or not np.isfinite(behind):
            return float("nan")
        self._counts.append((behind * measurements, mean, var, measurements))
        count, mu, variance, total = (sum(c[k] for c in self._counts) for k in range(4))
        return float(count / total - noise_bound(mu, variance, total, self.z))
