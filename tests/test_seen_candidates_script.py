"""scripts/seen_candidates.py and template_coverage.py's edge probe (BENCHMARKS.md "The seen test on time
of flight"): the noise-scaled bound's constant and coverage against closed forms; the edge band's pixels."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import seen_candidates  # noqa: E402
import template_coverage  # noqa: E402


def _run(error_mm, std1_mm, f, noise_mm, sigma_mm):
    n = len(error_mm)
    return {"error_m": list(1e-3 * np.asarray(error_mm)), "std1_m": [1e-3 * std1_mm] * n, "f": [f] * n,
            "noise_m": [1e-3 * noise_mm] * n, "sigma_model_m": [1e-3 * sigma_mm] * n}


def test_calibrated_constant_is_the_squared_quantile_ratio():
    # error = 2 sigma1 sqrt(f rho^2) on every frame: c = 4 at any quantile
    f, rho = 3.0, 0.5
    run = _run([2.0 * 0.4 * np.sqrt(f) * rho] * 10, 0.4, f, 0.5, 1.0)
    assert seen_candidates.calibrate([run], 0.9) == pytest.approx(4.0)


def test_coverage_of_fixed_and_scaled_bounds():
    # sigma1 = 0.4 mm: fixed bound sqrt(6) 0.4 = 0.98 mm; scaled with c = 1, f rho^2 = 0.25: 0.2 mm
    run = _run([0.1, 0.3, 0.5, 1.2], 0.4, 1.0, 0.5, 1.0)
    (row,) = seen_candidates.rows({"tof": {"crest_x/static_clear": run}}, 1.0, 6.0, ("independent", "left"))
    assert row["fixed_cover"] == pytest.approx(0.75)
    assert row["scaled_cover"] == pytest.approx(0.25)
    assert row["fixed_mm"] == pytest.approx(np.sqrt(6) * 0.4)
    assert row["scaled_mm"] == pytest.approx(0.2)
    assert not row["calibration"]


def test_edge_band_invalidates_the_pixels_about_a_jump():
    depth = np.full((20, 20), 0.40, np.float32)
    depth[:, 10:] = 0.45                           # a 50 mm step between columns 9 and 10
    depth[0, 0] = 0.0                              # an invalid pixel is a jump too
    masked = template_coverage.edge_masked(depth, 2)
    # the 3x3 range flags columns 9 and 10; dilation by 2 reaches 7..12
    assert np.all(masked[5:15, 7:13] == 0.0)
    assert np.all(masked[5:15, :7] == 0.40) and np.all(masked[5:15, 13:] == np.float32(0.45))
    assert masked[1, 1] == 0.0 and masked[4, 4] == np.float32(0.40)
    assert template_coverage.edge_masked(depth, 0) is depth
