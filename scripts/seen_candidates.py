"""The seen test's bound on held-out sensor models: the fixed inflation against a noise-scaled one.

Usage (JSON files of scripts/template_coverage.py, one per sensor model, named SENSOR=FILE)::

    .venv/bin/python scripts/seen_candidates.py independent=/tmp/cov_independent.json \\
        stereo=/tmp/cov_stereo.json tof=/tmp/cov_tof.json --calibrate independent --crests left

The status's seen test bounds the template's error by sqrt(k) σ₁, σ₁ the refinement's predicted
largest std at inflation 1 (Σ = H⁻¹, app/filter/refine.py ``template_std``) and k =
``status.covariance_inflation`` (fixed). The candidate scales Σ by what the image measures instead,
as least squares does with an estimated residual variance and correlated samples:

    Σ = c · f · (σ̂_n / σ(z))² · H⁻¹

with f the residuals' correlation factor and σ̂_n their scale (app/tracking/fit_test.py), σ(z) the
configured noise H was weighted by, and c chosen so that the bound covers the measured worst-point
error on ``--quantile`` of the calibration frames (one sensor model, the crests whose name holds
``--crests``). The table gives, per sensor model and crest, each bound's coverage (share of frames
with error <= bound) and median, beside the measured error's median; the calibration's crests are
marked, everything else is held out.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def columns(run: dict) -> dict[str, np.ndarray]:
    """One run's per-frame arrays: error (m), σ₁ (m) and the noise scaling f (σ̂_n / σ(z))²."""
    error, std1 = np.asarray(run["error_m"]), np.asarray(run["std1_m"])
    rho = np.asarray(run["noise_m"]) / np.asarray(run["sigma_model_m"])
    return {"error": error, "std1": std1, "scaling": np.asarray(run["f"]) * rho * rho}


def calibrate(runs: list[dict], quantile: float) -> float:
    """c of the noise-scaled bound: quantile of error / (σ₁ sqrt(scaling)), squared."""
    ratio = np.concatenate([c["error"] / (c["std1"] * np.sqrt(c["scaling"])) for c in map(columns, runs)])
    return float(np.quantile(ratio, quantile) ** 2)


def rows(sensors: dict[str, dict], c: float, inflation: float, calibration: tuple[str, str]) -> list[dict]:
    """Per sensor model and run: coverage and median bound of the fixed and the noise-scaled bound."""
    out = []
    for sensor, runs in sensors.items():
        for name, run in runs.items():
            col = columns(run)
            fixed = np.sqrt(inflation) * col["std1"]
            scaled = np.sqrt(c * col["scaling"]) * col["std1"]
            out.append({"sensor": sensor, "run": name,
                        "calibration": sensor == calibration[0] and calibration[1] in name,
                        "error_mm": 1e3 * float(np.median(col["error"])),
                        "fixed_cover": float(np.mean(col["error"] <= fixed)), "fixed_mm": 1e3 * float(np.median(fixed)),
                        "scaled_cover": float(np.mean(col["error"] <= scaled)),
                        "scaled_mm": 1e3 * float(np.median(scaled)),
                        "scaling": float(np.median(col["scaling"]))})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", help="SENSOR=template_coverage.json")
    ap.add_argument("--calibrate", default="independent", help="the sensor model c is chosen on")
    ap.add_argument("--crests", default="left", help="c is chosen on the runs whose name holds this")
    ap.add_argument("--quantile", type=float, default=0.9)
    ap.add_argument("--inflation", type=float, default=None,
                    help="the fixed bound's inflation (default: configs/default.yaml's status.covariance_inflation)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    if args.inflation is None:
        from app.config import load_config

        args.inflation = load_config(None).status.covariance_inflation
    sensors = {}
    for item in args.files:
        sensor, _, path = item.partition("=")
        sensors[sensor] = json.loads(Path(path).read_text())["runs"]
    cal = [r for n, r in sensors[args.calibrate].items() if args.crests in n]
    c = calibrate(cal, args.quantile)
    table = rows(sensors, c, args.inflation, (args.calibrate, args.crests))
    print(f"c = {c:.2f} (q {args.quantile} on {args.calibrate}, {len(cal)} runs holding '{args.crests}')")
    print("sensor      | run                          | error mm | fixed: cover, bound mm | scaled: cover, bound mm | f rho^2")
    for r in table:
        mark = "*" if r["calibration"] else " "
        print(f"{r['sensor']:11s} | {r['run'][:27]:27s}{mark} | {r['error_mm']:8.2f} | {r['fixed_cover']:5.2f}, {r['fixed_mm']:5.2f}"
              f"          | {r['scaled_cover']:5.2f}, {r['scaled_mm']:5.2f}           | {r['scaling']:.2f}")
    if args.json:
        args.json.write_text(json.dumps({"c": c, "rows": table}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
