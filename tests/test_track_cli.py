"""End to end: ``osteonav track`` on a simulated session and on a RealSense recording session,
each recording a trial that ``osteonav replay`` reads back."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml


from app.cli import main
from tests.clocks import lockstep_sessions

SIM = {"scenario": "static_clear", "seconds": 1.5, "seed": 3}


@pytest.fixture(scope="module")
def sim_trial(tmp_path_factory):
    from app.sim.simulator import simulate

    out = tmp_path_factory.mktemp("sim") / "trial"
    simulate(out, scenario_name=SIM["scenario"], seconds=SIM["seconds"], seed=SIM["seed"])
    return out


def _check_outputs(out: Path, rec: Path, tmp_path: Path) -> dict:
    summary = json.loads((out / "summary.json").read_text())
    processed = summary["processed"]
    lat, stages = summary["latency_ms"], summary["latency_stages_ms"]
    assert lat["n"] == processed and all(v["n"] == processed for v in stages.values())
    # per frame: latency = capture->arrival + queue wait + tracker, so the largest latency is at most
    # the sum of the stages' largest (more would be time the stages do not account for)
    parts = ("capture_to_arrival", "queue_wait", "tracker")
    assert lat["max"] <= sum(stages[k]["max"] for k in parts) + 1e-6
    assert (out / "estimate.txt").read_text().count("\n") == processed + 1
    recorder = summary["outputs"]["Recorder"]
    assert recorder["dropped"]["queue"] == recorder["dropped"]["disk"] == 0 and recorder["complete"]
    assert Path(summary["outputs"]["RerunOutput"]["path"]).stat().st_size > 0
    replay_out = tmp_path / "replayed"
    assert main(["replay", str(rec), "--out", str(replay_out), "--no-rrd"]) == 0
    from app.trial.reader import open_trial

    n_recorded = len(open_trial(rec).stamps)
    assert n_recorded == summary["frames"]["frames_accepted"]
    assert (replay_out / "status.csv").read_text().count("\n") == n_recorded + 1
    return summary


def _tracking_errors(out: Path, rec: Path, sim_trial: Path):
    """The live estimates against the simulated trial's ground truth, frame by frame: (statuses,
    ADD errors in mm, the simulated trial's frame count).

    An estimate's stamp is its frame's (host) stamp; the recorded trial maps that stamp to the
    camera's frame id, and the simulated trial holds that frame's true pose.
    """
    from app.metrics import add
    from app.trial.reader import open_trial
    from app.trial.tum import read_status_csv, read_tum

    stamps, T_est = read_tum(out / "estimate.txt")
    recorded, truth = open_trial(rec), open_trial(sim_trial)
    rec_index = {round(float(t), 6): int(f) for t, f in zip(recorded.stamps, recorded.frame_ids)}
    gt_index = {int(f): k for k, f in enumerate(truth.frame_ids)}
    points = np.asarray(truth.load_mesh().vertices)
    _, statuses = read_status_csv(out / "status.csv")
    errors_mm = []
    first, span = int(truth.frame_ids[0]), int(truth.frame_ids[-1]) - int(truth.frame_ids[0]) + 1
    for t, T in zip(stamps, T_est):
        k = gt_index[(rec_index[round(float(t), 6)] - first) % span + first]   # a looped lap's ids run on (lap_frame_id)
        errors_mm.append(1e3 * add(T, truth.groundtruth[k], points))
    return np.asarray(statuses), np.asarray(errors_mm), len(truth.frame_ids)


def test_track_simulated_session_records_a_replayable_trial(tmp_path, sim_trial, monkeypatch):
    """The live loop on the lockstep clock (tests/clocks.py): the camera waits for the loop, so the
    tracker sees every frame whatever the machine's load, as replay would, and the live path must
    track as well as replay does on this trial. The robot streams 5 ms of joints past each frame; the
    loop may wait up to 30 s (real time, a safety net) for them to arrive."""
    clocks = lockstep_sessions(monkeypatch, lead_s=0.005)
    session = {
        "camera": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
        "robot": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
        "outputs": [{"plugin": "rerun", "params": {"path": str(tmp_path / "out" / "log.rrd")}}],
        "loop": {"robot_wait_s": 30.0},
    }
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(session))
    out, rec = tmp_path / "out", tmp_path / "rec"
    assert main(["track", "--config", str(path), "--out", str(out), "--record", str(rec)]) == 0
    summary = _check_outputs(out, rec, tmp_path)
    statuses, errors_mm, n_frames = _tracking_errors(out, rec, sim_trial)
    # every frame of the trial delivered, accepted, tracked with its camera pose; none skipped
    assert len(clocks) == 1 and clocks[0].frames_pushed == n_frames
    assert summary["processed"] == summary["frames"]["frames_accepted"] == len(errors_mm) == n_frames
    assert summary["frames_skipped_by_tracker"] == summary["frames_skipped_by_camera"] == 0
    assert "no_camera_pose" not in (out / "events.csv").read_text()
    # the latency on this clock: each frame arrives lead_s after its stamp and is popped and
    # tracked at once (the tracker's work takes no session time), so every stage is exact
    stages = summary["latency_stages_ms"]
    assert summary["latency_ms"]["max"] == pytest.approx(5.0) and summary["latency_ms"]["median"] == pytest.approx(5.0)
    assert stages["capture_to_arrival"]["max"] == pytest.approx(5.0)
    assert stages["queue_wait"]["max"] == pytest.approx(0.0, abs=1e-9) == stages["tracker"]["max"]
    # accuracy, as replay tracks this trial (every frame, with the refinement): measured here 0.015-0.035
    # mm ADD over the 134 frames (lockstep, seed 3, the cpu backend). Bound with a 14x margin for
    # another backend or machine: every frame under 0.5 mm. The status settles to ok (measured from
    # frame 45 on) and stays there: the second half all ok, and never ok more than 5 mm off
    assert errors_mm.max() < 0.5, errors_mm.round(3)
    assert set(statuses[n_frames // 2:]) == {"ok"}, statuses
    assert not ((statuses == "ok") & (errors_mm > 5.0)).any()


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
    (the tracker sees the frames it has time for), every ok frame within 5 mm of the truth.

    Real time on purpose (the lockstep test above tracks every frame): the filter's accuracy falls
    with the gap between the frames it sees (this trial, every frame: ADD 0.5 mm; every 8th: 2-3 mm;
    every 20th: ~10 mm; live on a loaded 2-core machine, 5-17 tracked per second: 2-20 mm, status
    uncertain), and the status must say so. Measured on a loaded machine: an ok frame at 5.09 mm
    on the third tracked frame now and then, a finding for the tracker's status rules.
    """
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
    statuses, errors_mm, _ = _tracking_errors(out, rec, sim)
    assert len(errors_mm) == processed >= 1
    dangerous = (statuses == "ok") & (errors_mm > 5.0)
    assert not dangerous.any(), f"{dangerous.sum()} of {processed} frames ok while > 5 mm off: {errors_mm[dangerous].round(2)}"


def test_a_sessions_estimates_do_not_depend_on_its_outputs(tmp_path, sim_trial, monkeypatch):
    """Issue 34: the tracker bounds the plan's template points whether or not the session has a
    projector output (app/pipeline/tracker.py ``use_projector_plan``: else the default projector
    configuration's plan, as replay does). The same session with a headless projector output and with
    no output at all writes byte-identical estimate.txt and status.csv (lockstep clock: every frame)."""
    runs = {}
    for name, outputs in (("projector", [{"plugin": "projector", "params": {"png_dir": str(tmp_path / "png"),
                                                                           "every": 50, "rerun": False}}]),
                          ("none", [])):
        monkeypatch.undo()                       # one lockstep clock per session (its hooks wrap the loop)
        lockstep_sessions(monkeypatch, lead_s=0.005)
        session = {"camera": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
                   "robot": {"plugin": "simulated", "params": {**SIM, "trial_dir": str(sim_trial)}},
                   "outputs": outputs, "loop": {"robot_wait_s": 30.0}}
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(session))
        out = tmp_path / name
        assert main(["track", "--config", str(path), "--out", str(out)]) == 0
        runs[name] = [(out / f).read_text() for f in ("estimate.txt", "status.csv")]
        assert runs[name][0].count("\n") == 135     # the header and each of the trial's 134 frames
    assert runs["projector"] == runs["none"]
