"""The rate benchmark's table (app/bench/rate.py): the refinement's stage and what it adds to a frame."""
from __future__ import annotations

import pytest

from app.bench import rate


def _row(backend, fps, refine_ms=None):
    """A row as ``rate.measure`` makes it; CPU per frame = wall per frame here, refinement CPU = its wall."""
    stages = {"predict": 0.3, "likelihood": 10.0, "weight": 0.1, "resample": 0.2, "estimate": 1.0}
    if refine_ms is not None:
        stages["refine"] = refine_ms
    frame_ms = 1e3 / fps
    return {"backend": backend, "particles": 200, "resolution": "160x120", "fps": fps, "full_frame_ms": frame_ms,
            "process_cpu_ms": frame_ms, "backend_ms": 9.0, "stages_ms": stages, "refine_ms": refine_ms,
            "refine_cpu_ms": refine_ms, "refine_added": rate._refine_added(refine_ms, frame_ms)}


def test_refine_added_is_the_refinement_over_the_rest_of_the_frame():
    assert rate._refine_added(3.0, 13.0) == pytest.approx(0.3)          # 10 ms of filter + 3 ms of refinement
    assert rate._refine_added(None, 13.0) is None                       # refinement off
    assert rate._refine_added(5.0, 4.0) is None                         # inconsistent timings: no claim


def test_the_table_shows_the_refine_column_only_when_a_row_refines():
    without = rate.table([_row("cpu", 80.0), _row("gl", 10.0)])
    assert "refine" not in without
    text = rate.table([_row("cpu", 50.0, refine_ms=4.0), _row("gl", 10.0)])
    header, _, cpu_line, gl_line = text.splitlines()
    assert header.split()[-2:] == ["refine", "+%cpu"]
    cpu = cpu_line.split()
    assert float(cpu[-2]) == pytest.approx(4.0) and cpu[-1] == "25"   # 4 / (20 - 4) = 25 %
    assert float(cpu[4]) == pytest.approx(5.0)                          # x gl: 50 / 10 frames/s
    assert gl_line.split()[-2:] == ["nan", "-"]


def test_the_refinement_cpu_wrapper_passes_calls_through_and_adds_up_only_their_cpu_time(monkeypatch):
    """On a manual process clock: each refinement call costs 3 ms, the work between calls 50 ms; the
    total is the calls' 6 ms (a failing call's time included), never the work around them."""
    import types

    cpu = types.SimpleNamespace(t=10.0)
    monkeypatch.setattr(rate, "time", types.SimpleNamespace(process_time=lambda: cpu.t))

    class Track:
        def __init__(self):
            self.calls = []

        def update(self, depth, T_base_camera, T_guess):
            self.calls.append((depth, T_base_camera, T_guess))
            cpu.t += 0.003
            if depth is None:
                raise ValueError("no depth")
            return "fit"

    class Tracker:
        refined_track = Track()

    tracker = Tracker()
    total = rate._time_refinement_cpu(tracker)
    assert total == [0.0]
    cpu.t += 0.05                                        # the rest of the frame
    assert tracker.refined_track.update(1, 2, T_guess=3) == "fit"
    cpu.t += 0.05
    with pytest.raises(ValueError):
        tracker.refined_track.update(None, 2, T_guess=3)
    assert tracker.refined_track.calls == [(1, 2, 3), (None, 2, 3)]
    assert total[0] == pytest.approx(0.006, abs=1e-12)
    Tracker.refined_track = None
    assert rate._time_refinement_cpu(Tracker()) == [0.0]


# ------------------------------------------------------------------------------------------------
# --whole: the whole tracker beside the ICP baseline on one trial (app/bench/whole.py)
# ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_trial(tmp_path_factory):
    """A 0.1 s static_clear trial of the default mesh: 9 frames."""
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("whole") / "trial"
    simulate(out, scenario_name="static_clear", seconds=0.1, seed=1)
    return out


def test_whole_runs_both_engines_on_the_same_frames_and_its_rows_add_up(tmp_path, tiny_trial):
    """No time is asserted: the rows exist, both engines timed the same frames, the stage shares are
    shares of the frame's wall time (sum <= 100 %, the rest is 'other'), and the counts fit."""
    import json

    from app.cli import main

    out = tmp_path / "whole.json"
    assert main(["bench-rate", "--whole", "--trial", str(tiny_trial), "--frames", "4", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    t, i = result["tracker"], result["icp"]
    assert result["frames"] == t["frames"] == i["frames"] == 4 and result["warmup"] == 3
    assert t["timed_frames_in_stages"] == 4                   # the tracker's own timings cover the timed frames
    assert sum(t["status_counts"].values()) == sum(i["status_counts"].values()) == 4
    for row in (t, i):
        assert row["fps"] > 0 and row["frame_ms"] == pytest.approx(1e3 * row["wall_s"] / 4)
        assert row["fps"] == pytest.approx(1e3 / row["frame_ms"])
    assert result["ratio"] == pytest.approx(t["fps"] / i["fps"])
    assert result["cpu_ratio"] == pytest.approx(i["cpu_ms"] / t["cpu_ms"])
    # the default tracker: its filter stages and the refinement, each a share of the frame
    assert {"predict", "likelihood", "weight", "resample", "estimate", "refine"} <= set(t["stages_ms"])
    shares = t["stage_shares"]
    assert all(0 <= v for v in shares.values()) and sum(shares.values()) <= 1.0 + 1e-9
    assert t["other_share"] == pytest.approx(1.0 - sum(shares.values()))
    for stage, ms in t["stages_ms"].items():
        assert shares[stage] == pytest.approx(ms / t["frame_ms"])
    assert all(k.startswith(f"{t['description'].split(', ')[1].split()[0]}_") for k in t["backend_stages_ms"])
    assert 0 <= t["refined_frames"] <= 4 and 0 <= t["search_frames"] <= 4
    assert t["search_share"] == pytest.approx(t["search_frames"] / 4)
    # filter.stages side by side (app/pipeline/stages.py): a row each, the same statuses, identical outputs
    rows = result["stages"]
    assert set(rows) == {"serial", "parallel"} and rows[result["configured_stages"]] == t
    assert rows["serial"]["stages_mode"] == "serial" and rows["parallel"]["stages_mode"] == "parallel"
    assert rows["serial"]["status_counts"] == rows["parallel"]["status_counts"]
    assert result["stages_identical"] and result["stages_differing_frames"] == 0
    assert result["stages_compared_frames"] == 4 + result["warmup"]
    assert result["stages_ratio"] == pytest.approx(rows["parallel"]["fps"] / rows["serial"]["fps"])
    assert result["stages_cpu_ratio"] == pytest.approx(rows["parallel"]["cpu_ms"] / rows["serial"]["cpu_ms"])
    assert all(0 < row["main_cpu_ms"] <= row["cpu_ms"] + 1e-6 for row in rows.values())
    assert "refine_ahead" in rows["parallel"]["overlapped_ms"] and not rows["serial"]["overlapped_ms"]
    assert "refine_ahead" not in rows["parallel"]["stages_ms"]          # not a share of the frame: it overlapped


def test_whole_runs_one_stages_mode_when_asked(tmp_path, tiny_trial, capsys):
    import json

    from app.cli import main

    out = tmp_path / "whole.json"
    assert main(["bench-rate", "--whole", "--trial", str(tiny_trial), "--frames", "1", "--stages", "serial",
                 "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["stages"]) == {"serial"} and result["stages_ratio"] is None
    assert result["tracker"]["stages_mode"] == "serial"
    assert "tracker serial" in capsys.readouterr().out


def test_whole_refuses_bad_input_with_one_line(tmp_path, tiny_trial, capsys):
    from app.cli import main

    assert main(["bench-rate", "--whole", "--trial", str(tmp_path), "--json", str(tmp_path / "a.json")]) != 0
    assert "--trial" in capsys.readouterr().err
    assert main(["bench-rate", "--trial", str(tiny_trial), "--json", str(tmp_path / "b.json")]) != 0
    assert "--whole" in capsys.readouterr().err
    assert main(["bench-rate", "--whole", "--trial", str(tiny_trial), "--frames", "4", "--particles", "100",
                 "--json", str(tmp_path / "c.json")]) != 0
    assert "--config" in capsys.readouterr().err
    assert main(["bench-rate", "--stages", "serial", "--json", str(tmp_path / "d.json")]) != 0
    assert "--whole" in capsys.readouterr().err
    assert not any((tmp_path / n).exists() for n in ("a.json", "b.json", "c.json", "d.json"))
