"""Success against budget (app/bench/budget.py; issue 33, item 4): the curve's counts from known runs,
and ``osteonav bench-init`` writing it into its JSON and as a PNG beside it on a tiny run."""
from __future__ import annotations

import json

import numpy as np
import pytest

from app.bench.budget import curve


def _run(method, solved_at, spent):
    return {"sampler": method, "evaluations_to_success": solved_at, "evaluations": spent}


def test_the_curve_counts_the_starts_solved_within_each_budget():
    rows = [_run("mh", 300, 1000), _run("mh", None, 1000), _run("mh", 900, 1000),
            _run("detector", 4000, 4000), _run("detector", 4000, 4000), _run("detector", None, 8000)]
    result = curve(rows)
    assert result["budgets"] == [0, 300, 900, 4000, 8000]
    assert result["successes"] == {"mh": [0, 1, 2, 2, 2], "detector": [0, 0, 0, 2, 2]}
    assert result["starts"] == {"mh": 3, "detector": 3}


def test_the_curve_of_no_success_is_flat_at_zero():
    result = curve([_run("smc", None, 500)])
    assert result["budgets"] == [0, 500] and result["successes"] == {"smc": [0, 0]}


def _pelvis_or_skip():
    from tests.conftest import PELVIS_DIR, pelvis_meshes

    if not pelvis_meshes():
        pytest.skip(f"real pelvis meshes not found in {PELVIS_DIR}")


def test_bench_init_writes_the_success_against_budget_curve_and_its_plot(tmp_path, capsys):
    """One crest, one view, one point, a 0.2 s trial, a 100-evaluation budget: every sampler and the
    detector run; the JSON's curve is non-decreasing for each of them and ends at its successes; the
    PNG is written beside the JSON, and a second run without --overwrite is refused before any work."""
    _pelvis_or_skip()
    from app.cli import main

    out = tmp_path / "init.json"
    argv = ["bench-init", "--crests", "crest_left_02.ply", "--seconds", "0.2", "--samplers", "--budget", "100",
            "--work", str(tmp_path / "work"), "--json", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    result = report["budget"]
    budgets = np.asarray(result["budgets"])
    assert budgets[0] == 0 and np.all(np.diff(budgets) > 0)
    for method, counts in result["successes"].items():
        assert len(counts) == len(budgets) and np.all(np.diff(counts) >= 0), method
        successes = sum(1 for r in report["runs"] if r["sampler"] == method and r["success"])
        assert counts[-1] == successes and result["starts"][method] == 1
    assert set(result["successes"]) == {"mh", "mtm", "smc", "smc_verified", "detector"}
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"wrote {out} and {png}" in capsys.readouterr().out
    out.unlink()                                                    # the plot alone still stops a rerun
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert "--json's plot" in err and "init.png already exists; pass --overwrite" in err and not out.exists()


def test_bench_init_without_samplers_plots_the_replays_start_against_its_evaluations(tmp_path):
    """The replay's start (one crest, one view, a 0.2 s trial): the curve of 'detector, from the point'
    steps from 0 to the runs found within 1 mm at the evaluations their attempts spent."""
    _pelvis_or_skip()
    from app.cli import main

    out = tmp_path / "start.json"
    main(["bench-init", "--crests", "crest_left_02.ply", "--seconds", "0.2", "--work", str(tmp_path / "work"),
          "--json", str(out)])
    report = json.loads(out.read_text())
    (run,) = report["runs"]
    result = report["budget"]
    counts = result["successes"]["detector, from the point"]
    assert counts[0] == 0 and counts[-1] == int(run["found_1mm"]) and np.all(np.diff(counts) >= 0)
    if run["found_1mm"]:
        assert counts[result["budgets"].index(run["evaluations"])] == 1
    assert out.with_suffix(".png").read_bytes()[:4] == b"\x89PNG"


def test_bench_init_simulates_the_sensor_and_the_views_asked_for(tmp_path):
    """``--sensor stereo --first-view 2``: the start's trial is the stereo model's (its trial.yaml says so)
    of the simulator's seed 2, and each row names its sensor and view (held-out views and sensors)."""
    _pelvis_or_skip()
    import yaml

    from app.cli import main

    out = tmp_path / "init.json"
    code = main(["bench-init", "--crests", "crest_left_02.ply", "--seconds", "0.2", "--sensor", "stereo",
                 "--first-view", "2", "--work", str(tmp_path / "work"), "--json", str(out)])
    report = json.loads(out.read_text())
    (row,) = report["runs"]
    assert (row["sensor"], row["view"], row["seed"]) == ("stereo", 2, 0)
    assert code == (0 if row["found_1mm"] and not row["ok_off_2mm"] else 1)
    start = tmp_path / "work" / "crest_left_02_static_clear_stereo_v2_s0"
    meta = yaml.safe_load((start / "trial.yaml").read_text())
    assert meta["sensor"]["model"] == "stereo" and "initial_pose" not in meta
    # the start's trial shares the cached trial's frames (hard links), with its own trial.yaml; the cache keeps its pose
    cached = tmp_path / "work" / "crest_left_02_stereo_view2_0.2s"
    assert "initial_pose" in yaml.safe_load((cached / "trial.yaml").read_text())
    files = [p for p in start.rglob("*") if p.is_file() and p.name != "trial.yaml"]
    assert files and all(p.stat().st_ino == (cached / p.relative_to(start)).stat().st_ino for p in files)
    assert (start / "trial.yaml").stat().st_ino != (cached / "trial.yaml").stat().st_ino
