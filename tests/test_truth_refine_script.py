"""scripts/truth_refine.py (BENCHMARKS.md §6o): the refinement started at the ground truth of a clean
simulated CT-crest frame stays at the truth, at width 0 and at the default width; a bad frame step
is refused with the option named."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from app.sim.simulator import simulate

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("truth_refine", ROOT / "scripts" / "truth_refine.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_fit_started_at_the_truth_of_a_clear_view_stays_there(tmp_path, crest_mesh_path):
    simulate(tmp_path / "trial", mesh_path=crest_mesh_path, scenario_name="static_clear", seconds=0.1, seed=0)
    rows = _script().main([str(tmp_path / "trial"), "--every", "4", "--json", str(tmp_path / "rows.json")])
    assert len(rows) >= 2 and (tmp_path / "rows.json").exists()
    for row in rows:
        for fit in (row["width0"], row["default"]):
            assert fit["converged"] and fit["add_mm"] < 0.5 and fit["rot_deg"] < 1.0
            assert fit["sharp"] > 0.5 and fit["behind_excess"] <= 0.002


def test_a_frame_step_below_one_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        _script().main([str(tmp_path), "--every", "0"])
    assert "--every 0" in capsys.readouterr().err
