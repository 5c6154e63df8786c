"""Issue 15's command-line fixes that succeed: replay on any CT crest, --overwrite clearing stale
outputs, the k3 decision, the session's rig in `calibrate capture`, the viewer checks, help texts."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml

from app.cli import main
from app.errors import MeshError, OsteonavError
from tests.conftest import pelvis_meshes

REPO = Path(__file__).resolve().parents[1]
CT_CRESTS = pelvis_meshes()


# ---------------------------------------------------------------- replay with defaults on CT crests

@pytest.mark.parametrize("mesh", [pytest.param(p, id=p.stem) for p in CT_CRESTS[1:3]])
def test_replay_with_defaults_succeeds_on_a_ct_crest_and_names_its_plan(tmp_path, capsys, mesh):
    """The default plan (a box at x = -20 mm) leaves these crests; replay used to exit 2."""
    trial, out = tmp_path / "trial", tmp_path / "replay"
    assert main(["simulate", "--out", str(trial), "--mesh", str(mesh), "--seconds", "0.1", "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["replay", str(trial), "--out", str(out)]) == 0   # the defaults: projector on, log.rrd written
    text = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["projector"]["plan"].startswith("box derived from the mesh")
    assert summary["projector"]["plan"] in text
    assert summary["projector"]["frames"] > 0


def test_derived_plan_lies_on_the_ridge_of_every_ct_crest():
    """On each crest the derived 20 x 10 mm box fits (every point on the bone, within the snap
    tolerance) and sits high: its mean height is above the 80th percentile of the top view's."""
    from app.projector.geometry import closest_points_on_mesh
    from app.projector.plan import _height_map, derive_crest_plan

    if not CT_CRESTS:
        pytest.skip("no CT crests")
    for path in CT_CRESTS:
        mesh = trimesh.load(path, process=False)
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        plan = derive_crest_plan("box", v, f)
        _, dist, _ = closest_points_on_mesh(plan.points(), v, f)
        assert dist.max() < 1e-5, path.name   # snapped onto the surface (0.01 mm)
        _, _, z = _height_map(v, f, 0.002)
        assert plan.points()[:, 2].mean() > np.nanpercentile(z, 80), path.name
        extent = np.ptp(plan.points()[:, :2] @ np.linalg.svd(plan.points()[:, :2] - plan.points()[:, :2].mean(0))[2].T,
                        axis=0)
        assert extent[0] == pytest.approx(0.020, abs=0.0015), path.name   # the configured size, not shrunk


def test_replay_skips_the_projector_with_one_warning_when_no_plan_fits(tmp_path, monkeypatch, capsys, caplog):
    from app.projector import config as projector_config

    def nothing_fits(*args, **kwargs):
        raise MeshError("plan 'box': a 20 x 10 mm outline fits nowhere on the crest seen from +z")

    monkeypatch.setattr(projector_config, "derive_crest_plan", nothing_fits)
    monkeypatch.setattr(projector_config, "_configured_plan", nothing_fits)
    trial = tmp_path / "trial"
    assert main(["simulate", "--out", str(trial), "--seconds", "0.05"]) == 0
    assert main(["replay", str(trial), "--out", str(tmp_path / "r"), "--no-rrd"]) == 0
    assert len([r for r in caplog.records if "projector skipped" in r.getMessage()]) == 1
    assert "fits nowhere" in json.loads((tmp_path / "r" / "summary.json").read_text())["projector"]["skipped"]


# ---------------------------------------------------------------- --overwrite clears what the command wrote

def test_replay_overwrite_leaves_no_stale_log_rrd_and_never_removes_anothers(tmp_path):
    from app.outputs import MANIFEST

    trial, out = tmp_path / "trial", tmp_path / "out"
    assert main(["simulate", "--out", str(trial), "--seconds", "0.05"]) == 0
    assert main(["replay", str(trial), "--out", str(out), "--no-projector"]) == 0
    assert main(["replay", str(trial), "--out", str(out), "--no-rrd", "--no-projector"]) == 2
    assert (out / "log.rrd").is_file()
    assert main(["replay", str(trial), "--out", str(out), "--no-rrd", "--no-projector", "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "estimate.txt", "status.csv", "summary.json"]
    (out / "log.rrd").write_bytes(b"another trial's recording")   # not this command's: never removed
    assert main(["replay", str(trial), "--out", str(out), "--no-rrd", "--no-projector", "--overwrite"]) == 2
    assert (out / "log.rrd").read_bytes() == b"another trial's recording"


def test_calibrate_simulate_overwrite_replaces_every_capture_and_the_stale_hand_eye(tmp_path):
    cal = tmp_path / "cal"
    assert main(["calibrate", "simulate", "--out", str(cal), "--captures", "6"]) == 0
    assert main(["calibrate", "hand-eye", "--captures", str(cal)]) == 0   # its default --out: cal/hand_eye.yaml
    assert main(["calibrate", "simulate", "--out", str(cal), "--captures", "3"]) == 2
    assert len((cal / "captures.csv").read_text().splitlines()) == 7
    assert main(["calibrate", "simulate", "--out", str(cal), "--captures", "3", "--overwrite"]) == 0
    assert len((cal / "captures.csv").read_text().splitlines()) == 4
    assert len(list((cal / "images").glob("*.png"))) == 3
    assert not (cal / "hand_eye.yaml").exists()


def test_calibrate_projector_simulate_3_into_a_folder_of_6_poses_uses_3(tmp_path, capsys):
    folder = tmp_path / "proj"
    assert main(["calibrate", "projector", "--simulate", "6", "--captures", str(folder)]) == 0
    assert main(["calibrate", "projector", "--simulate", "3", "--captures", str(folder)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["calibrate", "projector", "--simulate", "3", "--captures", str(folder), "--overwrite"]) == 0
    assert "3 board poses used" in capsys.readouterr().out
    assert sorted(p.name for p in folder.glob("pose_*")) == ["pose_000", "pose_001", "pose_002"]


# ---------------------------------------------------------------- k3

def test_intrinsics_on_the_documented_simulated_flow_does_not_overfit_k3(tmp_path, capsys):
    """calibration/README.md's flow: free k3 put the image corners 34 px off the true model (RMS 0.073 px)."""
    cal = tmp_path / "cal"
    assert main(["calibrate", "simulate", "--out", str(cal), "--noise"]) == 0
    fit = cal / "camera_fit.yaml"
    assert main(["calibrate", "intrinsics", "--images", str(cal / "images"), "--out", str(fit)]) == 0
    text = capsys.readouterr()
    assert "k3 fixed (not constrained)" in text.out and "k3 fixed at 0" in text.err
    cam = yaml.safe_load(fit.read_text())["camera"]
    truth = yaml.safe_load((cal / "camera.yaml").read_text())["camera"]
    K_true, K, dist = np.array(truth["K"]), np.array(cam["K"]), np.array(cam["dist"])
    corners = np.array([[0, 0], [639, 0], [0, 479], [639, 479]], float)
    rays = np.column_stack([corners, np.ones(4)]) @ np.linalg.inv(K_true).T
    uv, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    assert np.linalg.norm(uv.reshape(-1, 2) - corners, axis=1).max() < 5.0   # was 34 px; 3 px measured fixed


# ---------------------------------------------------------------- calibrate capture uses the session's rig

def test_capture_solves_the_session_trials_hand_eye_and_writes_truth(tmp_path, capsys):
    from app.geometry import se3
    from app.sim import world

    session = tmp_path / "session.yaml"
    session.write_text("camera: simulated\nrobot: simulated\n")
    out = tmp_path / "live"
    assert main(["calibrate", "capture", "--config", str(session), "--out", str(out), "--count", "8"]) == 0
    truth = yaml.safe_load((out / "truth.yaml").read_text())
    np.testing.assert_allclose(truth["hand_eye"], world.T_FLANGE_CAMERA)
    assert main(["calibrate", "hand-eye", "--captures", str(out), "--method", "park"]) == 0
    solved = np.array(yaml.safe_load((out / "hand_eye.yaml").read_text())["hand_eye"])
    assert np.linalg.norm(solved[:3, 3] - world.T_FLANGE_CAMERA[:3, 3]) < 1e-3            # noise-free: < 1 mm
    assert np.rad2deg(se3.rotation_angle(solved, world.T_FLANGE_CAMERA)) < 0.05


# ---------------------------------------------------------------- view without --rrd

def test_view_without_display_says_to_use_rrd(tmp_path, monkeypatch, capsys):
    trial = tmp_path / "trial"
    assert main(["simulate", "--out", str(trial), "--seconds", "0.05"]) == 0
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    capsys.readouterr()
    assert main(["view", str(trial)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--rrd" in err and "display" in err


def test_view_finds_the_viewer_beside_python_and_names_it_when_missing(tmp_path, monkeypatch):
    from app.viz import trial_view

    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setenv("PATH", str(tmp_path))              # not on PATH
    bindir = tmp_path / "venv" / "bin"
    bindir.mkdir(parents=True)
    monkeypatch.setattr(sys, "executable", str(bindir / "python"))
    with pytest.raises(OsteonavError, match="rerun viewer was not found.*--rrd"):
        trial_view.viewer_executable()
    (bindir / "rerun").write_text("#!/bin/sh\n")
    assert trial_view.viewer_executable() == bindir / "rerun"


def test_view_reports_a_viewer_that_exits_at_once_instead_of_hanging(tmp_path, monkeypatch):
    from app.viz import trial_view

    fake = tmp_path / "rerun"
    fake.write_text("#!/bin/sh\necho 'Failed to open connection to X server' >&2\nexit 1\n")
    fake.chmod(0o755)
    monkeypatch.setattr(trial_view, "viewer_executable", lambda: fake)
    with pytest.raises(OsteonavError, match="exited at once.*X server.*--rrd"):
        trial_view._spawn(port=9, start_s=120.0)   # the fake exits at once; 120 s is only a safety net


# ---------------------------------------------------------------- messages and help

def test_record_without_track_prints_no_tracker_counts(capsys):
    from app.commands.track import print_summary

    print_summary({"seconds": 2.0, "frames": {"frames_accepted": 40}, "processed": 0,
                   "status_counts": {"lost": 40}}, tracked=False)
    out = capsys.readouterr().out
    assert "40 frames accepted" in out and "tracked" not in out.replace("not tracked", "") and "lost" not in out


def test_calibrate_help_is_plain_text_and_lists_every_step(capsys):
    assert main(["calibrate", "--help"]) == 0
    out = capsys.readouterr().out
    assert "``" not in out and "::" not in out
    for step in ("intrinsics", "hand-eye", "capture", "simulate", "projector", "--overwrite"):
        assert step in out


def test_bench_marker_help_states_the_seconds_rule(capsys):
    assert main(["bench-marker", "--help"]) == 0
    assert "must exceed 5" in " ".join(capsys.readouterr().out.split())


def test_a_millimetre_mesh_is_refused_wherever_it_is_loaded(tmp_path):
    from app.mesh import load_mesh
    from app.projector.plan import mesh_outline

    path = tmp_path / "mm.ply"
    trimesh.creation.box(extents=(120.0, 30.0, 40.0)).export(path)
    for load in (lambda: load_mesh(path), lambda: mesh_outline(path, np.zeros((3, 3)), np.array([[0, 1, 2]]))):
        with pytest.raises(MeshError, match=r"~120 m across.*millimetres.*prepare-mesh .*mm\.ply --out .* --scale 0.001"):
            load()
    assert len(load_mesh(path, check=False).faces) == 12   # prepare-mesh loads before scaling


def test_a_second_session_needs_overwrite_which_clears_out_its_record_and_rrd(tmp_path):
    """The simulated session's layout: record and the rerun file inside out (configs/sessions/simulated.yaml).
    What the earlier session wrote (listed in the manifests) goes; the user's own .rrd beside it stays."""
    from app.commands.outdir import OutputError
    from app.commands.track import prepare_session_dirs
    from app.outputs import LOCK, MANIFEST, close_all, wrote
    from app.session import load_session

    out = tmp_path / "session"
    config = load_session(REPO / "configs" / "sessions" / "simulated.yaml", {
        "out": str(out), "record": str(out / "trial"),
        "outputs": [{"plugin": "rerun", "params": {"path": str(out / "log.rrd")}}]})
    prepare_session_dirs(config, overwrite=False)
    for name in ("estimate.txt", "events.csv", "log.rrd", "trial/trial.yaml", "trial/frames.csv"):
        wrote(out / name)
        (out / name).write_text("an earlier session\n")
    close_all()
    with pytest.raises(OutputError, match=f"out {out} is not empty.*--overwrite"):
        prepare_session_dirs(config, overwrite=False)
    assert (out / "log.rrd").exists()
    (out / "surgery_patient12.rrd").write_text("the user's")
    with pytest.raises(OutputError, match="did not write: surgery_patient12.rrd"):
        prepare_session_dirs(config, overwrite=True)
    (out / "surgery_patient12.rrd").unlink()
    prepare_session_dirs(config, overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == [LOCK, MANIFEST, "trial"]
    assert sorted(p.name for p in (out / "trial").iterdir()) == [LOCK, MANIFEST]
    close_all()


def test_errors_raised_while_the_session_runs_name_the_session_file(tmp_path):
    """run_session's own checks (bone.mesh, calibration.hand_eye, ...) raise without the file's name."""
    from app.commands.track import naming_the_session_file
    from app.errors import ConfigError

    path = tmp_path / "session.yaml"
    with pytest.raises(ConfigError, match=rf"^{path}: config key 'bone.mesh': missing: the tracker needs the bone mesh$"):
        with naming_the_session_file(path):
            raise ConfigError("bone.mesh", "missing: the tracker needs the bone mesh")
    with pytest.raises(ConfigError, match=rf"^{path}: config key 'loop.x': bad$"):   # already named: unchanged
        with naming_the_session_file(path):
            raise ConfigError("loop.x", "bad", str(path))
