"""End to end: ``osteonav track`` on a simulated session and on a RealSense recording session,
each recording a trial that ``osteonav replay`` reads back."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml


from app.cli import main

SIM = {"scenario": "static_clear", "seconds": 1.5, "seed": 3}


@pytest.fixture(scope="module")
def sim_trial(tmp_path_factory):
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("sim") / "trial"
    simulate(out, scenario_name=SIM["scenario"], seconds=SIM["seconds"], seed=SIM["seed"])
    return out


def _check_outputs(out: Path, rec: Path, tmp_path: Path) -> None:
    summary = json.loads((out / "summary.json").read_text())
    assert summary["processed"] > 3
    assert summary["latency_ms"]["median"] > 0 and summary["latency_ms"]["p99"] >= summary["latency_ms"]["median"]
    assert (out / "estimate.txt").read_text().count("\n") == summary["processed"] + 1
    assert summary["outputs"]["Recorder"]["dropped"] == 0
    assert (out / "log.rrd").stat().st_size > 0
    replay_out = tmp_path / "replayed"
    assert main(["replay", str(rec), "--out", str(replay_out), "--no-rrd"]) == 0
    from app.trial.reader import open_trial

    n_recorded = len(open_trial(rec).stamps)
    assert n_recorded == summary["frames"]["frames_accepted"]
    assert (replay_out / "status.csv").read_text().count("\n") == n_recorded + 1


def test_track_simulated_session_records_a_replayable_trial(tmp_path, sim_trial):
    session = {
        "camera": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
        "robot": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
        "outputs": [{"plugin": "rerun", "params": {"path": str(tmp_path / "out" / "log.rrd")}}],
    }
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(session))
    out, rec = tmp_path / "out", tmp_path / "rec"
    assert main(["track", "--config", str(path), "--out", str(out), "--record", str(rec)]) == 0
    _check_outputs(out, rec, tmp_path)


def test_track_realsense_recording_session(tmp_path, sim_trial):
    pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed")
    from plugins.realsense import write_trial_recording

    recording = write_trial_recording(sim_trial, tmp_path / "sim")
    session = {
        "camera": {"plugin": "realsense", "params": {"recording": str(recording)}},
        "robot": {"plugin": "recorded", "params": {"trial": str(sim_trial)}},
        "outputs": [{"plugin": "rerun", "params": {"path": str(tmp_path / "out" / "log.rrd")}}],
    }
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(session))
    out, rec = tmp_path / "out", tmp_path / "rec"
    assert main(["track", "--config", str(path), "--out", str(out), "--record", str(rec)]) == 0
    _check_outputs(out, rec, tmp_path)
    events = (out / "events.csv").read_text()
    assert "end of the recording" in events
