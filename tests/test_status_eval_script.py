"""scripts/status_eval.py (issue 32's benchmark scorer): on a simulated trial with estimates made from its own
ground truth, the counts of ok frames off by more than the tolerances are what the offsets imply."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

import status_eval  # noqa: E402

from app.sim.simulator import simulate  # noqa: E402
from app.trial import tum  # noqa: E402


def _shifted(T: np.ndarray, dx_m: float) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += (dx_m, 0.0, 0.0)       # a pure translation: every point, ADD and template error alike, moves dx
    return out


def test_ok_frames_off_by_more_than_each_tolerance_are_counted(tmp_path):
    trial = tmp_path / "trial"
    simulate(trial, scenario_name="static_clear", seconds=0.3, seed=3)
    t_gt, T_gt = tum.read_tum(trial / "groundtruth.txt")
    n = len(t_gt)
    offsets = np.array([0.0005, 0.0015, 0.0025])[np.arange(n) % 3]          # 0.5, 1.5 and 2.5 mm, in turn
    statuses = np.where(np.arange(n) % 2 == 0, "ok", "uncertain")          # every other frame ok
    out = tmp_path / "out" / "label" / "crest" / "static_clear@independent"
    out.mkdir(parents=True)
    tum.write_tum(out / "estimate.txt", t_gt, np.array([_shifted(T, d) for T, d in zip(T_gt, offsets)]))
    rows = ["stamp,status,state,reasons"] + [f"{t:.9f},{s},tracking," for t, s in zip(t_gt, statuses)]
    (out / "status.csv").write_text("\n".join(rows) + "\n")
    (out / "summary.json").write_text(json.dumps({"trial": str(trial)}))

    r = status_eval.score_run(out)
    ok = statuses == "ok"
    assert r["frames"] == n
    assert r["ok"] == np.mean(ok)
    assert r["ok_over_2mm"] == int(np.sum(ok & (offsets > 0.002)))
    assert r["ok_template_over_1mm"] == int(np.sum(ok & (offsets > 0.001)))
    assert abs(r["add_median_mm"] - np.median(1e3 * offsets)) < 1e-9
    assert abs(r["max_ok_add_mm"] - 1e3 * offsets[ok].max()) < 1e-9
