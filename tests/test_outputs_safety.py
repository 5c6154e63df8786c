"""Issue 34: never delete a user's file, never report a broken recording as written.

Each data-loss case of the issue through the command line (every one deleted the user's files on
the old owned-by-name rule), and the recorder's drops counted where they happen: camera, queue,
disk. A full disk is a write that raises ENOSPC after k frames, not a filled disk."""
from __future__ import annotations

import errno
import fcntl
import os
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from app.cli import main
from app.outputs import LOCK, MANIFEST, close_all, read_manifest
from app.trial.meta import MARKER_FILE
from test_session_faults import fake_plugins  # noqa: F401 (fixture)

V1_TRIAL = Path(__file__).parent / "data" / "trial_v1_sim"


@pytest.fixture(autouse=True)
def _release():
    yield
    close_all()


def _user_files(folder: Path) -> dict[str, str]:
    """A user's own files in ``folder`` (a trial.yaml among them: the old rule's 'this is a trial')."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "src").mkdir(exist_ok=True)
    files = {"thesis.tex": "chapter 1", "trial.yaml": "my own notes", "src/main.c": "int main;",
             "surgery_patient12.rrd": "a log", "NOTES.txt": "notes"}
    for name, text in files.items():
        (folder / name).write_text(text)
    (folder / "projector").mkdir(exist_ok=True)
    (folder / "photos").mkdir(exist_ok=True)
    return files


def _unchanged(folder: Path, files: dict[str, str]) -> None:
    assert {n: (folder / n).read_text() for n in files} == files
    assert (folder / "projector").is_dir() and (folder / "photos").is_dir()


def _session_yaml(tmp_path: Path, **extra) -> Path:
    """A session of the scripted sources (tests/test_session_faults.py): no GL, a second or two."""
    import trimesh

    trimesh.creation.box((0.05, 0.02, 0.01)).export(tmp_path / "bone.ply")
    raw = {"camera": {"plugin": "scripted", "params": {"seconds": 30.0, "faults": False}},
           "robot": {"plugin": "scripted", "params": {"faults": False}, "model": "ur5e"},
           "tracker": False, "calibration": {"hand_eye": np.eye(4).tolist()},
           "bone": {"mesh": str(tmp_path / "bone.ply"), "initial_pose": np.eye(4).tolist()}, **extra}
    path = tmp_path / "session.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


# ---------------------------------------------------------------- --overwrite deletes nothing of the user's

@pytest.mark.parametrize("command", ["simulate", "replay --no-projector", "prepare-mesh"])
def test_overwrite_refuses_a_folder_of_the_users_files_by_name(tmp_path, capsys, command):
    out = tmp_path / "D"
    files = _user_files(out)
    argv = {"simulate": ["simulate", "--out", str(out), "--seconds", "1"],
            "replay --no-projector": ["replay", str(V1_TRIAL), "--out", str(out), "--no-projector", "--no-rrd"],
            "prepare-mesh": ["prepare-mesh", str(V1_TRIAL / "iliac_crest_tracking.ply"), "--out",
                             str(out / "thesis.tex.ply")]}[command]
    code = main(argv + ["--overwrite"])
    if command == "prepare-mesh":   # a new file in the folder: written, nothing else touched
        assert code == 0 and (out / "thesis.tex.ply").is_file()
    else:
        assert code == 2
        err = capsys.readouterr().err
        assert "holds files this command did not write: NOTES.txt, photos/, projector/, src/, surgery_patient12.rrd, " \
               "thesis.tex, trial.yaml" in err
    _unchanged(out, files)


def test_record_and_track_refuse_the_users_files_and_the_users_rrd(tmp_path, capsys, fake_plugins):
    out = tmp_path / "D"
    files = _user_files(out)
    config = _session_yaml(tmp_path, out=str(out))
    assert main(["record", "--config", str(config), "--out", str(out), "--duration", "0.2", "--overwrite"]) == 2
    assert "did not write: NOTES.txt" in capsys.readouterr().err
    assert main(["track", "--config", str(config), "--duration", "0.2", "--overwrite"]) == 2
    assert "surgery_patient12.rrd" in capsys.readouterr().err
    _unchanged(out, files)


def test_track_soak_writes_nothing_and_deletes_nothing(tmp_path, fake_plugins):
    out = tmp_path / "D"
    out.mkdir()
    for k in range(4):
        (out / f"session-{k}.rrd").write_text("an earlier log")
    config = _session_yaml(tmp_path, out=str(out), record=str(tmp_path / "rec"),
                           outputs=[{"plugin": "rerun", "params": {"path": str(out / "log.rrd")}}])
    assert main(["track", "--config", str(config), "--soak", "--duration", "0.3", "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [f"session-{k}.rrd" for k in range(4)]
    assert not (tmp_path / "rec").exists()


def test_the_input_is_never_the_output(tmp_path, capsys):
    mesh = tmp_path / "bone.ply"
    shutil.copyfile(V1_TRIAL / "iliac_crest_tracking.ply", mesh)
    before = mesh.read_bytes()
    assert main(["prepare-mesh", str(mesh), "--out", str(mesh), "--overwrite"]) == 2
    assert "is the input this command reads" in capsys.readouterr().err and mesh.read_bytes() == before
    trial = tmp_path / "trial"
    shutil.copytree(V1_TRIAL, trial)
    assert main(["replay", str(trial), "--out", str(trial), "--overwrite", "--no-rrd", "--no-projector"]) == 2
    assert "would hold the input" in capsys.readouterr().err
    assert sorted(p.name for p in trial.iterdir()) == sorted(p.name for p in V1_TRIAL.iterdir())


def test_a_second_replay_into_one_out_is_refused_by_the_lock(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    held = os.open(out / LOCK, os.O_RDWR | os.O_CREAT)
    os.write(held, f"pid {os.getpid() + 1}, osteonav replay, since now\n".encode())
    fcntl.flock(held, fcntl.LOCK_EX)   # the first replay, still running
    try:
        assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-rrd", "--no-projector"]) == 2
        assert "being written by another osteonav run" in capsys.readouterr().err
        assert sorted(p.name for p in out.iterdir()) == [LOCK]
    finally:
        os.close(held)
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-rrd", "--no-projector"]) == 0
    assert read_manifest(out) == {"estimate.txt", "status.csv", "summary.json"}
    assert sorted(p.name for p in out.iterdir()) == [MANIFEST, "estimate.txt", "status.csv", "summary.json"]


def test_replay_overwrite_replaces_its_own_outputs_only(tmp_path):
    out = tmp_path / "out"
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-projector"]) == 0
    assert read_manifest(out) == {"estimate.txt", "status.csv", "summary.json", "log.rrd"}
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-projector", "--no-rrd", "--overwrite"]) == 0
    assert not (out / "log.rrd").exists()   # the earlier run's: listed, removed


# ---------------------------------------------------------------- a recording is complete or says it is not

def _full_disk_after(monkeypatch, k: int) -> None:
    """The trial writer's PNG writes fail with ENOSPC after ``k`` of them."""
    from app.trial.writer import TrialWriter

    original, calls = TrialWriter._write_png, [0]

    def write_png(dest, png):
        calls[0] += 1
        if calls[0] > k:
            raise OSError(errno.ENOSPC, "No space left on device", str(dest))
        original(dest, png)

    monkeypatch.setattr(TrialWriter, "_write_png", staticmethod(write_png))


def _recorder(tmp_path, max_queue: int = 2048, max_queue_mb: float = 256.0):
    from app.trial.meta import TrialMeta  # noqa: F401 (the recorder builds one)
    from plugins.recorder import Recorder
    from test_trial_images import bone_mesh, make_meta

    meta = make_meta(np.random.default_rng(3))
    rec = Recorder(str(tmp_path / "rec"), max_queue=max_queue, max_queue_mb=max_queue_mb)
    rec.open({"mesh_path": bone_mesh(tmp_path), "camera": meta.camera, "robot": {"model": "ur5e"}, "dh": meta.dh,
              "T_flange_camera": np.eye(4)})
    return rec, meta


def _frame(meta, k: int):
    from app.interfaces import DepthFrame

    return DepthFrame(k, 0.5 + 0.1 * k, np.full((meta.camera.height, meta.camera.width), 0.4, np.float32), 0.0)


def _stall_after_first_frame(rec, meta, monkeypatch) -> threading.Event:
    """The disk falls behind: frame 0 is handed to the recorder, whose writer then waits on its first write
    until the returned event is set, so every frame queued meanwhile stays in the queue (events, no clock:
    the 10 s are a safety net against a hung test)."""
    release, taken = threading.Event(), threading.Event()
    original = rec._write

    def stalled_write(item):
        taken.set()
        release.wait(10)
        original(item)

    monkeypatch.setattr(rec, "_write", stalled_write)
    rec.on_frame(_frame(meta, 0))
    assert taken.wait(10)
    return release


def test_a_full_disk_leaves_the_trial_marked_incomplete_with_its_losses_counted(tmp_path, monkeypatch):
    from app.trial.reader import open_trial

    _full_disk_after(monkeypatch, 3)
    rec, meta = _recorder(tmp_path)
    for k in range(10):
        rec.on_frame(_frame(meta, k))
    report = rec.close()
    assert report["frames"] == 3 and not report["complete"]
    assert report["dropped"] == {"camera": 0, "queue": 0, "disk": 7} and "the disk is full" in report["error"]
    trial = tmp_path / "rec"
    assert (trial / MARKER_FILE).exists()
    assert yaml.safe_load((trial / "trial.yaml").read_text())["dropped"] == {"camera": 0, "queue": 0, "disk": 7}
    assert len(open_trial(trial).stamps) == 3


def test_camera_gaps_are_counted_and_a_gap_alone_leaves_the_trial_complete(tmp_path):
    rec, meta = _recorder(tmp_path)
    for k in (0, 1, 2, 5, 6, 9):
        rec.on_frame(_frame(meta, k))
    report = rec.close()
    assert report["dropped"] == {"camera": 4, "queue": 0, "disk": 0} and report["complete"]
    assert not (tmp_path / "rec" / MARKER_FILE).exists()
    assert yaml.safe_load((tmp_path / "rec" / "trial.yaml").read_text())["dropped"]["camera"] == 4


def test_frames_the_queue_drops_are_counted_and_mark_the_trial_incomplete(tmp_path, monkeypatch):
    rec, meta = _recorder(tmp_path, max_queue=2)
    release = _stall_after_first_frame(rec, meta, monkeypatch)
    for k in range(1, 10):
        rec.on_frame(_frame(meta, k))
    release.set()
    report = rec.close()
    assert report["dropped"] == {"camera": 0, "queue": 7, "disk": 0} and report["frames"] == 3
    assert not report["complete"] and (tmp_path / "rec" / MARKER_FILE).exists()


def test_a_recorder_behind_the_camera_holds_a_bounded_weight_of_frames_however_many_come(tmp_path, monkeypatch):
    """The live session's memory grew 150-350 MB a minute with a recording (issue: RSS soak): the writer
    fell behind the camera on a busy host and its queue, bounded only by items (2048: frames and joint
    batches alike), held up to 2048 frames. Now what the queued frames weigh is bounded by max_queue_mb,
    whatever the number of frames; joint batches (weightless) stay and are written."""
    from app.interfaces import JointSamples

    from test_trial_io import HEIGHT, WIDTH

    frame_bytes = HEIGHT * WIDTH * 4                     # float32 depth
    rec, meta = _recorder(tmp_path, max_queue_mb=5.5 * frame_bytes / 1e6)   # room for five frames
    assert _frame(meta, 0).depth_m.nbytes == frame_bytes
    release = _stall_after_first_frame(rec, meta, monkeypatch)
    n = 200
    for k in range(1, n + 1):
        rec.on_frame(_frame(meta, k))
        rec.on_joints(JointSamples(np.array([0.5 + 0.1 * k]), np.zeros((1, 6))))
        assert rec.queue.nbytes_held <= 5 * frame_bytes
    frames_queued = sum(1 for what, _ in rec.queue._items if what == "frame")
    assert frames_queued == 5 and len(rec.queue) == 5 + n         # every joint batch kept
    release.set()
    report = rec.close()
    assert report["frames"] == 1 + 5 and report["dropped"] == {"camera": 0, "queue": n - 5, "disk": 0}
    assert report["joint_samples"] == n and report["joint_samples_lost"] == 0 and not report["complete"]


def test_the_drop_oldest_queue_bounds_the_weight_of_its_items():
    from app.interfaces import DropOldestQueue

    q = DropOldestQueue(100, max_bytes=10, nbytes=len)
    for item in ("aaaa", "", "bbbb", "", "cccc"):     # 4 + 4 + 4 > 10: "aaaa" goes, the weightless "" stay
        q.put(item)
    assert q.nbytes_held == 8 and q.dropped == 1 and q.drain() == ["", "bbbb", "", "cccc"]
    q.put("x" * 25)                                   # heavier than the budget alone: taken, alone
    q.put("")
    assert q.nbytes_held == 25 and q.get() == "x" * 25 and q.nbytes_held == 0 and q.get() == ""
    q.put("abc")
    q.put("de")
    assert q.get_latest() == "de" and q.nbytes_held == 0 and q.dropped == 2
    with pytest.raises(ValueError):
        DropOldestQueue(4, max_bytes=10)


def test_record_onto_a_full_disk_exits_non_zero_and_the_retry_can_overwrite_it(tmp_path, capsys, monkeypatch,
                                                                               fake_plugins):
    out = tmp_path / "trial"
    config = _session_yaml(tmp_path)
    _full_disk_after(monkeypatch, 3)
    assert main(["record", "--config", str(config), "--out", str(out), "--duration", "0.5"]) == 1
    captured = capsys.readouterr()
    assert "trial written" not in captured.out and "Traceback" not in captured.err
    assert "is incomplete" in captured.err and "the disk is full" in captured.err
    assert "not written (the disk is full" in captured.out
    assert (out / MARKER_FILE).exists()
    dropped = yaml.safe_load((out / "trial.yaml").read_text())["dropped"]
    assert dropped["disk"] > 0
    monkeypatch.undo()
    assert main(["record", "--config", str(config), "--out", str(out), "--duration", "0.3", "--overwrite"]) == 0
    assert "trial written" in capsys.readouterr().out and not (out / MARKER_FILE).exists()


# ---------------------------------------------------------------- a full disk under replay, view --save, calibrate --rrd

def _full_disk_for(monkeypatch, module, budget: int) -> None:
    """Files ``module`` opens for writing raise ENOSPC once ``budget`` bytes are written in all."""
    left = [budget]

    class FullFile:
        def __init__(self, f, path):
            self._f, self._path = f, str(path)

        def write(self, data):
            left[0] -= len(data)
            if left[0] < 0:
                raise OSError(errno.ENOSPC, "No space left on device", self._path)
            return self._f.write(data)

        def __getattr__(self, name):
            return getattr(self._f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._f.close()

    def full_open(path, mode="r", *args, **kwargs):
        f = open(path, mode, *args, **kwargs)
        return FullFile(f, path) if ("w" in mode or "a" in mode) else f

    monkeypatch.setattr(module, "open", full_open, raising=False)


def _one_error_line(err: str, command: str) -> str:
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.startswith(f"osteonav {command}: error:")]
    assert len(lines) == 1, err
    return lines[0]


def test_replay_onto_a_full_disk_is_a_clear_error_and_its_rows_are_readable(tmp_path, capsys, monkeypatch):
    import app.pipeline.sinks
    from app.trial.tum import read_tum

    out = tmp_path / "out"
    _full_disk_for(monkeypatch, app.pipeline.sinks, 900)
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-rrd", "--no-projector"]) == 2
    line = _one_error_line(capsys.readouterr().err, "replay")
    assert "the replay stopped at a failed write of" in line and "the disk is full" in line
    assert not (out / "summary.json").exists()
    stamps, _ = read_tum(out / "estimate.txt")
    assert 0 < len(stamps) < 14
    monkeypatch.undo()
    assert main(["replay", str(V1_TRIAL), "--out", str(out), "--no-rrd", "--no-projector", "--overwrite"]) == 0


def test_replay_view_and_hand_eye_with_an_rrd_onto_a_full_disk_fail_in_one_line(tmp_path, capsys, monkeypatch):
    import app.viz.rrd_file

    cal = tmp_path / "cal"
    assert main(["calibrate", "simulate", "--out", str(cal), "--captures", "4"]) == 0
    _full_disk_for(monkeypatch, app.viz.rrd_file, 4000)
    runs = {"replay": ["replay", str(V1_TRIAL), "--out", str(tmp_path / "r"), "--no-projector"],
            "view": ["view", str(V1_TRIAL), "--save", str(tmp_path / "v.rrd")],
            "calibrate": ["calibrate", "hand-eye", "--captures", str(cal), "--rrd", str(tmp_path / "he.rrd")]}
    for command, argv in runs.items():
        capsys.readouterr()
        assert main(argv) == 2, command
        captured = capsys.readouterr()
        line = _one_error_line(captured.err, command)
        assert "the disk is full; the file is incomplete" in line, line
        assert ".rrd" not in captured.out and "outputs in" not in captured.out, captured.out   # no success line


# ---------------------------------------------------------------- every file a command writes is listed

def test_every_file_the_writing_commands_leave_is_listed_in_a_manifest(tmp_path, fake_plugins):
    """What a manifest misses, --overwrite would refuse: each command lists all it writes."""
    from app.outputs import unlisted

    trial, replayed, rec, cal = tmp_path / "trial", tmp_path / "replayed", tmp_path / "rec", tmp_path / "cal"
    assert main(["simulate", "--out", str(trial), "--seconds", "0.05", "--streams", "depth,ir,color"]) == 0
    assert main(["replay", str(trial), "--out", str(replayed), "--projector-images"]) == 0
    config = _session_yaml(tmp_path, out=str(tmp_path / "session"),
                           outputs=[{"plugin": "rerun", "params": {"path": str(tmp_path / "session" / "log.rrd")}}])
    assert main(["record", "--config", str(config), "--out", str(rec), "--duration", "0.3", "--track",
                 "--track-out", str(tmp_path / "session")]) == 0
    assert main(["calibrate", "simulate", "--out", str(cal), "--captures", "4"]) == 0
    assert main(["calibrate", "hand-eye", "--captures", str(cal), "--rrd", str(cal / "he.rrd")]) == 0
    for folder in (trial, replayed, rec, tmp_path / "session", cal):
        assert len(read_manifest(folder)) >= 3 and unlisted(folder) == [], folder
    assert (replayed / "projector").is_dir() and "log.rrd" in read_manifest(replayed)
    for folder in (trial, replayed, cal):   # and so the rerun replaces all of it
        assert main(["calibrate", "simulate", "--out", str(folder), "--captures", "3", "--overwrite"]) == 0


def test_track_with_a_recording_onto_a_full_disk_exits_non_zero(tmp_path, capsys, monkeypatch, fake_plugins):
    config = _session_yaml(tmp_path, out=str(tmp_path / "out"))
    _full_disk_after(monkeypatch, 2)
    assert main(["track", "--config", str(config), "--record", str(tmp_path / "rec"), "--duration", "0.5"]) == 1
    captured = capsys.readouterr()
    assert "is incomplete" in captured.err and "Traceback" not in captured.err
    assert (tmp_path / "rec" / MARKER_FILE).exists()


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), "big", True])
def test_a_bad_queue_bound_names_its_key_and_writes_nothing(tmp_path, bad):
    """output.params.max_queue_mb: a ConfigError naming the key and an example, before any file is written."""
    from app.errors import ConfigError
    from plugins.recorder import Recorder

    with pytest.raises(ConfigError, match=r"output\.params\.max_queue_mb.*positive number of megabytes"):
        Recorder(str(tmp_path / "rec"), max_queue_mb=bad)
    assert not (tmp_path / "rec").exists()
