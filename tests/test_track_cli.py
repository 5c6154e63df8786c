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


def _check_outputs(out: Path, rec: Path, tmp_path: Path, sim_trial: Path | None = None) -> None:
    summary = json.loads((out / "summary.json").read_text())
    processed = summary["processed"]
    lat, stages = summary["latency_ms"], summary["latency_stages_ms"]
    assert lat["n"] == processed and all(v["n"] == processed for v in stages.values())
    # per frame: latency = capture->arrival + queue wait + tracker, each >= 0, so every order
    # statistic of the latency is at least the tracker's own
    assert lat["median"] >= stages["tracker"]["median"] and lat["max"] >= stages["tracker"]["max"]
    assert (out / "estimate.txt").read_text().count("\n") == processed + 1
    recorder = summary["outputs"]["Recorder"]
    assert recorder["dropped"]["queue"] == recorder["dropped"]["disk"] == 0 and recorder["complete"]
    assert Path(summary["outputs"]["RerunOutput"]["path"]).stat().st_size > 0
    if sim_trial is not None:
        _check_tracking_error(out, rec, sim_trial, processed)
    replay_out = tmp_path / "replayed"
    assert main(["replay", str(rec), "--out", str(replay_out), "--no-rrd"]) == 0
    from app.trial.reader import open_trial

    n_recorded = len(open_trial(rec).stamps)
    assert n_recorded == summary["frames"]["frames_accepted"]
    assert (replay_out / "status.csv").read_text().count("\n") == n_recorded + 1


def _check_tracking_error(out: Path, rec: Path, sim_trial: Path, processed: int):
    """The live estimates against the simulated trial's ground truth, frame by frame.

    An estimate's stamp is its frame's (host) stamp; the recorded trial maps that stamp to the
    camera's frame id, and the simulated trial holds that frame's true pose. The live loop tracks
    the newest frame and skips the rest, and the filter's accuracy falls with the gap between the
    frames it sees (this trial, every frame: ADD 0.5 mm; every 8th: 2-3 mm; every 20th: ~10 mm;
    live on a loaded 2-core machine, 5-17 tracked per second: 2-20 mm, status uncertain). So the
    bound is that the track stays on the bone (75 % of the frames within 20 mm; a diverged filter
    ends 100 mm and more away). The safety rule (no frame ok while ADD > 5 mm) is checked by the
    slow test below: in a live session on a loaded machine it is broken now and then (measured:
    an ok frame at 5.09 mm on the third tracked frame), a finding for the tracker's status rules,
    which replay (every frame) never shows on this trial.
    """
    from app.metrics import add
    from app.trial.reader import open_trial
    from app.trial.tum import read_tum

    stamps, T_est = read_tum(out / "estimate.txt")
    # how many frames a live loop tracks depends on the machine's load (wall time): at least one. A 2-core
    # machine running two bench workers beside this suite tracked 2 of the 1.5 s trial (the first frame,
    # with its multi-start, took 1.5 s there); an idle one ~15 per second
    assert len(stamps) == processed >= 1
    recorded, truth = open_trial(rec), open_trial(sim_trial)
    rec_index = {round(float(t), 6): int(f) for t, f in zip(recorded.stamps, recorded.frame_ids)}
    gt_index = {int(f): k for k, f in enumerate(truth.frame_ids)}
    points = np.asarray(truth.load_mesh().vertices)
    from app.trial.tum import read_status_csv

    _, statuses = read_status_csv(out / "status.csv")
    errors_mm = []
    for t, T in zip(stamps, T_est):
        k = gt_index[rec_index[round(float(t), 6)] % 10_000_000]
        errors_mm.append(1e3 * add(T, truth.groundtruth[k], points))
    errors_mm = np.asarray(errors_mm)
    assert np.mean(errors_mm < 20.0) >= 0.75, errors_mm.round(2)
    return np.asarray(statuses), errors_mm


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
    _check_outputs(out, rec, tmp_path, sim_trial)


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
    _check_outputs(out, rec, tmp_path)   # the bag's frame ids are the SDK's, not the trial's
    events = (out / "events.csv").read_text()
    assert "end of the recording" in events


@pytest.mark.slow
def test_live_session_never_reports_ok_while_more_than_5_mm_off(tmp_path):
    """The safety rule in the live loop: a 6 s simulated static_clear session played in real time
    (the tracker sees the frames it has time for), every ok frame within 5 mm of the truth."""
    from app.sim.simulator import simulate

    sim = tmp_path / "sim"
    params = {"scenario": "static_clear", "seconds": 6.0, "seed": 3, "trial_dir": str(sim)}
    simulate(sim, scenario_name="static_clear", seconds=6.0, seed=3)
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump({"camera": {"plugin": "simulated", "params": params},
                                    "robot": {"plugin": "simulated", "params": params}}))
    out, rec = tmp_path / "out", tmp_path / "rec"
    assert main(["track", "--config", str(path), "--out", str(out), "--record", str(rec)]) == 0
    processed = json.loads((out / "summary.json").read_text())["processed"]
    statuses, errors_mm = _check_tracking_error(out, rec, sim, processed)
    dangerous = (statuses == "ok") & (errors_mm > 5.0)
    assert not dangerous.any(), f"{dangerous.sum()} of {processed} frames ok while > 5 mm off: {errors_mm[dangerous].round(2)}"
