"""scripts/nearby_plateau.py (issue 32, BENCHMARKS.md "Residual tissue at seed 3: no rule on the fits' scores"):
on a clean simulated CT-crest frame kept at the truth, the kept fit is the truth's own, the far fits are those
whose template moved by more than the tolerance and ``delta`` is the best far fit's score less the kept fit's; an
estimate's poses are taken at the nearest stamp; bad counts are refused with the option named."""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

from app.geometry import se3
from app.sim.simulator import simulate
from app.trial.reader import open_trial
from app.trial.tum import write_tum

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("nearby_plateau", ROOT / "scripts" / "nearby_plateau.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_kept_at_the_truth_of_a_clear_view_the_far_fits_and_their_delta(tmp_path, crest_mesh_path):
    simulate(tmp_path / "trial", mesh_path=crest_mesh_path, scenario_name="static_clear", seconds=0.1, seed=0)
    rows = _script().main([str(tmp_path / "trial"), "--every", "4", "--from-frame", "0", "--starts", "3",
                           "--sigma-p", "0.004", "--sigma-r", "4", "--json", str(tmp_path / "rows.json")])
    assert len(rows) >= 2 and (tmp_path / "rows.json").exists()
    for row in rows:
        kept, truth = row["kept"], row["truth"]
        assert kept["converged"] and kept["add_mm"] < 0.5
        assert truth["gap_mm"] == pytest.approx(0.0, abs=1e-9)      # the same refinement from the same pose
        assert len(row["fits"]) == 6 and {f["width"] for f in row["fits"]} == {"0", "default"}
        far = [f for f in row["fits"] if f["converged"] and f["gap_mm"] > 1.0]
        assert row["far"] == far
        if far:
            best = max(far, key=lambda f: f["consistent"])
            assert row["delta"] == pytest.approx(best["consistent"] - kept["consistent"])
        else:
            assert row["best_far"] is None and math.isnan(row["delta"])


def test_an_estimate_is_taken_at_the_nearest_stamp(tmp_path, crest_mesh_path):
    simulate(tmp_path / "trial", mesh_path=crest_mesh_path, scenario_name="static_clear", seconds=0.1, seed=0)
    reader = open_trial(tmp_path / "trial")
    T_truth = np.asarray(reader.groundtruth, float)
    shifted = T_truth @ se3.from_quat_trans(np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.002, 0.0, 0.0]))
    (tmp_path / "est").mkdir()
    write_tum(tmp_path / "est" / "estimate.txt", np.asarray(reader.stamps) + 1e-4, shifted)
    kept = _script()._kept_poses(reader, str(tmp_path / "est"))
    np.testing.assert_allclose(kept, shifted)
    np.testing.assert_allclose(_script()._kept_poses(reader, None), T_truth)


@pytest.mark.parametrize("option", [["--every", "0"], ["--starts", "0"]])
def test_counts_below_one_are_refused(tmp_path, capsys, option):
    with pytest.raises(SystemExit):
        _script().main([str(tmp_path), *option])
    assert f"{option[0]} 0" in capsys.readouterr().err
